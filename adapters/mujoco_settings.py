"""MuJoCo's engine settings as physbench exposes them (adapters/mujoco.py
and adapters/mjx.py): names, defaults, bounds and what each means."""

from __future__ import annotations

from physbench.adapters.base import DT_SETTING, Setting
from physbench.adapters.mjcf import INTEGRATORS

_CONES = ("pyramidal", "elliptic")


def mujoco_settings() -> dict[str, Setting]:
    """MuJoCo's settings, their defaults and bounds (``physbench engines``);
    the MJX adapter takes them too, less what MJX lacks."""
    return {
        "dt": DT_SETTING,
        # implicitfast: MuJoCo's recommended integrator.  It is semi-implicit
        # Euler with the velocity-dependent forces (tendon dampers here)
        # integrated implicitly, so stiff dampers stay stable, at the cost of
        # Euler for free bodies (no Coriolis derivatives).  RK4 conserves
        # torque-free rotation far better (ENGINE_NOTES: Dzhanibekov energy
        # drift 0 % vs -14.5 %) but costs ~3x per step; sweeps vary it.
        "integrator": Setting("integrator", "implicitfast", str,
                              "MuJoCo integrator (mjtIntegrator)", choices=tuple(INTEGRATORS)),
        # elliptic: the true circular Coulomb cone (the pyramidal one is a
        # linearised approximation) and measurably less stick creep
        # (ENGINE_NOTES: 5.1 mm vs 9.1 mm over 5 s on a 20 deg slope).
        "cone": Setting("cone", "elliptic", str, "friction cone (mjtCone)", choices=_CONES),
        "impratio": Setting("impratio", 1.0, float,
                            "ratio of frictional to normal constraint impedance (MuJoCo default 1; "
                            "larger -> less slip when sticking)", lo=1.0, hi=1e6),
        "noslip_iterations": Setting("noslip_iterations", 0, int,
                                     "noslip post-solver iterations (MuJoCo default 0)", lo=0, hi=10000),
        "iterations": Setting("iterations", 100, int,
                              "main constraint solver iterations (MuJoCo default 100)", lo=1, hi=100000),
        "speculative": Setting("speculative", False, bool,
                               "MuJoCo 4.0 speculative contacts (mjENBL_SPECULATIVE): contacts are "
                               "created before touching, which stops tunnelling", ),
        "contact_steps": Setting("contact_steps", 10.0, float,
                                 "contact stiffness, as the duration in time steps of an undamped "
                                 "impact: K = (pi / (contact_steps * dt))^2.  Fewer steps: stiffer, "
                                 "less penetration, more scatter of the bounce with the impact "
                                 "phase (see adapters/mujoco_calibration.py)", lo=2.0, hi=1000.0),
        "restitution_phase": Setting("restitution_phase", "first_impact", str,
                                     "what the restitution calibration matches: 'first_impact' replays "
                                     "the scene's predicted first impact of each pair group (speed and "
                                     "step phase), 'averaged' the mean over eight step phases at the "
                                     "predicted impact speed", choices=("first_impact", "averaged")),
    }
