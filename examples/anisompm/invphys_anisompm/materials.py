"""Materials: the anisotropic damageable hyperelastic law of AnisoMPM, as per-run constants.

A :class:`MaterialSpec` names a body's material in physical units. Any field can be overridden per run
(each run of a batch has its own value) through :meth:`Model.set_material
<invphys_anisompm.model.Model.set_material>`, which is how a scene maps its parameters onto the engine.

The law (see ``docs/anisompm.md``): fixed-corotated elasticity with Lamé constants from (E, nu);
degradation ``g(d) = (1 - d)^2 (1 - r) + r`` of the deviatoric part and of the volumetric part in
tension only; a fibre term ``(k_f / 2)(|F a0| - 1)^2`` with ``k_f = fibre_ratio * mu`` (never
degraded); damage driven by the undegraded positive Cauchy stress seen through the structural tensor
``A = I + fibre_alpha (R a0)(R a0)^T``; the critical stress ``sigma_c`` from the percentage stretch
``fracture_stretch`` (a free uniaxial tension test of the intact material).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

#: columns of the per-run, per-body material table (B, n_bodies, N_MAT) handed to the kernels
M_MU, M_LAM, M_KF, M_RHO, M_SC, M_ETA, M_RES, M_ALPHA, M_DMG = range(9)
N_MAT = 9


@dataclass(frozen=True)
class MaterialSpec:
    """One body's material (defaults: a soft, isotropic, damageable solid).

    Attributes:
        E: Young's modulus (Pa).
        nu: Poisson ratio (explicit time steps shrink as nu -> 0.5).
        rho: density (kg/m^3).
        fracture_stretch: percentage stretch p at which a free tensile test starts to damage.
        eta: damage regularisation (s): damage grows at rate (driving force) / eta.
        residual: stiffness fraction r kept by fully damaged material.
        fibre_ratio: fibre stiffness k_f / mu along the particles' fibre direction (0: none).
        fibre_alpha: structural-tensor weight of the fibre: -1 lets tension along the fibre not drive
            damage (cracks run along fibres), 0 is isotropic damage.
        damage: whether this body's damage evolves at all.
    """

    E: float = 1e4
    nu: float = 0.3
    rho: float = 1000.0
    fracture_stretch: float = 0.2
    eta: float = 0.1
    residual: float = 0.01
    fibre_ratio: float = 0.0
    fibre_alpha: float = 0.0
    damage: bool = True

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        return tuple(f.name for f in fields(cls))


def lame(E: np.ndarray, nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mu, lambda) in Pa from Young's modulus (Pa) and Poisson ratio."""
    E, nu = np.asarray(E, float), np.asarray(nu, float)
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def critical_stress(p: np.ndarray, mu: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """sigma_c (Pa): the axial Cauchy stress of a free uniaxial tension test stretched by ``p``.

    The intact fixed-corotated material is stretched to F = diag(1 + p, s, s), with s such that the
    lateral stress vanishes; the state has one positive principal stress, so the crack driving force
    phi = |sigma+|^2 / sigma_c^2 of the isotropic model is exactly 1 at engineering strain p.
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


def material_columns(values: dict[str, np.ndarray]) -> np.ndarray:
    """(B, N_MAT) kernel columns from per-run arrays of every :class:`MaterialSpec` field."""
    mu, lam = lame(values["E"], values["nu"])
    B = len(mu)
    out = np.zeros((B, N_MAT))
    out[:, M_MU] = mu
    out[:, M_LAM] = lam
    out[:, M_KF] = values["fibre_ratio"] * mu
    out[:, M_RHO] = values["rho"]
    out[:, M_SC] = critical_stress(values["fracture_stretch"], mu, lam)
    out[:, M_ETA] = values["eta"]
    out[:, M_RES] = values["residual"]
    out[:, M_ALPHA] = values["fibre_alpha"]
    out[:, M_DMG] = np.asarray(values["damage"], float)
    return out


def wave_speed(table: np.ndarray) -> np.ndarray:
    """(B, n_bodies) bound on the elastic wave speed (m/s): sqrt((lambda + 2 mu + k_f) / rho)."""
    return np.sqrt((table[..., M_LAM] + 2.0 * table[..., M_MU] + table[..., M_KF]) / table[..., M_RHO])


__all__ = ["N_MAT", "MaterialSpec", "critical_stress", "lame", "material_columns", "wave_speed"]
