"""Loads and boundaries (DESIGN.md stage 8): pressure histories on faces, non-reflecting dashpots, velocity drivers.

Faces are node triples ordered so that their right-hand normal points out of the rock. A face's current area vector
a = ½ (x1 - x0) × (x2 - x0) is formed from reference edges E (float64 on the host, stored in float32) plus the
displacement differences, e = E + (u_k - u_0), so it keeps the precision of the displacements wherever the body sits
(as the tets do, kernels/tets.py).

Pressure: a pressure p pushes into the solid, f = -p a, lumped onto the nodes by their weights w_k: a third each on
a face inside its load's region, less where the region's edge crosses the face, so that a load pushes on exactly
the area its region covers, whatever the mesh (warpdem.build.face_cover: w_k = (1/A) ∫_{face ∩ region} N_k dA).
Histories are picked at code-generation time (:func:`make_face_pressure_kernel`); their parameters sit in one
:class:`PressureLoad` per load.

Impulse: each evaluation in a step adds dt |f_{n+1}| = dt p |a| Σ_k w_k per face to ``load_face_impulse`` (the
State's, per loaded face), the normal impulse ∫∫ p dA dt the two half kicks around it deliver, so that a report can
say what a load gave (a sum of magnitudes: on a cavity's wall the vector sum cancels).

Work of the loads: velocity Verlet's energy identity per step is, exactly,
ΔK = ½ dt (f_n + f_{n+1}) · v_{n+1/2} + dt²/8 (|f_{n+1}|²_{M⁻¹} - |f_n|²_{M⁻¹}) (v_{n+1/2} = v_n + dt/2 M⁻¹ f_n,
v_{n+1} = v_{n+1/2} + dt/2 M⁻¹ f_{n+1}; the second term telescopes to a bounded shadow term), so the load work is
booked by the same trapezoid, as the contacts and dashpots book theirs: the evaluation that makes f_{n+1} books the
half behind it, ½ dt f_{n+1}·v_{n+1/2} (:func:`make_face_pressure_kernel`), and keeps f_{n+1} per node
(``node_f_load``); the next evaluation books the half ahead, ½ dt f_{n+1}·v_{n+3/2}, once the drift has made
v_{n+3/2} (kernels/integrate.py ``book_half_ahead_kernel``). For a node of a rigid block the velocity of the half
ahead is the body's at the pose the force was made at, not at the next one (kernels/rigid.py
``node_velocity_ahead``): a force made again from the positions x_{n+1} - dt v_{n+1/2} (this module's way before)
is not f_n for a turning block. The kept forces need no list of the loaded nodes that a split would have to follow:
a split or conversion pass re-evaluates every force at dt = 0, which makes ``node_f_load`` again from the faces as
they are then (the daughters' shares included), and the next kick works with exactly those forces.

Hand-over: a pressure face whose tet turns into spheres (a conversion pass, or a region that starts as spheres) is
dropped from the nodes, but its push goes on, on that tet's spheres, for the rest of the load's history: the force
-p(t) a_c Σ_k w_k, a_c the face's area vector when its tet converted (``handed_area``, written by the pass:
kernels/conversion.py ``drop_converted_faces_kernel``), shared equally among the tet's ``spheres_per_tet`` spheres, p
evaluated at their mean position (where a Friedlander front arrives). Why this rule: the spheres hold no faces, so the
area and direction can only be those the face had; frozen, the load delivers exactly the impulse ∫p dt a_c that the
face would have delivered had it stayed (up to the face's small stretch and turn), whichever way the material is then
modelled, and equal shares keep it a push on the tet's mass as a whole (the lumped face load put a third on each face
node, ρV/4 of the tet's mass at each). A sphere flying off keeps its push in its own frozen direction, as a fragment
driven by the gas behind it. Its work is booked per face by the same trapezoid as the nodes' (the evaluation of
f_{n+1} books ½ dt (f_n + f_{n+1})·v_{n+1/2} at once, against the spheres' mean v_{n+1/2}: the half ahead of the kept
f_n and the half behind f_{n+1} are both against that velocity), into the State's ``load_face_work``, which the energy
balance adds to the load work line. A pass between steps re-evaluates at dt = 0 (no work): the handed face's kept
force is then exactly the force the nodes last felt (same time, same area vector), so the books run on.

Non-reflecting boundary (Lysmer & Kuhlemeyer 1969): the traction t = -ρ c_p (v·n) n - ρ c_s (v - (v·n) n) of a
semi-infinite continuum carrying a plane wave away normally. It is lumped per node (each node's dashpot sees its
own velocity, a third of each adjacent face's area), at the half-step velocity as the mass-proportional damping of
the integrator, and the energy it takes out is booked as Verlet does its work, the trapezoid above (half when the
force is made, half at the next evaluation).

Velocity drivers hold a node's velocity at V while start ≤ t < end; the integrator applies them
(kernels/integrate.py) with the predicates here.
"""

from __future__ import annotations

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})

PRESSURE_KINDS = ("blast", "table", "friedlander")
"""Pressure histories, each specialised into its own kernel."""


@wp.struct
class PressureLoad:
    """Parameters of one pressure history (the fields a kind does not use are 0).

    Attributes:
        peak: peak pressure [Pa]: blast peak, Friedlander peak overpressure P_s (table: unused).
        start: blast start time, Friedlander source time t0 [s], float64.
        rise: blast rise time t_rise [s].
        decay: blast decay time t_decay, Friedlander positive-phase duration t_d [s].
        shape: Friedlander decay coefficient b [-].
        source: Friedlander source point [m].
        slowness: 1 / front speed of the Friedlander front [s/m].
        table_first: first entry of this load's (time, value) table in the shared table arrays.
        table_count: entries of the table (≥ 2).
    """

    peak: float
    start: wp.float64
    rise: float
    decay: float
    shape: float
    source: wp.vec3
    slowness: float
    table_first: int
    table_count: int


@wp.struct
class NodeDriver:
    """A prescribed node velocity.

    Attributes:
        velocity: the velocity held [m/s].
        start: first time it holds [s], float64.
        end: time it lets go [s] (inf: never), float64.
    """

    velocity: wp.vec3
    start: wp.float64
    end: wp.float64


# ----------------------------------------------------------------------------------------------------------------
# Physics.


@wp.func
def blast_pressure(
    load: PressureLoad,
    t: wp.float64,
    x: wp.vec3,
    table_times: wp.array(dtype=wp.float64),
    table_values: wp.array(dtype=float),
) -> float:
    """Explosive cavity or borehole [Pa]: linear rise to the peak over t_rise, then exponential decay,
    p = P τ/t_rise for 0 ≤ τ < t_rise, P exp(-(τ - t_rise)/t_decay) after, τ = t - t_start; 0 before the start."""
    tau = float(t - load.start)
    if tau < 0.0:
        return 0.0
    if tau < load.rise:
        return load.peak * tau / load.rise
    return load.peak * wp.exp(-(tau - load.rise) / load.decay)


@wp.func
def table_pressure(
    load: PressureLoad,
    t: wp.float64,
    x: wp.vec3,
    table_times: wp.array(dtype=wp.float64),
    table_values: wp.array(dtype=float),
) -> float:
    """Piecewise-linear history through the points (t_k, p_k) [Pa], 0 outside [t_first, t_last]."""
    lo = load.table_first
    hi = lo + load.table_count - 1
    if t < table_times[lo] or t > table_times[hi]:
        return 0.0
    # Bisection for the interval [t_lo, t_hi] holding t: t_lo ≤ t ≤ t_hi throughout.
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if table_times[mid] <= t:
            lo = mid
        else:
            hi = mid
    w = float((t - table_times[lo]) / (table_times[hi] - table_times[lo]))
    return table_values[lo] + w * (table_values[hi] - table_values[lo])


@wp.func
def friedlander_pressure(
    load: PressureLoad,
    t: wp.float64,
    x: wp.vec3,
    table_times: wp.array(dtype=wp.float64),
    table_values: wp.array(dtype=float),
) -> float:
    """Surface airblast (Friedlander waveform) [Pa]: the front leaves the source at t0 with a constant speed and
    arrives at t_a(x) = t0 + |x - source| / front_speed; after it, p = P_s (1 - τ/t_d) exp(-b τ/t_d) with
    τ = t - t_a (its negative phase included); 0 before the arrival."""
    arrival = load.start + wp.float64(wp.length(x - load.source) * load.slowness)
    tau = float(t - arrival)
    if tau < 0.0:
        return 0.0
    s = tau / load.decay
    return load.peak * (1.0 - s) * wp.exp(-load.shape * s)


HISTORIES = {"blast": blast_pressure, "table": table_pressure, "friedlander": friedlander_pressure}


@wp.func
def area_vector(edge_a: wp.vec3, edge_b: wp.vec3, u0: wp.vec3, u1: wp.vec3, u2: wp.vec3) -> wp.vec3:
    """Current area vector of a face, ½ (x1 - x0) × (x2 - x0) [m²], from its reference edges E_a = X1 - X0,
    E_b = X2 - X0 and the displacements u_k of its nodes."""
    return 0.5 * wp.cross(edge_a + (u1 - u0), edge_b + (u2 - u0))


@wp.func
def face_area_vector(n: wp.vec3i, edge_a: wp.vec3, edge_b: wp.vec3, node_u: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """Current area vector of the face with nodes n [m²] (:func:`area_vector`)."""
    return area_vector(edge_a, edge_b, node_u[n[0]], node_u[n[1]], node_u[n[2]])


@wp.func
def handed_spheres(
    f: int,
    face_tet: wp.array(dtype=int),
    face_handed_area: wp.array(dtype=wp.vec3),
    tet_sphere: wp.array(dtype=int),
) -> int:
    """The first sphere slot of the tet behind a dropped pressure face whose push was handed over to its spheres, or
    -1: a face dropped without a hand-over (zero area: its tet had no spheres when it was dropped, or a restart of a
    run from before the hand-over)."""
    if wp.length_sq(face_handed_area[f]) == 0.0:
        return -1
    return tet_sphere[face_tet[f]]


@wp.func
def spheres_centre(particle_q: wp.array(dtype=wp.vec3d), first: int, count: int) -> wp.vec3:
    """Mean position of the spheres first .. first + count - 1 [m] (float64 centres, the mean rounded once)."""
    x = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for k in range(count):
        x = x + particle_q[first + k]
    x = x / wp.float64(count)
    return wp.vec3(float(x[0]), float(x[1]), float(x[2]))


@wp.func
def lysmer_traction(v: wp.vec3, normal: wp.vec3, impedance: wp.vec2) -> wp.vec3:
    """Viscous traction of a non-reflecting boundary [Pa] (Lysmer & Kuhlemeyer 1969):
    t = -ρ c_p (v·n) n - ρ c_s (v - (v·n) n), impedance = (ρ c_p, ρ c_s) [Pa s/m], n the unit normal."""
    vn = wp.dot(v, normal)
    return -impedance[0] * vn * normal - impedance[1] * (v - vn * normal)


@wp.func
def driver_holds(driver: NodeDriver, t: wp.float64) -> bool:
    """Whether a velocity driver holds its node at time t: start ≤ t < end."""
    if t < driver.start:
        return False
    return t < driver.end


# ----------------------------------------------------------------------------------------------------------------
# Kernels.


@functools.cache
def make_face_pressure_kernel(kind: str) -> wp.Kernel:
    """The pressure kernel of one history kind, the history picked at code-generation time.

    The kernel evaluates p at t_n + dt, the time of the positions the step has just drifted to (``time`` still holds
    t_n; the sum in float64 is the clock's own, as it will read after the step), adds f_{n+1} = -p a to the nodes'
    forces and to ``node_f_load``, and books the half of its work behind it, ½ dt f_{n+1}·v_{n+1/2} (``node_qd``
    holds v_{n+1/2}; the half ahead: module docstring). ``dt`` = 0 is an evaluation at the state's own time (set-up,
    after a pass), which books no work.

    Args:
        kind: one of :data:`PRESSURE_KINDS`.

    Raises:
        ValueError: an unknown kind.
    """
    if kind not in HISTORIES:
        raise ValueError(f"unknown pressure history {kind!r}; allowed: {', '.join(PRESSURE_KINDS)}")
    history = HISTORIES[kind]

    @wp.kernel(enable_backward=False, module="unique")
    def apply_face_pressure_kernel(
        # Model:
        face_nodes: wp.array(dtype=wp.vec3i),
        face_edge_a: wp.array(dtype=wp.vec3),
        face_edge_b: wp.array(dtype=wp.vec3),
        face_load: wp.array(dtype=int),
        loads: wp.array(dtype=PressureLoad),
        table_times: wp.array(dtype=wp.float64),
        table_values: wp.array(dtype=float),
        face_tet: wp.array(dtype=int),
        face_handed_area: wp.array(dtype=wp.vec3),
        face_weight: wp.array(dtype=wp.vec3),
        face_first: int,
        spheres_per_tet: int,
        dt: float,
        dt64: wp.float64,
        # State in:
        time: wp.array(dtype=wp.float64),
        node_u: wp.array(dtype=wp.vec3),
        node_q: wp.array(dtype=wp.vec3),
        node_qd: wp.array(dtype=wp.vec3),
        tet_sphere: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        particle_qd: wp.array(dtype=wp.vec3),
        # State out:
        node_f: wp.array(dtype=wp.vec3),
        node_f_load: wp.array(dtype=wp.vec3),
        node_energy_boundary_work: wp.array(dtype=wp.float64),
        particle_f: wp.array(dtype=wp.vec3),
        load_face_force: wp.array(dtype=wp.vec3),
        load_face_work: wp.array(dtype=wp.float64),
        load_face_impulse: wp.array(dtype=wp.float64),
    ):
        f = wp.tid()  # one thread per loaded face
        n = face_nodes[f]
        load = loads[face_load[f]]
        w = face_weight[f]  # 3 w_k: 1 each on a whole face, so its force rounds as -p/3 a did
        covered = (w[0] + w[1] + w[2]) / 3.0  # the share of the face the load's region covers (1 for a whole face)
        slot = face_first + f
        if n[0] == n[1]:
            # Dropped: its tet converted. Handed over to the tet's spheres where the pass recorded its area.
            first = handed_spheres(f, face_tet, face_handed_area, tet_sphere)
            if first < 0:
                return
            share = 1.0 / float(spheres_per_tet)
            v = wp.vec3(0.0)
            for k in range(spheres_per_tet):
                v = v + particle_qd[first + k]
            x = spheres_centre(particle_q, first, spheres_per_tet)
            p = history(load, time[0] + dt64, x, table_times, table_values)
            force = (-p * covered) * face_handed_area[f]
            if dt > 0.0:
                # The impulse the next kicks deliver, dt |f_{n+1}| (module docstring, Impulse).
                load_face_impulse[slot] = load_face_impulse[slot] + wp.float64(dt * wp.length(force))
                # ½ dt (f_n + f_{n+1})·v_{n+1/2} on the spheres, each with its share (module docstring, Hand-over).
                kept = load_face_force[slot]
                load_face_work[slot] = load_face_work[slot] + wp.float64(0.5 * dt * wp.dot(kept + force, v * share))
            load_face_force[slot] = force
            if p != 0.0:
                for k in range(spheres_per_tet):
                    wp.atomic_add(particle_f, first + k, force * share)
            return
        centroid = (node_q[n[0]] + node_q[n[1]] + node_q[n[2]]) / 3.0
        # The forces belong to the new positions, at t_{n+1} = t_n + dt (the clock advances at the end of the step).
        p = history(load, time[0] + dt64, centroid, table_times, table_values)
        if p == 0.0:
            return
        # f = -p a pushes into the solid; node k takes its share w_k (a third each on a whole face).
        area = area_vector(face_edge_a[f], face_edge_b[f], node_u[n[0]], node_u[n[1]], node_u[n[2]])
        if dt > 0.0:
            load_face_impulse[slot] = load_face_impulse[slot] + wp.float64(dt * covered * p * wp.length(area))
        for k in range(3):
            node = n[k]
            force = ((-p / 3.0) * w[k]) * area
            wp.atomic_add(node_f, node, force)
            wp.atomic_add(node_f_load, node, force)
            if dt > 0.0:
                # The half of Verlet's trapezoid behind the force, ½ dt f_{n+1}·v_{n+1/2} (module docstring).
                wp.atomic_add(node_energy_boundary_work, node, wp.float64(0.5 * dt * wp.dot(force, node_qd[node])))

    return apply_face_pressure_kernel


@functools.cache
def make_load_force_kernel(kind: str) -> wp.Kernel:
    """The kernel that sums the force of each pressure load of one history kind, -p a over its faces [N], at the
    state's own time and positions (the force :func:`make_face_pressure_kernel` applies with dt = 0), for output
    between frames."""
    history = HISTORIES[kind]

    @wp.kernel(enable_backward=False, module="unique")
    def sum_load_forces_kernel(
        # Model:
        face_nodes: wp.array(dtype=wp.vec3i),
        face_edge_a: wp.array(dtype=wp.vec3),
        face_edge_b: wp.array(dtype=wp.vec3),
        face_load: wp.array(dtype=int),
        loads: wp.array(dtype=PressureLoad),
        table_times: wp.array(dtype=wp.float64),
        table_values: wp.array(dtype=float),
        face_tet: wp.array(dtype=int),
        face_handed_area: wp.array(dtype=wp.vec3),
        face_weight: wp.array(dtype=wp.vec3),
        face_first: int,
        spheres_per_tet: int,
        # State in:
        time: wp.array(dtype=wp.float64),
        node_u: wp.array(dtype=wp.vec3),
        node_q: wp.array(dtype=wp.vec3),
        tet_sphere: wp.array(dtype=int),
        particle_q: wp.array(dtype=wp.vec3d),
        # Out:
        load_force: wp.array(dtype=wp.vec3d),
    ):
        f = wp.tid()  # one thread per loaded face
        n = face_nodes[f]
        index = face_load[f]
        w = face_weight[f]  # 3 w_k (:func:`make_face_pressure_kernel`)
        covered = (w[0] + w[1] + w[2]) / 3.0
        force = wp.vec3(0.0)
        if n[0] == n[1]:
            # Handed over to its tet's spheres (:func:`make_face_pressure_kernel`), or dropped before the hand-over.
            first = handed_spheres(f, face_tet, face_handed_area, tet_sphere)
            if first < 0:
                return
            x = spheres_centre(particle_q, first, spheres_per_tet)
            p = history(loads[index], time[0], x, table_times, table_values)
            force = (-p * covered) * face_handed_area[f]
        else:
            centroid = (node_q[n[0]] + node_q[n[1]] + node_q[n[2]]) / 3.0
            p = history(loads[index], time[0], centroid, table_times, table_values)
            area = area_vector(face_edge_a[f], face_edge_b[f], node_u[n[0]], node_u[n[1]], node_u[n[2]])
            force = (-p * covered) * area
        wp.atomic_add(load_force, index, wp.vec3d(wp.float64(force[0]), wp.float64(force[1]), wp.float64(force[2])))

    return sum_load_forces_kernel


@wp.kernel
def apply_dashpots_kernel(
    # Model:
    face_nodes: wp.array(dtype=wp.vec3i),
    face_edge_a: wp.array(dtype=wp.vec3),
    face_edge_b: wp.array(dtype=wp.vec3),
    face_impedance: wp.array(dtype=wp.vec2),
    dt: float,
    # State in:
    node_u: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    # State out:
    node_f: wp.array(dtype=wp.vec3),
    node_f_absorbed: wp.array(dtype=wp.vec3),
    node_energy_absorbed: wp.array(dtype=wp.float64),
):
    f = wp.tid()  # one thread per non-reflecting face
    n = face_nodes[f]
    a = face_area_vector(n, face_edge_a[f], face_edge_b[f], node_u)
    area = wp.length(a)
    if area == 0.0:
        return
    normal = a / area
    third = area / 3.0
    for k in range(3):
        node = n[k]
        v = node_qd[node]
        force = third * lysmer_traction(v, normal, face_impedance[f])
        wp.atomic_add(node_f, node, force)
        # Absorbed as Verlet does the work, -½ dt f_n·(v_{n-1/2} + v_{n+1/2}) ≥ 0 on the whole (v = v_{n-1/2}, the
        # half-step velocity the force is made from): the half behind now, the half ahead at the next evaluation from
        # node_f_absorbed (kernels/integrate.py book_half_ahead_kernel).
        wp.atomic_add(node_energy_absorbed, node, wp.float64(-0.5 * wp.dot(force, v) * dt))
        wp.atomic_add(node_f_absorbed, node, force)


@wp.func
def drive_first_half(
    driver: NodeDriver,
    t_mid: wp.float64,
    dt: float,
    free: wp.vec3,
    v_old: wp.vec3,
    v_kicked: wp.vec3,
    force: wp.vec3,
    mass: float,
):
    """Velocity v_{n+1/2} of a node with a driver, and the driver's work in this half step [J].

    While the driver holds at the step's midpoint t_mid, v = V and the driver does the first half of the trapezoid
    -½ dt f_n · V against the force f_n on the node (gravity included where it counts in the potential). When it
    takes hold or lets go (held at t_mid but not at t_mid - dt, or the reverse), the velocity jumps from v_n to V,
    or V loses its held components: that impulse's work is the jump of ½ m |v|².

    Args:
        free: the node's free components (1) and held ones (0) without the driver. v_old: v_n [m/s].
        v_kicked: v_{n+1/2} of the undriven node [m/s]. force: f_n [N]. mass: m [kg].
    """
    held = driver_holds(driver, t_mid)
    before = driver_holds(driver, t_mid - wp.float64(dt))
    v = v_kicked
    work = float(0.0)
    if held:
        v = driver.velocity
        work = -0.5 * dt * wp.dot(force, v)
    if held != before:
        target = wp.cw_mul(free, v_old)
        if held:
            target = driver.velocity
        work = work + 0.5 * mass * (wp.dot(target, target) - wp.dot(v_old, v_old))
    return v, work


@wp.func
def drive_second_half(driver: NodeDriver, t_mid: wp.float64, dt: float, v_kicked: wp.vec3, force: wp.vec3):
    """Velocity v_{n+1} of a node with a driver and the driver's work [J]: while it holds at t_mid, v = V and the
    second half of the trapezoid, -½ dt f_{n+1} · V."""
    if driver_holds(driver, t_mid):
        return driver.velocity, -0.5 * dt * wp.dot(force, driver.velocity)
    return v_kicked, float(0.0)
