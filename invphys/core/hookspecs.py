"""The hooks a plugin distribution implements to register its classes.

A distribution exposes a module in the ``invphys`` entry-point group; that module defines one or more
of these functions decorated with :data:`invphys.hookimpl`, each returning a list of plugin classes::

    # my_food/plugin.py            (pyproject: [project.entry-points.invphys] my_food = "my_food.plugin")
    from invphys import hookimpl

    @hookimpl
    def invphys_register_simulators():
        from my_food.simulator import MyFoodSimulator   # keep heavy imports out of this module
        return [MyFoodSimulator]

The built-in plugins are registered through the same hooks (``invphys.plugins.builtin``).
Every class returned must subclass the interface of its kind (:mod:`invphys.core.interfaces`) and
carry a ``name`` unique within that kind.
"""

from __future__ import annotations

import pluggy

PROJECT = "invphys"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def invphys_register_simulators() -> list[type]:  # type: ignore[empty-body]
    """Return :class:`~invphys.core.interfaces.Simulator` subclasses."""


@hookspec
def invphys_register_feature_extractors() -> list[type]:  # type: ignore[empty-body]
    """Return :class:`~invphys.core.interfaces.FeatureExtractor` subclasses."""


@hookspec
def invphys_register_executors() -> list[type]:  # type: ignore[empty-body]
    """Return :class:`~invphys.core.interfaces.Executor` subclasses."""


@hookspec
def invphys_register_surrogates() -> list[type]:  # type: ignore[empty-body]
    """Return :class:`~invphys.core.interfaces.Surrogate` subclasses."""


@hookspec
def invphys_register_latent_models() -> list[type]:  # type: ignore[empty-body]
    """Return :class:`~invphys.core.interfaces.LatentModel` subclasses."""


@hookspec
def invphys_register_optimizers() -> list[type]:  # type: ignore[empty-body]
    """Return :class:`~invphys.core.interfaces.Optimizer` subclasses."""


@hookspec
def invphys_register_validators() -> list[type]:  # type: ignore[empty-body]
    """Return :class:`~invphys.core.interfaces.Validator` subclasses."""


#: plugin kind -> the hook that registers it
HOOK_FOR_KIND: dict[str, str] = {
    "simulator": "invphys_register_simulators",
    "feature_extractor": "invphys_register_feature_extractors",
    "executor": "invphys_register_executors",
    "surrogate": "invphys_register_surrogates",
    "latent_model": "invphys_register_latent_models",
    "optimizer": "invphys_register_optimizers",
    "validator": "invphys_register_validators",
}
