"""Mutable simulation state and the per-step scratch context.

:class:`State` is what the engine advances: positions ``x`` (n, 3) m,
orientations ``q`` (n, 4) unit quaternions wxyz, linear velocities ``v``
(n, 3) m/s and angular velocities ``w`` (n, 3) rad/s, both world frame about
the centre of mass, time ``t`` (s), and caches (warm-start impulses).

:class:`Context` carries everything one (mini-)step computes and throws away:
the candidate end state the integrator produces (``x1``, ``q1``, ``v``, ``w``
with a world row at index n), the free-flight velocities, force
accumulators, the rotation and world inverse inertia at the start pose,
broad-phase pairs, contacts, and the time-of-impact event found by the CCD
stage.  All arrays are allocated once, at build.
"""

from __future__ import annotations

from collections import namedtuple
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from numba import njit

from physbench.engine.flight import begin_step
from physbench.engine.geometry import EndPose
from physbench.engine.pack import KeptPack, Pack
from physbench.engine.contact.scratch import Scratch
from physbench.engine.control import Event, EventMode, Impacts, TimeOfImpact
from physbench.engine.model import Model

if TYPE_CHECKING:
    from physbench.engine.collision.dispatch import Collider
    from physbench.engine.geometry import Geometry


@dataclass(eq=False)
class State:
    x: np.ndarray
    q: np.ndarray
    v: np.ndarray
    w: np.ndarray
    t: float = 0.0
    steps: int = 0
    #: the warm-start cache the last solve left (engine.solver.WarmCache),
    #: None to start cold
    warm: Any = None
    #: the step's scratch context (engine.state.Context), made by the first
    #: step (engine.pipeline.context) and kept with the state
    ctx: Any = field(default=None, repr=False)

    @classmethod
    def from_model(cls, model: Model) -> "State":
        x, q, v, w = model.x0.copy(), model.q0.copy(), model.v0.copy(), model.w0.copy()
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        return cls(x=np.array(x, float), q=np.array(q, float),
                   v=np.array(v, float), w=np.array(w, float))


@dataclass(eq=False)
class Contacts:
    """Contact rows, one per contact point.  ``a`` body index, ``b`` body
    index or n (the world) for statics, ``sidx`` static index or -1,
    ``normal`` (m, 3) unit vector from a toward b, ``point`` (m, 3) world
    point midway between the surfaces, ``gap`` (m,) signed distance (m,
    negative = penetration), ``fid`` (m,) feature ids for warm starting,
    ``e``, ``mus``, ``muk`` (m,) pair coefficients, ``mur`` (m,) the pair's
    rolling-friction coefficient (m)."""

    a: np.ndarray
    b: np.ndarray
    sidx: np.ndarray
    normal: np.ndarray
    point: np.ndarray
    gap: np.ndarray
    fid: np.ndarray
    e: np.ndarray | None = None
    mus: np.ndarray | None = None
    muk: np.ndarray | None = None
    mur: np.ndarray | None = None

    @property
    def m(self) -> int:
        return int(self.a.shape[0])

    @classmethod
    def empty(cls) -> "Contacts":
        z = np.zeros(0, np.int64)
        return cls(z, z, z, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), z,
                   np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))

    @classmethod
    def concat(cls, parts: list["Contacts"]) -> "Contacts":
        parts = [p for p in parts if p.m]
        if not parts:
            return cls.empty()
        if len(parts) == 1:
            return parts[0]
        fields = ("a", "b", "sidx", "normal", "point", "gap", "fid")
        if all(p.e is not None for p in parts):
            fields += ("e", "mus", "muk", "mur")
        return cls(*(np.concatenate([getattr(p, f) for p in parts]) for f in fields))

    def take(self, idx: np.ndarray) -> "Contacts":
        return Contacts(*(None if getattr(self, f) is None else getattr(self, f)[idx] for f in
                          ("a", "b", "sidx", "normal", "point", "gap", "fid", "e", "mus", "muk", "mur")))


@dataclass(eq=False)
class CcdKept:
    """What the CCD and impact stages keep in a context between calls, each
    made on first use or at build (``engine.ccd.CCD.prime``) by
    engine/ccd_kept.py and engine/ccd.py: the model's ``geometry`` as
    writable copies and as one Pack (``geometry_pack``), the ``collider``
    their collision calls run into, the missed-impact candidates' flags
    ``cand`` (>= m,) bool, the followed pair's collision arguments
    ``pair_query`` by (a, b, static index), the rotations' buffer ``R``
    (n, 3, 3), the gap kernel's work rows ``gap_work`` (>= m, 5), and the
    time-of-impact reruns' stages ``rerun`` (the step's stage list, the
    stages a rerun runs)."""

    geometry: Geometry | None = None
    geometry_pack: Pack | None = None
    collider: Collider | None = None
    cand: np.ndarray | None = None
    pair_query: dict[tuple[int, int, int], tuple] = field(default_factory=dict)
    R: np.ndarray | None = None
    gap_work: np.ndarray | None = None
    rerun: tuple | None = None


class Context:
    """Per-step scratch (see module docstring).  Shapes: ``x1`` (n, 3), ``q1``
    (n, 4), ``v``/``w`` (n+1, 3) working velocities with the world row n kept
    at zero, ``v_free``/``w_free`` (n, 3) free-flight end velocities,
    ``u_lin``/``u_ang`` (n, 3) the mean velocities over the step (displacement
    / h) of the free flight, ``F``/``T`` (n, 3) force and torque
    accumulators, ``R0`` (n, 3, 3) rotations at the start pose, ``Iinv0``
    (n+1, 3, 3) world inverse inertia at the start pose."""

    def __init__(self, model: Model):
        n = model.n
        self.h = model.h
        self.x1 = np.zeros((n, 3))
        self.q1 = np.zeros((n, 4))
        self.v = np.zeros((n + 1, 3))
        self.w = np.zeros((n + 1, 3))
        self.v_free = np.zeros((n, 3))
        self.w_free = np.zeros((n, 3))
        self.u_lin = np.zeros((n, 3))
        self.u_ang = np.zeros((n, 3))
        self.F = np.zeros((n, 3))
        self.T = np.zeros((n, 3))
        self.R0 = np.zeros((n, 3, 3))
        self.Iinv0 = np.zeros((n + 1, 3, 3))
        self._inv_I = np.array(model.inv_inertia_body[:n], float)
        # evaluation point for force stages (arrays of shape (n, 3)/(n, 4))
        self.ex = self.x1
        self.eq = self.q1
        self.ev = self.v[:n]
        self.ew = self.w[:n]
        self.eR: np.ndarray | None = None
        # pseudo velocities (split-impulse position correction), world row n
        self.vp = np.zeros((n + 1, 3))
        self.wp = np.zeros((n + 1, 3))
        # the step's mean torque (integrator weights), for the
        # energy-conserving rotation stage
        self.T_mean = np.zeros((n, 3))
        self.profile = None
        self._kept = KeptPack()
        #: how the solve treats impacts in this (mini-)step
        self.event_mode = EventMode.EVENT
        # collision products
        self.pairs_i = np.zeros(0, np.int64)
        self.pairs_j = np.zeros(0, np.int64)
        self.static_pairs_body = np.zeros(0, np.int64)
        self.static_pairs_static = np.zeros(0, np.int64)
        self.sweep = np.zeros(n)  # per-body bound on the distance a surface point moves in the step (m)
        self.plane_pairs = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        self.sbox_pairs = (np.zeros(0, np.int64), np.zeros(0, np.int64))
        self.impacts: Impacts | None = None  # the solve's impact rows
        self.contacts = None  # type: Contacts | None
        self.rows: Any = None  # solver rows (solver.Rows)
        self.reuse_contacts = False
        self.event: Event | None = None  # the CCD stage's earliest impact
        # friction stops (solver.Rows.stop_times): the earliest time (s)
        # within the step at which a sliding or rolling contact came to rest,
        # and whether the solver looks for one in this (mini-)step
        self.stop: float | None = None
        self.stop_allowed = False
        # pair codes whose missed impact had no time to it in this substep
        # (pipeline._substep; ccd.missed_impacts skips them)
        self.missed_skip: set[int] = set()
        self.toi: TimeOfImpact | None = None  # the last time-of-impact search's result
        # the impact rows of the step being searched (ccd.refine_toi): the
        # reruns leave out exactly these, at every tau
        self.drop_rows: np.ndarray | None = None
        # the warm-start cache the (mini-)step began with, which the step
        # loop may restore (pipeline._substep): the solve stores into others
        self.warm0: Any = None
        #: the step loop's plan of this context's pipeline (engine.pipeline.Plan,
        #: made by its first step)
        self.plan: Any = None
        #: what the CCD and impact stages keep between calls
        self.ccd = CcdKept()
        #: the CCD stage's end-pose check's buffers (engine.ccd.end_pose_pairs:
        #: moved pairs i, j, body-plane, body-static-box pairs (int64), end
        #: displacements (n,), end rotations (n, 3, 3)), grown geometrically
        self._end_pose = self._end_pose_buffers(n, 2 * n + 16)
        self._end_pose_pack = KeptPack()
        #: no sweep (n,) zeros: a margin that is the same for every pair
        self.no_sweep = np.zeros(n)
        #: the contact solve's work arrays (grown geometrically, kept)
        self.scratch = Scratch()

    @staticmethod
    def _end_pose_buffers(n: int, m: int) -> EndPose:
        i = np.empty(m, np.int64)
        return EndPose(ci=i, cj=i.copy(), cbp=i.copy(), cpk=i.copy(), cbs=i.copy(), csk=i.copy(), sw=np.empty(n),
                       R1=np.empty((n, 3, 3)))

    def end_pose_buffers(self, m: int) -> EndPose:
        """The CCD end-pose check's buffers (see ``_end_pose``) for at most
        ``m`` pairs of each kind: kept, grown geometrically."""
        buf = self._end_pose
        if buf.ci.shape[0] < m:
            buf = self._end_pose = self._end_pose_buffers(buf.sw.shape[0], max(m, 2 * buf.ci.shape[0]))
        return buf

    def end_pose_kept(self, m: int) -> tuple:
        """(:meth:`end_pose_buffers`, the same as one Pack, kept while they
        stay)."""
        buf = self.end_pose_buffers(m)
        # (keyed by the buffers' tuple: a new one when a buffer grows)
        return buf, self._end_pose_pack.of((buf,), lambda: Pack(buf))

    def kept(self, state: State) -> Pack:
        """The arrays of a (mini-)step's start and commit as one Pack (see
        engine/pack.py): the state's x, q, v, w, the body inverse inertias
        and the context's x1, q1, v, w, F, T, vp, wp, R0, Iinv0; kept while
        the state's arrays are the same objects (the context's never
        change)."""
        # (keyed by the state's four arrays: the context's are never rebound)
        return self._kept.of((state.x, state.q, state.v, state.w), lambda: Pack(StepArrays(
            x=state.x, q=state.q, v=state.v, w=state.w, inv_I=self._inv_I, x1=self.x1, q1=self.q1, V=self.v,
            W=self.w, F=self.F, T=self.T, vp=self.vp, wp=self.wp, R0=self.R0, Iinv0=self.Iinv0)))

    def commit(self, state: State) -> None:
        """The state's pose and velocities set to the candidate end state
        (x1, q1, v, w without the world row): one compiled call."""
        _commit_packed(self.kept(state))

    def begin(self, model: Model, state: State, h: float) -> None:
        """Start a (mini-)step of length ``h`` from ``state``."""
        self.h = h
        # x1, q1, v, w from the state; F, T, vp, wp zeroed; R0 and
        # I_world^-1 = R diag(1/I) R^T (world row zero): one compiled call
        _begin_packed(self.kept(state))
        self.reset(state, h)

    def reset(self, state: State, h: float) -> None:
        """The Python side of :meth:`begin` (a compiled caller that began
        the step itself calls only this)."""
        self.h = h
        self.event = None
        self.impacts = None
        self.stop = None
        self.stop_allowed = False
        # force stages first evaluate at the start state
        self.ex, self.eq, self.ev, self.ew = state.x, state.q, state.v, state.w
        self.eR = self.R0


#: a (mini-)step's start and commit arrays (:meth:`Context.kept`): the
#: state's pose and velocities ``x`` (n, 3), ``q`` (n, 4), ``v``, ``w`` (n,
#: 3), the body inverse inertias ``inv_I`` (n, 3), the context's candidate
#: end pose ``x1``, ``q1``, velocities ``V``, ``W`` (n+1, 3), forces and
#: torques ``F``, ``T``, pseudo velocities ``vp``, ``wp`` (n+1, 3), start
#: rotations ``R0`` (n, 3, 3) and inverse world inertias ``Iinv0`` (n+1, 3, 3)
StepArrays = namedtuple("StepArrays", ("x", "q", "v", "w", "inv_I", "x1", "q1", "V", "W", "F", "T", "vp", "wp", "R0",
                                       "Iinv0"))


@njit(cache=True)
def _begin_packed(k):
    """:func:`engine.flight.begin_step` over :meth:`Context.kept`'s arrays."""
    b = k.items
    begin_step(b.x, b.q, b.v, b.w, b.inv_I, b.x1, b.q1, b.V, b.W, b.F, b.T, b.vp, b.wp, b.R0, b.Iinv0)


@njit(cache=True)
def _commit_packed(k):
    """x, q, v, w = x1, q1, V[:n], W[:n] over :meth:`Context.kept`'s arrays
    (copies: the same bits)."""
    b = k.items
    x, q, v, w, x1, q1, V, W = b.x, b.q, b.v, b.w, b.x1, b.q1, b.V, b.W
    for i in range(x.shape[0]):
        for c in range(3):
            x[i, c] = x1[i, c]
            v[i, c] = V[i, c]
            w[i, c] = W[i, c]
        for c in range(4):
            q[i, c] = q1[i, c]


@njit(cache=True)
def record_packed(kb, k, rec_on, pos, quat, vel, angvel):
    """The state after a step (the context's kept pack ``kb``, as
    :func:`_commit_packed`'s) into row ``k`` of the record blocks (pos,
    vel, angvel (n, n_bodies, 3), quat (n, n_bodies, 4)) when ``rec_on``."""
    if rec_on:
        b = kb.items
        x, q, v, w = b.x, b.q, b.v, b.w
        for i in range(x.shape[0]):
            for c in range(3):
                pos[k, i, c] = x[i, c]
                vel[k, i, c] = v[i, c]
                angvel[k, i, c] = w[i, c]
            for c in range(4):
                quat[k, i, c] = q[i, c]
