"""Entry point of the toy spring (import-cheap: only the hook functions)."""

from invphys import hookimpl


@hookimpl
def invphys_register_simulators():
    from invphys_toy_spring.simulator import SpringSimulator

    return [SpringSimulator]


@hookimpl
def invphys_register_feature_extractors():
    from invphys_toy_spring.features import SpringFeatures

    return [SpringFeatures]
