"""pymunk (Chipmunk2D) adapter: planar scenes only.

pymunk 7.3.1 is a 2D engine.  A planar physbench scene lives in the world x-z
plane; the single conversion between world and engine state is
:func:`contract.conventions.planar_from_world` (at build) and
:func:`contract.conventions.world_from_planar` (in :meth:`read_state`):
2D x = world x, 2D y = world z, 2D counter-clockwise angular velocity w =
world angular velocity (0, -w, 0).  A body's local frame maps the same way:
body-local (x, z) is the 2D body-local (x, y), so a capsule or cylinder (axis
= body z) points along the 2D local y axis at angle 0.

Mass properties
    mass = ``Body.mass`` and moment = ``Body.inertia[1]`` (kg m^2), the 3D
    body's principal moment about its y axis.  This is exact, not an
    approximation: planar validation allows only rotations about y, so the
    body's y axis stays the world y axis, and for w = (0, w_y, 0) the angular
    momentum is L = R I R^T w = I_yy w (y is a principal axis; w x I w = 0).
    The 2D shape's own area moment would be wrong for the 3D body: a sphere
    (2/5 m r^2) is not a disc (1/2 m r^2), and a cylinder lying along z has
    I_yy = m (3 r^2 + 4 h^2) / 12, not the rectangle's m (4 r^2 + 4 h^2) / 12.
    Shapes are therefore given no mass or density of their own.

Shapes (the x-z cross-section through the body centre, which contains every
support point of the body in x-z directions, so contacts are those of the 3D
body): sphere -> ``Circle``; box -> ``Poly`` box 2a x 2c (half_extents x, z);
capsule -> ``Segment`` (0, -h)..(0, h) of radius r; cylinder -> ``Poly`` box
2r x 2h.

Statics: a plane (and a slope, which the Scene has already turned into a
plane) is a static ``Poly`` quad, 2 km along the plane's line and 1 km deep
on its solid side.  A zero-radius ``Segment`` would be two-sided: a body whose
centre sank past the line (fast impact, large dt) would be pushed out through
the wrong side.  The thick polygon keeps the solid side solid; measured bounce
ratios and resting overlaps equal those on a segment.  (A segment with a 1 km
radius below the line behaves the same but leaves a ~1e-14 rad spurious spin
on a resting circle from rounding at the 1 km lever arm; the polygon gives 0.)
A static box is a static ``Poly`` of its x-z cross-section.

Materials: pymunk combines a pair as the *product* of the two shapes'
elasticity and of their friction.  The adapter solves for per-material shape
values whose products give every pair the scene asks for
(:meth:`Scene.pair`), e.g. sqrt(v) when all pairs agree.  This needs no Python
callback.  Only when no per-shape solution exists does it register a
``pre_solve`` callback per material pair that sets ``arbiter.friction`` and
``arbiter.restitution`` to the exact pair value (exact, but one Python call per
touching pair per step; recorded in notes and stages).

Effects: ``gravity`` -> ``space.gravity``; without ``contact`` bodies get no
shapes at all (no broad or narrow phase runs: cheaper than shapes filtered
with ``ShapeFilter(categories=0)``, with the same physics: nothing collides);
``restitution``/``friction`` absent -> the Scene's pair values are 0;
``spring``/``damper`` -> ``DampedSpring``; ``drag_linear`` -> pymunk's own
``space.damping`` = e^(-c1 / m) where every body shares c1 / m and none spins
(:func:`adapters.forces.pymunk_damping`), else, and for ``drag_quadratic``,
a force F = -(c1 + c2 |v|) v on the centre of mass set before each engine
step (the row says so: notes, info["drag"]); ``joint`` -> Chipmunk
constraints (:mod:`adapters.pymunk_joints`); ``gyroscopic`` and
``rolling_friction`` are unsupported.

Integration order (Chipmunk): each step first moves positions with the old
velocities, x' = x + v dt, then detects contacts at x', then updates
velocities v' = v + (g + F/m) dt and solves contact and joint impulses.  Free
fall from rest therefore gives z_k = -g dt^2 k (k - 1) / 2 (10 steps of 0.01 s:
-0.044145 m), v_k = -g k dt.  Overlap is removed by a separate bias velocity
that moves positions but never enters the reported velocity; overlap below
``collision_slop`` is never removed.

Sibling modules: settings, capabilities and shapes in
:mod:`adapters.pymunk_scene`, the batched reads through pymunk's public API
in :mod:`adapters.pymunk_batch`, the private shortcuts (direct
``cpSpaceStep``, the allocation-free state reader) in
:mod:`adapters.pymunk_internals`, material factors in
:mod:`adapters.materials`, the drag law in :mod:`adapters.forces`.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from physbench.adapters import bare_loops
from physbench.adapters.base import (Adapter, Capabilities, Unsupported, module_version, optional_import,
                                     planar_gyroscopic_reason)
from physbench.adapters.forces import DRAG_EXTERNAL, DRAG_NOTE, dragged, pymunk_damping
from physbench.adapters.materials import per_material_factors
from physbench.adapters.pymunk_batch import ArbiterBatch, PublicBodyBatch
from physbench.adapters.pymunk_joints import add_joints
from physbench.adapters.pymunk_internals import BodyReader, c_stepper
from physbench.adapters.planar import planar_geometry_reason
from physbench.adapters.pymunk_scene import body_shape, declaration, static_shape
from physbench.contract.conventions import planar_from_world, world_from_planar, world_point_to_planar
from physbench.contract.scene import Scene

ENGINE = "pymunk"

GYROSCOPIC_REASON = planar_gyroscopic_reason("pymunk")
ROLLING_FRICTION_REASON = "pymunk has no rolling resistance (rolling_friction)"


class PymunkAdapter(Adapter):
    """Adapter for pymunk 7.x (2D, planar scenes in the world x-z plane)."""

    name = ENGINE

    # ---- declaration -------------------------------------------------------
    @classmethod
    def capabilities(cls) -> Capabilities:
        pm, why = optional_import("pymunk", "pymunk.batch")
        return declaration(ENGINE, pm.version if pm is not None else module_version("pymunk"), pm is not None, why)

    @classmethod
    def unsupported_reason(cls, scene: Scene) -> str | None:
        reason = super().unsupported_reason(scene)
        if reason is not None:
            if cls.capabilities().available and scene.planar:
                # give the specific reason rather than the generic 'cannot model'
                if "gyroscopic" in scene.effects:
                    return GYROSCOPIC_REASON
                if "rolling_friction" in scene.effects:
                    return ROLLING_FRICTION_REASON
            return reason
        return planar_geometry_reason(scene, "pymunk")

    # ---- life cycle --------------------------------------------------------
    def build(self, scene: Scene, settings: dict[str, Any]) -> None:
        reason = self.unsupported_reason(scene)
        if reason is not None:
            raise Unsupported(reason)
        pm, _ = optional_import("pymunk", "pymunk.batch")
        self._pm = pm
        n = scene.n_bodies
        dt = float(settings["dt"])
        self._substeps = int(settings["substeps"])
        self._h = dt / self._substeps

        space = pm.Space()
        space.iterations = int(settings["iterations"])
        space.collision_slop = float(settings["collision_slop"])
        space.collision_bias = float(settings["collision_bias"])
        space.damping = 1.0  # no hidden velocity damping
        space.sleep_time_threshold = math.inf  # no sleeping: body order and states stay live
        space.gravity = world_point_to_planar(scene.gravity)  # (g_x, g_z); (0, 0) without 'gravity'
        self._space = space

        # -- bodies ---------------------------------------------------------
        contact = scene.has("contact")
        self._contact = contact
        self._bodies = []
        body_shapes = []
        for b in scene.bodies:
            (x, y), (vx, vy), angle, w = planar_from_world(b.position, b.velocity, b.orientation,
                                                           b.angular_velocity)
            body = pm.Body(mass=float(b.mass), moment=float(b.inertia[1]))
            body.position = (x, y)
            body.angle = angle
            body.velocity = (vx, vy)
            body.angular_velocity = w
            shape = body_shape(pm, body, b) if contact else None
            space.add(body)
            if shape is not None:
                space.add(shape)
                body_shapes.append((b.material, shape))
            self._bodies.append(body)

        static_shapes = []
        if contact:
            for s in scene.statics:
                shape = static_shape(pm, space.static_body, s)
                shape.physbench_static = s.index  # adapters.contact_forces reads it
                space.add(shape)
                static_shapes.append((s.material, shape))

        # -- materials ------------------------------------------------------
        self._material_mode = "none"
        if contact:
            self._setup_materials(scene, body_shapes, static_shapes)

        # -- springs and dampers --------------------------------------------
        self._n_springs = 0
        for sp in scene.springs:
            if sp.stiffness == 0.0 and sp.damping == 0.0:
                continue  # effect(s) absent: the Scene zeroed it
            ba = space.static_body if sp.a < 0 else self._bodies[sp.a]
            bb = space.static_body if sp.b < 0 else self._bodies[sp.b]
            # body-frame anchor (x, y, z) -> 2D body-local (x, z); world anchors
            # map the same way onto the static body (at the origin, angle 0).
            c = pm.DampedSpring(ba, bb, world_point_to_planar(sp.anchor_a), world_point_to_planar(sp.anchor_b),
                                float(sp.rest_length), float(sp.stiffness), float(sp.damping))
            space.add(c)
            self._n_springs += 1
        if self._n_springs and scene.has("damper"):
            self.notes.append(
                "damper: pymunk's DampedSpring damps the relative velocity along the spring line "
                "and integrates that damping as an exact exponential decay over each step")

        # -- joints (adapters/pymunk_joints.py) --------------------------------
        if scene.joints:
            add_joints(pm, space, scene, self._bodies, self.notes, self.info)

        # -- drag -------------------------------------------------------------
        # pymunk's damping where it carries the linear drag, else the force law
        # (tests/test_adapter_pymunk.py::test_linear_drag_is_pymunk_damping)
        damping, why = pymunk_damping(scene)
        if damping is not None:
            self._space.damping = damping
            self.info["drag"] = "pymunk's space.damping = e^(-c_linear / m)"
            self.notes.append(f"linear drag: pymunk's space.damping = e^(-c_linear / m) = {damping:.9g} (the velocity "
                              "is scaled by damping^dt each step, the exact decay of m v' = -c_linear v)")
        self._drag = [] if damping is not None else [(self._bodies[i], c1, c2) for i, c1, c2 in dragged(scene)]
        if self._drag:
            self.info["drag"] = f"{DRAG_EXTERNAL} ({why})"
            self.notes.append(f"{DRAG_NOTE} ({why})")

        self.notes.append(
            "pymunk integrates positions with the velocity from before the step (x' = x + v dt, "
            "then v' = v + a dt): free fall from rest gives z_k = -g dt^2 k (k - 1) / 2")

        # -- fast stepping and state reads -------------------------------------
        self._c_step, self._c_space_step = c_stepper(space, self._bodies) or (None, None)
        self._setup_reader(n)
        # (space.static_body only where static shapes made it: reading it
        # creates a body, which the batch reader would then visit)
        self._arbiters = ArbiterBatch(pm.batch, space, self._bodies + ([space.static_body] if static_shapes else []))
        self._space_steps = 0
        self.info.update({
            "material_mode": self._material_mode,
            "moment_of_inertia": "Body.inertia[1] (I_yy of the 3D body)",
            "state_reader": self._reader_kind,
        })

    def _setup_materials(self, scene: Scene, body_shapes: list, static_shapes: list) -> None:
        """Give shapes elasticity/friction so that pymunk's products equal the
        Scene's pair values (:func:`adapters.materials.per_material_factors`),
        or install exact pre_solve callbacks where no such values exist."""
        shapes = body_shapes + static_shapes
        f = per_material_factors(scene, [m for m, _ in body_shapes], [m for m, _ in static_shapes], ENGINE)
        if f is None:
            return
        self.notes.extend(f.notes)
        if f.per_shape:
            self._material_mode = "per_shape"
            for m, shape in shapes:
                shape.elasticity = f.elasticity.get(m, 0.0)
                shape.friction = f.friction.get(m, 0.0)
            return
        self._material_mode = "pre_solve_callback"
        ctype = {m: k + 1 for k, m in enumerate(sorted({m for m, _ in shapes}))}
        for m, shape in shapes:
            shape.collision_type = ctype[m]
            shape.elasticity = 0.0
            shape.friction = 0.0
        for (a, b), v in f.pairs.items():
            self._space.on_collision(ctype[a], ctype[b], pre_solve=_pair_setter(v.restitution, v.friction))
        self.notes.append(
            "materials: no per-shape elasticity/friction reproduces every pair value as a product; "
            "exact pair values are set in a Python pre_solve callback per touching pair per step")


    def _setup_reader(self, n: int) -> None:
        """Batched reads of every body's state: the public
        ``pymunk.batch.get_space_bodies`` (its order and layout verified by
        :class:`adapters.pymunk_batch.PublicBodyBatch`), or its
        allocation-free twin :class:`adapters.pymunk_internals.BodyReader`
        when pymunk's internals allow."""
        self._public = PublicBodyBatch(self._pm.batch, self._space, self._bodies)
        try:
            self._c_each = BodyReader(self._space, self._public.fields, self._public.buf, self._pm.batch,
                                      self._public.total, n)
            self._reader_kind = "c_batch"
        except Exception:  # pragma: no cover - depends on pymunk internals
            self._c_each, self._reader_kind = None, "public_batch"

    def _stepper(self) -> tuple[Any, Any]:
        """(step function, its first argument): cpSpaceStep or Space.step."""
        return (self._c_step, self._c_space_step) if self._c_step is not None else (_call_step, self._space)

    def step(self, n: int = 1) -> None:
        """Advance n physbench steps (n * substeps engine steps of dt/substeps)."""
        st, cs = self._stepper()
        h = self._h
        k = n * self._substeps
        if self._drag:
            drag = self._drag
            for _ in range(k):
                for body, c1, c2 in drag:
                    v = body.velocity
                    f = -(c1 + c2 * math.hypot(v.x, v.y))
                    body.force = (f * v.x, f * v.y)
                st(cs, h)
        else:
            for _ in range(k):
                st(cs, h)
        self._space_steps += k

    def bare_loop(self, n: int) -> None:
        """The engine's public step call in a plain loop: space.step(dt)."""
        if self._drag or self._substeps != 1:
            return self.step(n)
        st, h = self._space.step, self._h
        for _ in range(n):
            st(h)
        self._space_steps += n

    bare_record = bare_loops.pymunk

    def step_record(self, n: int, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Step n times, the C batch reader appending each step's raw
        (x, y, angle, vx, vy, w) rows to one block buffer
        (:meth:`BodyReader.record`); then convert the whole block once with
        the conversion point world_from_planar (vectorised over steps and
        bodies), also the complete steps before an exception."""
        if self._c_each is None:
            return super().step_record(n, pos, quat, vel, angvel)
        simple = not self._drag and self._substeps == 1
        once = functools.partial(*self._stepper(), self._h) if simple else functools.partial(self.step, 1)
        try:
            self._c_each.record(n, once)
        finally:
            k, c = self._c_each.last_block  # (6, k steps, bodies)
            self.block_done = k
            if simple:
                self._space_steps += k
            world_from_planar(c[0], c[1], c[3], c[4], c[2], c[5], pos[:k].transpose(2, 0, 1),
                              quat[:k].transpose(2, 0, 1), vel[:k].transpose(2, 0, 1),
                              angvel[:k].transpose(2, 0, 1))

    def read_state(self, pos: np.ndarray, quat: np.ndarray, vel: np.ndarray, angvel: np.ndarray) -> None:
        """Write world positions (n, 3) m, quaternions (n, 4) wxyz, linear
        velocities (n, 3) m/s and angular velocities (n, 3) rad/s, in place.

        One batched engine read, then one vectorised call of the conversion
        point world_from_planar on the transposed (column) views."""
        c = self._c_each.read() if self._c_each is not None else self._public.read()
        world_from_planar(c[0], c[1], c[3], c[4], c[2], c[5], pos.T, quat.T, vel.T, angvel.T)

    def stages(self) -> dict[str, Any]:
        """Engine features switched on for this scene, and step counters."""
        if not hasattr(self, "_space"):
            return {}
        sp = self._space
        return {
            "gravity": tuple(sp.gravity) != (0.0, 0.0),
            "contact": self._contact,
            "material_mode": self._material_mode,
            "springs": self._n_springs,
            "drag_bodies": len(self._drag),
            "substeps": self._substeps,
            "iterations": sp.iterations,
            "collision_slop": sp.collision_slop,
            "space_steps": self._space_steps,
        }

    def contacts(self) -> np.ndarray:
        """The touching arbiters' contact points after the last step, read in
        one batched call (``pymunk.batch.get_space_arbiters``): point midway
        between point_a and point_b, depth = -distance, normal from the
        lower-indexed body toward the other body or the static (as
        ``Body.each_arbiter`` from the bodies in order orients it); 2D
        (x, y) -> world (x, 0, y).

        The batch visits every cached arbiter, also those kept for a few
        steps after their shapes separated; those report a contact count of
        0 and are left out
        (tests/test_adapter_pymunk.py::test_batched_contacts_equal_each_arbiter)."""
        c = self._arbiters.contact_rows()  # (k, 5): 2D point, 2D normal, depth
        out = np.zeros((len(c), 7))
        out[:, [0, 2, 3, 5, 6]] = c  # 2D (x, y) -> world (x, 0, y), as world_from_planar maps positions
        return out

    def close(self) -> None:
        # Drop references (the reader's views first); cffi frees the space and its bodies.
        self._c_each = self._public = self._arbiters = self._bodies = None
        self._drag = []


# ---- helpers ------------------------------------------------------------------


def _call_step(space: Any, h: float) -> None:
    space.step(h)


def _pair_setter(elasticity: float, friction: float):
    """A pre_solve callback that sets the arbiter's pair coefficients."""

    def pre_solve(arbiter: Any, space: Any, data: Any) -> None:
        # pymunk 7 names the pair value Arbiter.restitution; an attribute
        # 'elasticity' set on the arbiter would be silently ignored.
        arbiter.restitution = elasticity
        arbiter.friction = friction

    return pre_solve
