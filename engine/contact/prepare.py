"""Compiled contact row preparation (the prepare phase): the contacts'
normal velocities and classification, the normal rows' Jacobians and
effective masses, the friction patches' frames, Jacobians and effective
masses, and the patches' relative velocities.

Loops over rows (and patches) in row order; no BLAS, a fixed summation
order (the bits do not depend on the BLAS kernel:
tests/test_engine_blas_free.py).  Conventions as in
:mod:`engine.contact.gauss_seidel`: bodies 0..n-1, the world n (its inverse mass
and inverse inertia zero, its position the origin); a contact joins body
``a`` to ``b`` with its normal from a toward b.

Normal row i (contact ``sel[i]``, lever arms rA = p - xa, rB = p - xb):
``J[i]`` = [-n, -(rA x n) | n, rB x n], ``M[i]`` = [-n/ma, -IA^-1 (rA x n)
| n/mb, IB^-1 (rB x n)] (M^-1 J^T), ``mn[i]`` = 1 / (J[i] . M[i]).

Friction patch p (all rows of one pair, ``pid`` (m,) the patch of each
row): centroid P (mean of its points), normal N (normalised sum of its
normals), tangents t1 = N x e / |N x e| for the world axis e least aligned
with N (first on ties), t2 = N x t1; rows (tangent t1, tangent t2, twist
about N [, rolling about t1, t2]) at the centroid, ``Jt``/``Mt`` (np, nr,
12) as the normal rows, ``mt`` = 1 / (Jt . Mt) where positive, else 0;
``r_twist`` the mean distance of its points from P within the patch plane.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from physbench.engine.contact.gauss_seidel import row_velocity


@njit(cache=True)
def pair_code(a, b, sidx, n, n_statics):
    """Warm-cache key of the pair (a, b, static index): unique per pair
    (= solver._pair_codes_abs)."""
    return (a * (n + 1) + b) * (n_statics + 1) + (sidx + 1)


@njit(cache=True)
def _point_vn(V, W, a, b, p, n, xa, xb):
    """n . (vb + wb x rB - va - wa x rA) with rA = p - xa, rB = p - xb (p,
    n, xa, xb tuples of three scalars); velocity fields (k, 3) with k = nb
    (body b = nb, the world, at rest) or nb + 1 (its row zero)."""
    px, py, pz = p
    nx, ny, nz = n
    xa0, xa1, xa2 = xa
    xb0, xb1, xb2 = xb
    ax = px - xa0
    ay = py - xa1
    az = pz - xa2
    bx = px - xb0
    by = py - xb1
    bz = pz - xb2
    rx = 0.0
    ry = 0.0
    rz = 0.0
    if b < V.shape[0]:
        rx = V[b, 0] + (W[b, 1] * bz - W[b, 2] * by)
        ry = V[b, 1] + (W[b, 2] * bx - W[b, 0] * bz)
        rz = V[b, 2] + (W[b, 0] * by - W[b, 1] * bx)
    rx = rx - V[a, 0] - (W[a, 1] * az - W[a, 2] * ay)
    ry = ry - V[a, 1] - (W[a, 2] * ax - W[a, 0] * az)
    rz = rz - V[a, 2] - (W[a, 0] * ay - W[a, 1] * ax)
    return rx * nx + ry * ny + rz * nz


@njit(cache=True)
def classify(kc, kx, kk, ko, n_statics, h, thr, lever, slop, warm):
    """Normal velocities and classification of the contacts (m of them).

    The arrays come as :class:`engine.pack.Pack` s of the named tuples of
    engine.contact.packs: ``kc`` the :class:`Pose` (positions ``X`` (nb, 3)
    at the start pose, velocity fields as :func:`_point_vn`: ``V``/``W``
    the free flight's end, ``V0``/``W0`` the start of the step), ``kx`` the
    :class:`Classified` (``UL``/``UA`` the free flight's mean motion, and
    the outputs), ``kk`` the :class:`ContactArrays`, ``ko`` the last
    solve's :class:`Cache`.  Writes ``vn`` (3, m): rows vn_free, vn0, un
    (m/s); ``touching`` (m,) gap <= 1e-6 m; ``impact`` (m,) rows this
    step's motion closes at an approach above ``thr`` m/s (see
    solver.Solve); ``codes`` (m,) pair codes.  With ``warm`` (the last
    solve's cache: sorted pair codes ``code`` (k,), points in body a's
    frame ``loc`` (k, 3), normal forces ``fn`` (k,), ``touch`` (k,) bool),
    a touching row approaching faster than ``thr`` that a speculative row
    would sink beyond ``slop`` is an impact too, and in a pair that
    pressed last step (a cached point with a positive force) a closing row
    stays an impact only when it is not near a point that pressed at rest
    (within 0.1 bound radius + 0.1 mm in body a's frame, ``R0`` (nb, 3, 3)
    the start rotations), it approached faster than ``thr`` at the start,
    and it would sink beyond ``slop``.  Returns the number of impact rows."""
    pose, cl, c, o = kc.items, kx.items, kk.items, ko.items
    X, V1, W1, V0, W0, R0, bound_radius = pose.X, pose.V, pose.W, pose.V0, pose.W0, pose.R0, pose.bound_radius
    UL, UA, vn, touching, impact, codes = cl.UL, cl.UA, cl.vn, cl.touching, cl.impact, cl.codes
    a, b, sidx, point, normal, gap = c.a, c.b, c.sidx, c.point, c.normal, c.gap
    o_code, o_loc, o_fn, o_touch = o.code, o.loc, o.fn, o.touch
    nb = X.shape[0]
    m = a.shape[0]
    k = o_code.shape[0]
    count = 0
    for i in range(m):
        ia = a[i]
        ib = b[i]
        xa0, xa1, xa2 = X[ia, 0], X[ia, 1], X[ia, 2]
        xb0 = xb1 = xb2 = 0.0  # the world's origin
        if ib < nb:
            xb0, xb1, xb2 = X[ib, 0], X[ib, 1], X[ib, 2]
        px, py, pz = point[i, 0], point[i, 1], point[i, 2]
        nx, ny, nz = normal[i, 0], normal[i, 1], normal[i, 2]
        p3, n3, xa, xb = (px, py, pz), (nx, ny, nz), (xa0, xa1, xa2), (xb0, xb1, xb2)
        v1 = _point_vn(V1, W1, ia, ib, p3, n3, xa, xb)
        v0 = _point_vn(V0, W0, ia, ib, p3, n3, xa, xb)
        un = _point_vn(UL, UA, ia, ib, p3, n3, xa, xb)
        vn[0, i] = v1
        vn[1, i] = v0
        vn[2, i] = un
        g = gap[i]
        code = pair_code(ia, ib, sidx[i], nb, n_statics)
        codes[i] = code
        touch = g <= 1e-6
        touching[i] = touch
        sinks = lever * h * v1 - g - h * un > slop
        imp = (not touch) and (g + h * un < 0.0) and (-un > thr)
        if warm and touch and (-v0 > thr) and sinks:
            imp = True
        if imp and warm:
            lo = np.searchsorted(o_code, code)
            persistent = False
            j = lo
            while j < k and o_code[j] == code:
                if o_fn[j] > 0.0:
                    persistent = True
                    break
                j += 1
            if persistent:
                keep = sinks and (-v0 > thr)
                if keep:
                    # a point that pressed at rest last step is no impact
                    dx = px - xa0
                    dy = py - xa1
                    dz = pz - xa2
                    lx = R0[ia, 0, 0] * dx + R0[ia, 1, 0] * dy + R0[ia, 2, 0] * dz
                    ly = R0[ia, 0, 1] * dx + R0[ia, 1, 1] * dy + R0[ia, 2, 1] * dz
                    lz = R0[ia, 0, 2] * dx + R0[ia, 1, 2] * dy + R0[ia, 2, 2] * dz
                    tol = 0.1 * bound_radius[ia] + 1e-4
                    j = lo
                    while j < k and o_code[j] == code:
                        if o_touch[j] and o_fn[j] > 0.0:
                            ex = o_loc[j, 0] - lx
                            ey = o_loc[j, 1] - ly
                            ez = o_loc[j, 2] - lz
                            if ex * ex + ey * ey + ez * ez <= tol * tol:
                                keep = False
                                break
                        j += 1
                imp = keep
        impact[i] = imp
        if imp:
            count += 1
    return count


@njit(cache=True)
def _basis(nx, ny, nz):
    """Tangents (t1, t2) completing the unit normal (nx, ny, nz):
    t1 = n x e / |n x e| for the world axis e least aligned with n (the
    first on ties), t2 = n x t1."""
    ax, ay, az = abs(nx), abs(ny), abs(nz)
    if ax <= ay and ax <= az:
        ex, ey, ez = 1.0, 0.0, 0.0
    elif ay <= az:
        ex, ey, ez = 0.0, 1.0, 0.0
    else:
        ex, ey, ez = 0.0, 0.0, 1.0
    t1x = ny * ez - nz * ey
    t1y = nz * ex - nx * ez
    t1z = nx * ey - ny * ex
    s = math.sqrt(t1x * t1x + t1y * t1y + t1z * t1z)
    t1x /= s
    t1y /= s
    t1z /= s
    t2x = ny * t1z - nz * t1y
    t2y = nz * t1x - nx * t1z
    t2z = nx * t1y - ny * t1x
    return t1x, t1y, t1z, t2x, t2y, t2z


@njit(cache=True, inline="always")
def _row(J, M, i, lin, ang_a, ang_b, ima, imb, IA, IB):
    """Fill row i of J/M (k, 12) for the direction ``lin`` = (l0, l1, l2)
    (zero for an angular row) with angular parts ``ang_a`` = (a0, a1, a2)
    for a and ``ang_b`` = (b0, b1, b2) for b (J's a side is -lin, -ang_a);
    returns J[i] . M[i] (summed in column order).  Tuples of scalars, not
    arrays: nothing is allocated
    (tests/test_engine_steady.py::test_steady_step_allocates_nothing)."""
    l0, l1, l2 = lin
    a0, a1, a2 = ang_a
    b0, b1, b2 = ang_b
    J[i, 0] = -l0
    J[i, 1] = -l1
    J[i, 2] = -l2
    J[i, 3] = -a0
    J[i, 4] = -a1
    J[i, 5] = -a2
    J[i, 6] = l0
    J[i, 7] = l1
    J[i, 8] = l2
    J[i, 9] = b0
    J[i, 10] = b1
    J[i, 11] = b2
    M[i, 0] = -ima * l0
    M[i, 1] = -ima * l1
    M[i, 2] = -ima * l2
    M[i, 6] = imb * l0
    M[i, 7] = imb * l1
    M[i, 8] = imb * l2
    for r in range(3):
        sa = 0.0
        sa += IA[r, 0] * a0
        sa += IA[r, 1] * a1
        sa += IA[r, 2] * a2
        sb = 0.0
        sb += IB[r, 0] * b0
        sb += IB[r, 1] * b1
        sb += IB[r, 2] * b2
        M[i, 3 + r] = -sa
        M[i, 9 + r] = sb
    k = 0.0
    for c in range(12):
        k += J[i, c] * M[i, c]
    return k


@njit(cache=True)
def _arms(px, py, pz, X, ia, ib, nb):
    """Lever arms p - x_a and p - x_b of the point (px, py, pz) (the
    world's origin for b = nb)."""
    ax = px - X[ia, 0]
    ay = py - X[ia, 1]
    az = pz - X[ia, 2]
    if ib < nb:
        return ax, ay, az, px - X[ib, 0], py - X[ib, 1], pz - X[ib, 2]
    return ax, ay, az, px, py, pz


@njit(cache=True)
def normal_rows(X, Iinv, inv_mass, R0, want_loc, a, b, point, normal, sel, nb, J, M, mn, loc):
    """The normal rows of the contacts ``sel`` (m,) in that order (see the
    module doc): ``J``/``M`` (m, 12), ``mn`` (m,) and, with ``want_loc``,
    ``loc`` (m, 3) the contact points in body a's frame (``R0`` (nb, 3, 3)
    the start rotations; the warm cache's matching key)."""
    for i in range(sel.shape[0]):
        k = sel[i]
        ia = a[k]
        ib = b[k]
        ax, ay, az, bx, by, bz = _arms(point[k, 0], point[k, 1], point[k, 2], X, ia, ib, nb)
        nx, ny, nz = normal[k, 0], normal[k, 1], normal[k, 2]
        kn = _row(J, M, i, (nx, ny, nz), (ay * nz - az * ny, az * nx - ax * nz, ax * ny - ay * nx),
                  (by * nz - bz * ny, bz * nx - bx * nz, bx * ny - by * nx), inv_mass[ia], inv_mass[ib], Iinv[ia],
                  Iinv[ib])
        mn[i] = 1.0 / kn
        if not want_loc:
            continue
        for r in range(3):
            loc[i, r] = R0[ia, 0, r] * ax + R0[ia, 1, r] * ay + R0[ia, 2, r] * az


@njit(cache=True)
def patch_rows(bodies, c, sel, ps, nb, rolling, out):
    """The friction patches of the rows ``sel`` (m,) (engine.contact.packs:
    ``bodies`` a :class:`Bodies`, ``c`` the :class:`ContactArrays`, ``ps``
    the :class:`PatchSet`: patch of row i ``pid[i]``, patch bodies
    ``pa``/``pb`` (np,), rows per patch ``cnt`` (np,) float) into ``out``
    (a :class:`RowArrays`): centroids ``P`` and normals ``N`` (np, 3),
    ``rt`` (np,) m the twist radii, tangents ``t`` (np, 2, 3), ``Jt``/``Mt``
    (np, nr, 12) and ``mt`` (np, nr) with nr = 5 when ``rolling`` else 3
    (module doc)."""
    X, Iinv, inv_mass = bodies.X, bodies.Iinv, bodies.inv_mass
    point, normal = c.point, c.normal
    pid, pa, pb, cnt = ps.pid, ps.pa, ps.pb, ps.cnt
    P, N, r_twist, t, Jt, Mt, mt = out.P, out.N, out.rt, out.t, out.Jt, out.Mt, out.mt
    npch = pa.shape[0]
    m = sel.shape[0]
    P[:, :] = 0.0
    N[:, :] = 0.0
    r_twist[:] = 0.0
    for i in range(m):  # sums in row order
        k = sel[i]
        p = pid[i]
        for c in range(3):
            P[p, c] += point[k, c]
            N[p, c] += normal[k, c]
    for p in range(npch):
        for c in range(3):
            P[p, c] /= cnt[p]
        s = math.sqrt(N[p, 0] ** 2 + N[p, 1] ** 2 + N[p, 2] ** 2)
        if not s > 1e-9 * cnt[p]:
            # the pair's normals cancel (a capsule through a box: +n and -n
            # rows): the patch takes its first row's normal, a unit vector
            # (tests/test_fuzz.py::test_reference_engine_cancelling_patch_normals)
            i0 = 0
            while pid[i0] != p:
                i0 += 1
            s = 1.0
            for c in range(3):
                N[p, c] = normal[sel[i0], c]
        for c in range(3):
            N[p, c] /= s
    for i in range(m):
        k = sel[i]
        p = pid[i]
        ox = point[k, 0] - P[p, 0]
        oy = point[k, 1] - P[p, 1]
        oz = point[k, 2] - P[p, 2]
        d = ox * N[p, 0] + oy * N[p, 1] + oz * N[p, 2]
        ox -= d * N[p, 0]
        oy -= d * N[p, 1]
        oz -= d * N[p, 2]
        r_twist[p] += math.sqrt(ox * ox + oy * oy + oz * oz)
    for p in range(npch):
        r_twist[p] /= cnt[p]
        t1x, t1y, t1z, t2x, t2y, t2z = _basis(N[p, 0], N[p, 1], N[p, 2])
        t[p, 0, 0], t[p, 0, 1], t[p, 0, 2] = t1x, t1y, t1z
        t[p, 1, 0], t[p, 1, 1], t[p, 1, 2] = t2x, t2y, t2z
        ia = pa[p]
        ib = pb[p]
        ax, ay, az, bx, by, bz = _arms(P[p, 0], P[p, 1], P[p, 2], X, ia, ib, nb)
        ima = inv_mass[ia]
        imb = inv_mass[ib]
        IA = Iinv[ia]
        IB = Iinv[ib]
        Jp = Jt[p]  # (nr, 12) views: the rows are written in place
        Mp = Mt[p]
        for r in range(2):  # tangent rows: lever arms x t
            l0, l1, l2 = t[p, r, 0], t[p, r, 1], t[p, r, 2]
            kt = _row(Jp, Mp, r, (l0, l1, l2), (ay * l2 - az * l1, az * l0 - ax * l2, ax * l1 - ay * l0),
                      (by * l2 - bz * l1, bz * l0 - bx * l2, bx * l1 - by * l0), ima, imb, IA, IB)
            mt[p, r] = 1.0 / kt if kt > 0.0 else 0.0
        n0, n1, n2 = N[p, 0], N[p, 1], N[p, 2]
        kt = _row(Jp, Mp, 2, (0.0, 0.0, 0.0), (n0, n1, n2), (n0, n1, n2), ima, imb, IA, IB)  # twist about N
        mt[p, 2] = 1.0 / kt if kt > 0.0 else 0.0
        if rolling:
            for r in range(2):
                l0, l1, l2 = t[p, r, 0], t[p, r, 1], t[p, r, 2]
                kt = _row(Jp, Mp, 3 + r, (0.0, 0.0, 0.0), (l0, l1, l2), (l0, l1, l2), ima, imb, IA, IB)
                mt[p, 3 + r] = 1.0 / kt if kt > 0.0 else 0.0


@njit(cache=True)
def patch_velocity(Jt, U, pab, r0, r1, out):
    """Relative velocities of the patch rows r0..r1-1, ``out`` (np, r1-r0):
    rows 0, 1 the tangential velocity at the centroids (m/s), 3, 4 the
    rolling angular velocity (rad/s).  ``U`` (nb+1, 6)."""
    for p in range(Jt.shape[0]):
        ia = pab[p, 0]
        ib = pab[p, 1]
        for r in range(r0, r1):
            out[p, r - r0] = row_velocity(Jt, U, p, r, ia, ib)


@njit(cache=True)
def stop_candidate(pid, lam_n, Jt, U, pab, vt0, slip_tol, rolling, wr0, mur, roll_tol):
    """Whether a patch may have come to rest within the step: the test that
    opens solver.Rows.stop_times (a pressed patch, Fn > 0, that slid at the
    start, |vt0| > ``slip_tol``, with its end velocity along the start
    direction below ``slip_tol``; with ``rolling`` alike for the rolling
    velocities ``wr0`` (np, 2), ``mur`` (np,) > 0 and ``roll_tol``), as
    one compiled pass over the patches instead of its numpy.  A
    conservative gate: it lets through every patch the numpy test could
    pass (its end-velocity projection compared with a slack of 1e-9 of its
    terms' magnitude, whatever the summation order of numpy's einsum), and
    the numpy test then decides; False only when that test finds none.
    ``U`` (nb+1, 6) end velocities, ``vt0`` (np, 2) start tangential
    velocities, ``pid`` (m,) the rows' patches, ``lam_n`` (m,) impulses."""
    for p in range(vt0.shape[0]):
        ia = pab[p, 0]
        ib = pab[p, 1]
        s0 = math.sqrt(vt0[p, 0] * vt0[p, 0] + vt0[p, 1] * vt0[p, 1])
        if s0 > slip_tol * (1.0 - 1e-9):
            d0 = vt0[p, 0] / s0
            d1 = vt0[p, 1] / s0
            e0 = row_velocity(Jt, U, p, 0, ia, ib) * d0
            e1 = row_velocity(Jt, U, p, 1, ia, ib) * d1
            if e0 + e1 < slip_tol + 1e-9 * (abs(e0) + abs(e1)) and _pressed(pid, lam_n, p):
                return True
        if rolling and mur[p] > 0.0:
            r0 = math.sqrt(wr0[p, 0] * wr0[p, 0] + wr0[p, 1] * wr0[p, 1])
            if r0 > roll_tol * (1.0 - 1e-9):
                e0 = row_velocity(Jt, U, p, 3, ia, ib) * (wr0[p, 0] / r0)
                e1 = row_velocity(Jt, U, p, 4, ia, ib) * (wr0[p, 1] / r0)
                if e0 + e1 < roll_tol + 1e-9 * (abs(e0) + abs(e1)) and _pressed(pid, lam_n, p):
                    return True
    return False


@njit(cache=True)
def _pressed(pid, lam_n, p):
    """Whether patch p's rows' impulses sum (in row order, as np.bincount)
    to more than zero."""
    f = 0.0
    for i in range(pid.shape[0]):
        if pid[i] == p:
            f += lam_n[i]
    return f > 0.0


@njit(cache=True)
def sliding(Jt, U, pab, r_twist, slip_tol, vt, slip):
    """Patches that slide at velocities ``U`` (see solver.Rows.sliding):
    writes the centroids' relative tangential velocities ``vt`` (np, 2) and
    ``slip`` (np,) bool."""
    patch_velocity(Jt, U, pab, np.int64(0), np.int64(2), vt)
    for p in range(Jt.shape[0]):
        ia = pab[p, 0]
        ib = pab[p, 1]
        wn = row_velocity(Jt, U, p, 2, ia, ib)
        slip[p] = (math.sqrt(vt[p, 0] * vt[p, 0] + vt[p, 1] * vt[p, 1]) > slip_tol) or (
            abs(wn) * r_twist[p] > slip_tol)


@njit(cache=True)
def rows(bodies, want_loc, c, sel, nb, out, ps, friction, rolling):
    """The rows of a solve in one call (engine.contact.packs: ``bodies`` a
    :class:`Bodies`, ``c`` the :class:`ContactArrays`, ``out`` the
    :class:`RowArrays` written, ``ps`` the :class:`PatchSet`):
    :func:`normal_rows` of the contacts ``sel`` (m,), then (with
    ``friction``) :func:`patch_rows`; the impulses ``lam_n`` (m,) and
    ``lam_t`` (np, nr), the ``target`` (m,) and the ``slip`` (np,) flags
    cleared, ``mu`` (np,) set to the static coefficients ``mus`` (np,)
    (the same arithmetic as the separate calls: tests/test_determinism.py)."""
    normal_rows(bodies.X, bodies.Iinv, bodies.inv_mass, bodies.R0, want_loc, c.a, c.b, c.point, c.normal, sel, nb,
                out.J, out.M, out.mn, out.loc)
    out.lam_n[:] = 0.0
    out.target[:] = 0.0
    if friction:
        patch_rows(bodies, c, sel, ps, nb, rolling, out)
        out.lam_t[:] = 0.0
        out.slip[:] = False
        out.mu[:] = ps.mus


@njit(cache=True)
def targets(sel, touching, vn, gap, e, h, lever, thr, beta, slop, target, bias):
    """Normal rows' targets (the least allowed end normal velocity, m/s)
    for the contacts ``sel`` (m,) (see solver module doc): touching rows
    vn1 >= 0, separated ones min(vn_free - (max(gap, 0) + h un) / (lever
    h), 0), raised to -e vn0 for a touching row approaching faster than
    ``thr`` at the start of the step; and the position correction's
    push-out velocities ``bias`` = beta (depth - slop) / h where the depth
    -gap exceeds ``slop`` (m), else 0.  Returns the number of rows pushed
    out."""
    pushed = 0
    for i in range(sel.shape[0]):
        k = sel[i]
        g = gap[k]
        if touching[k]:
            s = 0.0
            if vn[1, k] < -thr:
                s = max(s, -e[k] * vn[1, k])
        else:
            s = min(vn[0, k] - (max(g, 0.0) + h * vn[2, k]) / (lever * h), 0.0)
        target[i] = s
        depth = -g
        bias[i] = 0.0
        if depth > slop:
            bias[i] = beta * (depth - slop) / h
            if bias[i] > 0.0:
                pushed += 1
    return pushed
