"""Every scenario runs on all four engines: status ok or unsupported (with a
reason), and every metric finite when ok (NaN only where a metric does not
apply, e.g. momentum under external forces)."""

import math

import pytest

from physbench.harness.references import undefined_reason

from physbench.adapters import ENGINES
from physbench.harness.runner import run
from physbench.contract.scene import load_scene, scenario_ids

# metrics that are NaN by definition in some scenes (not applicable)
MAY_BE_NAN = {"linear_momentum_drift", "angular_momentum_drift", "max_penetration", "mean_penetration",
              "post_impact_velocity_error", "energy_drift", "energy_dissipated"}


#: runs that diverge, measured (docs/ENGINE_FINDINGS.md); an xfail with the figure
KNOWN_DIVERGED = {
    ("gyroscopic.fast_spin", "drake"): "drake 1.51.1: the discrete plant does not renormalise quaternions "
                                       "(drake#14800); |q| overflows by step 256",
    ("gyroscopic.fast_spin", "mjx"): "mujoco-mjx 3.17.0 implicitfast: non-finite by step 256 (MuJoCo 4.0.0 holds)",
}


@pytest.mark.parametrize("engine", [e for e in ENGINES if e != "reference"])  # reference: test_scenarios.py
@pytest.mark.parametrize("sid", scenario_ids())
def test_scenario_runs_on_engine(sid, engine):
    scene = load_scene(sid)
    r = run(scene, engine)
    if (sid, engine) in KNOWN_DIVERGED and r.status == "diverged":
        pytest.xfail(f"{KNOWN_DIVERGED[sid, engine]}: {r.message}")
    assert r.status in ("ok", "unsupported"), f"{engine} {sid}: {r.status}: {r.message}"
    if r.status == "unsupported":
        assert r.message, "unsupported needs a reason"
        return
    # a metric with no value on this run is NaN with its reason
    # (harness.references.undefined), never a silent NaN
    bad = {k: v for k, v in r.metrics.items()
           if isinstance(v, float) and not math.isfinite(v) and k not in MAY_BE_NAN and not undefined_reason(r.metrics, k)}
    assert not bad, f"{engine} {sid}: non-finite metrics {bad}"
    assert r.metrics["stable"] in (True, False)
