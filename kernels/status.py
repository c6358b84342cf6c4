"""The chunk status (warpdem.stages.status): what the host must know after a run of steps, gathered on the device
into one small vector read back once (issue 24), where each stage read its own counters and whole flag arrays."""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

# Slots of the status vector (float64: every entry is an integer below 2^31 or the clock, all exact).
NBR_NEEDED = wp.constant(0)
SPHERE_FACE_NEEDED = wp.constant(1)
NODE_FACE_NEEDED = wp.constant(2)
TIME = wp.constant(3)
GUARD = wp.constant(4)  # four slots: the guard's report (key and count of bad spheres, of bad nodes)
BONDS_BROKEN = wp.constant(8)
COHESIVE_BROKEN = wp.constant(9)
COHESIVE_COUNT = wp.constant(10)
SLOTS = 11


@wp.kernel
def chunk_status_kernel(
    # State in:
    nbr_needed: wp.array(dtype=int),
    sphere_face_needed: wp.array(dtype=int),
    node_face_needed: wp.array(dtype=int),
    time: wp.array(dtype=wp.float64),
    bond_count: wp.array(dtype=int),
    bond_broken: wp.array(dtype=int),
    cohesive_count: wp.array(dtype=int),
    cohesive_broken: wp.array(dtype=int),
    # In:
    clean_report: wp.array(dtype=int),
    # Out (status zeroed before the launch; the guard's report read and reset to clean for the next check):
    report: wp.array(dtype=int),
    status: wp.array(dtype=wp.float64),
):
    k = wp.tid()  # one thread per bond and cohesive slot (over the larger capacity, at least one)
    if k == 0:
        status[NBR_NEEDED] = wp.float64(nbr_needed[0])
        status[SPHERE_FACE_NEEDED] = wp.float64(sphere_face_needed[0])
        status[NODE_FACE_NEEDED] = wp.float64(node_face_needed[0])
        status[TIME] = time[0]
        status[COHESIVE_COUNT] = wp.float64(cohesive_count[0])
        for r in range(4):
            status[GUARD + r] = wp.float64(report[r])
            report[r] = clean_report[r]
    if k < bond_count[0]:
        if bond_broken[k] != 0:
            wp.atomic_add(status, BONDS_BROKEN, wp.float64(1.0))
    if k < cohesive_count[0]:
        if cohesive_broken[k] != 0:
            wp.atomic_add(status, COHESIVE_BROKEN, wp.float64(1.0))


@wp.kernel
def list_needs_kernel(
    # State in:
    nbr_needed: wp.array(dtype=int),
    sphere_face_needed: wp.array(dtype=int),
    node_face_needed: wp.array(dtype=int),
    # Out:
    needs: wp.array(dtype=int),
):
    _i = wp.tid()  # one thread: the lists' largest counts since their last build, for one read-back
    needs[0] = nbr_needed[0]
    needs[1] = sphere_face_needed[0]
    needs[2] = node_face_needed[0]
