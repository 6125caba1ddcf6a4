"""JUnit XML of a check's outcomes."""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET
from pathlib import Path

from physbench.harness.conformance.verdicts import ERROR, FAIL, UNSUPPORTED, XFAIL, XPASS, Outcome, case_names, fmt_measured
from physbench.harness.results import write_text_atomic


def junit_xml(outcomes: list[Outcome]) -> ET.ElementTree:
    """JUnit XML: one <testsuite> per engine; testcase name
    '<scenario>[<variant>]::<metric>', unique in its suite (the bound added
    where one metric is checked twice: :func:`case_names`), classname 'physbench.<engine>.<family>'.
    FAIL -> <failure>; ERROR -> <error>; XPASS -> <failure> 'unexpected pass';
    XFAIL -> <skipped> 'xfail: reason'; UNSUPPORTED -> <skipped>.  A
    testcase with a trace (check --traces) carries it as
    ``<property name="trace" value="PATH"/>`` and a ``trace: PATH`` line in
    ``<system-out>``."""
    root = ET.Element("testsuites", name="physbench conformance")
    by_engine: dict[str, list[Outcome]] = {}
    for o in outcomes:
        by_engine.setdefault(o.engine, []).append(o)
    totals = dict(tests=0, failures=0, errors=0, skipped=0)
    names = {id(o): n for o, n in zip(outcomes, case_names(outcomes))}
    for eng, outs in by_engine.items():
        counts = dict(tests=len(outs),
                      failures=sum(o.outcome in (FAIL, XPASS) for o in outs),
                      errors=sum(o.outcome == ERROR for o in outs),
                      skipped=sum(o.outcome in (XFAIL, UNSUPPORTED) for o in outs))
        t = sum(o.time_s for o in outs)
        suite = ET.SubElement(root, "testsuite", name=eng, time=f"{t:.3f}",
                              **{k: str(v) for k, v in counts.items()})
        for k in totals:
            totals[k] += counts[k]
        for o in outs:
            family = o.scenario.split(".")[0]
            tc = ET.SubElement(suite, "testcase", name=names[id(o)], classname=f"physbench.{eng}.{family}",
                               time=f"{o.time_s:.3f}")
            if o.trace:
                props = ET.SubElement(tc, "properties")
                ET.SubElement(props, "property", name="trace", value=o.trace)
            if o.outcome == FAIL:
                ET.SubElement(tc, "failure", message=o.message, type="FAIL").text = _detail(o)
            elif o.outcome == XPASS:
                ET.SubElement(tc, "failure", message=o.message, type="XPASS").text = _detail(o)
            elif o.outcome == ERROR:
                ET.SubElement(tc, "error", message=o.message, type="ERROR").text = _detail(o)
            elif o.outcome in (XFAIL, UNSUPPORTED):
                ET.SubElement(tc, "skipped", message=o.message, type=o.outcome)
            if o.trace:
                ET.SubElement(tc, "system-out").text = f"trace: {o.trace}"
    for k, v in totals.items():
        root.set(k, str(v))
    return ET.ElementTree(root)


def _detail(o: Outcome) -> str:
    return f"metric {o.metric}: value {fmt_measured(o.value, o.bounds)}, threshold {o.threshold}\n{o.message}"


def write_junit(outcomes: list[Outcome], path: str | Path) -> None:
    tree = junit_xml(outcomes)
    ET.indent(tree)
    buf = io.BytesIO()
    tree.write(buf, encoding="utf-8", xml_declaration=True)
    write_text_atomic(buf.getvalue().decode("utf-8"), path)
