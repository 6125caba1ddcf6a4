"""Overlaps at the start: the depth (m) by which shapes overlap in a
compiled scene's initial poses, measured with the same geometry as the
``max_penetration`` metric (:func:`measure_penetration` on one frame).

:func:`contract.scene.compile_scene` refuses a scene whose deepest initial
overlap exceeds ``[scenario] max_initial_overlap`` (default
:data:`MAX_INITIAL_OVERLAP`): a radius typed in millimetres as metres, or a
slope angle in radians, buries a body inside its support, and a run from
there measures the solver's escape, not the physics the scene names
(tests/test_spec.py::test_buried_start_is_a_spec_error).  Shapes that touch
exactly (a stack resting face on face, a ball on its plane) overlap by
rounding only, far below the tolerance.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

from physbench.contract.geometry.penetration import measure_penetration
from physbench.contract.scene_model import Scene

#: default ``[scenario] max_initial_overlap`` (m): the deepest overlap a start
#: may have without saying so.  1 um: well above the rounding of shapes
#: placed exactly in contact (< 1e-12 m in every shipped scene), well below
#: any overlap a typo makes.
MAX_INITIAL_OVERLAP = 1e-6


@dataclass(frozen=True)
class Overlap:
    """One overlapping pair at the start: body ``a`` (Body.index) and body
    ``b`` or static ``b`` (``kind`` 'body' / 'static'), ``depth`` m (the
    shortest move that separates them); ``what_a``/``what_b`` name them as
    the spec does, with their key paths."""

    a: int
    kind: str
    b: int
    depth: float
    what_a: str
    what_b: str

    def describe(self) -> str:
        return f"{self.what_a} overlaps {self.what_b} by {self.depth:.6g} m"


def _body_what(scene: Scene, i: int) -> str:
    b = scene.bodies[i]
    return f"body {b.name!r} ({scene.body_key(i, 'position')})"


def _static_what(scene: Scene, s: int) -> str:
    st = scene.statics[s]
    key = {"plane": "offset", "slope": "angle"}.get(st.kind, "position")
    return f"{st.kind} {st.name!r} (static[{st.index}].{key})"


def initial_overlaps(scene: Scene) -> list[Overlap]:
    """Every pair of shapes overlapping in ``scene``'s initial poses, deepest
    first (depth > 0 m; exact zeros are contact, not overlap).  Empty
    without the ``contact`` effect: shapes then pass through each other by
    the scene's own statement."""
    if not scene.has("contact") or scene.n_bodies == 0:
        return []
    pos = np.array([[b.position for b in scene.bodies]], float)
    quat = np.array([[b.orientation for b in scene.bodies]], float)
    pen = measure_penetration(scene, SimpleNamespace(pos=pos, quat=quat))
    out = []
    for col, depth in zip(pen.cols.tolist(), pen.depths.tolist()):
        if not depth > 0.0:  # NaN: no kernel for the pair; not a measured overlap
            continue
        a, kind, b = pen.pairs[col]
        what_b = _static_what(scene, b) if kind == "static" else _body_what(scene, b)
        out.append(Overlap(a, kind, b, float(depth), _body_what(scene, a), what_b))
    return sorted(out, key=lambda o: -o.depth)


#: a clearance (m) below which two shapes at the start count as touching
#: (:func:`initial_contacts`)
CONTACT_GAP = 1e-9


def initial_contacts(scene: Scene, gap: float = CONTACT_GAP) -> list[Overlap]:
    """Every pair of shapes touching or overlapping in ``scene``'s initial
    poses: signed overlap > -``gap`` m (``depth`` < 0 is a clearance
    smaller than ``gap``, 0 exact contact, > 0 an overlap), deepest first.
    Unlike :func:`initial_overlaps` it sees shapes that touch exactly
    (a ball resting on its plane); for ``physbench validate``.  Empty
    without the ``contact`` effect."""
    from physbench.contract.geometry.dispatch import signed_gap
    from physbench.contract.geometry.placed import placed_body, placed_static_box
    from physbench.contract.geometry.support import plane_gap

    if not scene.has("contact") or scene.n_bodies == 0:
        return []
    bodies = scene.bodies
    pos = np.array([b.position for b in bodies], float)
    quat = np.array([b.orientation for b in bodies], float)
    rb = np.array([b.bounding_radius for b in bodies], float)
    placed = [placed_body(b, pos[i:i + 1], quat[i:i + 1]) for i, b in enumerate(bodies)]
    out: list[Overlap] = []
    for st in scene.statics:
        for i, b in enumerate(bodies):
            if st.shape == "plane":
                d = float(plane_gap(placed[i], st.normal, st.offset)[0])
            elif st.shape == "box":
                d = float(signed_gap(placed[i], placed_static_box(st, 1))[0])
            else:
                continue
            if d > -gap:
                out.append(Overlap(i, "static", st.index, d, _body_what(scene, i), _static_what(scene, st.index)))
    n = len(bodies)
    if n > 1:
        if n <= 2000:
            ii, jj = np.triu_indices(n, 1)
            near = np.linalg.norm(pos[ii] - pos[jj], axis=1) <= rb[ii] + rb[jj] + gap
            pairs = zip(ii[near].tolist(), jj[near].tolist())
        else:
            from scipy.spatial import cKDTree

            pairs = (p for p in cKDTree(pos).query_pairs(2 * float(rb.max()) + gap)
                     if np.linalg.norm(pos[p[0]] - pos[p[1]]) <= rb[p[0]] + rb[p[1]] + gap)
        for i, j in pairs:
            i, j = min(i, j), max(i, j)
            d = float(signed_gap(placed[i], placed[j])[0])
            if d > -gap:
                out.append(Overlap(i, "body", j, d, _body_what(scene, i), _body_what(scene, j)))
    return sorted(out, key=lambda o: -o.depth)


def overlap_errors(scene: Scene, label: str, tolerance: float) -> list[str]:
    """Spec-error lines for the initial overlaps deeper than ``tolerance`` m:
    each names both shapes, the depth and the key paths."""
    errs = []
    for o in initial_overlaps(scene):
        if o.depth > tolerance:
            key = scene.body_key(o.a, "position")
            errs.append(f"{label}: {key}: the start is buried: {o.describe()}, deeper than "
                        f"scenario.max_initial_overlap = {tolerance:g} m (check units: lengths in m, "
                        f"angles in degrees); move the shapes apart, or set [scenario] max_initial_overlap "
                        f"where the overlap is the point")
    return errs
