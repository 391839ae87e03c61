"""invphys hook implementations of the orange-peel distribution (import-cheap: no taichi, no warp)."""

from __future__ import annotations

from invphys import hookimpl


@hookimpl
def invphys_register_simulators() -> list[type]:
    from invphys_orange_peel.simulator import OrangePeelSimulator

    return [OrangePeelSimulator]


@hookimpl
def invphys_register_feature_extractors() -> list[type]:
    from invphys_orange_peel.features import OrangePeelFeatures

    return [OrangePeelFeatures]
