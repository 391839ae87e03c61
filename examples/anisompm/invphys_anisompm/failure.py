"""Blow-up detection: per-frame device statistics -> a failure reason string, or None.

A run fails, and is reported with its reason, when at the end of a frame

* ``nan``: a particle has a non-finite (or > 1e20) position, velocity, deformation gradient or damage;
* ``domain``: a particle left the simulation box (closer than 1.5 cells to a face);
* ``energy``: the kinetic energy exceeds ``energy_factor * 1/2 M v_ref^2``, M the run's total mass and
  v_ref the larger of the elastic wave-speed bound and the kinematic objects' peak speed;
* ``dt``: the velocity CFL asks for more than ``max_substeps_per_frame`` substeps in a frame.
"""

from __future__ import annotations

import numpy as np

#: leading columns of the per-run frame statistics (B, N_STATS) every backend returns; then, per body
#: ``b``, the sums of its particles' positions (3 columns at BODY0 + 4 b) and of their damage (BODY0 + 4 b + 3)
STAT_VMAX, STAT_KE, STAT_NONFINITE, STAT_OUTSIDE = range(4)
BODY0 = 4


def n_stats(n_bodies: int) -> int:
    return BODY0 + 4 * n_bodies


def energy_bound(total_mass: np.ndarray, wave_speed: np.ndarray, kinematic_speed: float,
                 factor: float) -> np.ndarray:
    """Kinetic-energy ceiling (J) per run."""
    v_ref = np.maximum(wave_speed, kinematic_speed)
    return factor * 0.5 * total_mass * v_ref ** 2


def frame_failure(stats: np.ndarray, bound: float, frame: int, extra_finite: float = 0.0) -> str | None:
    """The failure reason of one run from its frame statistics, or None if it is healthy."""
    if stats[STAT_NONFINITE] > 0:
        return f"nan: {int(stats[STAT_NONFINITE])} particle(s) with non-finite state at frame {frame}"
    if not np.all(np.isfinite(stats)) or not np.isfinite(extra_finite):
        return f"nan: non-finite damage, force or work at frame {frame}"
    if stats[STAT_OUTSIDE] > 0:
        return f"domain: {int(stats[STAT_OUTSIDE])} particle(s) left the simulation box at frame {frame}"
    if stats[STAT_KE] > bound:
        return f"energy: kinetic energy {stats[STAT_KE]:.3g} J exceeds the bound {bound:.3g} J at frame {frame}"
    return None


def unhealthy(stats: np.ndarray, bound: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """(n,) whether :func:`frame_failure` finds a reason for each row of ``stats`` (n, n_stats), with the
    rows' energy ``bound`` and ``extra_finite`` values: one numpy test for many runs, so that only the
    flagged rows need :func:`frame_failure`'s message (``test_unhealthy_flags_the_rows_frame_failure_fails``
    holds the two equal)."""
    with np.errstate(invalid="ignore"):
        return ((stats[:, STAT_NONFINITE] > 0) | ~np.isfinite(stats).all(axis=1) | ~np.isfinite(extra)
                | (stats[:, STAT_OUTSIDE] > 0) | (stats[:, STAT_KE] > bound))


def substep_failure(nsub: int, limit: int, frame: int, vmax: float) -> str | None:
    """Failure when the adaptive dt collapses (a velocity blow-up in disguise)."""
    if nsub > limit:
        return f"dt: {nsub} substeps needed in frame {frame} (limit {limit}); peak particle speed {vmax:.3g} m/s"
    return None


__all__ = ["BODY0", "STAT_KE", "STAT_NONFINITE", "STAT_OUTSIDE", "STAT_VMAX", "energy_bound", "frame_failure",
           "n_stats", "substep_failure", "unhealthy"]
