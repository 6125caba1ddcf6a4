"""The model's predictions as numbers (harness/references/predict.py): every
key documented in docs/METRICS.md, every shipped scene's keys among them,
and the values against closed forms computed here."""

import math
import re

import pytest

from physbench.contract.scene import load_scene, scenario_ids
from physbench.harness.references.predict import PREDICTION_KEYS, predictions
from tests.conftest import ROOT


def test_prediction_keys_are_documented():
    text = (ROOT / "docs" / "METRICS.md").read_text()
    table = text[text.index("## Predictions"):text.index("## Verdicts")]
    keys = re.findall(r"^\| `(\w+)` \|", table, re.M)
    assert keys == list(PREDICTION_KEYS)


def test_every_shipped_scene_predicts_documented_keys():
    models = set()
    for sid in scenario_ids():
        s = load_scene(sid)
        values, text = predictions(s)
        assert set(values) <= set(PREDICTION_KEYS), sid
        if values:
            models.add(s.reference_model)
            for v in values.values():
                flat = v.values() if isinstance(v, dict) else [v]
                for x in flat:
                    assert all(math.isfinite(y) for y in (x if isinstance(x, list) else [x])), (sid, v)
    assert len(models) == 13  # every model of predict._VALUES has a shipped scene


def test_prediction_values_against_closed_forms():
    # a solid ball rolling down 20 degrees: a = 5/7 g sin a, alpha = a / R
    v, _ = predictions(load_scene("friction.ball_rolls"))
    a = 5 / 7 * 9.81 * math.sin(math.radians(20))
    assert v["roll_accel_ref"] == pytest.approx(a, rel=1e-12)
    assert v["spin_accel_ref"] == pytest.approx(a / 0.1, rel=1e-12)
    # a ball dropped onto a plane: apexes h0 e^(2k)
    s = load_scene("billiards.ball_drop_bounce")
    v, _ = predictions(s)
    b = s.bodies[0]
    e = s.pair(b.material, s.statics[0].material).restitution
    h0 = v["impact_speed_ref"] ** 2 / (2 * 9.81)
    assert v["apex_heights_ref"] == pytest.approx([h0 * e ** (2 * k) for k in range(1, len(v["apex_heights_ref"]) + 1)],
                                                  rel=1e-12)
    # a box sliding to rest: t = u0 / (mu g), d = u0^2 / (2 mu g)
    s = load_scene("friction.box_slides_to_rest")
    v, _ = predictions(s)
    u0 = float(abs(s.bodies[0].velocity[0]))
    mu = s.pair(s.bodies[0].material, s.statics[0].material).friction
    assert v["stop_time_ref"] == pytest.approx(u0 / (mu * 9.81), rel=1e-12)
    assert v["stop_distance_ref"] == pytest.approx(u0 ** 2 / (2 * mu * 9.81), rel=1e-12)
