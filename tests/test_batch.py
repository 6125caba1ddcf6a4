"""Batched runs (harness/batch.py): W starts of one scene in one adapter
call.  MJX's batch (jax.vmap of its compiled scan over the worlds) equals
the W sequential MJX runs to 1e-12 in every state component; an adapter
without batches runs them one at a time (runner.run, bit for bit); a batch
of scenes that differ in more than their start is refused; the ensemble
takes the batched path and gets the same members."""

from __future__ import annotations

import numpy as np
import pytest

from physbench.contract.scene import compile_scene
from physbench.contract.spec import validate_raw
from physbench.harness.batch import run_batch, same_but_start
from physbench.harness.ensemble import Perturbation, perturb_scene
from physbench.harness.runner import run


def drop_scene(mass: float = 1.0, duration: float = 0.4):
    """Two spheres dropped spinning and sliding onto a plane (contact,
    friction), dt 2 ms, 0.5 m apart, never meeting (so MuJoCo's model of
    every start has the same contact pairs)."""
    raw = {"scenario": {"family": "batch", "title": "t", "duration": duration, "dt": 0.002,
                        "effects": ["gravity", "contact", "friction"]},
           "material": {"default": {"friction": 0.5, "static_friction": 0.5, "restitution": 0.0}},
           "body": [{"name": "a", "shape": "sphere", "radius": 0.1, "mass": mass,
                     "position": [0, 0, 0.3], "angular_velocity": [1.0, 2.0, 0.5], "velocity": [0, 0.5, 0]},
                    {"name": "ball", "shape": "sphere", "radius": 0.05, "mass": 0.3, "position": [0.5, 0, 0.2]}],
           "static": [{"name": "floor", "shape": "plane", "normal": [0, 0, 1]}]}
    return compile_scene(validate_raw(raw, "<batch test>"))


def members(scene, w: int):
    p = Perturbation(n=w, position=0.01, velocity=0.05, orientation=0.05, angular_velocity=0.2, seed=3)
    return [perturb_scene(scene, p, i) for i in range(w)]


def test_a_batch_is_one_model_with_different_starts():
    base = drop_scene()
    assert same_but_start(members(base, 3)) is None
    why = same_but_start([base, drop_scene(mass=2.0)])
    assert why is not None and "scene 1" in why and "one model" in why
    with pytest.raises(ValueError, match="one model"):
        run_batch([base, drop_scene(mass=2.0)], "mujoco")


def test_without_batches_each_world_is_a_plain_run():
    scenes = members(drop_scene(duration=0.1), 2)
    out = run_batch(scenes, "mujoco")
    for sc, r in zip(scenes, out):
        ref = run(sc, "mujoco", compute_metrics=False)
        assert r.status == ref.status == "ok" and "batch" not in r.info
        np.testing.assert_array_equal(r.trace.valid().pos, ref.trace.valid().pos)


@pytest.mark.slow  # two cold XLA compiles (the batched and the single-world scan): 1-4 min
def test_mjx_batch_equals_the_sequential_mjx_runs(tmp_path, monkeypatch):
    pytest.importorskip("mujoco.mjx")
    monkeypatch.setenv("PHYSBENCH_JAX_CACHE", str(tmp_path / "jax"))
    # 4 worlds, 200 steps, both spheres land and slide with friction: the
    # vmapped scan gives each world's sequential trajectory (measured max
    # difference 3e-15, in angular velocity; the test allows 1e-12).  With a
    # box landing on the plane (the convex solver's iterations) the worlds
    # drift apart from the sequential runs after the landing: 3e-11 m in
    # 100 steps (docs/ENGINE_FINDINGS.md)
    scenes = members(drop_scene(), 4)
    out = run_batch(scenes, "mjx")
    for sc, r in zip(scenes, out):
        assert r.status == "ok", r.message
        assert r.info["batch"]["worlds"] == 4 and r.info["batch"]["us_per_world_step"] > 0
        assert r.timing["jit_s"] > 0 and r.stages["worlds"] == 4
        ref = run(sc, "mjx", compute_metrics=False)
        assert ref.status == "ok"
        a, b = r.trace.valid(), ref.trace.valid()
        assert len(a.t) == len(b.t) == 201
        for x, y in ((a.pos, b.pos), (a.quat, b.quat), (a.vel, b.vel), (a.angvel, b.angvel)):
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-12)
    # the worlds did differ, and both spheres rest on the plane (contact acted)
    finals = np.array([r.trace.valid().pos[-1] for r in out])
    assert np.ptp(finals[:, 0, 0]) > 1e-3
    np.testing.assert_allclose(finals[:, :, 2], [[0.1, 0.05]] * 4, atol=1e-3)


def test_the_ensemble_hands_a_batched_engine_one_batch(monkeypatch):
    # an adapter that declares batches gets every member in one call, and
    # the members are the ones the per-member path makes (a stand-in
    # batched adapter: MuJoCo's runs behind the batch interface)
    from physbench.adapters import get_adapter
    from physbench.harness import ensemble as E

    cls = get_adapter("mujoco")
    calls = []

    def build_batch(self, scenes, settings):
        calls.append(len(scenes))
        self._worlds = []
        for sc in scenes:
            a = cls()
            a.build(sc, settings)
            self._worlds.append(a)

    def read_state_batch(self, pos, quat, vel, angvel):
        for k, a in enumerate(self._worlds):
            a.read_state(pos[k], quat[k], vel[k], angvel[k])

    def step_record_batch(self, n, pos, quat, vel, angvel):
        for k, a in enumerate(self._worlds):
            a.step_record(n, pos[k], quat[k], vel[k], angvel[k])

    for name, fn in (("build_batch", build_batch), ("read_state_batch", read_state_batch),
                     ("step_record_batch", step_record_batch)):
        monkeypatch.setattr(cls, name, fn, raising=False)
    monkeypatch.setattr(cls, "batched", True, raising=False)
    p = E.Perturbation(n=3, position=0.001, seed=1)
    batched = E.run_ensemble("billiards.head_on", "mujoco", p, executor="inline")
    assert calls == [3] and batched["batch"]["worlds"] == 3
    monkeypatch.setattr(cls, "batched", False)
    plain = E.run_ensemble("billiards.head_on", "mujoco", p, executor="inline")
    assert plain["batch"] is None and calls == [3]
    for a, b in zip(batched["per_member"], plain["per_member"]):
        assert a["status"] == b["status"] == "ok" and a["events"] == b["events"]
        np.testing.assert_allclose(a["final_pos"], b["final_pos"], rtol=0, atol=1e-12)
    assert batched["final_spread"] == pytest.approx(plain["final_spread"], rel=1e-9)


def test_a_refused_batch_runs_one_world_at_a_time(monkeypatch):
    # an adapter whose model depends on the start refuses the batch
    # (NotOneBatch); the worlds then run as plain runs, each noting why
    from physbench.adapters import get_adapter
    from physbench.adapters.base import NotOneBatch

    cls = get_adapter("mujoco")

    def build_batch(self, scenes, settings):
        raise NotOneBatch("the contact pairs differ")

    monkeypatch.setattr(cls, "build_batch", build_batch, raising=False)
    monkeypatch.setattr(cls, "batched", True, raising=False)
    scenes = members(drop_scene(duration=0.1), 2)
    out = run_batch(scenes, "mujoco")
    for sc, r in zip(scenes, out):
        assert r.status == "ok" and "batch" not in r.info
        assert any("cannot batch these starts: the contact pairs differ" in n for n in r.notes)
        np.testing.assert_array_equal(r.trace.valid().pos, run(sc, "mujoco", compute_metrics=False).trace.valid().pos)
