"""Targets for ``invphys invert``: a file, ``--feature name=value`` items, or an observed trajectory.

An observed trajectory is the framework's trajectory file (:mod:`invphys.core.trajectory_io`, as
``invphys simulate`` writes it; older files load too) or a run directory holding ``trajectory.npz``;
the bundle's feature extractor turns it into the target.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.core.user_targets import (
    TargetError,
    UserTargets,
    from_array,
    parse_assignments,
    read_target_file,
)


def load_trajectory(path: str | Path) -> Any:
    """A :class:`~invphys.core.results.Trajectory` from a trajectory file or a run directory (any format
    :func:`invphys.core.trajectory_io.load_trajectory` reads, the one ``invphys simulate`` writes included)."""
    from invphys.core.trajectory_io import load_trajectory as read

    try:
        return read(path)
    except InvphysError as exc:
        raise TargetError(f"cannot read trajectory {str(path)!r}: {str(exc).splitlines()[0]}") from None


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
