"""Stability guard: an explicit time step above the critical one is refused at set-up, and a run whose state goes
non-finite or runs away is stopped between runs of steps with a message that names the time, the step, the first
bad sphere or node and the likely cause.

Set-up: the builder estimates the critical time step and what sets it (:class:`CriticalStep`: a tet, a contact,
a bond, a dashpot, a penalty spring); :func:`check_time_step` refuses an explicit dt above it. The refusal is at
the critical step itself, not at the ``safety_factor`` fraction of it that ``dt = "auto"`` takes: the estimates are
bounds (element eigenvalue bounds, the fastest mode of the stiffest sphere), so a dt between the two may well be
stable and is the user's call, while one above the bound is not stable by the estimate's own argument.

Run time: :class:`StabilityGuard` launches one check over the spheres and one over the FEM nodes after each run of
steps (``kernels/guard.py``; no read-back inside the step): a non-finite position, velocity or spin, or a speed above
the run-away bound ``Model.speed_limit + |g| t`` (:func:`run_away_speed`): the fastest P-wave speed c_p of the
materials and bond chains, or SPEED_LIMIT_FACTOR times the fastest initial, wall or driver speed, or particle
velocity 2 p / (ρ c_p) of a pressure load, if that is higher.
A material point moving at c_p would be at 100 % strain (v = ε c), a sphere can gain no more than its launch speeds
from collisions, and gravity adds at most |g| t: what passes the bound is a blow-up. A blow-up that saturates below
it (an unconfined bonded cluster whose bonds all break flies apart at about c_p) is not caught here; the energy
balance of the summary shows it.

Contact reach: a contact acts only while two bodies overlap, and the overlap a step can resolve is bounded by the
bodies' size: the smallest sphere radius or the shortest tet edge (``Model.contact_reach``). A body moving more than
REACH_FRACTION of that in one step can step over a contact (a ball tunnelling through a boulder, blocks falling
through their base). At set-up the fastest launch speed bounds the step (:func:`reach_step`, one more candidate of the
critical step, so ``dt = "auto"`` respects it and an explicit dt above it is refused); at run time the guard stops a
run whose sphere or node moves faster than ``REACH_FRACTION × contact_reach / dt`` (:func:`reach_speed`) whether or
not the step is stable, naming the body and its speed.

Penetration past what a contact resolves, whether or not the step is stable (``kernels/guard.py`` says each rule and
its threshold): a sphere's centre behind a wall, inside another sphere or behind a face it projects into (unless a
coupling ties it to the rock), an FEM
node let go of by a face it went half the tet's height behind, or a surface node behind a wall by more than that for
the largest tets. The message names the body, the depth and the reach it passed. The FEM contact records the faces
passed in the step, where they happen (:meth:`StabilityGuard.watch`); the guard reads and clears them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import guard as kg
from ..model import Model, State

SPEED_LIMIT_FACTOR = 10.0
"""Run-away speed bound relative to the fastest launch speed of the scene (initial, wall, driver, load) [-]."""

REACH_FRACTION = 0.5
"""The most a sphere or node may move in one step, as a fraction of the smallest contact reach [-]: a sphere moving
half its radius per step still meets a sphere or face of its own size in at least two steps of overlap."""

PROBLEMS = {
    kg.PROBLEM_POSITION: "non-finite position",
    kg.PROBLEM_VELOCITY: "non-finite velocity",
    kg.PROBLEM_SPIN: "non-finite angular velocity",
    kg.PROBLEM_SPEED: "run-away speed",
    kg.PROBLEM_REACH: "too fast for the contact reach",
    kg.PROBLEM_PENETRATION: "penetration past the contact's reach",
    kg.PROBLEM_OVERLAP: "penetration past the contact's reach",
    kg.PROBLEM_PASSED_FACE: "penetration past the contact's reach",
}


@dataclass(frozen=True)
class CriticalStep:
    """A critical time step [s] and what sets it, in words (``"tet 123 of material granite"``)."""

    value: float
    source: str


class UnstableTimeStepError(ValueError):
    """An explicit time step above the critical one, refused at set-up.

    Attributes:
        dt: the time step asked for [s]. critical: the estimate and what sets it.
    """

    def __init__(self, dt: float, critical: CriticalStep) -> None:
        self.dt = dt
        self.critical = critical
        super().__init__(
            f"dt = {dt:.4g} s exceeds the critical time step {critical.value:.4g} s, set by {critical.source}"
        )


def check_time_step(dt: float, critical: CriticalStep, allow_unstable: bool = False) -> None:
    """Refuse an explicit time step [s] above the critical one, unless ``allow_unstable``.

    Raises:
        UnstableTimeStepError: dt > critical.value and not allow_unstable.
    """
    if dt > critical.value and not allow_unstable:
        raise UnstableTimeStepError(dt, critical)


def p_wave_speed(density: float, young: float, poisson: float) -> float:
    """c_p = sqrt((λ + 2μ)/ρ) = sqrt(E (1 - ν) / ((1 + ν)(1 - 2ν) ρ)) [m/s], the fastest wave of an elastic solid."""
    return math.sqrt(young * (1.0 - poisson) / ((1.0 + poisson) * (1.0 - 2.0 * poisson) * density))


def run_away_speed(wave_speeds: list[float], launch_speeds: list[float]) -> float:
    """The run-away bound ``Model.speed_limit`` [m/s]: the fastest wave speed, or SPEED_LIMIT_FACTOR × the fastest
    launch speed (initial, wall, driver, pressure load) if higher (inf when there is none: only non-finite values
    are caught)."""
    fastest = max(max(wave_speeds, default=0.0), SPEED_LIMIT_FACTOR * max(launch_speeds, default=0.0))
    return fastest if fastest > 0.0 else math.inf


def reach_step(reach: float, reach_source: str, speed: float, body: str) -> CriticalStep:
    """The step [s] at which a body at ``speed`` [m/s] moves REACH_FRACTION of the smallest contact reach ``reach``
    [m] (inf when nothing moves or nothing has a reach); ``body`` names the fastest body, ``reach_source`` what sets
    the reach."""
    if speed <= 0.0 or not math.isfinite(reach):
        return CriticalStep(math.inf, "")
    return CriticalStep(
        REACH_FRACTION * reach / speed,
        f"the contact reach: {body} at {speed:.4g} m/s may move at most {REACH_FRACTION:g} x the smallest contact "
        f"reach {reach:.4g} m ({reach_source}) per step",
    )


def reach_speed(model: Model) -> float:
    """The fastest a sphere or node may move at the model's step [m/s]: REACH_FRACTION × contact_reach / dt."""
    return REACH_FRACTION * model.contact_reach / model.dt if model.dt > 0.0 else math.inf


BOOKS_SLACK = 0.01
"""What the books may drift by relative to the energy that can flow [-]: twice the bound the shipped scenes' balance
keeps (tests/test_scenes.py, MESH_BOUND 5e-3)."""


def energy_from_nowhere(
    start: tuple[float, float, float, float],
    now: tuple[float, float, float, float, float, float],
    dt: float,
    critical_dt: float,
) -> tuple[float, float] | None:
    """Energy that appeared from nowhere [J] and the most a sane run may show, or None when within it.

    Velocity Verlet conserves kinetic − shadow + the rest of the books (warpdem.stages.energy) at any step, stable or
    not: past the critical step the shadow term S = dt²/8 Σ |f|²/m grows with the kinetic energy and the books still
    close. Counting S as the energy it stands for, ``appeared`` = Δ(total + S) is what the kinetic and stored energies
    gained beyond the work put in, the gravity released and what was dissipated. In a stable step S is at most
    (dt / critical_dt)² of the energy stored (S/U = (ω dt)²/4 for a mode of frequency ω, ≤ 1 at ω dt = 2), so a sane
    run keeps ``appeared`` ≤ (min(1, (dt/critical_dt)²) + BOOKS_SLACK) × the energy that can flow (in play at the
    start, work put in, gravity released) + S at the start + float32 rounding of the largest term.

    Args:
        start: (total, shadow, in play, gravity potential) of the books at the start [J].
        now: (total, shadow, gravity potential, work put in by walls and drivers, load work, stiffness and contact
            topology gains) of the books now [J].
        dt: the step [s].
        critical_dt: the critical step [s].
    """
    total0, shadow0, in_play0, gravity0 = start
    total, shadow, gravity, boundary_work, load_work, gains = now
    appeared = (total + shadow) - (total0 + shadow0)
    flow = in_play0 + abs(boundary_work) + abs(load_work) + abs(gains) + max(gravity0 - gravity, 0.0)
    ratio = min(1.0, (dt / critical_dt) ** 2) if math.isfinite(critical_dt) and critical_dt > 0.0 else 1.0
    rounding = 16.0 * float(np.finfo(np.float32).eps) * max(abs(gravity0), abs(gravity), flow)
    allowed = (ratio + BOOKS_SLACK) * flow + abs(shadow0) + rounding
    return (appeared, allowed) if appeared > allowed else None


class UnstableRunError(RuntimeError):
    """A run stopped because its state went non-finite or ran away.

    Attributes:
        time: simulated time of the first bad state [s]. step: its step. entity: the first bad sphere or node, in
        words. problem: what is wrong with it. cause: the likely cause. outputs: what the run left behind (the
        runner adds it: the published stage, the last good checkpoint), or "".
    """

    def __init__(self, time: float, step: int, entity: str, problem: str, cause: str) -> None:
        self.time, self.step, self.entity, self.problem, self.cause = time, step, entity, problem, cause
        self.outputs = ""
        super().__init__()

    def __str__(self) -> str:
        line = (
            f"unstable run stopped at t = {self.time:.6g} s (step {self.step}): {self.entity}: {self.problem}; "
            f"likely cause: {self.cause}"
        )
        return f"{line}; {self.outputs}" if self.outputs else line


@dataclass
class GuardReport:
    """The guard's findings after a run of steps: the first bad sphere and node slots (-1 for none), what is wrong
    with each (a ``kernels.guard.PROBLEM_*`` code) and how many are bad."""

    sphere: int
    sphere_problem: int
    spheres_bad: int
    node: int
    node_problem: int
    nodes_bad: int
    sphere_face: int = -1
    """The face the first bad sphere went past the reach of (its problem ``PROBLEM_PASSED_FACE``), else -1."""
    node_face: int = -1
    """The same for the first bad node."""


class StabilityGuard:
    """The run-time check of a simulation: two launches and a read-back of four ints, between runs of steps (the
    read-back shared with the chunk status's, warpdem.stages.status, in a run).

    Args:
        device: Warp device of the model.
    """

    def __init__(self, device: wp.context.Device) -> None:
        clean = np.array([kg.NO_KEY, 0, kg.NO_KEY, 0], dtype=np.int32)
        self.report = wp.array(clean, dtype=int, device=device)
        self.clean = wp.array(clean, dtype=int, device=device)  # on the device: a reset without a transfer
        self._none = wp.empty(0, dtype=int, device=device)
        self._no_stiffness = wp.empty(0, dtype=float, device=device)
        self.node_passed: wp.array | None = None
        self.sphere_passed: wp.array | None = None

    def watch(self, node_passed: wp.array | None, sphere_passed: wp.array | None) -> None:
        """Read the faces each node and sphere went past the reach of in the steps since the last check (the FEM
        contact stage's records, warpdem.stages.fem_contact.FemContact ``node_passed`` / ``sphere_passed``; None for a
        model without FEM contact), and clear them once read."""
        self.node_passed, self.sphere_passed = node_passed, sphere_passed

    def check(self, model: Model, state: State) -> GuardReport | None:
        """Check the state now; None when every sphere and node is finite, below the run-away bound and the contact
        reach's speed, and no contact was passed since the last check."""
        wp.copy(self.report, self.clean)
        self.launch(model, state)
        return self.interpret(self.report.numpy())

    def launch(self, model: Model, state: State, sphere_lists: bool | None = None) -> None:
        """The check's launches (no read-back): they raise ``self.report`` from clean (its state after the last
        :meth:`check`, or after the chunk status read it: warpdem.stages.status). ``sphere_lists``: whether the
        spheres have contact lists (the caller knows; None: read the radii back to find out)."""
        m, s = model, state
        if sphere_lists is None:
            sphere_lists = m.max_radius > 0.0
        gravity_norm = float(np.linalg.norm(m.gravity))
        reach = min(reach_speed(m), 3.0e38)  # float32 kernel argument
        if m.particle_capacity:
            if self.sphere_passed is not None and m.coupling_capacity:
                wp.launch(
                    kg.drop_coupled_records_kernel,
                    dim=m.coupling_capacity,
                    inputs=[s.coupling_count, s.coupling_particle],
                    outputs=[self.sphere_passed],
                    device=m.device,
                )
            wp.launch(
                kg.check_spheres_kernel,
                dim=m.particle_capacity,
                inputs=[
                    m.speed_limit,
                    gravity_norm,
                    reach,
                    m.num_walls,
                    m.wall_normal,
                    m.particle_inv_mass,
                    m.particle_radius,
                    m.max_neighbors if sphere_lists else 0,  # no sphere contact stage: no lists
                    s.particle_count,
                    s.particle_q,
                    s.particle_qd,
                    s.particle_omega,
                    s.time,
                    s.wall_point,
                    s.nbr_count,
                    s.nbr_index,
                    self._none if self.sphere_passed is None else self.sphere_passed,
                ],
                outputs=[self.report],
                device=m.device,
            )
        if m.node_capacity:
            stiffness = m.node_contact_stiffness
            wp.launch(
                kg.check_nodes_kernel,
                dim=m.node_capacity,
                inputs=[
                    m.speed_limit,
                    gravity_norm,
                    reach,
                    m.num_walls,
                    m.wall_normal,
                    m.node_inv_mass,
                    self._no_stiffness if stiffness is None else stiffness,
                    m.face_depth_max,
                    s.node_count,
                    s.node_u,
                    s.node_q,
                    s.node_qd,
                    s.time,
                    s.wall_point,
                    self._none if self.node_passed is None else self.node_passed,
                ],
                outputs=[self.report],
                device=m.device,
            )

    def interpret(self, values: Sequence[float]) -> GuardReport | None:
        """The report of the check's values (key and count of bad spheres, of bad nodes: ``self.report`` read back, or
        the chunk status's copy of it); None when all is well. Reads back the faces passed when one was."""
        key_s, bad_s, key_n, bad_n = (int(v) for v in values)
        if not bad_s and not bad_n:
            return None
        np_ = kg.NUM_PROBLEMS
        report = GuardReport(
            sphere=key_s // np_ if bad_s else -1,
            sphere_problem=key_s % np_,
            spheres_bad=bad_s,
            node=key_n // np_ if bad_n else -1,
            node_problem=key_n % np_,
            nodes_bad=bad_n,
        )
        # The faces passed, read before the records are cleared (a replay of the steps writes them again).
        if report.sphere >= 0 and report.sphere_problem == kg.PROBLEM_PASSED_FACE:
            report.sphere_face = int(self.sphere_passed.numpy()[report.sphere])
        if report.node >= 0 and report.node_problem == kg.PROBLEM_PASSED_FACE:
            report.node_face = int(self.node_passed.numpy()[report.node])
        for record in (self.node_passed, self.sphere_passed):
            if record is not None:
                record.fill_(-1)
        return report

    def error(self, model: Model, state: State, report: GuardReport, step: int, time: float) -> UnstableRunError:
        """The error for a report: the first bad sphere (else node) in words, what is wrong, the likely cause."""
        m, s = model, state
        bound = m.speed_limit + float(np.linalg.norm(m.gravity)) * time
        if report.sphere >= 0:
            i, code = report.sphere, report.sphere_problem
            pid = int(m.particle_id.numpy()[i])
            part = _part_name(m, int(m.particle_part.numpy()[i]))
            entity = f"sphere {pid} (part {part})"
            values = {
                kg.PROBLEM_POSITION: s.particle_q,
                kg.PROBLEM_PENETRATION: s.particle_q,
                kg.PROBLEM_OVERLAP: s.particle_q,
                kg.PROBLEM_PASSED_FACE: s.particle_q,
                kg.PROBLEM_SPIN: s.particle_omega,
            }.get(code, s.particle_qd)
        else:
            i, code = report.node, report.node_problem
            tets = m.tet_nodes.numpy()[: int(s.tet_count.numpy()[0])]
            in_tet = np.nonzero((tets == i).any(axis=1))[0]
            where = ""
            if len(in_tet):
                t = int(in_tet[0])
                where = f" (of tet {t}, material {m.material_names[int(m.tet_material.numpy()[t])]})"
            entity = f"FEM node {i}{where}"
            values = {
                kg.PROBLEM_POSITION: s.node_u,
                kg.PROBLEM_PENETRATION: s.node_q,
                kg.PROBLEM_PASSED_FACE: s.node_q,
            }.get(code, s.node_qd)
        value = values.numpy()[i].astype(np.float64)
        cause = likely_cause(m)
        if code == kg.PROBLEM_SPEED:
            problem = f"speed {np.linalg.norm(value):.3g} m/s above the run-away bound {bound:.3g} m/s"
        elif code == kg.PROBLEM_REACH:
            speed = float(np.linalg.norm(value))
            problem = (
                f"speed {speed:.4g} m/s moves it {speed * m.dt:.3g} m per step (dt = {m.dt:.4g} s), more than "
                f"{REACH_FRACTION:g} x the smallest contact reach {m.contact_reach:.4g} m ({m.contact_reach_source}): "
                "a contact can be stepped over"
            )
            if m.dt <= m.critical_dt:
                cause = (
                    f"a body too fast for the time step (tunnelling or penetration past the contact); use "
                    f"dt <= {REACH_FRACTION * m.contact_reach / speed:.4g} s"
                )
        elif code in (kg.PROBLEM_PENETRATION, kg.PROBLEM_OVERLAP, kg.PROBLEM_PASSED_FACE):
            sphere = report.sphere >= 0
            face = report.sphere_face if sphere else report.node_face
            problem, what = penetration(m, s, i, sphere, code, value, face)
            problem = f"{PROBLEMS[code]}: {problem}: more than the contact resolves"
            cause = (
                f"an impact or load {what} cannot stop within its reach (speeds, gravity or forces far beyond what "
                "the contact carries)"
            )
            if m.dt > m.critical_dt:
                cause = likely_cause(m)
        else:
            problem = f"{PROBLEMS[code]} {np.array2string(value, precision=3)}"
        problem += f" ({report.spheres_bad} spheres and {report.nodes_bad} FEM nodes bad)"
        return UnstableRunError(time, step, entity, problem, cause)


def penetration(
    model: Model, state: State, i: int, sphere: bool, code: int, x: np.ndarray, face: int
) -> tuple[str, str]:
    """What a penetration report says of sphere or node ``i`` at ``x`` [m] (``face``: the face it passed, for
    ``PROBLEM_PASSED_FACE``): the depth and the reach it passed, in words, and the contact it passed (for the cause).
    Reads back (the error path only)."""
    m, s = model, state
    where = f"{np.array2string(x, precision=3)}"
    if code == kg.PROBLEM_PENETRATION:
        gaps = np.einsum(
            "ij,ij->i", x - s.wall_point.numpy().astype(np.float64), m.wall_normal.numpy().astype(np.float64)
        )
        w = int(np.argmin(gaps))
        if sphere:
            radius = float(m.particle_radius.numpy()[i])
            return (
                f"its centre {where} is {-gaps[w]:.3g} m behind wall {w}, an overlap of {radius - gaps[w]:.3g} m "
                f"beyond its radius {radius:.3g} m",
                "the wall's contact",
            )
        return (
            f"it is at {where}, {-gaps[w]:.3g} m behind wall {w}, deeper than the node contact's largest reach "
            f"{m.face_depth_max:.3g} m (half the tallest tet over a boundary face)",
            "the wall's contact",
        )
    if code == kg.PROBLEM_OVERLAP:
        k = m.max_neighbors
        count = min(int(s.nbr_count.numpy()[i]), k)
        partners = s.nbr_index.numpy()[i * k : i * k + count]
        q = s.particle_q.numpy().astype(np.float64)
        r = m.particle_radius.numpy().astype(np.float64)
        overlap = r[i] + r[partners] - np.linalg.norm(q[partners] - q[i], axis=1)
        smaller = np.minimum(r[i], r[partners])
        best = int(np.argmax(overlap / smaller))
        j = int(partners[best])
        pid = int(m.particle_id.numpy()[j])
        part = _part_name(m, int(m.particle_part.numpy()[j]))
        return (
            f"its centre {where} and sphere {pid}'s (part {part}) overlap by {overlap[best]:.3g} m, past the smaller "
            f"radius {smaller[best]:.3g} m: the smaller one's centre is inside the larger",
            "the spheres' contact",
        )
    fn = m.face_nodes.numpy()[face]
    a, b, c = s.node_q.numpy()[fn].astype(np.float64)
    normal = np.cross(b - a, c - a)
    depth = -float((x - a) @ normal) / float(np.linalg.norm(normal))
    t = int(m.face_tet.numpy()[face])
    of = f"face {face} (of tet {t}, material {m.material_names[int(m.tet_material.numpy()[t])]})"
    if sphere:
        radius = float(m.particle_radius.numpy()[i])
        return (
            f"its centre {where} went {depth:.3g} m behind {of}, an overlap of {radius + depth:.3g} m past its "
            f"radius {radius:.3g} m, where the face's contact lets go",
            "the face's contact",
        )
    reach = float(m.face_depth.numpy()[face])
    return (
        f"it is at {where}, {depth:.3g} m behind {of}, past the face's reach {reach:.3g} m (half the tet's height over "
        "it), where the node–face contact lets go",
        "the node–face contact",
    )


def likely_cause(model: Model) -> str:
    """The likely cause of a blow-up, from the time step against the critical one."""
    dt, critical, source = model.dt, model.critical_dt, model.critical_dt_source
    if dt > critical:
        return (
            f"time step too large: dt = {dt:.4g} s is {dt / critical:.3g} x the critical time step {critical:.4g} s "
            f"set by {source} (allowed by allow_unstable_dt); use dt <= {critical:.4g} s or dt = 'auto'"
        )
    within = f"{critical:.4g} s set by {source}" if math.isfinite(critical) else "(no estimate: nothing to bound it)"
    return (
        f"dt = {dt:.4g} s is within the critical time step {within}, so the state itself is extreme: initial "
        "overlaps, loads or velocities far beyond what the materials carry, or a contact stiffer than estimated; "
        "try a smaller run.safety_factor or dt"
    )


def _part_name(model: Model, part: int) -> str:
    """A sphere's part in words: its name, or its id where the model names no such part (spheres made by a conversion
    pass in a model built without spheres), so that describing a bad run never fails on the description."""
    names = model.part_names
    return names[part] if 0 <= part < len(names) else f"#{part}"
