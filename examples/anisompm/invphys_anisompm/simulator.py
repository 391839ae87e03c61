"""The base of every invphys simulator built on the engine (the orange peel, the cheese cut).

A food subclasses :class:`EngineSimulator` and gives its scene, its parameter-to-material map and its
result; the base owns the warm :class:`~invphys_anisompm.engine.Engine` and the batching (lockstep or
continuous). Its settings are :class:`EngineSimulatorConfig`: the engine's knobs (:class:`EngineSettings`,
which a food may extend) may be written flat or in one ``engine:`` block::

    simulator: {type: cheese_cut, preset: quick, engine: {backend: warp, arch: cuda, batch_size: 64}}

The canonical config is flat: ``engine:`` is folded into the flat fields when the config is validated
(a key given both ways takes the flat value, so a flat override such as ``--sim-option arch=cpu``
applies to a config written with ``engine:``) and is never part of the dump. The config hash a run's
stored identity holds is therefore the same whichever form a spec uses, and equal to that of the flat
configs recorded before the block existed.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from invphys.core.interfaces import PluginConfig, Simulator
from invphys.core.results import RunStats, SimulationResult

#: the description of a food's ``engine:`` field
ENGINE_BLOCK_HELP = ("the engine's settings as one block (the same keys may be given flat; a key given both "
                     "ways takes the flat value)")


class EngineSettings(PluginConfig):
    """The engine's knobs every engine simulator has (a food's ``engine:`` block; it may add its own)."""

    backend: Literal["taichi", "warp"] = Field("taichi", description="compute backend of the engine")
    arch: Literal["cpu", "cuda", "auto"] = Field("auto", description="device; auto = CUDA if present")
    allow_cpu_fallback: bool = Field(False, description="run on CPU when CUDA is asked for but absent")
    batch_size: int = Field(16, ge=1, le=4096, description="runs advanced together by one launch")
    scheduling: Literal["lockstep", "continuous"] = Field(
        "lockstep", description="lockstep: batches of similar cost run together until the slowest ends; "
                                "continuous: batch_size slots stay full, a finished run's slot takes the "
                                "next run at once (results stream out as runs finish)")
    cfl: float = Field(0.4, gt=0, le=10, description="elastic-wave CFL number")
    velocity_cfl: float = Field(0.3, gt=0, le=10, description="particle-velocity CFL number")
    eta_dt_factor: float = Field(0.1, gt=0, le=10, description="dt <= this * eta: damage resolved in time")
    max_substeps_per_frame: int = Field(4000, ge=1, description="more than this fails the run")
    damage: bool = Field(True, description="evolve the phase-field damage")
    deterministic: bool = Field(True, description="serialise CPU scatter so runs repeat bit-for-bit")


class EngineSimulatorConfig(EngineSettings):
    """A food's config: the engine's knobs (flat or under ``engine:``) and the food's own settings.

    A food declares ``engine: <its EngineSettings class> | None = Field(None, exclude=True,
    description=ENGINE_BLOCK_HELP)`` so that the block is checked field by field (errors name
    ``engine.<key>``) and stays out of the dump.
    """

    engine: EngineSettings | None = Field(None, exclude=True, description=ENGINE_BLOCK_HELP)

    @model_validator(mode="after")
    def _fold_engine_block(self) -> EngineSimulatorConfig:
        block = self.__dict__.get("engine")
        if block is None:
            return self
        given = set(self.model_fields_set)
        for name in block.model_fields_set:
            if name not in given:  # a flat key wins over the block's
                setattr(self, name, getattr(block, name))
        self.__dict__["engine"] = None
        return self

    @classmethod
    def engine_keys(cls) -> tuple[str, ...]:
        """The keys the ``engine:`` block takes."""
        block = cls.model_fields["engine"].annotation
        kinds = [t for t in getattr(block, "__args__", (block,)) if isinstance(t, type) and issubclass(t, EngineSettings)]
        return tuple(kinds[0].model_fields) if kinds else tuple(EngineSettings.model_fields)


class EngineSimulator(Simulator):
    """A :class:`Simulator` on the engine: a food gives :meth:`build_engine_scene`, :meth:`model_for_params`
    and :meth:`record_result` (and a ``preset`` with ``name``, ``frames`` and ``record_every``); the base
    checks parameters, keeps the engine warm and runs the batches."""

    Config: ClassVar[type[PluginConfig]] = EngineSimulatorConfig

    def __init__(self, config: PluginConfig | dict[str, Any] | None = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._engine: Any = None

    @classmethod
    def canonical_block(cls, block: dict[str, Any]) -> dict[str, Any]:
        """A spec block with its ``engine:`` block folded into flat keys (a flat key wins), unvalidated: the form
        whose stage keys equal those of a spec written flat (for a cache that hashes raw blocks)."""
        engine = block.get("engine")
        if not isinstance(engine, dict):
            return dict(block)
        flat = {k: v for k, v in block.items() if k != "engine"}
        return {**engine, **flat}

    # -- what a food gives ----------------------------------------------------------------------
    preset: Any  # the food's preset (name, frames, record_every, fps)

    def build_engine_scene(self) -> Any:
        """The engine :class:`~invphys_anisompm.scene.Scene` of this config."""
        raise NotImplementedError

    def model_for_params(self, x: np.ndarray) -> Any:
        """The :class:`~invphys_anisompm.model.Model` of checked parameter rows ``x`` (B, d)."""
        raise NotImplementedError

    def record_result(self, params: np.ndarray, rec: Any, stats: RunStats) -> SimulationResult:
        """The result of an ok or failed run record (``stats`` made by the base)."""
        raise NotImplementedError

    def backend_options(self) -> dict[str, Any]:
        """Extra keyword arguments of the backend (none by default)."""
        return {}

    def stream_options(self) -> dict[str, Any]:
        """Extra keyword arguments of :meth:`Engine.stream` (none by default)."""
        return {}

    # -- settings in use -----------------------------------------------------------------------
    @property
    def frames(self) -> int:
        return int(getattr(self.config, "frames", None) or self.preset.frames)

    @property
    def record_every(self) -> int:
        return int(getattr(self.config, "record_every", None) or self.preset.record_every)

    @property
    def batch_size(self) -> int:
        return int(self.config.batch_size)

    @property
    def scheduling(self) -> str:
        return str(self.config.scheduling)

    @property
    def native_stream(self) -> bool:  # type: ignore[override]
        return self.scheduling == "continuous"

    @property
    def engine(self) -> Any:
        """The warm :class:`invphys_anisompm.Engine` (kernels compiled and fields allocated once)."""
        if self._engine is None:
            from invphys_anisompm.engine import Engine

            c = self.config
            self._engine = Engine(self.build_engine_scene(), backend=c.backend, arch=c.arch,
                                  allow_cpu_fallback=c.allow_cpu_fallback, **self.backend_options())
        return self._engine

    # -- simulation ------------------------------------------------------------------------------
    def simulate(self, params: np.ndarray,
                 on_result: Callable[[int, SimulationResult], None] | None = None) -> list[SimulationResult]:
        """Simulate each row of ``params`` (B, d); see :meth:`Simulator.simulate`."""
        x = self._check(params)
        results: list[SimulationResult | None] = [None] * len(x)

        def done(i: int, rec: Any) -> None:
            results[i] = res = self.result_from_record(x[i], rec)
            if on_result is not None:
                on_result(i, res)

        model = self.model_for_params(x)
        if self.scheduling == "continuous":
            for i, rec in self._stream(model, self.batch_size):
                done(i, rec)
        else:
            self.engine.run_batched(model, self.frames, self.record_every, self.batch_size, on_result=done)
        return [r for r in results if r is not None]

    def simulate_stream(self, params: np.ndarray, batch_size: int | None = None
                        ) -> Iterator[tuple[int, SimulationResult]]:
        """Yield ``(i, result)`` as runs finish: continuous batching over every row, ``batch_size`` (default:
        the config's) slots kept full on the warm engine, whatever ``scheduling`` says."""
        x = self._check(params)
        for i, rec in self._stream(self.model_for_params(x), int(batch_size or self.batch_size)):
            yield i, self.result_from_record(x[i], rec)

    @property
    def native_feed(self) -> bool:  # type: ignore[override]
        return True

    def simulate_feed(self, feeder: Any, batch_size: int | None = None) -> Iterator[tuple[int, SimulationResult]]:
        """An open stream on the warm engine (:meth:`Engine.stream_feed`): ``feeder(free)`` gives new rows while
        other runs are in flight (nothing: none ready yet); yields ``(i, result)``, ``i`` counting fed rows."""
        fed: list[np.ndarray] = []

        def models(free: int) -> Any:
            rows = feeder(free)
            if rows is None or len(rows) == 0:
                return None
            x = self._check(np.asarray(rows, dtype=np.float64))
            fed.extend(x)
            return self.model_for_params(x)

        min_chunk = int(self.stream_options().get("min_chunk") or 1)
        for i, rec in self.engine.stream_feed(models, self.frames, self.record_every,
                                              int(batch_size or self.batch_size), min_chunk=min_chunk):
            yield i, self.result_from_record(fed[i], rec)

    def _stream(self, model: Any, batch_size: int) -> Iterator[tuple[int, Any]]:
        return self.engine.stream(model, self.frames, self.record_every, batch_size, **self.stream_options())

    def estimate_cost(self, params: np.ndarray) -> np.ndarray:
        """Each run's estimated substeps (settling included): host arithmetic, no kernels."""
        return self.engine.estimate_cost(self.model_for_params(self._check(params)), self.frames)

    def _check(self, params: np.ndarray) -> np.ndarray:
        space = self.parameter_space()
        return space.check(np.atleast_2d(np.asarray(params, dtype=np.float64))).reshape(-1, space.dim)

    def result_from_record(self, params: np.ndarray, rec: Any) -> SimulationResult:
        """The :class:`SimulationResult` of parameters ``params`` from the engine's run record (for callers
        that drive :attr:`engine` themselves, e.g. benchmarks timing a warm engine)."""
        stats = RunStats(substeps=rec.substeps + rec.settle_substeps, wall_time_s=rec.wall_time_s,
                         backend=self.config.backend, device=self.engine.device, preset=self.preset.name,
                         simulator=self.name, simulator_version=self.version)
        if rec.failure is not None:
            return SimulationResult(params=params, ok=False, stats=stats, failure=rec.failure)
        return self.record_result(params, rec, stats)


__all__ = ["ENGINE_BLOCK_HELP", "EngineSettings", "EngineSimulator", "EngineSimulatorConfig"]
