"""What a run takes and gives: its options (:class:`RunOptions`), each frame it yields (:class:`Frame`), its
summary (:class:`RunSummary`, :func:`summary_json`) and the exceptions that end it early.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..limits import MAX_STEPS
from ..stages.energy import EnergyBalance


class NothingToDo(Exception):
    """A restart from a checkpoint at or past the end of the run: nothing is simulated and nothing is written."""


class RunInterrupted(KeyboardInterrupt):
    """A run stopped at once (a second Ctrl-C, or Ctrl-C in a script): the frames written so far are published in
    the USD stage, no checkpoint is written of the state the stop found.

    Attributes:
        outputs: what the run left behind, in words (the stage and its frames, the last checkpoint written).
    """

    def __init__(self, outputs: str) -> None:
        super().__init__(outputs)
        self.outputs = outputs


@dataclass
class RunOptions:
    """Command-line overrides of a scene's run and output settings (None = the scene's value).

    Attributes:
        device: Warp device.
        end_time: simulated end time [s].
        frames: number of output frames after the first (wins over end_time).
        out_dir: output directory.
        usd: USD file path.
        checkpoint_every: checkpoint period [s] (0 = at the end only).
        restart: checkpoint file to continue from.
        quiet: no progress bar or summary.
        max_steps: most time steps the run may take; more is refused before the first step (SceneError).
    """

    device: str | None = None
    end_time: float | None = None
    frames: int | None = None
    out_dir: Path | None = None
    usd: Path | None = None
    checkpoint_every: float | None = None
    restart: Path | None = None
    quiet: bool = False
    max_steps: int = MAX_STEPS


@dataclass
class RunSummary:
    """What a run did: simulated time [s], steps, wall time [s], throughput [particle-steps/s], contacts now,
    bonds broken, the energy balance at start and end, and the files written; FEM nodes and live tets, throughput
    [tet-steps/s] and the VTU collection where the scene has a mesh (or writes its spheres as VTU); the time series
    CSV (warpdem.io.timeseries).

    ``wall_time`` is the time spent stepping and writing the frames, less the time Warp took to compile (or load from
    its kernel cache) the kernel modules the run used for the first time: that is ``compile_time``, counted over the
    whole run (the build included), and the throughputs leave it out too.

    ``energy_in_play`` [J] is the largest :attr:`EnergyBalance.in_play` (kinetic + elastic + strain, or the work put
    in so far; no gravity potential) over the run's frames, and ``energy_error`` the balance's change over the run
    relative to it: a scale with no arbitrary datum, so the error does not depend on where z = 0 is.

    With fracture on (``fracture``; warpdem.io.timeseries.fracture_values): node ``splits``, cohesive elements
    ``cohesive_intact`` and ``cohesive_broken``, the crack area made (``crack_area``, one face [m²]) and fully
    opened (``crack_area_opened``), the energy the cohesive elements dissipated (``dissipated_cohesive`` [J]) and,
    to compare, Γ A_f of the broken ones (``cohesive_work_broken`` [J]: a broken element has dissipated exactly that,
    LDEC eq. 9; the intact ones add ½ f_c δ_max each)."""

    simulated_time: float
    steps: int
    wall_time: float
    particle_steps_per_second: float
    particles: int
    contacts: int
    bonds_broken: int
    bonds_intact: int
    energy_start: EnergyBalance
    energy_end: EnergyBalance
    usd_path: Path | None
    checkpoints: list[Path]
    nodes: int = 0
    tets: int = 0
    tet_steps_per_second: float = 0.0
    pvd_path: Path | None = None
    usd_sphere_stride: int = 1
    frame: int = 0
    """The last frame written (a run stopped between two frames ends after it, at ``simulated_time``)."""
    interrupted_by: int | None = None
    """The signal (SIGINT, SIGTERM) that stopped the run after ``frame``, once its checkpoint and stage were written."""
    series_path: Path | None = None
    energy_in_play: float = 0.0
    energy_error: float = 0.0
    fracture: bool = False
    splits: int = 0
    cohesive_intact: int = 0
    cohesive_broken: int = 0
    crack_area: float = 0.0
    crack_area_opened: float = 0.0
    dissipated_cohesive: float = 0.0
    cohesive_work_broken: float = 0.0
    fragments_path: Path | None = None
    """The per-frame fragment record (warpdem.stages.fragments), for scenes that can break apart; None otherwise."""
    fragment_count: int = 0
    fragment_largest: float = 0.0
    """Mass of the largest fragment at the last frame [kg]."""
    fragment_mass: float = 0.0
    """Mass of all fragments at the last frame [kg]."""
    ejecta_count: int = 0
    ejecta_speed_max: float = 0.0
    ejecta_speed_median: float = 0.0
    """The pieces broken off at the last frame (:func:`ejecta_speeds`: every fragment but the largest breakable one
    and the loose spheres, such as an impactor), their number and the largest and median speed of their centres of
    mass [m/s] (0 without any)."""
    rigid: str = ""
    """What the switch to rigid blocks did in this run (warpdem.stages.rigid.RigidReport.format), empty without one."""
    compile_time: float = 0.0
    """Time Warp spent compiling kernel modules on their first use, or loading them from its kernel cache [s]
    (:func:`kernel_load_seconds`), over the whole run; not part of ``wall_time``."""
    time_step: float = 0.0
    """The time step at the end of the run [s]."""
    critical_dt: float = math.inf
    """The critical time step it is held under [s] (``Model.critical_dt``), and what sets it (``critical_dt_source``:
    a tet, a contact, a bond, or the contact reach of the fastest body, warpdem.stages.guard.reach_step)."""
    critical_dt_source: str = ""
    loads: list[tuple[str, float, float]] = field(default_factory=list)
    """Each pressure load's name, the area it pushes on [m²] and the normal impulse ∫∫ p dA dt it delivered [N s]
    (warpdem.load_data.LoadModel.loaded_areas, .impulses)."""
    ranks: int = 1
    """The MPI ranks the run was decomposed over (warpdem.parallel; 1: one process)."""
    halo_bytes_per_step: int = 0
    """On ranks: the bytes all ranks' halo messages carry in one step at the end of the run (0 in one process)."""
    migrations: int = 0
    """On ranks: how many times the spheres migrated, or the tets' items were decomposed again, between ranks."""

    def format(self) -> str:
        e0, e1 = self.energy_start, self.energy_end
        spheres = self.particles > 0
        lines = [f"simulated time   {self.simulated_time:.6g} s in {self.steps} steps"]
        if self.time_step > 0.0:
            step = f"time step        {self.time_step:.4g} s"
            if math.isfinite(self.critical_dt):
                step += f"  (critical {self.critical_dt:.4g} s, set by {self.critical_dt_source})"
            lines.append(step)
        wall = f"wall time        {self.wall_time:.3f} s"
        if self.ranks > 1:
            wall += (
                f" on {self.ranks} ranks (halo {self.halo_bytes_per_step / 1e3:.1f} kB a step, "
                f"{self.migrations} migration{'s' if self.migrations != 1 else ''})"
            )
        if spheres:
            wall += f"  ({self.particle_steps_per_second / 1e6:.3f} M particle-steps/s)"
        if self.compile_time > 0.0:
            wall += f"; kernel compiling {self.compile_time:.2f} s more (first use, not counted)"
        lines.append(wall)
        if spheres:
            lines += [
                f"particles        {self.particles}   contacts {self.contacts}",
                f"bonds            {self.bonds_intact} intact, {self.bonds_broken} broken",
            ]
        if self.nodes:
            rate = self.tet_steps_per_second / 1e6
            lines.append(f"rock mesh        {self.nodes} nodes, {self.tets} tets  ({rate:.3f} M tet-steps/s)")
        if self.rigid:
            lines.append(f"rigid blocks     {self.rigid.removeprefix('rigid switch: ')}")
        for name, area, impulse in self.loads:
            lines.append(f"load {name:<11} {area:.6g} m² loaded, impulse {impulse:.6g} N s")
        if self.fracture:
            lines += [
                f"fracture         {self.splits} node splits; cohesive elements {self.cohesive_intact} intact, "
                f"{self.cohesive_broken} broken",
                f"crack area       {self.crack_area:.6g} m² made, {self.crack_area_opened:.6g} m² opened (one face)",
                f"cohesive energy  {self.dissipated_cohesive:.6g} J dissipated; Γ × area of the broken elements "
                f"{self.cohesive_work_broken:.6g} J",
            ]

        def row(label: str, a: float, b: float) -> str:
            return f"  {label:<15}{a:<14.6g} {b:.6g}"

        lines += ["energy [J]       start          end", row("kinetic", e0.kinetic, e1.kinetic)]
        if self.nodes:
            lines.append(row("  of nodes", e0.kinetic_nodes, e1.kinetic_nodes))
        if e0.kinetic_rigid or e1.kinetic_rigid:
            lines.append(row("  of rigid bl.", e0.kinetic_rigid, e1.kinetic_rigid))
        lines.append(row("Verlet shadow", e0.shadow, e1.shadow))
        if e1.released_rigid_switch:
            lines.append(row("rigid switch", e0.released_rigid_switch, e1.released_rigid_switch))
        if e0.step_change or e1.step_change:
            # What taking another time step, or the forces of a split pass, changed Verlet's shadow term by
            # (Simulation.set_time_step, Simulation.fracture_pass).
            lines.append(row("step change", e0.step_change, e1.step_change))
        if self.nodes:
            lines += [
                row("strain", e0.strain, e1.strain),
                row("viscous diss.", e0.dissipated_viscous, e1.dissipated_viscous),
                row("non-refl. abs.", e0.absorbed_boundaries, e1.absorbed_boundaries),
                row("load work", e0.load_work, e1.load_work),
                row("contact diss.", e0.dissipated_fem_contact, e1.dissipated_fem_contact),
            ]
            if spheres:
                lines.append(row("sph-face diss.", e0.dissipated_sphere_face, e1.dissipated_sphere_face))
        if self.fracture:
            lines += [
                row("cohesive el.", e0.cohesive_elastic, e1.cohesive_elastic),
                row("cohesive diss.", e0.dissipated_cohesive, e1.dissipated_cohesive),
                row("coh. trapezoid", e0.cohesive_trapezoid, e1.cohesive_trapezoid),
            ]
            if e0.substep_work or e1.substep_work:
                # The other forces' work over the sub-stepped daughters' motion (warpdem.stages.substep).
                lines.append(row("sub-step work", e0.substep_work, e1.substep_work))
        if e0.released_conversion or e1.released_conversion or e0.coupling_elastic or e1.coupling_elastic:
            # FEM → DEM conversion: what left the mechanical books as tets turned into spheres, and the penalty
            # springs tying the spheres to the continuum (warpdem.stages.conversion, warpdem.stages.coupling), so the
            # lines printed add up to the balance.
            lines += [
                row("conversion", e0.released_conversion, e1.released_conversion),
                row("coupling el.", e0.coupling_elastic, e1.coupling_elastic),
            ]
        if self.fracture or e1.contact_topology != 0.0:
            # What split and conversion passes put into the FEM contact springs (Simulation._book_contact_topology).
            lines.append(row("contact gain", e0.contact_topology, e1.contact_topology))
        lines.append(row("elastic", e0.elastic, e1.elastic))
        if e0.gravity_potential != 0.0 or e1.gravity_potential != 0.0:
            lines.append(row("gravity pot.", e0.gravity_potential, e1.gravity_potential))
        if spheres:
            lines += [
                row("damping diss.", e0.dissipated_damping, e1.dissipated_damping),
                row("friction diss.", e0.dissipated_friction, e1.dissipated_friction),
                row("k_t(δ) change", e0.stiffness_change, e1.stiffness_change),
                row("bond breakage", e0.released_by_bond_breakage, e1.released_by_bond_breakage),
                row("bond trapezoid", e0.bond_trapezoid, e1.bond_trapezoid),
                row("wall work", e0.boundary_work, e1.boundary_work),
            ]
        lines.append(
            f"  balance        {e0.total:<14.6g} {e1.total:.6g}   "
            f"(error {self.energy_error:+.2e} of {self.energy_in_play:.3g} J in play)"
        )
        if self.usd_path is not None:
            lines.append(f"USD              {self.usd_path}")
            if self.usd_sphere_stride > 1:
                lines.append(
                    f"                 spheres subsampled: those whose id is a multiple of {self.usd_sphere_stride} "
                    "(a frame held more than output.usd_max_spheres)"
                )
        if self.pvd_path is not None:
            lines.append(f"VTU series       {self.pvd_path}")
        if self.fragments_path is not None:
            share = self.fragment_largest / self.fragment_mass if self.fragment_mass > 0.0 else 0.0
            lines.append(
                f"fragments        {self.fragment_count}, largest {self.fragment_largest:.6g} kg ({share:.1%} of "
                f"{self.fragment_mass:.6g} kg)"
            )
            if self.ejecta_count:
                pieces = f"{self.ejecta_count} piece{'s' if self.ejecta_count != 1 else ''}"
                lines.append(
                    f"ejecta speed     max {self.ejecta_speed_max:.6g} m/s, median {self.ejecta_speed_median:.6g} m/s "
                    f"of the {pieces} broken off (fragments but the largest; loose spheres such as an impactor "
                    "left out)"
                )
        if self.series_path is not None:
            lines.append(f"time series      {self.series_path}")
        if self.fragments_path is not None:
            lines.append(f"fragment record  {self.fragments_path}")
        if self.checkpoints:
            lines.append(f"checkpoint       {self.checkpoints[-1]}")
        return "\n".join(lines)


@dataclass(frozen=True)
class FrameEnergy:
    """The energy books at an output frame.

    Attributes:
        balance: every line of the books [J] (warpdem.stages.energy.EnergyBalance); its fields read through this
            object too (``frame.energy.kinetic``).
        error: the balance's drift since the first frame of the run's timeline, relative to ``in_play`` [-] (the
            time series' ``energy_error``, the number the summary prints).
        in_play: the largest energy in play over the timeline so far [J] (the error's scale).
    """

    balance: EnergyBalance
    error: float
    in_play: float

    def __getattr__(self, name: str) -> Any:
        if name == "balance":  # not set yet (copy, unpickling): no recursion through the delegation below
            raise AttributeError(name)
        return getattr(self.balance, name)


@dataclass(frozen=True)
class Frame:
    """An output frame, as :meth:`Run.frames` yields it once its outputs are written.

    Attributes:
        index: frame number (the USD time code; 0 is the initial state).
        time: simulated time [s].
        step: time steps taken so far.
        energy: the energy books (:class:`FrameEnergy`; ``energy.error`` is the balance's relative drift).
        splits: node splits so far (0 without nodal fracture).
        fragments: the number of fragments, where the run labels them (None elsewhere).
        series: the frame's row of the time series, column → value (warpdem.io.timeseries: counts, wall and load
            forces, every energy line).
    """

    index: int
    time: float
    step: int
    energy: FrameEnergy
    splits: int = 0
    fragments: int | None = None
    series: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------------------
# Kernel compile time


def ejecta_speeds(model: Any, state: Any, fragments: Any) -> np.ndarray:
    """Centre-of-mass speeds of the pieces broken off [m/s], shape (K,), float64: every fragment but the largest
    breakable one, leaving out the loose spheres (reads back; call between steps).

    A loose sphere is one that never had a bond (none intact, none broken) and was not made by conversion: an
    impactor, a grain poured in. A fragment of loose spheres alone was never part of anything that could break,
    so its speed (an impactor's own) says nothing about what the impact threw off.

    Args:
        model: the run's model.
        state: its state, as labelled.
        fragments: their fragments (warpdem.stages.fragments.FragmentStats).
    """
    from ..io.output import sphere_damage

    count = fragments.count
    if count == 0:
        return np.zeros(0)
    breakable = np.zeros(count, dtype=bool)
    nodes = fragments.node_label[fragments.node_label >= 0]
    breakable[nodes] = True
    label = fragments.particle_label
    if len(label):
        broken, _ = sphere_damage(model, state)
        n = len(label)
        nb = int(state.bond_count.numpy()[0]) if model.bond_capacity else 0
        intact = state.bond_broken.numpy()[:nb] == 0
        ends = np.concatenate([state.bond_i.numpy()[:nb][intact], state.bond_j.numpy()[:nb][intact]])
        bonded = (broken > 0) | (np.bincount(ends, minlength=n)[:n] > 0)
        if model.conversion_interval > 0 or model.tet_may_convert is not None:
            bonded |= model.particle_part.numpy()[:n] == model.conversion_part
        breakable[label[(label >= 0) & bonded]] = True
    kept = np.flatnonzero(breakable)
    if len(kept) == 0:
        return np.zeros(0)
    # The largest of them is the body they broke from; ties keep the id order, as the fragment listing does.
    largest = kept[np.argsort(-fragments.fragment_mass[kept], kind="stable")[0]]
    others = kept[kept != largest]
    return np.linalg.norm(fragments.fragment_velocity[others], axis=1)


def summary_json(summary: RunSummary) -> str:
    """The summary as JSON (for scripts)."""
    d = dataclasses.asdict(summary)
    d["usd_path"] = str(summary.usd_path) if summary.usd_path else None
    d["critical_dt"] = summary.critical_dt if math.isfinite(summary.critical_dt) else None
    d["checkpoints"] = [str(p) for p in summary.checkpoints]
    d["pvd_path"] = str(summary.pvd_path) if summary.pvd_path else None
    d["series_path"] = str(summary.series_path) if summary.series_path else None
    d["fragments_path"] = str(summary.fragments_path) if summary.fragments_path else None
    return json.dumps(d, indent=1)
