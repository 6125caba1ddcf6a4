"""Analytic and high-accuracy reference models.

A model is named by a scene's ``[reference] model = "..."``.  It takes every
parameter it can from the scene itself (masses, radii, inertias, slope angle,
materials, initial velocities) so the same model serves any scene of its kind;
``[reference] params`` holds only what the scene cannot say.

Each model is a :class:`ReferenceModel` subclass in its own module that
declares what it takes from the scene (``takes``), its ``params``
(:class:`Param`: name, type, default, meaning), the metrics it produces
(``produces``: name -> meaning with units) and its ``primary`` metric.  The
registry (``contract.models.MODELS``) holds names only (name ->
"module:Class", imported lazily), so loading a spec never imports a model;
the load-time check is there too.  ``docs/MODELS.md`` and ``physbench models``
are both written from the declarations (:func:`describe`, :func:`models_markdown`;
tests/test_models.py pins the document to them).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from physbench.contract.models import MODEL_ORIGINS, MODELS, SHIPPED_MODELS, ReferenceError, get_model

if TYPE_CHECKING:
    from physbench.contract.scene import Scene


@dataclass(frozen=True)
class Param:
    """One ``[reference] params`` key: ``type`` is one of 'str', 'int',
    'float', 'list of str'; ``default`` None means "see meaning"."""

    name: str
    type: str
    default: Any
    meaning: str


_TYPE_OK = {
    "str": lambda v: isinstance(v, str),
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "float": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool),
    "list of str": lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
}

#: the trajectory metrics of :func:`trajectory_metrics`
TRAJECTORY = {
    "trajectory_rmse": "RMS over frames and bodies of |x - x_ref| (m)",
    "final_position_error": "largest |x - x_ref| over the bodies at the last frame (m)",
}
BODY_PARAM = Param("body", "str", None, "the body the model follows (default: the scene's only body)")


#: the metric column naming the metrics a run could not define, each with its
#: reason, "name: reason; name: reason" (contract.metric_defs.GENERIC_METRICS)
UNDEFINED = "undefined_metrics"


def undefined(out: dict[str, Any], name: str, reason: str) -> None:
    """Record metric ``name`` as missing from this run: NaN in ``out`` and
    "name: reason" added to ``out[UNDEFINED]``.  For a metric whose
    definition has no value on this run (a zero denominator: no initial
    kinetic energy, no apex to compare with): never a ZeroDivisionError that
    costs the run every other metric, never a silent 0 or inf; a check on
    it is an error that gives the reason (harness.conformance.verdicts;
    tests/test_metrics.py::test_undefined_metric_is_missing_with_its_reason)."""
    out[name] = float("nan")
    prev = out.get(UNDEFINED)
    out[UNDEFINED] = f"{prev}; {name}: {reason}" if prev else f"{name}: {reason}"


def divide(out: dict[str, Any], name: str, num: float, den: float, what: str) -> None:
    """``out[name] = num / den`` (Python floats), or :func:`undefined` with
    the reason "``what`` is 0" when ``den`` is 0 (or NaN)."""
    den = float(den)
    if not abs(den) > 0.0:
        undefined(out, name, f"{what} is {den:g}")
    else:
        out[name] = float(num) / den


def undefined_reason(metrics: dict[str, Any], name: str) -> str:
    """The reason metric ``name`` was recorded undefined (:func:`undefined`),
    or ''."""
    text = metrics.get(UNDEFINED)
    if not isinstance(text, str):
        return ""
    for part in text.split("; "):
        key, sep, why = part.partition(": ")
        if sep and key == name:
            return why
    return ""


@dataclass(frozen=True)
class ReferenceSeries:
    """A scalar the model predicts over time, drawn in traces as a
    reference line beside the same quantity measured on each run.

    ``key``: entity path tail ("<body>/<quantity>"); ``unit``; ``text``:
    what it is, with the predicted value (the trace's context document);
    ``model(t)``: the prediction (F,) at times t (F,) s, NaN where it says
    nothing; ``measure(trace)``: the same quantity (F,) in a recorded
    trace, or None for a prediction with no measured twin (an apex level
    drawn over the measured height)."""

    key: str
    unit: str
    text: str
    model: Callable[[np.ndarray], np.ndarray]
    measure: Callable[[Any], np.ndarray] | None = None


def constant(value: float) -> Callable[[np.ndarray], np.ndarray]:
    """A ReferenceSeries ``model`` predicting ``value`` at every time: t (F,)
    s -> (F,) filled with it (a conserved quantity, a level)."""
    return lambda t: np.full(np.shape(t), float(value))


class ReferenceModel:
    """Base class.  ``__init__(scene)`` extracts parameters (raise
    ReferenceError naming what does not fit); ``metrics(trace)`` returns the
    model's metrics for a recorded trace (harness.runner.Trace: t (F,),
    pos (F, n, 3), quat (F, n, 4), vel (F, n, 3), angvel (F, n, 3)).

    Class declarations (the one source of docs/MODELS.md and
    ``physbench models``): ``summary`` (one line), ``takes`` (what it reads
    from the scene, and what it refuses), ``params``, ``produces``
    (metric -> meaning with units), ``primary``."""

    name = ""
    summary = ""
    takes = ""
    params: tuple[Param, ...] = ()
    produces: dict[str, str] = {}
    primary = ""

    def __init__(self, scene: "Scene"):
        self.scene = scene
        allowed = {p.name: p for p in self.params}
        unknown = sorted(set(scene.reference_params) - set(allowed))
        if unknown:
            raise ReferenceError(
                f"unknown key(s) {unknown} for model {self.name!r}; allowed: {list(allowed) or 'none'}",
                key=f"reference.params.{unknown[0]}")
        for k, v in scene.reference_params.items():
            p = allowed[k]
            if not _TYPE_OK[p.type](v):
                raise ReferenceError(f"expected {p.type} ({p.meaning}), got {v!r}", key=f"reference.params.{k}")

    def param(self, key: str, default: Any = None) -> Any:
        return self.scene.reference_params.get(key, default)

    def named(self, key: str, items: Any, what: str) -> list | None:
        """The ``items`` (bodies or statics: anything with ``.name``) that
        the list ``params.<key>`` names, in its order; None when the param
        is not set.  A name the scene does not have is a ReferenceError at
        ``reference.params.<key>`` that lists the names it has."""
        names = self.param(key)
        if names is None:
            return None
        by_name = {x.name: x for x in items}
        missing = [n for n in names if n not in by_name]
        if missing:
            raise ReferenceError(f"{self.name}: params.{key} names unknown {what} {missing}; "
                                 f"the scene has {sorted(by_name)}", key=f"reference.params.{key}")
        return [by_name[n] for n in names]

    def the_body(self):
        """The body ``params.body`` names, else the scene's only body."""
        bname = self.param("body")
        if bname is not None:
            try:
                return self.scene.bodies[self.scene.body_index(bname)]
            except KeyError:
                raise ReferenceError(f"no body named {bname!r}; bodies: {[b.name for b in self.scene.bodies]}",
                                     key="reference.params.body") from None
        if self.scene.n_bodies != 1:
            raise ReferenceError(f"{self.name} needs exactly one body (or params.body), "
                                 f"the scene has {self.scene.n_bodies}")
        return self.scene.bodies[0]

    def positions(self, t: np.ndarray) -> np.ndarray | None:
        """Reference positions (F, n, 3) at times t (F,), if the model has a
        trajectory; None otherwise."""
        return None

    def trajectory(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray | None] | None:
        """The model's motion at times t (F,): (positions (F, n, 3) m,
        orientations (F, n, 4) wxyz or None when the model predicts none),
        NaN for bodies it does not model; None without a trajectory.  Drawn
        as the ghost in traces (harness.trace)."""
        pos = self.positions(t)
        return None if pos is None else (pos, None)

    def predictions(self) -> dict[str, str]:
        """The model's scalar predictions as label -> text with units
        (post-impact velocity, apex heights, flip period, stop time...), for
        the trace's context document; {} when it has none to show."""
        return {}

    def reference_series(self) -> list[ReferenceSeries]:
        """The model's scalar predictions as time series (post-impact
        velocity, bounce heights, flips, stop), drawn as reference lines in
        traces; [] by default."""
        return []

    def reference_times(self) -> list[tuple[float, str]]:
        """Moments the model predicts, (t s, text) (impact, bounces, flips,
        stop), drawn as event markers at /events/model; [] by default."""
        return []

    def events(self, trace) -> list[tuple[int, int, str]]:
        """Moments the model recognises in a recorded trace, as (frame,
        body index, text), e.g. a body passing through a wall; [] by
        default.  Drawn as event markers in traces."""
        return []

    def metrics(self, trace) -> dict[str, float]:
        ref = self.positions(trace.t)
        if ref is None:
            return {}
        return trajectory_metrics(trace.pos, ref)


def fit_slope(t: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope dy/dt (units of y per s) of y (F,) over t (F,)
    s; NaN when t does not vary."""
    tm = t - t.mean()
    den = float(tm @ tm)
    return float(tm @ (y - y.mean()) / den) if den > 0 else float("nan")


def trajectory_metrics(pos: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """trajectory_rmse: RMS over frames and bodies of |x - x_ref| (m);
    final_position_error: max over bodies of |x - x_ref| at the last frame (m)."""
    err = np.linalg.norm(pos - ref, axis=-1)
    return {
        "trajectory_rmse": float(np.sqrt(np.mean(err * err))),
        "final_position_error": float(np.max(err[-1])),
    }


# --------------------------------------------------------------------------
# the declarations, for people


def describe(name: str | None = None) -> list[dict[str, Any]]:
    """Every model's declaration (or one model's) as JSON-able dicts:
    name, summary, takes, params [{name, type, default, meaning}],
    produces {metric: meaning}, primary."""
    out = []
    for n in sorted(MODELS) if name is None else [name]:
        try:
            cls = get_model(n)
        except Exception as e:  # a broken plug-in model: listed with its error
            out.append({"name": n, "origin": MODEL_ORIGINS.get(n, ""), "error": f"{type(e).__name__}: {e}"})
            continue
        out.append({
            "name": n,
            "origin": MODEL_ORIGINS.get(n, ""),
            "summary": cls.summary,
            "takes": cls.takes,
            "params": [{"name": p.name, "type": p.type, "default": p.default, "meaning": p.meaning}
                       for p in cls.params],
            "produces": dict(cls.produces),
            "primary": cls.primary,
        })
    return out


def models_markdown() -> str:
    """docs/MODELS.md, written from the declarations."""
    lines = [
        "# Reference models",
        "",
        "<!-- written from the models' declarations in harness/references/ by",
        "     harness.references.models_markdown(); `physbench models` prints the same.",
        "     tests/test_models.py fails when this file and the declarations differ. -->",
        "",
        "A scene names its model in `[reference] model = \"...\"`. The model reads",
        "everything it can from the scene (bodies, statics, materials, effects,",
        "initial state) and refuses at load time, as a spec error naming the key",
        "path, a scene it cannot model. `[reference] params` holds only what the",
        "scene cannot say. A scene's `primary_metric` and every `[[check]]` metric",
        "must be produced by its model or by the harness (docs/METRICS.md); that is",
        "checked at load too.",
        "",
        "| model | what it models | primary metric |",
        "| --- | --- | --- |",
    ]
    descs = [d for d in describe() if d["name"] in SHIPPED_MODELS]  # the shipped models, not plug-ins
    for d in descs:
        lines.append(f"| [`{d['name']}`](#{d['name']}) | {d['summary']} | `{d['primary']}` |")
    for d in descs:
        lines += ["", f"## {d['name']}", "", d["summary"], "", f"**Takes from the scene.** {d['takes']}", ""]
        if d["params"]:
            lines += ["**Params** (`[reference] params`):", "", "| key | type | default | meaning |",
                      "| --- | --- | --- | --- |"]
            for p in d["params"]:
                default = "—" if p["default"] is None else f"`{p['default']!r}`"
                lines.append(f"| `{p['name']}` | {p['type']} | {default} | {p['meaning']} |")
        else:
            lines.append("**Params:** none.")
        lines += ["", f"**Metrics** (primary: `{d['primary']}`):", ""]
        for m, meaning in d["produces"].items():
            lines.append(f"- `{m}`: {meaning}")
    lines += ["", "## Judging a scene without a model", ""] + judge_lines()
    return "\n".join(lines) + "\n"


def judge_lines() -> list[str]:
    """What judges a scene that has no closed form besides
    ``self_consistency`` (docs/MODELS.md's last section, ``physbench
    models``' last lines): the contact-law residuals, the ensemble's
    measures and the engines' consensus, from contract.metric_defs."""
    from physbench.contract.metric_defs import CONSENSUS_METRICS, CONTACT_LAWS, ENSEMBLE_METRICS

    out = ["Checks may name these in any scene (docs/METRICS.md defines them).", "",
           "**Contact-law residuals** (each as `<name>_max`, `<name>_mean`, `<name>_rows`; recorded only when a "
           "check or the primary metric names one; undefined, with the reason, on an engine whose adapter reads "
           "no contact forces):", ""]
    out += [f"- `{n}`: {meaning}" for n, meaning in CONTACT_LAWS.items()]
    out += ["", "**Predictability** (on the scene's ensemble of perturbed starts, its `[perturbation]` or "
            "`physbench check --ensemble N --sigma S`; a row of its own):", ""]
    out += [f"- `{n}` ({d.units}): {d.meaning}" for n, d in ENSEMBLE_METRICS.items()]
    out += ["", "**Consensus** (the checked engines' runs at dt / k^2 compared; a row of engine `consensus`):", ""]
    out += [f"- `{n}` ({d.units}): {d.meaning}" for n, d in CONSENSUS_METRICS.items()]
    return out
