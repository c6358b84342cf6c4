"""FEM→DEM conversion through the scene machinery: a slab under a local impact converts only in the high-stress
zone, and a ``start_as_spheres`` region converts exactly the tets whose centroid it holds.

Oracles:
- local impact (wave front and plane-wave stress): a pressure p switched on at t = 0 over a disc of radius A on the
  top of a tet slab sends a compressional wave down into it. Under the disc, before the release waves from its rim
  arrive, the wave is planar (uniaxial strain): σ_zz = −p, σ_xx = σ_yy = −ν/(1 − ν) p, so the Tresca stress is
  (σ1 − σ3)/2 = p (1 − 2ν) / (2 (1 − ν)) (0.375 p at ν = 0.2). The slab's τ_f is set so the conversion threshold
  f τ_f is half of that: in one conversion pass run when the front is halfway down the slab, every tet in the
  top layer well inside the disc (r < A/2) must convert. Nothing can be
  stressed where the wave has not been: after time t the front lies within A + c_p t of the disc's centre, c_p =
  sqrt(E (1 − ν) / (ρ (1 + ν)(1 − 2ν))) the P-wave speed; an explicit mesh smears a front over about two elements,
  so every converted tet's centroid lies within A + c_p t + FRONT_CELLS · (cell diagonal) of the centre, and the
  slab extends well beyond that radius (tets that must stay tets).
- start_as_spheres: the tets converted before the first step are exactly those whose reference centroid lies in the
  region (brute-force test of every centroid), and the spawned spheres carry exactly their mass Σ ρ V₀ (to float32
  round-off of the per-tet masses, MASS_RTOL).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from warpdem.build.scene_build import build_scene, start_as_spheres
from warpdem.scene import SceneError, parse_scene
from warpdem.simulation import Simulation
from warpdem.stages.overlap_band import tet_alpha

RHO, E, NU = 2400.0, 3.0e10, 0.2
PEAK = 5.0e7
"""Pressure on the disc [Pa]."""
A = 0.05
"""Radius of the loaded disc [m]."""
HALF, DEPTH, CELLS = 0.2, 0.1, (16, 16, 4)
"""Slab [−HALF, HALF]² × [0, DEPTH] [m] in CELLS Kuhn cells (0.025 m cubes)."""
FRACTION = 0.9
FRONT_CELLS = 2.0
"""Elements over which the explicit mesh smears the wave front [-]."""
MASS_RTOL = 1e-6
"""float32 sums of a few hundred masses: ~n ε₃₂ relative."""


def slab(**conversion) -> dict:
    """The slab scene: a box mesh on a roller base, the pressure disc on its top centre, conversion on."""
    tresca_plane = PEAK * (1.0 - 2.0 * NU) / (2.0 * (1.0 - NU))
    return {
        "run": {"end_time": 1e-4, "safety_factor": 0.5},
        "gravity": {"vector": [0.0, 0.0, 0.0]},
        "materials": {
            "concrete": {
                "density": RHO,
                "youngs_modulus": E,
                "poisson_ratio": NU,
                # f τ_f = half the plane-wave Tresca stress under the disc.
                "tresca_strength": 0.5 * tresca_plane / FRACTION,
            }
        },
        "mesh": {
            "kind": "box",
            "lo": [-HALF, -HALF, 0.0],
            "hi": [HALF, HALF, DEPTH],
            "divisions": list(CELLS),
            "material": "concrete",
        },
        "loads": [
            {
                "kind": "pressure",
                "region": {"cylinder": {"center": [0.0, 0.0, DEPTH - 0.01], "radius": A, "height": 0.02}},
                "history": {"kind": "table", "times": [0.0, 1.0], "values": [PEAK, PEAK]},
            }
        ],
        "boundaries": [{"faces": "z-", "kind": "roller"}],
        "conversion": {"enabled": True, "fraction": FRACTION, **conversion},
    }


def reference_centroids(sim: Simulation) -> np.ndarray:
    nt = int(sim.state.tet_count.numpy()[0])
    return sim.model.node_ref_q.numpy()[sim.model.tet_nodes.numpy()[:nt]].astype(np.float64).mean(axis=1)


def test_local_impact_converts_only_in_the_high_stress_zone(device):
    # One conversion pass, when the front is halfway down the slab: the pressure faces of converted tets stop
    # pushing, so a pass every step would cut the pulse short before the top layer carries the plane wave.
    scene = parse_scene(slab(check_interval=100_000))
    sim = Simulation(*build_scene(scene, device))
    c_p = math.sqrt(E * (1.0 - NU) / (RHO * (1.0 + NU) * (1.0 - 2.0 * NU)))
    cell = 2.0 * HALF / CELLS[0]
    steps = round(0.5 * DEPTH / c_p / sim.model.dt)
    sim.advance(steps)
    assert sim.conversion_pass().converted > 0

    centroid = reference_centroids(sim)
    converted = (
        sim.state.tet_sphere.numpy()[: len(centroid)] >= 0
    )  # (the band keeps some active, warpdem.stages.overlap_band)
    distance = np.linalg.norm(centroid - np.array([0.0, 0.0, DEPTH]), axis=1)
    reach = A + c_p * sim.time + FRONT_CELLS * math.sqrt(3.0) * cell
    assert np.count_nonzero(distance > reach) > len(centroid) // 4  # a good part of the slab lies beyond the front
    assert converted.any()
    assert distance[converted].max() <= reach, (distance[converted].max(), reach)
    # The high-stress zone: the top layer well inside the disc, under the plane wave at twice the threshold.
    under = (np.hypot(centroid[:, 0], centroid[:, 1]) < 0.5 * A) & (centroid[:, 2] > DEPTH - cell)
    assert under.any() and converted[under].all()
    assert sim.particle_count == np.count_nonzero(converted)


@pytest.mark.parametrize("spheres_per_tet", [1, 4])
def test_start_as_spheres_converts_the_region(device, spheres_per_tet):
    region = {"box": {"lo": [-0.1, -0.1, 0.0], "hi": [0.1, 0.05, 0.05]}}
    spec = slab(start_as_spheres=region, check_interval=100, spheres_per_tet=spheres_per_tet)
    spec["run"]["safety_factor"] = 0.5 if spheres_per_tet == 1 else 0.2  # the sub-spheres' bonds need ~1/4 of the tets'
    scene = parse_scene(spec)
    sim = Simulation(*build_scene(scene, device))
    centroid = reference_centroids(sim)
    inside = scene.conversion.start_as_spheres.contains(centroid)
    volume = sim.model.tet_volume.numpy()[: len(centroid)].astype(np.float64)

    assert start_as_spheres(scene, sim) == np.count_nonzero(inside)
    np.testing.assert_array_equal(sim.state.tet_sphere.numpy()[: len(centroid)] >= 0, inside)
    n = sim.particle_count
    assert n == spheres_per_tet * np.count_nonzero(inside)
    mass = sim.model.particle_mass.numpy()[:n]
    # The spheres hold (1 − α) ρ V of their tets: α = 0 where the tie drops them (four spheres per tet), α of the
    # overlap band (the default with one) on the region's rim, where the tets keep the rest.
    alpha = tet_alpha(sim.model, sim.state)
    share = (1.0 - alpha[inside]) * volume[inside]
    np.testing.assert_allclose(mass.astype(np.float64).sum(), RHO * share.sum(), rtol=MASS_RTOL)


def test_start_as_spheres_region_without_tets(device):
    region = {"box": {"lo": [1.0, 1.0, 1.0], "hi": [2.0, 2.0, 2.0]}}
    scene = parse_scene(slab(start_as_spheres=region))
    sim = Simulation(*build_scene(scene, device))
    with pytest.raises(SceneError, match=r"conversion\.start_as_spheres: contains no tet centroid"):
        start_as_spheres(scene, sim)
