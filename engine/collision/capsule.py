"""Capsule pairs: capsule-plane (both end caps), sphere-capsule,
capsule-capsule (closest points of the segments, plus the ends of their
overlap so a capsule lying along another rests on two points), capsule-box
(minimum of the box's signed distance along the segment by golden-section
search -- the signed distance of a convex set is convex -- plus the end
caps).  Each is one compiled loop over the pairs; contacts come slot by
slot (every pair's first contact, then every pair's second, ...)."""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.collision.kernels import (SDF_BOX, gather, segment_and_caps1, segment_closest1, segment_segment, slots,
                                      sphere_plane1, sphere_sphere1)

#: capsule-capsule: the clipped overlap's ends are contacts of their own
#: when they lie more than this times the smaller radius apart along the
#: axis, from each other and from the closest points (nearer, they are
#: the closest-point contact again: a duplicate row)
CLIP_APART = 0.1

#: length of the capsule kernels' float scratch ``fw`` (their 3-vectors as
#: slices of the collider's kept work: nothing allocated a call,
#: tests/test_engine_steady_gyro.py::test_every_gyroscopic_setting_steps_without_allocating)
CAPSULE_FW = 18


@njit(cache=True)
def capsule_ends1(c, R, hl, e0, e1):
    """The segment's ends e0 = c - hl z, e1 = c + hl z (z = R's column 2)."""
    for i in range(3):
        e0[i] = c[i] - R[i, 2] * hl
        e1[i] = c[i] + R[i, 2] * hl


@njit(cache=True)
def _capsule_plane_kernel(c, R, hl, r, pn, po, S_n, S_p, S_g, S_f, S_ok, fw):
    e0 = fw[0:3]
    e1 = fw[3:6]
    for k in range(c.shape[0]):
        capsule_ends1(c[k], R[k], hl[k], e0, e1)
        S_g[k, 0] = sphere_plane1(e0, r[k], pn[k], po[k], S_n[k, 0], S_p[k, 0])
        S_g[k, 1] = sphere_plane1(e1, r[k], pn[k], po[k], S_n[k, 1], S_p[k, 1])
        S_f[k, 1] = 1
        S_ok[k, 0] = S_ok[k, 1] = True


@njit(cache=True)
def _sphere_capsule_kernel(cs, rs, c, R, hl, r, n, p, g, fw):
    e0 = fw[0:3]
    e1 = fw[3:6]
    q = fw[6:9]
    for k in range(c.shape[0]):
        capsule_ends1(c[k], R[k], hl[k], e0, e1)
        segment_closest1(cs[k], e0, e1, q)
        g[k] = sphere_sphere1(cs[k], rs[k], q, r[k], n[k], p[k])


@njit(cache=True)
def _capsule_capsule_kernel(ca, Ra, hla, ra, cb, Rb, hlb, rb, S_n, S_p, S_g, S_f, S_ok, fw):
    """Slot 0: the segments' closest points.  Slots 1, 2: the ends of
    the overlap of the two segments along a's axis (a's segment clipped
    to the span of b's ends projected onto it), each against its closest
    point of b's segment, where the overlap is longer than
    :data:`CLIP_APART` times the smaller radius and the end lies that far
    along the axis from slot 0's point (nearer, it is slot 0's contact
    again).  No angle decides: the driver keeps a slot only when its gap
    is below the pair's margin (the contact margin plus both bodies'
    motion in the step), so a capsule lying along another rests on two
    points where both ends of the overlap touch, and a far end closing
    within the step (a capsule slapping down on another at a shallow
    angle) has a speculative row there before it arrives; crossing
    capsules' clipped ends lie far beyond the margin
    (tests/test_engine_collision.py::test_capsule_capsule_clipped_manifold,
    tests/test_engine_collision.py::test_capsule_landing_on_another_at_8_degrees_stays_out)."""
    V = fw[:18].reshape((6, 3))
    a0, a1, b0, b1, pa, pb = V[0], V[1], V[2], V[3], V[4], V[5]
    for k in range(ca.shape[0]):
        capsule_ends1(ca[k], Ra[k], hla[k], a0, a1)
        capsule_ends1(cb[k], Rb[k], hlb[k], b0, b1)
        segment_segment(a0, a1, b0, b1, pa, pb)
        S_g[k, 0] = sphere_sphere1(pa, ra[k], pb, rb[k], S_n[k, 0], S_p[k, 0])
        S_ok[k, 0] = True
        # axial coordinates along a's axis (from a's centre) of slot 0's
        # point and of b's ends
        z0, z1, z2 = Ra[k, 0, 2], Ra[k, 1, 2], Ra[k, 2, 2]
        sp = (pa[0] - ca[k, 0]) * z0 + (pa[1] - ca[k, 1]) * z1 + (pa[2] - ca[k, 2]) * z2
        s0 = (b0[0] - ca[k, 0]) * z0 + (b0[1] - ca[k, 1]) * z1 + (b0[2] - ca[k, 2]) * z2
        s1 = (b1[0] - ca[k, 0]) * z0 + (b1[1] - ca[k, 1]) * z1 + (b1[2] - ca[k, 2]) * z2
        lo = max(-hla[k], min(s0, s1))
        hi = min(hla[k], max(s0, s1))
        apart = CLIP_APART * min(ra[k], rb[k])
        if not hi - lo > apart:
            continue
        for j in range(1, 3):
            s = lo if j == 1 else hi
            if not abs(s - sp) > apart:
                continue
            for i in range(3):
                pa[i] = ca[k, i] + Ra[k, i, 2] * s
            segment_closest1(pa, b0, b1, pb)
            S_g[k, j] = sphere_sphere1(pa, ra[k], pb, rb[k], S_n[k, j], S_p[k, j])
            S_f[k, j] = j
            S_ok[k, j] = True


@njit(cache=True)
def _capsule_box_kernel(c, R, hl, r, cb, Rb, hb, S_n, S_p, S_g, S_f, S_ok, fw):
    e0 = fw[0:3]
    e1 = fw[3:6]
    x = fw[6:9]
    for k in range(c.shape[0]):
        capsule_ends1(c[k], R[k], hl[k], e0, e1)
        segment_and_caps1(SDF_BOX, e0, e1, hl[k], r[k], cb[k], Rb[k], hb[k], x, S_n[k], S_p[k], S_g[k], S_f[k],
                          S_ok[k])


def _f(a):
    return np.ascontiguousarray(a, dtype=float)


def _slotted(kernel, S, *args):
    out = slots(args[0].shape[0], S)
    if args[0].shape[0]:
        kernel(*(_f(a) for a in args), *out, np.empty(CAPSULE_FW))
    return gather(*out)


def capsule_plane(c, R, hl, r, pn, po):
    """Capsules (centres, rotations with the axis as body z, half lengths
    hl, radii r) against planes: both end caps (fid 0, 1); normal -pn."""
    return _slotted(_capsule_plane_kernel, 2, c, R, hl, r, pn, po)


def sphere_capsule(cs, rs, c, R, hl, r):
    """Spheres against capsules: the segment's closest point as a sphere."""
    m = c.shape[0]
    n, p, g = np.empty((m, 3)), np.empty((m, 3)), np.empty(m)
    if m:
        _sphere_capsule_kernel(_f(cs), _f(rs), _f(c), _f(R), _f(hl), _f(r), n, p, g, np.empty(CAPSULE_FW))
    return np.arange(m), n, p, g, np.zeros(m, np.int64)


def capsule_capsule(ca, Ra, hla, ra, cb, Rb, hlb, rb):
    """Capsule against capsule: the segments' closest points (fid 0) and
    the ends of their overlap along a's axis (fid 1, 2;
    :func:`_capsule_capsule_kernel`); the caller keeps those within its
    margin (slots 3, 4 are never set)."""
    return _slotted(_capsule_capsule_kernel, 5, ca, Ra, hla, ra, cb, Rb, hlb, rb)


def capsule_box(c, R, hl, r, cb, Rb, hb):
    """Capsule (first) against box (second): the segment's point of least
    box signed distance (fid 0) and the end caps away from it (fid 1, 2)."""
    return _slotted(_capsule_box_kernel, 3, c, R, hl, r, cb, Rb, hb)
