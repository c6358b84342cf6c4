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
NUM_PROBLEMS = wp.constant(4)
NO_PROBLEM = wp.constant(4)

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
def point_problem(q: Any, v: wp.vec3, bound: float) -> int:
    """The first thing wrong with a point of position ``q`` [m] and velocity ``v`` [m/s] (NO_PROBLEM if none)."""
    if not wp.isfinite(q):
        return PROBLEM_POSITION
    if not wp.isfinite(v):
        return PROBLEM_VELOCITY
    if wp.dot(v, v) > bound * bound:
        return PROBLEM_SPEED
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
    # State in:
    particle_count_in: wp.array(dtype=int),
    particle_q_in: wp.array(dtype=Any),
    particle_qd_in: wp.array(dtype=wp.vec3),
    particle_omega_in: wp.array(dtype=wp.vec3),
    time_in: wp.array(dtype=wp.float64),
    # Out:
    report: wp.array(dtype=int),
):
    i = wp.tid()  # one thread per sphere slot
    if i >= particle_count_in[0]:
        return
    problem = point_problem(particle_q_in[i], particle_qd_in[i], speed_bound(speed_limit, gravity_norm, time_in))
    if problem > PROBLEM_VELOCITY and not wp.isfinite(particle_omega_in[i]):
        problem = PROBLEM_SPIN
    if problem != NO_PROBLEM:
        report_problem(i, problem, SPHERE_KEY, report)


@wp.kernel
def check_nodes_kernel(
    # Model:
    speed_limit: float,
    gravity_norm: float,
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
    problem = point_problem(node_u_in[n], node_qd_in[n], speed_bound(speed_limit, gravity_norm, time_in))
    if problem != NO_PROBLEM:
        report_problem(n, problem, NODE_KEY, report)
