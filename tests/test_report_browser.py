"""The report in a real browser: headless Chromium opens the page built from
planted rows, driven over the DevTools protocol (a pipe, standard library
only).  No console errors, every section and image present and decoded, the
screenshot not blank.  Also the report's new analyses on the same rows: the
accuracy ladder, At a glance and Breaking points."""

from __future__ import annotations

import base64
import fcntl
import json
import math
import os
import select
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from physbench.harness import report as rp
from physbench.harness.results import write_rows
from tests.test_report import as_written

SID = "20261124T010000Z-abcd"
SECTIONS = ("at-a-glance", "header", "work-precision", "cost-to-target", "breaking-points", "stability", "phases",
            "history")


def _row(scenario, engine, dt, error, cost, metric, status="ok", **settings):
    swept = {"dt": dt, **settings}
    return {"scenario": scenario, "variant": None, "engine": engine, "engine_version": "1", "status": status,
            "message": "" if status == "ok" else "blew up", "cpu_s_per_sim_s": cost,
            "stable": status == "ok", metric: error if status == "ok" else None, "setting.dt": dt,
            **{f"setting.{k}": v for k, v in settings.items()}, "machine.host": "box", "commit": "abcd",
            "timestamp": "2026-11-24T01:00:00+00:00", "suite": "nightly", "sweep_id": SID,
            "point_key": json.dumps([scenario, engine, swept], sort_keys=True),
            "point_settings": json.dumps(swept, sort_keys=True), "primary_metric": metric,
            "primary_error": error if status == "ok" else math.nan, "cpu_s_per_sim_s_median": cost,
            "cpu_s_per_sim_s_min": cost * 0.98, "repeats": 3, "phase": 0.0}


def plant(root: Path) -> None:
    """A nightly's worth of rows: two scenarios over dt x settings on four
    engines (errors ~ dt^order, some reaching 1e-9, some not), a diverged
    point, and breaking-point searches with their evaluations."""
    rows = []
    m1 = "post_impact_velocity_error"
    for en, order, c0 in (("reference", 4, 0.5), ("mujoco", 1, 0.05), ("pybullet", 1, 0.08), ("pymunk", 1, 0.02)):
        for it in (10, 50):
            for dt in (0.004, 0.002, 0.001, 0.0005):
                err = (dt / 0.004) ** order * (1e-3 if en == "reference" else 3e-2) * (10 / it)
                rows.append(_row("billiards.head_on", en, dt, err, c0 * 0.004 / dt * (1 + it / 50), m1, iterations=it))
    m2 = "slide_accel_error"
    for en in ("reference", "mujoco", "pybullet", "pymunk"):
        for dt in (0.008, 0.004, 0.002, 0.001):
            rows.append(_row("friction.block_slides", en, dt, dt * (0.1 if en == "mujoco" else 1.0), 0.01 / dt, m2))
    rows.append(_row("friction.block_slides", "pymunk", 0.016, 0, 0.5, m2, status="diverged"))
    # tunnelling: ran and stayed finite, but the check failed (tunnelled = 1)
    for dt in (0.004166666666666667, 0.03333333333333333):
        r = _row("tunnelling.bullet_1000", "pymunk", dt, 1.5, 0.001, "reflected_velocity_error")
        r["tunnelled"] = 1.0
        rows.append(as_written(r))  # with its verdicts, as the sweep writes it
    # breaking points: dt of the column and speed of the bullet
    lim = [("stacking.column_5", "dt", {"reference": 0.03, "mujoco": 0.007, "pybullet": 0.0095, "pymunk": 0.0088},
            (0.001, 0.0666)),
           ("tunnelling.bullet_100", "body[0].velocity[0]",
            {"reference": None, "mujoco": 0.73, "pybullet": 1.77, "pymunk": 1.77}, (0.3, 1000.0))]
    for sc, par, limits, (lo, hi) in lim:
        for en, lv in limits.items():
            lid = f"{sc}-{par}-{en}"
            vals = np.geomspace(lo, hi, 9)
            for v in vals:
                held = lv is None or v <= lv
                rows.append({**_row(sc, en, 0.004, 1e-4 * v / lo, 0.01, "stack_drift"), "row_kind": "limit_eval",
                             "point_key": f"limit:{lid}|{v!r}", "limit_id": lid, "limit_param": par,
                             "limit_value": float(v), "limit_holds": bool(held),
                             "limit_reason": "" if held else "max_penetration: 0.0021 > 0.002"})
            found = lv is not None
            rows.append({"row_kind": "limit", "point_key": f"limit:{lid}", "limit_id": lid, "scenario": sc,
                         "variant": None, "engine": en, "status": "ok", "suite": "nightly", "sweep_id": SID,
                         "timestamp": "2026-11-24T01:00:00+00:00", "commit": "abcd", "limit_param": par,
                         "limit_outcome": "found" if found else "holds_throughout",
                         "limit_value": lv if found else hi, "limit_lo": lv if found else math.nan,
                         "limit_hi": lv * 1.08 if found else math.nan, "limit_direction": "below",
                         "limit_failed_check": "max_penetration: 0.0021 > 0.002" if found else "",
                         "limit_runs": 9, "limit_cpu_s": 0.5, "limit_range_lo": lo, "limit_range_hi": hi,
                         "limit_phases": 1, "limit_overrides": "{}", "schema_version": 1})
    write_rows(rows, root / "sweeps" / "m1" / "nightly" / f"{SID}.parquet", append=False)


# --- the analyses on the planted rows -------------------------------------------


def test_ladder_at_a_glance_and_breaking_points(tmp_path):
    plant(tmp_path)
    df = rp.load_results(tmp_path)
    lad = rp.ladder(df)
    hd = lad[lad["scenario"] == "billiards.head_on"].set_index(["engine", "rung"])
    # the reference (4th order) reaches 1e-9 at dt 0.0005 only with 50 iterations: err 1e-3 * (1/8)^4 / 5
    assert bool(hd.loc[("reference", 1e-9), "reached"]) is False
    assert hd.loc[("reference", 1e-6), "reached"] and hd.loc[("reference", 1e-6), "settings"]
    assert not hd.loc[("mujoco", 1e-6), "reached"]
    # "not reached" gives the best error reached and where
    best = hd.loc[("mujoco", 1e-6)]
    assert best["best_error"] == pytest.approx(3e-2 / 8 / 5) and "dt=0.0005" in best["best_error_settings"]
    ag = rp.at_a_glance(df).set_index(["family", "rung"])
    assert ag.loc[("billiards", 1e-6), "wins"] == {"reference": 1}
    assert ag.loc[("billiards", 1e-9), "reached"] == 0
    # block_slides: error = dt (mujoco dt/10), cost 0.01/dt: mujoco reaches 1e-4 at dt 0.001, nobody else
    assert ag.loc[("friction", 1e-4), "wins"] == {"mujoco": 1}
    bp = rp.breaking_points(df).set_index(["scenario", "engine"])
    assert bp.loc[("stacking.column_5", "mujoco"), "limit_value"] == 0.007
    assert rp.fmt_limit(bp.loc[("stacking.column_5", "mujoco")]) == "\u2264 0.007 [0.007, 0.00756]"
    assert rp.fmt_limit(bp.loc[("tunnelling.bullet_100", "reference")]).startswith("holds over")
    # limit rows stay out of the grid analyses
    assert not any(str(k).startswith("limit:") for k in rp.latest_points(df)["point_key"])
    # the matrix separates running finite from meeting the checks
    sm = rp.stability_matrix(df, scenarios=["tunnelling.bullet_1000"]).set_index("engine")
    assert sm.loc["pymunk", "ok_stable"] == 2 and sm.loc["pymunk", "met_checks"] == 0
    assert "tunnelled" in sm.loc["pymunk", "checks_failed"]


def test_frontier_is_the_pareto_front():
    pts = [(1.0, 1e-2), (2.0, 1e-3), (3.0, 5e-3), (4.0, 1e-4), (0.5, 1e-1)]
    assert rp.frontier(pts) == [(0.5, 1e-1), (1.0, 1e-2), (2.0, 1e-3), (4.0, 1e-4)]


def test_engine_colours_fixed_and_legends_short(tmp_path):
    import matplotlib.image as mpimg

    plant(tmp_path)
    df = rp.load_results(tmp_path)
    assert len({rp.engine_colour(e) for e in ("reference", "mujoco", "pybullet", "pymunk")}) == 4
    wp = rp.work_precision(df)[("billiards.head_on", "")]
    fig_b64 = rp.plot_work_precision(wp)
    p = tmp_path / "wp.png"
    p.write_bytes(base64.b64decode(fig_b64))
    img = mpimg.imread(p)
    assert img.shape[1] >= 900  # wide enough to read at 100 %
    # the engine colour is in the picture (the frontier lines are drawn in it)
    rgb = np.array([int(rp.engine_colour("mujoco")[i:i + 2], 16) / 255 for i in (1, 3, 5)])
    assert (np.abs(img[..., :3] - rgb).max(axis=-1) < 0.02).sum() > 100


# --- the browser ------------------------------------------------------------------


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


class DevTools:
    """Chromium's DevTools protocol over ``--remote-debugging-pipe``:
    JSON messages separated by NUL bytes on fds 3 (to the browser) and 4
    (from it)."""

    def __init__(self, exe: str, profile: Path):
        to_r, to_w = os.pipe()
        from_r, from_w = os.pipe()
        # move the browser's ends above fd 10, so that dup2 onto 3 and 4 cannot clobber them
        hi_r, hi_w = fcntl.fcntl(to_r, fcntl.F_DUPFD, 10), fcntl.fcntl(from_w, fcntl.F_DUPFD, 10)
        os.close(to_r)
        os.close(from_w)

        def child() -> None:
            os.dup2(hi_r, 3)
            os.dup2(hi_w, 4)

        self.proc = subprocess.Popen(
            [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--disable-extensions", f"--user-data-dir={profile}", "--remote-debugging-pipe", "about:blank"],
            preexec_fn=child, pass_fds=(3, 4), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(hi_r)
        os.close(hi_w)
        self.w, self.r = to_w, from_r
        self.buf = b""
        self.next_id = 0
        self.events: list[dict] = []

    def _read(self, deadline: float) -> dict:
        while b"\0" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.r], [], [], left)[0]:
                raise TimeoutError("no message from the browser")
            chunk = os.read(self.r, 1 << 20)
            if not chunk:
                raise EOFError("the browser closed its pipe")
            self.buf += chunk
        msg, _, self.buf = self.buf.partition(b"\0")
        return json.loads(msg)

    def send(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 60):
        self.next_id += 1
        msg = {"id": self.next_id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        os.write(self.w, json.dumps(msg).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            m = self._read(deadline)
            if m.get("id") == self.next_id:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m["result"]
            self.events.append(m)

    def wait_event(self, method: str, timeout: float = 60) -> dict:
        deadline = time.monotonic() + timeout
        for i, m in enumerate(self.events):
            if m.get("method") == method:
                return self.events.pop(i)
        while True:
            m = self._read(deadline)
            if m.get("method") == method:
                return m
            self.events.append(m)

    def close(self) -> None:
        try:
            self.send("Browser.close", timeout=10)
        except Exception:
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self.w)
        os.close(self.r)


def open_page(exe: str, url: str, profile: Path, width: int = 1280, height: int = 900) -> dict:
    """Open ``url``; returns console errors, exceptions, log errors, the
    page's facts (sections, images decoded) and screenshots (PNG bytes)."""
    dt = DevTools(exe, profile)
    try:
        target = dt.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        sess = dt.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        for dom in ("Page", "Runtime", "Log"):
            dt.send(f"{dom}.enable", session=sess)
        dt.send("Emulation.setDeviceMetricsOverride", {"width": width, "height": height, "deviceScaleFactor": 1,
                                                        "mobile": False}, session=sess)
        dt.send("Page.navigate", {"url": url}, session=sess)
        dt.wait_event("Page.loadEventFired")
        facts = json.loads(dt.send("Runtime.evaluate", {"expression": """JSON.stringify({
            sections: [...document.querySelectorAll('section')].map(s => s.id),
            images: [...document.images].map(i => ({alt: i.alt, ok: i.complete && i.naturalWidth > 0,
                                                   w: i.naturalWidth, shown: i.getBoundingClientRect().width})),
            glanceBottom: document.querySelector('#at-a-glance') ?
                document.querySelector('#at-a-glance').getBoundingClientRect().bottom : -1,
            scrollWidth: document.documentElement.scrollWidth})""", "returnByValue": True},
                                   session=sess)["result"]["value"])
        shot = base64.b64decode(dt.send("Page.captureScreenshot", {"format": "png"}, session=sess)["data"])
        full = base64.b64decode(dt.send("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True},
                                        session=sess)["data"])
        errors = []
        for m in dt.events:
            p = m.get("params", {})
            if m.get("method") == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                errors.append(json.dumps(p.get("args"))[:300])
            elif m.get("method") == "Runtime.exceptionThrown":
                errors.append(json.dumps(p.get("exceptionDetails"))[:4000])
            elif m.get("method") == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                errors.append(p["entry"].get("text", "")[:300])
        return {"errors": errors, "facts": facts, "shot": shot, "full": full}
    finally:
        dt.close()


@pytest.fixture(scope="module")
def chromium():
    exe = _chromium()
    if exe is None:
        pytest.skip("no Chromium on this machine (.ci/run installs Debian's chromium package; here apt-get "
                    "was unavailable or failed)")
    return exe


def test_browser_catches_console_errors(chromium, tmp_path):
    # the harness must be able to fail: a page that logs an error and throws
    bad = tmp_path / "bad.html"
    bad.write_text("<!DOCTYPE html><html><body><p>x</p><script>console.error('planted');"
                   "throw new Error('boom')</script></body></html>")
    got = open_page(chromium, bad.as_uri(), tmp_path / "profile")
    assert any("planted" in e for e in got["errors"]) and any("boom" in e for e in got["errors"])


def test_report_in_headless_chromium(chromium, tmp_path):
    import matplotlib.image as mpimg

    plant(tmp_path)
    out = tmp_path / "report.html"
    assert rp.report_main(tmp_path, out=out) == 0
    got = open_page(chromium, out.as_uri(), tmp_path / "profile")
    assert got["errors"] == []
    f = got["facts"]
    assert f["sections"][0] == "at-a-glance" and set(SECTIONS) <= set(f["sections"])
    page = out.read_text()
    n_img = page.count("<img ")
    assert len(f["images"]) == n_img == 5  # work-precision x3, breaking points x2, no history yet
    assert all(i["ok"] and i["w"] > 300 for i in f["images"]), f["images"]
    # plots are shown at (nearly) their natural size: readable at 100 % zoom
    assert all(i["shown"] >= 0.7 * min(i["w"], 1200) for i in f["images"]), f["images"]
    assert f["scrollWidth"] <= 1280  # nothing forces a horizontal scroll
    assert 0 < f["glanceBottom"] <= 900 * 1.5  # At a glance fits about one screen
    for name, png in (("shot", got["shot"]), ("full", got["full"])):
        p = tmp_path / f"{name}.png"
        p.write_bytes(png)
        img = mpimg.imread(p)
        assert img.shape[1] >= 1200
        assert float(img[..., :3].var()) > 1e-3, f"{name} screenshot is blank"
    if os.environ.get("PHYSBENCH_KEEP_SCREENSHOTS"):  # for a human look at legibility
        d = Path(os.environ["PHYSBENCH_KEEP_SCREENSHOTS"])
        d.mkdir(parents=True, exist_ok=True)
        (d / "report_top.png").write_bytes(got["shot"])
        (d / "report_full.png").write_bytes(got["full"])
