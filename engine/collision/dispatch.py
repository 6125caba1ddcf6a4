"""Narrow-phase dispatch (the collision driver): candidate pairs grouped by
shape pair, each group handed to its family's function from the tables
``TABLE`` (body-body, keyed by canonically ordered shape codes),
``PLANE_TABLE`` and ``SBOX_TABLE`` (body-static, keyed by the body's
shape), the results gathered into :class:`engine.state.Contacts` with
their pair coefficients (looked up per material pair)."""

from __future__ import annotations

import numpy as np

from engine.mathutil import quat_to_matrix
from engine.model import BOX, CAPSULE, CYLINDER, S_PLANE, SPHERE
from engine.profile import Stage
from engine.state import Contacts
from engine.collision.sphere import sphere_box, sphere_plane, sphere_sphere
from engine.collision.capsule import capsule_box, capsule_capsule, capsule_plane, sphere_capsule
from engine.collision.box import box_box, box_plane
from engine.collision.cylinder import box_cylinder, capsule_cylinder, cylinder_plane, sphere_cylinder
from engine.collision.cylinder_pair import cylinder_cylinder


class _BodyGeom(dict):
    """Geometry of the bodies ``idx``: ``c`` centres, ``R`` rotations, ``r``
    radii, ``h`` half-extents, ``hl`` half-lengths, each gathered on first
    use (a pair function reads only what its shapes need).  ``const``: the
    pose-independent entries already gathered (kept by the pair groups)."""

    def __init__(self, model, X, R, idx, const=None):
        super().__init__()
        self._src = {"c": X, "R": R, "r": model.radius, "h": model.half_extents, "hl": model.half_length}
        self._idx = idx
        self._const = const

    def __missing__(self, key):
        const = self._const
        if const is not None and key in const:
            v = self[key] = const[key]
            return v
        v = self[key] = self._src[key][self._idx]
        if const is not None and key in ("r", "h", "hl"):
            const[key] = v
        return v


def _body_geom(model, X, R, idx, const=None):
    return _BodyGeom(model, X, R, idx, const)


def _bb_sphere_sphere(A, B, margin):
    return sphere_sphere(A["c"], A["r"], B["c"], B["r"])


def _bb_sphere_box(A, B, margin):
    return sphere_box(A["c"], A["r"], B["c"], B["R"], B["h"])


def _bb_box_box(A, B, margin):
    return box_box(A["c"], A["R"], A["h"], B["c"], B["R"], B["h"], margin)


def _bb_sphere_capsule(A, B, margin):
    return sphere_capsule(A["c"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_sphere_cylinder(A, B, margin):
    return sphere_cylinder(A["c"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_box_capsule(A, B, margin):
    # capsule_box has the capsule first: swap and flip the normal
    k, n, p, g, f = capsule_box(B["c"], B["R"], B["hl"], B["r"], A["c"], A["R"], A["h"])
    return k, -n, p, g, f


def _bb_capsule_capsule(A, B, margin):
    return capsule_capsule(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_box_cylinder(A, B, margin):
    return box_cylinder(A["c"], A["R"], A["h"], B["c"], B["R"], B["hl"], B["r"], margin)


def _bb_capsule_cylinder(A, B, margin):
    return capsule_cylinder(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_cylinder_cylinder(A, B, margin):
    return cylinder_cylinder(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["hl"], B["r"], margin)


def _cylinder_sbox(A, B, m):
    # box_cylinder has the box first: swap and flip the normal
    k, n, p, g, f = box_cylinder(B["c"], B["R"], B["h"], A["c"], A["R"], A["hl"], A["r"], m)
    return k, -n, p, g, f


def _plane(model, pk):
    return dict(n=model.plane_normal[pk], o=model.plane_offset[pk])


def _sbox(model, sk):
    return dict(c=model.sbox_pos[sk], R=model.sbox_R[sk], h=model.sbox_half[sk])


#: body-body functions keyed by canonically ordered shape codes
TABLE = {
    (SPHERE, SPHERE): _bb_sphere_sphere,
    (SPHERE, BOX): _bb_sphere_box,
    (BOX, BOX): _bb_box_box,
    (SPHERE, CAPSULE): _bb_sphere_capsule,
    (BOX, CAPSULE): _bb_box_capsule,
    (CAPSULE, CAPSULE): _bb_capsule_capsule,
    (SPHERE, CYLINDER): _bb_sphere_cylinder,
    (BOX, CYLINDER): _bb_box_cylinder,
    (CAPSULE, CYLINDER): _bb_capsule_cylinder,
    (CYLINDER, CYLINDER): _bb_cylinder_cylinder,
}


#: body-plane functions keyed by the body's shape code
PLANE_TABLE = {
    SPHERE: lambda A, P, m: sphere_plane(A["c"], A["r"], P["n"], P["o"]),
    BOX: lambda A, P, m: box_plane(A["c"], A["R"], A["h"], P["n"], P["o"]),
    CAPSULE: lambda A, P, m: capsule_plane(A["c"], A["R"], A["hl"], A["r"], P["n"], P["o"]),
    CYLINDER: lambda A, P, m: cylinder_plane(A["c"], A["R"], A["hl"], A["r"], P["n"], P["o"]),
}


#: body-static-box functions keyed by the body's shape code
SBOX_TABLE = {
    SPHERE: lambda A, B, m: sphere_box(A["c"], A["r"], B["c"], B["R"], B["h"]),
    BOX: lambda A, B, m: box_box(A["c"], A["R"], A["h"], B["c"], B["R"], B["h"], m),
    CAPSULE: lambda A, B, m: capsule_box(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["h"]),
    CYLINDER: _cylinder_sbox,
}


def unsupported_pairs(model) -> list[str]:
    """Shape pairs the scene may bring into contact that the table lacks."""
    if not model.has("contact"):
        return []
    names = {SPHERE: "sphere", BOX: "box", CAPSULE: "capsule", CYLINDER: "cylinder"}
    shapes = sorted(set(int(s) for s in model.shape))
    out = []
    if model.n >= 2:
        for a in shapes:
            for b in shapes:
                if a <= b and (a, b) not in TABLE and (a != b or int(np.sum(model.shape == a)) >= 2):
                    out.append(f"{names[a]}-{names[b]}")
    if model.plane_normal.shape[0]:
        out += [f"{names[s]}-plane" for s in shapes if s not in PLANE_TABLE]
    if model.sbox_pos.shape[0]:
        out += [f"{names[s]}-box(static)" for s in shapes if s not in SBOX_TABLE]
    return out


def _ro(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _bb_groups(model, pi, pj) -> list:
    """Body-body candidate pairs grouped by canonically ordered shape pair:
    [(fn, sel, a, b, const_a, const_b, (e, mus, muk, mur))] with ``sel`` the
    pairs of the group, a/b its bodies (first/second shape) and the pair
    coefficients per pair.  Depends only on the candidate pairs."""
    si, sj = model.shape[pi], model.shape[pj]
    swap = si > sj
    a = np.where(swap, pj, pi)
    b = np.where(swap, pi, pj)
    sa = np.minimum(si, sj)
    sb = np.maximum(si, sj)
    key = sa * 8 + sb
    out = []
    for kv in np.unique(key):
        sel = np.flatnonzero(key == kv)
        fn = TABLE.get((int(kv) // 8, int(kv) % 8))
        if fn is None:
            continue
        ga, gb = _ro(a[sel]), _ro(b[sel])
        mat = tuple(_ro(t) for t in model.pair_coefficients(ga, gb, np.full(ga.size, -1, np.int64)))
        out.append((fn, sel, ga, gb, {}, {}, mat))
    return out


def _static_groups(model, pairs, table, statics) -> list:
    """Body-static candidate pairs grouped by the body's shape:
    [(fn, sel, bodies, rows, static indices, const, (e, mus, muk, mur))]."""
    bi, sk = pairs
    shapes = model.shape[bi]
    out = []
    for s in np.unique(shapes):
        sel = np.flatnonzero(shapes == s)
        fn = table.get(int(s))
        if fn is None:
            continue
        b_, k_ = _ro(bi[sel]), _ro(sk[sel])
        st = _ro(statics[k_])
        mat = tuple(_ro(t) for t in model.pair_coefficients(b_, np.full(b_.size, model.n, np.int64), st))
        out.append((fn, sel, b_, k_, st, {}, mat))
    return out


#: pair groupings a narrow phase keeps (keyed by the candidate pairs);
#: cleared when full
GROUP_CACHE = 16


def _cached(cache, key, make):
    if cache is None:
        return make()
    v = cache.get(key)
    if v is None:
        if len(cache) >= GROUP_CACHE:
            cache.clear()
        v = cache[key] = make()
    return v


def collide_pairs(model, X, R, pi, pj, plane_pairs, sbox_pairs, margin_bb, margin_bp, margin_bs,
                  cache: dict | None = None) -> Contacts:
    """Contacts for candidate pairs at the pose (X (n, 3), R (n, 3, 3)).

    ``pi``/``pj`` body-body pairs (i < j) with margins ``margin_bb``;
    ``plane_pairs``/``sbox_pairs`` (body, row) with margins.  Returns
    :class:`Contacts` with b = n for statics, ordered deterministically
    (body-body by pair, then planes, then static boxes), with their pair
    coefficients.  ``cache``: a dict in which the grouping of the candidate
    pairs by shape (and their coefficients) is kept, keyed by the pairs --
    it depends on nothing else, and a resting scene has the same candidates
    every step."""
    n = model.n
    parts: list[Contacts] = []
    if pi.size:
        groups = _cached(cache, ("bb", pi.tobytes(), pj.tobytes()), lambda: _bb_groups(model, pi, pj))
        for fn, sel, ga, gb, ca, cb, mat in groups:
            mg = margin_bb[sel]
            k, nn, p, g, f = fn(_body_geom(model, X, R, ga, ca), _body_geom(model, X, R, gb, cb), mg)
            keep = g < mg[k]
            if keep.all():
                parts.append(Contacts(ga[k], gb[k], np.full(k.size, -1, np.int64), nn, p, g, f,
                                      mat[0][k], mat[1][k], mat[2][k], mat[3][k]))
                continue
            k = k[keep]
            parts.append(Contacts(ga[k], gb[k], np.full(k.size, -1, np.int64), nn[keep], p[keep], g[keep], f[keep],
                                  mat[0][k], mat[1][k], mat[2][k], mat[3][k]))
    for tag, pairs, table, geom, margins, statics in (
            ("plane", plane_pairs, PLANE_TABLE, _plane, margin_bp, model.plane_static),
            ("sbox", sbox_pairs, SBOX_TABLE, _sbox, margin_bs, model.sbox_static)):
        bi, sk = pairs
        if bi.size == 0:
            continue
        groups = _cached(cache, (tag, bi.tobytes(), sk.tobytes()),
                         lambda: _static_groups(model, pairs, table, statics))
        for fn, sel, b_, k_, st, const, mat in groups:
            mg = margins[sel]
            G = const.get("geom")
            if G is None:  # writable gathers: the kernels are compiled for writable arrays
                G = const["geom"] = geom(model, k_)
            k, nn, p, g, f = fn(_body_geom(model, X, R, b_, const), G, mg)
            keep = g < mg[k]
            if not keep.all():
                k = k[keep]
                nn, p, g, f = nn[keep], p[keep], g[keep], f[keep]
            parts.append(Contacts(b_[k], np.full(k.size, n, np.int64), st[k], nn, p, g, f,
                                  mat[0][k], mat[1][k], mat[2][k], mat[3][k]))
    return Contacts.concat(parts)


class NarrowPhase(Stage):
    """Contacts at the start pose for the broad phase's pairs, with a margin
    per pair of ``contact_margin`` plus both bodies' sweep (how far they can
    close in this step)."""

    name = "narrowphase"
    family = "narrowphase"

    def __init__(self, model):
        self.margin = float(model.setting("contact_margin"))
        self.speculative = model.setting("ccd") != "off"
        self.groups: dict = {}  # pair groupings by candidate pairs (see collide_pairs)

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        sw = ctx.sweep if self.speculative else np.zeros(model.n)
        pi, pj = ctx.pairs_i, ctx.pairs_j
        mbb = self.margin + sw[pi] + sw[pj]
        mbp = self.margin + sw[ctx.plane_pairs[0]]
        mbs = self.margin + sw[ctx.sbox_pairs[0]]
        ctx.contacts = collide_pairs(model, state.x, ctx.R0, pi, pj, ctx.plane_pairs, ctx.sbox_pairs, mbb, mbp, mbs,
                                     self.groups)


def pair_contacts(model, X, q_or_R, a: int, b: int, sidx: int) -> Contacts:
    """All features of one pair at a pose, with no margin (for time-of-impact
    refinement).  ``b`` is a body index, or n with ``sidx`` the static."""
    R = q_or_R if q_or_R.ndim == 3 else quat_to_matrix(q_or_R)
    inf = np.array([np.inf])
    z = np.zeros(0, np.int64)
    if sidx < 0:
        i, j = min(a, b), max(a, b)
        return collide_pairs(model, X, R, np.array([i]), np.array([j]), (z, z), (z, z), inf, inf, inf)
    if model.static_shape[sidx] == S_PLANE:
        row = int(np.flatnonzero(model.plane_static == sidx)[0])
        return collide_pairs(model, X, R, z, z, (np.array([a]), np.array([row])), (z, z), inf, inf, inf)
    row = int(np.flatnonzero(model.sbox_static == sidx)[0])
    return collide_pairs(model, X, R, z, z, (z, z), (np.array([a]), np.array([row])), inf, inf, inf)


def warm_up() -> None:
    """Compile (or load from the cache) every narrow-phase kernel and the
    broad phase's, with the argument types of the step (writable
    C-contiguous float64 and int64 arrays), on one tiny pair each (see
    :mod:`engine.jit`)."""
    from engine import broadphase

    I = np.eye(3)[None]
    c0, c1 = np.zeros((1, 3)), np.array([[0.0, 0.0, 0.15]])
    r, h, pn, po, mg = np.full(1, 0.1), np.full((1, 3), 0.1), np.array([[0.0, 0.0, 1.0]]), np.zeros(1), np.ones(1)
    sphere_sphere(c0, r, c1, r)
    sphere_plane(c0, r, pn, po)
    sphere_box(c0, r, c1, I, h)
    box_plane(c0, I, h, pn, po)
    box_box(c0, I, h, c1, I, h, mg)
    capsule_plane(c0, I, r, r, pn, po)
    sphere_capsule(c0, r, c1, I, r, r)
    capsule_capsule(c0, I, r, r, c1, I, r, r)
    capsule_box(c0, I, r, r, c1, I, h)
    cylinder_plane(c0, I, r, r, pn, po)
    sphere_cylinder(c0, r, c1, I, r, r)
    sphere_cylinder(c0, r, c1, I, r, r, np.ones(1, bool))
    box_cylinder(c0, I, h, c1, I, r, r, mg)
    box_cylinder(c0, I, h, c1, I, r, r)
    capsule_cylinder(c0, I, r, r, c1, I, r, r)
    cylinder_cylinder(c0, I, r, r, c1, I, r, r, mg)
    cylinder_cylinder(c0, I, r, r, c1, I, r, r)
    broadphase.warm_up()
