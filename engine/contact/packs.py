"""The contact solve's arrays by name.

Each group of arrays the solve's compiled kernels share is a named tuple
(numba types it field by field: one argument, read by name at no cost,
and compiled and cached like any tuple).  The kept groups travel from
Python inside one :class:`engine.pack.Pack` each (one pointer to unbox);
inside compiled code they are handed on as they are, or a kernel builds
the smaller group its callee reads (e.g. :class:`Bodies` out of a
:class:`Pose`).  Shapes: n dynamic bodies (the world is row n), m normal
rows (or contacts), np friction patches, nr = 5 friction rows per patch
with rolling friction, else 3; units SI.
"""

from __future__ import annotations

from collections import namedtuple

#: the pose and velocities of a step (engine.solver.Solve._pose):
#: positions ``X`` (n, 3) m, inverse world inertia ``Iinv`` (n+1, 3, 3),
#: start rotations ``R0`` (n, 3, 3), end velocities ``V``, ``W`` (n+1, 3),
#: start velocities ``V0``, ``W0`` (n, 3), pseudo velocities ``Vp``, ``Wp``
#: (n+1, 3), inverse masses ``inv_mass`` (n+1,) 1/kg, ``bound_radius`` (n,) m
Pose = namedtuple("Pose", ("X", "Iinv", "R0", "V", "W", "V0", "W0", "Vp", "Wp", "inv_mass", "bound_radius"))

#: what the rows' Jacobians read of the bodies (the first fields of a Pose)
Bodies = namedtuple("Bodies", ("X", "Iinv", "inv_mass", "R0"))

#: the topology of a contact graph (engine.contact.topology.Topology):
#: row bodies ``ab`` (m, 2), ``a``, ``b`` (m,); the rows' patches ``pid``
#: (m,), patch bodies ``pa``, ``pb`` (np,), rows per patch ``cnt`` (np,)
#: float, ``pab`` (np, 2); pair codes ``codes`` (m,), their stable sort
#: ``code_order`` (m,), the first sorted row of each distinct pair
#: ``code_first`` (p,) and its patch ``uniq_pid`` (p,); the patches' static,
#: kinetic and rolling friction coefficients ``mus``, ``muk``, ``mur`` (np,)
Topo = namedtuple("Topo", ("ab", "a", "b", "pid", "pa", "pb", "cnt", "pab", "codes", "code_order", "code_first",
                           "uniq_pid", "mus", "muk", "mur"))

#: the rows' arrays (filled by engine.contact.prepare.rows): normal rows
#: ``J``, ``M`` (m, 12), ``mn`` (m,), contact points in body a's frame
#: ``loc`` (m, 3), impulses ``lam_n`` (m,) N s, ``target`` (m,) m/s; patch
#: centroids ``P`` and normals ``N`` (np, 3), twist radii ``rt`` (np,) m,
#: tangents ``t`` (np, 2, 3), ``Jt``, ``Mt`` (np, nr, 12), ``mt`` (np, nr),
#: impulses ``lam_t`` (np, nr), ``slip`` (np,) bool, ``mu`` (np,)
RowArrays = namedtuple("RowArrays", ("J", "M", "mn", "loc", "lam_n", "target", "P", "N", "rt", "t", "Jt", "Mt", "mt",
                                     "lam_t", "slip", "mu"))

#: the solve stage's work arrays (engine.solver._work_items): the rows'
#: (:class:`RowArrays`), the velocities ``U``, ``U0``, ``Ud`` (n+1, 6),
#: the patches' start tangential velocities ``vt0`` (np, 2), the sweeps'
#: pins ``pin_t`` (np,) bool and ``dir_t`` (np, 2), ``matched`` (np,) bool,
#: ``r_direct`` (m,), the push-out ``bias`` (m,) m/s, the pseudo
#: velocities ``Up`` (n+1, 6) and impulses ``lam_p`` (m,), ``touch_rows``
#: (m,) bool, the sweeps' work ``wk`` and the direct start's ``dwf``,
#: ``dwi`` (engine.contact.phases.direct_work_size)
Work = namedtuple("Work", ("rows", "U", "U0", "Ud", "vt0", "pin_t", "dir_t", "matched", "r_direct", "bias", "Up",
                           "lam_p", "touch_rows", "wk", "dwf", "dwi"))

#: the classification of a step's contacts and what it reads of the free
#: flight: mean velocities ``UL``, ``UA`` (n, 3), normal velocities ``vn``
#: (3, m), ``touching``, ``impact`` (m,) bool, pair ``codes`` (m,)
Classified = namedtuple("Classified", ("UL", "UA", "vn", "touching", "impact", "codes"))

#: a step's contacts (engine.state.Contacts): bodies ``a``, ``b`` (m,),
#: static index ``sidx`` (m,) (-1 for a body pair), ``point``, ``normal``
#: (m, 3), ``gap`` (m,) m, restitution ``e`` (m,)
ContactArrays = namedtuple("ContactArrays", ("a", "b", "sidx", "point", "normal", "gap", "e"))

#: the warm-start cache (engine.contact.warm.WarmCache): per cached point
#: its pair code ``code`` (k,), point in body a's frame ``loc`` (k, 3),
#: normal force ``fn`` (k,) N, ``touch`` (k,) bool; per distinct pair its
#: code ``pairs`` (p,), friction force ``ft`` (p, 3) N, twist ``tw`` (p,)
#: N m, rolling torque ``rr`` (p, 3) N m
Cache = namedtuple("Cache", ("code", "loc", "fn", "pairs", "ft", "tw", "rr", "touch"))

#: the solve's settings (constant over a plan): static rows ``n_statics``,
#: the contact lever, the restitution threshold ``thr`` m/s, the position
#: correction's ``beta`` and ``slop`` m, ``friction``, ``rolling``, the
#: direct start (``direct``, its resting speed m/s, dense rows at most
#: ``max_rows``, active-set ``passes``), the slip tolerance m/s, the
#: sweeps' ``iterations``, the split-impulse relax ``relax_on``
Settings = namedtuple("Settings", ("n_statics", "lever", "thr", "beta", "slop", "friction", "rolling", "direct",
                                   "resting", "max_rows", "passes", "slip_tol", "iterations", "relax_on"))

#: the Gauss-Seidel sweeps' normal rows: bodies ``ab`` (m, 2), ``J``, ``M``
#: (m, 12), ``mn`` (m,), impulses ``lam`` (m,), ``target`` (m,)
NormalRows = namedtuple("NormalRows", ("ab", "J", "M", "mn", "lam", "target"))

#: the Gauss-Seidel sweeps' friction patches: ``pab`` (np, 2), the rows'
#: patches ``pid`` (m,), ``Jt``, ``Mt`` (np, nr, 12), ``mt``, ``lam_t``
#: (np, nr), ``mu``, ``rt``, ``mur`` (np,), the pinned directions of the
#: sliding (``pin_t`` (np,) bool, ``dir_t`` (np, 2)) and rolling rows
#: (``pin_r``, ``dir_r``)
Patches = namedtuple("Patches", ("pab", "pid", "Jt", "Mt", "mt", "lam_t", "mu", "rt", "mur", "pin_t", "dir_t",
                                 "pin_r", "dir_r"))

#: what the rows' preparation reads of a topology's patches: the rows'
#: patches ``pid`` (m,), patch bodies ``pa``, ``pb`` (np,), rows per patch
#: ``cnt`` (np,) float, static friction coefficients ``mus`` (np,)
PatchSet = namedtuple("PatchSet", ("pid", "pa", "pb", "cnt", "mus"))

#: the impact solve's rows (engine.contact.propagate): ``J``, ``M`` (m, 12),
#: bodies ``ab`` (m, 2), restitution ``e`` (m,), the rows' patches ``pid`` (m,)
ImpactRows = namedtuple("ImpactRows", ("J", "M", "ab", "e", "pid"))

#: the impact solve's index lists (engine.contact.propagate.setup): the
#: rows of pair g ``go[gs[g]:gs[g + 1]]``, the pair of each row ``inv``
#: (m,), the rows of body i ``bo[b0[i]:b0[i + 1]]``
ImpactGroups = namedtuple("ImpactGroups", ("go", "gs", "inv", "bo", "b0"))

#: the impact solve's friction patches: ``Jt``, ``Mt`` (np, nr, 12), ``mt``
#: (np, nr), bodies ``pa``, ``pb`` (np,), static and kinetic coefficients
#: ``mus``, ``muk`` (np,), twist radii ``r_twist`` (np,) m, rolling
#: coefficients ``mur`` (np,) m
ImpactPatches = namedtuple("ImpactPatches", ("Jt", "Mt", "mt", "pa", "pb", "mus", "muk", "r_twist", "mur"))
