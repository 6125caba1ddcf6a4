"""Part of the contract between the staged and the fused step (stated in
tests/test_engine_steady.py), for forces: the force stages' one table
(engine.forces.FORCES) is what both steps run.

* The staged step runs the stages of the table in its order
  (engine.forces.force_stages); the compiled force model lists their
  kernels in the same order (engine.flight.apply_forces), which the
  integrators' evaluations at intermediate states and the fused steps'
  flight part (engine/fused/part.py) call.
* For every entry of the table, a scene with that effect gives bit for
  bit the staged frames through the fused calls: with no contact (the
  flight step, engine/fused/loop.py) and with a box pair sliding on a
  plane (the steady and contact-free steps, engine/fused/steady.py).

A new force effect is its kernel, its field of ``ForceModel`` and its line
in ``apply_forces`` (engine/flight.py) and its stage class in the table
(engine/forces.py: ``wanted``, ``fields``, ``kernel``, ``warm``); this
test then runs it on every path once it has a scene recipe in
:data:`RECIPES` (it fails for an entry without one)."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap

import numpy as np
import pytest

from physbench.engine import Engine, flight, forces, jit
from physbench.engine.fused import SteadyStep
from physbench.engine.fused.loop import FLIGHT_NAME, FlightStep
from physbench.engine.fused.steady import FREE_NAME, NAME, warm_scene

#: each force stage's scene recipe: (effects, SceneInput fields, settings)
#: for two 0.2 m boxes moving and turning (engine.fused.steady.warm_scene)
RECIPES = {
    "Gravity": ({"gravity"}, {}, {}),
    "LinearDrag": ({"drag_linear"}, {"drag_linear": np.array([0.8, 0.3])}, {}),
    "QuadraticDrag": ({"drag_quadratic"}, {"drag_quadratic": np.array([0.5, 1.2])}, {}),
    "Springs": ({"spring", "damper"}, {
        "spring_a": np.array([0], np.int64), "spring_b": np.array([1], np.int64),
        "spring_anchor_a": np.array([[0.05, 0.0, 0.1]]), "spring_anchor_b": np.array([[0.0, 0.05, -0.1]]),
        "spring_k": np.array([40.0]), "spring_c": np.array([0.3]), "spring_rest": np.array([0.12])}, {}),
    "GyroscopicTorque": ({"gyroscopic"}, {"inertia": np.array([[0.004, 0.007, 0.009], [0.005, 0.006, 0.011]])},
                         {"gyroscopic": "explicit"}),
}


def _input(kind: str, contact: bool, with_effect: bool = True):
    """The recipe's scene: two boxes with a sideways velocity and a spin,
    stacked on a plane (``contact``, with gravity and friction) or alone in
    space (the effect alone); ``with_effect`` False drops the effect."""
    effects, fields, settings = RECIPES[kind]
    inp = warm_scene(("box", "box"), plane=contact)
    n = len(inp.shape)
    v = np.tile([0.4, -0.2, 0.0], (n, 1))
    w = np.tile([0.2, -0.1, 1.5], (n, 1)) if not contact else np.tile([0.0, 0.0, 1.5], (n, 1))
    eff = set(effects) if with_effect else set()
    if contact:
        eff |= {"contact", "friction"} | ({"gravity"} if with_effect or kind != "Gravity" else set())
    inp = dataclasses.replace(inp, v=v, w=w, effects=frozenset(eff), **fields)
    return inp, settings


def _frames(eng, steps: int, staged: bool) -> list[np.ndarray]:
    """The (x, q, v, w) of every step, one step a call."""
    eng.profile.by_stage = staged
    out = []
    for _ in range(steps):
        eng.step(1)
        s = eng.state
        out.append(np.concatenate([s.x.ravel(), s.q.ravel(), s.v.ravel(), s.w.ravel()]))
    return out


def _calls(eng, name: str) -> int:
    return eng.profile.as_dict().get(name, {}).get("calls", 0)


def test_every_force_stage_has_a_recipe_and_a_compiled_form():
    assert set(RECIPES) == {S.__name__ for S in forces.FORCES}
    # the staged stages' order, the force model's fields and the compiled
    # list (engine.flight.apply_forces) are the table's
    src = textwrap.dedent(inspect.getsource(flight.apply_forces.py_func))
    body = ast.parse(src).body[0].body
    calls = [n.func.id for st in body for n in ast.walk(st) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
    assert calls == [S.kernel.py_func.__name__ for S in forces.FORCES]
    for S in forces.FORCES:
        jit._warm_force(S.__name__)  # the warm-up compiles (or loads) the stage's own kernel from the table
        assert S.kernel.signatures
        inp, settings = _input(S.__name__, False)
        eng = Engine(inp, settings)
        stages = [s for s in eng.stages if s.family == "forces"]
        assert [type(s) for s in stages] == [S]  # the recipe makes exactly this stage
        fm = forces.force_model(eng.model, stages)
        present = [f for f in flight.ForceModel._fields if getattr(fm, f).shape[0]]
        assert present == list(stages[0].fields())  # the stage fills its own fields of the model


@pytest.mark.parametrize("kind", [S.__name__ for S in forces.FORCES])
@pytest.mark.parametrize("contact,integrator", [(False, None), (False, "rk4"), (True, None)])
def test_every_force_stage_gives_the_staged_bits_on_the_fused_paths(kind, contact, integrator):
    inp, settings = _input(kind, contact)
    if integrator:
        settings = {**settings, "integrator": integrator}
    steps = 60
    staged_eng = Engine(inp, settings)
    staged = _frames(staged_eng, steps, True)
    stage_name = next(S.name for S in forces.FORCES if S.__name__ == kind)
    assert _calls(staged_eng, stage_name) == steps  # the staged step ran the stage itself, every step
    eng = Engine(inp, settings)
    plan_fast = eng.state.ctx.plan.fast
    assert isinstance(plan_fast, SteadyStep if contact else FlightStep)  # the plan fuses the scene
    fused = _frames(eng, steps, False)
    names = (NAME, FREE_NAME) if contact else (FLIGHT_NAME,)
    assert sum(_calls(eng, k) for k in names) >= 0.9 * steps  # through the fused calls
    for a, b in zip(staged, fused):
        assert np.array_equal(a, b)  # every frame, bit for bit
    # the comparison sees the effect: the same scene without it moves otherwise
    bare, _ = _input(kind, contact, with_effect=False)
    without = _frames(Engine(bare, settings), steps, False)
    assert not np.array_equal(fused[-1], without[-1])
