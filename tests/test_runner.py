"""The runner turns every engine failure into a recorded status, records
every step into preallocated arrays, and block recording equals the plain
step/read loop bit for bit on every engine."""

import numpy as np
import pytest

from physbench.adapters import ENGINES, get_adapter
from physbench.adapters.base import Adapter, Capabilities, DT_SETTING, Setting, register
from physbench.harness.runner import Trace, run
from physbench.contract.scene import load_scene
from tests.conftest import HEAD_ON


class Fake(Adapter):
    """Free flight of every body; misbehaves on request (setting `fault`)."""

    name = "fake"

    @classmethod
    def capabilities(cls):
        return Capabilities("fake", "1", 3, frozenset({"sphere", "box"}), frozenset({"plane"}),
                            frozenset({"contact", "restitution"}),
                            {"dt": DT_SETTING, "fault": Setting("fault", "none", str, "",
                                                                choices=("none", "build", "step", "nan", "slow"))})

    def build(self, scene, settings):
        self.fault = settings["fault"]
        if self.fault == "build":
            raise RuntimeError("model rejected")
        self.dt = settings["dt"]
        self.x, self.q, self.v, self.w = (a.copy() for a in scene.initial_state())
        self.k = 0

    def step(self, n=1):
        for _ in range(n):
            self.k += 1
            if self.fault == "step" and self.k == 300:
                raise FloatingPointError("solver exploded")
            if self.fault == "nan" and self.k == 400:
                self.v[:] = np.nan
            if self.fault == "slow":
                import time
                time.sleep(0.002)
            self.x += self.v * self.dt

    def read_state(self, pos, quat, vel, angvel):
        pos[...] = self.x
        quat[...] = self.q
        vel[...] = self.v
        angvel[...] = self.w


@pytest.fixture(autouse=True, scope="module")
def _fake_engine():
    from physbench.adapters import base

    register("fake", lambda: Fake)
    yield
    base._REGISTRY.pop("fake", None)


@pytest.fixture(scope="module")
def scene():
    return load_scene(HEAD_ON)


def test_ok_run_records_every_step(scene):
    r = run(scene, "fake")
    assert r.status == "ok" and r.trace.n_frames == scene.n_steps + 1
    tr = r.trace.valid()
    assert np.allclose(tr.t, np.arange(scene.n_steps + 1) * scene.dt)
    assert tr.pos[-1, 0, 0] == pytest.approx(2.0 * 0.5)
    assert r.timing["steps"] == scene.n_steps and r.metrics["cpu_s_per_sim_s"] >= 0


def test_build_failure_is_status_failed(scene):
    r = run(scene, "fake", {"fault": "build"})
    assert r.status == "failed" and "model rejected" in r.message


def test_step_exception_is_status_error_and_keeps_frames(scene):
    r = run(scene, "fake", {"fault": "step"})
    assert r.status == "error" and "solver exploded" in r.message
    assert r.trace.n_frames == 300  # frames 0..299 recorded: nothing lost
    assert np.isfinite(r.trace.valid().pos).all()


def test_non_finite_is_status_diverged(scene):
    r = run(scene, "fake", {"fault": "nan"})
    assert r.status == "diverged" and "non-finite" in r.message
    assert r.metrics["stable"] is False


def test_timeout(scene):
    r = run(scene, "fake", {"fault": "slow"}, timeout_s=0.2)
    assert r.status == "timeout" and r.trace.n_frames < scene.n_steps + 1


def test_unsupported_effect(tmp_path):
    p = tmp_path / "g.toml"
    # without the restitution effect its coefficients go too (a coefficient
    # without its effect is a spec error)
    p.write_text(HEAD_ON.read_text().replace('["contact", "restitution"]', '["contact", "gravity"]')
                 .replace("restitution = 0.9\n", "").replace('"material.default.restitution" = 1.0', "")
                 .replace('"material.default.restitution" = 0.0', ""))
    r = run(load_scene(p), "fake")
    assert r.status == "unsupported" and "gravity" in r.message


def test_bad_setting_is_a_value_error(scene):
    with pytest.raises(ValueError, match="setting fault: expected one of"):
        run(scene, "fake", {"fault": "sometimes"})


@pytest.mark.parametrize("target_s, wall_s, grows", [(1e9, 1e9, True), (0.0, 1e9, False), (1e9, 0.0, False)])
def test_blocks_grow_and_lose_nothing(scene, monkeypatch, target_s, wall_s, grows):
    """Blocks start at CHECK_EVERY steps and double while a block takes
    less than BLOCK_TARGET_S of CPU time and BLOCK_WALL_S of wall time (set
    here, so the test does not depend on the machine's speed), never beyond
    MAX_BLOCK; every step is recorded and time stamps are exact multiples of
    dt."""
    from physbench.harness import runner
    from physbench.contract.scene import Scene

    long = Scene(**{**scene.__dict__, "duration": 20.0})
    sizes = []
    orig = Fake.step_record

    def counting(self, n, *views):
        sizes.append(n)
        return orig(self, n, *views)

    monkeypatch.setattr(Fake, "step_record", counting)
    monkeypatch.setattr(runner, "BLOCK_TARGET_S", target_s)
    monkeypatch.setattr(runner, "BLOCK_WALL_S", wall_s)
    r = run(long, "fake")
    assert r.status == "ok" and r.trace.n_frames == long.n_steps + 1
    assert sum(sizes) == long.n_steps and sizes[0] == runner.CHECK_EVERY
    assert max(sizes) <= runner.MAX_BLOCK
    if grows:
        assert sizes[:4] == [runner.CHECK_EVERY * 2 ** k for k in range(4)]
    else:
        assert set(sizes[:-1]) == {runner.CHECK_EVERY}
    tr = r.trace.valid()
    np.testing.assert_array_equal(tr.t, np.arange(long.n_steps + 1) * long.dt)
    assert np.isfinite(tr.pos).all()


@pytest.mark.parametrize("name, bound", [("pos", 1e6), ("quat", 2.0), ("vel", 1e6), ("angvel", 1e6)])
def test_runaway_finds_every_bad_value(name, bound):
    """_runaway (max and min per array, no temporary) reports a NaN, an
    infinity of either sign and a component beyond its bound of either sign,
    in any frame of the range and only there; a state at the bound is none."""
    from physbench.harness.runner import _runaway

    tr = Trace.allocate(6, 3)
    for a in (tr.pos, tr.quat, tr.vel, tr.angvel):
        a[...] = 0.5
    arr = getattr(tr, name)
    arr[2, 1, 0] = -bound
    arr[4, 2, 1] = bound
    assert _runaway(tr, 0, 6) == ""
    for bad, what in [(np.nan, "non-finite"), (np.inf, "non-finite"), (-np.inf, "non-finite"),
                      (bound * 1.5, "beyond"), (-bound * 1.5, "beyond")]:
        arr[3, 0, 2] = bad
        msg = _runaway(tr, 1, 5)
        assert what in msg and (name in msg or name != "quat" and what == "beyond"), (bad, msg)
        assert _runaway(tr, 4, 6) == ""  # the frame is outside [4, 6)
        arr[3, 0, 2] = 0.5


def test_record_every(scene):
    r = run(scene, "fake", record_every=7)
    tr = r.trace.valid()
    assert tr.t[-1] == pytest.approx(0.5) and tr.t[1] == pytest.approx(7 * scene.dt)


#: settings under which an engine runs the head-on scene at all: Drake's
#: discrete step cannot realise its e = 0.9 (unsupported), continuous time can
BLOCK_SETTINGS = {"drake": {"time_step": 0.0}}


@pytest.mark.parametrize("engine", ENGINES)
def test_block_recording_equals_step_loop(engine, scene):
    cls = get_adapter(engine)
    if not cls.capabilities().available:
        pytest.skip(f"{engine} is not installed: {cls.capabilities().unavailable_reason}")
    st = cls.resolve_settings(scene, BLOCK_SETTINGS.get(engine))
    n, nb = 300, scene.n_bodies
    outs = []
    for block in (False, True):
        a = cls()
        a.build(scene, st)
        bufs = [np.zeros((n, nb, k)) for k in (3, 4, 3, 3)]
        for k0 in range(0, n, 128):
            m = min(128, n - k0)
            views = [b[k0:k0 + m] for b in bufs]
            (a.step_record if block else (lambda *v: Adapter.step_record(a, *v)))(m, *views)
        a.close()
        outs.append(bufs)
    for x, y in zip(*outs):
        assert np.array_equal(x, y)
