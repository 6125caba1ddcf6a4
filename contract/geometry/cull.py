"""Culling body pairs per frame with bounding spheres: all pairs vectorised
for small scenes, a cKDTree per frame with bodies bucketed by bounding
radius for large ones.  Exact (disjoint bounding spheres imply depth 0),
never subsampled."""

from __future__ import annotations

import numpy as np

def _radius_classes(rb: np.ndarray) -> list[tuple[np.ndarray, float]]:
    """Bodies bucketed by bounding radius (factor-4 bands), each with its
    largest radius: a tree query per band pair then uses a radius that fits."""
    if rb.size == 0:
        return []
    rmin = max(float(rb.min()), 1e-12)
    band = np.floor(np.log(np.maximum(rb, rmin) / rmin) / np.log(4.0)).astype(np.int64)
    out = []
    for k in np.unique(band):
        idx = np.nonzero(band == k)[0]
        out.append((idx, float(rb[idx].max())))
    return out


_ALL_PAIRS_MAX = 4096  # all-pairs culling up to this many pairs, KD-trees above


def _body_events(pos: np.ndarray, bad: np.ndarray, rb: np.ndarray, f0: int, f1: int,
                 classes, allpairs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, i, j) with i < j whose bounding spheres meet, frames [f0, f1)."""
    if allpairs is not None:
        I, J = allpairs
        lim = (rb[I] + rb[J]) ** 2
        fs, ps = [], []
        step = max(1, (1 << 20) // max(1, I.size))
        for a in range(f0, f1, step):
            b = min(f1, a + step)
            dv = pos[a:b, J] - pos[a:b, I]
            ff, pp = np.nonzero(np.einsum("fpi,fpi->fp", dv, dv) <= lim)
            fs.append(ff + a)
            ps.append(pp)
        f = np.concatenate(fs)
        p = np.concatenate(ps)
        return f, I[p], J[p]
    from scipy.spatial import cKDTree

    fs, Is, Js = [], [], []
    any_bad = bad[f0:f1].any(axis=1)
    for f in range(f0, f1):
        P = pos[f]
        trees = []
        for idx, rmax in classes:
            sel = idx[~bad[f, idx]] if any_bad[f - f0] else idx
            if sel.size:
                trees.append((sel, cKDTree(P[sel], leafsize=16, balanced_tree=False, compact_nodes=False), rmax))
        for ka, (sa, ta, ra) in enumerate(trees):
            pr = ta.query_pairs(2.0 * ra, output_type="ndarray")
            if pr.size:
                Is.append(sa[pr[:, 0]])
                Js.append(sa[pr[:, 1]])
                fs.append(np.full(pr.shape[0], f))
            for sb, tb, rbb in trees[ka + 1:]:
                sm = ta.sparse_distance_matrix(tb, ra + rbb, output_type="ndarray")
                if sm.size:
                    Is.append(sa[sm["i"]])
                    Js.append(sb[sm["j"]])
                    fs.append(np.full(sm.shape[0], f))
    if not fs:
        e = np.zeros(0, np.int64)
        return e, e, e
    f = np.concatenate(fs)
    i = np.concatenate(Is)
    j = np.concatenate(Js)
    i, j = np.minimum(i, j), np.maximum(i, j)
    dv = pos[f, j] - pos[f, i]
    keep = np.einsum("ei,ei->e", dv, dv) <= (rb[i] + rb[j]) ** 2  # exact bounding-sphere test
    return f[keep], i[keep], j[keep]

