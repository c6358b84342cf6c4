"""Kernels of a subdomain's per-step exchange (warpdem.parallel.subdomain, .continuum): the Verlet-skin test over the
items a rank owns, for the list rebuild every rank decides together, and the same test against the migration margin;
and the halo messages' rows packed from and unpacked into the items' arrays."""

from __future__ import annotations

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def owned_moved_kernel(
    # Model:
    half_skin: float,
    margin: float,
    # State in:
    particle_count: wp.array(dtype=int),
    particle_owned: wp.array(dtype=int),
    particle_q: wp.array(dtype=wp.vec3d),
    particle_q_at_build: wp.array(dtype=wp.vec3d),
    particle_q_at_migration: wp.array(dtype=wp.vec3d),
    # Out (zeroed before the launch):
    moved: wp.array(dtype=int),
):
    """``moved[0] = 1`` when an owned sphere moved more than half the skin since the list was built: the drift's own
    test (kernels/integrate.py drift_particle) over owned spheres only, since a ghost drifts on a partial force between
    two halo messages and its owner tests it with its true position. ``moved[1] = 1`` when one moved more than
    ``margin`` [m] since the spheres last migrated."""
    i = wp.tid()  # one thread per particle slot
    if i >= particle_count[0] or particle_owned[i] == 0:
        return
    x = particle_q[i]
    d = wp.vec3(x - particle_q_at_build[i])
    if wp.dot(d, d) > half_skin * half_skin:
        moved[0] = 1
    d = wp.vec3(x - particle_q_at_migration[i])
    if wp.dot(d, d) > margin * margin:
        moved[1] = 1


@wp.kernel
def owned_nodes_moved_kernel(
    # Model:
    half_fem_skin: float,
    margin: float,
    node_contact_stiffness: wp.array(dtype=float),
    # State in:
    node_count: wp.array(dtype=int),
    node_owned: wp.array(dtype=int),
    node_q: wp.array(dtype=wp.vec3),
    node_q_at_fem_build: wp.array(dtype=wp.vec3),
    node_q_at_decomposition: wp.array(dtype=wp.vec3),
    joint_failed: wp.array(dtype=int),
    # Out (zeroed before the launch):
    moved: wp.array(dtype=int),
):
    """``moved[0] = 1`` when an owned contact node moved more than half the FEM skin since the FEM lists were built
    (the node drift's own test, kernels/neighbors.py flag_past_half_fem_skin, over owned nodes only; ``half_fem_skin``
    < 0: no FEM contact), or a joint element this rank holds failed in the last step (``joint_failed[0]``: its pair
    enters the lists at this step's build, kernels/joints.py); ``moved[1] = 1`` when an owned node moved more than
    ``margin`` [m] since the items were last decomposed."""
    i = wp.tid()  # one thread per node slot
    if i == 0 and joint_failed[0] != 0:
        moved[0] = 1
    if i >= node_count[0] or node_owned[i] == 0:
        return
    x = node_q[i]
    if half_fem_skin >= 0.0:
        if node_contact_stiffness[i] != 0.0:
            d = x - node_q_at_fem_build[i]
            if wp.dot(d, d) > half_fem_skin * half_fem_skin:
                moved[0] = 1
    d = x - node_q_at_decomposition[i]
    if wp.dot(d, d) > margin * margin:
        moved[1] = 1


@wp.kernel
def forget_ghost_records_kernel(
    # State in:
    count: wp.array(dtype=int),
    owned: wp.array(dtype=int),
    # Out:
    passed: wp.array(dtype=int),
):
    """Clear the faces a ghost went past (-1, warpdem.stages.guard): its owner judges it; a ghost at the rim of what a
    rank holds misses faces its owner sees, and its record would stop the run for nothing."""
    i = wp.tid()  # one thread per slot
    if i < count[0] and owned[i] == 0:
        passed[i] = -1


@wp.kernel
def pack_rows_kernel(
    a: wp.array(dtype=Any),
    b: wp.array(dtype=Any),
    c: wp.array(dtype=Any),
    index: wp.array(dtype=int),
    # Out:
    rows: wp.array(dtype=Any),
):
    """Row r of a halo message (three vec3 of the message's precision, ``rows[3 r .. 3 r + 2]``) from item
    ``index[r]`` of the three fields ``a``, ``b``, ``c`` (vec3 or vec3d each; a float32 value is exact in float64).
    One thread per row; ``index`` holds every destination's rows, one after the other."""
    r = wp.tid()
    k = index[r]
    rows[3 * r] = rows.dtype(a[k])
    rows[3 * r + 1] = rows.dtype(b[k])
    rows[3 * r + 2] = rows.dtype(c[k])


@wp.kernel
def unpack_rows_kernel(
    rows: wp.array(dtype=Any),
    index: wp.array(dtype=int),
    # Out:
    a: wp.array(dtype=Any),
    b: wp.array(dtype=Any),
    c: wp.array(dtype=Any),
):
    """Item ``index[r]`` of the three fields from row r of the received messages (:func:`pack_rows_kernel`'s layout;
    a float32 field gets back the float32 value its owner sent). One thread per row."""
    r = wp.tid()
    k = index[r]
    a[k] = a.dtype(rows[3 * r])
    b[k] = b.dtype(rows[3 * r + 1])
    c[k] = c.dtype(rows[3 * r + 2])
