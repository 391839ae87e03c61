"""The ``cheese_cut`` simulator plugin: a wire cutting a block of cheese (AnisoMPM engine, batched)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from invphys_anisompm.simulator import (
    ENGINE_BLOCK_HELP,
    EngineSettings,
    EngineSimulator,
    EngineSimulatorConfig,
)
from pydantic import Field, field_validator

from invphys.core.interfaces import PluginConfig
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


class CheeseEngine(EngineSettings):
    """The engine's settings of the cheese cut (its ``engine:`` block): the common ones, as they were."""


class CheeseCutSimulator(EngineSimulator):
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

    class Config(CheeseEngine, EngineSimulatorConfig):
        """Settings of the cheese-cut simulator; the engine's may also be given as one ``engine:`` block."""

        engine: CheeseEngine | None = Field(None, exclude=True, description=ENGINE_BLOCK_HELP)  # type: ignore[assignment]
        preset: str = Field("quick", description="scene resolution: full, quick or tiny")
        record_every: int | None = Field(None, ge=1, description="frame stride of particle frames "
                                                                 "(default: the preset's)")

        @field_validator("preset")
        @classmethod
        def _known_preset(cls, value: str) -> str:
            if value not in PRESETS:
                get_preset(value)
            return value

    def __init__(self, config: PluginConfig | dict[str, Any] | None = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._scene = None

    def parameter_space(self) -> ParameterSpace:
        return parameter_space()

    def default_feature_extractor(self) -> str | None:
        return "cheese_cut_features"

    @property
    def preset(self) -> Preset:  # type: ignore[override]
        return get_preset(self.config.preset)

    @property
    def scene(self):
        """The engine scene of this config (built once)."""
        if self._scene is None:
            c = self.config
            self._scene = build_scene(self.preset, cfl=c.cfl, velocity_cfl=c.velocity_cfl,
                                      eta_dt_factor=c.eta_dt_factor, max_substeps_per_frame=c.max_substeps_per_frame,
                                      damage=c.damage, deterministic=c.deterministic)
        return self._scene

    def build_engine_scene(self) -> Any:
        return self.scene

    def model_for_params(self, x: np.ndarray) -> Any:
        return model_for(self.scene, x)

    def record_result(self, params: np.ndarray, rec: Any, stats: RunStats) -> SimulationResult:
        return self._result(params, rec, stats)

    def _finished(self, params: np.ndarray, rec: Any) -> SimulationResult:
        """The result of a run record (the name benchmarks use; :meth:`result_from_record`)."""
        return self.result_from_record(params, rec)

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
