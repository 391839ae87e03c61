"""``invphys.simulator_from_function``: a plain Python function becomes a registered simulator and feature
extractor (the classes: :mod:`invphys.plugins.simulators.function`, which imports only core; this module
registers them, so the registry, which finds functions through the other, never imports it)."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from invphys.plugins.simulators.function import FunctionPlugins

#: name -> the hook namespace registered for it (a second call with the same name replaces the first)
_REGISTERED: dict[str, object] = {}


def simulator_from_function(fn: Callable[..., Any], parameters: Any, features: Sequence[str] | Mapping[str, str],
                            *, units: Mapping[str, str] | None = None,
                            feature_units: Sequence[str] | Mapping[str, str] | None = None,
                            vectorised: bool | None = None, name: str | None = None, version: str | None = None,
                            description: str = "") -> FunctionPlugins:
    """Make ``fn`` a simulator with a matching feature extractor, registered as ``name`` (default ``fn``'s name).

    Args:
        fn: physical parameters in, features out: a batch ``(N, d) -> (N, M)`` when ``vectorised``, one
            row ``(d,) -> (M,)`` otherwise. A call that raises or returns non-finite values fails that run
            (a recorded failure with its reason), never the dataset.
        parameters: ``{name: (low, high)}`` in ``fn``'s order; a value may also be ``(low, high, unit)``,
            ``{"low", "high", "log", "unit", "description"}`` or a :class:`~invphys.core.params.Parameter`.
        features: the M output names, in order (or ``{name: unit}``).
        units: units by name, for parameters and features alike (``{"speed": "m/s", "range": "m"}``).
        feature_units: the features' units, one per feature or by name (the extractor's ``feature_units``).
        vectorised: True: ``fn`` takes a batch; False: one row per call; None: tried on the first batch
            (a batch call that returns ``(N, M)``), else row by row.
        name: the registered plugin name (a lower-case identifier).
        version: part of every stored run's identity; default: a hash of ``fn``'s source, so editing the
            function re-runs what depends on it (helpers it calls are not hashed: pass a version for them).
        description: one line for ``invphys plugins`` and docs (default: ``fn``'s docstring).

    Returns:
        ``(simulator_class, extractor_class)``; both are also attached to ``fn``, so a spec names them as
        ``simulator: {type: "module:function"}`` (any process that imports the module finds them) or, in
        this process, by ``name``.
    """
    from invphys import registry
    from invphys.core.errors import DuplicatePluginError, InvphysError
    from invphys.core.hookspecs import hookimpl
    from invphys.plugins.simulators.function import make_plugins

    pair = make_plugins(fn, parameters, features, units=units, feature_units=feature_units, vectorised=vectorised,
                        name=name, version=version, description=description)
    namespace = SimpleNamespace(
        invphys_register_simulators=hookimpl(lambda: [pair.simulator], specname="invphys_register_simulators"),
        invphys_register_feature_extractors=hookimpl(lambda: [pair.extractor],
                                                     specname="invphys_register_feature_extractors"))
    reg = registry.default_registry()
    previous = _REGISTERED.pop(pair.simulator.name, None)
    if previous is not None:
        reg.unregister(previous)
    reg.register(namespace, "<function>", "")
    try:
        reg.names("simulator")
    except DuplicatePluginError as exc:
        reg.unregister(namespace)
        raise InvphysError(f"{exc}: give the function simulator another name (name=...)") from None
    _REGISTERED[pair.simulator.name] = namespace
    return pair
