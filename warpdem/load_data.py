"""The data of a model's loads and boundary dashpots, as the Model holds it (:attr:`warpdem.model.Model.loads`).

The load stage (:mod:`warpdem.stages.loads`) fills and evaluates these; they live below the Model so that the Model
can hold them without importing the stage that uses them (tests/test_layers.py keeps the layers apart).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

__all__ = ["FaceSet", "LoadModel", "covered_areas"]


def covered_areas(edge_a: np.ndarray, edge_b: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """The area each face's load covers [m²], |½ E_a × E_b| × ``covered`` (the share Σ_k w_k), from the faces'
    edges X1 − X0, X2 − X0 [m] (each (F, 3)); shape (F,), float64."""
    a, b = np.asarray(edge_a, dtype=np.float64), np.asarray(edge_b, dtype=np.float64)
    return 0.5 * np.linalg.norm(np.cross(a, b), axis=1) * np.asarray(covered, dtype=np.float64)


@dataclass
class FaceSet:
    """Faces on the device.

    Attributes:
        nodes: node ids, outward order, shape (F,), vec3i.
        edge_a: reference edge X1 - X0 [m] (float64 on the host), shape (F,), vec3.
        edge_b: reference edge X2 - X0 [m] (float64 on the host), shape (F,), vec3.
        index: pressure load of each face (into LoadModel.pressure_loads), shape (F,), int32; or None.
        impedance: (ρ c_p, ρ c_s) of the tet behind each dashpot face [Pa s/m], shape (F,), vec2; or None.
        tet: the tet behind each pressure face, shape (F,), int32; or None (dashpots).
        weight: three times the share w_k of the face's pressure force each of its nodes takes [-], shape (F,),
            vec3: (1, 1, 1) for a face inside its load's region, less where the region's edge crosses it
            (warpdem.build.face_cover: Σ w_k = the covered fraction of the face); or None (dashpots).
        handed_area: the area vector of each pressure face when its tet converted [m²], shape (F,), vec3: the face's
            push p(t) a then acts on that tet's spheres (kernels/loads.py, "Hand-over"); zero while the tet is a tet,
            and for a face dropped before the hand-over existed (a restart of such a run). Written by the
            conversion pass; or None (dashpots).
        first: the set's first slot in the State's per-loaded-face arrays (``load_face_force``, ``load_face_work``:
            the pressure sets one after the other, in ``LoadModel.pressure``'s order).
    """

    nodes: wp.array
    edge_a: wp.array
    edge_b: wp.array
    index: wp.array | None = None
    impedance: wp.array | None = None
    tet: wp.array | None = None
    weight: wp.array | None = None
    handed_area: wp.array | None = None
    first: int = 0

    @property
    def count(self) -> int:
        return self.nodes.shape[0]

    @staticmethod
    def create(
        points: np.ndarray,
        faces: np.ndarray,
        device,
        index: np.ndarray | None = None,
        impedance: np.ndarray | None = None,
        tet: np.ndarray | None = None,
        first: int = 0,
        weight: np.ndarray | None = None,
    ) -> FaceSet:
        """Faces (F, 3) of ``points`` [m] (N, 3); with ``tet`` (F,), the tet behind each, the hand-over arrays of a
        pressure face set (zero: no face handed over yet), its State slots from ``first``, and the nodes' shares
        ``weight`` (F, 3) (None: a third each)."""
        x = np.asarray(points, dtype=np.float64)[faces]
        handed = {}
        if tet is not None:
            handed = {
                "tet": wp.array(np.asarray(tet, dtype=np.int32), dtype=int, device=device),
                "handed_area": wp.zeros(len(faces), dtype=wp.vec3, device=device),
                "weight": wp.array(
                    np.ones((len(faces), 3)) if weight is None else 3.0 * np.asarray(weight, dtype=np.float64),
                    dtype=wp.vec3,
                    device=device,
                ),
                "first": int(first),
            }
        return FaceSet(
            nodes=wp.array(faces.astype(np.int32), dtype=wp.vec3i, device=device),
            edge_a=wp.array((x[:, 1] - x[:, 0]).astype(np.float32), dtype=wp.vec3, device=device),
            edge_b=wp.array((x[:, 2] - x[:, 0]).astype(np.float32), dtype=wp.vec3, device=device),
            index=None if index is None else wp.array(index.astype(np.int32), dtype=int, device=device),
            impedance=None
            if impedance is None
            else wp.array(impedance.astype(np.float32), dtype=wp.vec2, device=device),
            **handed,
        )


@dataclass
class LoadModel:
    """Loads and boundary dashpots of a model (static during a step).

    Attributes:
        pressure: loaded faces by history kind (one launch per kind).
        pressure_loads: parameters of every pressure load, shape (L,), PressureLoad; None without loads.
        pressure_names: name of each pressure load, index = load id.
        table_times: times of all table histories, concatenated [s], float64.
        table_values: their pressures [Pa], float32.
        dashpots: the non-reflecting faces with their impedances, or None.
        node_driver: velocity driver of each node or -1, shape (node_capacity,), int32; None without drivers.
        drivers: the velocity drivers, shape (D,), NodeDriver; None without drivers.
    """

    pressure: dict[str, FaceSet]
    pressure_loads: wp.array | None
    pressure_names: list[str]
    table_times: wp.array
    table_values: wp.array
    dashpots: FaceSet | None
    node_driver: wp.array | None
    drivers: wp.array | None

    def loaded_areas(self) -> np.ndarray:
        """The area each pressure load pushes on, Σ |A_f| Σ_k w_fk over its faces [m²], shape (L,), float64 (index =
        load id): a face's reference area while its tet is a tet; a face handed over to the spheres of its converted
        tet counts with the area it pushes them with, |a_c| (``handed_area``, its area when its tet converted); a face
        dropped without a hand-over (a restart of an older run) pushes on nothing and counts zero."""
        areas = np.zeros(len(self.pressure_names))
        for faces in self.pressure.values():
            covered = faces.weight.numpy().astype(np.float64).sum(axis=1) / 3.0
            area = covered_areas(faces.edge_a.numpy(), faces.edge_b.numpy(), covered)
            if faces.handed_area is not None:
                # A handed-over face's reference edges are zero (dropped): its area is the handed one's.
                handed = np.linalg.norm(faces.handed_area.numpy().astype(np.float64), axis=1) * covered
                area = area + handed
            np.add.at(areas, faces.index.numpy(), area)
        return areas

    def impulses(self, load_face_impulse: np.ndarray) -> np.ndarray:
        """The normal impulse each pressure load delivered [N s], shape (L,), float64, from the State's
        ``load_face_impulse`` (per loaded face, each face set from its ``first``)."""
        impulses = np.zeros(len(self.pressure_names))
        for faces in self.pressure.values():
            np.add.at(impulses, faces.index.numpy(), load_face_impulse[faces.first : faces.first + faces.count])
        return impulses

    @property
    def num_drivers(self) -> int:
        return 0 if self.drivers is None else self.drivers.shape[0]
