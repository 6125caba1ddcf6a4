"""Coulomb friction on an incline: a sliding/sticking block and a rolling or
slipping sphere.

The slope is the scene's ``slope`` static (normal n = (sin a, 0, cos a),
downhill d = (cos a, 0, -sin a)), or a level ``plane`` as the flat case
(a = 0, n = +z, d the direction of the body's initial horizontal velocity,
+x if it has none); gravity g acts along -z, so along the slope
the driving acceleration is g_d = g . d = |g| sin a and the normal load per
unit mass is g_n = -g . n = |g| cos a.  Coefficients are the body-slope pair's
(static mu_s, kinetic mu_k).

Block (``incline_block``), starting at rest:

    tan a <= mu_s :  sticks, a = 0
    tan a >  mu_s :  slides, a = g (sin a - mu_k cos a)

(with an initial velocity along the slope the block slides with
a = g sin a -+ mu_k g cos a until it stops, then the static test applies).

Sphere (``rolling_sphere``), radius R, moment of inertia I about a diameter,
k = I / (m R^2) (2/5 for a solid sphere), starting at rest: rolling without
slipping needs the friction force f = m g sin a k / (1 + k) to stay within
mu_s m g cos a:

    mu_s >= tan a k / (1 + k)  (2/7 tan a) :  rolls,
        a = g sin a / (1 + k)  (5/7 g sin a),  alpha = a / R
    otherwise :  slips with kinetic friction,
        a = g (sin a - mu_k cos a),  alpha = mu_k m g cos a R / I

(alpha is the angular acceleration about e = n x d, the axis a ball rolling
downhill spins about).

Measured accelerations are least-squares slopes of the velocity along d
(and of the angular velocity about e) over the run after its first 10 %
(contacts settle in the first steps).

Modules: ``slope`` (the slope and coefficients every model but the spin
reads, and the window of the acceleration fits), ``sliding`` (``incline_block``,
``slide_to_rest``), ``rolling`` (``rolling_sphere``, ``rolling_cylinder``,
``rolling_resistance``), ``spin`` (``spin_to_rest``).  This package
re-exports the model classes (the registry, contract/models.py, names them
here).
"""

from __future__ import annotations

from physbench.harness.references.friction.rolling import RollingCylinder, RollingResistance, RollingSphere
from physbench.harness.references.friction.sliding import InclineBlock, SlideToRest
from physbench.harness.references.friction.spin import SpinToRest
