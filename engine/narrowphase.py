"""Narrow phase: contact points, normals and signed gaps per shape pair.

``TABLE`` maps a shape pair to a function; body-body pairs are grouped by
their (canonically ordered) shape pair when the model is built
(:func:`pair_kinds`), body-static pairs by the body's shape.  Every function
is vectorised over the pairs of its group and returns

    (k, normal, point, gap, fid)

with ``k`` the index of the pair each contact belongs to, ``normal`` (m, 3)
the unit normal from the first shape toward the second, ``point`` (m, 3) the
world point midway between the two surfaces, ``gap`` (m,) the signed
distance (m, negative = penetration) and ``fid`` a feature id.  Contacts with
``gap`` below the pair's margin are kept: beyond touching contacts, the
margin admits *speculative* contacts that the step might close (the broad
phase sizes it from the bodies' motion), which the solver and CCD use.

Pairs:
* sphere-sphere, sphere-plane, sphere-box: exact closest points.
* box-plane: the eight corners.
* box-box: separating-axis test over 15 axes (3 + 3 face normals, 9 edge
  cross products, faces preferred within a tolerance), then for a face axis
  the incident face clipped against the reference face's side planes
  (Sutherland-Hodgman), at most four points kept (deepest, farthest from it,
  and the two spanning the largest area); for an edge axis the closest
  points of the two edges.
* capsules: their segment's closest points make sphere-like contacts:
  capsule-plane (both end caps), sphere-capsule, capsule-capsule (closest
  points, plus the end projections when nearly parallel so a lying capsule
  rests on two points), capsule-box (minimum of the box's signed distance
  along the segment by golden-section search -- the signed distance of a
  convex set is convex -- plus the end caps).
* cylinder-plane: the deepest rim point of each cap plus four fixed rim
  points per cap.  Other cylinder pairs are not modelled (the adapter reports
  them unsupported).
"""

from __future__ import annotations

import numpy as np

from engine.mathutil import cross, quat_to_matrix
from engine.model import BOX, CAPSULE, CYLINDER, SPHERE
from engine.profile import Stage
from engine.state import Contacts

_EPS = 1e-12


def _norm(v):
    return np.sqrt(np.einsum("...i,...i->...", v, v))


# ---------------------------------------------------------------------------
# primitives (vectorised)

def sphere_sphere(ca, ra, cb, rb):
    d = cb - ca
    L = _norm(d)
    ok = L > _EPS
    n = np.where(ok[:, None], d / np.where(ok, L, 1.0)[:, None], np.array([0.0, 0.0, 1.0]))
    gap = L - ra - rb
    point = ca + n * (ra + 0.5 * gap)[:, None]
    k = np.arange(ca.shape[0])
    return k, n, point, gap, np.zeros(k.size, np.int64)


def sphere_plane(c, r, pn, po):
    gap = np.einsum("ki,ki->k", pn, c) - po - r
    point = c - pn * (r + 0.5 * gap)[:, None]
    k = np.arange(c.shape[0])
    return k, -pn, point, gap, np.zeros(k.size, np.int64)


def sphere_box(c, r, cb, Rb, hb):
    """Sphere (first) against box (second); normal from sphere to box."""
    local = np.einsum("kji,kj->ki", Rb, c - cb)
    cl = np.clip(local, -hb, hb)
    diff = local - cl
    dist = _norm(diff)
    outside = dist > _EPS
    # inside: leave through the face of least penetration
    pen = hb - np.abs(local)
    face = np.argmin(pen, axis=1)
    k = np.arange(c.shape[0])
    n_in = np.zeros_like(local)
    n_in[k, face] = np.where(local[k, face] >= 0.0, 1.0, -1.0)
    n_loc = np.where(outside[:, None], diff / np.where(outside, dist, 1.0)[:, None], n_in)
    gap = np.where(outside, dist, -pen[k, face]) - r
    n_out = np.einsum("kij,kj->ki", Rb, n_loc)  # box outward normal, world
    point = c - n_out * (r + 0.5 * gap)[:, None]
    return k, -n_out, point, gap, np.zeros(k.size, np.int64)


_CORNERS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)  # (8, 3)


def box_plane(c, R, half, pn, po):
    loc = _CORNERS[None, :, :] * half[:, None, :]  # (k, 8, 3)
    corners = c[:, None, :] + np.einsum("kij,kmj->kmi", R, loc)
    gap = np.einsum("kmi,ki->km", corners, pn) - po[:, None]
    k = np.repeat(np.arange(c.shape[0]), 8)
    gap = gap.reshape(-1)
    corners = corners.reshape(-1, 3)
    pnr = np.repeat(pn, 8, axis=0)
    point = corners - pnr * (0.5 * gap)[:, None]
    fid = np.tile(np.arange(8), c.shape[0])
    return k, -pnr, point, gap, fid


def _segment_closest(p, a0, a1):
    """Closest points on segments [a0, a1] to points p (k, 3); returns
    (point, s in [0, 1])."""
    d = a1 - a0
    dd = np.einsum("ki,ki->k", d, d)
    s = np.where(dd > _EPS, np.einsum("ki,ki->k", p - a0, d) / np.where(dd > _EPS, dd, 1.0), 0.0)
    s = np.clip(s, 0.0, 1.0)
    return a0 + d * s[:, None], s


def _segment_segment(p0, p1, q0, q1):
    """Closest points between segments [p0,p1] and [q0,q1] (Ericson 5.1.9)."""
    d1 = p1 - p0
    d2 = q1 - q0
    r = p0 - q0
    a = np.einsum("ki,ki->k", d1, d1)
    e = np.einsum("ki,ki->k", d2, d2)
    f = np.einsum("ki,ki->k", d2, r)
    c = np.einsum("ki,ki->k", d1, r)
    b = np.einsum("ki,ki->k", d1, d2)
    denom = a * e - b * b
    s = np.where(denom > _EPS * np.maximum(a * e, _EPS), np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0, 1), 0.0)
    t = np.where(e > _EPS, (b * s + f) / np.where(e > _EPS, e, 1.0), 0.0)
    # clamp t and recompute s
    t_lo = t < 0.0
    t_hi = t > 1.0
    t = np.clip(t, 0.0, 1.0)
    s = np.where(t_lo, np.clip(np.where(a > _EPS, -c / np.where(a > _EPS, a, 1.0), 0.0), 0, 1), s)
    s = np.where(t_hi, np.clip(np.where(a > _EPS, (b - c) / np.where(a > _EPS, a, 1.0), 0.0), 0, 1), s)
    return p0 + d1 * s[:, None], q0 + d2 * t[:, None]


def _capsule_ends(c, R, hl):
    ax = R[:, :, 2]
    return c - ax * hl[:, None], c + ax * hl[:, None]


def capsule_plane(c, R, hl, r, pn, po):
    e0, e1 = _capsule_ends(c, R, hl)
    k0, n0, p0, g0, _ = sphere_plane(e0, r, pn, po)
    k1, n1, p1, g1, _ = sphere_plane(e1, r, pn, po)
    m = c.shape[0]
    return (np.concatenate([k0, k1]), np.concatenate([n0, n1]), np.concatenate([p0, p1]),
            np.concatenate([g0, g1]), np.concatenate([np.zeros(m, np.int64), np.ones(m, np.int64)]))


def sphere_capsule(cs, rs, c, R, hl, r):
    e0, e1 = _capsule_ends(c, R, hl)
    p, _ = _segment_closest(cs, e0, e1)
    return sphere_sphere(cs, rs, p, r)


def capsule_capsule(ca, Ra, hla, ra, cb, Rb, hlb, rb):
    a0, a1 = _capsule_ends(ca, Ra, hla)
    b0, b1 = _capsule_ends(cb, Rb, hlb)
    pa, pb = _segment_segment(a0, a1, b0, b1)
    out = [sphere_sphere(pa, ra, pb, rb)]
    par = np.abs(np.einsum("ki,ki->k", Ra[:, :, 2], Rb[:, :, 2])) > 0.995
    if par.any():
        idx = np.flatnonzero(par)
        for end, fid in ((a0, 1), (a1, 2)):
            q, _ = _segment_closest(end[idx], b0[idx], b1[idx])
            k, n, p, g, _ = sphere_sphere(end[idx], ra[idx], q, rb[idx])
            out.append((idx[k], n, p, g, np.full(k.size, fid)))
        for end, fid in ((b0, 3), (b1, 4)):
            q, _ = _segment_closest(end[idx], a0[idx], a1[idx])
            k, n, p, g, _ = sphere_sphere(q, ra[idx], end[idx], rb[idx])
            out.append((idx[k], n, p, g, np.full(k.size, fid)))
    return _cat(out)


def _box_sdf(p, cb, Rb, hb):
    local = np.einsum("kji,kj->ki", Rb, p - cb)
    q = np.abs(local) - hb
    outside = _norm(np.maximum(q, 0.0))
    inside = np.minimum(np.max(q, axis=1), 0.0)
    return outside + inside


def capsule_box(c, R, hl, r, cb, Rb, hb):
    """Capsule (first) against box (second)."""
    e0, e1 = _capsule_ends(c, R, hl)
    lo = np.zeros(c.shape[0])
    hi = np.ones(c.shape[0])
    g = 0.5 * (np.sqrt(5.0) - 1.0)
    d = e1 - e0
    for _ in range(40):  # golden-section search for the minimum of the convex sdf along the segment
        m1 = hi - g * (hi - lo)
        m2 = lo + g * (hi - lo)
        f1 = _box_sdf(e0 + d * m1[:, None], cb, Rb, hb)
        f2 = _box_sdf(e0 + d * m2[:, None], cb, Rb, hb)
        left = f1 < f2
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
    s = 0.5 * (lo + hi)
    # the minimum may sit at an end: compare with the end points exactly
    f_s = _box_sdf(e0 + d * s[:, None], cb, Rb, hb)
    f_0 = _box_sdf(e0, cb, Rb, hb)
    f_1 = _box_sdf(e1, cb, Rb, hb)
    s = np.where(f_0 <= f_s, 0.0, s)
    s = np.where(f_1 < np.minimum(f_s, f_0), 1.0, s)
    out = [sphere_box(e0 + d * s[:, None], r, cb, Rb, hb)]
    for end, fid, sv in ((e0, 1, 0.0), (e1, 2, 1.0)):
        keep = np.flatnonzero(np.abs(s - sv) * 2.0 * hl > 0.02 * (2.0 * hl + r))
        if keep.size:
            k, n, p, gg, _ = sphere_box(end[keep], r[keep], cb[keep], Rb[keep], hb[keep])
            out.append((keep[k], n, p, gg, np.full(k.size, fid)))
    return _cat(out)


def cylinder_plane(c, R, hl, r, pn, po):
    ax = R[:, :, 2]
    m = c.shape[0]
    pts = []
    fids = []
    # deepest rim direction: the plane normal's component in the cap plane, reversed
    t = pn - np.einsum("ki,ki->k", pn, ax)[:, None] * ax
    tl = _norm(t)
    ok = tl > 1e-6
    tdir = np.where(ok[:, None], t / np.where(ok, tl, 1.0)[:, None], R[:, :, 0])
    for s, base in ((-1.0, 0), (1.0, 8)):
        cap = c + s * ax * hl[:, None]
        pts.append(cap - tdir * r[:, None])
        fids.append(np.full(m, base))
        for j, (cx, cy) in enumerate(((1, 0), (0, 1), (-1, 0), (0, -1))):
            pts.append(cap + r[:, None] * (cx * R[:, :, 0] + cy * R[:, :, 1]))
            fids.append(np.full(m, base + 1 + j))
    P = np.stack(pts, axis=1)  # (m, 10, 3)
    F = np.stack(fids, axis=1)
    gap = np.einsum("kmi,ki->km", P, pn) - po[:, None]
    # the deepest-rim points duplicate a fixed one when the cylinder stands upright: drop them then
    gap[~ok, 0] = np.inf
    gap[~ok, 5] = np.inf
    k = np.repeat(np.arange(m), P.shape[1])
    pnr = np.repeat(pn, P.shape[1], axis=0)
    P = P.reshape(-1, 3)
    gap = gap.reshape(-1)
    return k, -pnr, P - pnr * (0.5 * gap)[:, None], gap, F.reshape(-1)


# ---------------------------------------------------------------------------
# box-box

def _clip(poly: list[tuple], nrm: tuple, off: float) -> list[tuple]:
    """Sutherland-Hodgman: keep the part of polygon ``poly`` (list of 3-tuples)
    with n.p <= off.  Plain floats: these polygons have four to eight
    vertices, where numpy's per-call overhead dominates."""
    out: list[tuple] = []
    m = len(poly)
    if m == 0:
        return out
    nx, ny, nz = nrm
    for i in range(m):
        p, q = poly[i], poly[(i + 1) % m]
        dp = nx * p[0] + ny * p[1] + nz * p[2] - off
        dq = nx * q[0] + ny * q[1] + nz * q[2] - off
        if dp <= 0.0:
            out.append(p)
        if (dp < 0.0 < dq) or (dq < 0.0 < dp):
            t = dp / (dp - dq)
            out.append((p[0] + (q[0] - p[0]) * t, p[1] + (q[1] - p[1]) * t, p[2] + (q[2] - p[2]) * t))
    return out


def _reduce4(P: np.ndarray, gap: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Indices of at most four points of a manifold: deepest, farthest from
    it, then the points on either side of that line farthest from it."""
    m = P.shape[0]
    if m <= 4:
        return np.arange(m)
    i0 = int(np.argmin(gap))
    d = np.einsum("ki,ki->k", P - P[i0], P - P[i0])
    i1 = int(np.argmax(d))
    area = cross(P[i1] - P[i0], P - P[i0]) @ n
    i2 = int(np.argmax(area))
    i3 = int(np.argmin(area))
    keep = []
    for i in (i0, i1, i2, i3):
        if i not in keep:
            keep.append(i)
    return np.array(keep)


def box_box(cA, RA, hA, cB, RB, hB, margin):
    """Separating axes + clipping; normal from A to B.  ``margin`` (k,)."""
    k = cA.shape[0]
    d = cB - cA
    C = np.einsum("kji,kjl->kil", RA, RB)  # C[i, j] = A_i . B_j
    absC = np.abs(C) + 1e-9
    dA = np.einsum("kji,kj->ki", RA, d)
    # faces of A
    sepA = np.abs(dA) - (hA + np.einsum("kij,kj->ki", absC, hB))
    dB = np.einsum("kij,ki->kj", C, dA)
    sepB = np.abs(dB) - (hB + np.einsum("kij,ki->kj", absC, hA))
    # edges A_i x B_j, in A's frame: L = e_i x C[:, :, j]
    sepE = np.full((k, 9), -np.inf)
    axesE = np.zeros((k, 9, 3))
    for i in range(3):
        ei = np.zeros(3)
        ei[i] = 1.0
        for j in range(3):
            L = cross(ei[None, :], C[:, :, j])
            ln = _norm(L)
            ok = ln > 1e-5
            Ln = L / np.where(ok, ln, 1.0)[:, None]
            rA = np.einsum("ki,ki->k", np.abs(Ln), hA)
            rB = np.einsum("kj,kj->k", np.abs(np.einsum("ki,kij->kj", Ln, C)), hB)
            s = np.abs(np.einsum("ki,ki->k", Ln, dA)) - rA - rB
            # an edge axis parallel to a face normal duplicates that face axis
            dup = (np.max(np.abs(Ln), axis=1) > 1 - 1e-9) | (np.max(np.abs(np.einsum("ki,kij->kj", Ln, C)), axis=1) > 1 - 1e-9)
            sepE[:, 3 * i + j] = np.where(ok & ~dup, s, -np.inf)
            axesE[:, 3 * i + j] = Ln
    ks, ns, ps, gs, fs = [], [], [], [], []
    for p in range(k):
        fa = int(np.argmax(sepA[p]))
        fb = int(np.argmax(sepB[p]))
        sa, sb = sepA[p, fa], sepB[p, fb]
        e = int(np.argmax(sepE[p]))
        se = sepE[p, e]
        # prefer face axes (stable manifolds): an edge axis or B's face must be
        # clearly better (larger separation) than the alternative
        tol_abs = 1e-5 * (hA[p].max() + hB[p].max())
        best_face = max(sa, sb)
        if se > best_face + 0.05 * abs(best_face) + tol_abs:
            # edge-edge
            i, j = divmod(e, 3)
            L = RA[p] @ axesE[p, e]
            if L @ d[p] < 0:
                L = -L
            sA = np.sign(RA[p].T @ L)
            sB = -np.sign(RB[p].T @ L)
            pa = cA[p] + RA[p] @ (np.where(np.arange(3) == i, 0.0, sA) * hA[p])
            pb = cB[p] + RB[p] @ (np.where(np.arange(3) == j, 0.0, sB) * hB[p])
            a0, a1 = pa - RA[p][:, i] * hA[p, i], pa + RA[p][:, i] * hA[p, i]
            b0, b1 = pb - RB[p][:, j] * hB[p, j], pb + RB[p][:, j] * hB[p, j]
            qa, qb = _segment_segment(a0[None], a1[None], b0[None], b1[None])
            gap = se
            if gap < margin[p]:
                ks.append(np.array([p]))
                ns.append(L[None])
                ps.append(0.5 * (qa + qb))
                gs.append(np.array([gap]))
                fs.append(np.array([64 + e]))
            continue
        if not sb > sa + 0.05 * abs(sa) + tol_abs:
            ref_c, ref_R, ref_h, inc_c, inc_R, inc_h, face, flip = cA[p], RA[p], hA[p], cB[p], RB[p], hB[p], fa, False
            nrm = ref_R[:, face] * (1.0 if dA[p, face] >= 0 else -1.0)
        else:
            ref_c, ref_R, ref_h, inc_c, inc_R, inc_h, face, flip = cB[p], RB[p], hB[p], cA[p], RA[p], hA[p], fb, True
            nrm = ref_R[:, face] * (1.0 if dB[p, face] <= 0 else -1.0)  # from B toward A
        # incident face: the face of the other box most anti-parallel to nrm
        dots = inc_R.T @ nrm
        fi = int(np.argmax(np.abs(dots)))
        sgn = -1.0 if dots[fi] > 0 else 1.0
        fc = inc_c + inc_R[:, fi] * (sgn * inc_h[fi])
        u_i, v_i = [a for a in range(3) if a != fi]
        U = inc_R[:, u_i] * inc_h[u_i]
        V = inc_R[:, v_i] * inc_h[v_i]
        poly = [tuple(fc + U + V), tuple(fc - U + V), tuple(fc - U - V), tuple(fc + U - V)]
        ref_face_c = ref_c + nrm * ref_h[face]
        for a in range(3):
            if a == face:
                continue
            ax = ref_R[:, a]
            off = float(ax @ ref_c)
            axt = (float(ax[0]), float(ax[1]), float(ax[2]))
            poly = _clip(poly, axt, off + ref_h[a])
            poly = _clip(poly, (-axt[0], -axt[1], -axt[2]), -off + ref_h[a])
            if not poly:
                break
        if not poly:
            continue
        P = np.array(poly)
        gap = (P - ref_face_c) @ nrm
        keep = gap < margin[p]
        if not keep.any():
            continue
        P, gap = P[keep], gap[keep]
        sel = _reduce4(P, gap, nrm)
        P, gap = P[sel], gap[sel]
        normal = -nrm if flip else nrm
        ks.append(np.full(P.shape[0], p))
        ns.append(np.repeat(normal[None], P.shape[0], axis=0))
        ps.append(P - nrm[None] * (0.5 * gap)[:, None])
        gs.append(gap)
        fs.append((16 if flip else 0) + 4 * face + np.arange(P.shape[0]))
    if not ks:
        return _empty()
    return (np.concatenate(ks), np.concatenate(ns), np.concatenate(ps), np.concatenate(gs),
            np.concatenate(fs).astype(np.int64))


def _empty():
    return (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))


def _cat(parts):
    parts = [p for p in parts if p[0].size]
    if not parts:
        return _empty()
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(5))


# ---------------------------------------------------------------------------
# dispatch

def _body_geom(model, X, R, idx):
    return dict(c=X[idx], R=R[idx], r=model.radius[idx], h=model.half_extents[idx], hl=model.half_length[idx])


def _bb_sphere_sphere(A, B, margin):
    return sphere_sphere(A["c"], A["r"], B["c"], B["r"])


def _bb_sphere_box(A, B, margin):
    return sphere_box(A["c"], A["r"], B["c"], B["R"], B["h"])


def _bb_box_box(A, B, margin):
    return box_box(A["c"], A["R"], A["h"], B["c"], B["R"], B["h"], margin)


def _bb_sphere_capsule(A, B, margin):
    return sphere_capsule(A["c"], A["r"], B["c"], B["R"], B["hl"], B["r"])


def _bb_box_capsule(A, B, margin):
    # capsule_box has the capsule first: swap and flip the normal
    k, n, p, g, f = capsule_box(B["c"], B["R"], B["hl"], B["r"], A["c"], A["R"], A["h"])
    return k, -n, p, g, f


def _bb_capsule_capsule(A, B, margin):
    return capsule_capsule(A["c"], A["R"], A["hl"], A["r"], B["c"], B["R"], B["hl"], B["r"])


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


def collide_pairs(model, X, R, pi, pj, plane_pairs, sbox_pairs, margin_bb, margin_bp, margin_bs) -> Contacts:
    """Contacts for candidate pairs at the pose (X (n, 3), R (n, 3, 3)).

    ``pi``/``pj`` body-body pairs (i < j) with margins ``margin_bb``;
    ``plane_pairs``/``sbox_pairs`` (body, row) with margins.  Returns
    :class:`Contacts` with b = n for statics, ordered deterministically
    (body-body by pair, then planes, then static boxes)."""
    n = model.n
    parts: list[Contacts] = []
    if pi.size:
        si, sj = model.shape[pi], model.shape[pj]
        swap = si > sj
        a = np.where(swap, pj, pi)
        b = np.where(swap, pi, pj)
        sa = np.minimum(si, sj)
        sb = np.maximum(si, sj)
        key = sa * 8 + sb
        for kv in np.unique(key):
            sel = np.flatnonzero(key == kv)
            fn = TABLE.get((int(kv) // 8, int(kv) % 8))
            if fn is None:
                continue
            ga, gb = a[sel], b[sel]
            k, nn, p, g, f = fn(_body_geom(model, X, R, ga), _body_geom(model, X, R, gb), margin_bb[sel])
            keep = g < margin_bb[sel][k]
            k = k[keep]
            parts.append(Contacts(ga[k], gb[k], np.full(k.size, -1, np.int64), nn[keep], p[keep], g[keep], f[keep]))
    for pairs, table, geom, margins, statics in ((plane_pairs, PLANE_TABLE, _plane, margin_bp, model.plane_static),
                                                 (sbox_pairs, SBOX_TABLE, _sbox, margin_bs, model.sbox_static)):
        bi, sk = pairs
        if bi.size == 0:
            continue
        shapes = model.shape[bi]
        for s in np.unique(shapes):
            sel = np.flatnonzero(shapes == s)
            fn = table.get(int(s))
            if fn is None:
                continue
            k, nn, p, g, f = fn(_body_geom(model, X, R, bi[sel]), geom(model, sk[sel]), margins[sel])
            keep = g < margins[sel][k]
            k = k[keep]
            parts.append(Contacts(bi[sel][k], np.full(k.size, n, np.int64), statics[sk[sel][k]], nn[keep], p[keep],
                                  g[keep], f[keep]))
    c = Contacts.concat(parts)
    _materials(model, c)
    return c


def _materials(model, c: Contacts) -> None:
    st = c.sidx >= 0
    bb = ~st
    e = np.empty(c.m)
    mus = np.empty(c.m)
    muk = np.empty(c.m)
    if bb.any():
        e[bb] = model.e_bb[c.a[bb], c.b[bb]]
        mus[bb] = model.mus_bb[c.a[bb], c.b[bb]]
        muk[bb] = model.muk_bb[c.a[bb], c.b[bb]]
    if st.any():
        e[st] = model.e_bs[c.a[st], c.sidx[st]]
        mus[st] = model.mus_bs[c.a[st], c.sidx[st]]
        muk[st] = model.muk_bs[c.a[st], c.sidx[st]]
    c.e, c.mus, c.muk = e, mus, muk


class NarrowPhase(Stage):
    """Contacts at the start pose for the broad phase's pairs, with a margin
    per pair of ``contact_margin`` plus both bodies' sweep (how far they can
    close in this step)."""

    name = "narrowphase"
    family = "narrowphase"

    def __init__(self, model):
        self.margin = float(model.setting("contact_margin"))
        self.speculative = model.setting("ccd") != "off"

    def __call__(self, model, state, ctx) -> None:
        if ctx.reuse_contacts:
            return
        sw = ctx.sweep if self.speculative else np.zeros(model.n)
        pi, pj = ctx.pairs_i, ctx.pairs_j
        mbb = self.margin + sw[pi] + sw[pj]
        mbp = self.margin + sw[ctx.plane_pairs[0]]
        mbs = self.margin + sw[ctx.sbox_pairs[0]]
        ctx.contacts = collide_pairs(model, state.x, ctx.R0, pi, pj, ctx.plane_pairs, ctx.sbox_pairs, mbb, mbp, mbs)


def pair_contacts(model, X, q_or_R, a: int, b: int, sidx: int) -> Contacts:
    """All features of one pair at a pose, with no margin (for time-of-impact
    refinement).  ``b`` is a body index, or n with ``sidx`` the static."""
    R = q_or_R if q_or_R.ndim == 3 else quat_to_matrix(q_or_R)
    inf = np.array([np.inf])
    z = np.zeros(0, np.int64)
    if sidx < 0:
        i, j = min(a, b), max(a, b)
        return collide_pairs(model, X, R, np.array([i]), np.array([j]), (z, z), (z, z), inf, inf, inf)
    st = model.scene.statics[sidx]
    if st.shape == "plane":
        row = int(np.flatnonzero(model.plane_static == sidx)[0])
        return collide_pairs(model, X, R, z, z, (np.array([a]), np.array([row])), (z, z), inf, inf, inf)
    row = int(np.flatnonzero(model.sbox_static == sidx)[0])
    return collide_pairs(model, X, R, z, z, (z, z), (np.array([a]), np.array([row])), inf, inf, inf)
