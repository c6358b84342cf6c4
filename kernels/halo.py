"""Kernels of a subdomain's per-step exchange (warpdem.parallel.subdomain): the Verlet-skin test over the spheres a
rank owns, for the list rebuild every rank decides together, and the same test against the migration margin."""

from __future__ import annotations

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
