"""The DEM/FEM interface on a wave (issue 28 item 2): a bar half FEM, half DEM (``start_as_spheres``), a bar pulse
launched in the FEM half towards the interface, its reflection measured for the tie (warpdem.stages.coupling) and for
the blended overlap band (warpdem.stages.overlap_band) at several widths and penalties.

The bar: ``CELLS`` = 60 cubic cells of ``CELL`` = 0.05 m, 2 × 2 across, Kuhn tets, E = 1 GPa, ν = 0.25,
ρ = 2000 kg/m³ (c = sqrt(E/ρ) = 707 m/s), no bulk viscosity, no damping; the tets whose centroid lies past
x1 = 40 cells start as spheres. The pulse: u = a cos²(π (x − x_c)/w), w = 12 cells, x_c = 8 cells, moving right
with its Poisson contraction (tests/test_coupling.py ``launch_pulse``). Timeline at c: its front meets x1 at 1.27 ms,
its tail at 2.69 ms; what x1 reflects reaches the free left end at 4.1 ms, what the DEM's free end sends back is at
x1 from 4.1 ms. Measured:

- ``R_energy``: sqrt(E_left(3.2 ms) / E_0), E_left the kinetic and strain energy of the FEM half (nodes and tets
  left of x1) once the incident pulse has crossed, E_0 the pulse's energy: the reflected amplitude over the
  incident's for a pulse whose shape the reflection keeps;
- ``R_gauge``: the reflected over the incident peak of the mean axial velocity of the nodes at x_g = 27 cells (the
  incident passes the gauge from 0.92 to 1.77 ms, the reflection from 2.19 ms), signed: + where the reflected
  velocity has the incident's sign (a softer medium behind), − where opposite;
- the analytic impedance-mismatch reflection R = (Z_D − Z_F)/(Z_D + Z_F), Z = ρ c A, with c_F and c_D the bar speeds
  measured on the same mesh, all FEM and fully converted (a 12-cell bar's lowest longitudinal mode; same ρ and A on
  both sides, so Z_D / Z_F = c_D / c_F);
- ``floor``: the same measurement on the bar without spheres (what the FEM's own dispersion leaves behind).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ..build.builder import InteractionProps, ModelBuilder
from ..build.mesh import box_mesh
from ..simulation import Simulation
from ..stages.conversion import ConversionProps, attach_conversion
from ..stages.tets import TetProps, tet_energies

CELL = 0.05  # [m]
CELLS = 60
INTERFACE = 40  # cells: x1 = 2 m
GAUGE = 27  # cells
YOUNG = 1.0e9  # [Pa]
POISSON = 0.25
DENSITY = 2000.0  # [kg/m³]
TENSILE = 1.0e6  # [Pa]; never reached (the pulse's strain is 5e-5, its stress 50 kPa)
WAVE = math.sqrt(YOUNG / DENSITY)  # [m/s]
AMPLITUDE = 1.0e-5  # [m]
PULSE_WIDTH = 12  # cells
PULSE_CENTRE = 8  # cells
MEASURE_AT = 3.2e-3  # [s]


@dataclass
class Reflection:
    """One row of the comparison.

    Attributes:
        coupling: "tie", "band" or "none" (no spheres: the floor).
        band_width: tet layers of the band (0 for the tie). penalty: factor on the coupling rule [-].
        r_energy: sqrt(E_reflected / E_incident) [-]. r_gauge: reflected / incident peak velocity at the gauge [-].
        transmitted: energy right of x1 at MEASURE_AT over E_0 (spheres, band and couplings included) [-].
        books: |Δ total| / in play over the run [-].
        steps: time steps run.
    """

    coupling: str
    band_width: int
    penalty: float
    r_energy: float
    r_gauge: float
    transmitted: float
    books: float
    steps: int


def build_bar(
    device: str,
    cells: int,
    spheres_from: float | None,
    band_width: int = 0,
    penalty: float = 1.0,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
):
    """The bar (module docstring), ``cells`` long, its corner at ``origin`` [m]; tets with centroid past
    ``spheres_from`` [cells] from the corner converted (None: none). Returns (sim, points, tets)."""
    lo = np.asarray(origin, dtype=np.float64)
    points, tets = box_mesh(tuple(lo), tuple(lo + np.array([cells * CELL, 2 * CELL, 2 * CELL])), (cells, 2, 2))
    b = ModelBuilder(gravity=(0.0, 0.0, 0.0))
    b.add_material("rock", DENSITY, YOUNG, POISSON)
    b.set_tet_properties("rock", TetProps(bulk_viscosity_linear=0.0, bulk_viscosity_quadratic=0.0))
    b.set_interaction("rock", "rock", InteractionProps(friction=0.0, restitution=1.0))
    b.add_tet_mesh(points, tets, "rock")
    model, state = b.finalize(device, sort=False)
    props = ConversionProps(criterion="rankine", tensile_strength=TENSILE, fraction=1.0)
    model, state = attach_conversion(
        model, state, [props], check_interval=10**9, band_width=band_width, band_penalty=penalty
    )
    sim = Simulation(model, state, use_graph=False)
    if spheres_from is not None:
        sim.convert_tets((points[tets].mean(axis=1)[:, 0] - lo[0]) / CELL > spheres_from)
    return sim, points, tets


def launch_pulse(
    sim: Simulation, centre: float, width: float, amplitude: float, origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
) -> None:
    """A right-going bar wave on the nodes: u = a cos²(π (x − x_c) / w) for |x − x_c| < w / 2, v = −c u' with
    c = sqrt(E/ρ), and the lateral Poisson contraction of uniaxial stress, u_y = −ν ε (y − y_c) with ε = u' (and its
    rate): without it the launch holds the uniaxial-strain energy E (1 − ν) / ((1 + ν)(1 − 2ν)) ε² / 2, 20 % more
    than the bar wave's, which stays behind as slow breathing modes of the cross-section. ``centre`` is measured from
    the bar's corner ``origin`` [m]; the bar is CELLS × 2 × 2 cubic cells of CELL (tests/test_coupling.py's too)."""
    m, s = sim.model, sim.state
    nn = int(s.node_count.numpy()[0])
    corner = np.asarray(origin, dtype=np.float64)
    x = m.node_ref_q.numpy()[:nn].astype(np.float64) - corner
    xi = (x[:, 0] - centre) / width
    inside = np.abs(xi) < 0.5
    strain = np.where(inside, -amplitude * np.pi / width * np.sin(2.0 * np.pi * xi), 0.0)
    slope = np.where(inside, -2.0 * amplitude * (np.pi / width) ** 2 * np.cos(2.0 * np.pi * xi), 0.0)
    lateral = x[:, 1:] - CELL
    u = np.zeros((m.node_capacity, 3), dtype=np.float32)
    v = np.zeros((m.node_capacity, 3), dtype=np.float32)
    u[:nn, 0] = np.where(inside, amplitude * np.cos(np.pi * xi) ** 2, 0.0)
    u[:nn, 1:] = -POISSON * strain[:, None] * lateral
    v[:nn, 0] = -WAVE * strain
    v[:nn, 1:] = POISSON * WAVE * slope[:, None] * lateral
    s.node_u.assign(u)
    s.node_qd.assign(v)
    q = np.zeros((m.node_capacity, 3), dtype=np.float32)
    q[:nn] = x + corner + u[:nn]
    s.node_q.assign(q)
    sim.evaluate_forces()


def left_energy(sim: Simulation, points: np.ndarray, tets: np.ndarray, x1: float) -> float:
    """Kinetic energy of the nodes at x ≤ x1 and strain energy of the unconverted tets left of x1 [J]."""
    m, s = sim.model, sim.state
    nn = int(s.node_count.numpy()[0])
    x = m.node_ref_q.numpy()[:nn, 0]
    v = s.node_qd.numpy()[:nn].astype(np.float64)
    kinetic = 0.5 * m.node_mass.numpy()[:nn] * np.sum(v * v, axis=1)
    strain = tet_energies(m, s).numpy()[: len(tets)]
    centre = points[tets].mean(axis=1)[:, 0]
    return float(kinetic[x <= x1 + 1e-9].sum() + strain[centre < x1].sum())


@dataclass
class Run:
    """What one case's run records: the gauge's mean axial velocity [m/s] at ``times`` [s], the node velocities
    [m/s] at MEASURE_AT, the books' largest drift [-], the energy right of x1 over E_0 [-], E_0 [J], steps run."""

    times: np.ndarray
    gauge: np.ndarray
    node_qd: np.ndarray
    books: float
    transmitted: float
    incident: float
    steps: int


def run_case(device: str, coupling: str, band_width: int = 0, penalty: float = 1.0, cells: int = CELLS) -> Run:
    """Run one case (module docstring) to MEASURE_AT: "none" (all FEM), "tie" or "band"."""
    spheres_from = None if coupling == "none" else float(INTERFACE)
    sim, points, tets = build_bar(device, cells, spheres_from, band_width if coupling == "band" else 0, penalty)
    x1 = INTERFACE * CELL
    launch_pulse(sim, PULSE_CENTRE * CELL, PULSE_WIDTH * CELL, AMPLITUDE)
    m = sim.model
    nn = sim.node_count
    gauge = np.isclose(m.node_ref_q.numpy()[:nn, 0], GAUGE * CELL)
    e0 = sim.energy()
    incident = left_energy(sim, points, tets, x1)
    steps = round(MEASURE_AT / m.dt)
    times, velocity = [], []
    books = 0.0
    chunk = 2
    for k in range(steps // chunk):
        sim.advance(chunk)
        times.append(sim.time)
        velocity.append(float(sim.state.node_qd.numpy()[:nn, 0][gauge].mean()))
        if k % 50 == 0:
            books = max(books, abs(sim.energy().total - e0.total) / e0.in_play)
    e1 = sim.energy()
    books = max(books, abs(e1.total - e0.total) / e0.in_play)
    left = left_energy(sim, points, tets, x1)
    return Run(
        times=np.array(times),
        gauge=np.array(velocity),
        node_qd=sim.state.node_qd.numpy()[:nn].astype(np.float64),
        books=float(books),
        transmitted=float((e1.in_play - left) / incident),
        incident=incident,
        steps=len(times) * chunk,
    )


def reflection(reference: Run, case: Run, coupling: str, band_width: int, penalty: float) -> Reflection:
    """The reflection of ``case`` against the all-FEM ``reference`` (the same mesh, launch and steps): left of the
    interface the two differ only by what the interface sent back, so the difference of their fields is the
    reflected wave, free of the FEM's own dispersion (which both carry alike).

    - R_energy = sqrt(2 K_Δ / E_0), K_Δ = ½ Σ m_a |v_a − v_a^ref|² over the nodes left of x1 (the reflected pulse,
      wholly left of x1 at MEASURE_AT, holds as much strain as kinetic energy);
    - R_gauge = the peak of v_g − v_g^ref after the incident has passed the gauge, over the incident's peak, signed.
    """
    x = reference_x()
    left = x < INTERFACE * CELL - 1e-9
    dv = case.node_qd - reference.node_qd
    mass = reference_mass()
    kinetic = 0.5 * float(np.sum(mass[left] * np.sum(dv[left] ** 2, axis=1)))
    split = (GAUGE - PULSE_CENTRE + 0.5 * PULSE_WIDTH) * CELL / WAVE
    diff = case.gauge - reference.gauge
    incident = reference.gauge[reference.times < split]
    reflected = diff[case.times >= split]
    return Reflection(
        coupling=coupling,
        band_width=band_width,
        penalty=penalty,
        r_energy=math.sqrt(2.0 * kinetic / reference.incident),
        r_gauge=float(reflected[np.argmax(np.abs(reflected))] / incident[np.argmax(np.abs(incident))]),
        transmitted=case.transmitted,
        books=case.books,
        steps=case.steps,
    )


def reference_x() -> np.ndarray:
    """Reference x of the bar's nodes [m] (box_mesh's order, as build_bar makes them)."""
    points, _ = box_mesh((0.0, 0.0, 0.0), (CELLS * CELL, 2 * CELL, 2 * CELL), (CELLS, 2, 2))
    return points[:, 0]


def reference_mass() -> np.ndarray:
    """Lumped masses of the all-FEM bar's nodes [kg] (ρ V / 4 from each tet)."""
    points, tets = box_mesh((0.0, 0.0, 0.0), (CELLS * CELL, 2 * CELL, 2 * CELL), (CELLS, 2, 2))
    x = points[tets]
    volume = np.abs(np.linalg.det(x[:, 1:] - x[:, :1])) / 6.0
    mass = np.zeros(len(points))
    np.add.at(mass, tets.ravel(), np.repeat(0.25 * DENSITY * volume, 4))
    return mass


def bar_speed(device: str, converted: bool, cells: int = 12) -> float:
    """Bar wave speed [m/s] of a ``cells``-long free bar, all FEM or fully converted, from the zero crossings of its
    left half's momentum in the lowest longitudinal mode v = v0 cos(π x / L) (ω = π c / L; as
    tests/test_coupling.py measures it)."""
    sim, _, _ = build_bar(device, cells, -1.0 if converted else None)
    m, s = sim.model, sim.state
    length = cells * CELL
    # The bodies that carry the bar: its spheres, or its nodes.
    if converted:
        n, place, masses, velocity = sim.particle_count, s.particle_q, m.particle_mass, s.particle_qd
    else:
        n, place, masses, velocity = sim.node_count, m.node_ref_q, m.node_mass, s.node_qd
    x = place.numpy()[:n, 0].astype(np.float64)
    mass = masses.numpy()[:n].astype(np.float64)
    v = np.zeros((*velocity.shape, 3), dtype=np.float32)
    v[:n, 0] = 0.01 * np.cos(np.pi * x / length)
    velocity.assign(v)
    sim.evaluate_forces()
    left = x < 0.5 * length
    times, momenta = [], []
    chunk = 2
    for _ in range(round(2.2 * 2.0 * length / WAVE / (chunk * m.dt))):
        sim.advance(chunk)
        times.append(sim.time)
        vel = (sim.state.particle_qd if converted else sim.state.node_qd).numpy()[:n, 0]
        momenta.append(float(np.sum(mass[left] * vel[left])))
    t, p = np.array(times), np.array(momenta)
    k = np.nonzero(p[:-1] * p[1:] < 0.0)[0]
    crossings = t[k] - p[k] * (t[k + 1] - t[k]) / (p[k + 1] - p[k])
    return float(2.0 * length / (2.0 * np.mean(np.diff(crossings))))


def compare(device: str, widths: list[int], penalties: list[float]) -> dict:
    """The whole comparison: the floor, the tie at each penalty... (the tie's stiffness is its rule's, penalty 1),
    the band at each width and penalty, and the analytic impedance mismatch. Returns a JSON-able dict."""
    c_f = bar_speed(device, converted=False)
    c_d = bar_speed(device, converted=True)
    reference = run_case(device, "none")
    rows = [reflection(reference, run_case(device, "tie"), "tie", 0, 1.0)]
    for w in widths:
        for p in penalties:
            rows.append(reflection(reference, run_case(device, "band", w, p), "band", w, p))
    return {
        "bar": {
            "cells": CELLS,
            "cell_m": CELL,
            "interface_cells": INTERFACE,
            "gauge_cells": GAUGE,
            "pulse_width_cells": PULSE_WIDTH,
            "E_Pa": YOUNG,
            "nu": POISSON,
            "rho": DENSITY,
            "measure_at_s": MEASURE_AT,
        },
        "c_fem_m_s": c_f,
        "c_dem_m_s": c_d,
        "r_impedance": (c_d - c_f) / (c_d + c_f),
        "rows": [asdict(r) for r in rows],
    }
