"""Cohesive stage (host side): the weakening elements between the daughters of split nodes (LDEC eqs. 5–10, force
law and energy books in kernels/cohesive.py), their stored and dissipated energy, the removal of broken elements by
the compaction helper, and growth of their slots.

An element lives in the slots < ``State.cohesive_count``; ``cohesive_broken`` marks the ones that broke (d_max ≥ δ_c)
and wait for :func:`compact_cohesive` between steps. The energy they dissipated stays with their nodes
(``State.node_energy_cohesive``), so compaction loses nothing from the books.
"""

from __future__ import annotations

import dataclasses

import warp as wp

from ..kernels import cohesive as kc
from ..model import COHESIVE_FIELDS, Model, State
from .compaction import Compactor, grow_live_slots
from .integrate import pose_ahead


def eval_cohesive(
    model: Model, state: State, dt: float | None = None, track_energy: bool = True, substeps: int = 1
) -> None:
    """Add the forces of the intact cohesive elements to ``state.node_f`` and advance their history (launches only).

    Per element (one thread per slot of ``model.cohesive_capacity``): the central force of LDEC eqs. 5–8, +f on A
    towards B and −f on B; d_max (eq. 8) and ``node_damage`` (atomic max of δ_max/δ_c on A and B) updated; with
    ``track_energy`` the trapezoid work of the step less the change of the spring energy booked into
    ``node_energy_cohesive``, half on each node (kernels/cohesive.py: the books as velocity Verlet does the work, so
    ``node_qd`` must hold v_{n+1/2}, as it does during a step's force evaluation). An element whose d_max reaches δ_c
    breaks: no force, ``cohesive_broken`` = 1, what its spring held released into the books, the counters
    ``cohesive_broken_total`` / ``cohesive_area_broken`` / ``cohesive_work_broken`` (Γ A_f, eq. 9) advanced, damage 1
    on both nodes (the FEM contact lists are not rebuilt: their candidates do not depend on the elements).

    Args:
        model: the model (``node_ref_q``, ``cohesive_capacity``).
        state: the state; its ``node_f`` accumulates the forces [N].
        dt: time step [s] (None: ``model.dt``); 0 evaluates the forces only (the set-up and post-split evaluation):
            no history, no books, no break.
        track_energy: book the dissipated energy.
        substeps: n > 1: the elements' nodes are sub-stepped (warpdem.stages.substep): the forces go to
            ``state.node_f_fast`` instead of ``node_f``, and the opening threshold follows the sub-step dt/n
            (kernels/cohesive.py ``open_length``); ``dt`` is then the sub-step's.
    """
    if model.cohesive_capacity == 0:
        return
    m, s = model, state
    wp.launch(
        kc.eval_cohesive_kernel,
        dim=m.cohesive_capacity,
        inputs=[
            # Model:
            m.node_ref_q,
            m.node_inv_mass,
            m.dt / substeps,
            m.dt if dt is None else dt,
            # State in:
            s.cohesive_count,
            s.cohesive_a,
            s.cohesive_b,
            s.cohesive_fc,
            s.cohesive_delta_c,
            s.cohesive_alpha,
            s.cohesive_area,
            s.cohesive_dir,
            s.node_u,
            s.node_qd,
            pose_ahead(s),
            # In:
            int(track_energy),
        ],
        outputs=[
            s.cohesive_d_max,
            s.cohesive_f_prev,
            s.cohesive_energy_prev,
            s.cohesive_broken,
            s.cohesive_broken_total,
            s.cohesive_area_broken,
            s.cohesive_work_broken,
            s.node_f_fast if substeps > 1 else s.node_f,
            s.node_damage,
            s.node_energy_cohesive,
            s.node_energy_cohesive_trapezoid,
        ],
        device=m.device,
    )


def launch_cohesive_stored(model: Model, state: State, energy: wp.array) -> None:
    """Each intact live cohesive element's spring energy at its last evaluation [J] into ``energy`` (float64, shape
    (cohesive_capacity,); other slots left as they are: zero it first; launch only)."""
    if model.cohesive_capacity:
        s = state
        wp.launch(
            kc.cohesive_energy_kernel,
            dim=model.cohesive_capacity,
            inputs=[s.cohesive_count, s.cohesive_energy_prev, s.cohesive_broken],
            outputs=[energy],
            device=model.device,
        )


def cohesive_stored(model: Model, state: State) -> float:
    """The spring energy of the intact live cohesive elements on their unloading lines at their last evaluation [J]
    (``cohesive_energy_prev``: ½ k d², k = f(δ_max)/δ_max, once open; kernels/cohesive.py ``spring_energy``).
    Allocates and reads back: call between steps."""
    energy = wp.zeros(model.cohesive_capacity, dtype=wp.float64, device=model.device)
    launch_cohesive_stored(model, state, energy)
    return float(energy.numpy().sum())


def cohesive_energy(model: Model, state: State) -> tuple[float, float]:
    """The cohesive elements' energy [J]: (stored, spent).

    stored: :func:`cohesive_stored`; spent: the work done on the elements less what they hold, Σ
    ``node_energy_cohesive`` (the law's dissipation: ½ f_c δ_max per intact element, Γ A_f per broken one) +
    Σ ``node_energy_cohesive_trapezoid`` (Verlet's work off the law, 0 where the steps resolve δ_c) over the live nodes.
    Allocates and reads back: call between steps.
    """
    s = state
    nodes = int(s.node_count.numpy()[0])
    spent = float(s.node_energy_cohesive.numpy()[:nodes].sum() + s.node_energy_cohesive_trapezoid.numpy()[:nodes].sum())
    return cohesive_stored(model, state), spent


def compact_cohesive(model: Model, state: State, compactor: Compactor) -> int:
    """Remove the broken elements (a topology pass between steps): the survivors keep their order in the slots
    ``0 .. count - 1`` and the slots past them are zero. Returns the live element count (reads back).

    Args:
        model: the model.
        state: the state; every array of ``COHESIVE_FIELDS`` and ``cohesive_count`` are updated in place.
        compactor: a :class:`warpdem.stages.compaction.Compactor` of ``model.cohesive_capacity`` slots.

    Raises:
        ValueError: the compactor's capacity is not the model's cohesive capacity.
    """
    if compactor.capacity != model.cohesive_capacity:
        raise ValueError(
            f"compact_cohesive: the compactor has {compactor.capacity} slots, the model {model.cohesive_capacity} "
            "cohesive slots (make a new Compactor after growing them)"
        )
    if model.cohesive_capacity == 0:
        return 0
    fields = [getattr(state, name) for name in COHESIVE_FIELDS]
    compactor.remove(state.cohesive_count, state.cohesive_broken, fields)
    return int(state.cohesive_count.numpy()[0])


def regrow_cohesive(model: Model, state: State, capacity: int) -> tuple[Model, State]:
    """Copies of ``model`` and ``state`` with ``capacity`` cohesive element slots: the live elements (slots below
    ``cohesive_count``) copied in place, the other slots zero; every other array is shared. Reads the count back:
    call between steps.

    Raises:
        ValueError: ``capacity`` is below the live element count.
    """
    live = int(state.cohesive_count.numpy()[0])
    if capacity < live:
        raise ValueError(f"regrow_cohesive: capacity {capacity} is below the {live} live cohesive elements")
    fields = grow_live_slots(state, COHESIVE_FIELDS, live, capacity)
    return dataclasses.replace(model, cohesive_capacity=capacity), dataclasses.replace(state, **fields)
