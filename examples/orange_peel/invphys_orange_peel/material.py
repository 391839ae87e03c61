"""Physical parameters -> per-run material constants and the time-step bound (pure NumPy).

Conventions (see docs/orange-peel/physics.md): SI units; ``rho`` given in 10^3 kg/m^3; Poisson
ratio fixed at 0.4; fixed-corotated elasticity with Lame constants from (E, nu); skin fibre stiffness
``k_f = f_s * mu``; the critical stress ``sigma_c`` of a region is the one that makes the crack
driving force ``phi`` equal 1 in a free uniaxial tension test of the intact material at strain ``p``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from invphys_orange_peel.parameters import PARAMETER_NAMES

POISSON = 0.4
DENSITY_UNIT = 1000.0  # kg/m^3 per unit of the rho parameter

_IDX = {n: i for i, n in enumerate(PARAMETER_NAMES)}


def lame(E: np.ndarray, nu: float = POISSON) -> tuple[np.ndarray, np.ndarray]:
    """(mu, lambda) in Pa from Young's modulus and Poisson ratio."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def critical_stress(p: np.ndarray, mu: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """sigma_c (Pa): the tensile Cauchy stress of a uniaxial tension test stretched by ``p``.

    The intact fixed-corotated material is stretched to F = diag(1 + p, s, s) with the lateral stretch
    s chosen so that the lateral stress vanishes (a free tensile test); sigma_c is the axial Cauchy
    stress there. Since that state has a single positive principal stress, the crack driving force
    phi = |sigma+|_F^2 / sigma_c^2 of the isotropic model is exactly 1 at engineering strain p.
    """
    p, mu, lam = np.broadcast_arrays(np.asarray(p, float), np.asarray(mu, float), np.asarray(lam, float))
    a = 1.0 + p
    lo, hi = np.full(p.shape, 1e-6), np.ones(p.shape)

    def lateral(s: np.ndarray) -> np.ndarray:  # J * lateral Cauchy stress; increasing in s
        J = a * s * s
        return 2.0 * mu * (s - 1.0) * s + lam * (J - 1.0) * J

    for _ in range(60):
        mid = 0.5 * (lo + hi)
        pos = lateral(mid) > 0
        hi = np.where(pos, mid, hi)
        lo = np.where(pos, lo, mid)
    s = 0.5 * (lo + hi)
    J = a * s * s
    return (2.0 * mu * (a - 1.0) * a + lam * (J - 1.0) * J) / J


@dataclass
class Materials:
    """Per-run constants (each array has shape (B,)); region 0 = skin, 1 = interior."""

    mu: np.ndarray
    lam: np.ndarray
    rho: np.ndarray          # kg/m^3
    kf: np.ndarray           # skin fibre stiffness (Pa)
    sigma_c: np.ndarray      # (B, 2) critical stress per region (Pa)
    eta: np.ndarray          # (B, 2) damage regularisation per region (s)
    residual: np.ndarray     # (B, 2) residual stiffness fraction per region
    wave_speed: np.ndarray   # (B,) bound on the elastic wave speed (m/s)

    @property
    def batch(self) -> int:
        return int(self.mu.shape[0])

    def elastic_dt(self, dx: float, cfl: float) -> np.ndarray:
        """The elastic-wave CFL bound on dt: cfl * dx / c, c = sqrt((lam + 2 mu + k_f) / rho)."""
        return cfl * dx / self.wave_speed

    def take(self, index: np.ndarray) -> Materials:
        return Materials(*(getattr(self, f)[index] for f in self.__dataclass_fields__))


def materials_from_params(params: np.ndarray) -> Materials:
    """Per-run constants for physical parameter rows (B, 9) in :data:`PARAMETER_NAMES` order."""
    x = np.atleast_2d(np.asarray(params, dtype=np.float64))
    col = {n: x[:, i] for n, i in _IDX.items()}
    mu, lam = lame(col["E"])
    rho = col["rho"] * DENSITY_UNIT
    kf = col["f_s"] * mu
    sigma_c = np.stack([critical_stress(col["sigma_s"], mu, lam), critical_stress(col["sigma_i"], mu, lam)], 1)
    eta = np.stack([col["eta_s"], col["eta_i"]], 1)
    residual = np.stack([col["r_s"], col["r_i"]], 1)
    wave = np.sqrt((lam + 2.0 * mu + kf) / rho)
    return Materials(mu=mu, lam=lam, rho=rho, kf=kf, sigma_c=sigma_c, eta=eta, residual=residual,
                     wave_speed=wave)
