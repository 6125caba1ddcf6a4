"""The scene's geometry and pair lists as the compiled kernels read them:
named tuples (numba types them field by field: one argument, read by name
at no cost).  Shapes: n bodies, k static planes or boxes; units SI."""

from __future__ import annotations

from collections import namedtuple

import numpy as np

#: the bodies' shapes: codes ``shape`` (n,) int64 (engine.model's SPHERE,
#: BOX, CAPSULE, CYLINDER), ``radius`` (n,) m, box half extents ``half``
#: (n, 3) m, ``half_length`` (n,) m, ``bound_radius`` (n,) m
Shapes = namedtuple("Shapes", ("shape", "radius", "half", "half_length", "bound_radius"))

#: the static planes (unit normals ``planes_n`` (k, 3), offsets
#: ``planes_off`` (k,) m) and the static boxes' AABBs (``slo``, ``shi``
#: (k, 3) m)
Statics = namedtuple("Statics", ("planes_n", "planes_off", "slo", "shi"))

#: the model's geometry as the CCD stages' kernels read it
#: (engine.ccd_kept._geometry): the bodies' :class:`Shapes`, the
#: :class:`Statics` and the static shape codes ``static_shape``
#: (n_statics,) int64
Geometry = namedtuple("Geometry", ("shapes", "statics", "static_shape"))

#: candidate pairs: bodies ``pi`` < ``pj``; (body ``bp``, plane row ``pk``);
#: (body ``bs``, static-box row ``sk``), int64 each
Pairs = namedtuple("Pairs", ("pi", "pj", "bp", "pk", "bs", "sk"))


def shapes_of(model) -> Shapes:
    """``model``'s :class:`Shapes` as writable float64 (int64 codes) copies
    (the kernels are compiled for writable arrays, the model's are
    read-only)."""
    return Shapes(shape=np.array(model.shape, np.int64), radius=np.array(model.radius, float),
                  half=np.array(model.half_extents, float).reshape(-1, 3),
                  half_length=np.array(model.half_length, float), bound_radius=np.array(model.bound_radius, float))


def statics_of(model) -> Statics:
    """``model``'s :class:`Statics` as writable float64 copies."""
    return Statics(planes_n=np.array(model.plane_normal, float).reshape(-1, 3),
                   planes_off=np.array(model.plane_offset, float),
                   slo=np.array(model.sbox_aabb_lo, float).reshape(-1, 3),
                   shi=np.array(model.sbox_aabb_hi, float).reshape(-1, 3))


#: the CCD stage's end-pose check's buffers (engine.ccd_end.
#: end_pose_candidates, kept by engine.state.Context.end_pose_buffers):
#: the moved pairs written to the front of ``ci``, ``cj`` (bodies),
#: ``cbp``, ``cpk`` (body, plane row), ``cbs``, ``csk`` (body, static-box
#: row), int64 each; the end displacements ``sw`` (n,) m and the end
#: rotations ``R1`` (n, 3, 3)
EndPose = namedtuple("EndPose", ("ci", "cj", "cbp", "cpk", "cbs", "csk", "sw", "R1"))
