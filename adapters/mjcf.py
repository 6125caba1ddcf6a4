"""MJCF for a :class:`contract.scene.Scene`: the MuJoCo model the adapter
builds (layout in the module docstring of :mod:`adapters.mujoco`).  Every
float is written with ``repr`` (round-trips exactly); every name from the
scene goes through :func:`xml_escape`.  Pinned by
tests/test_adapter_mujoco.py and tests/test_fuzz.py (hostile names).
"""

from __future__ import annotations

import re
from collections import Counter
from typing import Any

import numpy as np

from physbench.contract.scene import Scene
from physbench.adapters.forces import mujoco_fluid

#: setting value -> MJCF <option integrator=...> (mjINT_EULER, mjINT_RK4, ...)
INTEGRATORS = {"euler": "Euler", "rk4": "RK4", "implicit": "implicit", "implicitfast": "implicitfast"}


def _f(x: float) -> str:
    """A float for MJCF, exactly (repr round-trips)."""
    return repr(float(x))


def _v(xs) -> str:
    return " ".join(_f(x) for x in xs)


def _pair_contact(mat, cal_solref: tuple[float, float]) -> tuple[int, tuple[float, ...], tuple[float, float]]:
    """(condim, friction 5-vector (slide, slide, torsion, roll, roll), solref)
    for a pair material: condim 1 frictionless, 3 sliding, 6 with rolling."""
    mu = float(mat.friction)
    roll = float(mat.rolling_friction)
    if roll > 0.0:
        condim = 6
    elif mu > 0.0:
        condim = 3
    else:
        condim = 1
    return condim, (mu, mu, 0.0, roll, roll), cal_solref


#: MuJoCo's compiler refuses a moving body whose mass or any principal
#: inertia is not above mjMINVAL (1e-15): "mass and inertia of moving bodies
#: must be larger than mjMINVAL" (mujoco 4.0.1; a 1e-9 kg sphere of radius
#: 1e-6 m has 4e-22 kg m^2, inside the spec bounds).  Below MASS_FLOOR the
#: model's masses are scaled up (:func:`mass_scale`).
MASS_FLOOR = 1e-12


def mass_scale(scene: Scene) -> float:
    """The factor k (a power of two, exact in binary) every mass, principal
    inertia (kg, kg m^2), spring stiffness and damping and drag coefficient
    of the MuJoCo model is multiplied by: 1 unless the scene's smallest mass
    or principal inertia is below MASS_FLOOR, then the least power of two
    that lifts it to MASS_FLOOR.  A uniform mass scale leaves the motion
    unchanged: gravity's force scales with the masses, MuJoCo's contact
    (solref) and friction constraints are mass-normalised, and the forces
    the adapter applies (springs, drag) are scaled by the same k.  Pinned by
    tests/test_fuzz.py::test_mujoco_runs_micrometre_bodies_with_a_mass_scale."""
    smallest = min((min(b.mass, *b.inertia) for b in scene.bodies), default=MASS_FLOOR)
    if smallest >= MASS_FLOOR:
        return 1.0
    return float(2.0 ** int(np.ceil(np.log2(MASS_FLOOR / smallest))))


def build_mjcf(scene: Scene, settings: dict[str, Any], pair_solref: dict[int, tuple[float, float]],
               notes: list[str], fluid_drag: bool = True) -> tuple[str, dict[str, Any]]:
    """The MJCF for ``scene`` with resolved ``settings`` and each contact
    pair's calibrated ``solref`` (by index into ``scene.contact_pairs()``);
    appends notes on what MuJoCo cannot model to ``notes``.  Returns (xml,
    meta: dynamic_contacts, explicit_pairs, condim, tendons, mass_scale
    (:func:`mass_scale`), fluid (:func:`adapters.forces.mujoco_fluid`'s
    parameters when MuJoCo's fluid model carries the drag, else None),
    fluid_refused (why it cannot, '' without drag)).  ``fluid_drag=False``
    never uses the fluid model (MJX: its implicitfast has none)."""
    dt = float(settings["dt"])
    mscale = mass_scale(scene)
    if mscale != 1.0:
        notes.append(f"masses, inertias, springs and drag are scaled by {mscale:g} in MuJoCo's model (the motion "
                     f"is unchanged): its compiler refuses a mass or principal inertia below mjMINVAL = 1e-15")
    integrator = settings["integrator"]
    fluid, fluid_refused = mujoco_fluid(scene, mscale)
    if not fluid_drag and fluid:
        fluid, fluid_refused = None, "MJX applies drag inside its scan, not through MuJoCo's fluid model"
    contact = scene.has("contact")
    pairs = scene.contact_pairs()

    # ---- pair signatures: majority on the geoms, the rest explicit ----------
    sigs: list[tuple[int, tuple[float, ...], tuple[float, float]]] = []
    for k, (ka, ia, kb, ib, mat) in enumerate(pairs):
        sigs.append(_pair_contact(mat, pair_solref[k]))
    if sigs:
        common_sig = Counter(sigs).most_common(1)[0][0]
    else:
        common_sig = (1, (0.0, 0.0, 0.0, 0.0, 0.0), (0.02, 1.0))
    explicit = [(k, s) for k, s in enumerate(sigs) if s != common_sig]
    if contact and scene.has("friction"):
        for name, mt in scene.materials.items():
            if mt.static_friction > mt.friction:
                notes.append(f"MuJoCo has one friction coefficient: material {name!r} static_friction "
                             f"{mt.static_friction:g} > friction {mt.friction:g} is modelled with the "
                             f"kinetic value {mt.friction:g} only")
    if contact and scene.has("rolling_friction"):
        notes.append("rolling friction uses condim 6; MuJoCo's torsional friction is set to 0 "
                     "(clamped internally to 1e-5)")
    if not scene.has("gyroscopic") and any(np.ptp(b.inertia) > 1e-12 * max(b.inertia) for b in scene.bodies):
        notes.append("MuJoCo always integrates the gyroscopic term; it is zero at t = 0 here, but "
                     "acts on bodies with unequal inertia if they start turning off a principal axis")

    ct = 1 if contact else 0
    gcondim, gfric, gsolref = common_sig
    geom_contact = (f'contype="{ct}" conaffinity="{ct}" condim="{gcondim}" '
                    f'friction="{_f(gfric[0])} {_f(gfric[2])} {_f(gfric[3])}" solref="{_v(gsolref)}"')

    flags = []
    if not scene.has("gravity"):
        flags.append('gravity="disable"')
    if not contact:
        flags.append('contact="disable"')
    if not scene.springs:
        # the damper flag also gates the fluid forces (no joint has damping)
        flags.append('spring="disable"' + ('' if fluid else ' damper="disable"'))
    flags.append(f'speculative="{"enable" if settings["speculative"] else "disable"}"')
    integ_xml = INTEGRATORS[integrator]
    lines = [
        f'<mujoco model="{xml_escape(scene.id)}">',
        '  <compiler angle="radian" inertiafromgeom="false" autolimits="true"/>',
        f'  <option timestep="{_f(dt)}" gravity="{_v(scene.gravity)}" integrator="{integ_xml}" '
        f'cone="{settings["cone"]}" impratio="{_f(settings["impratio"])}" '
        f'iterations="{int(settings["iterations"])}" noslip_iterations="{int(settings["noslip_iterations"])}"'
        + (f' density="{_f(fluid["density"])}" viscosity="{_f(fluid["viscosity"])}"' if fluid else "") + '>',
        f'    <flag {" ".join(flags)}/>',
        '  </option>',
        '  <worldbody>',
    ]
    for s in scene.statics:
        if s.shape == "plane":
            n = np.asarray(s.normal, float)
            lines.append(f'    <geom name="s{s.index}" type="plane" size="0 0 1" pos="{_v(n * s.offset)}" '
                         f'zaxis="{_v(n)}" {geom_contact}/>')
        else:
            lines.append(f'    <geom name="s{s.index}" type="box" size="{_v(s.half_extents)}" '
                         f'pos="{_v(s.position)}" quat="{_v(s.orientation)}" {geom_contact}/>')
    # world-anchored spring sites
    for k, sp in enumerate(scene.springs):
        if sp.a < 0:
            lines.append(f'    <site name="sp{k}a" pos="{_v(sp.anchor_a)}"/>')
        if sp.b < 0:
            lines.append(f'    <site name="sp{k}b" pos="{_v(sp.anchor_b)}"/>')
    tree, loops = joint_tree(scene)
    held = {j.body: j for j in tree}  # each body's one joint, to its parent (joint_tree)
    children: dict[int, list[int]] = {}
    for j in tree:
        children.setdefault(j.other, []).append(j.body)
    from physbench.contract.rotation import quat_mul, quat_to_matrix

    def emit(b, pad: str) -> None:
        if b.shape == "sphere":
            gs = f'type="sphere" size="{_f(b.radius)}"'
        elif b.shape == "box":
            gs = f'type="box" size="{_v(b.half_extents)}"'
        else:
            gs = f'type="{b.shape}" size="{_f(b.radius)} {_f(b.half_length)}"'
        j = held.get(b.index)
        pos, quat = b.position, b.orientation
        if j is not None and j.other >= 0:  # nested: the pose relative to the parent body
            o = scene.bodies[j.other]
            pos = quat_to_matrix(o.orientation).T @ (b.position - o.position)
            quat = quat_mul(o.orientation * np.array([1.0, -1.0, -1.0, -1.0]), b.orientation)
        lines.append(f'{pad}<body name="b{b.index}" pos="{_v(pos)}" quat="{_v(quat)}">')
        jx = joint_xml(j, pad + "  ") if j is not None else f'{pad}  <freejoint/>'
        if jx:
            lines.append(jx)
        lines.append(f'{pad}  <inertial pos="0 0 0" mass="{_f(b.mass * mscale)}" '
                     f'diaginertia="{_v(np.multiply(b.inertia, mscale))}"/>')
        fl = f' fluidshape="ellipsoid" fluidcoef="{_f(fluid["blunt"][b.index])} 0 0 0 0"' if fluid else ""
        lines.append(f'{pad}  <geom name="g{b.index}" {gs} {geom_contact}{fl}/>')
        for k, sp in enumerate(scene.springs):
            if sp.a == b.index:
                lines.append(f'{pad}  <site name="sp{k}a" pos="{_v(sp.anchor_a)}"/>')
            if sp.b == b.index:
                lines.append(f'{pad}  <site name="sp{k}b" pos="{_v(sp.anchor_b)}"/>')
        for c in children.get(b.index, []):
            emit(scene.bodies[c], pad + "  ")
        lines.append(f'{pad}</body>')

    for b in scene.bodies:
        if b.index not in held or held[b.index].other < 0:  # the roots: free bodies and bodies held by the world
            emit(b, "    ")
    lines.append('  </worldbody>')
    if explicit:
        lines.append('  <contact>')
        for k, (condim, fr, solref) in explicit:
            ka, ia, kb, ib, _ = pairs[k]
            g2 = f"s{ib}" if kb == "static" else f"g{ib}"
            lines.append(f'    <pair geom1="g{ia}" geom2="{g2}" condim="{condim}" friction="{_v(fr)}" '
                         f'solref="{_v(solref)}"/>')
        lines.append('  </contact>')
    if loops:  # the loops' joints: a point held in common (joint_tree, loop_reason)
        lines.append('  <equality>')
        for j in loops:
            b2 = f' body2="b{j.other}"' if j.other >= 0 else ""
            lines.append(f'    <connect name="loop{j.index}" body1="b{j.body}"{b2} anchor="{_v(j.anchor_body)}"/>')
        lines.append('  </equality>')
    if scene.springs:
        lines.append('  <tendon>')
        for k, sp in enumerate(scene.springs):
            lines.append(f'    <spatial name="spring{k}" stiffness="{_f(sp.stiffness * mscale)}" '
                         f'damping="{_f(sp.damping * mscale)}" springlength="{_f(sp.rest_length)}">')
            lines.append(f'      <site site="sp{k}a"/>')
            lines.append(f'      <site site="sp{k}b"/>')
            lines.append('    </spatial>')
        lines.append('  </tendon>')
    lines.append('</mujoco>')
    condims = sorted({s[0] for s in sigs})
    meta = {
        "dynamic_contacts": bool(contact and pairs),
        "explicit_pairs": len(explicit),
        "condim": (condims[0] if len(condims) == 1 else condims) if condims else None,
        "tendons": len(scene.springs),
        "mass_scale": mscale,
        "fluid": fluid,
        "fluid_refused": fluid_refused,
    }
    return "\n".join(lines) + "\n", meta


#: contract joint kind -> MJCF joint type; a fixed joint to the world is a
#: body without a joint (welded to its parent, the world)
JOINT_TYPES = {"revolute": "hinge", "spherical": "ball", "prismatic": "slide", "fixed": None}


def joint_xml(j, pad: str = "      ") -> str:
    """The MJCF ``<joint>`` line of joint ``j`` (to its parent: the world or
    the ``other`` body), in its body's frame: anchor and axis as compiled
    (contract Joint.anchor_body, axis_body), no limits, damping, armature or
    friction loss; '' for a fixed joint (no degree of freedom: a weld)."""
    kind = JOINT_TYPES[j.kind]
    if kind is None:
        return ""
    axis = f' axis="{_v(j.axis_body)}"' if j.axis_body is not None else ""
    return (f'{pad}<joint name="j{j.index}" type="{kind}" pos="{_v(j.anchor_body)}"{axis} '
            f'damping="0" armature="0" frictionloss="0"/>')


def joint_tree(scene: Scene) -> tuple[list, list]:
    """The scene's joints split into the body tree's and the loops':
    taken in order, a joint nests its ``body`` in ``other`` (the world or a
    body) unless its body is already nested or nesting it would close a
    loop; such a joint closes a loop and becomes an equality constraint
    (:func:`loop_reason` says which it can be).  Returns (tree, loops)."""
    parent: dict[int, int] = {}
    tree, loops = [], []
    for j in scene.joints:
        i = j.other
        while i in parent:  # does `other` hang below `body`?
            i = parent[i]
            if i == j.body:
                break
        if j.body in parent or i == j.body or j.other == j.body:
            loops.append(j)
        else:
            parent[j.body] = j.other
            tree.append(j)
    return tree, loops


def loop_reason(scene: Scene, loops: list) -> str | None:
    """Why a loop-closing joint cannot be an equality constraint here, or
    None.  A ``connect`` equality holds a point: exactly a spherical joint,
    and exactly a revolute joint when every joint of the scene is a
    revolute joint about the same axis (a planar linkage: the tree's hinges
    already hold the relative turn to that axis)."""
    for j in loops:
        if j.kind == "spherical":
            continue
        if j.kind == "revolute" and all(k.kind == "revolute" and np.linalg.norm(np.cross(k.axis, j.axis)) <= 1e-12
                                        for k in scene.joints):
            continue
        return (f"joints: MuJoCo adapter closes a loop with a connect equality (a point), which is a {j.kind} joint "
                f"only in a planar linkage of parallel hinges; joint {j.name!r} is not one")
    return None


#: the deepest body tree MuJoCo's XML parser reads (measured on 4.0.1:
#: tests/test_joints_mujoco.py::test_a_chain_past_the_xml_nesting_is_unsupported)
MAX_NESTING = 496


def joint_tree_reason(scene: Scene) -> str | None:
    """Why this adapter cannot build the scene's joints, or None.  It
    builds a body tree (:func:`joint_tree`): each tree joint nests its
    ``body`` in ``other`` with a hinge, ball or slide, a weld for fixed;
    a joint that closes a loop is a ``connect`` equality
    (:func:`loop_reason`).  Drag on a jointed scene is not built."""
    tree, loops = joint_tree(scene)
    why = loop_reason(scene, loops)
    if why:
        return why
    parent = {j.body: j.other for j in tree}
    depth = 0
    for i in parent:
        d = 0
        while i in parent:
            i, d = parent[i], d + 1
        depth = max(depth, d)
    if depth > MAX_NESTING:
        return (f"joints: a chain {depth} bodies deep nests {depth} MJCF <body> elements, past what MuJoCo's XML "
                f"parser reads (a chain of {MAX_NESTING} builds, {MAX_NESTING + 1} does not: 'Element nesting is "
                f"too deep', 4.0.1)")
    if scene.joints and (scene.has("drag_linear") or scene.has("drag_quadratic")):
        return "joints: MuJoCo adapter applies drag to free bodies only"
    return None


def joint_start(scene: Scene, m: Any, d: Any) -> None:
    """Write the scene's initial state into MuJoCo's qpos/qvel (scene body
    i is MuJoCo's body "b<i>"; a body's pose at the start is its MJCF pose,
    so a joint's qpos is 0 and its quaternion the identity; a joint's rate
    is the body's motion relative to its parent).  A start the
    joint cannot hold (a hinge body moving other than by turning about the
    hinge, a slider turning or moving off its axis, a welded body moving) is
    a ValueError with the reason: reduced coordinates would drop it."""
    from physbench.contract.rotation import world_to_body_angvel

    import mujoco

    held = {j.body: j for j in joint_tree(scene)[0]}  # a loop's joint has no coordinates
    x0, q0, v0, w0 = scene.initial_state()
    scale = 1.0 + float(np.max(np.abs(v0), initial=0.0))
    for i, b in enumerate(scene.bodies):
        bid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"b{i}")
        jnt = [k for k in range(m.njnt) if m.jnt_bodyid[k] == bid]
        j = held.get(i)
        if j is None:  # a free body
            qa, da = m.jnt_qposadr[jnt[0]], m.jnt_dofadr[jnt[0]]
            d.qpos[qa:qa + 7] = np.concatenate([x0[i], q0[i]])
            d.qvel[da:da + 3] = v0[i]
            d.qvel[da + 3:da + 6] = world_to_body_angvel(q0[i], w0[i])
            continue
        r = x0[i] - j.anchor
        # the motion relative to the parent (the world: at rest)
        w, v = w0[i].copy(), v0[i].copy()
        if j.other >= 0:
            o = j.other
            w -= w0[o]
            v -= v0[o] + np.cross(w0[o], x0[i] - x0[o])
        if j.kind == "revolute":
            rate = float(w @ j.axis)
            bad = np.linalg.norm(w - rate * j.axis) + np.linalg.norm(v - rate * np.cross(j.axis, r)) / scale
            value = [rate]
        elif j.kind == "spherical":
            bad = np.linalg.norm(v - np.cross(w, r)) / scale
            value = list(world_to_body_angvel(q0[i], w))  # a ball joint's qvel is in the body frame
            d.qpos[m.jnt_qposadr[jnt[0]]:m.jnt_qposadr[jnt[0]] + 4] = (1.0, 0.0, 0.0, 0.0)
        elif j.kind == "prismatic":
            rate = float(v @ j.axis)
            bad = np.linalg.norm(w) + np.linalg.norm(v - rate * j.axis) / scale
            value = [rate]
        else:
            bad, value = np.linalg.norm(w) + np.linalg.norm(v) / scale, []
        if bad > 1e-9:
            raise ValueError(f"joints: body {b.name!r} starts with a motion its {j.kind} joint does not allow "
                             f"(velocity {v.tolist()}, angular velocity {w.tolist()} relative to its other side); "
                             f"MuJoCo's reduced "
                             f"coordinates would drop it")
        if value:
            da = m.jnt_dofadr[jnt[0]]
            d.qvel[da:da + len(value)] = value


def xml_escape(s: str) -> str:
    """``s`` as the text of a double-quoted XML attribute: markup characters
    and whitespace escaped (an attribute's raw newline or tab would be read
    as a space), characters XML 1.0 cannot hold at all replaced by U+FFFD.
    Pinned by tests/test_fuzz.py::test_mjcf_escape_round_trips."""
    out = s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")
    out = out.replace("\t", "&#9;").replace("\n", "&#10;").replace("\r", "&#13;")
    return re.sub("[\x00-\x08\x0b\x0c\x0e-\x1f\ud800-\udfff\ufffe\uffff]", "\ufffd", out)
