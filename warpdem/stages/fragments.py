"""Fragments: the connected pieces of the material, their masses and speeds, and their per-frame HDF5 record.

A fragment is a connected component of the graph whose vertices are the FEM nodes that still carry mass and the
free spheres, and whose edges are what the material still holds together: an active tet joins its four nodes (so
tets connect through shared, unsplit nodes), an intact cohesive element joins its daughters A and B, an intact joint
element its two nodes, an intact bond its two spheres, and a penalty coupling (overlap zone) its sphere to the nodes
of its still-active tet. Nodes without mass (every tet around them converted) and spheres the scene holds (fixed or
prescribed motion: boundaries, not material) belong to no fragment (label -1).

:func:`label_fragments` labels on the device (kernels/fragments.py: union–find with compare-and-swap hooking and path
halving; the root of a component is its smallest item, whatever the thread order) and numbers the fragments by an
exclusive scan over the roots, so fragment ids follow their smallest items — nodes first, then spheres — and are the
same on every device and capacity. Masses and centre-of-mass velocities are summed on the host in one vectorised pass
(``np.bincount`` in float64, in item order: the same numbers bit for bit on every device, which float atomics on a GPU
would not give).

Output (warpdem.runner, at every output frame of a scene that can break apart: :func:`can_fragment`):
``<directory>/<name>_fragments.h5`` (:class:`FragmentFile`) holds one group per frame, ``frame_<frame:06d>``, with
attributes ``frame``, ``time`` [s], ``count``, ``largest`` [kg], ``total_mass`` [kg] and datasets ``masses`` [kg]
(descending) and ``speeds`` [m/s] (the speed of each fragment's centre of mass, in the order of ``masses``).
"""

from __future__ import annotations

import os
import pathlib
import shutil
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from ..kernels import fragments as kf

if TYPE_CHECKING:
    from ..model import Model, State

__all__ = [
    "FragmentFile",
    "FragmentSeries",
    "FragmentStats",
    "block_labels",
    "can_fragment",
    "fragment_colors",
    "label_fragments",
    "read_fragments",
    "tets_per_fragment",
]


@dataclass
class FragmentStats:
    """The fragments of a state.

    Attributes:
        count: number of fragments.
        masses: fragment masses [kg], sorted descending, shape (count,), float64.
        largest: mass of the largest fragment [kg] (0 without fragments).
        speeds: speed of each fragment's centre of mass |Σ m v / Σ m| [m/s], in the order of ``masses``, shape
            (count,), float64.
        node_label: fragment id of each live node (ids 0..count-1 in the order of their smallest items, nodes before
            spheres), -1 for a node without mass, shape (node_count,), int32.
        particle_label: fragment id of each live sphere, -1 for a held one, shape (particle_count,), int32.
        fragment_mass: mass of fragment k [kg], indexed by fragment id, shape (count,), float64.
        fragment_velocity: centre-of-mass velocity of fragment k [m/s], indexed by fragment id, shape (count, 3).
    """

    count: int
    masses: np.ndarray
    largest: float
    speeds: np.ndarray
    node_label: np.ndarray
    particle_label: np.ndarray
    fragment_mass: np.ndarray = field(default_factory=lambda: np.zeros(0))
    fragment_velocity: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def total_mass(self) -> float:
        """Mass of all fragments together [kg]."""
        return float(self.masses.sum())

    @property
    def ejecta_speeds(self) -> np.ndarray:
        """Speeds of the fragments other than the largest [m/s] (the pieces thrown off the main body), shape
        (count - 1,) or (0,)."""
        return self.speeds[1:]


def can_fragment(model: Model) -> bool:
    """Whether a model can break apart at all: nodal fracture or conversion on, bonds or joint elements present.
    Fragment output is written only for such scenes (elsewhere it would count the same pieces every frame)."""
    return bool(model.has_fracture or model.conversion_interval > 0 or model.bond_capacity > 0 or model.joint_capacity)


def label_fragments(model: Model, state: State) -> FragmentStats:
    """Label the fragments of a state on its device and measure them (reads back; call between steps).

    Args:
        model: the model (tets, joints, sphere masses and motions, node masses).
        state: the state (live counts, active tets, cohesive elements, bonds, couplings, velocities).

    Returns:
        The fragments (:class:`FragmentStats`).
    """
    device = model.device
    ncap, pcap = model.node_capacity, model.particle_capacity
    nn = int(state.node_count.numpy()[0]) if ncap else 0
    n = int(state.particle_count.numpy()[0]) if pcap else 0
    items = ncap + pcap
    if items == 0:
        return _stats(
            np.zeros(0, np.int32),
            np.zeros(0, np.int32),
            0,
            np.zeros(0),
            np.zeros((0, 3)),
            np.zeros(0),
            np.zeros((0, 3)),
        )
    is_item, parent = _init_items(model, state)
    if model.tet_capacity:
        wp.launch(
            kf.unite_tets_kernel,
            dim=model.tet_capacity,
            inputs=[model.tet_nodes, state.tet_count, state.tet_active, is_item],
            outputs=[parent],
            device=device,
        )
    links = []
    if model.cohesive_capacity:
        links.append((state.cohesive_count, state.cohesive_a, state.cohesive_b, state.cohesive_broken, 0))
    if model.joint_capacity:
        links.append((state.joint_count, model.joint_a, model.joint_b, state.joint_broken, 0))
    if model.bond_capacity:
        links.append((state.bond_count, state.bond_i, state.bond_j, state.bond_broken, ncap))
    for count, a, b, broken, offset in links:
        wp.launch(
            kf.unite_pairs_kernel,
            dim=len(a),
            inputs=[count, a, b, broken, offset, is_item],
            outputs=[parent],
            device=device,
        )
    if model.coupling_capacity and len(state.coupling_particle):
        wp.launch(
            kf.unite_couplings_kernel,
            dim=len(state.coupling_particle),
            inputs=[
                model.tet_nodes,
                state.tet_active,
                state.coupling_count,
                state.coupling_particle,
                state.coupling_tet,
                ncap,
                is_item,
            ],
            outputs=[parent],
            device=device,
        )
    labels, count = _root_labels(is_item, parent)
    node_label, particle_label = labels[:nn], labels[ncap : ncap + n]
    return _stats(
        node_label,
        particle_label,
        count,
        model.node_mass.numpy()[:nn],
        state.node_qd.numpy()[:nn],
        model.particle_mass.numpy()[:n],
        state.particle_qd.numpy()[:n],
    )


def _init_items(model: Model, state: State) -> tuple[wp.array, wp.array]:
    """The union–find items (FEM nodes with mass, then free spheres), each its own parent: ``is_item`` and ``parent``,
    shape (node_capacity + particle_capacity,)."""
    items = model.node_capacity + model.particle_capacity
    is_item = wp.empty(items, dtype=int, device=model.device)
    parent = wp.empty(items, dtype=int, device=model.device)
    wp.launch(
        kf.init_items_kernel,
        dim=items,
        inputs=[model.node_mass, model.particle_motion, state.node_count, state.particle_count],
        outputs=[is_item, parent],
        device=model.device,
    )
    return is_item, parent


def _root_labels(is_item: wp.array, parent: wp.array) -> tuple[np.ndarray, int]:
    """Component ids of the items after the unions, numbered by their smallest items (an exclusive scan over the
    roots), -1 for what is no item; and the number of components (reads back)."""
    device, items = parent.device, parent.shape[0]
    is_root = wp.empty(items, dtype=int, device=device)
    wp.launch(kf.flag_roots_kernel, dim=items, inputs=[is_item], outputs=[parent, is_root], device=device)
    offset = wp.empty(items, dtype=int, device=device)
    wp.utils.array_scan(is_root, offset, inclusive=False)
    label = wp.empty(items, dtype=int, device=device)
    fragment_count = wp.zeros(1, dtype=int, device=device)
    wp.launch(
        kf.fragment_labels_kernel,
        dim=items,
        inputs=[is_item, parent, is_root, offset],
        outputs=[label, fragment_count],
        device=device,
    )
    return label.numpy(), int(fragment_count.numpy()[0])


def block_labels(model: Model, state: State) -> tuple[np.ndarray, int]:
    """The blocks of rigid mode (warpdem.stages.rigid): connected sets of the deformable tets that may turn rigid
    (``Model.tet_may_rigid``, every tet when None), connected through shared nodes only — joint, cohesive and
    coupling elements do not glue them (they act between the blocks). Labelled on the device as the fragments are.

    Returns:
        The block id of each live node (0..count-1 in the order of their smallest nodes; -1 for a node of no such
        tet), shape (node_count,), int32; and the number of blocks.
    """
    nn = int(state.node_count.numpy()[0])
    nt = int(state.tet_count.numpy()[0])
    if nn == 0 or nt == 0:
        return np.full(nn, -1, dtype=np.int32), 0
    mask = model.tet_may_rigid
    if mask is None:
        mask = wp.full(model.tet_capacity, 1, dtype=int, device=model.device)
    is_item, parent = _init_items(model, state)
    wp.launch(
        kf.unite_masked_tets_kernel,
        dim=model.tet_capacity,
        inputs=[model.tet_nodes, mask, state.tet_count, state.tet_active, is_item],
        outputs=[parent],
        device=model.device,
    )
    labels, _ = _root_labels(is_item, parent)
    tets = model.tet_nodes.numpy()[:nt]
    used = (state.tet_active.numpy()[:nt] == 1) & (mask.numpy()[:nt] != 0)
    touched = np.zeros(nn, dtype=bool)
    touched[tets[used].ravel()] = True
    touched &= labels[:nn] >= 0
    label = np.full(nn, -1, dtype=np.int32)
    roots, inverse = np.unique(labels[:nn][touched], return_inverse=True)
    label[touched] = inverse.astype(np.int32)
    return label, len(roots)


def _stats(
    node_label: np.ndarray,
    particle_label: np.ndarray,
    count: int,
    node_mass: np.ndarray,
    node_v: np.ndarray,
    particle_mass: np.ndarray,
    particle_v: np.ndarray,
) -> FragmentStats:
    """Masses and centre-of-mass velocities of ``count`` labelled fragments (one host pass, float64, item order)."""
    label = np.concatenate([node_label, particle_label]).astype(np.int64)
    mass = np.concatenate([node_mass, particle_mass]).astype(np.float64)
    v = np.concatenate([np.reshape(node_v, (-1, 3)), np.reshape(particle_v, (-1, 3))]).astype(np.float64)
    live = label >= 0
    label, mass, v = label[live], mass[live], v[live]
    fragment_mass = np.bincount(label, weights=mass, minlength=count)
    momentum = np.stack([np.bincount(label, weights=mass * v[:, k], minlength=count) for k in range(3)], axis=1)
    velocity = momentum / np.where(fragment_mass > 0.0, fragment_mass, 1.0)[:, None]
    speed = np.linalg.norm(velocity, axis=1)
    order = np.argsort(-fragment_mass, kind="stable")  # ties keep the id order, so the listing is deterministic
    masses = fragment_mass[order]
    return FragmentStats(
        count=count,
        masses=masses,
        largest=float(masses[0]) if count else 0.0,
        speeds=speed[order],
        node_label=np.asarray(node_label, dtype=np.int32),
        particle_label=np.asarray(particle_label, dtype=np.int32),
        fragment_mass=fragment_mass,
        fragment_velocity=velocity,
    )


def tets_per_fragment(model: Model, state: State, stats: FragmentStats) -> np.ndarray:
    """Active tets in each fragment, indexed by fragment id, shape (count,), int64 (0 for a fragment of spheres only;
    a tet's nodes share one fragment, so its first node's label is the tet's). Reads back the tets."""
    nt = int(state.tet_count.numpy()[0]) if model.tet_capacity else 0
    first = model.tet_nodes.numpy()[:nt, 0][state.tet_active.numpy()[:nt] != 0]  # rigid tets too
    return np.bincount(stats.node_label[first], minlength=stats.count).astype(np.int64)


def fragment_colors(labels: np.ndarray) -> np.ndarray:
    """Display colours of fragment ids, linear RGB, shape (N, 3): hues a golden angle apart (ids next to each other
    look nothing alike, and no palette length makes fragments k and k + L share a colour), grey for -1."""
    labels = np.asarray(labels, dtype=np.int64).reshape(-1)
    # HSV → RGB at saturation s and value v, vectorised (colorsys.hsv_to_rgb per label is a Python call each).
    s, v = 0.65, 0.9
    h6 = np.mod(labels * 0.618033988749895, 1.0) * 6.0
    sector = np.minimum(h6.astype(np.int64), 5)
    f = h6 - sector
    p, q, t = np.full_like(f, v * (1.0 - s)), v * (1.0 - s * f), v * (1.0 - s * (1.0 - f))
    vv = np.full_like(f, v)
    r = np.choose(sector, [vv, q, p, p, t, vv])
    g = np.choose(sector, [t, vv, vv, q, p, p])
    b = np.choose(sector, [p, p, t, vv, vv, q])
    colors = np.stack([r, g, b], axis=1)
    colors[labels < 0] = 0.5
    return colors


@dataclass
class FragmentSeries:
    """What a fragment file holds, frame by frame (:func:`read_fragments`).

    Attributes:
        frame: output frame numbers, shape (F,), int.
        time: their simulated times [s], shape (F,).
        count: fragments per frame, shape (F,), int.
        largest: largest fragment's mass [kg], shape (F,).
        total_mass: mass of all fragments [kg], shape (F,).
        masses: per frame, the fragment masses [kg], descending.
        speeds: per frame, the fragments' centre-of-mass speeds [m/s], in the order of ``masses``.
    """

    frame: np.ndarray
    time: np.ndarray
    count: np.ndarray
    largest: np.ndarray
    total_mass: np.ndarray
    masses: list[np.ndarray]
    speeds: list[np.ndarray]


def _group_name(frame: int) -> str:
    return f"frame_{frame:06d}"


def read_fragments(path: str | os.PathLike) -> FragmentSeries:
    """Read a ``<name>_fragments.h5`` file (module docstring) in frame order.

    Raises:
        OSError: the file cannot be opened as HDF5. KeyError: a frame group lacks a dataset or attribute.
    """
    import h5py

    rows = []
    with h5py.File(path, "r") as f:
        for name in sorted(k for k in f if k.startswith("frame_")):
            g = f[name]
            rows.append((g.attrs, np.asarray(g["masses"][()], np.float64), np.asarray(g["speeds"][()], np.float64)))
        series = FragmentSeries(
            frame=np.array([int(a["frame"]) for a, _, _ in rows], dtype=np.int64),
            time=np.array([float(a["time"]) for a, _, _ in rows]),
            count=np.array([int(a["count"]) for a, _, _ in rows], dtype=np.int64),
            largest=np.array([float(a["largest"]) for a, _, _ in rows]),
            total_mass=np.array([float(a["total_mass"]) for a, _, _ in rows]),
            masses=[m for _, m, _ in rows],
            speeds=[s for _, _, s in rows],
        )
    return series


class FragmentFile:
    """The per-frame fragment record of one run, ``<directory>/<name>_fragments.h5`` (module docstring).

    Every :meth:`record` publishes a complete file: the published one is copied to ``<name>_fragments.partial.h5``
    (a file copy, not a re-encoding of the frames before), this frame's group is added, and the copy is renamed over
    the final name — a reader never sees half a file, and a run that stops leaves the frames it finished. A run
    starting at frame 0 replaces an old file; a restart from frame M keeps that file's frames before M and continues
    it, as the time series does (warpdem.io.timeseries).

    Args:
        directory: output directory (created). name: stem of the file (that of the USD stage). first_frame: the
            frame this run starts at.
    """

    def __init__(self, directory: str | os.PathLike, name: str, first_frame: int = 0) -> None:
        self.directory = pathlib.Path(directory)
        self.path = self.directory / f"{name}_fragments.h5"
        self.partial_path = self.directory / f"{name}_fragments.partial.h5"
        self.first_frame = int(first_frame)
        self._fresh = True  # the first record builds the file anew (the kept frames of a restart copied over)

    def record(self, frame: int, time: float, stats: FragmentStats) -> pathlib.Path:
        """Add (or replace) the group of one frame and publish the file. Returns its path."""
        import h5py

        self.directory.mkdir(parents=True, exist_ok=True)
        tmp = self.partial_path
        try:
            if self._fresh:
                self._start(tmp)
            else:
                shutil.copyfile(self.path, tmp)
            with h5py.File(tmp, "a") as f:
                name = _group_name(frame)
                if name in f:
                    del f[name]
                g = f.create_group(name)
                g.attrs["frame"] = int(frame)
                g.attrs["time"] = float(time)
                g.attrs["count"] = int(stats.count)
                g.attrs["largest"] = float(stats.largest)
                g.attrs["total_mass"] = stats.total_mass
                masses = g.create_dataset("masses", data=np.asarray(stats.masses, dtype=np.float64))
                masses.attrs["unit"] = "kg"
                speeds = g.create_dataset("speeds", data=np.asarray(stats.speeds, dtype=np.float64))
                speeds.attrs["unit"] = "m/s"
            os.replace(tmp, self.path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
        self._fresh = False
        return self.path

    def _start(self, tmp: pathlib.Path) -> None:
        """A new file at ``tmp``: empty, or (a restart) with the frames of the published file before first_frame."""
        import h5py

        with h5py.File(tmp, "w") as out:
            out.attrs["description"] = (
                "warpdem fragments: one group per output frame; masses [kg] descending, speeds [m/s] of each "
                "fragment's centre of mass in the same order"
            )
            if self.first_frame > 0 and self.path.is_file():
                try:
                    with h5py.File(self.path, "r") as old:
                        for name in old:
                            if name.startswith("frame_") and int(old[name].attrs["frame"]) < self.first_frame:
                                old.copy(old[name], out, name=name)
                except (OSError, KeyError, ValueError):
                    pass  # an unreadable old file: the restart's frames start a new one, as the time series does
