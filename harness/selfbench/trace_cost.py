"""What tracing costs: a plain run against a traced run plus the
diagnosing write, side by side in one process, per engine (docs/TRACES.md,
"Cost").

    python -m physbench.harness.selfbench.trace_cost [--scenario stacking.column_10] [--duration 10]
        [--repeats 5] [--engines mujoco,pybullet,pymunk,reference] [--out DIR]

Every repeat runs each engine's plain run, traced run (engine contacts
read) and write one after the other, so the machine's load falls on all
three alike; a warm-up round first pays the imports, the JIT and rerun's
first write.  CPU seconds (``time.process_time``), medians over the
repeats.  A benchmark, not a test: nothing here asserts a time.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from physbench.contract.scene import load_scene
from physbench.harness.runner import run
from physbench.harness.trace import write_rrd
from physbench.harness.trace.contacts import DEFAULT_CAP


def _cpu(fn):
    c0 = time.process_time()
    out = fn()
    return time.process_time() - c0, out


def measure(scenario: str = "stacking.column_10", duration: float = 10.0, repeats: int = 5,
            engines: tuple[str, ...] = ("mujoco", "pybullet", "pymunk", "reference"),
            out_dir: str | Path | None = None) -> list[dict]:
    """One row per engine: median CPU s of the plain ``run`` (with metrics),
    the traced run (``contact_cap`` = DEFAULT_CAP), the diagnosing
    ``write_rrd``, and of a plain-trace write; the first write in the
    process (rerun's lazy imports); frames, engine contact rows and the
    .rrd size (bytes)."""

    scene = load_scene(scenario, overrides={"scenario.duration": duration})
    tmp = Path(out_dir) if out_dir else Path(tempfile.mkdtemp(prefix="trace_cost_"))
    warm = run(scene, engines[0])
    first_write, _ = _cpu(lambda: write_rrd(tmp / "first.rrd", scene, [warm], diagnose=True))
    times = {e: {"run": [], "traced": [], "write": [], "plain_write": []} for e in engines}
    info = {}
    for k in range(repeats + 1):  # round 0 warms up
        for e in engines:
            c_run, _ = _cpu(lambda: run(scene, e))
            c_tr, res = _cpu(lambda: run(scene, e, contact_cap=DEFAULT_CAP))
            path = tmp / f"{e}.rrd"
            c_w, _ = _cpu(lambda: write_rrd(path, scene, [res], diagnose=True))
            c_pw, _ = _cpu(lambda: write_rrd(tmp / f"{e}_plain.rrd", scene, [res]))
            if k:
                for key, v in (("run", c_run), ("traced", c_tr), ("write", c_w), ("plain_write", c_pw)):
                    times[e][key].append(v)
            info[e] = {"status": res.status, "frames": res.trace.n_frames,
                       "contact_rows": sum(len(c) for _, c in (res.contacts or [])),
                       "size": path.stat().st_size, "plain_size": (tmp / f"{e}_plain.rrd").stat().st_size}
    rows = []
    for e in engines:
        med = {key: statistics.median(v) for key, v in times[e].items()}
        rows.append({"engine": e, **med, **info[e], "first_write": first_write,
                     "ratio": (med["traced"] + med["write"]) / med["run"]})
    return rows


def markdown(rows: list[dict]) -> str:
    lines = ["| engine | run | traced run | write | trace / run | size | engine contact rows | plain write, size |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['engine']} | {r['run']:.2f} s | {r['traced']:.2f} s | {r['write']:.2f} s | "
                     f"{r['ratio']:.1f}x | {r['size'] / 1e6:.1f} MB | {r['contact_rows']} | "
                     f"{r['plain_write']:.2f} s, {r['plain_size'] / 1e6:.1f} MB |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m physbench.harness.selfbench.trace_cost", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="stacking.column_10")
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--engines", default="mujoco,pybullet,pymunk,reference")
    ap.add_argument("--out", default=None, help="directory for the .rrd files (default: a temporary one)")
    a = ap.parse_args(argv)
    rows = measure(a.scenario, a.duration, a.repeats, tuple(a.engines.split(",")), a.out)
    print(markdown(rows))
    print(f"first write in the process (rerun's imports): {rows[0]['first_write']:.2f} s CPU")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
