"""Blow-up detection: per-frame device statistics -> a failure reason string, or None.

A run fails, and is reported with ``ok=False`` and the reason, when at the end of a frame

* ``nan``: any particle has a non-finite (or > 1e20) position, velocity, deformation gradient or damage;
* ``domain``: any particle left the simulation box (closer than 1.5 cells to a face);
* ``energy``: the kinetic energy exceeds ``energy_factor * 1/2 M v_ref^2``, with M the run's total
  mass and v_ref the larger of the elastic wave speed bound and the gripper's peak speed;
* ``dt``: the velocity CFL asks for more than ``max_substeps_per_frame`` substeps in a frame.
"""

from __future__ import annotations

import numpy as np

#: columns of the per-run frame statistics (B, N_STATS) every backend returns: peak speed, kinetic energy,
#: non-finite and out-of-box particle counts, sums of skin and interior positions relative to the scene
#: centre (3 each), the sum of damage, and the gripper's work during the frame (J)
STAT_VMAX, STAT_KE, STAT_NONFINITE, STAT_OUTSIDE = range(4)
STAT_SSUM, STAT_ISUM, STAT_DSUM, STAT_WORK = 4, 7, 10, 11
N_STATS = 12


def energy_bound(total_mass: np.ndarray, wave_speed: np.ndarray, grip_speed: float,
                 factor: float) -> np.ndarray:
    """Kinetic-energy ceiling (J) per run."""
    v_ref = np.maximum(wave_speed, grip_speed)
    return factor * 0.5 * total_mass * v_ref ** 2


def frame_failure(stats: np.ndarray, bound: float, frame: int) -> str | None:
    """The failure reason of one run from its frame statistics (N_STATS,), or None if it is healthy."""
    if stats[STAT_NONFINITE] > 0:
        return f"nan: {int(stats[STAT_NONFINITE])} particle(s) with non-finite state at frame {frame}"
    if not np.isfinite(stats[STAT_WORK]) or not np.isfinite(stats[STAT_DSUM]):
        return f"nan: non-finite damage or gripper work at frame {frame}"
    if stats[STAT_OUTSIDE] > 0:
        return f"domain: {int(stats[STAT_OUTSIDE])} particle(s) left the simulation box at frame {frame}"
    if not np.isfinite(stats[STAT_KE]) or stats[STAT_KE] > bound:
        return (f"energy: kinetic energy {stats[STAT_KE]:.3g} J exceeds the bound {bound:.3g} J "
                f"at frame {frame}")
    return None


def substep_failure(nsub: int, limit: int, frame: int, vmax: float) -> str | None:
    """Failure when the adaptive dt collapses (a velocity blow-up in disguise)."""
    if nsub > limit:
        return (f"dt: {nsub} substeps needed in frame {frame} (limit {limit}); "
                f"peak particle speed {vmax:.3g} m/s")
    return None
