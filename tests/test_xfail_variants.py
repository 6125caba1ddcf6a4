"""A known limitation keyed to some of a spec's variants (contract/xfail.py,
``variants`` in an xfail table): in those scenes the check is XFAIL/XPASS,
in the others it is a plain check, so a variant that meets the bound is a
PASS, not an unexpected pass.  Engine versions here are fakes."""

from __future__ import annotations

from pathlib import Path

import pytest

from physbench.contract.scene import Check, load_scene
from physbench.contract.spec import SpecError
from physbench.contract.xfail import Xfail, shipped_xfails, xfail_for
from physbench.harness import conformance as C
from physbench.harness.runner import RunResult

ROOT = Path(__file__).resolve().parent.parent
HEAD_ON = ROOT / "tests" / "data" / "head_on.toml"


def result(value: float, variant: str | None, status: str = "ok") -> RunResult:
    return RunResult(scenario="fam.scn", variant=variant, engine="drake", engine_version="1.51.1", status=status,
                     message="diverged at step 256" if status != "ok" else "", settings={},
                     metrics={"err": value})


KEYED = Check("err", max=0.01, xfail={"drake": Xfail("measured 0.05 (base), 0.07 (plastic)", "1.51.1",
                                                     variants=("base", "plastic"))})


@pytest.mark.parametrize("variant", [None, "base", "plastic"])
def test_inside_its_variants_the_limitation_is_an_xfail(variant):
    assert C.evaluate_check(KEYED, result(0.05, variant)).outcome == C.XFAIL
    assert C.evaluate_check(KEYED, result(0.001, variant)).outcome == C.XPASS
    # a run that diverged is covered there too (its checks have no metric)
    o = C.evaluate_check(KEYED, result(float("nan"), variant, status="diverged"))
    assert o.outcome == C.XFAIL and "diverged at step 256" in o.message


def test_in_other_variants_the_check_is_plain_without_a_note():
    passing = C.evaluate_check(KEYED, result(0.001, "elastic"))
    failing = C.evaluate_check(KEYED, result(0.05, "elastic"))
    assert passing.outcome == C.PASS and failing.outcome == C.FAIL
    assert "xfail" not in failing.message and "known limitation" not in failing.message
    assert C.evaluate_check(KEYED, result(0.0, "elastic", status="diverged")).outcome == C.ERROR
    assert xfail_for(KEYED.xfail, "drake", "1.51.1", "elastic") == (None, "")
    assert xfail_for(KEYED.xfail, "drake", "1.51.1", None)[0].startswith("measured 0.05")
    # the version rule still applies inside the variants
    reason, note = xfail_for(KEYED.xfail, "drake", "1.52.0", "plastic")
    assert reason is None and "measured on drake 1.51.1" in note


def _spec(tmp_path: Path, xfail_toml: str) -> Path:
    text = HEAD_ON.read_text(encoding="utf-8").replace(
        'metric = "max_penetration"\nmax = 0.002\n', f'metric = "max_penetration"\nmax = 0.002\nxfail = {xfail_toml}\n')
    assert xfail_toml in text
    p = tmp_path / "head_on_v.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_the_spec_keys_an_xfail_to_variants_and_each_compiled_scene_judges_alike(tmp_path):
    p = _spec(tmp_path, '{ drake = { reason = "measured 4.5 mm", variants = ["base", "plastic"] }, '
                        'mujoco = "soft: measured 6 mm" }')
    for variant, keyed in ((None, True), ("plastic", True), ("elastic", False)):
        scene = load_scene(p, variant)
        check = [c for c in scene.checks if c.metric == "max_penetration"][0]
        assert check.xfail["drake"] == Xfail("measured 4.5 mm", "1.51.1", variants=("base", "plastic"))
        assert check.xfail["drake"].holds_in(variant) is keyed
        o = C.evaluate_check(check, RunResult(scene.id, variant, "drake", "1.51.1", "ok", "", {},
                                              metrics={"max_penetration": 0.0045}))
        assert o.outcome == (C.XFAIL if keyed else C.FAIL)
        # the other engine's plain entry holds in every variant
        o = C.evaluate_check(check, RunResult(scene.id, variant, "mujoco", "4.0.0", "ok", "", {},
                                              metrics={"max_penetration": 0.006}))
        assert o.outcome == C.XFAIL
    assert shipped_xfails(tmp_path)["drake"] == {("1.51.1", ">=1.51,<1.52"): 1}


@pytest.mark.parametrize("bad, why", [
    ('{ drake = { reason = "r", variants = ["bas"] } }', "unknown variant 'bas'; this spec has: base, elastic, plastic"),
    ('{ drake = { reason = "r", variants = [] } }', "variants: expected a non-empty list"),
    ('{ drake = { reason = "r", variants = "base" } }', "variants"),
    ('{ drake = { reason = "r", variants = ["base", "base"] } }', "named twice"),
])
def test_bad_variants_are_spec_errors_naming_the_key(tmp_path, bad, why):
    with pytest.raises(SpecError) as e:
        load_scene(_spec(tmp_path, bad))
    text = "\n".join(e.value.errors)
    assert "check[2].xfail.drake" in text and why in text, text


def test_a_variants_own_xfail_override_is_checked_too(tmp_path):
    p = _spec(tmp_path, '{ mujoco = "soft" }')
    p.write_text(p.read_text(encoding="utf-8") + '"check[2].xfail" = { drake = { reason = "r", variants = ["nope"] } }\n',
                 encoding="utf-8")
    with pytest.raises(SpecError) as e:
        load_scene(p)
    assert "variant 'plastic': check[2].xfail.drake.variants: unknown variant 'nope'" in "\n".join(e.value.errors)


def test_an_override_of_a_check_the_variant_does_not_run_is_refused(tmp_path):
    """A variant that overrides check[N] while check N holds only in other
    variants changes nothing: the spec is refused, naming the variant, the
    key and the check's variants (billiards.break_16 and
    tunnelling.spinning_long_box carried such dead overrides).  Overriding
    the check's ``variants`` in the same variant makes it live."""
    p = _spec(tmp_path, '{ mujoco = "soft" }')
    text = p.read_text(encoding="utf-8").replace('metric = "max_penetration"\nmax = 0.002\n',
                                                 'metric = "max_penetration"\nmax = 0.002\nvariants = ["base"]\n')
    dead = text + '"check[2].xfail" = { mujoco = "soft: measured 5 mm" }\n'
    p.write_text(dead, encoding="utf-8")
    with pytest.raises(SpecError) as e:
        load_scene(p)
    msg = "\n".join(e.value.errors)
    assert "variant 'plastic': 'check[2].xfail' overrides check[2], which holds only in variants ['base']" in msg, msg
    p.write_text(dead + '"check[2].variants" = ["plastic"]\n', encoding="utf-8")
    scene = load_scene(p, "plastic")
    check = [c for c in scene.checks if c.metric == "max_penetration"][0]
    assert check.xfail["mujoco"].reason == "soft: measured 5 mm"
