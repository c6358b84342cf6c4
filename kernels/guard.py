"""Stability guard: finds the first sphere or FEM node whose state is non-finite or runs away.

One pass over the spheres and one over the nodes, launched between runs of steps (never inside the step): a blow-up
of an explicit scheme grows geometrically and never recovers, so the state at the end of a run shows it. Each bad
item offers the key ``NUM_PROBLEMS * index + problem`` to an atomic minimum, so one int holds both the lowest bad
index and the first thing wrong with it; a second slot counts the bad items. The host reads these four ints.

Positions are generic (``Any``): a vec3 or a vec3d array (float64 positions) launches the same kernel.
"""

from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

# What is wrong with an item, in order of report (the lowest code of an item is its key).
PROBLEM_POSITION = wp.constant(0)  # a non-finite position (sphere centre or node displacement)
PROBLEM_VELOCITY = wp.constant(1)  # a non-finite velocity
PROBLEM_SPIN = wp.constant(2)  # a non-finite angular velocity (spheres)
PROBLEM_SPEED = wp.constant(3)  # speed above the run-away bound
PROBLEM_REACH = wp.constant(4)  # speed × dt above the contact reach's fraction (warpdem.stages.guard.reach_speed)
PROBLEM_PENETRATION = wp.constant(5)  # a free sphere's centre behind a wall: overlap past its radius
NUM_PROBLEMS = wp.constant(6)
NO_PROBLEM = wp.constant(6)

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


@wp.kernel
def check_spheres_kernel(
    # Model:
    speed_limit: float,
    gravity_norm: float,
    reach_speed: float,
    num_walls: int,
    wall_normal: wp.array(dtype=wp.vec3),
    particle_inv_mass: wp.array(dtype=float),
    # State in:
    particle_count_in: wp.array(dtype=int),
    particle_q_in: wp.array(dtype=Any),
    particle_qd_in: wp.array(dtype=wp.vec3),
    particle_omega_in: wp.array(dtype=wp.vec3),
    time_in: wp.array(dtype=wp.float64),
    wall_point_in: wp.array(dtype=wp.vec3d),
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
    if problem != NO_PROBLEM:
        report_problem(i, problem, SPHERE_KEY, report)


@wp.kernel
def check_nodes_kernel(
    # Model:
    speed_limit: float,
    gravity_norm: float,
    reach_speed: float,
    # State in:
    node_count_in: wp.array(dtype=int),
    node_u_in: wp.array(dtype=Any),
    node_qd_in: wp.array(dtype=wp.vec3),
    time_in: wp.array(dtype=wp.float64),
    # Out:
    report: wp.array(dtype=int),
):
    n = wp.tid()  # one thread per FEM node slot
    if n >= node_count_in[0]:
        return
    problem = point_problem(node_u_in[n], node_qd_in[n], speed_bound(speed_limit, gravity_norm, time_in), reach_speed)
    if problem != NO_PROBLEM:
        report_problem(n, problem, NODE_KEY, report)
