"""The 7 parameters of the cheese-cutting simulator, with units and physical ranges.

Ranges cover soft to semi-hard cheeses (Young's moduli of ~20 kPa for soft, brie-like paste to
~300 kPa for young gouda or cheddar; densities 0.9-1.3 g/cm^3); the upper Poisson ratio is capped at 0.45
because the explicit time step shrinks as nu -> 0.5 (real cheese is nearly incompressible, ~0.45-0.49).
"""

from __future__ import annotations

from invphys.core.params import Parameter, ParameterSpace

PARAMETER_NAMES: tuple[str, ...] = ("E", "nu", "rho", "fracture_stretch", "eta", "residual", "friction")

CHEESE_SPACE = ParameterSpace((
    Parameter("E", 2e4, 3e5, log=True, unit="Pa", description="Young's modulus of the cheese"),
    Parameter("nu", 0.25, 0.45, description="Poisson ratio of the cheese"),
    Parameter("rho", 0.9, 1.3, unit="1e3 kg/m^3", description="density in g/cm^3"),
    Parameter("fracture_stretch", 0.05, 0.5,
              description="percentage stretch p at which a free tensile test starts to damage"),
    Parameter("eta", 0.005, 0.5, log=True, unit="s", description="damage regularisation (viscosity)"),
    Parameter("residual", 0.001, 0.1, log=True, description="stiffness fraction kept by fully damaged cheese"),
    Parameter("friction", 0.0, 0.8, description="Coulomb friction coefficient between wire and cheese"),
))
assert CHEESE_SPACE.names == PARAMETER_NAMES


def parameter_space() -> ParameterSpace:
    """The cheese cut's :class:`~invphys.core.params.ParameterSpace` (physical units)."""
    return CHEESE_SPACE
