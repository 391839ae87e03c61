"""invphys hook implementations of the cheese-cut distribution (import-cheap: no taichi, no warp)."""

from __future__ import annotations

from invphys import hookimpl


@hookimpl
def invphys_register_simulators() -> list[type]:
    from invphys_cheese_cut.simulator import CheeseCutSimulator

    return [CheeseCutSimulator]


@hookimpl
def invphys_register_feature_extractors() -> list[type]:
    from invphys_cheese_cut.features import CheeseCutFeatures

    return [CheeseCutFeatures]
