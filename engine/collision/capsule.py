"""Capsule pairs: capsule-plane (both end caps), sphere-capsule,
capsule-capsule (closest points of the segments, plus the end projections
when nearly parallel so a lying capsule rests on two points), capsule-box
(minimum of the box's signed distance along the segment by golden-section
search -- the signed distance of a convex set is convex -- plus the end
caps)."""

from __future__ import annotations

import numpy as np

from engine.collision.common import _cat, _norm, _segment_closest, _segment_min, _segment_segment
from engine.collision.sphere import sphere_box, sphere_plane, sphere_sphere


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
    d = e1 - e0
    s = _segment_min(lambda p: _box_sdf(p, cb, Rb, hb), e0, e1)[0]
    out = [sphere_box(e0 + d * s[:, None], r, cb, Rb, hb)]
    for end, fid, sv in ((e0, 1, 0.0), (e1, 2, 1.0)):
        keep = np.flatnonzero(np.abs(s - sv) * 2.0 * hl > 0.02 * (2.0 * hl + r))
        if keep.size:
            k, n, p, gg, _ = sphere_box(end[keep], r[keep], cb[keep], Rb[keep], hb[keep])
            out.append((keep[k], n, p, gg, np.full(k.size, fid)))
    return _cat(out)
