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
from numba import njit

from physbench.engine.collision.kernels import Boxes, Slots, cross3, empty, segment_segment


@njit(cache=True)
def _box_plane_kernel(c, R, half, pn, po, S_n, S_p, S_g, S_f):
    for k in range(c.shape[0]):
        for m in range(8):
            sx = -1.0 if m < 4 else 1.0
            sy = -1.0 if m % 4 < 2 else 1.0
            sz = -1.0 if m % 2 == 0 else 1.0
            for i in range(3):
                S_p[k, m, i] = c[k, i] + (R[k, i, 0] * (sx * half[k, 0]) + R[k, i, 1] * (sy * half[k, 1])
                                          + R[k, i, 2] * (sz * half[k, 2]))
            g = S_p[k, m, 0] * pn[k, 0] + S_p[k, m, 1] * pn[k, 1] + S_p[k, m, 2] * pn[k, 2] - po[k]
            S_g[k, m] = g
            for i in range(3):
                S_p[k, m, i] -= pn[k, i] * (0.5 * g)
                S_n[k, m, i] = -pn[k, i]
            S_f[k, m] = m


def box_plane(c, R, half, pn, po):
    """Boxes (centres (k, 3), rotations (k, 3, 3), half-extents (k, 3))
    against planes (unit normals pn (k, 3), offsets po (k,)): the eight
    corners (``_CORNERS`` order), pair by pair; normal -pn."""
    k = c.shape[0]
    S_n, S_p, S_g, S_f = np.empty((k, 8, 3)), np.empty((k, 8, 3)), np.empty((k, 8)), np.empty((k, 8), np.int64)
    if k:
        f = np.ascontiguousarray
        _box_plane_kernel(f(c, float), f(R, float), f(half, float), f(pn, float), f(po, float), S_n, S_p, S_g, S_f)
    return np.repeat(np.arange(k), 8), S_n.reshape(-1, 3), S_p.reshape(-1, 3), S_g.reshape(-1), S_f.reshape(-1)


@njit(cache=True)
def _clip(P, cnt, nx, ny, nz, off, Q):
    """Sutherland-Hodgman: the part of the polygon P[:cnt] (rows (3,))
    with n.p <= off, written to Q; returns its vertex count.  Per edge
    (p, q): p if it is inside, then the crossing point if the edge crosses
    the plane.  When every vertex is inside, Q is P's copy."""
    allin = True
    for v in range(cnt):
        if nx * P[v, 0] + ny * P[v, 1] + nz * P[v, 2] - off > 0.0:
            allin = False
            break
    if allin:
        for v in range(cnt):
            for c in range(3):
                Q[v, c] = P[v, c]
        return cnt
    m = 0
    for v in range(cnt):
        w = (v + 1) % cnt
        dp = nx * P[v, 0] + ny * P[v, 1] + nz * P[v, 2] - off
        dq = nx * P[w, 0] + ny * P[w, 1] + nz * P[w, 2] - off
        if dp <= 0.0:
            for c in range(3):
                Q[m, c] = P[v, c]
            m += 1
        if (dp < 0.0 and 0.0 < dq) or (dq < 0.0 and 0.0 < dp):
            t = dp / (dp - dq)
            for c in range(3):
                Q[m, c] = P[v, c] + (P[w, c] - P[v, c]) * t
            m += 1
    return m


@njit(cache=True)
def _argmax3(a0, a1, a2):
    if a1 > a0:
        return 2 if a2 > a1 else 1
    return 2 if a2 > a0 else 0


#: lengths of :func:`_box_box_kernel`'s scratch (float64, int64)
BOX_FW, BOX_IW = 275, 20


@njit(cache=True)
def _box_box_kernel(A, B, margin, S, edge, se_out, fw, iw):
    """Separating axes and contacts of box pairs (k of them: the
    :class:`Boxes` ``A`` against ``B``, ``margin`` (k,) m), written into
    the :class:`Slots` ``S`` (k, 5): the edge-edge point (slot 0), then up
    to four face-manifold points; ``edge`` (k,) whether the pair's axis is
    an edge axis, ``se_out`` (k,) its best edge-axis separation (m).
    ``fw`` (>= :data:`BOX_FW`,) float64 and ``iw`` (>= :data:`BOX_IW`,)
    int64 its scratch: nothing is allocated
    (tests/test_engine_steady.py::test_steady_step_allocates_nothing)."""
    cA, RA, hA, cB, RB, hB = A.c, A.R, A.h, B.c, B.R, B.h
    S_n, S_p, S_g, S_f, S_ok = S.n, S.p, S.g, S.f, S.ok
    k = cA.shape[0]
    C = fw[0:9].reshape((3, 3))
    absC = fw[9:18].reshape((3, 3))
    Ln = fw[18:45].reshape((9, 3))
    V = fw[45:99].reshape((18, 3))  # 3-vector scratch
    d, dA, dB, sepA, sepB, L, aLB, nrm, w3 = V[0], V[1], V[2], V[3], V[4], V[5], V[6], V[7], V[8]
    pa, pb, a0, a1, b0, b1, qa, qb, cr = V[9], V[10], V[11], V[12], V[13], V[14], V[15], V[16], V[17]
    P = fw[99:147].reshape((16, 3))
    Q = fw[147:195].reshape((16, 3))
    E = fw[195:243].reshape((16, 3))
    gap = fw[243:259]
    area = fw[259:275]
    valid = iw[0:16]  # 1: the point is within the margin
    cand = iw[16:20]
    for p in range(k):
        for i in range(3):
            d[i] = cB[p, i] - cA[p, i]
        for i in range(3):
            for l in range(3):
                C[i, l] = RA[p, 0, i] * RB[p, 0, l] + RA[p, 1, i] * RB[p, 1, l] + RA[p, 2, i] * RB[p, 2, l]
                absC[i, l] = abs(C[i, l]) + 1e-9
        for i in range(3):
            dA[i] = RA[p, 0, i] * d[0] + RA[p, 1, i] * d[1] + RA[p, 2, i] * d[2]
        for i in range(3):
            sepA[i] = abs(dA[i]) - (hA[p, i] + (absC[i, 0] * hB[p, 0] + absC[i, 1] * hB[p, 1] + absC[i, 2] * hB[p, 2]))
        for j in range(3):
            dB[j] = C[0, j] * dA[0] + C[1, j] * dA[1] + C[2, j] * dA[2]
        for j in range(3):
            sepB[j] = abs(dB[j]) - (hB[p, j] + (absC[0, j] * hA[p, 0] + absC[1, j] * hA[p, 1] + absC[2, j] * hA[p, 2]))
        # edge axes A_i x B_j (A's frame), index 3 i + j
        best_e = 0
        se = -np.inf
        for i in range(3):
            for j in range(3):
                a = 3 * i + j
                c0, c1, c2 = C[0, j], C[1, j], C[2, j]
                if i == 0:
                    L[0], L[1], L[2] = 0.0, -c2, c1
                elif i == 1:
                    L[0], L[1], L[2] = c2, 0.0, -c0
                else:
                    L[0], L[1], L[2] = -c1, c0, 0.0
                ln = np.sqrt(L[0] * L[0] + L[1] * L[1] + L[2] * L[2])
                ok = ln > 1e-5
                div = ln if ok else 1.0
                for c in range(3):
                    Ln[a, c] = L[c] / div
                rA = abs(Ln[a, 0]) * hA[p, 0] + abs(Ln[a, 1]) * hA[p, 1] + abs(Ln[a, 2]) * hA[p, 2]
                for jj in range(3):
                    aLB[jj] = abs(Ln[a, 0] * C[0, jj] + Ln[a, 1] * C[1, jj] + Ln[a, 2] * C[2, jj])
                rB = aLB[0] * hB[p, 0] + aLB[1] * hB[p, 1] + aLB[2] * hB[p, 2]
                s = abs(Ln[a, 0] * dA[0] + Ln[a, 1] * dA[1] + Ln[a, 2] * dA[2]) - rA - rB
                dup = (max(abs(Ln[a, 0]), abs(Ln[a, 1]), abs(Ln[a, 2])) > 1 - 1e-9
                       or max(aLB[0], aLB[1], aLB[2]) > 1 - 1e-9)
                if not ok or dup:
                    s = -np.inf
                if a == 0 or s > se:  # the first of equal maxima (np.argmax)
                    se = s
                    best_e = a
        fa = _argmax3(sepA[0], sepA[1], sepA[2])
        fb = _argmax3(sepB[0], sepB[1], sepB[2])
        sa, sb = sepA[fa], sepB[fb]
        tol_abs = 1e-5 * (max(hA[p, 0], hA[p, 1], hA[p, 2]) + max(hB[p, 0], hB[p, 1], hB[p, 2]))
        best_face = max(sa, sb)
        is_edge = se > best_face + 0.05 * abs(best_face) + tol_abs
        fl = sb > sa + 0.05 * abs(sa) + tol_abs
        edge[p] = is_edge
        se_out[p] = se
        for sl in range(5):
            S_ok[p, sl] = False
        if is_edge and se < margin[p]:
            i, j = best_e // 3, best_e % 3
            for r in range(3):
                L[r] = RA[p, r, 0] * Ln[best_e, 0] + RA[p, r, 1] * Ln[best_e, 1] + RA[p, r, 2] * Ln[best_e, 2]
            if L[0] * d[0] + L[1] * d[1] + L[2] * d[2] < 0:
                for r in range(3):
                    L[r] = -L[r]
            for c in range(3):
                sgn = np.sign(RA[p, 0, c] * L[0] + RA[p, 1, c] * L[1] + RA[p, 2, c] * L[2])
                w3[c] = (0.0 if c == i else sgn) * hA[p, c]
            for r in range(3):
                pa[r] = cA[p, r] + (RA[p, r, 0] * w3[0] + RA[p, r, 1] * w3[1] + RA[p, r, 2] * w3[2])
            for c in range(3):
                sgn = -np.sign(RB[p, 0, c] * L[0] + RB[p, 1, c] * L[1] + RB[p, 2, c] * L[2])
                w3[c] = (0.0 if c == j else sgn) * hB[p, c]
            for r in range(3):
                pb[r] = cB[p, r] + (RB[p, r, 0] * w3[0] + RB[p, r, 1] * w3[1] + RB[p, r, 2] * w3[2])
            for r in range(3):
                a0[r] = pa[r] - RA[p, r, i] * hA[p, i]
                a1[r] = pa[r] + RA[p, r, i] * hA[p, i]
                b0[r] = pb[r] - RB[p, r, j] * hB[p, j]
                b1[r] = pb[r] + RB[p, r, j] * hB[p, j]
            segment_segment(a0, a1, b0, b1, qa, qb)
            for r in range(3):
                S_n[p, 0, r] = L[r]
                S_p[p, 0, r] = 0.5 * (qa[r] + qb[r])
            S_g[p, 0] = se
            S_f[p, 0] = 64 + best_e
            S_ok[p, 0] = True
        # the face manifold (every pair, edge pairs included: see box_box)
        if fl:
            rc, rR, rh, ic, iR, ih = cB[p], RB[p], hB[p], cA[p], RA[p], hA[p]
            face = fb
            sg = 1.0 if dB[fb] <= 0 else -1.0
        else:
            rc, rR, rh, ic, iR, ih = cA[p], RA[p], hA[p], cB[p], RB[p], hB[p]
            face = fa
            sg = 1.0 if dA[fa] >= 0 else -1.0
        for r in range(3):
            nrm[r] = rR[r, face] * sg
        # incident face: the other box's face most anti-parallel to nrm
        fi = 0
        best = -1.0
        dfi = 0.0
        for l in range(3):
            dl = iR[0, l] * nrm[0] + iR[1, l] * nrm[1] + iR[2, l] * nrm[2]
            if abs(dl) > best:
                best = abs(dl)
                fi = l
                dfi = dl
        sgn = -1.0 if dfi > 0 else 1.0
        u_i = 1 if fi == 0 else 0
        v_i = 1 if fi == 2 else 2
        for r in range(3):
            fc = ic[r] + iR[r, fi] * (sgn * ih[fi])
            U = iR[r, u_i] * ih[u_i]
            V = iR[r, v_i] * ih[v_i]
            P[0, r] = fc + U + V
            P[1, r] = fc - U + V
            P[2, r] = fc - U - V
            P[3, r] = fc + U - V
        cnt = np.int64(4)  # (typed: a literal 4 would compile _clip twice)
        a_lo = 1 if face == 0 else 0
        a_hi = 1 if face == 2 else 2
        for a in (a_lo, a_hi):
            ax0, ax1, ax2 = rR[0, a], rR[1, a], rR[2, a]
            off = ax0 * rc[0] + ax1 * rc[1] + ax2 * rc[2]
            ha = rh[a]
            cnt = _clip(P, cnt, ax0, ax1, ax2, off + ha, Q)
            cnt = _clip(Q, cnt, -ax0, -ax1, -ax2, -off + ha, P)
        nv = 0
        for v in range(cnt):
            g = 0.0
            for r in range(3):
                g += (P[v, r] - (rc[r] + nrm[r] * rh[face])) * nrm[r]
            gap[v] = g
            valid[v] = 1 if g < margin[p] else 0
            if valid[v]:
                nv += 1
        ns = 0
        if nv <= 4:
            for v in range(cnt):
                if valid[v]:
                    cand[ns] = v
                    ns += 1
        else:
            # the deepest, the one farthest from it, and the two on either
            # side of that line farthest from it (unique, in that order)
            i0 = -1
            for v in range(cnt):
                if valid[v] and (i0 < 0 or gap[v] < gap[i0]):
                    i0 = v
            i1 = -1
            bd = -np.inf
            for v in range(cnt):
                for r in range(3):
                    E[v, r] = P[v, r] - P[i0, r]
                if valid[v]:
                    dd = E[v, 0] * E[v, 0] + E[v, 1] * E[v, 1] + E[v, 2] * E[v, 2]
                    if dd > bd or i1 < 0:
                        bd = dd
                        i1 = v
            i2 = -1
            i3 = -1
            for v in range(cnt):
                cross3(E[i1], E[v], cr)
                area[v] = cr[0] * nrm[0] + cr[1] * nrm[1] + cr[2] * nrm[2]
                if valid[v]:
                    if i2 < 0 or area[v] > area[i2]:
                        i2 = v
                    if i3 < 0 or area[v] < area[i3]:
                        i3 = v
            for c in (i0, i1, i2, i3):
                dupc = False
                for t in range(ns):
                    if cand[t] == c:
                        dupc = True
                if not dupc:
                    cand[ns] = c
                    ns += 1
        for t in range(ns):
            v = cand[t]
            sl = 1 + t
            S_ok[p, sl] = True
            S_g[p, sl] = gap[v]
            for r in range(3):
                S_p[p, sl, r] = P[v, r] - nrm[r] * (0.5 * gap[v])
                S_n[p, sl, r] = -nrm[r] if fl else nrm[r]
            S_f[p, sl] = (16 if fl else 0) + 4 * face + t


#: whether box pairs whose least overlap is an edge axis keep their face
#: manifold's points (see :func:`box_box`; switched off only by the test
#: that shows what they stop, test_time_of_impact_safeguards)
EDGE_FACE_POINTS = True


@njit(cache=True)
def edge_pair_face_points(S_g, S_ok, edge, se, margin, keep):
    """The face-manifold points (slots 1-4 of ``S_g``, ``S_ok`` (k, 5)) of
    the edge pairs (``edge`` (k,) bool), in place: kept, their gaps clamped
    at the pair's edge-axis separation ``se`` (k,) m (see :func:`box_box`)
    -- and dropped where that puts them beyond the pair's ``margin`` (k,)
    m; all dropped when not ``keep``."""
    for t in range(S_g.shape[0]):
        if not edge[t]:
            continue
        for s in range(1, 5):
            g = S_g[t, s]
            if np.isnan(g) or np.isnan(se[t]):
                g = np.nan
            elif se[t] > g:
                g = se[t]
            S_g[t, s] = g
            S_ok[t, s] = keep and S_ok[t, s] and g < margin[t]


def box_box(cA, RA, hA, cB, RB, hB, margin):
    """Separating axes + clipping; normal from A to B.  ``margin`` (k,).

    One compiled loop over the pairs (:func:`_box_box_kernel`).  The face
    manifold of every pair is computed, edge pairs included.  An edge-edge
    point alone is blind to the faces about to come down and to the
    corners already inside: an edge pair keeps the face points' gaps
    clamped at the edge axis' separation (the edge axis is the pair's least
    overlap, and no point of a body lies deeper in the other than that,
    while its overlap along a face normal may be more;
    :func:`edge_pair_face_points`, pinned by
    test_box_edge_landing_keeps_the_face_points)."""
    k = cA.shape[0]
    if k == 0:
        return empty()
    S_n = np.zeros((k, 5, 3))
    S_p = np.zeros((k, 5, 3))
    S_g = np.zeros((k, 5))
    S_f = np.zeros((k, 5), np.int64)
    S_ok = np.zeros((k, 5), bool)
    edge = np.zeros(k, bool)
    se = np.zeros(k)
    f = np.ascontiguousarray
    mg = f(margin, float)
    _box_box_kernel(Boxes(c=f(cA, float), R=f(RA, float), h=f(hA, float)),
                    Boxes(c=f(cB, float), R=f(RB, float), h=f(hB, float)), mg,
                    Slots(n=S_n, p=S_p, g=S_g, f=S_f, ok=S_ok), edge, se, np.empty(BOX_FW), np.empty(BOX_IW, np.int64))
    edge_pair_face_points(S_g, S_ok, edge, se, mg, EDGE_FACE_POINTS)
    if not S_ok.any():
        return empty()
    kk = np.repeat(np.arange(k), 5).reshape(k, 5)
    m = S_ok
    return kk[m], S_n[m], S_p[m], S_g[m], S_f[m]
