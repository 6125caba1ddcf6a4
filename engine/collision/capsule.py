"""Capsule pairs: capsule-plane (both end caps), sphere-capsule,
capsule-capsule (closest points of the segments, plus the end projections
when nearly parallel so a lying capsule rests on two points), capsule-box
(minimum of the box's signed distance along the segment by golden-section
search -- the signed distance of a convex set is convex -- plus the end
caps).  Each is one compiled loop over the pairs; contacts come slot by
slot (every pair's first contact, then every pair's second, ...)."""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.collision.kernels import (SDF_BOX, gather, segment_and_caps1, segment_closest1, segment_segment, slots,
                                      sphere_plane1, sphere_sphere1)

#: capsule-capsule: |axis_a . axis_b| above which the end projections are
#: added (a lying capsule rests on two points)
PARALLEL_COS = 0.995

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
    V = fw[:18].reshape((6, 3))
    a0, a1, b0, b1, pa, pb = V[0], V[1], V[2], V[3], V[4], V[5]
    for k in range(ca.shape[0]):
        capsule_ends1(ca[k], Ra[k], hla[k], a0, a1)
        capsule_ends1(cb[k], Rb[k], hlb[k], b0, b1)
        segment_segment(a0, a1, b0, b1, pa, pb)
        S_g[k, 0] = sphere_sphere1(pa, ra[k], pb, rb[k], S_n[k, 0], S_p[k, 0])
        S_ok[k, 0] = True
        if abs(Ra[k, 0, 2] * Rb[k, 0, 2] + Ra[k, 1, 2] * Rb[k, 1, 2] + Ra[k, 2, 2] * Rb[k, 2, 2]) > PARALLEL_COS:
            segment_closest1(a0, b0, b1, pb)
            S_g[k, 1] = sphere_sphere1(a0, ra[k], pb, rb[k], S_n[k, 1], S_p[k, 1])
            segment_closest1(a1, b0, b1, pb)
            S_g[k, 2] = sphere_sphere1(a1, ra[k], pb, rb[k], S_n[k, 2], S_p[k, 2])
            segment_closest1(b0, a0, a1, pa)
            S_g[k, 3] = sphere_sphere1(pa, ra[k], b0, rb[k], S_n[k, 3], S_p[k, 3])
            segment_closest1(b1, a0, a1, pa)
            S_g[k, 4] = sphere_sphere1(pa, ra[k], b1, rb[k], S_n[k, 4], S_p[k, 4])
            for j in range(1, 5):
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
    """Capsule against capsule: the segments' closest points (fid 0), and
    where the axes are within PARALLEL_COS the four end projections (fid
    1-2: a's ends, 3-4: b's)."""
    return _slotted(_capsule_capsule_kernel, 5, ca, Ra, hla, ra, cb, Rb, hlb, rb)


def capsule_box(c, R, hl, r, cb, Rb, hb):
    """Capsule (first) against box (second): the segment's point of least
    box signed distance (fid 0) and the end caps away from it (fid 1, 2)."""
    return _slotted(_capsule_box_kernel, 3, c, R, hl, r, cb, Rb, hb)
