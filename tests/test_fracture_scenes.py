"""Nodal fracture through the scene machinery: seed cracks pre-split at build time, and a pre-notched plate under
mode-I tension that cracks from the notch tip along its symmetry plane.

Oracles:
- seed crack: the joint pre-split duplicates every node of the crack faces except those on the crack's rim inside
  the rock (warpdem.joints: the rock around the rim still joins the two sides), so a crack through the thickness of
  a box mesh, ending on a grid line inside the plate, adds (crack nodes along x − 1 rim) × (nodes through the
  thickness) nodes: an exact count.
- notched plate (symmetry): the plate, its edge notch and its loads are mirror-symmetric about y = 0, so the
  principal tension at the notch tip is along y and the crack must open along the element faces of that plane:
  every split node's reference position has y = 0 to float32 round-off (SYMMETRY_TOL); the first pass that splits
  does so at the notch tip (x = NOTCH), where the stress concentrates, and the crack then grows into the ligament
  (checked up to its first element of growth, before the waves reflected by the plate's edges reach the tip).
  The applied tension, 0.4 T_f, lies between the tip's onset (~T_f/3: the nodal stress averages the tip singularity
  over an element) and T_f/2, where the waves from the two loaded edges, doubling where they meet on the plane,
  would split the whole plane at once (scenes/pmma_plate.toml).
"""

from __future__ import annotations

import numpy as np

from warpdem.scene import parse_scene
from warpdem.scene_build import build_scene
from warpdem.simulation import Simulation

H = 0.002
"""Element size of the plates [m]."""
LENGTH, WIDTH, THICKNESS = 0.032, 0.016, 0.002
NOTCH = 0.008
"""Edge notch length from x = 0 along y = 0 [m]: 4 elements."""
SYMMETRY_TOL = 4.0 * float(np.finfo(np.float32).eps) * LENGTH
"""Split nodes lie on y = 0 to the float32 rounding of reference positions of the plate's size (a few ulp)."""

PLATE = f"""\
[run]
end_time = 3.0e-5
safety_factor = 0.5

[gravity]
vector = [0.0, 0.0, 0.0]

[materials.pmma]
density = 1190.0
youngs_modulus = 3.2e9
poisson_ratio = 0.35
tensile_strength = 1.2e7
fracture_energy = 350.0

[mesh]
kind = "box"
lo = [0.0, {-WIDTH / 2}, 0.0]
hi = [{LENGTH}, {WIDTH / 2}, {THICKNESS}]
divisions = [{round(LENGTH / H)}, {round(WIDTH / H)}, {round(THICKNESS / H)}]
material = "pmma"

[[loads]]
kind = "pressure"
faces = "y+"
history = {{ kind = "table", times = [0.0, 2.0e-6, 1.0], values = [0.0, -4.8e6, -4.8e6] }}

[[loads]]
kind = "pressure"
faces = "y-"
history = {{ kind = "table", times = [0.0, 2.0e-6, 1.0], values = [0.0, -4.8e6, -4.8e6] }}

[fracture]
enabled = true

[[fracture.seed_cracks]]
point = [0.0, 0.0, 0.0]
normal = [0.0, 1.0, 0.0]
region = {{ box = {{ lo = [-0.001, -0.001, -0.001], hi = [{NOTCH + H / 2}, 0.001, {THICKNESS + 0.001}] }} }}
"""


def grid_nodes() -> int:
    """Nodes of the box mesh before any split: (cells + 1) per axis."""
    return (round(LENGTH / H) + 1) * (round(WIDTH / H) + 1) * (round(THICKNESS / H) + 1)


def test_seed_crack_splits_its_nodes_at_build(device):
    scene = parse_scene({**_plate_dict(), "fracture": {**_plate_dict()["fracture"], "enabled": False}})
    model, state = build_scene(scene, device)
    # Crack nodes along x: x = 0, H, ..., NOTCH; the one at x = NOTCH is the rim inside the rock and stays whole.
    along_x = round(NOTCH / H) + 1 - 1
    through = round(THICKNESS / H) + 1
    assert int(state.node_count.numpy()[0]) == grid_nodes() + along_x * through
    assert model.fracture_interval == 0  # [fracture] off: no split pass


def test_notched_plate_cracks_from_the_tip_along_the_symmetry_plane(device):
    scene = parse_scene(_plate_dict())
    model, state = build_scene(scene, device)
    assert model.fracture_interval == 1
    n0 = int(state.node_count.numpy()[0])
    sim = Simulation(model, state)
    first_split_x = None
    born = np.zeros((0, 3))
    # Step (a split pass after every step) until the crack has advanced one element past the notch tip into the
    # ligament: the first growth of the crack, before reflections from the plate's edges reach the tip.
    for _ in range(int(scene.run.end_time / model.dt)):
        sim.advance(1)
        n = int(sim.state.node_count.numpy()[0])
        born = sim.model.node_ref_q.numpy()[n0:n].astype(np.float64)
        if n > n0 and first_split_x is None:
            first_split_x = born[:, 0].copy()
        if len(born) and born[:, 0].max() >= NOTCH + H * (1.0 - 1e-6):
            break
    assert first_split_x is not None, "the notched plate never cracked"
    # The first splits are the notch tip's nodes (x = NOTCH, the rim of the seed crack that the pre-split kept whole).
    np.testing.assert_allclose(first_split_x, NOTCH, atol=SYMMETRY_TOL)
    assert born[:, 0].max() >= NOTCH + H * (1.0 - 1e-6), "the crack did not grow past the notch tip"
    # Every split so far is on the symmetry plane y = 0, at the tip or one element ahead: it runs from the tip into
    # the ligament, never back into the notch or off the plane.
    np.testing.assert_allclose(born[:, 1], 0.0, atol=SYMMETRY_TOL)
    assert np.all((born[:, 0] >= NOTCH - SYMMETRY_TOL) & (born[:, 0] <= NOTCH + H + SYMMETRY_TOL)), born


def _plate_dict() -> dict:
    import tomllib

    return tomllib.loads(PLATE)
