"""Targets for ``invphys invert``: a file, ``--feature name=value`` items, or an observed trajectory.

An observed trajectory is a ``.npz`` as ``invphys simulate`` writes it (``positions``, ``damage``,
``labels``, ``frame_indices``, ``fps``, optional ``extra_*`` arrays), or a run directory holding
``trajectory.npz``; the bundle's feature extractor turns it into the target.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.user_targets import (
    TargetError,
    UserTargets,
    from_array,
    parse_assignments,
    read_target_file,
)

TRAJECTORY_FILE = "trajectory.npz"
TRAJECTORY_KEYS = ("positions", "damage", "labels", "frame_indices", "fps")


def load_trajectory(path: str | Path) -> Any:
    """A :class:`~invphys.core.results.Trajectory` from a ``.npz`` file or a run directory."""
    from invphys.core.results import Trajectory

    p = Path(path)
    if p.is_dir():
        p = p / TRAJECTORY_FILE
    if not p.is_file():
        raise TargetError(f"no trajectory at {str(path)!r} (expected a .npz file or a run directory with "
                          f"{TRAJECTORY_FILE})")
    try:
        with np.load(p, allow_pickle=False) as data:
            missing = [k for k in TRAJECTORY_KEYS if k not in data.files]
            if missing:
                raise TargetError(f"{p} is not a saved trajectory: it lacks {', '.join(missing)}")
            extra: dict[str, Any] = json.loads(str(data["extra_json"])) if "extra_json" in data.files else {}
            extra.update({k[6:]: data[k] for k in data.files if k.startswith("extra_") and k != "extra_json"})
            return Trajectory(positions=data["positions"], damage=data["damage"], labels=data["labels"],
                              frame_indices=data["frame_indices"], fps=float(data["fps"]), extra=extra)
    except TargetError:
        raise
    except (OSError, ValueError, KeyError) as exc:
        raise TargetError(f"cannot read trajectory {str(p)!r}: {exc}") from None


def observed_targets(inverter: Any, paths: Sequence[str | Path]) -> UserTargets:
    """Targets computed by the bundle's feature extractor from observed trajectories."""
    ext = inverter.extractor()
    rows = []
    for path in paths:
        try:
            rows.append(np.asarray(ext.extract(load_trajectory(path)), dtype=np.float64))
        except TargetError:
            raise
        except Exception as exc:  # the extractor's own complaint, as one line
            raise TargetError(f"cannot extract features from {str(path)!r}: {str(exc).splitlines()[0]}") from None
    t = from_array(np.array(rows), inverter.feature_names, source="observed trajectory")
    t.labels = [Path(p).stem if Path(p).is_file() else Path(p).name for p in paths]
    return t


def cli_targets(inverter: Any, target_file: str | None, features: Sequence[str], observed: Sequence[str],
                partial: bool) -> UserTargets:
    """The one target source the CLI was given (exactly one of the three)."""
    given = [n for n, v in (("--target", target_file), ("--feature", features), ("--observed", observed)) if v]
    if not given:
        raise TargetError("give a target: --target FILE, --feature NAME=VALUE (repeat) or --observed TRAJ. "
                          f"Features: {', '.join(inverter.feature_names)}")
    if len(given) > 1:
        raise TargetError(f"give one kind of target, not {' and '.join(given)}")
    if target_file:
        return read_target_file(target_file, inverter.feature_names, partial)
    if features:
        return parse_assignments(features, inverter.feature_names, partial)
    return observed_targets(inverter, observed)
