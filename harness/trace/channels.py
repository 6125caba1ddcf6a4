"""Rerun entity paths and time-indexed scalar series: the pieces the trace
writer and the diagnosis annotations both log with."""

from __future__ import annotations

import numpy as np
import rerun as rr

from physbench.contract.scene import Body

#: children of an engine's entity that are not bodies
RESERVED_CHILDREN = ("static", "status", "contacts", "engine_contacts", "joints")


def entity_part(name: str) -> str:
    return rr.escape_entity_path_part(name)


def body_entity(engine_path: str, body: Body) -> str:
    """Entity path of ``body`` under ``engine_path``."""
    name = body.name if body.name not in RESERVED_CHILDREN else f"{body.name}_body"
    return f"{engine_path}/{entity_part(name)}"


def joint_entity(engine_path: str, joint) -> str:
    """Entity path of ``joint`` (contract.scene_model.Joint) under
    ``engine_path``: ``<engine_path>/joints/<joint name>``."""
    return f"{engine_path}/joints/{entity_part(joint.name)}"


def time_columns(steps: np.ndarray, t: np.ndarray) -> list[rr.TimeColumn]:
    return [rr.TimeColumn("step", sequence=steps), rr.TimeColumn("sim_time", duration=t)]


def send_scalars(rec: rr.RecordingStream, path: str, steps: np.ndarray, t: np.ndarray, y: np.ndarray) -> None:
    ok = np.isfinite(y)
    if not ok.any():
        return
    if not ok.all():
        steps, t, y = steps[ok], t[ok], y[ok]
    rec.send_columns(path, indexes=time_columns(steps, t), columns=rr.Scalars.columns(scalars=y))
