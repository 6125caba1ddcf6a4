"""Drake's engine settings: the plant's time step, the discrete contact
approximation, the contact model, the continuous-time integrator and its
accuracy, and the point-contact parameters (adapters.drake)."""

from __future__ import annotations

from physbench.adapters.base import DT_SETTING, Setting

#: error-controlled integrators of the continuous-time plant (time_step = 0)
INTEGRATORS = ("runge_kutta3", "runge_kutta5", "bogacki_shampine3", "implicit_euler", "radau3",
               "velocity_implicit_euler")


def settings() -> dict[str, Setting]:
    """Drake's engine settings with their defaults (``physbench engines``)."""
    return {
        "dt": DT_SETTING,
        "time_step": Setting("time_step", -1.0, float, "plant time step (s); -1: dt; 0: continuous "
                             "time with the error-controlled integrator", lo=-1.0, hi=1.0),
        # similar: Drake's documented choice where strong transients matter
        # (impacts); lagged (Drake's default) weakly couples friction and sticks
        # a block that should slide under the heavy dissipation that realises
        # e = 0 (friction.block_slides: error 0.999 lagged, 0.0022 similar)
        "approximation": Setting("approximation", "similar", str, "discrete contact approximation",
                                 choices=("similar", "lagged", "sap", "tamsi")),
        # auto: hydroelastic (Drake's default model) except where the scene
        # asks for restitution, which only point contact's calibrated
        # dissipation realises.  Box stacks need it: a box-box pair's point
        # contact is one point, and column_5 drifts 0.48 m with it, 0.5 mm
        # hydroelastic (docs/ENGINE_FINDINGS.md)
        "contact_model": Setting("contact_model", "auto", str, "point; hydroelastic_with_fallback (point "
                                 "contact where a pair has no hydroelastic model); auto: point when the scene "
                                 "has restitution, else hydroelastic_with_fallback",
                                 choices=("auto", "point", "hydroelastic_with_fallback")),
        "integrator": Setting("integrator", "runge_kutta3", str, "integrator when time_step = 0",
                              choices=INTEGRATORS),
        "accuracy": Setting("accuracy", 1e-3, float, "integrator target accuracy when time_step = 0",
                            lo=1e-12, hi=1.0),
        "contact_steps": Setting("contact_steps", 10.0, float, "contact stiffness as the duration in dt of "
                                 "an undamped impact: k = m_eff (pi / (contact_steps dt))^2", lo=1.0, hi=1000.0),
        "point_stiffness": Setting("point_stiffness", 0.0, float, "point-contact stiffness of every body "
                                   "(N/m); 0: m (pi / (contact_steps dt))^2", lo=0.0, hi=1e15),
        "dissipation": Setting("dissipation", -1.0, float, "Hunt-Crossley dissipation of every body (s/m; "
                               "tamsi/similar/lagged/continuous); -1: calibrated to the restitution",
                               lo=-1.0, hi=1e6),
        "hydroelastic_modulus": Setting("hydroelastic_modulus", 1e7, float, "hydroelastic modulus of "
                                        "the bodies (Pa)", lo=1e3, hi=1e12),
    }
