"""Initial overlaps (host side): spheres that start deep in each other or in the rock, found before the first step.

Two spheres that start overlapping by δ store the elastic energy of a contact compressed by δ and fly apart on the
first step; a sphere that starts inside a tet block is not pushed out at all (the sphere–face contact acts within r of
the surface), so it passes straight through the rock. Both are set-up mistakes a scene should not hide, so the scene
builder measures them (:func:`initial_overlap`) and refuses a scene whose worst overlap exceeds
:data:`OVERLAP_TOLERANCE` unless its ``[run] allow_initial_overlap`` says so.

- Sphere pairs: candidates from the build-time hash-grid pair search of the bonds
  (:func:`warpdem.stages.bonds.find_bond_pairs`, O(N)), then δ = r_i + r_j − |x_i − x_j| in float64. A bonded lattice
  touches exactly (δ at round-off). A pair of which neither sphere is free (fixed or prescribed) is skipped: no
  contact force moves either.
- Spheres and rock: :func:`warpdem.kernels.overlap.sphere_rock_penetration_kernel` over a BVH of the tets' boxes:
  the depth r − (distance from the centre to the rock), and the tet that holds the centre, if any.

Positions go to the device relative to the middle of their bounding box, so float32 resolves them anywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from ..kernels import overlap as ko
from ..stages.bonds import find_bond_pairs

if TYPE_CHECKING:
    from ..model import Model, State

OVERLAP_TOLERANCE = 0.05
"""Largest initial overlap a scene may start with unless it allows more: of the smaller radius for a sphere pair, of
the sphere's radius for a sphere reaching into the rock [-]. A sphere whose centre lies in the rock always counts."""

ROUNDOFF = 1.0e-6
"""Relative overlaps up to this are touching, not overlapping: float64 lattices touch to ~1e-15, and the float32 pair
search (relative error ~1e-7 of the extent) must not decide what is reported [-]."""

_CANDIDATE_GAP = 1.0e-3
"""Gap tolerance of the float32 candidate search, relative to r_i + r_j: wide enough that no pair overlapping by more
than ROUNDOFF in float64 is lost to float32 rounding [-]."""


_FLOAT32_RESOLUTION = 1.0e-6
"""Distances computed in float32 relative to the middle of the model are good to a few 1e-8 of its extent; depths
into the rock below this fraction of the extent are touching [-]."""


def _point(x: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in x) + ") m"


@dataclass(frozen=True)
class InitialOverlap:
    """What overlaps at the start. Sphere ids are creation order (``Model.particle_id``); points in metres.

    Attributes:
        pairs: sphere pairs overlapping by more than ROUNDOFF of the smaller radius (at least one sphere free).
        worst_pair: ids (i, j) of the deepest pair, or None. worst_pair_overlap: its δ / min(r_i, r_j) [-].
        worst_pair_point: the middle of its overlap [m], shape (3,).
        inside: spheres whose centre lies in a tet. inside_sphere, inside_point, inside_tet: the first such sphere, its
            centre [m] and the tet (index in the builder's concatenated mesh), or None.
        penetrating: spheres whose centre is outside the rock but which reach into it by more than ROUNDOFF · r.
        worst_penetrating: id of the deepest of those, or None. worst_penetration: its depth / r [-].
        worst_penetrating_point: its centre [m], shape (3,).
    """

    pairs: int = 0
    worst_pair: tuple[int, int] | None = None
    worst_pair_overlap: float = 0.0
    worst_pair_point: np.ndarray | None = None
    inside: int = 0
    inside_sphere: int | None = None
    inside_point: np.ndarray | None = None
    inside_tet: int | None = None
    penetrating: int = 0
    worst_penetrating: int | None = None
    worst_penetration: float = 0.0
    worst_penetrating_point: np.ndarray | None = None

    @property
    def any(self) -> bool:
        """Whether anything overlaps beyond round-off."""
        return bool(self.pairs or self.inside or self.penetrating)

    def exceeds(self, tolerance: float = OVERLAP_TOLERANCE) -> bool:
        """Whether a scene must be refused: a pair or a rock penetration deeper than ``tolerance`` (relative), or a
        sphere centre in the rock."""
        return self.worst_pair_overlap > tolerance or self.worst_penetration > tolerance or self.inside > 0

    def format(self) -> str:
        """One line: counts, the worst overlap and where it is."""
        parts = []
        if self.pairs:
            i, j = self.worst_pair
            parts.append(
                f"{self.pairs} sphere pair(s) overlap, the worst by {100.0 * self.worst_pair_overlap:.3g} % of the "
                f"smaller radius (spheres {i} and {j}, at {_point(self.worst_pair_point)})"
            )
        if self.inside:
            parts.append(
                f"{self.inside} sphere(s) start with the centre inside the rock (sphere {self.inside_sphere} at "
                f"{_point(self.inside_point)}, in tet {self.inside_tet})"
            )
        if self.penetrating:
            worst = 100.0 * self.worst_penetration
            parts.append(
                f"{self.penetrating} sphere(s) reach into the rock, the worst by {worst:.3g} % of its radius (sphere "
                f"{self.worst_penetrating} at {_point(self.worst_penetrating_point)})"
            )
        return "; ".join(parts) if parts else "no sphere overlaps another or the rock"


def sphere_pair_overlaps(
    q: np.ndarray, radius: np.ndarray, device: wp.context.DeviceLike = None
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of spheres that overlap by more than ROUNDOFF of the smaller radius.

    Args:
        q: centres [m], shape (N, 3). radius: radii [m], shape (N,). device: Warp device of the pair search.

    Returns:
        Pairs (i < j), shape (M, 2), int64, and their overlaps δ = r_i + r_j − |x_i − x_j| [m], shape (M,), float64.
    """
    q = np.asarray(q, dtype=np.float64)
    radius = np.asarray(radius, dtype=np.float64)
    if len(q) < 2:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0)
    local = q - 0.5 * (q.min(axis=0) + q.max(axis=0))
    one_group = np.ones(len(q), dtype=np.int32)
    pairs = find_bond_pairs(local, radius, one_group, _CANDIDATE_GAP, wp.get_device(device)).astype(np.int64)
    i, j = pairs[:, 0], pairs[:, 1]
    delta = radius[i] + radius[j] - np.linalg.norm(q[i] - q[j], axis=1)
    deep = delta > ROUNDOFF * np.minimum(radius[i], radius[j])
    return pairs[deep], delta[deep]


def sphere_rock_penetration(
    q: np.ndarray, radius: np.ndarray, points: np.ndarray, tets: np.ndarray, device: wp.context.DeviceLike = None
) -> tuple[np.ndarray, np.ndarray]:
    """How far each sphere reaches into the rock, and the tet that holds its centre.

    Args:
        q: sphere centres [m], shape (N, 3). radius: [m], shape (N,).
        points: node positions [m], shape (P, 3). tets: node indices, shape (M, 4). device: Warp device.

    Returns:
        Depth r − (distance from the centre to the rock) [m], shape (N,) (≤ 0: clear of the rock; r when the centre
        is in it), and the index of a tet holding the centre, or -1, shape (N,).
    """
    n = len(q)
    if n == 0 or len(tets) == 0:
        return np.zeros(n), np.full(n, -1, dtype=np.int64)
    device = wp.get_device(device)
    q = np.asarray(q, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    everything = np.concatenate([q, points])
    origin = 0.5 * (everything.min(axis=0) + everything.max(axis=0))
    nodes32 = (points - origin).astype(np.float32)
    corners = nodes32[np.asarray(tets, dtype=np.int64)]  # (M, 4, 3): the boxes hold the float32 tets the kernel sees
    lowers = wp.array(corners.min(axis=1), dtype=wp.vec3, device=device)
    uppers = wp.array(corners.max(axis=1), dtype=wp.vec3, device=device)
    bvh = wp.Bvh(lowers, uppers)
    penetration = wp.zeros(n, dtype=float, device=device)
    containing = wp.zeros(n, dtype=int, device=device)
    wp.launch(
        ko.sphere_rock_penetration_kernel,
        dim=n,
        inputs=[
            # Model:
            wp.array(np.asarray(tets, dtype=np.int32), dtype=wp.vec4i, device=device),
            bvh.id,
            # In:
            wp.array(nodes32, dtype=wp.vec3, device=device),
            wp.array((q - origin).astype(np.float32), dtype=wp.vec3, device=device),
            wp.array(np.asarray(radius, dtype=np.float32), dtype=float, device=device),
        ],
        outputs=[penetration, containing],
        device=device,
    )
    return penetration.numpy().astype(np.float64), containing.numpy().astype(np.int64)


def initial_overlap(
    q: np.ndarray,
    radius: np.ndarray,
    free: np.ndarray,
    points: np.ndarray,
    tets: np.ndarray,
    device: wp.context.DeviceLike = None,
) -> InitialOverlap:
    """Measure the overlaps of an initial state (:class:`InitialOverlap`).

    Args:
        q: sphere centres [m], shape (N, 3), in id order. radius: [m], shape (N,). free: whether each sphere is free
            (not fixed or prescribed), shape (N,).
        points: tet mesh node positions [m], shape (P, 3). tets: node indices, shape (M, 4).
        device: Warp device of the searches.
    """
    q = np.asarray(q, dtype=np.float64).reshape(-1, 3)
    radius = np.asarray(radius, dtype=np.float64)
    free = np.asarray(free, dtype=bool)
    if len(q) == 0:
        return InitialOverlap()
    found: dict = {}
    pairs, delta = sphere_pair_overlaps(q, radius, device)
    moving = free[pairs[:, 0]] | free[pairs[:, 1]]
    pairs, delta = pairs[moving], delta[moving]
    if len(pairs):
        i, j = pairs[:, 0], pairs[:, 1]
        relative = delta / np.minimum(radius[i], radius[j])
        k = int(np.argmax(relative))
        a, b = int(i[k]), int(j[k])
        # The middle of the overlap lens, on the line of centres.
        direction = (q[b] - q[a]) / max(float(np.linalg.norm(q[b] - q[a])), 1e-300)
        middle = q[a] + direction * (radius[a] - 0.5 * delta[k])
        found |= {
            "pairs": len(pairs),
            "worst_pair": (a, b),
            "worst_pair_overlap": float(relative[k]),
            "worst_pair_point": middle,
        }
    depth, tet = sphere_rock_penetration(q, radius, points, tets, device)
    inside = np.nonzero(tet >= 0)[0]
    if len(inside):
        s = int(inside[0])
        found |= {"inside": len(inside), "inside_sphere": s, "inside_point": q[s], "inside_tet": int(tet[s])}
    relative_depth = np.where(tet < 0, depth / np.maximum(radius, 1e-300), 0.0)
    # The depth comes from float32 positions relative to the middle of the model: resolved to ~1e-7 of its extent.
    extent = float(np.ptp(np.concatenate([q, np.asarray(points, dtype=np.float64).reshape(-1, 3)]), axis=0).max())
    resolution = ROUNDOFF * radius + _FLOAT32_RESOLUTION * extent
    reaching = np.nonzero((tet < 0) & (depth > resolution))[0]
    if len(reaching):
        s = int(reaching[np.argmax(relative_depth[reaching])])
        found |= {
            "penetrating": len(reaching),
            "worst_penetrating": s,
            "worst_penetration": float(relative_depth[s]),
            "worst_penetrating_point": q[s],
        }
    return InitialOverlap(**found)


NODE_ROUNDOFF = 1.0e-3
"""Compressions up to this fraction of a face's reach (``Model.face_depth``, half the height of the tet over it) are
touching, not overlapping: the set-up evaluation carries a node's depth within float32 rounding of the model's extent
as its spring's offset, and this measure recomputes the depth in float64 from the same float32 positions [-]."""


@dataclass(frozen=True)
class NodeOverlap:
    """Mesh nodes whose node–face springs start compressed after the set-up evaluation: pressed into a face of another
    block beyond float32 rounding. Points in metres.

    Attributes:
        nodes: nodes with a spring compressed by more than NODE_ROUNDOFF of its face's reach.
        worst_node: the most compressed one (node index), or None. worst_share: its compression over the face's reach
            (half the height of the tet over the face) [-]. worst_depth: that compression [m].
        worst_point: its position [m], shape (3,). worst_face: the face it is pressed into.
    """

    nodes: int = 0
    worst_node: int | None = None
    worst_share: float = 0.0
    worst_depth: float = 0.0
    worst_point: np.ndarray | None = None
    worst_face: int | None = None

    def exceeds(self, tolerance: float = OVERLAP_TOLERANCE) -> bool:
        """Whether a scene must be refused: a node pressed deeper than ``tolerance`` of its face's reach."""
        return self.worst_share > tolerance

    def format(self) -> str:
        """One line: the count, the worst compression and where it is."""
        if not self.nodes:
            return "no mesh node starts pressed into another block"
        return (
            f"{self.nodes} mesh node(s) start pressed into a face of another block, the worst by "
            f"{self.worst_depth:.3g} m = {100.0 * self.worst_share:.3g} % of the face's reach (node "
            f"{self.worst_node} at {_point(self.worst_point)}, face {self.worst_face})"
        )


def initial_node_overlap(model: Model, state: State) -> NodeOverlap:
    """The node–face springs compressed at the start, from the State after the set-up force evaluation
    (warpdem.simulation.Simulation.evaluate_forces): each slot's depth behind its face's plane (float64, from the
    float32 positions) less the offset the evaluation carried, against the face's reach.

    Why it is checked: a mesh built from one geology puts no node inside another block, and a scene's bodies are
    meant to start apart or touching, so a compressed spring is a set-up mistake or a false contact of the set-up's
    target tests (kernels/node_face_target.py: a node at a T-junction of joints lies on one block's face and behind the
    rim of another's, which exits_over_convex_edge tells from a penetration; a case it missed would show here) that
    throws the blocks apart in the first steps."""
    k = model.node_springs
    nn = int(state.node_count.numpy()[0])
    if nn == 0 or model.face_capacity == 0:
        return NodeOverlap()
    spring = state.node_face_spring.numpy()[: nn * k]
    slots = np.nonzero(spring >= 0)[0]
    if len(slots) == 0:
        return NodeOverlap()
    faces = spring[slots]
    nodes = slots // k
    q = state.node_q.numpy()[:nn].astype(np.float64)
    corner = q[model.face_nodes.numpy()[faces]]
    normal = np.cross(corner[:, 1] - corner[:, 0], corner[:, 2] - corner[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    depth = -np.einsum("ij,ij->i", q[nodes] - corner[:, 0], normal)
    compression = np.maximum(depth - state.node_face_offset.numpy()[slots], 0.0)
    share = compression / model.face_depth.numpy()[faces]
    pressed = share > NODE_ROUNDOFF
    if not np.any(pressed):
        return NodeOverlap()
    w = int(np.argmax(share))
    return NodeOverlap(
        nodes=len(np.unique(nodes[pressed])),
        worst_node=int(nodes[w]),
        worst_share=float(share[w]),
        worst_depth=float(compression[w]),
        worst_point=q[nodes[w]],
        worst_face=int(faces[w]),
    )
