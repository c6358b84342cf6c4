"""Adaptive FEM→DEM conversion (CIMNE §4–5, DESIGN.md stage 7): the conversion properties of a material, and the
kernels of the between-steps conversion pass (criterion per tet, spawning spheres and their bonds)."""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

CRITERION_TRESCA = wp.constant(0)
CRITERION_RANKINE = wp.constant(1)
CRITERION_MOHR_COULOMB = wp.constant(2)


@wp.struct
class ConversionMaterial:
    """Conversion properties of one material (index = material id).

    Attributes:
        criterion: CRITERION_TRESCA ((σ1 − σ3)/2 ≥ f τ_f), CRITERION_RANKINE (σ1 ≥ f T_f) or CRITERION_MOHR_COULOMB
            (σ1 (1 − sin φ)/ (2 c cos φ) − σ3 (1 + sin φ)/(2 c cos φ) ≥ f, tension positive), int32.
        fraction: f, the fraction of the strength at which a tet converts (0.9: CIMNE's 90 %) [-].
        tresca_strength: τ_f [Pa] (a very large value, 3.4e38: never by Tresca).
        tensile_strength: T_f [Pa] (Rankine; also the bonds' tensile strength).
        cohesion: c of Mohr–Coulomb [Pa].
        friction_angle: φ of Mohr–Coulomb [rad].
    """

    criterion: int
    fraction: float
    tresca_strength: float
    tensile_strength: float
    cohesion: float
    friction_angle: float
