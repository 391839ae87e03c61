"""A plain Python function as a simulator: ``fn(theta) -> features``, with a matching feature extractor.

``fn`` takes physical parameters, either a batch (N, d) returning (N, M) (*vectorised*) or one row (d,)
returning (M,). :func:`make_plugins` builds a :class:`FunctionSimulator` subclass bound to ``fn`` and a
:class:`FunctionFeatures` subclass naming its M outputs, and attaches both to ``fn`` (attribute
``__invphys_plugins__``), so that a spec's ``simulator: {type: "module:function"}`` finds them through
the registry in any process that can import the module. A function without that attribute can still be
named in a spec when its block gives ``parameters:`` (and the spec's ``features:`` block, of the same
type, the outputs' ``names:``): :func:`plugin_for_callable`.

A call that raises, returns the wrong shape or non-finite values fails *that run* (``ok=False`` with a
reason), never the batch: a vectorised call that raises is repeated row by row to find the failing rows.
Imports only :mod:`invphys.core`.
"""

from __future__ import annotations

import hashlib
import inspect
import re
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import numpy as np
from pydantic import Field, field_validator

from invphys.core.errors import InvphysError, PluginLoadError
from invphys.core.interfaces import FeatureExtractor, PluginConfig, Simulator
from invphys.core.params import Parameter, ParameterSpace
from invphys.core.results import Rendering, RunStats, SimulationResult, Trajectory

ATTRIBUTE = "__invphys_plugins__"
SERIES = "features"  # the trajectory series holding the function's outputs (one sample at t = 0)
_NAME = re.compile(r"^[a-z_][a-z0-9_]*$")


class FunctionPlugins(NamedTuple):
    """What :func:`make_plugins` (and ``invphys.simulator_from_function``) return: two plugin classes."""

    simulator: type[FunctionSimulator]
    extractor: type[FunctionFeatures]


# ----------------------------------------------------------------------------------------------
# Descriptions
# ----------------------------------------------------------------------------------------------
def parameter_of(name: str, spec: Any, unit: str = "") -> Parameter:
    """A :class:`Parameter` from ``(low, high)``, ``(low, high, unit)``, a mapping ``{low, high, log,
    unit, description}`` or a Parameter; ``unit`` (from a ``units`` mapping) fills a missing unit."""
    try:
        if isinstance(spec, Parameter):
            fields = {"low": spec.low, "high": spec.high, "log": spec.log, "unit": spec.unit,
                      "description": spec.description}
        elif isinstance(spec, Mapping):
            unknown = set(spec) - {"low", "high", "log", "unit", "description"}
            if unknown:
                raise ValueError(f"unknown keys {sorted(unknown)} (low, high, log, unit, description)")
            fields = dict(spec)
        elif isinstance(spec, Sequence) and not isinstance(spec, str) and len(spec) in (2, 3):
            fields = {"low": spec[0], "high": spec[1], **({"unit": spec[2]} if len(spec) == 3 else {})}
        else:
            raise ValueError("give (low, high), (low, high, unit) or {low, high, log, unit, description}")
        fields.setdefault("unit", unit)
        if fields["unit"] != unit and unit:
            raise ValueError(f"unit {fields['unit']!r} here but {unit!r} in units")
        low, high = float(fields["low"]), float(fields["high"])  # type: ignore[arg-type]
        return Parameter(name, low, high, log=bool(fields.get("log", False)),
                         unit=str(fields["unit"] or ""), description=str(fields.get("description", "")))
    except (TypeError, ValueError, KeyError) as exc:
        raise InvphysError(f"parameter {name!r}: {exc}") from None


def space_of(parameters: Mapping[str, Any] | Sequence[Parameter] | ParameterSpace,
             units: Mapping[str, str] | None = None) -> ParameterSpace:
    """The :class:`ParameterSpace` of a ``{name: range spec}`` mapping (in order), Parameters or a space."""
    units = dict(units or {})
    if isinstance(parameters, ParameterSpace):
        parameters = parameters.parameters
    if isinstance(parameters, Mapping):
        items = list(parameters.items())
    else:
        items = [(p.name, p) for p in parameters]
    if not items:
        raise InvphysError("a function simulator needs at least one parameter")
    return ParameterSpace(tuple(parameter_of(str(n), s, units.get(str(n), "")) for n, s in items))


def features_of(features: Sequence[str] | Mapping[str, str], units: Mapping[str, str] | None = None,
                feature_units: Sequence[str] | Mapping[str, str] | None = None) -> tuple[list[str], list[str]]:
    """(names, units) of the features: ``features`` as names or ``{name: unit}``; units also from ``units``
    (by name) or ``feature_units`` (one per feature, or by name). The same unit given twice must agree."""
    names = [str(n) for n in features]
    if not names or isinstance(features, str):
        raise InvphysError("features must name at least one output, e.g. features=['range', 'apex']")
    if len(set(names)) != len(names):
        raise InvphysError(f"feature names repeat: {names}")
    sources: list[dict[str, str]] = [dict(features) if isinstance(features, Mapping) else {},
                                     {k: v for k, v in (units or {}).items() if k in names}]
    if isinstance(feature_units, Mapping):
        sources.append(dict(feature_units))
    elif feature_units is not None:
        if isinstance(feature_units, str) or len(feature_units) != len(names):
            raise InvphysError(f"feature_units needs one unit per feature ({len(names)}), got {feature_units!r}")
        sources.append(dict(zip(names, feature_units, strict=True)))
    out: dict[str, str] = {}
    for source in sources:
        for name, unit in source.items():
            if name not in names:
                raise InvphysError(f"a unit is given for {name!r}, which is not a feature ({', '.join(names)})")
            if out.get(name, unit or "") != (unit or "") and out.get(name):
                raise InvphysError(f"feature {name!r} has two units: {out[name]!r} and {unit!r}")
            out[name] = str(unit or out.get(name, ""))
    return names, [out.get(n, "") for n in names]


def source_version(fn: Callable[..., Any]) -> str:
    """``"src-<12 hex>"``: a hash of ``fn``'s source (or bytecode), so editing it changes runs' identity."""
    try:
        blob = inspect.getsource(fn).encode()
    except (OSError, TypeError):
        code = getattr(fn, "__code__", None)
        blob = repr((code.co_code, code.co_consts)).encode() if code is not None else repr(fn).encode()
    return "src-" + hashlib.sha256(blob).hexdigest()[:12]


def function_path(fn: Callable[..., Any]) -> str | None:
    """``"module:qualname"`` when another process can import ``fn`` by it, else None."""
    module, qual = getattr(fn, "__module__", None), getattr(fn, "__qualname__", "")
    if not module or module == "__main__" or "<" in qual:
        return None
    return f"{module}:{qual}"


# ----------------------------------------------------------------------------------------------
# The extractor
# ----------------------------------------------------------------------------------------------
class FunctionFeatures(FeatureExtractor):
    """The outputs of a function simulator, named: ``features: {type: "module:function", names: [...], units: ...}``.

    Reads the ``features`` series a :class:`FunctionSimulator` records (the function's M outputs) and
    checks that there are ``len(names)`` of them, all finite.
    """

    name: ClassVar[str] = "function_features"

    class Config(PluginConfig):
        """The names (in the function's output order) and units of the features."""

        names: list[str] = Field(..., min_length=1, description="the function's outputs, in order")
        units: dict[str, str] | list[str] = Field(default_factory=dict,
                                                  description="units by feature name, or one per feature")

        @field_validator("names")
        @classmethod
        def _unique(cls, v: list[str]) -> list[str]:
            if len(set(v)) != len(v):
                raise ValueError(f"feature names repeat: {v}")
            return v

    @property
    def feature_names(self) -> tuple[str, ...]:
        return tuple(self.config.names)

    @property
    def feature_units(self) -> tuple[str, ...]:
        return tuple(features_of(self.config.names, feature_units=self.config.units or None)[1])

    def extract(self, trajectory: Trajectory) -> np.ndarray:
        series = trajectory.series.get(SERIES)
        if series is None:
            raise InvphysError(f"the trajectory has no {SERIES!r} series: it was not made by a function simulator")
        y = np.asarray(series.values, dtype=np.float64).reshape(len(series), -1)[-1]
        if len(y) != len(self.config.names):
            raise InvphysError(f"the function returned {len(y)} values, the extractor names "
                               f"{len(self.config.names)} ({', '.join(self.config.names)})")
        if not np.isfinite(y).all():
            raise InvphysError("non-finite feature values")
        return y


# ----------------------------------------------------------------------------------------------
# The simulator
# ----------------------------------------------------------------------------------------------
class FunctionSimulator(Simulator):
    """Base of the simulators made from a Python function (:func:`make_plugins`, :func:`plugin_for_callable`).

    Each run's trajectory holds one series, ``features``: the function's M outputs at t = 0. A run whose
    call raised, or returned the wrong shape or a non-finite value, is ``ok=False`` with a reason.
    :meth:`render` draws the outputs as labelled bars.
    """

    name: ClassVar[str] = "function_simulator"
    #: ``"vectorised"`` only says how the function is called, not what it returns
    identity_ignores: ClassVar[tuple[str, ...]] = ("vectorised",)
    function: ClassVar[Callable[..., Any]]
    base_space: ClassVar[ParameterSpace | None] = None
    output_names: ClassVar[tuple[str, ...] | None] = None
    output_units: ClassVar[tuple[str, ...] | None] = None
    extractor_ref: ClassVar[str | None] = None

    class Config(PluginConfig):
        """How the function is called; its parameters when it was not described in Python."""

        parameters: dict[str, Any] | None = Field(
            None, description="name: [low, high], [low, high, unit] or {low, high, log, unit, description}, "
                              "in the function's order (default: as described in Python)")
        vectorised: bool | None = Field(
            None, description="true: fn takes (N, d) and returns (N, M); false: one row (d,) -> (M,); "
                              "null: tried on the first batch")

    def __init__(self, config: Any = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._space = space_of(self.config.parameters) if self.config.parameters else self.base_space
        if self._space is None:
            raise InvphysError(f"simulator {self.name!r} needs 'parameters' (name: [low, high], ...) in its block")
        self._vectorised: bool | None = self.config.vectorised

    def parameter_space(self) -> ParameterSpace:
        assert self._space is not None
        return self._space

    def default_feature_extractor(self) -> str | None:
        return self.extractor_ref

    def simulate(self, params: np.ndarray,
                 on_result: Callable[[int, SimulationResult], None] | None = None) -> list[SimulationResult]:
        p = np.atleast_2d(self.parameter_space().check(params))
        start = time.perf_counter()
        outputs = self._call(p)
        wall = (time.perf_counter() - start) / max(len(p), 1)
        results = []
        for i, (y, failure) in enumerate(outputs):
            stats = RunStats(wall_time_s=wall, backend="python", device="cpu", simulator=self.name,
                             simulator_version=str(self.version))
            if failure is None and not np.isfinite(y).all():
                bad = [self._label(int(j)) for j in np.flatnonzero(~np.isfinite(y))]
                failure = f"nan: non-finite output {', '.join(bad)}"
            if failure is not None:
                res = SimulationResult(params=p[i], ok=False, stats=stats, failure=failure)
            else:
                traj = Trajectory()
                traj.add_series(SERIES, np.zeros(1), y[None, :], description="the function's outputs")
                res = SimulationResult(params=p[i], ok=True, stats=stats, trajectory=traj)
            if on_result is not None:
                on_result(i, res)
            results.append(res)
        return results

    def render(self, trajectory: Trajectory, path: str | Path, *, max_frames: int = 60, animation: str = "gif",
               **options: Any) -> Rendering:
        """``outputs.png`` under ``path``: the function's outputs as labelled bars (there are no frames)."""
        if options:
            raise InvphysError(f"simulator {self.name!r} draws its outputs and takes no options "
                               f"(got {', '.join(sorted(options))})")
        if animation not in ("gif", "mp4", "none"):
            raise InvphysError(f"animation must be gif, mp4 or none, not {animation!r}")
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        y = np.asarray(trajectory.series[SERIES].values, dtype=np.float64).reshape(len(trajectory.series[SERIES]), -1)[-1]
        units = self.output_units or ("",) * len(y)
        labels = [f"{self._label(j)}" + (f" ({units[j]})" if j < len(units) and units[j] else "") for j in range(len(y))]
        out = Path(path)
        out.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(figsize=(5.0, 1.2 + 0.45 * len(y)))
        ax.barh(np.arange(len(y)), y, color="tab:blue")
        ax.set_yticks(np.arange(len(y)), labels, fontsize=8)
        ax.invert_yaxis()
        for j, v in enumerate(y):
            ax.annotate(f"{v:.4g}", (v, j), xytext=(3, 0), textcoords="offset points", va="center", fontsize=8)
        ax.set_title(f"{self.name}: outputs", fontsize=10)
        fig.tight_layout()
        image = out / "outputs.png"
        fig.savefig(image, dpi=90)
        plt.close(fig)
        return Rendering(images=[image])

    def _label(self, j: int) -> str:
        names = self.output_names
        return names[j] if names is not None and j < len(names) else f"#{j}"

    def _call(self, p: np.ndarray) -> list[tuple[np.ndarray, str | None]]:
        """One ``(outputs (M,), failure)`` per row: the whole batch in one call when vectorised.

        Undecided (``vectorised: null``), rows are tried one at a time, first as a (1, d) batch, then as a
        (d,) row, until one succeeds: that decides how the function is called from then on.
        """
        done: list[tuple[np.ndarray, str | None]] = []
        while self._vectorised is None and len(done) < len(p):
            done.append(self._probe(p[len(done)]))
        rest = p[len(done):]
        if not len(rest):
            return done
        if not self._vectorised:
            return done + [self._one(row, batch=False) for row in rest]
        try:
            y = self._check(self.function(rest.copy()), (len(rest),))
        except Exception as exc:
            if len(rest) == 1:
                return [*done, (np.empty(0), _reason(exc))]
            return done + [self._one(row[None, :], batch=True) for row in rest]  # find the failing rows
        return done + [(row, None) for row in y]

    def _probe(self, row: np.ndarray) -> tuple[np.ndarray, str | None]:
        y, failure = self._one(row[None, :], batch=True)
        if failure is None:
            self._vectorised = True
            return y, None
        y, as_row = self._one(row, batch=False)
        if as_row is None:
            self._vectorised = False
            return y, None
        return y, f"{failure} (called with a (1, d) batch; with a (d,) row: {as_row})"[:400]

    def _one(self, row: np.ndarray, batch: bool) -> tuple[np.ndarray, str | None]:
        try:
            y = self._check(self.function(row.copy()), (1,) if batch else ())
            return (y[0] if batch else y), None
        except Exception as exc:
            return np.empty(0), _reason(exc)

    def _check(self, out: Any, lead: tuple[int, ...]) -> np.ndarray:
        """``out`` as float64 with shape ``lead + (M,)`` (M = the named outputs' count when known)."""
        y = np.asarray(out, dtype=np.float64)
        m = len(self.output_names) if self.output_names is not None else None
        if y.ndim != len(lead) + 1 or y.shape[:len(lead)] != lead or (m is not None and y.shape[-1] != m):
            want = ", ".join([*map(str, lead), str(m) if m is not None else "M"])
            raise _OutputShape(f"output: the function returned shape {y.shape}, expected ({want})")
        return y


class _OutputShape(ValueError):
    """The function's result has the wrong shape."""


def _reason(exc: BaseException) -> str:
    if isinstance(exc, _OutputShape):
        return str(exc)
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"exception: {type(exc).__name__}{': ' + text if text else ''}"[:300]


# ----------------------------------------------------------------------------------------------
# Building and finding the classes
# ----------------------------------------------------------------------------------------------
def make_plugins(fn: Callable[..., Any], parameters: Any, features: Sequence[str] | Mapping[str, str], *,
                 units: Mapping[str, str] | None = None,
                 feature_units: Sequence[str] | Mapping[str, str] | None = None,
                 vectorised: bool | None = None, name: str | None = None, version: str | None = None,
                 description: str = "") -> FunctionPlugins:
    """A simulator and an extractor class for ``fn`` (see ``invphys.simulator_from_function``), attached to it."""
    if not callable(fn) or isinstance(fn, type):
        raise InvphysError(f"simulator_from_function needs a function, got {fn!r}")
    name = str(name or getattr(fn, "__name__", ""))
    if not _NAME.match(name):
        raise InvphysError(f"the simulator's name must be a lower-case identifier, got {name!r}: pass name=...")
    units = dict(units or {})
    space = space_of(parameters, units)
    names, funits = features_of(features, units, feature_units)
    unknown = set(units) - set(space.names) - set(names)
    if unknown:
        raise InvphysError(f"units for {sorted(unknown)}, which are neither parameters nor features")
    path, calls_batches = function_path(fn), vectorised
    doc = description or (inspect.getdoc(fn) or "").strip() or f"The Python function {name}."

    class Features(FunctionFeatures):
        class Config(FunctionFeatures.Config):
            names: list[str] = Field(default_factory=lambda: list(names), min_length=1,
                                     description="the function's outputs, in order")
            units: dict[str, str] | list[str] = Field(default_factory=lambda: dict(zip(names, funits, strict=True)),
                                                      description="units by feature name, or one per feature")

    class Sim(FunctionSimulator):
        class Config(FunctionSimulator.Config):
            vectorised: bool | None = Field(calls_batches, description=FunctionSimulator.Config.model_fields[
                "vectorised"].description)

    for cls, suffix in ((Sim, "Simulator"), (Features, "Features")):
        cls.name = name  # type: ignore[misc]
        cls.__doc__ = doc
        cls.__qualname__ = cls.__name__ = f"{name}_{suffix}"
    Sim.function = staticmethod(fn)  # type: ignore[assignment]
    Sim.version = str(version) if version is not None else source_version(fn)  # type: ignore[misc]
    Sim.base_space, Sim.output_names, Sim.extractor_ref = space, tuple(names), path or name
    Sim.output_units = tuple(funits)
    pair = FunctionPlugins(Sim, Features)
    try:
        setattr(fn, ATTRIBUTE, {"simulator": Sim, "feature_extractor": Features})
    except (AttributeError, TypeError):
        if path is not None:
            raise InvphysError(f"cannot attach the plugins to {fn!r}: wrap it in a def") from None
    return pair


_PLAIN: dict[tuple[str, int], type[FunctionSimulator]] = {}


def plugin_for_callable(kind: str, obj: Any, path: str) -> type:
    """The plugin class of ``kind`` that the function ``obj`` (found at ``path``, "module:function") gives.

    A function described in Python (``invphys.simulator_from_function``) gives its simulator and extractor.
    A plain function defined in that module gives a simulator whose block must hold ``parameters``, and an
    extractor whose block must hold the outputs' ``names`` (a spec's ``features: {type: "module:function",
    names: [...]}``).
    """
    attached = getattr(obj, ATTRIBUTE, None)
    if isinstance(attached, dict) and kind in attached:
        return attached[kind]
    module = path.partition(":")[0]
    if kind == "simulator" and inspect.isfunction(obj) and obj.__module__ == module:
        key = (path, id(obj))
        if key not in _PLAIN:
            cls = type(f"{obj.__name__}_Simulator", (FunctionSimulator,), {
                "__doc__": (inspect.getdoc(obj) or f"The Python function {path}.").strip(),
                "__module__": __name__, "name": obj.__name__.lower(), "function": staticmethod(obj),
                "version": source_version(obj)})
            _PLAIN[key] = cls
        return _PLAIN[key]
    if kind == "feature_extractor" and inspect.isfunction(obj) and obj.__module__ == module:
        return FunctionFeatures
    label = kind.replace("_", " ")
    raise PluginLoadError(f"{path!r} is a {type(obj).__name__}, not {'an' if label[0] in 'aeiou' else 'a'} {label} "
                          f"plugin class (or a function defined in {module!r} described as a simulator)")
