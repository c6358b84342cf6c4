"""Penalty coupling of a sphere to its material point in a still-continuous tet (the overlap zone of the CIMNE
adaptive DEM/FEM scheme, adaptive_dem_fem_blast.txt §4, eqs. 8–9; the host side and the physics are in
warpdem/stages/coupling.py).

Coupling c ties sphere p to tet t: the material point is x_mp = Σ_a N_a x_a, N_a the fixed barycentric coordinates
(``coupling_bary``) and x_a = X_a + u_a the tet's nodes; the gap g = x_mp - x_p; the force k g acts on the sphere and
-N_a k g on node a. Positions: sphere centres are float64, X_a and u_a float32. The gap is formed in float64,
Σ_a N_a ((X_a - x_p) + u_a), exact for the float32 state (each term a difference of points a tet's size apart), and
rounded to float32 once before its rest value is taken off (:func:`coupling_stretch`): g then carries ε₃₂ of itself,
wherever the pair is. Formed in float32
(X_a - x_p rounded to ε₃₂ of the tet's size, ~1e-8 m at 0.1 m) it carried that rounding against gaps of ~1e-6 m at
small strains: the springs' energy and force were off by about 1 % from step to step, so the force was not the gradient
of a smooth U and the books drifted by up to 3e-3 of the energy in play (tests/test_loads_handover.py: a pulsed block
whose top layer alone converted, now within 1.0e-6).
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def tet_barycentric(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, d: wp.vec3) -> wp.vec4:
    """Barycentric coordinates (N_a, N_b, N_c, N_d) of point p in the tet (a, b, c, d) [-]: p = Σ N_i x_i with
    Σ N_i = 1 (ratios of signed volumes; outside the tet some are negative). Pass positions relative to a point near
    the tet (e.g. p itself) so float32 keeps their precision."""
    ba = b - a
    ca = c - a
    da = d - a
    pa = p - a
    vol = wp.dot(ba, wp.cross(ca, da))
    nb = wp.dot(pa, wp.cross(ca, da)) / vol
    nc = wp.dot(ba, wp.cross(pa, da)) / vol
    nd = wp.dot(ba, wp.cross(ca, pa)) / vol
    return wp.vec4(1.0 - nb - nc - nd, nb, nc, nd)


@wp.func
def node_from_point(ref: wp.vec3, u: wp.vec3, x: wp.vec3d) -> wp.vec3:
    """x_a - x [m]: a node (reference position X_a plus displacement u_a, float32) seen from a float64 point, with
    X_a - x in float64 rounded once before u_a is added."""
    return wp.vec3(wp.vec3d(ref) - x) + u


@wp.func
def current_barycentric(
    x: wp.vec3d, nodes: wp.vec4i, node_ref_q: wp.array(dtype=wp.vec3), node_u: wp.array(dtype=wp.vec3)
) -> wp.vec4:
    """The barycentric coordinates of the point now at x in tet ``nodes`` at its current positions X + u: the
    shape functions N_a of eq. 9 of the material point there (an affine map keeps barycentric coordinates, so they
    are also the point's coordinates in the reference configuration), and Σ N_a x_a = x, a coupling of zero gap."""
    o = wp.vec3(0.0)
    return tet_barycentric(
        o,
        node_from_point(node_ref_q[nodes[0]], node_u[nodes[0]], x),
        node_from_point(node_ref_q[nodes[1]], node_u[nodes[1]], x),
        node_from_point(node_ref_q[nodes[2]], node_u[nodes[2]], x),
        node_from_point(node_ref_q[nodes[3]], node_u[nodes[3]], x),
    )


@wp.func
def coupling_gap(
    x: wp.vec3d,
    nodes: wp.vec4i,
    bary: wp.vec4,
    node_ref_q: wp.array(dtype=wp.vec3),
    node_u: wp.array(dtype=wp.vec3),
) -> wp.vec3d:
    """g = x_mp - x_p = Σ_a N_a (x_a - x_p) [m] in float64 (CIMNE eq. 9's constraint residual u_D - N_F u_F, up to
    sign): exact for the float32 X_a, u_a and N_a (module docstring)."""
    g = wp.vec3d(0.0, 0.0, 0.0)
    for a in range(4):
        g += wp.float64(bary[a]) * ((wp.vec3d(node_ref_q[nodes[a]]) - x) + wp.vec3d(node_u[nodes[a]]))
    return g


@wp.func
def coupling_stretch(g: wp.vec3d, rest: wp.vec3) -> wp.vec3:
    """The gap past its rest value at birth, g - g₀ [m] (warpdem.model.State.coupling_rest: g at birth rounded to
    float32): g rounded to float32 first, so a coupling whose pair has not moved since its birth holds exactly zero.
    Subtracted in float64 instead, the rest's own rounding (~1e-15 m) was left as a force of ~1e-6 N at rest, which
    moved the spheres by less than a rounding of their centres and the bonds, whose length resolves to a float32 ulp,
    answered with tens of newtons (dam_crest_blast at rest: tests/test_scenes_at_rest.py). The rounding of g is of
    g's own size (a few 1e-15 m at the ~5e-8 m of a rest gap), not of the tet's."""
    return wp.vec3(g) - rest


@wp.kernel
def eval_coupling_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    node_ref_q: wp.array(dtype=wp.vec3),
    # State in:
    particle_q: wp.array(dtype=wp.vec3d),
    node_u: wp.array(dtype=wp.vec3),
    tet_active: wp.array(dtype=int),
    coupling_count: wp.array(dtype=int),
    coupling_particle: wp.array(dtype=int),
    coupling_tet: wp.array(dtype=int),
    coupling_bary: wp.array(dtype=wp.vec4),
    coupling_k: wp.array(dtype=float),
    coupling_rest: wp.array(dtype=wp.vec3),
    # In:
    track_energy: int,
    # State out:
    coupling_energy_prev: wp.array(dtype=float),
    particle_f: wp.array(dtype=wp.vec3),
    node_f: wp.array(dtype=wp.vec3),
):
    c = wp.tid()  # one thread per coupling slot
    if c >= coupling_count[0]:
        return
    t = coupling_tet[c]
    if tet_active[t] == 0:  # its tet converted: released (compact_coupling removes the slot between steps)
        return
    p = coupling_particle[c]
    nodes = tet_nodes[t]
    bary = coupling_bary[c]
    k = coupling_k[c]
    # The gap past its rest value at birth (the float32 rounding of N_a, warpdem.model.State.coupling_rest).
    g = coupling_stretch(coupling_gap(particle_q[p], nodes, bary, node_ref_q, node_u), coupling_rest[c])
    # Penalty form of eq. 9: U = ½ k |g|², f_p = -∂U/∂x_p = k g, f_a = -∂U/∂x_a = -N_a k g.
    f = k * g
    wp.atomic_add(particle_f, p, f)
    for a in range(4):
        wp.atomic_add(node_f, nodes[a], -bary[a] * f)
    if track_energy != 0:
        coupling_energy_prev[c] = 0.5 * k * wp.dot(g, g)


@wp.kernel
def coupling_energy_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    node_ref_q: wp.array(dtype=wp.vec3),
    # State in:
    particle_q: wp.array(dtype=wp.vec3d),
    node_u: wp.array(dtype=wp.vec3),
    tet_active: wp.array(dtype=int),
    coupling_count: wp.array(dtype=int),
    coupling_particle: wp.array(dtype=int),
    coupling_tet: wp.array(dtype=int),
    coupling_bary: wp.array(dtype=wp.vec4),
    coupling_k: wp.array(dtype=float),
    coupling_rest: wp.array(dtype=wp.vec3),
    # Out:
    energy: wp.array(dtype=wp.float64),
):
    """Each live coupling's spring energy ½ k |g|² [J] into ``energy[c]`` where its tet is active (other slots are not
    written)."""
    c = wp.tid()  # one thread per coupling slot
    if c >= coupling_count[0]:
        return
    t = coupling_tet[c]
    if tet_active[t] == 0:
        return
    g64 = coupling_gap(particle_q[coupling_particle[c]], tet_nodes[t], coupling_bary[c], node_ref_q, node_u)
    g = coupling_stretch(g64, coupling_rest[c])
    energy[c] = wp.float64(0.5 * coupling_k[c]) * wp.float64(wp.dot(g, g))


@wp.kernel
def flag_released_couplings_kernel(
    # State in:
    tet_active: wp.array(dtype=int),
    coupling_count: wp.array(dtype=int),
    coupling_tet: wp.array(dtype=int),
    # Out:
    dead: wp.array(dtype=int),
):
    c = wp.tid()  # one thread per coupling slot
    dead[c] = 0
    if c >= coupling_count[0]:
        return
    if tet_active[coupling_tet[c]] == 0:
        dead[c] = 1


@wp.kernel
def material_point_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    node_ref_q: wp.array(dtype=wp.vec3),
    # State in:
    node_u: wp.array(dtype=wp.vec3),
    # In:
    tets: wp.array(dtype=int),
    points: wp.array(dtype=wp.vec3d),
    # Out:
    bary: wp.array(dtype=wp.vec4),
):
    i = wp.tid()  # one thread per queried point
    bary[i] = current_barycentric(points[i], tet_nodes[tets[i]], node_ref_q, node_u)


@wp.kernel
def coupling_rest_kernel(
    # Model:
    tet_nodes: wp.array(dtype=wp.vec4i),
    node_ref_q: wp.array(dtype=wp.vec3),
    # State in:
    particle_q: wp.array(dtype=wp.vec3d),
    node_u: wp.array(dtype=wp.vec3),
    coupling_count: wp.array(dtype=int),
    coupling_particle: wp.array(dtype=int),
    coupling_tet: wp.array(dtype=int),
    coupling_bary: wp.array(dtype=wp.vec4),
    # In:
    first: int,
    # State out:
    coupling_rest: wp.array(dtype=wp.vec3),
):
    c = wp.tid()  # one thread per coupling slot; only the slots from ``first`` on (new couplings) are written
    if c < first or c >= coupling_count[0]:
        return
    # Born relaxed: the gap now, as eval_coupling_kernel forms it, is the rest it subtracts (the float32 rounding
    # of N_a, a few ε₃₂ of the tet's size).
    p = coupling_particle[c]
    g = coupling_gap(particle_q[p], tet_nodes[coupling_tet[c]], coupling_bary[c], node_ref_q, node_u)
    coupling_rest[c] = wp.vec3(g)
