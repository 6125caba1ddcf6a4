"""MJX adapter: MuJoCo's JAX port (mujoco-mjx 3.17 on jax's CPU backend).

The model is MuJoCo's: the same MJCF (:func:`adapters.mjcf.build_mjcf`),
the same per-pair restitution calibration (:func:`adapters.mujoco_impacts.
calibrate_pairs`, run on MuJoCo's C engine), compiled by MuJoCo and handed
to MJX with ``mjx.put_model``.  MJX runs it in float64 (``jax_enable_x64``,
set process-wide at import), so differences from MuJoCo are MJX's own
algorithms, not single precision.

Stepping
    ``step_record`` runs a block of up to BLOCK steps in one
    ``jax.lax.scan`` of ``mjx.step`` compiled once per model (a step i >= n
    of the block is skipped by ``lax.cond``, so any n <= BLOCK reuses the
    one compiled function); longer requests run several blocks.  Drag is a
    force from the velocity at the start of each step, written into
    ``xfrc_applied`` inside the scan (as the MuJoCo adapter does in Python).
    Compilation happens in :meth:`MjxAdapter.build` and its wall time is
    reported apart as ``jit_s``; compiled functions persist in JAX's
    compilation cache under ``$XDG_CACHE_HOME/physbench/jax`` (default
    ``~/.cache/physbench/jax``; ``PHYSBENCH_JAX_CACHE`` overrides), so a
    second process with the same model shape loads instead of compiling.
State
    As in MuJoCo: qpos [x y z qw qx qy qz], qvel [v (world), w (body)] per
    free body; the angular velocity is rotated to the world frame with the
    recorded quaternions (:func:`contract.rotation.quat_rotate`).
Batches
    ``build_batch``/``step_record_batch`` (``batched = True``) run W starts
    of one scene as one ``jax.vmap`` of the compiled scan over a leading
    world axis of the data; a model array that differs between the worlds
    (the reference pose; the restitution calibration replays each start's
    first impact) gets a world axis too; models of different structure are
    refused (NotOneBatch: the harness runs the worlds one at a time).  harness/batch.py hands such batches over
    (tests/test_batch.py: equal to the sequential MJX runs to 1e-12).
Contact forces
    Read only when a check asks for a contact-law metric
    (:func:`adapters.contact_forces.mjx_rows`, from the last step's raw
    ``efc_force`` off the device).  The runner then steps one step per
    call: each is one call of the compiled block (BLOCK scan iterations,
    all but one skipped), measured 2.8 ms a step against 0.26 ms inside a
    block on the resting cubes (a one-step function compiles in 17 s, so
    the block is kept); the read adds 0.18 ms a step.
Settings
    MuJoCo's, less what MJX does not implement: no noslip solver and no
    speculative contacts (both off).  ``ls_iterations``: MJX's line-search
    iterations.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from physbench.adapters.base import Adapter, Capabilities, Setting, Unsupported, module_version, not_installed
from physbench.adapters.forces import drag_coefficients
from physbench.adapters.mjx_batch import batched_models
from physbench.adapters.mjcf import build_mjcf
from physbench.adapters.mujoco_impacts import calibrate_pairs
from physbench.contract.rotation import quat_rotate, world_to_body_angvel
from physbench.contract.scene import Scene

ENGINE = "mjx"
#: steps per compiled scan block
BLOCK = 256
#: body shapes whose pairs MJX collides by its general convex routine
CONVEX_SHAPES = frozenset({"box", "cylinder"})
#: the most such body pairs a scene may have (MJX evaluates every pair every
#: step; XLA's compile grows with them): stacking.column_10, 10 boxes = 45
#: pairs, compiles in 193 s cold and steps in 7 ms; stacking.pyramid, 15
#: boxes = 105 pairs, steps in 52 ms with a warm compilation cache, but its
#: cold compile did not finish within 400 s on a loaded 2-core machine, nor
#: did the 28-box variant's (378 pairs)
#: (tests/test_adapter_mjx.py::test_too_many_convex_pairs_are_unsupported)
MAX_CONVEX_PAIRS = 100


def cache_dir() -> Path:
    """Where JAX's persistent compilation cache lives (never in the package)."""
    env = os.environ.get("PHYSBENCH_JAX_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "physbench" / "jax"


def _import():
    import logging

    logging.getLogger("absl").setLevel(logging.ERROR)
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_platforms", "cpu")
    jax.config.update("jax_compilation_cache_dir", str(cache_dir()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    from physbench.adapters.quiet import quiet_import

    mjx = quiet_import("mujoco.mjx")  # prints "Failed to import warp" without the GPU backend
    return jax, mjx


#: MuJoCo, JAX and MJX, imported by the first model built (:func:`_load`):
#: a suite's check reads this adapter's capabilities without them (JAX's
#: import is ~1 s of a sweep client's start-up)
jax = mjx = mujoco = None
#: '' when MuJoCo MJX and JAX are installed, else what is missing (nothing imported)
_MISSING = not_installed("mujoco-mjx", "jax")


def _load() -> None:
    """Import MuJoCo, JAX and MJX once (an ImportError here fails the run
    that needed them, with its reason)."""
    global jax, mjx, mujoco
    if mjx is None:
        import mujoco

        jax, mjx = _import()


def _settings() -> dict[str, Setting]:
    from physbench.adapters.mujoco_settings import mujoco_settings

    s = mujoco_settings()
    for name in ("noslip_iterations", "speculative"):
        del s[name]
    s["integrator"] = Setting("integrator", "implicitfast", str, "MJX integrator",
                              choices=("euler", "implicitfast", "rk4"))
    s["ls_iterations"] = Setting("ls_iterations", 50, int, "MJX line-search iterations (MuJoCo default 50)",
                                 lo=1, hi=10000)
    return s


class MjxAdapter(Adapter):
    """Adapter for MJX (MuJoCo in JAX, CPU, float64)."""

    name = ENGINE
    gyroscopic_always_on = "MJX"

    @classmethod
    def capabilities(cls) -> Capabilities:
        from physbench.adapters.mujoco import _EFFECTS, _SHAPES, _STATIC_SHAPES

        return Capabilities(
            engine=ENGINE, version=module_version("mujoco-mjx"), dimensions=3, shapes=_SHAPES,
            static_shapes=_STATIC_SHAPES, effects=_EFFECTS, settings=_settings(),
            available=not _MISSING, unavailable_reason=_MISSING,
            notes=("MuJoCo's model (same MJCF and restitution calibration) stepped by MJX in float64",
                   "compiled once per model shape: jit_s apart", "no noslip solver, no speculative contacts",
                   "batched: many starts of one scene in one vmap call (physbench ensemble)"))

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        why = super().unsupported_reason(scene)
        if why is not None:
            return why
        k = sum(b.shape in CONVEX_SHAPES for b in scene.bodies)
        pairs = k * (k - 1) // 2
        if pairs > MAX_CONVEX_PAIRS:
            return (f"MJX evaluates every body pair's collision every step: {k} boxes and cylinders make {pairs} "
                    f"convex pairs, beyond the {MAX_CONVEX_PAIRS} it compiles and runs in reasonable time on a "
                    f"2-core CPU (45 pairs: 193 s cold compile, 7 ms per step; 105 pairs: 52 ms per step, and a "
                    f"cold compile that did not finish within 400 s)")
        return None

    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        self._model(scene, settings)
        self._compile(self._block, self.dx)

    def _model(self, scene: Scene, settings: dict[str, Any]) -> None:
        """The MuJoCo model of ``scene`` on MJX (self.m, self.mx), its
        start as MJX data (self.dx) and the block function (not compiled)."""
        _load()
        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        self.scene, self.settings, self.n = scene, dict(settings), scene.n_bodies
        m, xml, meta = _mj_model(scene, settings, self.notes, self.info)
        self.xml, self.meta = xml, meta
        d = mujoco.MjData(m)
        n = self.n
        x0, q0, v0, w0 = scene.initial_state()
        qpos, qvel = d.qpos.reshape(n, 7), d.qvel.reshape(n, 6)
        qpos[:, 0:3], qpos[:, 3:7], qvel[:, 0:3] = x0, q0, v0
        qvel[:, 3:6] = world_to_body_angvel(q0, w0)
        mujoco.mj_forward(m, d)
        self.m = m
        try:
            self.mx = mjx.put_model(m)
        except NotImplementedError as e:
            raise Unsupported(f"MJX cannot model this scene: {e}") from None
        dx = mjx.put_data(m, d)
        # put_data keeps some int32 fields that mjx.step returns as int64 under
        # x64: cast to the step's own output types (traced, not compiled)
        shapes = jax.eval_shape(mjx.step, self.mx, dx)
        self.dx = jax.tree_util.tree_map(lambda a, s: jax.numpy.asarray(a, s.dtype), dx, shapes)
        c1, c2 = drag_coefficients(scene)
        drag = bool(np.any(c1 > 0) or np.any(c2 > 0))
        if drag:
            self.notes.append("drag is a force at the centre of mass from the velocity at the start of "
                              "each step (explicit, inside the scan); no drag torque")
        self._block = _block_fn(n, drag)
        self._c = (jax.numpy.asarray(c1 * meta["mass_scale"]), jax.numpy.asarray(c2 * meta["mass_scale"]))
        self._last = (x0, q0, v0, np.asarray(w0, float))
        self.steps = 0
        self._stages = {"engine": ENGINE, "integrator": settings["integrator"], "cone": settings["cone"],
                        "condim": meta["condim"], "explicit_pairs": meta["explicit_pairs"],
                        "mass_scale": meta["mass_scale"], "drag": drag, "block": BLOCK, "float64": True,
                        "restitution_calibrated": len(self.info.get("restitution_calibration", []))}

    def _compile(self, fn, dx) -> None:
        """Compile ``fn`` (a block function) for ``dx``; its wall time is jit_s."""
        jax.config.update("jax_compilation_cache_dir", str(cache_dir()))  # the environment of this run
        t0 = time.perf_counter()
        try:
            self._compiled = jax.jit(fn).lower(self.mx, dx, self._c, 0).compile()
        except NotImplementedError as e:
            raise Unsupported(f"MJX cannot model this scene: {e}") from None
        self.jit_s = time.perf_counter() - t0

    # ---- batched worlds: one vmap of the scan over the worlds' starts ------
    batched = True

    def build_batch(self, scenes: list[Scene], settings: dict[str, Any]) -> None:
        """W worlds of one model: the data of scenes[0] broadcast over a
        leading world axis with each world's qpos and qvel; the block
        function vmapped over it (one compile; jit_s).  Every other field
        of the data is recomputed from qpos and qvel by the first step."""
        self._model(scenes[0], settings)
        w, nb = len(scenes), self.n
        # each world's own model where its start changes it (MuJoCo's
        # restitution calibration replays each start's first impact): the
        # parameters that differ get a world axis
        mxs, differ = [self.mx], 0
        for sc in scenes[1:]:
            m, xml, _ = _mj_model(sc, settings, [], {})
            differ += xml != self.xml
            mxs.append(self.mx if xml == self.xml else mjx.put_model(m))
        mx_axes = None
        if differ:
            self.mx, mx_axes = batched_models(mxs)
            self.notes.append(f"{differ} of {w} worlds have their own model arrays (the start pose and the "
                              f"restitution calibration enter MuJoCo's model: batched fields); the model "
                              f"statistics (mean inertia, extent) are world 0's")
        qpos, qvel = np.empty((w, nb, 7)), np.empty((w, nb, 6))
        starts = []
        for k, sc in enumerate(scenes):
            x0, q0, v0, w0 = sc.initial_state()
            qpos[k, :, 0:3], qpos[k, :, 3:7], qvel[k, :, 0:3] = x0, q0, v0
            qvel[k, :, 3:6] = world_to_body_angvel(q0, w0)
            starts.append((x0, q0, v0, np.asarray(w0, float)))
        jnp = jax.numpy
        dxb = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (w,) + a.shape), self.dx)
        self.dx = dxb.replace(qpos=jnp.asarray(qpos.reshape(w, -1), dxb.qpos.dtype),
                              qvel=jnp.asarray(qvel.reshape(w, -1), dxb.qvel.dtype))
        self.worlds = w
        self._last_batch = tuple(np.stack([s[i] for s in starts]) for i in range(4))
        self._compile(jax.vmap(self._block, in_axes=(mx_axes, 0, None, None)), self.dx)
        self._stages["worlds"] = w
        self._stages["worlds_with_own_model"] = differ

    def read_state_batch(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        for out, src in zip((pos, quat, vel, angvel), self._last_batch):
            np.copyto(out, src)

    def step_record_batch(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray,
                          angvel: np.ndarray) -> None:
        """n steps of every world, BLOCK steps per compiled call; (W, n, nb, .) out."""
        w, nb, done = self.worlds, self.n, 0
        while done < n:
            k = min(BLOCK, n - done)
            self.dx, (qp, qv) = self._compiled(self.mx, self.dx, self._c, k)
            self.steps += k
            qp = np.asarray(qp)[:, :k].reshape(w, k, nb, 7)
            qv = np.asarray(qv)[:, :k].reshape(w, k, nb, 6)
            s = slice(done, done + k)
            pos[:, s], quat[:, s], vel[:, s] = qp[..., 0:3], qp[..., 3:7], qv[..., 0:3]
            quat_rotate(quat[:, s], qv[..., 3:6], out=angvel[:, s])
            done += k
        self._last_batch = (pos[:, n - 1], quat[:, n - 1], vel[:, n - 1], angvel[:, n - 1])

    def _run_block(self, n: int):
        """Advance n <= BLOCK steps; the (n, nq) and (n, nv) states after each."""
        self.dx, (qp, qv) = self._compiled(self.mx, self.dx, self._c, n)
        self.steps += n
        return np.asarray(qp)[:n], np.asarray(qv)[:n]

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """n steps in blocks of one compiled scan each; the block is
        converted to physbench's conventions at once."""
        self.block_done = 0
        nb = self.n
        while self.block_done < n:
            k = min(BLOCK, n - self.block_done)
            qp, qv = self._run_block(k)
            qp, qv = qp.reshape(k, nb, 7), qv.reshape(k, nb, 6)
            s = slice(self.block_done, self.block_done + k)
            pos[s], quat[s], vel[s] = qp[..., 0:3], qp[..., 3:7], qv[..., 0:3]
            quat_rotate(quat[s], qv[..., 3:6], out=angvel[s])
            self._last = (pos[s.stop - 1], quat[s.stop - 1], vel[s.stop - 1], angvel[s.stop - 1])
            self.block_done += k

    def step(self, n: int = 1) -> None:
        nb = self.n
        buf = [np.empty((n, nb, 3)), np.empty((n, nb, 4)), np.empty((n, nb, 3)), np.empty((n, nb, 3))]
        self.step_record(n, *buf)

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        for out, src in zip((pos, quat, vel, angvel), self._last):
            np.copyto(out, src)

    def stages(self) -> dict[str, Any]:
        out = dict(getattr(self, "_stages", {}))
        out["steps"] = getattr(self, "steps", 0)
        if hasattr(self, "jit_s"):
            out["jit_s"] = self.jit_s
        return out

    def close(self) -> None:
        self.mx = self.dx = self._compiled = None


def _mj_model(scene: Scene, settings: dict[str, Any], notes: list[str], info: dict[str, Any]):
    """(MjModel, MJCF text, MJCF meta) of ``scene``: MuJoCo's, whose
    restitution calibration replays the first impact of this start."""
    full = dict(settings, noslip_iterations=0, speculative=False)
    pair_solref = calibrate_pairs(scene, full, notes, info)
    xml, meta = build_mjcf(scene, full, pair_solref, notes, fluid_drag=False)
    m = mujoco.MjModel.from_xml_string(xml)
    m.opt.ls_iterations = int(settings["ls_iterations"])
    if settings["cone"] == "elliptic" and not np.any(m.geom_condim > 1) and not np.any(m.pair_dim > 1):
        # mujoco-mjx 3.17's elliptic-cone solver fails to trace without a
        # frictional contact (an empty float index array); without
        # friction both cones give the same constraint rows
        m.opt.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
        notes.append("no frictional contact: the cone is pyramidal (MJX 3.17 cannot trace its elliptic "
                     "solver without friction; the two are the same constraint without friction)")
    return m, xml, meta


def _block_fn(n_bodies: int, drag: bool):
    """(mx, dx, (c1, c2), n) -> (dx after n steps, (qpos, qvel) (BLOCK, nq|nv)):
    BLOCK iterations of a lax.scan, step i applied when i < n."""
    jnp, lax = jax.numpy, jax.lax

    def one(mx, dx, c):
        if drag:
            v = dx.qvel.reshape(n_bodies, 6)[:, 0:3]
            coef = c[0] + c[1] * jnp.sqrt(jnp.sum(v * v, axis=1))
            f = jnp.zeros((n_bodies + 1, 6)).at[1:, 0:3].set(-coef[:, None] * v)
            dx = dx.replace(xfrc_applied=f)
        return mjx.step(mx, dx)

    def block(mx, dx, c, n):
        def body(dx, i):
            dx = lax.cond(i < n, lambda d: one(mx, d, c), lambda d: d, dx)
            return dx, (dx.qpos, dx.qvel)

        return lax.scan(body, dx, jnp.arange(BLOCK))

    return block
