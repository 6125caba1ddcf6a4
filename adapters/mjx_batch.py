"""MJX's batch of worlds: the worlds' models as one vmapped model
(:func:`batched_models`, used by adapters.mjx's ``build_batch``)."""

from __future__ import annotations

import numpy as np

from physbench.adapters.base import NotOneBatch


def batched_models(mxs: list):
    """The worlds' MJX models as one: (model, in_axes) where an array leaf
    equal in every world is world 0's (axis None) and one that differs is
    stacked (axis 0).  The static part (MJX keeps ``stat``, the model
    statistics of the reference pose, out of the arrays) is world 0's.
    Raises NotOneBatch when the worlds' arrays do not match in number or
    shape."""
    import jax

    tu = jax.tree_util
    leaves0, tree = tu.tree_flatten(mxs[0])
    per = [leaves0]
    for mx in mxs[1:]:
        leaves, _ = tu.tree_flatten(mx)
        bad = [i for i, (a, b) in enumerate(zip(leaves, leaves0)) if np.shape(a) != np.shape(b)]
        if len(leaves) != len(leaves0) or bad:
            raise NotOneBatch(f"the worlds' MuJoCo models differ in structure ({len(leaves)} vs {len(leaves0)} "
                              f"arrays; shapes differ at {bad[:3]}: e.g. an explicit contact pair for an impact "
                              f"predicted from one start and not from another)")
        per.append(leaves)
    out, axes = [], []
    for i, leaf in enumerate(leaves0):
        if all(p[i] is leaf or np.array_equal(np.asarray(p[i]), np.asarray(leaf)) for p in per[1:]):
            out.append(leaf)
            axes.append(None)
        else:
            out.append(jax.numpy.stack([p[i] for p in per]))
            axes.append(0)
    return tu.tree_unflatten(tree, out), tu.tree_unflatten(tree, axes)
