"""Nodal fracture (host side; LDEC §2.2–2.3, DESIGN.md stage 6): a node whose averaged stress reaches the tensile
strength splits into two daughters joined by a cohesive element (warpdem.stages.cohesive), in a between-steps pass on
the device (:class:`FracturePass`, run by ``Simulation.fracture_pass`` every ``model.fracture_interval`` steps).

Rules of the split pass (others rely on them):

- Nodal stress: the volume-weighted average of the ``tet_stress`` of the node's live, active tets (LDEC eq. 1),
  summed in ascending tet order; principal values and directions with ``wp.eig3``, tension positive; σ1 is the
  largest and p1 its direction, signed so that its largest component is positive (the same stress always gives the
  same p1).
- Candidates: σ1 ≥ T_f (the smallest of its tets' materials), ``node_may_split`` = 1, and its star has tets on
  both sides of the plane through the node normal to p1 with at least one face between the sides (so A_f > 0).
  Also a *freed hinge* in tension (0 < σ1 < T_f, ``node_may_split`` = 1): its neighbours' cracks already cut its
  star into ≥ 2 pieces (rule (1) of the partition), and every half-open face of its star is traction-free: of the
  two copies that each of the face's other nodes left across it, at least one holds no intact cohesive or joint
  element, so no element joins them. The crack around such a node has let go and the node alone pins two free
  faces together, a point strength the continuum has not (the tension around a point bridge between traction-free
  faces is unbounded); its σ1 is low only because its star's tets are unloaded by those faces (on the Brazilian disc
  most nodes left holding cut faces, median σ1 0.6 T_f). It splits along the cut with an element of its own (eq. 4's
  force, eq. 10's δ_c), so its share of the crack area still costs Γ A_f and nothing is released at the split. A
  node at a crack front or on a crack still bridged by intact elements does not qualify (the notched plate's crack
  does not run ahead, tests/test_fracture_scenes.py). Once an element has broken (``cohesive_broken_total`` > 0)
  every pass evaluates the nodal stresses; before that, a pass in which no tet's stress bound reaches the lowest
  T_f stops after one tet pass. Candidates are listed in node order (exclusive scan).
- Partition (``partition_star``), made when the candidate wins its round, with the topology of that round's start:
  the + tets take the new daughter B, A keeps K's index, and the crack opens along the star's faces between + and −
  tets. Plane rule: a tet is + when (centroid − x_K)·p1 > 0 (current positions), so the faces that open are those
  whose normals lie closest to p1. Each node would cut by its own plane, though, and on an unstructured mesh
  neighbouring nodes along one crack would then cut different faces: a face only comes apart when all three of its
  nodes split across it, and a face cut by one or two of them stays held by the rest (a hinge: on the Brazilian
  disc, after 140 splits only 28 crack faces were open, 335 hinged, and the disc never came apart). So the
  partition follows the cracks the neighbours have opened. A star face (holding K, between two star tets that were
  face neighbours in the unsplit mesh, ``ref_tet_face_nbr``) is *half-open* when the tet across no longer holds
  the face's other two nodes: a neighbour has split across it.
  (1) If the star's tets, joined only across faces that are not half-open, fall into ≥ 2 components, the
  neighbours' cracks already cut the star and K splits along them (the crack just completes, as the joint
  pre-split follows its components): each component goes to the side of its tets' mean centroid offset along p1,
  the highest +, the lowest −. (2) Otherwise the plane rule, except that a tet with half-open faces takes the side
  their outward normals n point away from (+ when Σ −area n·p1 > 0 over them): both tets of a half-open face lie on
  either side of it, so that face opens fully. Both rules give two sides with a face between them; where they would
  not (a star split only through non-face contacts), the plane rule, which the candidate test has checked.
- Races: rounds of independent sets. Each pending candidate claims its star tets: first an atomic max of σ1 per
  tet, then, among the candidates of that σ1, an atomic min of the node id; a candidate splits in this round only
  if it won every tet of its star (no tet then holds two splitting nodes, so each split node rewrites only its own
  star; the three nodes of a face never split in the same round, so each sees the cuts the others made before).
  Losers retry in the next round of the same pass with the stress of the pass's start (a split changes neither the
  tets' stresses nor positions) and a partition made with the topology of their round; after ``max_rounds`` rounds
  the rest wait for the next pass.
  The result does not depend on thread order: every claim is a max or min, and every sum runs in a fixed order.
- Daughters: B's slot by exclusive scan over the round's split nodes (``Compactor.plan_append``), so numbering is
  deterministic; every per-node array is replicated into it (positions, displacements, velocities, motion kinds,
  damage, the may-split flag, drivers); masses re-lumped per side from each side's own tets (m_A + m_B = m_K).
- Cohesive element: f_c = |(m_A F_B − m_B F_A)/(m_A + m_B)| (eq. 4), F_A, F_B the elastic forces of each side's
  tets on the node (no bulk viscosity, no contact or cohesive forces); A_f = 2 Σ area/3 over the star faces between
  − and + tets (reference areas, found through the unsplit face adjacency ``ref_tet_face_nbr``); δ_c = 2 Γ A_f /
  ((2 − α) f_c) (eq. 10) with Γ, α of the material of the element's representative face; ``cohesive_dir`` = the
  direction of eq. 4's force vector, which points from A's side to B's (its component along p1 is positive in a
  tensile split; p1 itself where it is not). Not p1 itself: the element's force before any opening is f_c along
  ``cohesive_dir``, so with eq. 4's own direction both daughters keep the parent's acceleration exactly (eq. 3),
  lateral force components included; with p1 they would slip sideways by round-off-sized amounts at once, and the
  central force would then turn with that slip (measured: a 1e-2 error in the energy books of a cracking bar, 1e-3
  with this rule). ``cohesive_tet_face`` = the largest of those faces, as the tet-face slot on A's side (the first
  of equals in star order).
- Hand-over: every cohesive and joint element has a representative tet on each side: A's is the tet of its face
  slot (``cohesive_tet_face``, ``joint_tet_face``), B's the tet across that slot in the unsplit mesh. A split moves
  neither, and each always holds its element's node, so when a node splits again each of its elements goes to the
  daughter whose side holds the representative tet. Joint elements are then re-sorted by their node pair
  (min, max), the order the contact stage searches them in; an element's A stays the node of its face slot's tet.
- Capacities: the candidate count bounds the pass's new nodes and elements, so the rounds run only where the node
  and cohesive capacities hold it (kernel pass_gate, on the device); where they do not, nothing has changed, and the
  host grows them ×2 until they do (warpdem.stages.topology.regrow_nodes, warpdem.stages.cohesive.regrow_cohesive) and
  runs the pass again, so a pass never overflows half way: a grown run equals a large-capacity one.
- On the device: a whole pass is one program (:meth:`FracturePass.find_and_split`: the bound, then the search and
  the rounds in conditional branches, the rounds a device loop), recorded and replayed (warpdem.recorded), with its
  counts in a status vector read back once.
- After a pass with splits (Simulation): boundary faces rebuilt on the device (crack faces become contact faces),
  the face ids held by the FEM contact state remapped through their tet-face slots, contact lists rebuilt, pressure
  faces and node drivers following the split, forces re-evaluated at the current positions with dt = 0.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import fracture as kfr
from ..limits import MAX_SUBSTEPS
from ..model import Model, State, fracture_state
from ..recorded import Recorded, arrays_key
from .compaction import Compactor
from .joints import load_face_arrays
from .tets import eval_tet_stresses
from .topology import NodeSplitter, live_flags, reference_face_neighbors, sort_joint_elements

MAX_ROUNDS = 8
"""Independent-set rounds per pass; candidates still waiting after them retry at the next pass."""


@dataclass
class FractureProps:
    """Fracture properties of one material (host side).

    Attributes:
        tensile_strength: T_f [Pa]; None: the material never splits.
        fracture_energy: Γ [J/m²] (both faces of a crack counted in A_f); required where tensile_strength is set.
        alpha: α of the weakening law (LDEC eq. 6), in ``[0, 1]`` [-].
    """

    tensile_strength: float | None
    fracture_energy: float | None
    alpha: float = 1.0

    def check(self, where: str) -> None:
        """Raise ValueError naming ``where`` when the values are not usable."""
        if self.tensile_strength is None:
            return
        if not (math.isfinite(self.tensile_strength) and self.tensile_strength > 0.0):
            raise ValueError(f"{where}: tensile_strength must be a finite number > 0 [Pa], got {self.tensile_strength}")
        if self.fracture_energy is None or not (math.isfinite(self.fracture_energy) and self.fracture_energy > 0.0):
            raise ValueError(
                f"{where}: fracture_energy must be a finite number > 0 [J/m²] where tensile_strength is set, got "
                f"{self.fracture_energy}"
            )
        if not 0.0 <= self.alpha <= 1.0:
            raise ValueError(f"{where}: alpha must lie in [0, 1], got {self.alpha}")


@dataclass
class PassStatus:
    """What a whole split pass found and did, as its status vector read it (kernels/fracture.py PASS_*).

    Attributes:
        reached: a tet reached the tension bound (else nothing more was evaluated).
        candidates: nodes that qualified.
        go: the rounds ran (candidates, and room for a daughter and a cohesive element each).
        before: node count before the pass (the daughters' first slot).
        after: node count after it.
        rounds: independent-set rounds run.
    """

    reached: int
    candidates: int
    go: int
    before: int
    after: int
    rounds: int


@dataclass
class SplitReport:
    """What one split pass did.

    Attributes:
        splits: nodes split in this pass.
        rounds: independent-set rounds it took.
        grew: a capacity grew (node or cohesive slots), so graphs were re-captured.
    """

    splits: int
    rounds: int
    grew: bool


def fracture_material_table(materials: Sequence[FractureProps], device: wp.context.Device) -> wp.array:
    """FractureMaterial of every material id (T_f = 3.4e38 for a material that never splits)."""
    table = []
    for p in materials:
        m = kfr.FractureMaterial()
        m.tensile_strength = float(kfr.NEVER)
        m.fracture_energy = 0.0
        m.alpha = float(p.alpha)
        if p.tensile_strength is not None:
            m.tensile_strength = float(p.tensile_strength)
            m.fracture_energy = float(p.fracture_energy)
        table.append(m)
    return wp.array(table, dtype=kfr.FractureMaterial, device=device)


def attach_fracture(
    model: Model,
    state: State,
    materials: Sequence[FractureProps],
    *,
    check_interval: int = 1,
    may_split: np.ndarray | None = None,
    cohesive_capacity: int | None = None,
    cohesive_substeps: int = 1,
) -> tuple[Model, State]:
    """Turn nodal fracture on for a built model (before its Simulation is made).

    Args:
        materials: fracture properties per material id, in order (one per material of the model).
        check_interval: steps between split passes (>= 1).
        may_split: bool per live node, True where a node may split; None: every node.
        cohesive_capacity: initial cohesive element slots (grown ×2 on demand); None: max(64, node_count // 8).
        cohesive_substeps: sub-steps of the cohesive elements' nodes per step (>= 1; warpdem.stages.substep): 1
            steps them with every other force; n > 1 resolves an opening crossed within a step (n ≥ √β, β the share
            of δ_c an element's peak force opens in one step).

    Returns:
        The model (``fracture_interval``, ``cohesive_capacity``, ``node_may_split``, ``fracture_material_table``,
        ``ref_tet_face_nbr`` set) and the state with empty cohesive elements.

    Raises:
        ValueError: a bad argument (the message says which and what is allowed).
    """
    if len(materials) != model.num_materials:
        raise ValueError(
            f"attach_fracture: need one FractureProps per material ({model.num_materials}), got {len(materials)}"
        )
    for i, p in enumerate(materials):
        name = model.material_names[i] if i < len(model.material_names) else str(i)
        p.check(f"attach_fracture: material {name!r}")
    if isinstance(check_interval, bool) or not isinstance(check_interval, (int, np.integer)) or check_interval < 1:
        raise ValueError(f"attach_fracture: check_interval must be an integer >= 1, got {check_interval!r}")
    if model.tet_capacity == 0:
        raise ValueError("attach_fracture: the model has no tets to split")
    if (
        isinstance(cohesive_substeps, bool)
        or not isinstance(cohesive_substeps, (int, np.integer))
        or not 1 <= cohesive_substeps <= MAX_SUBSTEPS
    ):
        raise ValueError(
            f"attach_fracture: cohesive_substeps must be an integer from 1 to {MAX_SUBSTEPS}, got {cohesive_substeps!r}"
        )

    nn = int(state.node_count.numpy()[0])
    flags = live_flags(may_split, nn, model.node_capacity, "attach_fracture", "may_split", "node")
    if cohesive_capacity is None:
        cohesive_capacity = max(64, nn // 8)
    if (
        isinstance(cohesive_capacity, bool)
        or not isinstance(cohesive_capacity, (int, np.integer))
        or cohesive_capacity < 1
    ):
        raise ValueError(f"attach_fracture: cohesive_capacity must be an integer >= 1, got {cohesive_capacity!r}")
    d = model.device
    model = dataclasses.replace(
        model,
        fracture_interval=int(check_interval),
        cohesive_capacity=int(cohesive_capacity),
        cohesive_substeps=int(cohesive_substeps),
        node_may_split=wp.array(flags, dtype=int, device=d),
        fracture_material_table=fracture_material_table(materials, d),
        ref_tet_face_nbr=reference_face_neighbors(model, state),
    )
    return model, dataclasses.replace(state, **fracture_state(model))


class FracturePass:
    """The scratch buffers and launches of a split pass for one set of capacities (module docstring).

    Args:
        model: the model (its node and tet capacities size the buffers).
        use_graph: record a whole pass into a graph and replay it (:meth:`find_and_split`); False: launch it launch
            by launch.
    """

    def __init__(self, model: Model, use_graph: bool = True) -> None:
        d = model.device
        ncap, tcap = model.node_capacity, model.tet_capacity
        self.device = d
        self.node_capacity = ncap
        self.tet_capacity = tcap
        self.splitter = NodeSplitter(ncap, tcap, d)
        self.select = Compactor(ncap, d)
        n1, t1 = max(ncap, 1), max(tcap, 1)
        self.sigma1 = wp.zeros(n1, dtype=float, device=d)
        self.p1 = wp.zeros(n1, dtype=wp.vec3, device=d)
        self.candidate = wp.zeros(n1, dtype=int, device=d)
        self.candidates = wp.zeros(n1, dtype=int, device=d)
        self.pending = wp.zeros(n1, dtype=int, device=d)
        self.won = wp.zeros(n1, dtype=int, device=d)
        self.won_offset = wp.zeros(n1, dtype=int, device=d)
        self.won_area = wp.zeros(n1, dtype=float, device=d)
        self.claim_sigma = wp.zeros(t1, dtype=float, device=d)
        self.claim_node = wp.zeros(t1, dtype=int, device=d)
        self.pending_count = wp.zeros(1, dtype=int, device=d)
        self.reached = wp.zeros(1, dtype=int, device=d)
        self.bonded = wp.zeros(n1, dtype=int, device=d)
        # The conditions of the pass's branches and round loop, and its status vector (kernels/fracture.py PASS_*).
        self.go = wp.zeros(1, dtype=int, device=d)
        self.more = wp.zeros(1, dtype=int, device=d)
        self.pass_status = wp.zeros(kfr.PASS_SLOTS, dtype=int, device=d)
        # The first daughter's slot of the last pass, on the device (a view into the status).
        self.first_new_slot = self.pass_status[kfr.PASS_BEFORE : kfr.PASS_BEFORE + 1]
        # The whole pass (find_and_split), recorded and replayed.
        self.whole = Recorded(d, use_graph)
        # The partition finds the faces neighbours have opened through the tets across them, joint faces included.
        self.no_joints = wp.zeros(0, dtype=int, device=d)
        table = model.fracture_material_table
        # The lowest T_f of any material (host copy, read once per capacity): the threshold of the tension bound.
        self.lowest_strength = float(table.numpy()["tensile_strength"].min()) if table is not None else 0.0

    def fits(self, model: Model) -> bool:
        """Whether the buffers match the model's capacities."""
        return self.node_capacity == model.node_capacity and self.tet_capacity == model.tet_capacity

    def find_and_split(
        self,
        model: Model,
        state: State,
        before_split: Callable[[], None],
        stresses_current: bool = False,
        max_rounds: int = MAX_ROUNDS,
        key: tuple = (),
        retain: Sequence[object] = (),
    ) -> PassStatus:
        """A whole split pass as one device program, read back once: the tension bound; where a tet reached it, the
        candidate search; where there are candidates and room for a daughter and an element each (the node and
        cohesive capacities), ``before_split`` (the caller's launches: marks of the books, the faces' slots) and the
        rounds. Its branches are conditional graph nodes (``wp.capture_if``) and its rounds a device loop
        (``wp.capture_while``), so the pass is recorded (warpdem.recorded) the second time it runs with the same arrays
        and ``key`` (what ``before_split`` reads besides the model and state) and replayed after: one replay and one
        read-back of :attr:`pass_status`, whatever it found. ``retain``: what ``before_split``'s launches read that the
        key does not keep alive. Where candidates found no room, nothing changed: grow and run the pass again.
        ``stresses_current``: as :meth:`find_candidates`. The daughters take the node slots from ``before`` on."""
        m, s = model, state
        if m.node_capacity == 0 or m.tet_capacity == 0:
            return PassStatus(0, 0, 0, 0, 0, 0)
        driver = getattr(m.loads, "node_driver", None)
        table = self.splitter.sides_table(m, s, [driver] if isinstance(driver, wp.array) else [])
        self.whole.run(
            (arrays_key(m, m.loads, s), stresses_current, max_rounds, *key),
            lambda: self._whole_pass(m, s, before_split, stresses_current, max_rounds),
            retain=[table, *retain],
        )
        status = PassStatus(*(int(x) for x in self.pass_status.numpy()))
        self.first_new_node = status.before
        if status.after > status.before and m.joint_capacity:
            sort_joint_elements(m, s)
        return status

    def _whole_pass(
        self, model: Model, state: State, before_split: Callable[[], None], stresses_current: bool, max_rounds: int
    ) -> None:
        """:meth:`find_and_split`'s launches (its branches read their conditions back when not recorded)."""
        m, s, d = model, state, self.device
        self.pass_status.zero_()
        self.go.zero_()
        wp.launch(
            kfr.begin_rounds_kernel, dim=1, inputs=[s.node_count], outputs=[self.pass_status, self.more], device=d
        )
        self._tension_bound(m, s, stresses_current)
        wp.capture_if(self.reached, lambda: self._search_and_gate(m, s, before_split, max_rounds))
        wp.launch(kfr.finish_pass_kernel, dim=1, inputs=[self.reached, self.go], outputs=[self.pass_status], device=d)

    def _search_and_gate(self, model: Model, state: State, before_split: Callable[[], None], max_rounds: int) -> None:
        """The candidate search, then the rounds where there is room for them (launches only)."""
        m, s, d = model, state, self.device
        self._search(m, s)
        wp.launch(
            kfr.pass_gate_kernel,
            dim=1,
            inputs=[
                s.node_count,
                s.cohesive_count,
                self.candidate_count,
                m.node_capacity,
                m.cohesive_capacity,
            ],
            outputs=[self.pass_status, self.go],
            device=d,
        )

        def rounds() -> None:
            before_split()
            # The loop's condition and the node count before were set as the pass began (begin_rounds_kernel).
            wp.capture_while(self.more, lambda: self._round(m, s, max_rounds))

        wp.capture_if(self.go, rounds)

    def _tension_bound(self, model: Model, state: State, stresses_current: bool) -> None:
        """The tet stresses (unless current) and the tension bound into :attr:`reached` (launches only): 1 where a tet's
        stress bound reaches the lowest T_f or an element has broken (a freed hinge may split below T_f)."""
        m, s = model, state
        if not stresses_current:
            eval_tet_stresses(m, s)
        self.reached.zero_()
        wp.launch(
            kfr.tension_bound_kernel,
            dim=m.tet_capacity,
            inputs=[s.tet_count, s.tet_active, s.tet_stress, s.cohesive_broken_total, self.lowest_strength],
            outputs=[self.reached],
            device=self.device,
        )

    @property
    def candidate_count(self) -> wp.array:
        """Candidates of the pass, shape (1,), int32 (after :meth:`find_candidates`)."""
        return self.select.new_count

    def find_candidates(self, model: Model, state: State, stresses_current: bool = False) -> int:
        """The first half of :meth:`find_and_split` on its own, launch by launch (for a caller that inspects the
        candidates before :meth:`split`): refresh the tet stresses (unless ``stresses_current``: the caller has just
        evaluated them at the current positions), build the stars, evaluate the nodal stress and list the candidates
        in node order. Reads back the candidate count."""
        m, s = model, state
        if m.node_capacity == 0 or m.tet_capacity == 0:
            return 0
        # The common case, no tet near its strength and no crack let go, costs one tet pass and one read-back.
        self._tension_bound(m, s, stresses_current)
        if int(self.reached.numpy()[0]) == 0:
            return 0
        self._search(m, s)
        return int(self.select.new_count.numpy()[0])

    def _search(self, model: Model, state: State) -> None:
        """Stars, intact elements per node, nodal stresses, the candidates listed in node order (launches only)."""
        m, s, d = model, state, self.device
        stars = self.splitter.stars
        # The pass reads the unsplit adjacency (ref_tet_face_nbr), not the current face neighbours.
        stars.build(m.tet_nodes, s.tet_count, s.tet_active, s.node_count, face_neighbors=False)
        self.count_bonds(model, state)
        wp.launch(
            kfr.nodal_stress_kernel,
            dim=m.node_capacity,
            inputs=[
                m.node_ref_q,
                m.tet_nodes,
                m.tet_volume,
                m.tet_material,
                m.fracture_material_table,
                m.node_may_split,
                m.ref_tet_face_nbr,
                s.node_count,
                s.node_q,
                s.tet_stress,
                *stars.csr(),
                self.no_joints,
                self.bonded,
            ],
            outputs=[self.sigma1, self.p1, self.candidate, self.splitter.star_comp],
            device=d,
        )
        # Candidates in node order: Compactor.plan keeps the flagged slots (dead = not a candidate).
        self.select.plan(s.node_count, self.candidate_dead())
        self.pending.zero_()
        wp.launch(
            kfr.gather_candidates_kernel,
            dim=m.node_capacity,
            inputs=[s.node_count, self.candidate, self.select.old_to_new],
            outputs=[self.candidates, self.pending],
            device=d,
        )

    def count_bonds(self, model: Model, state: State) -> None:
        """``bonded``: the intact cohesive and joint elements at each node (the freed-hinge test, "Candidates")."""
        m, s, d = model, state, self.device
        self.bonded.zero_()
        if m.cohesive_capacity:
            wp.launch(
                kfr.count_bonds_kernel,
                dim=m.cohesive_capacity,
                inputs=[s.cohesive_count, s.cohesive_a, s.cohesive_b, s.cohesive_broken],
                outputs=[self.bonded],
                device=d,
            )
        if m.joint_capacity:
            wp.launch(
                kfr.count_bonds_kernel,
                dim=m.joint_capacity,
                inputs=[s.joint_count, m.joint_a, m.joint_b, s.joint_broken],
                outputs=[self.bonded],
                device=d,
            )

    def candidate_dead(self) -> wp.array:
        """1 - candidate (the Compactor's removal flag), in the ``won`` buffer (free until the rounds)."""
        wp.launch(
            kfr.not_candidate_kernel,
            dim=self.candidate.shape[0],
            inputs=[self.candidate],
            outputs=[self.won],
            device=self.device,
        )
        return self.won

    def split(self, model: Model, state: State, max_rounds: int = MAX_ROUNDS) -> tuple[int, int]:
        """The second half of :meth:`find_and_split` on its own, launch by launch (after :meth:`find_candidates`):
        split the candidates in rounds of independent sets (module docstring). The capacities must hold
        ``node_count + candidates`` nodes and ``cohesive_count + candidates`` elements. The daughters take the node
        slots from ``first_new_node`` (set here) on. Reads back the loop's condition each round and the status once.

        Returns:
            (nodes split, rounds run).
        """
        m, s, d = model, state, self.device
        wp.launch(
            kfr.begin_rounds_kernel, dim=1, inputs=[s.node_count], outputs=[self.pass_status, self.more], device=d
        )
        wp.capture_while(self.more, lambda: self._round(m, s, max_rounds))
        status = self.pass_status.numpy()
        before, after, rounds = (int(status[k]) for k in (kfr.PASS_BEFORE, kfr.PASS_AFTER, kfr.PASS_ROUNDS))
        self.first_new_node = before
        splits = after - before
        if splits and m.joint_capacity:
            sort_joint_elements(m, s)
        return splits, rounds

    def _round(self, model: Model, state: State, max_rounds: int) -> None:
        """One round of independent sets: claims, partitions, the elements handed over and born, the daughters
        replicated; its last launch counts it in :attr:`pass_status` and sets :attr:`more` (launches only)."""
        m, s, d = model, state, self.device
        sp = self.splitter
        first_new = sp.compactor.first_new
        ncap = m.node_capacity
        driver = getattr(m.loads, "node_driver", None)
        extra_nodes = [driver] if isinstance(driver, wp.array) else []
        self.claim_sigma.fill_(-float(kfr.NEVER))
        self.claim_node.fill_(int(kfr.NO_NODE))
        sp.copies.zero_()
        sp.star_comp.zero_()
        self.pending_count.zero_()
        claim_in = [self.candidate_count, self.candidates, self.pending, self.sigma1, *sp.stars.csr()]
        wp.launch(kfr.claim_sigma_kernel, dim=ncap, inputs=claim_in, outputs=[self.claim_sigma], device=d)
        wp.launch(
            kfr.claim_node_kernel,
            dim=ncap,
            inputs=[*claim_in, self.claim_sigma],
            outputs=[self.claim_node],
            device=d,
        )
        wp.launch(
            kfr.resolve_claims_kernel,
            dim=ncap,
            inputs=[
                m.tet_nodes,
                m.ref_tet_face_nbr,
                s.node_q,
                self.candidate_count,
                self.candidates,
                self.p1,
                *sp.stars.csr(),
                self.claim_node,
                self.no_joints,
            ],
            outputs=[self.pending, self.won, sp.copies, sp.star_comp, self.pending_count],
            device=d,
        )
        wp.utils.array_scan(self.won, self.won_offset, inclusive=False)
        sp.plan_sides(s.node_count)
        # Elements first (they read the split nodes' stars and sides, not the tets), then the new elements.
        sp.hand_over(m.ref_tet_face_nbr, s.cohesive_count, s.cohesive_tet_face, s.cohesive_a, s.cohesive_b)
        if m.joint_capacity:
            sp.hand_over(m.ref_tet_face_nbr, s.joint_count, m.joint_tet_face, m.joint_a, m.joint_b)
        wp.launch(
            kfr.birth_cohesive_kernel,
            dim=ncap,
            inputs=[
                m.node_ref_q,
                m.tet_nodes,
                m.tet_inv_ref,
                m.tet_volume,
                m.tet_material,
                m.tet_material_table,
                m.fracture_material_table,
                m.ref_tet_face_nbr,
                s.node_u,
                self.candidate_count,
                self.candidates,
                self.won,
                self.won_offset,
                self.p1,
                *sp.stars.csr(),
                sp.star_comp,
                first_new,
            ],
            outputs=[
                s.cohesive_count,
                s.cohesive_a,
                s.cohesive_b,
                s.cohesive_fc,
                s.cohesive_delta_c,
                s.cohesive_alpha,
                s.cohesive_area,
                s.cohesive_dir,
                s.cohesive_d_max,
                s.cohesive_f_prev,
                s.cohesive_energy_prev,
                s.cohesive_broken,
                s.cohesive_tet_face,
                self.won_area,
            ],
            device=d,
        )
        wp.launch(
            kfr.book_splits_kernel,
            dim=1,
            inputs=[self.candidate_count, self.won, self.won_area],
            outputs=[s.cohesive_count, s.node_splits_total, s.crack_area_total],
            device=d,
        )
        for faces in load_face_arrays(m.loads):
            sp.remap_face_list_sides(m.tet_nodes, faces)
        sp.apply_sides(m, s, extra_nodes)
        wp.launch(
            kfr.end_round_kernel,
            dim=1,
            inputs=[s.node_count, self.pending_count, max_rounds],
            outputs=[self.pass_status, self.more],
            device=d,
        )
