"""Sphere pairs: sphere-sphere, sphere-plane, sphere-box (exact closest
points; normal from the sphere toward the other shape).  Each is one
compiled loop over the pairs around the one-pair kernels of
:mod:`engine.collision.kernels`."""

from __future__ import annotations

import numpy as np
from numba import njit

from physbench.engine.collision.kernels import sphere_box1, sphere_plane1, sphere_sphere1


@njit(cache=True)
def _sphere_sphere_kernel(ca, ra, cb, rb, n, p, g):
    for k in range(ca.shape[0]):
        g[k] = sphere_sphere1(ca[k], ra[k], cb[k], rb[k], n[k], p[k])


@njit(cache=True)
def _sphere_plane_kernel(c, r, pn, po, n, p, g):
    for k in range(c.shape[0]):
        g[k] = sphere_plane1(c[k], r[k], pn[k], po[k], n[k], p[k])


@njit(cache=True)
def _sphere_box_kernel(c, r, cb, Rb, hb, n, p, g):
    for k in range(c.shape[0]):
        g[k] = sphere_box1(c[k], r[k], cb[k], Rb[k], hb[k], n[k], p[k])


def _f(a):
    return np.ascontiguousarray(a, dtype=float)


def _one_each(kernel, *args):
    """One contact per pair: (k, normal, point, gap, fid 0)."""
    m = args[0].shape[0]
    n, p, g = np.empty((m, 3)), np.empty((m, 3)), np.empty(m)
    if m:
        kernel(*(_f(a) for a in args), n, p, g)
    return np.arange(m), n, p, g, np.zeros(m, np.int64)


def sphere_sphere(ca, ra, cb, rb):
    """Spheres (centres (k, 3), radii (k,)) against spheres: normal from a
    to b (+z for coincident centres)."""
    return _one_each(_sphere_sphere_kernel, ca, ra, cb, rb)


def sphere_plane(c, r, pn, po):
    """Spheres against planes (unit normals pn (k, 3), offsets po (k,))."""
    return _one_each(_sphere_plane_kernel, c, r, pn, po)


def sphere_box(c, r, cb, Rb, hb):
    """Sphere (first) against box (second); normal from sphere to box."""
    return _one_each(_sphere_box_kernel, c, r, cb, Rb, hb)
