"""Save and load orange-peel trajectories as ``.npz`` (plain NumPy, no pickles)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.results import Trajectory

TRAJECTORY_FILE = "trajectory.npz"


def save_trajectory(traj: Trajectory, path: str | Path) -> Path:
    """Write ``traj`` to ``path`` (a ``.npz``); array extras become ``extra_<key>`` arrays."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, Any] = {"positions": traj.positions, "damage": traj.damage, "labels": traj.labels,
                              "frame_indices": traj.frame_indices, "fps": np.float64(traj.fps)}
    scalars: dict[str, Any] = {}
    for key, value in traj.extra.items():
        if isinstance(value, np.ndarray):
            arrays[f"extra_{key}"] = value
        elif isinstance(value, (int, float, str, bool)) or value is None:
            scalars[key] = value
        elif isinstance(value, np.generic):
            scalars[key] = value.item()
    arrays["extra_json"] = np.array(json.dumps(scalars))
    np.savez_compressed(path, **arrays)
    return path


def load_trajectory(path: str | Path) -> Trajectory:
    """Read a trajectory written by :func:`save_trajectory` (``path`` may be a run directory)."""
    path = Path(path)
    if path.is_dir():
        path = path / TRAJECTORY_FILE
    if not path.exists():
        raise InvphysError(f"no trajectory at {path} (expected a run directory or a .npz file)")
    try:
        with np.load(path, allow_pickle=False) as data:
            extra: dict[str, Any] = json.loads(str(data["extra_json"])) if "extra_json" in data else {}
            for key in data.files:
                if key.startswith("extra_") and key != "extra_json":
                    extra[key[len("extra_"):]] = data[key]
            return Trajectory(positions=data["positions"], damage=data["damage"], labels=data["labels"],
                              frame_indices=data["frame_indices"], fps=float(data["fps"]), extra=extra)
    except (KeyError, ValueError, OSError) as exc:
        raise InvphysError(f"{path} is not an orange-peel trajectory file: {exc}") from exc
