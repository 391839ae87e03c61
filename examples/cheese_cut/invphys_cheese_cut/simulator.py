"""The ``cheese_cut`` simulator plugin: a wire cutting a block of cheese (AnisoMPM engine, batched)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator

from invphys.core.interfaces import PluginConfig, Simulator
from invphys.core.params import ParameterSpace
from invphys.core.results import Rendering, RunStats, SimulationResult, TimeSeries, Trajectory
from invphys_cheese_cut import SIMULATOR_VERSION
from invphys_cheese_cut.parameters import parameter_space
from invphys_cheese_cut.presets import PRESETS, Preset, get_preset
from invphys_cheese_cut.scene import GAP, build_scene, model_for

#: the time series every ok run carries: name -> (unit, description)
SERIES: dict[str, tuple[str, str]] = {
    "wire_force": ("N", "vertical force of the cheese on the wire (up is positive), mean over each frame"),
    "wire_drag": ("N", "force of the cheese on the wire along its axis, against its slide (friction drag)"),
    "wire_depth": ("m", "depth of the wire's bottom below the block's initial top surface"),
    "wire_work": ("J", "work done by the wire on the cheese since frame 0"),
    "board_force": ("N", "load of the cheese on the board (down is positive)"),
    "mean_damage": ("", "mean damage of the cheese's particles"),
    "damaged_fraction": ("", "soft fraction of broken particles (damage above ~0.5)"),
    "column_drop": ("m", "mean downward displacement of the cheese within two wire radii of the cut plane"),
    "sag": ("m", "height of the block's centroid relative to its unloaded start (negative: lower)"),
}


class CheeseCutSimulator(Simulator):
    """A block of cheese on a board cut by a wire pressed down and slid along its axis (a wire-cutting test).

    Each row of ``params`` is one run (7 parameters, physical units: E, nu, rho, fracture_stretch, eta,
    residual, friction). Runs are sorted by cost and advanced ``batch_size`` at a time by the
    ``invphys-anisompm`` engine. Each result carries the series of :data:`SERIES` (every frame) and the
    particle frames every ``record_every`` frames.
    """

    name: ClassVar[str] = "cheese_cut"
    version: ClassVar[str] = SIMULATOR_VERSION
    #: continuous batching changes how runs share the device, not their results (particle states are
    #: identical; force and work sums agree to float32 rounding), so it does not enter the config hash
    identity_ignores: ClassVar[tuple[str, ...]] = ("scheduling",)

    class Config(PluginConfig):
        """Settings of the cheese-cut simulator."""

        backend: Literal["taichi", "warp"] = Field("taichi", description="compute backend of the engine")
        preset: str = Field("quick", description="scene resolution: full, quick or tiny")
        arch: Literal["cpu", "cuda", "auto"] = Field("auto", description="device; auto = CUDA if present")
        allow_cpu_fallback: bool = Field(False, description="run on CPU when CUDA is asked for but absent")
        batch_size: int = Field(16, ge=1, le=4096, description="runs advanced together by one launch")
        record_every: int | None = Field(None, ge=1, description="frame stride of particle frames "
                                                                 "(default: the preset's)")
        cfl: float = Field(0.4, gt=0, le=10, description="elastic-wave CFL number")
        velocity_cfl: float = Field(0.3, gt=0, le=10, description="particle-velocity CFL number")
        eta_dt_factor: float = Field(0.1, gt=0, le=10, description="dt <= this * eta: damage resolved in time")
        max_substeps_per_frame: int = Field(4000, ge=1, description="more than this fails the run")
        damage: bool = Field(True, description="evolve the phase-field damage")
        deterministic: bool = Field(True, description="serialise CPU scatter so runs repeat bit-for-bit")
        scheduling: Literal["lockstep", "continuous"] = Field(
            "lockstep", description="lockstep: batches of similar cost run together until the slowest ends; "
                                    "continuous: batch_size slots stay full, a finished run's slot takes the "
                                    "next run at once (results stream out as runs finish)")

        @field_validator("preset")
        @classmethod
        def _known_preset(cls, value: str) -> str:
            if value not in PRESETS:
                get_preset(value)
            return value

    def __init__(self, config: PluginConfig | dict[str, Any] | None = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._scene = None
        self._engine = None

    def parameter_space(self) -> ParameterSpace:
        return parameter_space()

    def default_feature_extractor(self) -> str | None:
        return "cheese_cut_features"

    @property
    def preset(self) -> Preset:
        return get_preset(self.config.preset)

    @property
    def scene(self):
        if self._scene is None:
            c = self.config
            self._scene = build_scene(self.preset, cfl=c.cfl, velocity_cfl=c.velocity_cfl,
                                      eta_dt_factor=c.eta_dt_factor, max_substeps_per_frame=c.max_substeps_per_frame,
                                      damage=c.damage, deterministic=c.deterministic)
        return self._scene

    @property
    def engine(self):
        if self._engine is None:
            from invphys_anisompm import Engine

            self._engine = Engine(self.scene, backend=self.config.backend, arch=self.config.arch,
                                  allow_cpu_fallback=self.config.allow_cpu_fallback)
        return self._engine

    @property
    def record_every(self) -> int:
        return self.config.record_every or self.preset.record_every

    @property
    def native_stream(self) -> bool:  # type: ignore[override]
        return self.config.scheduling == "continuous"

    def simulate(self, params: np.ndarray,
                 on_result: Callable[[int, SimulationResult], None] | None = None) -> list[SimulationResult]:
        """Simulate each row of ``params`` (B, 7); see :meth:`Simulator.simulate`."""
        x = self._check(params)
        results: list[SimulationResult | None] = [None] * len(x)

        def done(i: int, rec: Any) -> None:
            results[i] = res = self._finished(x[i], rec)
            if on_result is not None:
                on_result(i, res)

        if self.config.scheduling == "continuous":
            for i, rec in self.engine.stream(model_for(self.scene, x), self.preset.frames, self.record_every,
                                             self.config.batch_size):
                done(i, rec)
        else:
            self.engine.run_batched(model_for(self.scene, x), self.preset.frames, self.record_every,
                                    self.config.batch_size, on_result=done)
        return [r for r in results if r is not None]

    def simulate_stream(self, params: np.ndarray, batch_size: int | None = None):
        """Yield ``(i, result)`` as runs finish: continuous batching over every row, ``batch_size`` (default:
        the config's) slots kept full on the warm engine, whatever ``scheduling`` says."""
        x = self._check(params)
        for i, rec in self.engine.stream(model_for(self.scene, x), self.preset.frames, self.record_every,
                                         int(batch_size or self.config.batch_size)):
            yield i, self._finished(x[i], rec)

    def estimate_cost(self, params: np.ndarray) -> np.ndarray:
        """Each run's estimated substeps: host arithmetic, no kernels."""
        return self.engine.estimate_cost(model_for(self.scene, self._check(params)), self.preset.frames)

    def _check(self, params: np.ndarray) -> np.ndarray:
        space = self.parameter_space()
        return space.check(np.atleast_2d(np.asarray(params, dtype=np.float64))).reshape(-1, space.dim)

    def _finished(self, params: np.ndarray, rec: Any) -> SimulationResult:
        stats = RunStats(substeps=rec.substeps + rec.settle_substeps, wall_time_s=rec.wall_time_s,
                         backend=self.config.backend, device=self.engine.device, preset=self.preset.name,
                         simulator=self.name, simulator_version=self.version)
        return self._result(params, rec, stats)

    def _result(self, params: np.ndarray, rec: Any, stats: RunStats) -> SimulationResult:
        if rec.failure is not None:
            return SimulationResult(params=params, ok=False, stats=stats, failure=rec.failure)
        scene, p = self.scene, self.preset
        n = len(rec.series["max_speed"])
        times = np.arange(n) / p.fps
        centroid_y = rec.series_array("centroid/cheese")[:, 1]
        values = {
            "wire_force": rec.series_array("force/wire")[:, 1],
            "wire_drag": -rec.series_array("force/wire")[:, 2],
            "wire_depth": -rec.series_array("position/wire")[:, 1] - GAP,
            "wire_work": rec.series_array("work/wire"),
            "board_force": -rec.series_array("force/board")[:, 1],
            "mean_damage": rec.series_array("mean_damage/cheese"),
            "damaged_fraction": rec.series_array("damaged_fraction"),
            "column_drop": rec.series_array("column_drop"),
            "sag": centroid_y - float(scene.positions[:, 1].mean()),
        }
        series = {k: TimeSeries(times=times, values=v, unit=SERIES[k][0], description=SERIES[k][1])
                  for k, v in values.items()}
        info = scene.info
        traj = Trajectory(
            series=series,
            positions=np.stack(rec.positions).astype(np.float32),
            damage=np.stack(rec.damage).astype(np.float32),
            labels=np.zeros(scene.n_particles, np.int8),
            frame_indices=np.asarray(rec.frames, dtype=np.int64),
            fps=p.fps,
            extra={"dx": p.dx, "wire_radius": p.wire_radius, "wire_start_y": info["start_y"],
                   "centre_x": info["centre_x"], "top": info["top"], "preset": p.name, "dt": rec.dt,
                   "settle_substeps": rec.settle_substeps, "guard_frames": rec.guard_frames},
        )
        return SimulationResult(params=params, ok=True, stats=stats, trajectory=traj)

    def render(self, trajectory: Trajectory, path: str | Path, *, max_frames: int = 60, animation: str = "gif",
               **options: Any) -> Rendering:
        """Side views (x-y, the cut plane) coloured by damage with the wire drawn, plus the force-depth
        curve; see :func:`invphys_cheese_cut.render.render_cut`."""
        from invphys_cheese_cut.render import render_cut

        return render_cut(trajectory, path, max_frames=max_frames, animation=animation, **options)
