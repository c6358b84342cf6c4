"""Materials and material pairs as the builder takes them: elastic properties, contact properties of a pair, and the
pair's effective moduli (Hertz, Mindlin).

A leaf below the builder and the stages, so that both can name a material without importing each other
(tests/test_layers.py keeps it a leaf).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["InteractionProps", "MaterialProps", "effective_moduli"]


@dataclass
class MaterialProps:
    """Elastic properties of a material: density [kg/m³], Young's modulus [Pa], Poisson ratio [-]."""

    density: float
    youngs_modulus: float
    poisson_ratio: float


@dataclass
class InteractionProps:
    """Contact properties of a material pair: Coulomb friction [-], restitution (0, 1] [-], rolling friction [-]."""

    friction: float = 0.5
    restitution: float = 0.5
    rolling_friction: float = 0.0


def effective_moduli(a: MaterialProps, b: MaterialProps) -> tuple[float, float]:
    """E* and G* of a pair [Pa] (Hertz and Mindlin)."""
    estar = 1.0 / ((1.0 - a.poisson_ratio**2) / a.youngs_modulus + (1.0 - b.poisson_ratio**2) / b.youngs_modulus)
    ga = 2.0 * (2.0 - a.poisson_ratio) * (1.0 + a.poisson_ratio) / a.youngs_modulus
    gb = 2.0 * (2.0 - b.poisson_ratio) * (1.0 + b.poisson_ratio) / b.youngs_modulus
    return estar, 1.0 / (ga + gb)
