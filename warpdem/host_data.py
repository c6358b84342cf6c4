"""Host-side descriptions of what a model is built from (warpdem.build.builder): spheres, FEM nodes and tets, bonds and
walls as numpy arrays, in the order they get their device ids."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BondData", "ParticleData", "TetMeshData", "WallData"]


@dataclass
class ParticleData:
    """Host-side description of the spheres to create, in the order they get their ids.

    Attributes:
        q: centres [m], shape (N, 3). qd: velocities [m/s], (N, 3). omega: spins [rad/s], (N, 3).
        radius: [m], (N,). material: material id, (N,). motion: 0 free / 1 fixed / 2 prescribed, (N,).
        part: part id, (N,).
    """

    q: np.ndarray
    qd: np.ndarray
    omega: np.ndarray
    radius: np.ndarray
    material: np.ndarray
    motion: np.ndarray
    part: np.ndarray

    def __len__(self) -> int:
        return len(self.radius)


@dataclass
class TetMeshData:
    """Host-side FEM nodes and tets to create.

    Attributes:
        points: node positions [m], (N, 3). velocity: node velocities [m/s], (N, 3). motion: 0 free / 1 fixed /
        2 z only, (N,). tets: positively oriented node indices, (M, 4). material: material id per tet, (M,).
    """

    points: np.ndarray
    velocity: np.ndarray
    motion: np.ndarray
    tets: np.ndarray
    material: np.ndarray

    @staticmethod
    def empty() -> TetMeshData:
        z3 = np.zeros((0, 3))
        return TetMeshData(z3, z3, np.zeros(0, np.int32), np.zeros((0, 4), np.int32), np.zeros(0, np.int32))


@dataclass
class BondData:
    """Host-side bonds to create: pairs (i < j), rest lengths [m], stiffnesses [N/m], areas [m²], strengths [Pa],
    damping ratios [-]; all shape (M,) except ``pairs`` (M, 2)."""

    pairs: np.ndarray
    rest_length: np.ndarray
    kn: np.ndarray
    ks: np.ndarray
    area: np.ndarray
    tensile_strength: np.ndarray
    shear_strength: np.ndarray
    damping: np.ndarray

    @staticmethod
    def empty() -> BondData:
        z = np.zeros(0, dtype=np.float32)
        return BondData(np.zeros((0, 2), dtype=np.int32), z, z, z, z, z, z, z)

    def __len__(self) -> int:
        return len(self.pairs)


@dataclass
class WallData:
    """Host-side planar walls: points [m] (W, 3), inward unit normals (W, 3), velocities [m/s] (W, 3),
    material ids (W,)."""

    point: np.ndarray
    normal: np.ndarray
    velocity: np.ndarray
    material: np.ndarray

    def __len__(self) -> int:
        return len(self.material)
