"""The built-in plugins, registered through the same hooks a third-party distribution uses.

invphys's ``pyproject.toml`` names this module in the ``invphys`` entry-point group, as a plugin
distribution would; the registry finds it there and imports nothing of ``invphys.plugins`` itself.

Each hook imports only the light package ``__init__`` that lists its classes; the classes import
their heavy dependencies (torch, cma, stable-baselines3, ...) inside their methods.
"""

from __future__ import annotations

from invphys.core.hookspecs import hookimpl


@hookimpl
def invphys_register_executors() -> list[type]:
    from invphys.plugins.executors import EXECUTORS

    return list(EXECUTORS)


@hookimpl
def invphys_register_surrogates() -> list[type]:
    from invphys.plugins.surrogates import SURROGATES

    return list(SURROGATES)


@hookimpl
def invphys_register_latent_models() -> list[type]:
    from invphys.plugins.latents import LATENT_MODELS

    return list(LATENT_MODELS)


@hookimpl
def invphys_register_optimizers() -> list[type]:
    from invphys.plugins.baselines import BASELINES
    from invphys.plugins.optimizers import OPTIMIZERS

    return [*OPTIMIZERS, *BASELINES]


@hookimpl
def invphys_register_validators() -> list[type]:
    from invphys.plugins.validators import VALIDATORS

    return list(VALIDATORS)


@hookimpl
def invphys_plugin_for_callable(kind: str, obj: object, path: str) -> type:
    """The plugin class a Python function named by ``path`` ("module:function") gives (the registry's
    escape hatch for functions: :func:`invphys.plugins.simulators.function.plugin_for_callable`)."""
    from invphys.plugins.simulators.function import plugin_for_callable

    return plugin_for_callable(kind, obj, path)
