"""Stability guard: finds the first sphere or FEM node whose state is non-finite or runs away.

One pass over the spheres and one over the nodes, launched between runs of steps (never inside the step): a blow-up
of an explicit scheme grows geometrically and never recovers, so the state at the end of a run shows it. Each bad
item offers the key ``NUM_PROBLEMS * index + problem`` to an atomic minimum, so one int holds both the lowest bad
index and the first thing wrong with it; a second slot counts the bad items. The host reads these four ints.

Penetration past what a contact resolves (issue 30), whether or not the step is stable:

- a free sphere whose centre is behind a wall (an overlap past its radius: the wall now pushes it on through), or a
  surface node of the rock deeper behind a wall than the deepest reach of the node–face contact (``face_depth_max``,
  half the largest tet height over a boundary face: its boundary tets have passed the wall);
- two spheres of which the smaller's centre lies inside the larger, an overlap of at least the smaller radius (a
  wall is a sphere of infinite radius: the same rule). A penalty or Hertz contact at its design load overlaps a few
  percent of the radius, and the hardest impact of the shipped scenes 0.64 of it (bonded_slab_impact: a steel ball
  at 15 m/s on soft concrete); past the radius the normal turns with the centres' line through each other. Pairs of
  two spheres that do not move (fixed, prescribed) are left alone: a user may overlap them on purpose;
- a sphere or node that went past a face's reach in a step (kernels/fem_contact.py ``passed_face``: a node let go
  of by a face it had gone half the tet's height behind, its spring compressed by at least half that; kernels/
  sphere_face.py: a sphere centre behind a face it projects into). The contact stops pushing there, so the body moves
  on through the rock and no later state shows where: the contact kernels record the face where it happens, these
  passes read it. A sphere tied to the continuum by a penalty coupling (the overlap zone of FEM→DEM conversion,
  warpdem.stages.coupling) follows the rock it is tied to and may lie in it: its record is dropped
  (``drop_coupled_records_kernel``).

Positions are generic (``Any``): a vec3 or a vec3d array (float64 positions) launches the same kernel.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from .fem_contact import wall_gap

wp.set_module_options({"enable_backward": False})

# What is wrong with an item, in order of report (the lowest code of an item is its key).
PROBLEM_POSITION = wp.constant(0)  # a non-finite position (sphere centre or node displacement)
PROBLEM_VELOCITY = wp.constant(1)  # a non-finite velocity
PROBLEM_SPIN = wp.constant(2)  # a non-finite angular velocity (spheres)
PROBLEM_SPEED = wp.constant(3)  # speed above the run-away bound
PROBLEM_REACH = wp.constant(4)  # speed × dt above the contact reach's fraction (warpdem.stages.guard.reach_speed)
PROBLEM_PENETRATION = wp.constant(5)  # behind a wall past the contact's reach (a sphere's centre, a node)
PROBLEM_OVERLAP = wp.constant(6)  # a sphere's centre inside another sphere, or the smaller one's inside it
PROBLEM_PASSED_FACE = wp.constant(7)  # went past a face's reach in a step (the FEM contact's record)
NUM_PROBLEMS = wp.constant(8)
NO_PROBLEM = wp.constant(8)

# Slots of the guard's report array (int32, shape (4,)).
SPHERE_KEY = wp.constant(0)  # lowest NUM_PROBLEMS * sphere slot + problem, or NO_KEY
SPHERE_COUNT = wp.constant(1)  # bad spheres
NODE_KEY = wp.constant(2)  # the same for FEM nodes
NODE_COUNT = wp.constant(3)
NO_KEY = wp.constant(2147483647)


@wp.func
def speed_bound(speed_limit: float, gravity_norm: float, time: wp.array(dtype=wp.float64)) -> float:
    """Run-away bound on a speed at the current time [m/s]: the scene's bound plus what gravity can add, |g| t."""
    return speed_limit + gravity_norm * float(time[0])


@wp.func
def point_problem(q: Any, v: wp.vec3, bound: float, reach_speed: float) -> int:
    """The first thing wrong with a point of position ``q`` [m] and velocity ``v`` [m/s] (NO_PROBLEM if none):
    ``bound`` is the run-away bound, ``reach_speed`` the fastest it may move for the contact reach [m/s]."""
    if not wp.isfinite(q):
        return PROBLEM_POSITION
    if not wp.isfinite(v):
        return PROBLEM_VELOCITY
    if wp.dot(v, v) > bound * bound:
        return PROBLEM_SPEED
    if wp.dot(v, v) > reach_speed * reach_speed:
        return PROBLEM_REACH
    return NO_PROBLEM


@wp.func
def report_problem(index: int, problem: int, slot: int, report: wp.array(dtype=int)):
    """Offer a bad item to the report: the lowest key wins, every bad item counts."""
    wp.atomic_min(report, slot, NUM_PROBLEMS * index + problem)
    wp.atomic_add(report, slot + 1, 1)


@wp.func
def centre_inside(xi: Any, xj: Any, ri: float, rj: float) -> bool:
    """Whether of two spheres (centres xi, xj [m], radii ri, rj [m]) the smaller's centre lies inside the larger: an
    overlap ri + rj - d of at least the smaller radius, d <= max(ri, rj) (the difference in the centres' precision)."""
    d = wp.vec3(wp.vec3d(xi) - wp.vec3d(xj))
    rmax = wp.max(ri, rj)
    return wp.dot(d, d) <= rmax * rmax


@wp.kernel
def drop_coupled_records_kernel(
    # State in:
    coupling_count_in: wp.array(dtype=int),
    coupling_particle_in: wp.array(dtype=int),
    # Out:
    sphere_passed: wp.array(dtype=int),
):
    c = wp.tid()  # one thread per coupling slot: its sphere's record of a face passed is dropped
    if c >= coupling_count_in[0]:
        return
    sphere_passed[coupling_particle_in[c]] = -1  # several couplings of one sphere write the same value


@wp.kernel
def check_spheres_kernel(
    # Model:
    speed_limit: float,
    gravity_norm: float,
    reach_speed: float,
    num_walls: int,
    wall_normal: wp.array(dtype=wp.vec3),
    particle_inv_mass: wp.array(dtype=float),
    particle_radius: wp.array(dtype=float),
    max_neighbors: int,
    # State in:
    particle_count_in: wp.array(dtype=int),
    particle_q_in: wp.array(dtype=Any),
    particle_qd_in: wp.array(dtype=wp.vec3),
    particle_omega_in: wp.array(dtype=wp.vec3),
    time_in: wp.array(dtype=wp.float64),
    wall_point_in: wp.array(dtype=wp.vec3d),
    nbr_count_in: wp.array(dtype=int),
    nbr_index_in: wp.array(dtype=int),
    # In:
    sphere_passed: wp.array(dtype=int),
    # Out:
    report: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per sphere slot
    if i >= particle_count_in[0]:
        return
    problem = point_problem(
        particle_q_in[i], particle_qd_in[i], speed_bound(speed_limit, gravity_norm, time_in), reach_speed
    )
    if problem > PROBLEM_VELOCITY and not wp.isfinite(particle_omega_in[i]):
        problem = PROBLEM_SPIN
    if problem == NO_PROBLEM and particle_inv_mass[i] > 0.0:
        # A wall's contact holds a sphere while the overlap r - gap stays below r; a centre behind the plane
        # (gap < 0) has passed what the contact resolves, and the plane now pushes it further through.
        for w in range(num_walls):
            if wp.dot(wp.vec3(wp.vec3d(particle_q_in[i]) - wall_point_in[w]), wall_normal[w]) < 0.0:
                problem = PROBLEM_PENETRATION
    if problem == NO_PROBLEM and i < sphere_passed.shape[0]:
        if sphere_passed[i] >= 0:
            problem = PROBLEM_PASSED_FACE
    if problem == NO_PROBLEM and max_neighbors > 0:
        # Its half list (j > i): each pair once, from the lower index.
        xi = particle_q_in[i]
        ri = particle_radius[i]
        for s in range(wp.min(nbr_count_in[i], max_neighbors)):
            j = nbr_index_in[i * max_neighbors + s]
            if particle_inv_mass[i] > 0.0 or particle_inv_mass[j] > 0.0:
                if centre_inside(xi, particle_q_in[j], ri, particle_radius[j]):
                    problem = PROBLEM_OVERLAP
    if problem != NO_PROBLEM:
        report_problem(i, problem, SPHERE_KEY, report)


@wp.kernel
def check_nodes_kernel(
    # Model:
    speed_limit: float,
    gravity_norm: float,
    reach_speed: float,
    num_walls: int,
    wall_normal: wp.array(dtype=wp.vec3),
    node_inv_mass: wp.array(dtype=float),
    node_contact_stiffness: wp.array(dtype=float),
    face_depth_max: float,
    # State in:
    node_count_in: wp.array(dtype=int),
    node_u_in: wp.array(dtype=Any),
    node_q_in: wp.array(dtype=wp.vec3),
    node_qd_in: wp.array(dtype=wp.vec3),
    time_in: wp.array(dtype=wp.float64),
    wall_point_in: wp.array(dtype=wp.vec3d),
    # In:
    node_passed: wp.array(dtype=int),
    # Out:
    report: wp.array(dtype=int),
):
    n = wp.tid()  # one thread per FEM node slot
    if n >= node_count_in[0]:
        return
    problem = point_problem(node_u_in[n], node_qd_in[n], speed_bound(speed_limit, gravity_norm, time_in), reach_speed)
    if problem == NO_PROBLEM and n < node_passed.shape[0]:
        if node_passed[n] >= 0:
            problem = PROBLEM_PASSED_FACE
    if problem == NO_PROBLEM and n < node_contact_stiffness.shape[0] and node_inv_mass[n] > 0.0:
        if node_contact_stiffness[n] > 0.0:  # a surface node: a wall spring holds it
            for w in range(num_walls):
                if wall_gap(node_q_in[n], wall_point_in[w], wall_normal[w]) < -face_depth_max:
                    problem = PROBLEM_PENETRATION
    if problem != NO_PROBLEM:
        report_problem(n, problem, NODE_KEY, report)
