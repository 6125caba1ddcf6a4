"""Box pairs: box-plane (the eight corners) and box-box: separating-axis
test over 15 axes (3 + 3 face normals, 9 edge cross products, faces
preferred within a tolerance), then for a face axis the incident face
clipped against the reference face's side planes (Sutherland-Hodgman), at
most four points kept (deepest, farthest from it, and the two spanning the
largest area); for an edge axis the closest points of the two edges plus
the face manifold's points, their gaps clamped at the edge axis' separation
(:func:`box_box`)."""

from __future__ import annotations

import numpy as np

from engine.mathutil import cross
from engine.collision.common import _CORNERS, _empty, _segment_segment


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


def _clip_batch(P: np.ndarray, cnt: np.ndarray, nrm: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sutherland-Hodgman over a batch of polygons: keep the part of each
    polygon with n.p <= off.  ``P`` (k, w, 3) vertices (the first ``cnt``
    (k,) of each row valid), ``nrm`` (k, 3), ``off`` (k,).  Same vertices in
    the same order as the one-polygon algorithm: per edge (p, q), p if it is
    inside, then the crossing point if the edge crosses the plane."""
    k, w = P.shape[0], P.shape[1]
    if w == 0:
        return P, cnt
    nx, ny, nz = nrm[:, 0:1], nrm[:, 1:2], nrm[:, 2:3]
    dp = nx * P[:, :, 0] + ny * P[:, :, 1] + nz * P[:, :, 2] - off[:, None]  # (k, w)
    slot = np.arange(w)
    valid = slot[None, :] < cnt[:, None]
    if np.all((dp <= 0.0) | ~valid):
        return P, cnt  # every vertex inside: all kept, no edge crosses
    nxt = (slot[None, :] + 1) % np.maximum(cnt, 1)[:, None]  # (k, w)
    rows = np.arange(k)[:, None]
    Q = P[rows, nxt]
    dq = dp[rows, nxt]
    keep_p = valid & (dp <= 0.0)
    cross_ = valid & (((dp < 0.0) & (0.0 < dq)) | ((dq < 0.0) & (0.0 < dp)))
    den = np.where(cross_, dp - dq, 1.0)
    t = (dp / den)[:, :, None]
    X = P + (Q - P) * t
    cand = np.empty((k, 2 * w, 3))
    cand[:, 0::2] = P
    cand[:, 1::2] = X
    mask = np.empty((k, 2 * w), bool)
    mask[:, 0::2] = keep_p
    mask[:, 1::2] = cross_
    new_cnt = mask.sum(axis=1)
    wn = int(new_cnt.max(initial=0))
    order = np.argsort(~mask, axis=1, kind="stable")[:, :wn]
    return cand[rows, order], new_cnt


def _edge_axes(C, dA, hA, hB):
    """Separations (k, 9) and unit axes (k, 9, 3) (A's frame) of the edge
    axes A_i x B_j, index 3 i + j; -inf where the axis is degenerate or
    duplicates a face normal."""
    k = C.shape[0]
    # e_i x c for c = C[:, :, j]: (0, -c2, c1), (c2, 0, -c0), (-c1, c0, 0)
    L = np.zeros((k, 3, 3, 3))  # [k, i, j, component]
    c0, c1, c2 = C[:, 0, :], C[:, 1, :], C[:, 2, :]  # (k, 3) over j
    L[:, 0, :, 1] = -c2
    L[:, 0, :, 2] = c1
    L[:, 1, :, 0] = c2
    L[:, 1, :, 2] = -c0
    L[:, 2, :, 0] = -c1
    L[:, 2, :, 1] = c0
    L = L.reshape(k, 9, 3)
    # (einsum reductions: the same sums, bit for bit, as per-axis einsums)
    ln = np.sqrt(np.einsum("kai,kai->ka", L, L))
    ok = ln > 1e-5
    Ln = L / np.where(ok, ln, 1.0)[..., None]
    aL = np.abs(Ln)
    rA = np.einsum("kai,ki->ka", aL, hA)
    aLB = np.abs(np.einsum("kai,kij->kaj", Ln, C))
    rB = np.einsum("kaj,kj->ka", aLB, hB)
    s = np.abs(np.einsum("kai,ki->ka", Ln, dA)) - rA - rB
    # an edge axis parallel to a face normal duplicates that face axis
    dup = (aL.max(axis=2) > 1 - 1e-9) | (aLB.max(axis=2) > 1 - 1e-9)
    return np.where(ok & ~dup, s, -np.inf), Ln


def _edge_contact(p, e, cA, RA, hA, cB, RB, hB, d, axesE):
    """Edge-edge contact of pair ``p`` on edge axis ``e``: (normal, point)."""
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
    return L, 0.5 * (qa[0] + qb[0])


def box_box(cA, RA, hA, cB, RB, hB, margin):
    """Separating axes + clipping; normal from A to B.  ``margin`` (k,).

    Vectorised over the pairs: the face case clips every pair's incident
    face at once (:func:`_clip_batch`); the rare edge-edge case is a loop."""
    k = cA.shape[0]
    if k == 0:
        return _empty()
    d = cB - cA
    C = np.einsum("kji,kjl->kil", RA, RB)  # C[i, j] = A_i . B_j
    absC = np.abs(C) + 1e-9
    dA = np.einsum("kji,kj->ki", RA, d)
    # faces of A
    sepA = np.abs(dA) - (hA + np.einsum("kij,kj->ki", absC, hB))
    dB = np.einsum("kij,ki->kj", C, dA)
    sepB = np.abs(dB) - (hB + np.einsum("kij,ki->kj", absC, hA))
    # edges A_i x B_j, in A's frame: L = e_i x C[:, :, j]
    sepE, axesE = _edge_axes(C, dA, hA, hB)
    ar = np.arange(k)
    fa = np.argmax(sepA, axis=1)
    fb = np.argmax(sepB, axis=1)
    sa, sb = sepA[ar, fa], sepB[ar, fb]
    e = np.argmax(sepE, axis=1)
    se = sepE[ar, e]
    # prefer face axes (stable manifolds): an edge axis or B's face must be
    # clearly better (larger separation) than the alternative
    tol_abs = 1e-5 * (hA.max(axis=1) + hB.max(axis=1))
    best_face = np.maximum(sa, sb)
    edge = se > best_face + 0.05 * np.abs(best_face) + tol_abs
    flip = sb > sa + 0.05 * np.abs(sa) + tol_abs
    # slots: the edge-edge point, then up to four face-manifold points, per
    # pair, emitted in pair order
    S_n = np.zeros((k, 5, 3))
    S_p = np.zeros((k, 5, 3))
    S_g = np.zeros((k, 5))
    S_f = np.zeros((k, 5), np.int64)
    S_ok = np.zeros((k, 5), bool)
    for p in np.flatnonzero(edge).tolist():
        if se[p] < margin[p]:
            L, pt = _edge_contact(p, int(e[p]), cA, RA, hA, cB, RB, hB, d, axesE)
            S_n[p, 0], S_p[p, 0], S_g[p, 0], S_f[p, 0], S_ok[p, 0] = L, pt, se[p], 64 + int(e[p]), True
    # The face manifold of every pair, edge pairs included.  An edge-edge
    # point alone is blind to the faces about to come down and to the
    # corners already inside: a box spinning at 20-27 rad/s about an edge
    # that crossed another box's edge brought the edge's end down onto that
    # box's face at 2 m/s; the axis of least overlap switched between the
    # face and the edge from one rerun of the step to the next, and with it
    # the contacts, so the time of impact search never converged and the
    # corner went 5.7 mm in.  An edge pair keeps the face points' gaps
    # clamped at the edge axis' separation: the edge axis is the pair's
    # least overlap, and no point of a body lies deeper in the other than
    # that, while its overlap along a face normal may be more.
    _box_box_faces(ar, cA, RA, hA, cB, RB, hB, margin, dA, dB, fa, fb, flip,
                   S_n[:, 1:], S_p[:, 1:], S_g[:, 1:], S_f[:, 1:], S_ok[:, 1:])
    _edge_pair_face_points(S_ok[:, 1:], S_g[:, 1:], edge, se, margin)
    if not S_ok.any():
        return _empty()
    kk = np.repeat(ar, 5).reshape(k, 5)
    m = S_ok
    return kk[m], S_n[m], S_p[m], S_g[m], S_f[m]


def _edge_pair_face_points(ok: np.ndarray, gap: np.ndarray, edge: np.ndarray, se: np.ndarray,
                           margin: np.ndarray) -> None:
    """The face-manifold points of the edge pairs (``edge`` (k,) bool),
    slots ``ok``, ``gap`` (k, 4), in place: kept, their gaps clamped at the
    pair's edge-axis separation ``se`` (k,) m (see :func:`box_box`) -- and
    dropped where that puts them beyond the pair's ``margin`` (k,) m."""
    gap[edge] = np.maximum(gap[edge], se[edge, None])
    ok[edge] &= gap[edge] < margin[edge, None]


def _box_box_faces(idx, cA, RA, hA, cB, RB, hB, margin, dA, dB, fa, fb, flip, S_n, S_p, S_g, S_f, S_ok):
    """Face-case contacts of the pairs ``idx``, written into the slots."""
    k = idx.size
    ar = np.arange(k)
    fl = flip[idx]
    f3 = fl[:, None]
    # reference box: A, or B when flipped (rows of the stacked [A; B] arrays)
    nA = cA.shape[0]
    ref_i = idx + nA * fl
    inc_i = idx + nA * ~fl
    cAB = np.concatenate([cA, cB])
    RAB = np.concatenate([RA, RB])
    hAB = np.concatenate([hA, hB])
    ref_c, ref_R, ref_h = cAB[ref_i], RAB[ref_i], hAB[ref_i]
    inc_c, inc_R, inc_h = cAB[inc_i], RAB[inc_i], hAB[inc_i]
    face = np.where(fl, fb[idx], fa[idx])
    # A's face: normal toward B; B's face: from B toward A
    sgnA = np.where(dA[idx, fa[idx]] >= 0, 1.0, -1.0)
    sgnB = np.where(dB[idx, fb[idx]] <= 0, 1.0, -1.0)
    nrm = ref_R[ar, :, face] * np.where(fl, sgnB, sgnA)[:, None]
    # incident face: the face of the other box most anti-parallel to nrm
    # (batched matmul: the same sums, bit for bit, as one pair's inc_R.T @ nrm)
    dots = np.matmul(inc_R.transpose(0, 2, 1), nrm[:, :, None])[:, :, 0]
    fi = np.argmax(np.abs(dots), axis=1)
    sgn = np.where(dots[ar, fi] > 0, -1.0, 1.0)
    fc = inc_c + inc_R[ar, :, fi] * (sgn * inc_h[ar, fi])[:, None]
    u_i = np.where(fi == 0, 1, 0)
    v_i = np.where(fi == 2, 1, 2)
    U = inc_R[ar, :, u_i] * inc_h[ar, u_i][:, None]
    V = inc_R[ar, :, v_i] * inc_h[ar, v_i][:, None]
    P = np.empty((k, 4, 3))
    P[:, 0] = fc + U + V
    P[:, 1] = fc - U + V
    P[:, 2] = fc - U - V
    P[:, 3] = fc + U - V
    cnt = np.full(k, 4)
    ref_face_c = ref_c + nrm * ref_h[ar, face][:, None]
    # side planes of the reference face: its other two axes, ascending
    a_lo = np.where(face == 0, 1, 0)
    a_hi = np.where(face == 2, 1, 2)
    for a in (a_lo, a_hi):
        ax = ref_R[ar, :, a]
        off = np.matmul(ax[:, None, :], ref_c[:, :, None])[:, 0, 0]  # = ax @ ref_c per pair, bit for bit
        ha = ref_h[ar, a]
        P, cnt = _clip_batch(P, cnt, ax, off + ha)
        P, cnt = _clip_batch(P, cnt, -ax, -off + ha)
    w = P.shape[1]
    if w == 0:
        return
    valid = np.arange(w)[None, :] < cnt[:, None]
    D = P - ref_face_c[:, None, :]
    gap = np.matmul(D, nrm[:, :, None])[..., 0]
    valid &= gap < margin[idx][:, None]
    nv = valid.sum(axis=1)
    # at most four points: all when there are <= 4, else the deepest, the one
    # farthest from it, and the two on either side of that line farthest from it
    sel = np.full((k, 4), -1, np.int64)
    few = nv <= 4
    if few.any():
        o = np.argsort(~valid[few], axis=1, kind="stable")[:, :4]
        fi_ = np.flatnonzero(few)
        sel[fi_[:, None], np.arange(o.shape[1])[None, :]] = np.where(np.take_along_axis(valid[few], o, axis=1), o, -1)
    many = np.flatnonzero(~few)
    if many.size:
        Pm, vm, gm, nm = P[many], valid[many], gap[many], nrm[many]
        r = np.arange(many.size)
        i0 = np.argmin(np.where(vm, gm, np.inf), axis=1)
        E = Pm - Pm[r, i0][:, None, :]
        dd = np.where(vm, np.einsum("kmi,kmi->km", E, E), -np.inf)
        i1 = np.argmax(dd, axis=1)
        cr = cross(E[r, i1][:, None, :], E)
        area = np.matmul(cr, nm[:, :, None])[..., 0]
        i2 = np.argmax(np.where(vm, area, -np.inf), axis=1)
        i3 = np.argmin(np.where(vm, area, np.inf), axis=1)
        cand = np.stack([i0, i1, i2, i3], axis=1)
        # unique, first occurrence order
        dup = np.zeros((many.size, 4), bool)
        for s in range(1, 4):
            dup[:, s] = np.any(cand[:, s:s + 1] == cand[:, :s], axis=1)
        kept = np.where(dup, -1, cand)
        o = np.argsort(kept < 0, axis=1, kind="stable")
        sel[many] = np.take_along_axis(kept, o, axis=1)
    ok = sel >= 0
    sidx = np.where(ok, sel, 0)
    Ps = P[ar[:, None], sidx] if w else np.zeros((k, 4, 3))
    gs = gap[ar[:, None], sidx]
    normal = np.where(f3, -nrm, nrm)
    rows = idx
    S_ok[rows] = ok
    S_g[rows] = np.where(ok, gs, 0.0)
    S_p[rows] = Ps - nrm[:, None, :] * (0.5 * gs)[:, :, None]
    S_n[rows] = normal[:, None, :]
    S_f[rows] = (np.where(fl, 16, 0) + 4 * face)[:, None] + np.arange(4)[None, :]
