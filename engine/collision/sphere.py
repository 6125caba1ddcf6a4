"""Sphere pairs: sphere-sphere, sphere-plane, sphere-box (exact closest
points; normal from the sphere toward the other shape)."""

from __future__ import annotations

import numpy as np

from engine.collision.common import _EPS, _norm


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
