"""Scatter or gather: the tets' nodal forces summed with float atomics (what the step does, kernels/tets.py
``eval_tet_forces_kernel``) against a deterministic gather (each tet writes its four nodal forces to its own slots,
then each node adds its star's in the star's order), on the vibrating block of ``bench tets`` (issue 24,
"Deterministic forces").

    python benchmarks/gather_forces.py [--tets 200000 1000000] [--repeat 5] [--device cpu]

A float atomic add lands in whatever order the threads arrive, so on a GPU two runs can differ in the last bit of a
node's force (and then everywhere); the CPU runs a kernel's threads in order, so there the scatter is already
deterministic and the question is only its cost. The gather fixes the order on every device: node v sums
``tet_force[4 t + k]`` over its star ``star_tets[star_offset[v] ..]`` (sorted tet ids, kept by every topology pass).

Checked before timing (each run): the gather's forces equal the scatter's to float32 rounding (a node's force is a sum
of at most ``star_count`` terms, each exact in both, added in another order: within (star_count − 1) ε₃₂ Σ|f| of each
other), on the CPU bit for bit (its scatter adds tet by tet in thread order, which is the star's sorted order), and
two gathers are bit-identical. Reported: ms per evaluation of the scatter, of the gather (both kernels)
and the bytes the gather adds per tet.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp
from warpdem.kernels.tets import (
    J_MIN,
    TET_ACTIVE,
    TetMaterial,
    bulk_viscosity_pressure,
    cofactor,
    deformation_cofactor,
    det_minus_one,
    director_forces,
    displacement_gradient,
    shifted_pressure,
    stretch_less_cofactor,
)
from warpdem.kernels.topology import local_index

from warpdem.bench.tets import vibrating_block
from warpdem.stages.tets import eval_tets

EPS32 = float(np.finfo(np.float32).eps)


@wp.kernel
def tet_forces_to_slots_kernel(
    tet_nodes: wp.array(dtype=wp.vec4i),
    tet_inv_ref: wp.array(dtype=wp.mat33),
    tet_volume: wp.array(dtype=float),
    tet_length: wp.array(dtype=float),
    tet_material: wp.array(dtype=int),
    tet_material_table: wp.array(dtype=TetMaterial),
    tet_count: wp.array(dtype=int),
    tet_active: wp.array(dtype=int),
    node_u: wp.array(dtype=wp.vec3),
    node_qd: wp.array(dtype=wp.vec3),
    # Out:
    tet_force: wp.array(dtype=wp.vec3),
):
    """The forces of eval_tet_forces_kernel (elastic and viscous together), node k of tet t into tet_force[4 t + k]
    (zeros for an inactive tet: the star lists active tets only, but a slot is never left stale)."""
    t = wp.tid()
    if t >= tet_count[0]:
        return
    if tet_active[t] != TET_ACTIVE:
        for k in range(4):
            tet_force[4 * t + k] = wp.vec3(0.0)
        return
    n = tet_nodes[t]
    inv_ref = tet_inv_ref[t]
    mat = tet_material_table[tet_material[t]]
    h = displacement_gradient(node_u[n[0]], node_u[n[1]], node_u[n[2]], node_u[n[3]], inv_ref)
    cof_h = cofactor(h)
    cof = deformation_cofactor(h, cof_h)
    j_minus_one = det_minus_one(h, cof_h)
    a = inv_ref * wp.transpose(cof)
    v0 = node_qd[n[0]]
    j_rate = wp.dot(a[0], node_qd[n[1]] - v0) + wp.dot(a[1], node_qd[n[2]] - v0) + wp.dot(a[2], node_qd[n[3]] - v0)
    q = bulk_viscosity_pressure(j_rate / wp.max(1.0 + j_minus_one, J_MIN), tet_length[t], mat)
    pressure = shifted_pressure(j_minus_one, mat) - q
    forces = director_forces(stretch_less_cofactor(h, cof_h), a, pressure, mat.mu, tet_volume[t], inv_ref)
    tet_force[4 * t + 0] = -(forces[0] + forces[1] + forces[2])
    tet_force[4 * t + 1] = forces[0]
    tet_force[4 * t + 2] = forces[1]
    tet_force[4 * t + 3] = forces[2]


@wp.kernel
def gather_node_forces_kernel(
    tet_nodes: wp.array(dtype=wp.vec4i),
    star_offset: wp.array(dtype=int),
    star_count: wp.array(dtype=int),
    star_tets: wp.array(dtype=int),
    node_count: wp.array(dtype=int),
    tet_force: wp.array(dtype=wp.vec3),
    # Out:
    node_f: wp.array(dtype=wp.vec3),
):
    """node_f[v] += Σ over v's star, in star order, of the tet's force on v. One thread per node."""
    v = wp.tid()
    if v >= node_count[0]:
        return
    acc = wp.vec3(0.0)
    first = star_offset[v]
    for s in range(star_count[v]):
        t = star_tets[first + s]
        acc += tet_force[4 * t + local_index(tet_nodes[t], v)]
    node_f[v] = node_f[v] + acc


def gather(sim, tet_force: wp.array) -> None:
    m, s = sim.model, sim.state
    wp.launch(
        tet_forces_to_slots_kernel,
        dim=m.tet_capacity,
        inputs=[
            m.tet_nodes,
            m.tet_inv_ref,
            m.tet_volume if m.tet_band_volume is None else m.tet_band_volume,
            m.tet_length,
            m.tet_material,
            m.tet_material_table,
            s.tet_count,
            s.tet_active,
            s.node_u,
            s.node_qd,
        ],
        outputs=[tet_force],
        device=m.device,
    )
    wp.launch(
        gather_node_forces_kernel,
        dim=m.node_capacity,
        inputs=[m.tet_nodes, m.star_offset, m.star_count, m.star_tets, s.node_count, tet_force],
        outputs=[s.node_f],
        device=m.device,
    )


def best_ms(f, repeat: int, device: str) -> float:
    f()
    wp.synchronize_device(device)
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        for _ in range(10):
            f()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t) / 10)
    return 1e3 * min(times)


def compare(tets: int, device: str, repeat: int) -> dict:
    """Check and time one size; returns the row's figures."""
    sim = vibrating_block(tets, device)
    sim.advance(20)  # a vibrating state: every tet strained, the viscous pressure live in some
    m, s = sim.model, sim.state
    tet_force = wp.zeros(4 * m.tet_capacity, dtype=wp.vec3, device=device)
    nn = int(s.node_count.numpy()[0])

    def scatter_forces() -> np.ndarray:
        s.node_f.zero_()
        eval_tets(m, s, dt=0.0)  # dt = 0: the same forces, nothing booked
        return s.node_f.numpy()[:nn].copy()

    def gather_forces() -> np.ndarray:
        s.node_f.zero_()
        gather(sim, tet_force)
        return s.node_f.numpy()[:nn].copy()

    f_scatter, f_gather, f_again = scatter_forces(), gather_forces(), gather_forces()
    assert np.array_equal(f_gather.view(np.uint32), f_again.view(np.uint32)), "two gathers differ"
    # Σ|f| per node bounds the rounding of either order: (star_count - 1) ε₃₂ Σ|f_t| (float32 sums of the same terms).
    star = m.star_count.numpy()[:nn].astype(np.float64)
    slots = tet_force.numpy().reshape(-1, 4, 3)
    nodes = m.tet_nodes.numpy()[: int(s.tet_count.numpy()[0])]
    magnitude = np.zeros(nn)
    np.add.at(magnitude, nodes.ravel(), np.linalg.norm(slots[: len(nodes)], axis=2).ravel())
    bound = np.maximum(star - 1.0, 1.0) * EPS32 * magnitude * np.sqrt(3.0) + 1e-30
    diff = np.linalg.norm(f_gather.astype(np.float64) - f_scatter, axis=1)
    worst = float(np.max(diff / bound))
    assert worst <= 1.0, f"gather and scatter differ beyond rounding: {worst:.2f} of the bound"
    if wp.get_device(device).is_cpu:
        # The CPU adds a scatter's terms in thread order, tet by tet: the star's sorted order, so the two agree
        # bit for bit there (and a gather on a GPU reproduces the CPU's tet forces exactly).
        assert np.array_equal(f_gather.view(np.uint32), f_scatter.view(np.uint32)), "CPU gather != CPU scatter"
    scatter_ms = best_ms(lambda: eval_tets(m, s, dt=0.0), repeat, device)
    gather_ms = best_ms(lambda: gather(sim, tet_force), repeat, device)
    return {
        "tets": int(s.tet_count.numpy()[0]),
        "nodes": nn,
        "scatter_ms": scatter_ms,
        "gather_ms": gather_ms,
        "ratio": gather_ms / scatter_ms,
        "worst_of_bound": worst,
        "extra_bytes_per_tet": 4 * 12 * 2,  # four vec3 written, then read back by the stars
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tets", type=int, nargs="+", default=[200_000, 1_000_000], help="tets wanted")
    p.add_argument("--repeat", type=int, default=5, help="timed runs of 10 evaluations; the fastest counts")
    p.add_argument("--device", default="cpu")
    a = p.parse_args()
    from warpdem.cli import init_warp

    init_warp()
    print(f"{'tets':>9} {'nodes':>8} {'scatter ms':>11} {'gather ms':>10} {'gather/scatter':>15} {'diff/bound':>11}")
    for n in a.tets:
        r = compare(n, a.device, a.repeat)
        print(
            f"{r['tets']:>9} {r['nodes']:>8} {r['scatter_ms']:>11.2f} {r['gather_ms']:>10.2f} {r['ratio']:>15.2f} "
            f"{r['worst_of_bound']:>11.3f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
