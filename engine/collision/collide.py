"""The narrow phase's compiled driver: every candidate pair of a step --
body-body, body-plane, body-static-box -- collided in ONE compiled call
(:func:`collide`), written into caller-owned contact buffers.

Order (pinned by the determinism tests): body-body pairs grouped by their
canonically ordered shape pair (ascending ``FAMILY`` key sa * 8 + sb, the
pairs of a group in candidate order), then body-plane pairs grouped by the
body's shape, then body-static-box pairs likewise; within a group each
family's contacts in its own order (``BOUNDS``: slot blocks, each block
pair by pair).  A contact is kept where its gap is below its pair's margin.
Each group runs its family's compiled loop (the functions of
:mod:`engine.collision.sphere` ... :mod:`engine.collision.cylinder_pair`) on
its pairs' gathered geometry, so the contacts are bit for bit those of the
family functions called one group at a time."""

from __future__ import annotations

import warnings
from collections import namedtuple

import numpy as np
from numba import njit, typeof
from numba.core import types
from numba.core.errors import NumbaExperimentalFeatureWarning

from physbench.engine.collision.box import BOX_FW, BOX_IW, _box_box_kernel, _box_plane_kernel, edge_pair_face_points
from physbench.engine.collision.capsule import (CAPSULE_FW, _capsule_box_kernel, _capsule_capsule_kernel, _capsule_plane_kernel,
                                      _sphere_capsule_kernel)
from physbench.engine.collision.cylinder import (CYLINDER_FW, _BOX_EDGES, _CORNERS, _box_cylinder_kernel,
                                       _capsule_cylinder_kernel, _cylinder_plane_kernel, _sphere_cylinder_kernel)
from physbench.engine.collision.cylinder_pair import YY_FW, YY_IW, _SIDE_MAX, _cylinder_cylinder_kernel
from physbench.engine.collision.kernels import Boxes, Cylinders, Slots
from physbench.engine.collision.sphere import _sphere_box_kernel, _sphere_plane_kernel, _sphere_sphere_kernel
from physbench.engine.model import BOX, CAPSULE, CYLINDER, SPHERE
from physbench.engine.pack import Pack

# family codes: body-body by shape pair (sphere S, box B, capsule C,
# cylinder Y), then the body's shape against a plane (P_*) and a static box (X_*)
F_SS, F_SB, F_BB, F_SC, F_BC, F_CC, F_SY, F_BY, F_CY, F_YY = range(10)
F_PS, F_PB, F_PC, F_PY = range(10, 14)
F_XS, F_XB, F_XC, F_XY = range(14, 18)

#: body-body family keyed by canonically ordered shape codes
TABLE = {(SPHERE, SPHERE): F_SS, (SPHERE, BOX): F_SB, (BOX, BOX): F_BB, (SPHERE, CAPSULE): F_SC,
         (BOX, CAPSULE): F_BC, (CAPSULE, CAPSULE): F_CC, (SPHERE, CYLINDER): F_SY, (BOX, CYLINDER): F_BY,
         (CAPSULE, CYLINDER): F_CY, (CYLINDER, CYLINDER): F_YY}
#: body-plane and body-static-box family keyed by the body's shape code
PLANE_TABLE = {SPHERE: F_PS, BOX: F_PB, CAPSULE: F_PC, CYLINDER: F_PY}
SBOX_TABLE = {SPHERE: F_XS, BOX: F_XB, CAPSULE: F_XC, CYLINDER: F_XY}

#: the tables as arrays for the kernel: body-body family by canonical
#: shape key sa * 8 + sb (sa <= sb), body-static family by the body's
#: shape (-1: none)
FAMILY = np.full(32, -1, np.int64)
for (_a, _b), _f in TABLE.items():
    FAMILY[_a * 8 + _b] = _f
PLANE_FAMILY = np.full(4, -1, np.int64)
SBOX_FAMILY = np.full(4, -1, np.int64)
for _s, _f in PLANE_TABLE.items():
    PLANE_FAMILY[_s] = _f
for _s, _f in SBOX_TABLE.items():
    SBOX_FAMILY[_s] = _f

_YY_SLOTS = 4 + 2 * _SIDE_MAX
#: per family its slot blocks' boundaries (-1 padded): the contacts of block
#: [lo, hi) come pair by pair, slots lo..hi-1 within a pair; the number of
#: slots per pair is the last boundary
BOUNDS = np.full((18, 8), -1, np.int64)
for _f, _b in ((F_SS, (0, 1)), (F_SB, (0, 1)), (F_BB, (0, 5)), (F_SC, (0, 1)), (F_BC, (0, 1, 2, 3)),
               (F_CC, (0, 1, 2, 3, 4, 5)), (F_SY, (0, 1)), (F_BY, (0, 8, 20, 32, 44, 52)),
               (F_CY, (0, 1, 2, 3, 4, 5, 13)), (F_YY, (0, 4, _YY_SLOTS)),
               (F_PS, (0, 1)), (F_PB, (0, 8)), (F_PC, (0, 1, 2)), (F_PY, (0, 8)),
               (F_XS, (0, 1)), (F_XB, (0, 5)), (F_XC, (0, 1, 2, 3)), (F_XY, (0, 8, 20, 32, 44, 52))):
    BOUNDS[_f, :len(_b)] = _b
#: slots per pair of each family
SLOTS = np.array([BOUNDS[f][BOUNDS[f] >= 0][-1] for f in range(18)], np.int64)
MAX_SLOTS = int(SLOTS.max())
#: lengths of the families' per-call scratch (float64, int64) in the work
#: arrays ``W`` (the box, capsule and cylinder families'; nothing allocated
#: per step: tests/test_engine_steady.py::test_steady_step_allocates_nothing,
#: tests/test_engine_steady_gyro.py::test_every_gyroscopic_setting_steps_without_allocating;
FAMILY_FW, FAMILY_IW = max(BOX_FW, CAPSULE_FW, CYLINDER_FW, YY_FW), max(BOX_IW, YY_IW)


@njit(cache=True)
def _group(key_of, nkeys, perm, start):
    """Stable counting sort of the pairs by key_of[k] (< nkeys): perm (k,)
    the pairs in group order, start (nkeys + 1,) the groups' bounds."""
    for t in range(nkeys + 1):
        start[t] = 0
    for k in range(key_of.shape[0]):
        start[key_of[k] + 1] += 1
    for t in range(nkeys):
        start[t + 1] += start[t]
    for k in range(key_of.shape[0]):
        t = key_of[k]
        perm[start[t]] = k
        start[t] += 1
    for t in range(nkeys, 0, -1):
        start[t] = start[t - 1]
    start[0] = 0


@njit(cache=True)
def _gather_body(X, R, half, radius, hlen, idx, c, Rg, h, r, hl):
    """The bodies idx (k,)'s centres, rotations, half-extents, radii and
    half lengths into the first k rows of c, Rg, h, r, hl."""
    for t in range(idx.shape[0]):
        j = idx[t]
        for i in range(3):
            c[t, i] = X[j, i]
            h[t, i] = half[j, i]
            for l in range(3):
                Rg[t, i, l] = R[j, i, l]
        r[t] = radius[j]
        hl[t] = hlen[j]


#: the number of families; every family (the driver of a scene with every
#: shape, a plane and a static box)
N_FAMILIES = 18
ALL_FAMILIES = (True,) * N_FAMILIES


def families(shape) -> tuple:
    """The families compiled for a scene of bodies of shapes ``shape``
    (codes): an 18-tuple, entry ``f`` True when family ``f`` is compiled,
    else None -- every body-body family between two present shapes (a
    shape with itself too) and each present shape against a plane and a
    static box, whatever the scene's statics and counts.  Only these
    families' kernels are compiled (:func:`family_table`: a scene of
    spheres compiles the sphere-sphere, -plane and -box kernels, not
    box-cylinder:
    tests/test_engine_collision.py::test_driver_compiles_only_the_scenes_families);
    the driver and the fused steps that call it are compiled once whatever
    the families (tests/test_engine_collision.py::test_driver_type_is_the_same_for_every_family_set)."""
    present = sorted(set(int(s) for s in np.asarray(shape, np.int64)))
    on = [None] * N_FAMILIES
    for a in present:
        for b in present:
            if a <= b and (a, b) in TABLE:
                on[TABLE[(a, b)]] = True
        if a in PLANE_TABLE:
            on[PLANE_TABLE[a]] = True
        if a in SBOX_TABLE:
            on[SBOX_TABLE[a]] = True
    return tuple(on)


# ---------------------------------------------------------------------------
# The families' compiled loops behind one type.  Each family runs through a
# function of one signature (:func:`_signature`: the family code, the group's
# pair count and the driver's buffers), compiled on its own and only when a
# scene has the family (:func:`family_table`); the driver calls it through a
# tuple of 18 first-class function values, whose type is the same whatever
# families a scene has.  So the driver, and every fused step that calls it,
# compiles once, not once per set of families; a family a scene lacks is
# :func:`_missing`, which raises.

# The driver's contact slots are :class:`engine.collision.kernels.Slots`
# (normals, points, gaps, fids, flags): flat over a group's pairs x slots
# (``n``, ``p`` 3 floats a slot) in the collider's buffers, (k, S, 3) and
# (k, S) views of them in a group's family call.

#: a group's gathered side (one per pair, k of them): centres ``c`` (k, 3),
#: rotations ``R`` (k, 3, 3), box half extents ``h`` (k, 3), radii ``r``,
#: half lengths ``hl`` (k,); a plane's normal in ``c``, its offset in ``r``
Side = namedtuple("Side", ("c", "R", "h", "r", "hl"))

#: the bodies' shapes as the driver reads them: codes ``shape``, radii
#: ``radius``, half extents ``half`` (n, 3), ``half_length``, ``material``
BodyShapes = namedtuple("BodyShapes", ("shape", "radius", "half", "half_length", "material"))

#: the static planes: unit ``normal`` (k, 3), ``offset`` (k,) m, ``static``
#: index (k,)
PlaneRows = namedtuple("PlaneRows", ("normal", "offset", "static"))

#: the static boxes: ``centre`` (k, 3), rotation ``R`` (k, 3, 3), ``half``
#: extents (k, 3), ``static`` index (k,)
BoxRows = namedtuple("BoxRows", ("centre", "R", "half", "static"))

#: the pair coefficients over materials (a, b): restitution ``e``, static and
#: kinetic friction ``mus``, ``muk``, rolling friction ``mur`` (m)
PairTables = namedtuple("PairTables", ("e", "mus", "muk", "mur"))


@njit(cache=True)
def _slots(fam, k, slot):
    """The group's slot views (k, S, ...) of the flat ``slot`` buffers (a
    :class:`Slots`, as the views), fids and flags zeroed, and the
    flags set where the family writes every slot (one slot per pair, the
    box- and cylinder-plane families)."""
    S = SLOTS[fam]
    S_n = slot.n[:k * S * 3].reshape((k, S, 3))
    S_p = slot.p[:k * S * 3].reshape((k, S, 3))
    S_g = slot.g[:k * S].reshape((k, S))
    S_f = slot.f[:k * S].reshape((k, S))
    S_ok = slot.ok[:k * S].reshape((k, S))
    for t in range(k):
        for s in range(S):
            S_f[t, s] = 0
            S_ok[t, s] = False
    if S == 1 or fam == F_PB or fam == F_PY:
        for t in range(k):
            for s in range(S):
                S_ok[t, s] = True
    return Slots(n=S_n, p=S_p, g=S_g, f=S_f, ok=S_ok)


# Each family's loop over the k gathered pairs (A, B: the sides' (c, R, h,
# r, hl); a plane's normal in B's c, its offset in B's r) into the slots;
# returns whether the normals are to be negated (a family run with its sides
# swapped).  ``gm``, ``edge``, ``se``, ``capm1`` over the group's pairs;
# ``face_points`` see engine.collision.box.EDGE_FACE_POINTS; ``fw``, ``iw``
# the families' scratch (FAMILY_FW, FAMILY_IW).  Plain functions: compiled
# with :func:`_signature` by :func:`_compiled`.

@njit(cache=True)
def _boxes(side, k):
    """The first k rows of a gathered :class:`Side` as :class:`Boxes`."""
    return Boxes(c=side.c[:k], R=side.R[:k], h=side.h[:k])


@njit(cache=True)
def _cylinders(side, k):
    """The first k rows of a gathered :class:`Side` as :class:`Cylinders`."""
    return Cylinders(c=side.c[:k], R=side.R[:k], hl=side.hl[:k], r=side.r[:k])


def _ss(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _sphere_sphere_kernel(A.c[:k], A.r[:k], B.c[:k], B.r[:k], S.n[:, 0, :], S.p[:, 0, :], S.g[:, 0])
    return False


def _sb(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):  # also F_XS
    S = _slots(fam, k, slot)
    _sphere_box_kernel(A.c[:k], A.r[:k], B.c[:k], B.R[:k], B.h[:k], S.n[:, 0, :], S.p[:, 0, :], S.g[:, 0])
    return False


def _bb(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):  # also F_XB
    S = _slots(fam, k, slot)
    mg, ed, sep = gm[:k], edge[:k], se[:k]
    _box_box_kernel(_boxes(A, k), _boxes(B, k), mg, S, ed, sep, fw, iw)
    edge_pair_face_points(S.g, S.ok, ed, sep, mg, face_points)
    return False


def _sc(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _sphere_capsule_kernel(A.c[:k], A.r[:k], B.c[:k], B.R[:k], B.hl[:k], B.r[:k], S.n[:, 0, :], S.p[:, 0, :],
                           S.g[:, 0], fw)
    return False


def _bc(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _capsule_box_kernel(B.c[:k], B.R[:k], B.hl[:k], B.r[:k], A.c[:k], A.R[:k], A.h[:k], S.n, S.p, S.g, S.f, S.ok,
                        fw)
    return True


def _cc(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _capsule_capsule_kernel(A.c[:k], A.R[:k], A.hl[:k], A.r[:k], B.c[:k], B.R[:k], B.hl[:k], B.r[:k], S.n, S.p,
                            S.g, S.f, S.ok, fw)
    return False


def _sy(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _sphere_cylinder_kernel(A.c[:k], A.r[:k], B.c[:k], B.R[:k], B.hl[:k], B.r[:k], capm1[:k], S.n[:, 0, :],
                            S.p[:, 0, :], S.g[:, 0])
    return False


def _by(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    _box_cylinder_kernel(_boxes(A, k), _cylinders(B, k), gm[:k], True, _CORNERS, _BOX_EDGES, _slots(fam, k, slot),
                         fw)
    return False


def _cy(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    _capsule_cylinder_kernel(A.c[:k], A.R[:k], A.hl[:k], A.r[:k], _cylinders(B, k), _slots(fam, k, slot), fw)
    return False


def _yy(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    _cylinder_cylinder_kernel(_cylinders(A, k), _cylinders(B, k), gm[:k], True, _slots(fam, k, slot), fw, iw)
    return False


def _ps(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _sphere_plane_kernel(A.c[:k], A.r[:k], B.c[:k], B.r[:k], S.n[:, 0, :], S.p[:, 0, :], S.g[:, 0])
    return False


def _pb(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _box_plane_kernel(A.c[:k], A.R[:k], A.h[:k], B.c[:k], B.r[:k], S.n, S.p, S.g, S.f)
    return False


def _pc(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _capsule_plane_kernel(A.c[:k], A.R[:k], A.hl[:k], A.r[:k], B.c[:k], B.r[:k], S.n, S.p, S.g, S.f, S.ok, fw)
    return False


def _py(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _cylinder_plane_kernel(A.c[:k], A.R[:k], A.hl[:k], A.r[:k], B.c[:k], B.r[:k], S.n, S.p, S.g, S.f)
    return False


def _xc(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    S = _slots(fam, k, slot)
    _capsule_box_kernel(A.c[:k], A.R[:k], A.hl[:k], A.r[:k], B.c[:k], B.R[:k], B.h[:k], S.n, S.p, S.g, S.f, S.ok,
                        fw)
    return False


def _xy(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    _box_cylinder_kernel(_boxes(B, k), _cylinders(A, k), gm[:k], True, _CORNERS, _BOX_EDGES, _slots(fam, k, slot),
                         fw)
    return True


def _missing(fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw):
    if k >= 0:  # (always: typed as the others, returning a bool)
        raise RuntimeError("a collision family this scene's driver was not compiled for "
                           "(engine.collision.collide.families)")
    return False


#: each family's function (the sphere-box and box-box loops serve a static
#: box too)
_FAMILY_FN = {F_SS: _ss, F_SB: _sb, F_BB: _bb, F_SC: _sc, F_BC: _bc, F_CC: _cc, F_SY: _sy, F_BY: _by, F_CY: _cy,
              F_YY: _yy, F_PS: _ps, F_PB: _pb, F_PC: _pc, F_PY: _py, F_XS: _sb, F_XB: _bb, F_XC: _xc, F_XY: _xy}


def _signature():
    """The families' one signature: bool(fam, k, A, B, gm, slot, edge, se,
    capm1, face_points, fw, iw), the types of the driver's buffers
    (:class:`engine.collision.dispatch.Collider`: writable C-contiguous
    float64, int64 and bool arrays)."""
    f1, i1, b1 = np.zeros(1), np.zeros(1, np.int64), np.zeros(1, np.bool_)
    side = typeof(Side(c=np.zeros((1, 3)), R=np.zeros((1, 3, 3)), h=np.zeros((1, 3)), r=f1, hl=f1))
    return types.boolean(types.int64, types.int64, side, side, typeof(f1), typeof(Slots(n=f1, p=f1, g=f1, f=i1, ok=b1)),
                         typeof(b1), typeof(f1), typeof(i1), types.boolean, typeof(f1), typeof(i1))


#: the functions compiled (or loaded) in this process, by plain function
_COMPILED: dict = {}
#: the tables made in this process, by families
_TABLES: dict = {}


def _compiled(fn):
    """``fn`` compiled with :func:`_signature` (or loaded from the cache),
    once per process."""
    d = _COMPILED.get(fn)
    if d is None:
        d = _COMPILED[fn] = njit(_signature(), cache=True)(fn)
    return d


# numba calls the typing of a tuple of compiled functions (family_table's,
# in every Pack of the driver's buffers) experimental; it is what keeps the
# driver's type one (see above), so its warning is not repeated to users
warnings.filterwarnings("ignore", message="First-class function type", category=NumbaExperimentalFeatureWarning)


def family_table(fams: tuple) -> tuple:
    """The driver's ``fams`` argument for the families ``fams``
    (:func:`families`): 18 compiled functions of one signature, family
    ``f``'s where ``fams[f]`` is True (compiled, or loaded from the cache,
    here, once per process), else :func:`_missing`'s.  The same tuple for
    the same families (a kept Pack stays)."""
    key = tuple(f is True for f in fams)
    t = _TABLES.get(key)
    if t is None:
        t = _TABLES[key] = tuple(_compiled(_FAMILY_FN[f] if key[f] else _missing) for f in range(N_FAMILIES))
    return t


#: :func:`family_table_pack`'s Packs, per families
_TABLE_PACKS: dict = {}


def family_table_pack(fams: tuple) -> Pack:
    """:func:`family_table` as one Pack, made once per process for the
    families ``fams``: :func:`narrow_pack` takes it, so a build's call
    types one Pack instead of a tuple of 18 compiled functions (~1 ms a
    build, typed in Python)."""
    key = tuple(f is True for f in fams)
    p = _TABLE_PACKS.get(key)
    if p is None:
        p = _TABLE_PACKS[key] = Pack(family_table(fams))
    return p


#: the narrow phase's contacts as :func:`collide` writes them (m,) each:
#: bodies ``a``, ``b`` (b = n for statics), static index ``sidx`` (-1 for a
#: body pair), ``normal``, ``point`` (m, 3), ``gap`` m, feature id ``fid``,
#: restitution ``e``, friction coefficients ``mus``, ``muk``, ``mur``
ContactOut = namedtuple("ContactOut", ("a", "b", "sidx", "normal", "point", "gap", "fid", "e", "mus", "muk", "mur"))

#: the narrow phase's work arrays over pairs (:func:`collide`): the pairs'
#: order ``perm``, group bounds ``start`` (33,), keys ``key``, a group's
#: bodies ``ga``, ``gb``, statics ``st``, margins ``gm``, materials ``ma``,
#: ``mb``, edge flags ``edge`` and separations ``se``, -1s ``capm1``; the
#: families' scratch ``fw`` (FAMILY_FW floats) and ``iw`` (FAMILY_IW ints)
NarrowWork = namedtuple("NarrowWork", ("perm", "start", "key", "ga", "gb", "st", "gm", "ma", "mb", "edge", "se",
                                       "capm1", "fw", "iw"))

#: the narrow phase's kept arrays (engine.collision.dispatch.Collider):
#: ``body`` (shape, radius, half_extents, half_length, material) over the
#: bodies, ``planes`` (normal, offset, static index), ``sboxes`` (centre,
#: rotation, half-extents, static index), the statics' materials ``smat``,
#: the pair tables ``coef`` (e, mus, muk, mur), the work arrays ``W``,
#: ``A``, ``B``, ``slot``, the output ``out`` (:func:`collide`) and the
#: families' functions ``fams`` (:func:`family_table`)
Narrow = namedtuple("Narrow", ("body", "planes", "sboxes", "smat", "coef", "W", "A", "B", "slot", "out", "fams"))


@njit(cache=True)
def narrow_pack(body, planes, sboxes, smat, coef, W, A, B, slot, out, kfams):
    """The collider's kept arrays as one Pack of a :class:`Narrow`, made in
    compiled code, with the table of compiled functions of ``kfams``
    (:func:`family_table_pack`): numba types a Pack argument on its fast
    path, a tuple of compiled functions in Python (~1 ms a call; inside a
    named tuple handed from Python it took ~3-5 ms)."""
    return Pack(Narrow(body=body, planes=planes, sboxes=sboxes, smat=smat, coef=coef, W=W, A=A, B=B, slot=slot,
                       out=out, fams=kfams.items))


@njit(cache=True)
def _emit(fam, k, neg, ga, gb, st, mg, S, mat_a, mat_b, coef, out, cnt):
    """Write the kept contacts (gap < the pair's margin mg) of a group's k
    pairs in the family's order (``BOUNDS``), from its slots ``S`` (a
    :class:`Slots` of views): bodies ga (k,), gb (k,) (or the world n with statics st
    (k,) >= 0), their materials mat_a, mat_b (k,) into the pair tables
    ``coef`` (e, mus, muk, mur); ``out`` (a :class:`ContactOut`) written
    from cnt on while there is room.  Returns the count after them."""
    S_n, S_p, S_g, S_f, S_ok = S.n, S.p, S.g, S.f, S.ok
    cap = out.a.shape[0]
    bnd = BOUNDS[fam]
    for q in range(bnd.shape[0] - 1):
        lo, hi = bnd[q], bnd[q + 1]
        if hi < 0:
            break
        for t in range(k):
            for s in range(lo, hi):
                if not (S_ok[t, s] and S_g[t, s] < mg[t]):
                    continue
                if cnt < cap:
                    out.a[cnt] = ga[t]
                    out.b[cnt] = gb[t]
                    out.sidx[cnt] = st[t]
                    for i in range(3):
                        out.normal[cnt, i] = -S_n[t, s, i] if neg else S_n[t, s, i]
                        out.point[cnt, i] = S_p[t, s, i]
                    out.gap[cnt] = S_g[t, s]
                    out.fid[cnt] = S_f[t, s]
                    ma, mb = mat_a[t], mat_b[t]
                    out.e[cnt] = coef.e[ma, mb]
                    out.mus[cnt] = coef.mus[ma, mb]
                    out.muk[cnt] = coef.muk[ma, mb]
                    out.mur[cnt] = coef.mur[ma, mb]
                cnt += 1
    return cnt


@njit(cache=True)
def collide(k_, X, R, pi, pj, bp, pk, bs, sk, margins, from_sweep, margin, sweep, face_points):
    """Contacts of every candidate pair at the pose X (n, 3), R (n, 3, 3).

    ``k_`` the collider's arrays (a :class:`Narrow`): ``body`` (shape,
    radius, half_extents, half_length, material) over the n bodies; pairs:
    body-body ``pi``/``pj`` (i < j), body-plane ``bp`` (body) / ``pk``
    (plane row), body-static-box ``bs`` / ``sk``, with margins (m)
    ``margins`` (body-body, body-plane, body-static-box) -- written here as
    ``margin`` + both bodies' ``sweep`` (n,) when ``from_sweep``;
    ``planes`` (normal,
    offset, static index), ``sboxes`` (centre, rotation, half-extents,
    static index); ``smat`` the statics' materials, ``coef`` the pair
    tables (e, mus, muk, mur) over materials; ``face_points`` see
    :data:`engine.collision.box.EDGE_FACE_POINTS`; ``fams`` the families'
    functions (:func:`family_table`: a pair of a family not compiled
    raises).

    Work arrays (caller-owned, sized by :class:`engine.collision.dispatch.Collider`):
    ``W`` (perm, group bounds (33,), keys, ga, gb, st, group margins,
    materials a, b, edge flags, edge separations, -1s over pairs and
    groups; the families' scratch ``FAMILY_FW`` floats, ``FAMILY_IW``
    ints), ``A``/``B`` the gathered sides (c, R, h, r, hl) over a group's
    pairs, ``slot`` (normals, points, gaps, fids, flags) flat over a
    group's pairs x slots.  Output ``out`` (a, b, sidx, normal, point, gap,
    fid, e, mus, muk, mur) in the module doc's order.

    Returns (contacts, pairs in the largest group, slots it needs): the
    contacts are written only while they fit ``out`` and the groups run
    only while they fit ``A``/``B`` and ``slot``; the caller grows what was
    short and calls again."""
    body, planes, sboxes, smat, coef, fams = k_.body, k_.planes, k_.sboxes, k_.smat, k_.coef, k_.fams
    W, A, B, slot, out = k_.W, k_.A, k_.B, k_.slot, k_.out
    mbb, mbp, mbs = margins
    shape, radius, half, hlen, bmat = body.shape, body.radius, body.half, body.half_length, body.material
    perm, start, key, ga, gb, st, gm = W.perm, W.start, W.key, W.ga, W.gb, W.st, W.gm
    ma, mb, edge, se, capm1, fw, iw = W.ma, W.mb, W.edge, W.se, W.capm1, W.fw, W.iw
    n = shape.shape[0]
    K = A.c.shape[0]
    cap_slots = slot.g.shape[0]
    need_k = 0
    need_s = 0
    cnt = np.int64(0)  # (typed, not Literal[int](0): _emit compiles once; engine/README.md "Compiled code and compile time")
    if from_sweep:
        for t in range(pi.shape[0]):
            mbb[t] = margin + sweep[pi[t]] + sweep[pj[t]]
        for t in range(bp.shape[0]):
            mbp[t] = margin + sweep[bp[t]]
        for t in range(bs.shape[0]):
            mbs[t] = margin + sweep[bs[t]]
    for part in range(3):
        if part == 0:
            m = pi.shape[0]
            for t in range(m):
                sa, sb = shape[pi[t]], shape[pj[t]]
                key[t] = min(sa, sb) * 8 + max(sa, sb)
            nkeys = 32
        else:
            m = bp.shape[0] if part == 1 else bs.shape[0]
            for t in range(m):
                key[t] = shape[bp[t]] if part == 1 else shape[bs[t]]
            nkeys = 4
        if m == 0:
            continue
        _group(key[:m], nkeys, perm, start)
        for g in range(nkeys):
            lo, hi = start[g], start[g + 1]
            k = hi - lo
            if k == 0:
                continue
            fam = FAMILY[g] if part == 0 else (PLANE_FAMILY[g] if part == 1 else SBOX_FAMILY[g])
            if fam < 0:
                continue
            S = SLOTS[fam]
            need_k = max(need_k, k)
            need_s = max(need_s, k * S)
            if k > K or k * S > cap_slots:
                continue
            for t in range(k):
                p = perm[lo + t]
                if part == 0:
                    i, j = pi[p], pj[p]
                    if shape[i] > shape[j]:
                        i, j = j, i
                    ga[t], gb[t], st[t] = i, j, -1
                    gm[t] = mbb[p]
                    ma[t], mb[t] = bmat[i], bmat[j]
                elif part == 1:
                    ga[t], gb[t] = bp[p], n
                    st[t] = planes.static[pk[p]]
                    gm[t] = mbp[p]
                    ma[t], mb[t] = bmat[bp[p]], smat[st[t]]
                else:
                    ga[t], gb[t] = bs[p], n
                    st[t] = sboxes.static[sk[p]]
                    gm[t] = mbs[p]
                    ma[t], mb[t] = bmat[bs[p]], smat[st[t]]
            _gather_body(X, R, half, radius, hlen, ga[:k], A.c, A.R, A.h, A.r, A.hl)
            if part == 0:
                _gather_body(X, R, half, radius, hlen, gb[:k], B.c, B.R, B.h, B.r, B.hl)
            elif part == 1:
                for t in range(k):
                    row = pk[perm[lo + t]]
                    for i in range(3):
                        B.c[t, i] = planes.normal[row, i]
                    B.r[t] = planes.offset[row]
            else:
                for t in range(k):
                    row = sk[perm[lo + t]]
                    for i in range(3):
                        B.c[t, i] = sboxes.centre[row, i]
                        B.h[t, i] = sboxes.half[row, i]
                        for l in range(3):
                            B.R[t, i, l] = sboxes.R[row, i, l]
            neg = fams[fam](fam, k, A, B, gm, slot, edge, se, capm1, face_points, fw, iw)
            views = Slots(n=slot.n[:k * S * 3].reshape((k, S, 3)), p=slot.p[:k * S * 3].reshape((k, S, 3)),
                          g=slot.g[:k * S].reshape((k, S)), f=slot.f[:k * S].reshape((k, S)),
                          ok=slot.ok[:k * S].reshape((k, S)))
            cnt = _emit(fam, k, neg, ga, gb, st, gm, views, ma, mb, coef, out, cnt)
    return cnt, need_k, need_s


@njit(cache=True)
def collide_packed(kept, X, R, pi, pj, margins, bp, pk, bs, sk, from_sweep, margin, sweep, face_points):
    """:func:`collide` with the arrays kept between calls in ONE argument:
    ``kept`` an :class:`engine.pack.Pack` of a :class:`Narrow` (the
    Collider's buffers and the scene's :func:`family_table`, whose type is
    the same for every scene; one pointer to unbox instead of ~55 arrays);
    the rest as :func:`collide`."""
    return collide(kept.items, X, R, pi, pj, bp, pk, bs, sk, margins, from_sweep, margin, sweep, face_points)
