"""The energy books reduced on the device (kernels/books.py, warpdem.stages.energy.DeviceBooks) against the books
summed on the host (tests/books_reference.py: every array read back whole, the kinetic energies, gravity potential,
shadow term, joint springs and rigid bodies in NumPy).

Oracle: both compute every term in float64 from the same float32 (and float64) state and add the terms in a different
order, so a line differs by float64 rounding only. A sum of N terms in any order is within (N − 1) ε₆₄ Σ|t| of the
exact sum, and each term is a product of a few float64 roundings (≤ TERM_ROUNDINGS ε₆₄ |t|), so

    |device − reference| ≤ (2 N + TERM_ROUNDINGS) ε₆₄ Σ|t|,

N bounded by the model's slot count, Σ|t| from the reference summed over the terms' magnitudes. The states are
shipped scenes after a frame (spheres, bonds and walls; tets with cohesive elements; a conversion with couplings,
sphere–face contacts and loaded faces; rigid blocks on rollers) and a bonded joint, each as run and again with every
booked per-item array, velocity and force filled with random values, past the live counts too: a slot beyond a count
entering a sum would be off by O(1) of the line.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import warp as wp
from books_reference import reference_balance

from warpdem.api import build
from warpdem.build.builder import ModelBuilder
from warpdem.build.mesh import box_mesh
from warpdem.scene import default_scene_path
from warpdem.simulation import Simulation
from warpdem.stages.energy import LINE, DeviceBooks, EnergyBalance
from warpdem.stages.joints import JointProps
from warpdem.stages.rigid import has_bodies
from warpdem.tables import TET_FACES

EPS64 = float(np.finfo(np.float64).eps)
TERM_ROUNDINGS = 16
"""float64 roundings in one term (a product of up to four factors, a dot product, a rotation), with margin."""

SCENES = {
    "default": (default_scene_path(), 1),
    "pmma_plate": ("scenes/pmma_plate.toml", 1),
    "masonry_wall_blast": ("scenes/masonry_wall_blast.toml", 1),
    "rigid_slope": ("scenes/rigid_slope.toml", 4),
}


def slots(model) -> int:
    """Every slot a line may sum over: a bound on any line's number of terms."""
    m = model
    return (
        m.particle_capacity
        + m.node_capacity
        + m.tet_capacity
        + m.bond_capacity
        + m.coupling_capacity
        + m.cohesive_capacity
        + m.joint_capacity
        + max(m.face_capacity, 1)
    )


def assert_books_match(model, state, where: str) -> EnergyBalance:
    books = DeviceBooks(model)
    device = books.read(model, state)
    again = books.evaluate(model, state).numpy()
    # One order of summation per device: the same state gives the same bits.
    np.testing.assert_array_equal(again, [getattr(device, name) for name in LINE], err_msg=f"{where}: not repeatable")
    reference = reference_balance(model, state)
    magnitude = reference_balance(model, state, absolute=True)
    n = slots(model)
    for name in LINE:
        dev, ref, scale = getattr(device, name), getattr(reference, name), abs(getattr(magnitude, name))
        bound = (2 * n + TERM_ROUNDINGS) * EPS64 * scale
        assert abs(dev - ref) <= bound, f"{where}: {name} device {dev!r} reference {ref!r} (bound {bound:.3g})"
    return device


def scramble(model, state, seed: int) -> None:
    """Random values in every booked per-item array and accumulator, the velocities and forces of spheres, nodes and
    bodies (past the live counts too) and the bodies' roller constraints; positions and counts as they are."""
    rng = np.random.default_rng(seed)
    s = state

    def fill(a: wp.array | None, positive: bool = False) -> None:
        if a is None or a.shape[0] == 0:
            return
        values = rng.normal(size=a.numpy().shape)
        a.assign((np.abs(values) if positive else values).astype(a.numpy().dtype))

    for name in (
        "energy_damping",
        "energy_friction",
        "energy_bond_broken",
        "energy_boundary_work",
        "energy_stiffness_change",
        "energy_bond_trapezoid",
        "sphere_face_dissipated",
        "node_energy_damping",
        "node_energy_boundary_work",
        "node_energy_absorbed",
        "node_energy_cohesive",
        "node_energy_cohesive_trapezoid",
        "node_energy_contact",
        "node_energy_sphere_face",
        "load_face_work",
        "energy_released_conversion",
        "energy_released_rigid",
        "energy_contact_topology",
        "energy_step_change",
        "particle_qd",
        "particle_omega",
        "particle_f",
        "particle_t",
        "node_qd",
        "node_f",
    ):
        fill(getattr(s, name, None))
    if model.cohesive_capacity:
        fill(s.cohesive_energy_prev, positive=True)
        s.cohesive_broken.assign(rng.integers(0, 2, model.cohesive_capacity).astype(np.int32))
    if has_bodies(s):
        for name in ("body_v", "body_l", "body_f", "body_t"):
            fill(getattr(s, name))
        b = s.body_mass.shape[0]
        axis = rng.normal(size=(b, 3))
        s.body_axis.assign(axis / np.linalg.norm(axis, axis=1, keepdims=True))
        s.body_constraint.assign(rng.integers(0, 3, b).astype(np.int32))
        s.body_fixed.assign((rng.random(b) < 0.2).astype(np.int32))


@pytest.mark.parametrize("name", list(SCENES))
def test_device_books_match_the_host_sums_on_shipped_scenes(device, tmp_path, name):
    path, frames = SCENES[name]
    run = build(path, device=device, frames=frames, out_dir=tmp_path)
    try:
        for _ in run.frames():
            pass
        m, s = run.sim.model, run.sim.state
        books = assert_books_match(m, s, f"{name} as run")
        # What each case is for: its lines are live.
        live = {
            "default": ("kinetic_translational", "elastic", "dissipated_damping"),
            "pmma_plate": ("strain", "kinetic_nodes", "load_work"),
            "masonry_wall_blast": ("kinetic_translational", "elastic", "released_conversion"),
            "rigid_slope": ("kinetic_rigid", "gravity_potential"),
        }[name]
        assert all(getattr(books, line) != 0.0 for line in live), books
        for seed in (1, 2):
            scramble(m, s, seed)
            assert_books_match(m, s, f"{name} scrambled ({seed})")
    finally:
        run.close()


def test_device_books_match_the_host_sums_on_a_bonded_joint(device):
    """A 1 × 1 × 1 m block split by a bonded horizontal joint, sagging under gravity: the joint elements' springs
    (``elastic``) and the shadow term of its nodes."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), (2, 2, 2))
    faces = tets[:, TET_FACES].reshape(-1, 3)
    joint = np.unique(np.sort(faces[np.all(np.isclose(points[faces][:, :, 2], 0.5), axis=1)], axis=1), axis=0)
    b = ModelBuilder(gravity=(0.0, 0.0, -9.81))
    b.add_material("rock", 2500.0, 1.0e9, 0.25)
    js = b.add_joint_set(JointProps(friction=0.5, tensile_strength=1.0e6, cohesion=1.0e6))
    b.add_tet_mesh(points, tets, "rock", joint_faces=joint, joint_set=js, fixed_nodes=np.flatnonzero(points[:, 2] == 0))
    model, state = b.finalize(device, safety_factor=0.5)
    assert model.joint_capacity > 0
    sim = Simulation(model, state)
    sim.advance(50)
    books = assert_books_match(model, sim.state, "bonded joint")
    assert books.elastic > 0.0 and books.shadow > 0.0
    scramble(model, sim.state, 3)
    assert_books_match(model, sim.state, "bonded joint scrambled")


def test_line_indices_follow_the_balance():
    """kernels/books.py's vector is read by field name: every field has its own index."""
    assert sorted(LINE.values()) == list(range(len(dataclasses.fields(EnergyBalance))))
