"""The contact forces of the shipped third-party adapters, read through
each engine's public API after a step (:meth:`adapters.base.Adapter.
contact_forces` calls the reader named for the adapter): one row per
contact (MuJoCo, MJX, pybullet, Rapier, Drake's point pairs) or per contact
patch (pymunk, whose public API sums an arbiter's points; Drake's
hydroelastic surfaces, a resultant at the centroid), in the contract of
``contact_forces``: ``a``
body index, ``b`` body index or -1 with ``static`` the static's index,
``point`` (R, 3) m, ``normal`` (R, 3) unit from a toward b, ``gap`` (R,)
m (< 0 overlap, as the engine measured it), ``lam_n`` (R,) N the normal
force on b along ``normal``, ``lam_t`` (R, 3) N the friction force on b
(NaN rows where the engine's friction cannot be read: the harness then
leaves the friction laws undefined with the adapter's
``friction_forces_reason``).

Sign conventions, each measured on two cubes resting on a floor
(tests/test_contact_laws.py::test_resting_box_forces_on_every_engine: the
normal forces carry the weights, positive, along normals from a to b).
Only called when a check asks for a contact-law metric; none of this runs
in a plain run.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np

Rows = dict[str, np.ndarray]


def _mj_geom_side(ad: Any) -> tuple[np.ndarray, np.ndarray]:
    """geom -> scene body index or -1, geom -> static index or -1 (cached
    on ``ad``): bodies are "b<i>", statics' geoms "s<index>" (adapters.mjcf)."""
    import mujoco

    m, n_bodies = ad.m, ad.scene.n_bodies
    if getattr(ad, "_geom_side", None) is None:
        body = np.full(m.nbody, -1, np.int64)
        for i in range(n_bodies):
            body[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"b{i}")] = i
        gs = np.full(m.ngeom, -1, np.int64)
        for g in range(m.ngeom):
            name = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or ""
            if name[:1] == "s" and name[1:].isdigit():
                gs[g] = int(name[1:])
        ad._geom_side = (body[m.geom_bodyid], gs)
    return ad._geom_side


def _mj_rows(ad: Any, f: np.ndarray, frame: np.ndarray, g1: np.ndarray, g2: np.ndarray, pos: np.ndarray,
             dist: np.ndarray) -> Rows:
    """Rows of k MuJoCo contacts from their forces ``f`` (k, >= 3) in the
    contact frame (normal, tangent 1, tangent 2; on geom2), ``frame`` (k,
    3, 3) rows those axes, geoms, points and distances: to the world,
    divided by the model's mass scale (adapters.mjcf.mass_scale: forces
    scale with the masses).  A static on geom1's side is made side b: the
    normal and the friction on b negate, lam_n stays."""
    gb, gs = _mj_geom_side(ad)
    scale = ad.meta["mass_scale"]
    nrm = frame[:, 0].copy()
    lam_t = np.einsum("kj,kji->ki", f[:, 1:3], frame[:, 1:3]) / scale
    flip = gb[g1] < 0  # a static is geom1
    nrm[flip] *= -1.0
    lam_t[flip] *= -1.0
    return {"a": np.where(flip, gb[g2], gb[g1]), "b": np.where(flip, -1, gb[g2]),
            "static": np.where(flip, gs[g1], np.where(gb[g2] < 0, gs[g2], -1)), "point": np.array(pos, float),
            "normal": nrm, "gap": np.array(dist, float), "lam_n": f[:, 0] / scale, "lam_t": lam_t}


def mujoco_rows(ad: Any) -> Rows:
    """MuJoCo 3.x/4.x: one row per ``d.contact`` (the last ``mj_step``'s,
    found at its start).  ``mj_contactForce`` gives the force in the
    contact frame (rows: normal from geom1 toward geom2, tangent 1, 2) on
    geom2 (:func:`_mj_rows` to the world); gap = ``dist``."""
    import mujoco

    m, d = ad.m, ad.d
    k = int(d.ncon)
    f = np.zeros((k, 6))
    for i in range(k):
        mujoco.mj_contactForce(m, d, i, f[i])
    c = d.contact
    return _mj_rows(ad, f, c.frame[:k].reshape(k, 3, 3), c.geom1[:k], c.geom2[:k], c.pos[:k], c.dist[:k])


def mjx_rows(ad: Any) -> Rows:
    """MJX (mujoco-mjx 3.17; ``Data._impl`` holds its contacts and constraint
    forces): the MuJoCo reader's rows (:func:`_mj_rows`) from the last
    step's MJX data, copied off the device here only (never inside the
    compiled scan).  MJX keeps a fixed set of candidate contacts, each
    with ``dim`` constraint rows at ``efc_address`` in ``efc_force``
    whether touching or not; the contacts are those with dist <= 0 (as
    ``mjx.get_data`` selects them).  The force in the contact frame is
    ``mj_contactForce``'s, done on the arrays: elliptic cones the rows
    themselves, pyramidal ones decoded (normal = the sum of the 2(dim-1)
    edge forces, tangent j = mu_j (f_2j - f_2j+1)).  Not through
    ``mjx.get_data`` and ``mj_contactForce``: get_data leaves the MjContact
    fields MJX lacks (``exclude`` among them) as arena garbage, and
    mj_contactForce skips a contact whose ``exclude`` is not 0 (measured
    on the resting cubes: contacts lost, forces of 1e200 N read)."""
    import jax

    c = jax.device_get(ad.dx._impl.contact)
    efc = np.asarray(jax.device_get(ad.dx._impl.efc_force))
    on = np.nonzero(np.asarray(c.dist) <= 0.0)[0]
    k = len(on)
    dim, addr = np.asarray(c.dim)[on], np.asarray(c.efc_address)[on]
    mu = np.asarray(c.friction)[on]
    f = np.zeros((k, 6))
    pyramidal = int(ad.m.opt.cone) == 0  # mjCONE_PYRAMIDAL
    for i in range(k):
        n, a = int(dim[i]), int(addr[i])
        if pyramidal and n > 1:
            p = efc[a:a + 2 * (n - 1)]
            f[i, 0] = p.sum()
            f[i, 1:n] = mu[i, :n - 1] * (p[0::2] - p[1::2])
        else:
            f[i, :n] = efc[a:a + n]
    return _mj_rows(ad, f, np.asarray(c.frame)[on].reshape(k, 3, 3), np.asarray(c.geom1)[on],
                    np.asarray(c.geom2)[on], np.asarray(c.pos)[on], np.asarray(c.dist)[on])


def pybullet_rows(ad: Any) -> Rows:
    """pybullet 3.2: one row per ``getContactPoints`` point after the
    step.  The force on A is normalForce along contactNormalOnB (B toward
    A) plus lateralFriction1 and 2 along their directions (Bullet applies
    each constraint's impulse + to A, - to B).  Row a is A's body (B's
    when A is a static): the normal a -> b and the force on b are those on
    A negated (kept when swapped), lam_n = normalForce either way; gap =
    contactDistance; point midway between positionOnA and positionOnB."""
    p, cid = ad._p, ad._cid
    side = getattr(ad, "_contact_side", None)
    if side is None:
        side = {bid: (i, -1) for i, bid in enumerate(ad._ids)}
        side.update({sid: (-1, k) for k, sid in enumerate(ad._static_ids)})
        ad._contact_side = side
    pts = p.getContactPoints(physicsClientId=cid)
    k = len(pts)
    out = {"a": np.empty(k, np.int64), "b": np.empty(k, np.int64), "static": np.empty(k, np.int64),
           "point": np.empty((k, 3)), "normal": np.empty((k, 3)), "gap": np.empty(k), "lam_n": np.empty(k),
           "lam_t": np.empty((k, 3))}
    for i, c in enumerate(pts):
        (ia, sa), (ib, sb) = side[c[1]], side[c[2]]
        sign = 1.0 if ia < 0 else -1.0
        out["a"][i], out["b"][i], out["static"][i] = (ib, -1, sa) if ia < 0 else (ia, ib, sb)
        out["point"][i] = 0.5 * (np.asarray(c[5]) + np.asarray(c[6]))
        out["normal"][i] = sign * np.asarray(c[7])
        out["gap"][i] = c[8]
        out["lam_n"][i] = c[9]
        out["lam_t"][i] = sign * (np.asarray(c[11]) * c[10] + np.asarray(c[13]) * c[12])
    return out


def pymunk_rows(ad: Any) -> Rows:
    """pymunk 7: one row per touching arbiter, taken from body a (the
    lower scene index, or the body facing a static).  Measured on pymunk
    7.3.1: an arbiter's normal points from its first body toward its
    second and ``total_impulse`` is the impulse on the first (a circle
    resting on a segment gets +m g dt), whichever order ``each_arbiter``
    gives the bodies in.  The force on b is its impulse over the last
    substep / the substep's dt, split into the normal part and the 2D
    tangential rest; point the mean of the points' midpoints, gap their
    smallest distance; 2D (x, y) -> world (x, 0, y) as positions map."""
    bodies, h = ad._bodies, ad._h
    index = {id(b): i for i, b in enumerate(bodies)}
    rows: list[tuple] = []
    for i, body in enumerate(bodies):
        arbs: list = []
        body.each_arbiter(arbs.append)
        for arb in arbs:
            first = arb.bodies[0] is body
            j = index.get(id(arb.bodies[1] if first else arb.bodies[0]), -1)
            ps = arb.contact_point_set
            if -1 < j < i or not ps.points:
                continue  # visited from body j, or no point
            sign = 1.0 if first else -1.0  # orient first -> second as a -> b
            n = ps.normal * sign
            imp = arb.total_impulse * -sign  # on b
            jn = imp.x * n.x + imp.y * n.y
            st = getattr(arb.shapes[1 if first else 0], "physbench_static", -1) if j < 0 else -1
            mid = [(0.5 * (q.point_a.x + q.point_b.x), 0.5 * (q.point_a.y + q.point_b.y)) for q in ps.points]
            rows.append((i, j, st, np.mean(mid, axis=0), (n.x, n.y), min(q.distance for q in ps.points),
                         jn / h, ((imp.x - jn * n.x) / h, (imp.y - jn * n.y) / h)))
    k = len(rows)
    out = {"a": np.array([r[0] for r in rows], np.int64), "b": np.array([r[1] for r in rows], np.int64),
           "static": np.array([r[2] for r in rows], np.int64), "point": np.zeros((k, 3)),
           "normal": np.zeros((k, 3)), "gap": np.array([r[5] for r in rows], float),
           "lam_n": np.array([r[6] for r in rows], float), "lam_t": np.zeros((k, 3))}
    for key, col in (("point", 3), ("normal", 4), ("lam_t", 7)):
        if k:
            out[key][:, [0, 2]] = [r[col] for r in rows]
    return out


def _rapier_tangents(force_dir: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rapier's friction basis of a contact whose force on body 1 points
    along ``force_dir`` (3,) unit: t1 its ``orthonormal_vector`` (the
    branch-free basis of Duff et al. 2017, sign from z), t2 = force_dir x
    t1.  Rapier 0.36 builds it from the normal alone (not from the bodies'
    velocities), which the momentum check pins
    (tests/test_contact_laws.py::test_rapier_friction_basis_balances_momentum)."""
    x, y, z = force_dir
    s = 1.0 if z >= 0.0 else -1.0
    a = -1.0 / (s + z)
    t1 = np.array([x * y * a, s + y * y * a, -y])
    return t1, np.cross(force_dir, t1)


def rapier_rows(ad: Any) -> Rows:
    """Rapier 0.36 (rapier3d bindings): one row per solver contact of
    every manifold (the contacts the solver saw, speculative ones within
    the prediction distance included).  Measured on the resting cubes:
    ``ContactData.impulse`` is the normal impulse over the whole step (its
    TGS substeps summed: four points carry (m1 + m2) g dt), applied along
    -normal to collider 1's body, so lam_n = impulse / dt along the
    manifold normal (collider 1 toward 2) on collider 2's body;
    ``tangent_impulse`` (2,) is the friction impulse on body 1 along
    :func:`_rapier_tangents` of -normal.  It is per point only with
    ``friction_model = "coulomb"``: Rapier's default "simplified" model
    solves one friction and one twist constraint per manifold and writes
    neither to the points (measured: 0 on a block sliding down a slope), so
    lam_t is NaN and the friction laws undefined.  A static on collider 1's
    side is made side b (normal and friction negate, lam_n stays); gap =
    the solver contact's ``dist``; point midway between its two world
    points."""
    import rapier3d as rp

    w = ad._world
    dt = float(w.integration_parameters.dt)
    coulomb = w.integration_parameters.friction_model == rp.FrictionModel.COULOMB
    ad.friction_forces_reason = "" if coulomb else (
        "friction_model 'simplified' (Rapier's default) solves one friction and one twist constraint per "
        "manifold and the bindings expose neither impulse (per-point friction needs friction_model = 'coulomb')")
    body_of = {h.index: i for i, h in enumerate(ad._handles)}
    bodies = w.rigid_bodies
    rows: list[tuple] = []
    for pair in w.narrow_phase.contact_pairs():
        for m in pair.manifolds:
            d = m.data
            if not d.solver_contacts:
                continue
            n = np.array(d.normal.to_tuple(), float)
            t1, t2 = _rapier_tangents(-n)
            r1 = body_of[d.rigid_body1.index] if d.rigid_body1 is not None else -1
            r2 = body_of[d.rigid_body2.index] if d.rigid_body2 is not None else -1
            flip = r1 < 0
            st = ad._static_of.get((pair.collider1 if flip else pair.collider2).index, -1)
            sign = -1.0 if flip else 1.0
            for c in d.solver_contacts:
                pt = m.points[c.contact_id]
                p1, p2 = d.solver_contact_world_points(c, bodies)
                ti = pt.tangent_impulse
                f1 = (ti[0] * t1 + ti[1] * t2) / dt  # friction on body 1
                rows.append((r2 if flip else r1, -1 if flip or r2 < 0 else r2, st,
                             0.5 * (np.array(p1.to_tuple()) + np.array(p2.to_tuple())), sign * n, float(c.dist),
                             float(pt.impulse) / dt, f1 if flip else -f1))
    k = len(rows)
    out = {"a": np.array([r[0] for r in rows], np.int64), "b": np.array([r[1] for r in rows], np.int64),
           "static": np.array([r[2] for r in rows], np.int64), "point": np.array([r[3] for r in rows]).reshape(k, 3),
           "normal": np.array([r[4] for r in rows]).reshape(k, 3), "gap": np.array([r[5] for r in rows], float),
           "lam_n": np.array([r[6] for r in rows], float), "lam_t": np.array([r[7] for r in rows]).reshape(k, 3)}
    if not coulomb:
        out["lam_t"][:] = np.nan
    return out


def _drake_rows_out(rows: list[tuple]) -> Rows:
    k = len(rows)
    return {"a": np.array([r[0] for r in rows], np.int64), "b": np.array([r[1] for r in rows], np.int64),
            "static": np.array([r[2] for r in rows], np.int64), "point": np.array([r[3] for r in rows]).reshape(k, 3),
            "normal": np.array([r[4] for r in rows]).reshape(k, 3), "gap": np.array([r[5] for r in rows], float),
            "lam_n": np.array([r[6] for r in rows], float), "lam_t": np.array([r[7] for r in rows]).reshape(k, 3)}


def drake_rows(ad: Any) -> Rows:
    """Drake 1.x: the plant's ``ContactResults`` (for a discrete plant
    those of the last step, found at its start), evaluated only here.
    Geometry -> side by name: bodies' geometries "g<i>", statics' "s<k>".

    Point contact: one row per ``point_pair_contact_info``: its
    ``contact_force`` is the force on body B at the contact point,
    ``nhat_BA_W`` points from B into A and ``depth`` > 0 is overlap, so
    the normal A -> B is -nhat, gap = -depth.  Hydroelastic contact: one
    row per contact surface (a patch, as the reference engine's and
    pymunk's rows), at its ``centroid`` with the resultant force
    ``F_Ac_W`` (on the body of geometry M, at the centroid; the force on N
    is its negative), normal M -> N the negated area-weighted mean of the
    face normals (Drake's point out of N into M); gap NaN: a pressure
    field has no one gap, the harness takes the pair's own signed distance
    at the recorded pose (harness.contact_laws.own_gap).  The torque
    about the centroid is not a row's (it is not a contact law's).  A
    static on side a is made side b: the normal and the force on b
    negate, lam_n stays.  Measured on the resting cubes
    (tests/test_contact_laws.py::test_resting_box_forces_on_every_engine):
    each patch carries the weight above it."""
    plant, ctx = ad.plant, ad.pctx
    insp = plant.EvalSceneGraphInspector(ctx)
    side: dict = getattr(ad, "_geom_side", None) or {}
    ad._geom_side = side

    def of(gid) -> tuple[int, int]:  # geometry -> (body index or -1, static index or -1)
        if gid not in side:
            name = insp.GetName(gid).rsplit("::", 1)[-1]
            side[gid] = (int(name[1:]), -1) if name[0] == "g" else (-1, int(name[1:]))
        return side[gid]

    cr = plant.get_contact_results_output_port().Eval(ctx)
    rows: list[tuple] = []

    def add(ga, gb, point, n, gap, f_b) -> None:
        (ia, sa), (ib, sb) = of(ga), of(gb)
        if ia < 0:  # a static on side a: swap
            (ia, sa), (ib, sb), n, f_b = (ib, sb), (ia, sa), -n, -f_b
        lam = float(f_b @ n)
        rows.append((ia, ib, sb, np.asarray(point, float), n, gap, lam, f_b - lam * n))

    for i in range(cr.num_point_pair_contacts()):
        info = cr.point_pair_contact_info(i)
        pp = info.point_pair()
        add(pp.id_A, pp.id_B, info.contact_point(), -np.asarray(pp.nhat_BA_W, float), -float(pp.depth),
            np.asarray(info.contact_force(), float))
    for i in range(cr.num_hydroelastic_contacts()):
        info = cr.hydroelastic_contact_info(i)
        s = info.contact_surface()
        n = -sum(s.area(f) * np.asarray(s.face_normal(f), float) for f in range(s.num_faces()))
        add(s.id_M(), s.id_N(), s.centroid(), n / np.linalg.norm(n), float("nan"),
            -np.asarray(info.F_Ac_W().translational(), float))
    return _drake_rows_out(rows)


#: the reader of each shipped adapter that has one (by adapter name)
READERS: dict[str, Callable[[Any], Rows]] = {"mujoco": mujoco_rows, "pybullet": pybullet_rows, "pymunk": pymunk_rows,
                                             "rapier": rapier_rows, "drake": drake_rows,
                                             "mjx": mjx_rows}
