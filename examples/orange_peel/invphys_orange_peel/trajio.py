"""Save and load orange-peel trajectories: the framework's trajectory file (:mod:`invphys.core.trajectory_io`).

Kept as this module's names for older imports; files written by its earlier own format still load.
"""

from __future__ import annotations

from invphys.core.trajectory_io import TRAJECTORY_FILE, load_trajectory, save_trajectory

__all__ = ["TRAJECTORY_FILE", "load_trajectory", "save_trajectory"]
