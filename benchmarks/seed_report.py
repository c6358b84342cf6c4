"""Side-by-side reports of the seed papers' scenarios: ``python benchmarks/seed_report.py [SCENE ...] [--out DIR]
[--work DIR] [--device cpu] [--end-time T]``, SCENE among the scenarios below (default: all).

Each scenario is a shipped scene that reproduces an example of one of the two source papers. Its report sets the
paper's claims (quoted, with the section or figure) beside the figure warpdem measures for each and a verdict:
``as published`` / ``differs`` for the set-up, ``reproduced`` / ``partly`` / ``not reproduced`` for an outcome, with
the criterion that decides it written in the row. The scene is run to its end through the Python API (``wd.build``,
the run's outputs in ``WORK/<scene>``), sampled at every output frame, and the report is written as
``OUT/<scene>.md`` (the table and where every figure comes from) and ``OUT/<scene>.png`` (the scene at the report's
three instants, drawn from the run's USD stage, over the measured series).

The papers do not give the times of their figures' instants ("three time instants"), so the pictures are drawn at
fixed fractions of the run (a sixth, a half, the end), said in the captions.
"""

from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from facility_report import FACILITY, write_facility_report  # beside this script, in benchmarks/
from report_common import CIMNE, LDEC, OUT_DIR, ROOT, SCENES_DIR, Claim, claim_table, write_atomically

INSTANTS = (1.0 / 6.0, 0.5, 1.0)
"""Fractions of the run the pictures show."""


@dataclass
class Samples:
    """What a scenario's run measured, one entry per output frame (frame 0 first).

    Attributes:
        time: simulated time of each frame [s], shape (F,).
        columns: measured quantity → values per frame, each shape (F,).
        facts: figures of the run as a whole (counts, areas, the criterion's time...), name → value.
    """

    time: list[float] = field(default_factory=list)
    columns: dict[str, list[float]] = field(default_factory=dict)
    facts: dict[str, float] = field(default_factory=dict)

    def add(self, name: str, value: float) -> None:
        """Appends one frame's value of a column."""
        self.columns.setdefault(name, []).append(float(value))

    def column(self, name: str) -> np.ndarray:
        """A column as a float64 array, shape (F,)."""
        return np.asarray(self.columns[name], dtype=np.float64)

    def first_time(self, name: str, above: float = 0.0) -> float | None:
        """Time of the first frame whose ``name`` exceeds ``above`` [s]; None if none does."""
        values = self.column(name)
        hits = np.nonzero(values > above)[0]
        return None if len(hits) == 0 else self.time[int(hits[0])]


@dataclass(frozen=True)
class Scenario:
    """A seed paper's example as a shipped scene.

    Attributes:
        scene: the scene's name (``scenes/<scene>.toml``).
        title: the example's title in the paper.
        source: the paper.
        sample: (run, frame, samples) → None: records the frame's measured quantities in ``samples``.
        claims: the report's rows.
        plot: the columns drawn under the pictures, column → label.
        view: the preview's view of the pictures.
        window: the part of the view drawn (warpdem.io.preview.render's ``window``: horizontal and vertical bounds in
            the view's axes [m]); None: the whole scene.
        instants: the fractions of the run the pictures show (the paper's instants where it gives them).
        color_by: the pictures' colours (warpdem.io.preview.render's ``color_by``: "stage", or "speed" as the
            paper's figure colours them).
        scale: the value drawn red when recolouring (the paper's key's top), or None: the largest drawn.
        output_rate: the run's frames per second of simulated time where the report needs finer samples than the
            scene writes [1/s]; None: the scene's.
    """

    scene: str
    title: str
    source: str
    sample: Callable[..., None]
    claims: tuple[Claim, ...]
    plot: dict[str, str]
    view: str = "xz"
    window: tuple[float, float, float, float] | None = None
    instants: tuple[float, ...] = INSTANTS
    color_by: str = "stage"
    scale: float | None = None
    output_rate: float | None = None


# ----------------------------------------------------------------------------------------------------------------------
# Measurement shared by the CIMNE scenarios
# ----------------------------------------------------------------------------------------------------------------------


def sample_conversion(run, frame, samples: Samples) -> None:
    """Once: each material's tets and those that start as spheres, and the masonry's mean tet edge and thickness
    along x [m] (conversion_scenes.wall_resolution). Per frame: the converted fraction of each material's tets
    (``converted_<material>``; a converted tet is one with a sphere, ``tet_sphere`` >= 0: with the overlap band, the
    default, band tets stay active with weight alpha), their reference volume (``converted_volume`` [m³]), spheres,
    fragments, the fastest sphere [m/s], sphere–face contact dissipation [J] (nonzero once spheres hit a continuum
    surface), the load's force |F| [N] (the time series' load0), and the largest intact piece of the masonry as a
    share of its mass (``masonry_piece``, conversion_scenes.largest_piece_share)."""
    from conversion_scenes import largest_piece_share, wall_resolution  # beside this script, in benchmarks/

    model, state = run.model, run.state
    nt = int(state.tet_count.numpy()[0])
    converted = state.tet_sphere.numpy()[:nt] >= 0
    material = model.tet_material.numpy()[:nt]
    tets = model.tet_nodes.numpy()[:nt]
    if not samples.time:
        samples.facts["tets"] = nt
        corners = model.node_ref_q.numpy()[tets].astype(np.float64)
        samples.facts["volume"] = np.abs(np.linalg.det(corners[:, 1:] - corners[:, :1])) / 6.0
        for m, name in enumerate(model.material_names):
            samples.facts[f"tets_{name}"] = int(np.count_nonzero(material == m))
            samples.facts[f"start_as_spheres_{name}"] = int(np.count_nonzero(converted & (material == m)))
        if "masonry" in model.material_names:
            masonry = material == model.material_names.index("masonry")
            samples.facts["wall_resolution"] = wall_resolution(model.node_ref_q.numpy(), tets[masonry])
        samples.facts["peak_pressure"] = max(
            (load.history.peak for load in run.scene.loads if load.kind == "pressure"), default=0.0
        )
    samples.time.append(frame.time)
    for m, name in enumerate(model.material_names):
        total = max(1, int(np.count_nonzero(material == m)))
        samples.add(f"converted_{name}", np.count_nonzero(converted & (material == m)) / total)
    samples.add("converted_volume", float(samples.facts["volume"][converted].sum()))
    if "masonry" in model.material_names:
        masonry = material == model.material_names.index("masonry")
        nodes = np.zeros(run.sim.node_count, dtype=bool)
        nodes[np.unique(tets[masonry])] = True
        samples.add("masonry_piece", largest_piece_share(run.sim, masonry, nodes))
    n = run.sim.particle_count
    samples.add("spheres", n)
    samples.add("fragments", frame.fragments or 0)
    speed = np.linalg.norm(state.particle_qd.numpy()[:n], axis=1) if n else np.zeros(1)
    samples.add("max_sphere_speed", float(speed.max()))
    samples.add("sphere_face_dissipation", frame.series.get("energy_dissipated_sphere_face", 0.0))
    force = np.array([frame.series.get(f"load0_f{axis}", 0.0) for axis in "xyz"])
    samples.add("load_force", float(np.linalg.norm(force)))


def _fraction_at(samples: Samples, name: str, fractions=INSTANTS) -> str:
    """The column's values at the report's instants, as '12 % at 1.0 ms, ...'."""
    t = np.asarray(samples.time)
    values = samples.column(name)
    parts = []
    for f in fractions:
        k = int(np.argmin(np.abs(t - f * t[-1])))
        parts.append(f"{100 * values[k]:.1f} % at {1e3 * t[k]:.2f} ms")
    return ", ".join(parts)


def _ms(t: float | None) -> str:
    return "never" if t is None else f"{1e3 * t:.2f} ms"


# ----------------------------------------------------------------------------------------------------------------------
# Running and writing
# ----------------------------------------------------------------------------------------------------------------------


def run_scenario(scenario: Scenario, work: Path, device: str, end_time: float | None) -> tuple[Samples, Path]:
    """Runs the scenario's scene to its end (or ``end_time``), sampling every frame. Returns the samples and the
    USD stage's path."""
    import warpdem as wd

    scene = wd.load_scene(SCENES_DIR / f"{scenario.scene}.toml")
    if scenario.output_rate is not None:
        scene = scene.model_copy(update={"run": scene.run.model_copy(update={"output_rate": scenario.output_rate})})
    samples = Samples()
    run = wd.build(scene, device=device, end_time=end_time, out_dir=work / scenario.scene)
    for frame in run.frames():  # frame 0 (the state as built) first; at the end the stage is published
        scenario.sample(run, frame, samples)
    return samples, run.usd_path


def write_report(scenario: Scenario, samples: Samples, stage: Path, out: Path, command: str) -> list[Path]:
    """Writes OUT/<scene>.md (the table) and OUT/<scene>.png (the pictures over the plot). Returns the paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from warpdem.io.preview import render, stage_frames

    out.mkdir(parents=True, exist_ok=True)
    t_end = samples.time[-1]
    lines = [
        f"# {scenario.title} — the paper beside warpdem",
        "",
        f"Scene `scenes/{scenario.scene}.toml`, run to {1e3 * t_end:.2f} ms and sampled every "
        f"{1e3 * (samples.time[1] - samples.time[0]):.3g} ms (its output frames); paper: {scenario.source}.",
        f"Written by `{command}`; every figure below is measured on that run at its output frames.",
        "",
        *claim_table(scenario.claims, samples),
        "",
        f"![{scenario.scene}]({scenario.scene}.png)",
        "",
    ]
    md = out / f"{scenario.scene}.md"
    write_atomically(md, "\n".join(lines))

    # The pictures at the instants, drawn by the preview from the stage, then set over the plot.
    from pxr import Usd

    codes = stage_frames(Usd.Stage.Open(str(stage)))
    times = np.asarray(samples.time)
    picked = [codes[int(np.argmin(np.abs(times - f * t_end)))] for f in scenario.instants]
    with tempfile.TemporaryDirectory() as scratch:
        pictures = render(
            stage,
            scratch,
            frames=picked,
            view=scenario.view,
            size=(520, 520),
            window=scenario.window,
            color_by=scenario.color_by,
            scale=scenario.scale,
        )
        images = [plt.imread(p) for p in pictures]
    fig = plt.figure(figsize=(13, 8.5))
    grid = fig.add_gridspec(2, 3, height_ratios=(1.5, 1.0))
    for i, (image, code) in enumerate(zip(images, picked, strict=True)):
        ax = fig.add_subplot(grid[0, i])
        ax.imshow(image)
        ax.set_axis_off()
        ax.set_title(f"t = {1e3 * times[codes.index(code)]:.2f} ms")
    ax = fig.add_subplot(grid[1, :])
    for name, label in scenario.plot.items():
        ax.plot(1e3 * times, samples.column(name), marker="o", ms=3, label=label)
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("fraction [-]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    fig.suptitle(f"{scenario.title}: scenes/{scenario.scene}.toml")
    fig.tight_layout()
    png = out / f"{scenario.scene}.png"
    tmp_png = out / f".{scenario.scene}.tmp.png"
    fig.savefig(tmp_png, dpi=80)
    plt.close(fig)
    tmp_png.replace(png)
    return [md, png]


# ----------------------------------------------------------------------------------------------------------------------
# The CIMNE examples (§6)
# ----------------------------------------------------------------------------------------------------------------------


def _box_as_spheres(material: str) -> Callable[[Samples], tuple[str, str]]:
    """The set-up row of a charge box modelled with discrete elements from the start."""

    def judge(s: Samples) -> tuple[str, str]:
        spheres, tets = int(s.facts[f"start_as_spheres_{material}"]), int(s.facts[f"tets_{material}"])
        verdict = "as published" if tets and spheres == tets else "differs: the box starts (partly) as tets"
        return f"{spheres} of the box's {tets} tets are bonded spheres at t = 0", verdict

    return judge


def _hit(s: Samples) -> tuple[str, str]:
    # Sphere–face contact dissipation is zero until a sphere first touches a continuum surface: in these scenes
    # only the charge's fragments can (the continuum's own converted spheres start inside it).
    t = s.first_time("sphere_face_dissipation")
    return f"first sphere–face contact at {_ms(t)}", "reproduced" if t is not None else "not reproduced"


def _fragments(s: Samples) -> tuple[str, str]:
    n = int(s.column("fragments")[-1])
    return f"{n} fragments at the end", "reproduced (≥ 20 pieces)" if n >= 20 else "not reproduced (< 20 pieces)"


def _progressive(material: str, what: str) -> Callable[[Samples], tuple[str, str]]:
    """The DEM zone growing in ``material`` over the run (a row for Fig. 5 / Fig. 7)."""

    def judge(s: Samples) -> tuple[str, str]:
        values = s.column(f"converted_{material}")
        grows = np.count_nonzero(np.diff(values) > 0)
        first = s.first_time(f"converted_{material}", above=values[0])
        text = f"{what} converted: {_fraction_at(s, f'converted_{material}')}; first at {_ms(first)}"
        if grows >= 3:
            return text, f"reproduced (grows over {grows} frames)"
        return text, "partly (grows over fewer than 3 frames)" if grows else "not reproduced (no growth)"

    return judge


def _peak(s: Samples) -> tuple[str, str]:
    """The set-up row of the charge: a 600 MPa peak pressure pulse (CIMNE §6.1 and Fig. 7's caption)."""
    peak = s.facts["peak_pressure"]
    return f"pressure pulse, peak {peak / 1e6:.0f} MPa", "as published" if peak == 600e6 else "differs"


FAILED_SHARE = 0.5
"""A wall has failed when its largest intact piece holds less than this share of its mass: it is in pieces, none of
which carries the rest (as benchmarks/conversion_scenes.py's FAILED_SHARE)."""

INSTANT = 2.0e-3
"""How soon after the first hit a failure still counts as the paper's "instant failure" [s]: the box's fragments
cross the 0.15 m gap at 60-120 m/s in 1.3-2.5 ms, so a failure within that time of the first hit is as quick as the
loading itself; slower is a failure, not an instant one."""


def _wall_fails(s: Samples) -> tuple[str, str]:
    share = s.column("masonry_piece")
    hit = s.first_time("sphere_face_dissipation")
    below = np.nonzero(share < FAILED_SHARE)[0]
    failed = None if len(below) == 0 else s.time[int(below[0])]
    text = (
        f"largest intact piece of the wall {100 * share[-1]:.0f} % of its mass at the end; "
        f"below {100 * FAILED_SHARE:.0f} % from {_ms(failed)} (first hit {_ms(hit)})"
    )
    if failed is None:
        return text, "not reproduced (the wall holds together)"
    if hit is not None and failed - hit <= INSTANT:
        return text, f"reproduced (fails within {1e3 * INSTANT:.0f} ms of the first hit)"
    return text, f"partly (fails, but more than {1e3 * INSTANT:.0f} ms after the first hit)"


WALL_ELEMENTS = 8
"""Elements through the wall's thickness that issue 28 asks for (the paper's wall fails by its elements: fewer makes
each tet a large share of the section)."""


def _wall_mesh(s: Samples) -> tuple[str, str]:
    """The wall's resolution: its thickness (the masonry's extent along x, across the wall) over its tets' mean
    edge."""
    edge, thickness = s.facts["wall_resolution"]
    through = thickness / edge
    text = (
        f"{s.facts['tets_masonry']} tets of mean edge {1e3 * edge:.1f} mm: {through:.1f} through its {thickness:.2f} m"
    )
    return text, f"{'fine enough' if through >= WALL_ELEMENTS else 'coarse'} (≥ {WALL_ELEMENTS} elements asked)"


def _final_zone(s: Samples) -> tuple[str, str]:
    """The fractured zone reaches a final extent: its converted volume stops growing before the run ends."""
    volume = s.column("converted_volume")
    grew = np.nonzero(np.diff(volume) > 0)[0]
    last = s.time[int(grew[-1]) + 1] if len(grew) else s.time[0]
    text = f"converted volume {volume[-1]:.1f} m³ at the end, last growth at {_ms(last)} of {_ms(s.time[-1])}"
    settled = len(grew) and last < s.time[-1] - 2 * (s.time[1] - s.time[0])
    return text, "reproduced (no growth over the last frames)" if settled else "not reproduced (still growing)"


# ----------------------------------------------------------------------------------------------------------------------
# The LDEC limestone tunnel (§4, Fig. 9)
# ----------------------------------------------------------------------------------------------------------------------

RUBBLE_BAND = 1.0
"""How far into the rock around the tunnel the rubble row looks [m] (the rock LDEC's reflected waves break)."""
RUBBLE_PIECE = 0.45
"""A piece smaller than this share of a whole brick counts as rubble [-]: below the half bricks the tunnel's cut
leaves on its walls by construction (exactly 0.5 of a brick, so a threshold at 0.5 counted them or not by the
rounding of their volumes: 67 % with float64 volumes, 62 % with the model's float32 ones)."""
LDEC_CELL = 0.1
"""LDEC's element size in §4 [m] ("10 cm" tets: docs/scenes.md)."""


def sample_limestone(run, frame, samples: Samples) -> None:
    """Once: the tunnel as cut and the charge's place (benchmarks/limestone_tunnel.py ``tunnel_section``), the
    bricks, the cell size, the slab's top, and each tet's reference centroid and volume. Per frame: the fill (the
    solid volume in the tunnel over its volume, limestone_tunnel.py ``rubble_volume``), the highest rock above the
    slab's top [m], and the share of the rock within RUBBLE_BAND of the tunnel that lies in pieces smaller than
    RUBBLE_PIECE of a brick (``band_rubble``: 0 before the rigid switch, whose bodies are the pieces)."""
    from limestone_tunnel import rock_heights, rubble_volume, tunnel_section  # beside this script, in benchmarks/

    model, state, scene = run.model, run.state, run.scene
    nt = int(state.tet_count.numpy()[0])
    tets = model.tet_nodes.numpy()[:nt]
    if not samples.time:
        lo, hi = tunnel_section(scene)
        tunnel, charge = scene.mesh.openings[0], scene.mesh.openings[1]
        top = float(model.node_ref_q.numpy()[:, 2].max())
        samples.facts.update(
            lo=lo,
            hi=hi,
            volume=float(np.prod(hi - lo)),
            brick_x=scene.mesh.brick[0],
            brick_z=scene.mesh.brick[2],
            brick_volume=float(np.prod(scene.mesh.brick)),
            tunnel_w=tunnel.width,
            tunnel_h=tunnel.height,
            charge_dx=charge.center[0] - tunnel.center[0],
            charge_dz=charge.center[1] - tunnel.center[1],
            charge_r=charge.radius,
            cover=top - (charge.center[1] + charge.radius),
            cell=scene.mesh.h / scene.run.resolution,
            top=top,
            peak_pressure=max(load.history.peak for load in scene.loads if load.kind == "pressure"),
        )
        centre = model.node_ref_q.numpy()[tets].astype(np.float64).mean(axis=1)
        x, z = centre[:, 0], centre[:, 2]
        d = RUBBLE_BAND
        near = (x > lo[0] - d) & (x < hi[0] + d) & (z > lo[2] - d) & (z < hi[2] + d)
        inside = (x > lo[0]) & (x < hi[0]) & (z > lo[2]) & (z < hi[2])
        samples.facts["band"] = near & ~inside
    facts = samples.facts
    samples.time.append(frame.time)
    samples.add("fill", rubble_volume(run.sim, facts["lo"], facts["hi"])[0] / facts["volume"])
    samples.add("cover_rise", float(rock_heights(run.sim).max()) - facts["top"])
    share = 0.0
    body = getattr(state, "node_body", None)
    if run.sim.rigid and body is not None and body.shape[0]:
        owner = body.numpy()[tets[:, 0]]
        volume = model.tet_volume.numpy()[:nt].astype(np.float64)
        pieces = np.bincount(owner[owner >= 0], weights=volume[owner >= 0])
        small = np.zeros(nt, dtype=bool)
        small[owner >= 0] = pieces[owner[owner >= 0]] < RUBBLE_PIECE * facts["brick_volume"]
        band = facts["band"]
        share = float(volume[band & small].sum() / volume[band].sum())
    samples.add("band_rubble", share)


def _limestone_setup(s: Samples) -> tuple[str, str]:
    f = s.facts
    text = (
        f"bricks {f['brick_x']:.2f} m × {f['brick_z']:.2f} m; the tunnel {f['tunnel_w']:.2f} m × "
        f"{f['tunnel_h']:.2f} m, cut cell by cell {f['hi'][0] - f['lo'][0]:.3f} m × {f['hi'][2] - f['lo'][2]:.3f} m"
    )
    return text, "as published (to a cell)"


def _limestone_charge(s: Samples) -> tuple[str, str]:
    f = s.facts
    text = (
        f"an equivalent cavity (its crushed zone) of radius {f['charge_r']:.2f} m, {-f['charge_dx']:.2f} m left of and "
        f"{f['charge_dz']:.2f} m above the tunnel's centre, {f['peak_pressure'] / 1e6:.0f} MPa on its wall (calibrated "
        "on the peak particle speed at the tunnel: docs/scenes.md)"
    )
    return text, "as published (the charge as a cavity)"


def _limestone_cells(s: Samples) -> tuple[str, str]:
    cell = s.facts["cell"]
    text = f"cells of {100 * cell:.1f} cm (LDEC: {100 * LDEC_CELL:.0f} cm; `[run] resolution = 3` builds them)"
    return text, "as published" if cell <= 1.05 * LDEC_CELL else "differs (coarser)"


def _limestone_rubble(s: Samples) -> tuple[str, str]:
    share = s.column("band_rubble")[-1]
    text = (
        f"{100 * share:.0f} % of the rock within {RUBBLE_BAND:g} m of the tunnel lies in pieces under "
        f"{100 * RUBBLE_PIECE:.0f} % of a brick at {1e3 * s.time[-1]:.0f} ms"
    )
    verdict = "reproduced" if share >= 0.5 else "partly" if share >= 0.2 else "not reproduced"
    return text, f"{verdict} (reproduced from 50 %, partly from 20 %)"


def _limestone_fill(s: Samples) -> tuple[str, str]:
    fill = s.column("fill")
    text = f"solid fill {fill[-1]:.3f} of the tunnel's volume at {1e3 * s.time[-1]:.0f} ms (largest {fill.max():.3f})"
    from limestone_tunnel import RUBBLE_SOLID_FRACTION

    filled = fill[-1] >= RUBBLE_SOLID_FRACTION
    return text, f"{'reproduced' if filled else 'not reproduced'} (a loose pile fills it at {RUBBLE_SOLID_FRACTION})"


def _limestone_cover(s: Samples) -> tuple[str, str]:
    rise = s.column("cover_rise")
    f = s.facts
    text = f"the highest rock {rise.max():.1f} m above the slab's top (the cover over the charge: {f['cover']:.1f} m)"
    return text, "as published (the cover stays)" if rise.max() <= 1.0 else "differs (the cover is thrown)"


# ----------------------------------------------------------------------------------------------------------------------
# The LDEC PMMA plates (§2.3, Fig. 4)
# ----------------------------------------------------------------------------------------------------------------------

PLATE_FRAMES = 5.0e4
"""The plates' report frames per second [1/s]: a sample every 20 µs, while the tip crosses an element (10 mm) in
about 11 µs at c_R, as benchmarks/fracture_scenes.py samples them (the scenes write one every 100 µs, too few for the
plateau's window)."""
BAND_REACH = 3.0
"""Splits this many elements off the centre line make a widening band [-] (a straight crack's stay within one)."""
BRANCH_REACH = 10.0
"""Splits this many elements off the centre line make a branch [-]: a crack that leaves the line at an angle, where a
zigzag band of small pieces stays within a few elements of it (docs/scenes.md, pmma_plate_branching)."""


def sample_plate(run, frame, samples: Samples) -> None:
    """Once: the plate's speeds, mesh and geometry (fracture_scenes.py ``RemotePlate``) and the node count as built.
    Per frame: the crack tip's |x| (``tip`` [m]: the farthest daughter of a split from the centre) and how far off the
    centre line the splits reach (``off_line`` [m]), and both as shares of the plate's half width and half height."""
    from fracture_scenes import RemotePlate  # beside this script, in benchmarks/

    if not samples.time:
        samples.facts["plate"] = RemotePlate.of(run.scene)
        samples.facts["built_nodes"] = run.sim.node_count
    plate = samples.facts["plate"]
    x = run.model.node_ref_q.numpy()[int(samples.facts["built_nodes"]) : run.sim.node_count].astype(np.float64)
    tip = float(np.abs(x[:, 0]).max()) if len(x) else 0.0
    off = float(np.abs(x[:, 1]).max()) if len(x) else 0.0
    samples.time.append(frame.time)
    samples.add("tip", tip)
    samples.add("off_line", off)
    samples.add("tip_share", tip / plate.edge)
    samples.add("off_share", off / plate.half_height)


def _plate_setup(s: Samples) -> tuple[str, str]:
    plate = s.facts["plate"]
    text = (
        f"a PMMA plate of {2e3 * plate.edge:.0f} × {2e3 * plate.half_height:.0f} mm, a "
        f"{2e3 * (plate.seed_tip - 0.5 * plate.h):.0f} mm centre seed crack, tension "
        "ramped up on its top and bottom edges (remote, quasi-static)"
    )
    return text, "as published"


def _plate_line(s: Samples) -> tuple[str, str]:
    plate = s.facts["plate"]
    if plate.unconstrained:
        return "every node may split (the paper's unconstrained run)", "as published (the variant)"
    return "only the nodes on the centre line may split ([fracture] region)", "as published"


def _plate_mesh(s: Samples) -> tuple[str, str]:
    plate = s.facts["plate"]
    ratio = plate.h / plate.delta_c
    text = f"h = {1e3 * plate.h:.1f} mm = {ratio:.0f} δ_c (δ_c = 2Γ/T_f = {1e6 * plate.delta_c:.0f} µm)"
    return text, "as published" if abs(ratio / 1000.0 - 1.0) < 0.1 else f"differs ({1000.0 / ratio:.0f}× finer in δ_c)"


def _plate_speed(s: Samples) -> tuple[str, str]:
    plate = s.facts["plate"]
    times, tips = np.asarray(s.time), s.column("tip")
    t0, window = plate.plateau(times, tips)
    if t0 is None or np.count_nonzero(window) < 3:
        return "the crack did not run far enough for a window of 3 samples", "not reproduced"
    t_w, x_w = times[window], tips[window]
    ratio = float(np.polyfit(t_w, x_w, 1)[0]) / plate.c_r
    text = (
        f"{ratio:.2f} c_R over {1e6 * t_w[0]:.0f}–{1e6 * t_w[-1]:.0f} µs, tip |x| {1e3 * x_w[0]:.0f}–"
        f"{1e3 * x_w[-1]:.0f} mm (the crack starts at {1e6 * t0:.0f} µs; the window ends before its own waves are "
        "back from the loaded edges)"
    )
    verdict = "reproduced" if 0.8 <= ratio <= 1.0 else "partly" if 0.6 <= ratio < 0.8 else "not reproduced"
    return text, f"{verdict} (reproduced in 0.8–1.0 c_R, partly from 0.6)"


def _plate_branch(s: Samples) -> tuple[str, str]:
    plate = s.facts["plate"]
    reach = s.column("off_line").max() / plate.h
    text = f"splits reach {1e3 * s.column('off_line').max():.1f} mm = {reach:.1f} h off the centre line"
    verdict = "reproduced" if reach >= BRANCH_REACH else "partly" if reach >= BAND_REACH else "not reproduced"
    return text, (
        f"{verdict} (a branch leaving the line from {BRANCH_REACH:g} h off it; partly: a band of splits widening to "
        f"{BAND_REACH:g} h)"
    )


SCENARIOS: dict[str, Scenario] = {
    "masonry_wall_blast": Scenario(
        scene="masonry_wall_blast",
        title="Masonry wall under blast (CIMNE §6.1, Figs. 3–5)",
        source=CIMNE,
        sample=sample_conversion,
        claims=(
            Claim(
                "§6.1, Fig. 3a",
                '"an explosive placed within a concrete box modelled with discrete elements"',
                _box_as_spheres("concrete"),
            ),
            Claim("§6.1, Fig. 3a", '"a peak pressure load of 600 MPa acting the center of the box"', _peak),
            Claim("§6.1, Fig. 3a", "the masonry wall, meshed with tetrahedra", _wall_mesh),
            Claim("§6.1", '"The explosion induces the multifracture of the box in many fragments"', _fragments),
            Claim("§6.1", '"that impact the adjacent wall"', _hit),
            Claim("§6.1, Fig. 4", '"inducing its instant failure"', _wall_fails),
            Claim(
                "§6.1, Fig. 5",
                '"The discrete elements have been progressively introduced in the wall"',
                _progressive("masonry", "wall tets"),
            ),
        ),
        plot={
            "converted_masonry": "wall tets converted",
            "masonry_piece": "wall's largest intact piece (share of its mass)",
        },
    ),
    "masonry_tunnel_blast": Scenario(
        scene="masonry_tunnel_blast",
        title="Masonry cylinder under internal blast (CIMNE §6.1, Fig. 6)",
        source=CIMNE,
        sample=sample_conversion,
        claims=(
            Claim(
                "Fig. 6",
                '"internal blast load induced by an explosive within a concrete box"',
                _box_as_spheres("concrete"),
            ),
            Claim("§6.1", '"the same type of blast loading" (600 MPa)', _peak),
            Claim("§6.1", "the box breaks into many fragments (as in §6.1)", _fragments),
            Claim("Fig. 6", "fragments of the box hit the cylinder", _hit),
            Claim(
                "Fig. 6",
                '"Deformation of structure at three time instants": the lining breaks',
                _progressive("masonry", "lining tets"),
            ),
        ),
        plot={"converted_masonry": "lining tets converted", "converted_concrete": "box tets as spheres"},
    ),
    "dam_crest_blast": Scenario(
        scene="dam_crest_blast",
        title="Double-curvature dam under a crest blast (CIMNE §6.2, Fig. 7)",
        source=CIMNE,
        sample=sample_conversion,
        claims=(
            Claim(
                "§6.2",
                '"The region adjacent to the explosion has been modelled with discrete (spherical) elements while '
                'the rest of the dam has been modelled with standard 4-noded tetrahedral elements"',
                lambda s: (
                    f"{int(s.facts['start_as_spheres_concrete'])} of {int(s.facts['tets_concrete'])} tets start as "
                    "spheres",
                    "as published"
                    if 0 < s.facts["start_as_spheres_concrete"] < s.facts["tets_concrete"]
                    else "differs",
                ),
            ),
            Claim("Fig. 7", '"a peak pressure load of 600 MPa acting at the center of the dam top"', _peak),
            Claim(
                "§6.2, Fig. 7",
                '"the evolution of the fracture at the dam top due to the explosion"',
                _progressive("concrete", "dam tets"),
            ),
            Claim("§6.2, Fig. 7", '"and the final fractured zone"', _final_zone),
        ),
        plot={"converted_concrete": "dam tets converted (incl. the start region)"},
        window=(-9.0, 9.0, 50.0, 64.0),  # the crest about the charge, seen from downstream (as docs' crater picture)
    ),
    "pmma_plate_remote": Scenario(
        scene="pmma_plate_remote",
        title="Centre-line fracture in a PMMA plate (LDEC §2.3, Fig. 4)",
        source=LDEC,
        sample=sample_plate,
        claims=(
            Claim(
                "§2.3, Fig. 4a",
                '"an applied stress is used to initiate failure using a seed crack at the plate\'s center"',
                _plate_setup,
            ),
            Claim("§2.3", '"Cohesive elements are constrained to lie along the middle line only"', _plate_line),
            Claim("§2.3", '"the mesh resolution is 1000 δ_c"', _plate_mesh),
            Claim(
                "§2.3, Fig. 4b",
                '"The crack-tip velocity quickly asymptotes to a value near the Rayleigh wavespeed"',
                _plate_speed,
            ),
        ),
        plot={"tip_share": "crack tip |x| (share of the half width)"},
        view="xy",
        color_by="damage",
        output_rate=PLATE_FRAMES,
        instants=(0.76, 0.86, 0.96),  # the crack running (it starts at about 0.7 of the run and is through by 0.96)
    ),
    "pmma_plate_branching": Scenario(
        scene="pmma_plate_branching",
        title="PMMA plate, cohesive elements unconstrained (LDEC §2.3)",
        source=LDEC,
        sample=sample_plate,
        claims=(
            Claim("§2.3", "the plate of Fig. 4", _plate_setup),
            Claim("§2.3", '"when the initiation of cohesive elements is unconstrained"', _plate_line),
            Claim("§2.3", '"Crack branching is observed"', _plate_branch),
        ),
        plot={
            "tip_share": "crack tip |x| (share of the half width)",
            "off_share": "splits off the centre line (share of the half height)",
        },
        view="xy",
        color_by="damage",
        output_rate=PLATE_FRAMES,
        instants=(0.7, 0.85, 1.0),  # the crack running (it starts at about 0.55 of the run)
    ),
    "limestone_tunnel": Scenario(
        scene="limestone_tunnel",
        title="A tunnel in infrequently jointed limestone (LDEC §4, Fig. 9)",
        source=LDEC,
        sample=sample_limestone,
        claims=(
            Claim(
                "§4",
                '"blocks of limestone, measuring 1.83 m wide, by 0.30 m high, surrounding a tunnel measuring 2.73 m '
                'by 2.80 m"',
                _limestone_setup,
            ),
            Claim(
                "§4",
                '"a tamped, one-ton detonation located 4.88 m left and 5.75 m above the tunnel"',
                _limestone_charge,
            ),
            Claim("§4", "10 cm elements (the model's resolution)", _limestone_cells),
            Claim(
                "§4",
                '"a significant portion of the rock mass surrounding the tunnel is reduced to rubble"',
                _limestone_rubble,
            ),
            Claim("§4, Fig. 9", '"This rubble mass is sufficient to fill in the original tunnel"', _limestone_fill),
            Claim("Fig. 9", "the rock over the charge stays in place (no crater in the pictures)", _limestone_cover),
        ),
        plot={"fill": "solid fill of the tunnel", "band_rubble": "rubble share of the rock within 1 m of it"},
        window=(-0.8, 11.5, -0.5, 20.5),  # the slab and 20 m above its foot (as docs/limestone_tunnel.png)
        instants=(0.01, 0.5, 1.0),  # Fig. 9's 10, 500 and 1000 ms of the 1 s run
        color_by="speed",
        scale=10.0,  # Fig. 9's key: 0-10 m/s
    ),
}
"""The scenarios by scene name."""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="*", metavar="SCENE", help=f"one of {', '.join(SCENARIOS)} [all]")
    parser.add_argument("--device", default="cpu", help="Warp device [cpu]")
    parser.add_argument("--end-time", type=float, help="simulated end time [s] (default: the scene's)")
    parser.add_argument("--out", type=Path, default=OUT_DIR, help=f"where the reports go [{OUT_DIR.relative_to(ROOT)}]")
    parser.add_argument("--work", type=Path, help="where the runs go [a temporary folder]")
    args = parser.parse_args(argv)
    allowed = [*SCENARIOS, FACILITY]
    unknown = [name for name in args.scenes if name not in allowed]
    if unknown:
        parser.error(f"unknown scenario {unknown[0]!r}; allowed: {', '.join(allowed)}")
    # What reproduces the report: the scenes and the end time (where the runs and reports go does not change them).
    command = " ".join(
        ["python benchmarks/seed_report.py", *args.scenes]
        + ([f"--end-time {args.end_time:g}"] if args.end_time is not None else [])
        + ([f"--device {args.device}"] if args.device != "cpu" else [])
    )
    with tempfile.TemporaryDirectory() as scratch:
        work = args.work or Path(scratch)
        for name in args.scenes or allowed:
            if name == FACILITY:  # two scenes side by side (benchmarks/facility_report.py)
                for path in write_facility_report(args.out, args.device, args.end_time, command.strip()):
                    print(f"{name}: wrote {path}")
                continue
            scenario = SCENARIOS[name]
            samples, stage = run_scenario(scenario, work, args.device, args.end_time)
            for path in write_report(scenario, samples, stage, args.out, command.strip()):
                print(f"{name}: wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
