"""The 9 material parameters of the orange peel (paper Table 1), their units and ranges."""

from __future__ import annotations

from invphys.core.params import Parameter, ParameterSpace

#: Parameter order used everywhere (rows of ``params`` arrays follow it).
PARAMETER_NAMES: tuple[str, ...] = ("E", "rho", "sigma_s", "eta_s", "r_s", "f_s", "sigma_i", "eta_i", "r_i")

ORANGE_PEEL_SPACE = ParameterSpace((
    Parameter("E", 50.0, 8000.0, log=True, unit="Pa",
              description="Young's modulus, shared by skin and interior"),
    Parameter("rho", 0.5, 10.0, unit="1e3 kg/m^3",
              description="density in g/cm^3 (10^3 kg/m^3), shared"),
    Parameter("sigma_s", 0.05, 0.5,
              description="skin fracture threshold: percentage stretch p at which damage starts"),
    Parameter("eta_s", 0.01, 1.0, log=True, unit="s",
              description="skin damage regularisation (viscosity): damage rate is dt/eta"),
    Parameter("r_s", 0.001, 0.1, log=True,
              description="skin residual stiffness fraction of fully damaged material"),
    Parameter("f_s", 1.0, 100.0, log=True,
              description="skin fibre stiffness scale: k_f = f_s * mu"),
    Parameter("sigma_i", 0.1, 0.9,
              description="interior fracture threshold: percentage stretch p at which damage starts"),
    Parameter("eta_i", 0.01, 1.0, log=True, unit="s",
              description="interior damage regularisation (viscosity)"),
    Parameter("r_i", 0.001, 0.1, log=True,
              description="interior residual stiffness fraction"),
))
assert ORANGE_PEEL_SPACE.names == PARAMETER_NAMES


def parameter_space() -> ParameterSpace:
    """The orange peel's :class:`~invphys.core.params.ParameterSpace` (physical units as documented)."""
    return ORANGE_PEEL_SPACE
