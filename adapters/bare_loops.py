"""The bare loops of ``physbench bench overhead``: per engine, its public
step call and its cheapest public read of every body's position,
orientation, linear and angular velocity after every step, kept in the
engine's own form and converted to nothing -- what any caller recording a
trajectory pays at least (``Adapter.bare_record``; the runner's ``ratio`` is
measured against it).  One place, so that the baseline means the same for
every engine:

- MuJoCo: ``mj_step(m, d)``; ``d.qpos`` and ``d.qvel`` copied into rows of
  a preallocated block;
- pymunk: ``space.step(dt)``; ``pymunk.batch.get_space_bodies`` appending
  (x, y, angle, vx, vy, w) rows to one buffer (pymunk grows it);
- pybullet: ``stepSimulation``; ``getBasePositionAndOrientation`` and
  ``getBaseVelocity`` per body (its only reads), the tuples kept in lists;
- Rapier: ``world.step()``; one ``RigidBodySet.to_bytes()`` kept in a list
  (:mod:`adapters.rapier_batch`; the four getters per body when that
  reader is off);
- Box2D: ``World.step(dt, substeps)``; three batched f32 reads (transforms,
  linear and angular velocities) into rows of a preallocated block.

Scenes whose adapter applies explicit forces before every step take the
adapter's own step(1) and read_state() (the base class default).  Each
function is bound as a method of its adapter and may read its private
attributes (tests/test_bench.py::test_bare_record_steps_the_same_simulation
pins that each advances the simulation exactly as ``step(n)``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from physbench.adapters.base import Adapter


def mujoco_bare_loop(a: Any, n: int) -> None:
    """The engine's public step call in a Python loop: mj_step(m, d) n
    times (the adapter's step() hands n to mj_step, which loops in C)."""
    if a._drag:
        return a.step(n)
    import mujoco

    m, d, f = a.m, a.d, mujoco.mj_step
    for _ in range(n):
        f(m, d)
    a.steps += n


def mujoco(a: Any, n: int, n_bodies: int) -> None:
    if a._drag:
        return Adapter.bare_record(a, n, n_bodies)
    import mujoco as mj

    m, d, f = a.m, a.d, mj.mj_step
    qpos, qvel = np.empty((n, m.nq)), np.empty((n, m.nv))
    for i in range(n):
        f(m, d)
        qpos[i] = d.qpos
        qvel[i] = d.qvel
    a.steps += n


def pymunk(a: Any, n: int, n_bodies: int) -> None:
    if a._drag or a._substeps != 1:
        return Adapter.bare_record(a, n, n_bodies)
    st, h, space = a._space.step, a._h, a._space
    get, fields, buf = a._pm.batch.get_space_bodies, a._public.fields, a._pm.batch.Buffer()
    for _ in range(n):
        st(h)
        get(space, fields, buf)
    a._space_steps += n


def pybullet(a: Any, n: int, n_bodies: int) -> None:
    if a._forces:
        return Adapter.bare_record(a, n, n_bodies)
    p, cid, ids = a._p, a._cid, a._ids
    st, gpo, gv = p.stepSimulation, p.getBasePositionAndOrientation, p.getBaseVelocity
    po: list = []
    ve: list = []
    apo, ave = po.append, ve.append
    for _ in range(n):
        st(cid)
        for bid in ids:
            apo(gpo(bid, cid))
            ave(gv(bid, cid))
    a._steps += n


def rapier(a: Any, n: int, n_bodies: int) -> None:
    if a._forces is not None:
        return Adapter.bare_record(a, n, n_bodies)
    step = a._world.step
    kept: list = []
    add = kept.append
    if a._reader is not None:
        blob = a._reader.blob
        for _ in range(n):
            step()
            add(blob())
    else:
        for _ in range(n):
            step()
            for rb in a._bodies:
                add((rb.translation.to_tuple(), rb.rotation.to_tuple(), rb.linvel.to_tuple(), rb.angvel.to_tuple()))
    a.steps += n


def box2d(a: Any, n: int, n_bodies: int) -> None:
    if a._forces is not None:
        return Adapter.bare_record(a, n, n_bodies)
    world, dt, sub, bt = a._world, a._dt, a._substeps, a._batch
    step, gt, gv, gw = world.step, bt.get_transforms, bt.get_linear_velocities, bt.get_angular_velocities
    nb = len(a._bodies)
    t, v, w = np.zeros((n, nb, 4), np.float32), np.zeros((n, nb, 2), np.float32), np.zeros((n, nb), np.float32)
    for i in range(n):
        step(dt, sub)
        gt(t[i])
        gv(v[i])
        gw(w[i])
    a.steps += n
