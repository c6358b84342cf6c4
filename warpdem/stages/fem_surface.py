"""The FEM contact surface (host side): the boundary faces of the tet mesh, rebuilt on the device after every
topology pass (node splitting, conversion), with the node → tet stars, the tets' face neighbours, every surface
node's penalty stiffness and the faces' extent; and the map that carries each live face's id (and so every contact
history that names it) across a rebuild. The contact stage that uses them is :mod:`warpdem.stages.fem_contact`."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import warp as wp

from ..kernels import fem_contact as kf
from ..model import Model, State
from ..recorded import Recorded, arrays_key
from .compaction import Compactor
from .topology import NodeStars


def build_surface(model: Model, state: State) -> Model:
    """Rebuild the node → tet stars, the tet face neighbours, the boundary faces (a compaction of the tet-face slots
    to those with no neighbour), every node's penalty stiffness and the faces' extent, on the device. Between steps
    (reads back the face count and extent); the face arrays grow (×2) when the surface outgrows them.

    Returns:
        The model with the new topology arrays; ``state.face_count`` is set.
    """
    return rebuild_surface(model, state)[0]


class SurfaceScratch:
    """The scratch of :func:`rebuild_surface` for one model's node and tet capacities, kept by its caller so that a
    rebuild after every split or conversion pass allocates nothing (issue 24): the stars, the compactor of the
    tet-face slots, the boundary flags, the face count and the faces' extent. Each rebuild resets what it reads
    before writing, so a reused scratch gives what a fresh one gives, bit for bit."""

    def __init__(self, node_capacity: int, tet_capacity: int, device: wp.context.Device) -> None:
        self.key = (node_capacity, tet_capacity, str(device))
        slots = 4 * tet_capacity
        self.stars = NodeStars(node_capacity, tet_capacity, device)
        self.compactor = Compactor(slots, device)
        self.tet_face_count = wp.zeros(1, dtype=int, device=device)
        self.dead = wp.zeros(slots, dtype=int, device=device)
        self.extent = wp.zeros(2, dtype=float, device=device)

    def fits(self, model: Model) -> bool:
        """Whether this scratch serves ``model``'s capacities and device."""
        return self.key == (model.node_capacity, model.tet_capacity, str(model.device))

    def reset(self) -> None:
        """Back to a fresh scratch's values (memsets only): the star slots past their fill and the face neighbours
        past the live tets are copied into the model whole."""
        self.stars.tets.zero_()
        self.stars.tet_face_nbr.fill_(-1)
        self.tet_face_count.zero_()
        self.dead.zero_()
        self.extent.zero_()


def rebuild_surface(
    model: Model,
    state: State,
    scratch: SurfaceScratch | None = None,
    recordings: tuple[Recorded, Recorded] | None = None,
) -> tuple[Model, wp.array]:
    """:func:`build_surface`, writing into the model's existing topology arrays where they are large enough (so a
    captured graph that reads them stays valid), and also returning the new face of every tet-face slot (-1 for an
    interior slot), shape (4 tet_capacity,), int32: the map that carries face ids across the rebuild (a face keeps
    its tet-face slot through any split), valid until the next rebuild with the same ``scratch``.

    ``scratch``: the rebuild's working arrays (:class:`SurfaceScratch`), reused when it fits the model's capacities,
    else made here. A topology array the model does not have yet, or of another size, is a copy of the scratch's.
    ``recordings``: two recordings (warpdem.recorded) for its two runs of launches, the boundary faces flagged and
    counted, then (the face count read back: the face arrays grow when it passes their capacity) written with the
    nodes' stiffness and the faces' extent (read back: launches take it as a value); None: launched one by one.
    """
    m, s = model, state
    d = m.device
    ncap, tcap = m.node_capacity, m.tet_capacity
    if scratch is None or not scratch.fits(m):
        scratch = SurfaceScratch(ncap, tcap, d)
    first = (arrays_key(m, s), id(scratch))
    _run(recordings, 0, first, lambda: _flag_faces(m, s, scratch), [scratch])
    count = int(scratch.compactor.new_count.numpy()[0])
    cap = max(count, m.face_capacity)
    if m.face_nodes is not None and m.face_capacity >= count:
        faces = (m.face_nodes, m.face_tet, m.face_joint, m.face_depth)
    else:
        if m.face_nodes is not None:
            cap = max(count, 2 * m.face_capacity)  # a growing crack surface: amortised growth, as every capacity
        faces = tuple(wp.zeros(cap, dtype=t, device=d) for t in (wp.vec3i, int, int, float))
    stiffness = _sized(m.node_contact_stiffness, ncap, float, d)
    material = _sized(m.node_contact_material, ncap, int, d)
    # The stars and face neighbours go into the model's arrays where their shapes hold (copied with the writes);
    # else the model takes copies of the scratch's (which the next rebuild overwrites).
    stars = scratch.stars
    fresh = {"star_offset": stars.offset, "star_count": stars.count, "star_tets": stars.tets}
    fresh["tet_face_nbr"] = stars.tet_face_nbr
    topology = {}
    copies = []
    for name, new in fresh.items():
        old = getattr(m, name)
        if old is not None and old.shape == new.shape:
            copies.append((old, new))
            topology[name] = old
        else:
            topology[name] = None
    written = [*faces, stiffness, material, *(old for old, _ in copies)]
    second = (*first, cap, *(a.ptr for a in written))
    _run(
        recordings,
        1,
        second,
        lambda: _write_faces(m, s, scratch, faces, stiffness, material, cap, copies),
        [scratch, *written],
    )
    radius, depth_max = (float(v) for v in scratch.extent.numpy())
    for name, new in fresh.items():
        if topology[name] is None:
            topology[name] = wp.clone(new)
    face_nodes, face_tet, face_joint, face_depth = faces
    model = dataclasses.replace(
        m,
        face_capacity=cap,
        **topology,
        face_nodes=face_nodes,
        face_tet=face_tet,
        face_joint=face_joint,
        face_depth=face_depth,
        node_contact_stiffness=stiffness,
        node_contact_material=material,
        face_radius=radius,
        face_depth_max=depth_max,
    )
    return model, scratch.compactor.old_to_new


def _run(
    recordings: tuple[Recorded, Recorded] | None, k: int, key: tuple, body: Callable[[], None], retain: list
) -> None:
    """``body`` through recording ``k`` of ``recordings`` (warpdem.recorded), or launched (None)."""
    if recordings is None:
        body()
    else:
        recordings[k].run(key, body, retain=retain)


def _flag_faces(m: Model, s: State, scratch: SurfaceScratch) -> None:
    """The rebuild's first launches: the scratch reset, the stars and face neighbours, the boundary tet-face slots
    flagged and counted (``scratch.compactor.new_count``)."""
    d = m.device
    tcap = m.tet_capacity
    scratch.reset()
    scratch.stars.build(m.tet_nodes, s.tet_count, s.tet_active, s.node_count, ref_face_nbr=m.ref_tet_face_nbr)
    if tcap:
        wp.launch(kf.count_tet_faces_kernel, dim=1, inputs=[s.tet_count], outputs=[scratch.tet_face_count], device=d)
        wp.launch(
            kf.flag_boundary_faces_kernel,
            dim=4 * tcap,
            inputs=[s.tet_count, s.tet_active, scratch.stars.tet_face_nbr],
            outputs=[scratch.dead],
            device=d,
        )
    scratch.compactor.plan(scratch.tet_face_count, scratch.dead)


def _write_faces(
    m: Model,
    s: State,
    scratch: SurfaceScratch,
    faces: tuple[wp.array, wp.array, wp.array, wp.array],
    stiffness: wp.array,
    material: wp.array,
    cap: int,
    copies: list[tuple[wp.array, wp.array]],
) -> None:
    """The rebuild's second launches: the boundary faces scattered into ``faces`` (nodes, tet, joint, depth), the
    face count set, every node's penalty stiffness and contact material, the faces' extent (``scratch.extent``), and
    the ``copies`` (model array, scratch array) of the stars and face neighbours."""
    d = m.device
    ncap, tcap = m.node_capacity, m.tet_capacity
    stars = scratch.stars
    if tcap:
        wp.launch(
            kf.scatter_boundary_faces_kernel,
            dim=4 * tcap,
            inputs=[
                m.node_ref_q,
                m.tet_nodes,
                m.tet_volume,
                m.tet_face_joint,
                scratch.tet_face_count,
                scratch.compactor.old_to_new,
            ],
            outputs=list(faces),
            device=d,
        )
    wp.copy(s.face_count, scratch.compactor.new_count)
    stiffness.zero_()
    material.zero_()
    if ncap:
        wp.launch(
            kf.node_contact_stiffness_kernel,
            dim=ncap,
            inputs=[
                m.node_ref_q,
                m.tet_nodes,
                m.tet_volume,
                m.tet_material,
                m.tet_material_table,
                stars.tet_face_nbr,
                m.tet_face_joint,
                m.joint_material_table,
                m.contact_stiffness_factor,
                m.contact_face_normal_stiffness,
                *stars.csr(),
                s.node_count,
            ],
            outputs=[stiffness, material],
            device=d,
        )
    if cap:
        wp.launch(
            kf.face_extent_kernel,
            dim=cap,
            inputs=[m.node_ref_q, faces[0], faces[3], s.face_count],
            outputs=[scratch.extent],
            device=d,
        )
    for old, new in copies:
        wp.copy(old, new)


def _sized(a: wp.array | None, n: int, dtype: type, device: wp.context.Device) -> wp.array:
    """``a`` when it has n entries, else a new zero array of n (zeroed where it is written)."""
    if a is not None and a.shape[0] == n:
        return a
    return wp.zeros(n, dtype=dtype, device=device)


def remap_face_ids(
    model: Model, state: State, face_slot: wp.array, old_face_count: wp.array, slot_to_face: wp.array
) -> None:
    """Carry the face ids the FEM contact state holds (every spring slot's target ``node_face_spring``, the
    sphere–face candidate slots ``sphere_face_index``) across a surface rebuild: old face → its tet-face slot
    (``face_slot``, taken before the topology changed) → the new face of that slot (``slot_to_face`` from
    :func:`rebuild_surface`); ``old_face_count``: the face count before, shape (1,), on the device. Launches only."""
    for ids in (state.node_face_spring, state.sphere_face_index):
        if ids.shape[0]:
            wp.launch(
                kf.remap_face_ids_kernel,
                dim=ids.shape[0],
                inputs=[old_face_count, face_slot, slot_to_face],
                outputs=[ids],
                device=model.device,
            )


def face_slots(model: Model, state: State, out: wp.array | None = None) -> wp.array:
    """The tet-face slot 4t + k of every boundary face (-1 past the count), shape (face_capacity,), int32; call before
    a topology pass changes the tets (launches only)."""
    if out is None or out.shape[0] != max(model.face_capacity, 1):
        out = wp.full(max(model.face_capacity, 1), -1, dtype=int, device=model.device)
    if model.face_capacity:
        wp.launch(
            kf.tet_face_slots_kernel,
            dim=model.face_capacity,
            inputs=[model.tet_nodes, model.face_nodes, model.face_tet, state.face_count],
            outputs=[out],
            device=model.device,
        )
    return out


def smallest_face_depth(model: Model, state: State) -> float:
    """Smallest face_depth of the live boundary faces [m] (0 without faces)."""
    n = int(state.face_count.numpy()[0])
    return float(model.face_depth.numpy()[:n].min()) if n else 0.0
