"""invphys: inverse physics with non-differentiable simulators.

The public API is small:

* :data:`hookimpl` - decorate ``invphys_register_*`` functions in a plugin module;
* :mod:`invphys.registry` - look plugins up by kind and name (``registry.get("optimizer", "cma_es")``);
* :class:`~invphys.core.params.ParameterSpace`, :func:`~invphys.core.objectives.recovery_reward`;
* :func:`load_spec` and :func:`run` - validate and run a YAML experiment spec;
* :func:`load_inverter` - load a trained inverter bundle and answer targets with parameters.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from invphys.core.hookspecs import hookimpl
from invphys.core.objectives import recovery_reward
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.spec_lookup import install_default
from invphys.core.version import __version__
from invphys.plugins.simulators.from_function import simulator_from_function

__all__ = ["Parameter", "ParameterSpace", "__version__", "hookimpl", "load_inverter", "load_spec", "recovery_reward",
           "run", "simulator_from_function"]

if TYPE_CHECKING:
    from pathlib import Path

    from invphys.core.spec import ExperimentSpec
    from invphys.inverter import Inverter
    from invphys.registry import Registry


def _default_registry() -> Registry:
    """The process's plugin registry, imported on first use."""
    from invphys.registry import default_registry

    return default_registry()


install_default(_default_registry)  # the spec checks (in core, below the registry) look plugins up here


def load_spec(path: str | Path) -> ExperimentSpec:
    """Load and fully validate a YAML experiment spec (raises :class:`~invphys.core.errors.SpecError`)."""
    from invphys.core.spec import load_spec as _load

    return _load(path)


def run(spec: str | Path | ExperimentSpec, out: str | Path, **kwargs: Any) -> dict[str, Any]:
    """Run the stages a spec names, caching artifacts under ``out``; returns the stage summaries."""
    from invphys.pipeline.runner import run_spec

    return run_spec(spec, out, **kwargs)


def load_inverter(path: str | Path, strict: bool = True, threads: int | None = 1) -> Inverter:
    """Load an inverter bundle (e.g. ``inverters/orange_peel_paper`` or a run's ``OUT/inverter``).

    Checks its format, file hashes, and the installed simulator's version and features (``strict=False``
    turns a mismatch into a warning); ``threads``: BLAS threads while inverting batches (None: leave).
    ``inv.invert(target)`` then answers a target (a mapping of feature names to values) with an
    :class:`~invphys.inverter.InversionResult`.
    """
    from invphys.inverter import load_inverter as _load

    return _load(path, strict=strict, threads=threads)
