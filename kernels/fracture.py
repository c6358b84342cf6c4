"""Nodal fracture (LDEC §2.2–2.3, DESIGN.md stage 6): the fracture properties of a material, and the kernels of the
run-time split pass (nodal stress, candidates, claims, partition of a node's star, birth of cohesive elements)."""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class FractureMaterial:
    """Fracture properties of one material (index = material id).

    Attributes:
        tensile_strength: T_f, the largest principal nodal stress at which a node splits [Pa]; a very large value
            (3.4e38) for a material that never splits.
        fracture_energy: Γ, the energy per unit area of new crack surface (both faces counted in A_f) [J/m²].
        alpha: α of the weakening law (LDEC eq. 6), in [0, 1] [-].
    """

    tensile_strength: float
    fracture_energy: float
    alpha: float
