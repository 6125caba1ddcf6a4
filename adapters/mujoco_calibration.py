"""Restitution calibration for MuJoCo's soft contacts.

MuJoCo has no coefficient of restitution: a contact is a spring-damper in
acceleration space set by ``solref``.  We use the *direct* form
``solref = (-K, -B)`` (K: stiffness in 1/s^2, B: damping in 1/s; both
mass-normalised, so the same pair values serve any masses) and find, by a
small 1-D MuJoCo simulation and a root find, the (K, B) whose bounce ratio
equals the requested coefficient e.

Why numerics and not a formula: the damped-oscillator formula
e = exp(-pi z / sqrt(1 - z^2)) ignores the one-sided force (a damped contact
releases before the spring is relaxed), the impedance ``solimp``, gravity
acting during the contact, and the time discretisation (the contact lasts
only ~10 steps).  Measured on mujoco 4.0.1 along the path below (s in [0, 1],
contact_steps 10, implicitfast, dt 1 ms to 1/240 s, averaged over eight impact
phases) the formula is off by up to 0.15 in e, worst near damping ratio 0.7
(formula 0.03, MuJoCo 0.18); see ENGINE_NOTES.md.

The calibration model is a sphere on a plane along one axis, frictionless
(condim 1), stepped with the scene's dt, integrator and speculative flag.

The parameter path
------------------
One parameter s in [0, 2) moves monotonically from "elastic" to "plastic":

- s in [0, 1]: K = K0 = (pi / (contact_steps * dt))^2, B = s * B_max.
  K0 makes an undamped contact last about ``contact_steps`` steps (a half
  period pi/omega of the nominal spring); B_max = 0.8/dt keeps B*dt < 1 so
  the explicit damping term never overshoots (measured: B*dt > ~1.1 makes the
  bounce *grow* again and B*dt > 2 blows up).
- s in (1, 2): B = B_max, K = K0 * (2 - s)^2.  A heavily damped contact
  stops the approach within ~2 steps; the spring then pushes the bodies apart
  at a speed of about (omega/B)^2 times the approach speed, so softening K
  drives the bounce toward 0.  Without gravity this is the only way to reach
  e < ~0.1 (a one-sided spring-damper never stops dead); with gravity e = 0
  is reached already at s <= 1.

e = 0 is taken as "bounce ratio <= ZERO_TOL at the scene's impact and at
sixteen step phases", at the largest K (least resting sag) that achieves it,
and never with less than B_max damping.

Impact phase
------------
The discrete contact starts at a random fraction of a step, and for a
contact of ~10 steps that moves e by about +-(0.2 * B * dt) (measured:
+-0.014 at e 0.86, +-0.033 at e 0.57, +-0.045 at e 0.19).  When the scene
predicts its impact (``gap`` given: the initial normal gap and approach
speed), the calibration replays that approach step for step, so the phase
matches the scene's first impact.  Otherwise it averages over eight phases
and calibrates the average.  ``phase_spread``/``phase_mean`` report e over
sixteen phases at the chosen solref either way: later impacts of a scene
land at other phases.  e(phase) is a sawtooth with its maximum where the
contact begins at a step boundary (measured, e 0.9 at 4.4 m/s, dt 1 ms:
0.873..0.902), so a calibration to a first impact near that boundary leaves
later impacts up to ~3 % low; at e 0.5 the spread is about +-8 %.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass

import numpy as np

try:  # imported lazily so that a missing mujoco only affects mujoco runs
    import mujoco
except ImportError:  # pragma: no cover - exercised only without mujoco
    mujoco = None

#: e at or below this counts as "no bounce" (the tests allow 0.02).
ZERO_TOL = 0.005
#: B_max * dt: the largest damping per step (see module docstring).
DAMPING_STEP = 0.8
#: relative tolerance of the root find on e (well inside the 2 % target).
REL_TOL = 0.002
#: fallback impact speed (m/s) when the scene predicts no impact.
FALLBACK_SPEED = 1.0
#: the approach replay gives up (and averages phases) beyond this many steps.
MAX_APPROACH_STEPS = 200_000
#: impact phases (fraction of a step) averaged over when the scene gives none
_PHASES = tuple((k + 0.5) / 8 for k in range(8))
#: phases sampled for the reported scatter
_SPREAD_PHASES = tuple(k / 16 for k in range(16))
_RADIUS = 0.1  # calibration sphere radius (m); the result does not depend on it


@dataclass(frozen=True)
class Calibration:
    """Result of one calibration.

    ``requested``/``achieved`` are bounce ratios (separation / approach normal
    speed at the touching distance); ``solref`` is MuJoCo's direct form
    (-K [1/s^2], -B [1/s]); ``speed`` (m/s) the impact speed calibrated at;
    ``gravity`` (m/s^2) the gravity component pressing the pair together;
    ``phase_mode`` 'scene' (the scene's own approach replayed) or
    'averaged'; ``phase_spread`` (min, max) and ``phase_mean`` of e over
    sixteen impact phases at the chosen solref (what impacts at other
    phases get); ``penetration`` (m) the deepest overlap in the
    calibration run; ``s`` the path parameter (see module docstring).
    """

    requested: float
    achieved: float
    residual: float
    solref: tuple[float, float]
    speed: float
    gravity: float
    dt: float
    integrator: str
    contact_steps: float
    phase_mode: str
    phase_spread: tuple[float, float]
    phase_mean: float
    penetration: float
    s: float
    evaluations: int

    def as_dict(self) -> dict:
        d = asdict(self)
        d["solref"] = list(self.solref)
        d["phase_spread"] = list(self.phase_spread)
        return d


def path_solref(s: float, dt: float, contact_steps: float) -> tuple[float, float]:
    """Direct solref (-K, -B) at path parameter s in [0, 2) (see module doc)."""
    k0 = (math.pi / (contact_steps * dt)) ** 2
    bmax = DAMPING_STEP / dt
    if s <= 1.0:
        return (-k0, -s * bmax)
    return (-k0 * (2.0 - s) ** 2, -bmax)


_XML = """<mujoco model="restitution_calibration">
  <compiler inertiafromgeom="false"/>
  <option timestep="{dt!r}" gravity="0 0 {g!r}" integrator="{integrator}">
    <flag speculative="{spec}"/>
  </option>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1" contype="0" conaffinity="0"/>
    <body name="ball" pos="0 0 1">
      <freejoint/>
      <inertial pos="0 0 0" mass="1" diaginertia="0.004 0.004 0.004"/>
      <geom name="ball" type="sphere" size="{r!r}" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <contact>
    <pair geom1="floor" geom2="ball" condim="1" solref="-1 -1"/>
  </contact>
</mujoco>"""

INTEGRATORS = {"euler": "Euler", "rk4": "RK4", "implicit": "implicit", "implicitfast": "implicitfast"}


class _Bouncer:
    """A sphere on a plane; measures the bounce ratio for a given solref."""

    def __init__(self, dt: float, gravity: float, integrator: str, speculative: bool):
        xml = _XML.format(dt=float(dt), g=-float(gravity), integrator=INTEGRATORS[integrator],
                          spec="enable" if speculative else "disable", r=_RADIUS)
        self.m = mujoco.MjModel.from_xml_string(xml)
        self.d = mujoco.MjData(self.m)
        self.dt = float(dt)
        self.g = float(gravity)
        self.evaluations = 0

    def approach(self, gap: float, v0: float) -> tuple[float, float] | None:
        """Replay the approach from normal gap ``gap`` (m) at normal speed
        ``v0`` (m/s, > 0 toward the plane); return (gap, speed toward) one
        step before the first penetrating state, or None if it never comes."""
        m, d = self.m, self.d
        mujoco.mj_resetData(m, d)
        d.qpos[2] = _RADIUS + gap
        d.qvel[2] = -v0
        prev = (gap, v0)
        for _ in range(MAX_APPROACH_STEPS):
            mujoco.mj_step(m, d)
            z = d.qpos[2] - _RADIUS
            if z <= 0.0:
                return prev
            prev = (z, -d.qvel[2])
            if -d.qvel[2] <= 0.0 and self.g <= 0.0:
                return None
        return None

    def bounce(self, solref: tuple[float, float], gap: float, v: float, max_steps: int) -> tuple[float, float]:
        """(bounce ratio, max penetration) starting ``gap`` above the plane at
        ``v`` toward it.  Speeds are taken at the touching height, the flight
        in between converted by energy (v^2 + 2 g h is conserved in flight)."""
        m, d = self.m, self.d
        self.evaluations += 1
        m.pair_solref[0] = solref
        mujoco.mj_resetData(m, d)
        d.qpos[2] = _RADIUS + gap
        d.qvel[2] = -v
        v_in = math.sqrt(v * v + 2.0 * self.g * gap)
        deepest = 0.0
        still = 0
        for _ in range(max_steps):
            mujoco.mj_step(m, d)
            h = d.qpos[2] - _RADIUS
            vz = d.qvel[2]
            if not (math.isfinite(h) and math.isfinite(vz)):
                return math.inf, math.inf
            if h < 0.0:
                deepest = max(deepest, -h)
                # resting under gravity: too slow to climb out of the overlap
                still = still + 1 if self.g > 0.0 and vz * vz < 2.0 * self.g * -h * 1e-2 else 0
                if still >= 20:
                    return 0.0, deepest
            elif vz > 0.0:  # clear of the plane and leaving
                return math.sqrt(vz * vz + 2.0 * self.g * h) / v_in, deepest
        # still in contact: resting under gravity, or creeping out without
        vz = d.qvel[2]
        return (max(vz, 0.0) / v_in if self.g <= 0.0 else 0.0), deepest


def _evaluate(b: _Bouncer, s: float, starts: list[tuple[float, float]], dt: float,
              contact_steps: float) -> tuple[float, float, list[float]]:
    solref = path_solref(s, dt, contact_steps)
    # long enough for the slowest (softest, most damped) contact to creep out
    k = -solref[0]
    omega = math.sqrt(k)
    t_c = max(math.pi / omega, -solref[1] / k)  # half period, or damped creep time B/K
    max_steps = int(min(6.0 * t_c / dt + 50 * contact_steps + 200, 20_000))
    es, pens = [], []
    for gap, v in starts:
        e, p = b.bounce(solref, gap, v, max_steps)
        es.append(e)
        pens.append(p)
    return float(np.mean(es)), float(max(pens)), es


def _key(x: float, sig: int = 6) -> float:
    return float(f"{x:.{sig}g}")


def calibrate(e: float, dt: float, speed: float, gravity: float = 0.0, gap: float | None = None,
              integrator: str = "implicitfast", contact_steps: float = 10.0,
              speculative: bool = False) -> Calibration:
    """Find the direct solref that gives bounce ratio ``e`` in [0, 1].

    ``speed`` (m/s): the impact speed; if ``gap`` (m) is given, ``speed`` is
    instead the initial normal approach speed at that gap (the scene's own
    approach is replayed, see module docstring).  ``gravity`` (m/s^2): the
    gravity component pressing the pair together (0 for two free bodies).
    Cached: repeated calls with the same arguments cost nothing.
    """
    return _calibrate(_key(min(max(e, 0.0), 1.0)), _key(dt), _key(speed), _key(max(gravity, 0.0)),
                      None if gap is None else _key(gap, 9), integrator, _key(contact_steps),
                      bool(speculative))


@functools.lru_cache(maxsize=512)
def _calibrate(e: float, dt: float, speed: float, gravity: float, gap: float | None,
               integrator: str, contact_steps: float, speculative: bool) -> Calibration:
    if mujoco is None:  # pragma: no cover
        raise RuntimeError("mujoco is not installed")
    b = _Bouncer(dt, gravity, integrator, speculative)
    starts: list[tuple[float, float]] | None = None
    mode = "averaged"
    if gap is not None:
        pre = b.approach(gap, speed)
        if pre is not None and pre[1] ** 2 + 2.0 * gravity * pre[0] > 1e-12:
            starts = [pre]
            mode = "scene"
            v_imp = math.sqrt(pre[1] ** 2 + 2.0 * gravity * pre[0])
    if starts is None:
        v_imp = speed if (gap is None and speed > 0) else FALLBACK_SPEED
        starts = [(v_imp * dt * (2.0 + ph), v_imp) for ph in _PHASES]
        # the speed at touch is v_imp; start so that it is, under gravity too
        starts = [(h, math.sqrt(max(v_imp * v_imp - 2.0 * gravity * h, 0.0))) for h, _ in starts]

    cache: dict[float, tuple[float, float, list[float]]] = {}

    def f(s: float) -> float:
        if s not in cache:
            cache[s] = _evaluate(b, s, starts, dt, contact_steps)
        return cache[s][0]

    grid = [0.0, 0.02, 0.05, 0.1, 0.15, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0,
            1.2, 1.4, 1.6, 1.75, 1.85, 1.92, 1.96, 1.98, 1.99]
    target = e
    if e <= ZERO_TOL:
        # no bounce: at least B_max damping, then the stiffest K that stops
        # it at the scene's impact *and* at every sampled step phase (an
        # inelastic contact must stay inelastic on later impacts too)
        zstarts = list(starts) + [(h, math.sqrt(max(v_imp * v_imp - 2.0 * gravity * h, 0.0)))
                                  for h in (v_imp * dt * (2.0 + ph) for ph in _SPREAD_PHASES)]
        zcache: dict[float, float] = {}

        def fz(s: float) -> float:
            if s not in zcache:
                zcache[s] = max(_evaluate(b, s, zstarts, dt, contact_steps)[2])
            return zcache[s]

        lo, hi = None, None
        for s in grid:
            if s < 1.0:
                continue
            if fz(s) <= ZERO_TOL:
                hi = s
                break
            lo = s
        if hi is None:
            s_best = min(zcache, key=lambda s: zcache[s])
        elif lo is None:
            s_best = hi
        else:
            for _ in range(12):
                mid = 0.5 * (lo + hi)
                if fz(mid) <= ZERO_TOL:
                    hi = mid
                else:
                    lo = mid
            s_best = hi
    else:
        prev = None
        s_best = None
        for s in grid:
            val = f(s)
            if val - target <= 0.0:
                if prev is None:
                    s_best = s  # even s = 0 bounces less than asked
                else:
                    lo, hi = prev, s
                    for _ in range(40):
                        mid = 0.5 * (lo + hi)
                        fm = f(mid) - target
                        if abs(fm) <= REL_TOL * target * 0.5:
                            lo = hi = mid
                            break
                        if fm > 0:
                            lo = mid
                        else:
                            hi = mid
                    cand = (lo, hi)
                    s_best = min(cand, key=lambda x: abs(f(x) - target))
                break
            prev = s
        if s_best is None:
            s_best = min(cache, key=lambda s: abs(cache[s][0] - target))
    achieved, pen, _ = cache[s_best] if s_best in cache else _evaluate(b, s_best, starts, dt, contact_steps)
    solref = path_solref(s_best, dt, contact_steps)
    # scatter over impact phases at the chosen solref
    ph_starts = [(v_imp * dt * (2.0 + ph), v_imp) for ph in _SPREAD_PHASES]
    ph_starts = [(h, math.sqrt(max(v_imp * v_imp - 2.0 * gravity * h, 0.0))) for h, _ in ph_starts]
    _, _, ph_es = _evaluate(b, s_best, ph_starts, dt, contact_steps)
    return Calibration(
        requested=e, achieved=achieved, residual=achieved - e, solref=(float(solref[0]), float(solref[1])),
        speed=float(v_imp), gravity=gravity, dt=dt, integrator=integrator, contact_steps=contact_steps,
        phase_mode=mode, phase_spread=(float(min(ph_es)), float(max(ph_es))),
        phase_mean=float(np.mean(ph_es)), penetration=pen,
        s=float(s_best), evaluations=b.evaluations,
    )
