"""The ``orange_peel`` simulator plugin: batched AnisoMPM orange peeling (Taichi; Warp later)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, field_validator

from invphys.core.interfaces import PluginConfig, Simulator
from invphys.core.params import ParameterSpace
from invphys.core.results import RunStats, SimulationResult, Trajectory
from invphys_orange_peel import SIMULATOR_VERSION
from invphys_orange_peel.driver import RunRecord, StepSettings, estimated_substeps, run_batch
from invphys_orange_peel.material import materials_from_params
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.presets import PRESETS, Preset, get_preset
from invphys_orange_peel.scene import Scene, build_scene

#: default gravity (m/s^2); see docs/orange-peel/physics.md for why it is not -9.81
GRAVITY = -0.3


class OrangePeelSimulator(Simulator):
    """Half an orange peeled by a gripper along a fixed arc, simulated with AnisoMPM-style MPM.

    Each row of ``params`` is one run (9 parameters of paper Table 1, physical units). Runs are
    sorted by their elastic time step and advanced ``batch_size`` at a time, one kernel launch per
    substep for the whole batch. Each result carries a :class:`Trajectory` of every
    ``record_every``-th frame (labels 0 = skin, 1 = interior).
    """

    name: ClassVar[str] = "orange_peel"
    version: ClassVar[str] = SIMULATOR_VERSION
    #: settings that change where or how fast runs go, not their results: left out of a run's stored identity
    identity_ignores: ClassVar[tuple[str, ...]] = ("arch", "allow_cpu_fallback", "batch_size", "deterministic")

    class Config(PluginConfig):
        """Settings of the orange-peel simulator."""

        backend: Literal["taichi", "warp"] = Field("taichi", description="compute backend")
        preset: str = Field("quick", description="scene resolution: paper, quick or tiny")
        arch: Literal["cpu", "cuda", "auto"] = Field("auto", description="device; auto = CUDA if present")
        allow_cpu_fallback: bool = Field(False, description="run on CPU when CUDA is asked for but absent")
        batch_size: int = Field(16, ge=1, le=4096, description="runs advanced together by one launch")
        record_every: int | None = Field(None, ge=1, description="frame stride of trajectories "
                                                                 "(default: the preset's)")
        frames: int | None = Field(None, ge=1, description="override the preset's frame count")
        cfl: float = Field(0.4, gt=0, le=10, description="elastic-wave CFL number")
        velocity_cfl: float = Field(0.3, gt=0, le=10, description="particle-velocity CFL number")
        min_substeps_per_frame: int = Field(4, ge=1, description="dt cap: at least this many substeps/frame")
        max_substeps_per_frame: int = Field(2000, ge=1, description="more than this fails the run")
        eta_dt_factor: float = Field(0.1, gt=0, le=1e6, description="dt <= this * min(eta_s, eta_i): damage "
                                                                    "resolved in time")
        gravity: float = Field(GRAVITY, le=0, description="vertical gravity in m/s^2 (<= 0)")
        settle_seconds: float = Field(0.5, ge=0, le=10, description="gravity-only settling before frame 0 "
                                                                    "(gripper at rest, damage frozen)")
        l0_cells: float = Field(0.5, gt=0, le=4, description="phase-field length scale l0 in grid cells")
        apic_blend: float = Field(0.0, ge=0, le=1, description="0 = PIC (damped), 1 = APIC")
        gripper: bool = Field(True, description="drive the gripper (False: no load at all)")
        damage: bool = Field(True, description="evolve the phase-field damage")
        deterministic: bool = Field(True, description="serialise CPU scatter so runs repeat bit-for-bit")
        energy_factor: float = Field(4.0, gt=0, description="kinetic-energy blow-up bound factor")

        @field_validator("preset")
        @classmethod
        def _known_preset(cls, value: str) -> str:
            if value not in PRESETS:
                get_preset(value)  # raises UnknownPresetError with a did-you-mean
            return value

    def __init__(self, config: PluginConfig | dict[str, Any] | None = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._scene: Scene | None = None
        self._backends: dict[int, Any] = {}

    # -- description --------------------------------------------------------------------------
    def parameter_space(self) -> ParameterSpace:
        return parameter_space()

    def default_feature_extractor(self) -> str | None:
        return "orange_peel_features"

    @property
    def preset(self) -> Preset:
        return get_preset(self.config.preset)

    @property
    def scene(self) -> Scene:
        if self._scene is None:
            self._scene = build_scene(self.preset)
        return self._scene

    @property
    def frames(self) -> int:
        return self.config.frames or self.preset.frames

    @property
    def record_every(self) -> int:
        return self.config.record_every or self.preset.record_every

    def step_settings(self) -> StepSettings:
        c = self.config
        return StepSettings(cfl=c.cfl, velocity_cfl=c.velocity_cfl, min_substeps_per_frame=c.min_substeps_per_frame,
                            max_substeps_per_frame=c.max_substeps_per_frame, eta_dt_factor=c.eta_dt_factor,
                            gravity=c.gravity, settle_seconds=c.settle_seconds, l0_cells=c.l0_cells,
                            apic_blend=c.apic_blend, damage_on=c.damage, gripper_on=c.gripper,
                            deterministic=c.deterministic, energy_factor=c.energy_factor)

    def _backend(self, batch: int) -> Any:
        if batch not in self._backends:
            from invphys_orange_peel.backends import load_backend

            cls = load_backend(self.config.backend)
            self._backends[batch] = cls(self.scene, batch, self.step_settings(), arch=self.config.arch,
                                        allow_cpu_fallback=self.config.allow_cpu_fallback)
        return self._backends[batch]

    # -- simulation ---------------------------------------------------------------------------
    def simulate(self, params: np.ndarray,
                 on_result: Callable[[int, SimulationResult], None] | None = None) -> list[SimulationResult]:
        """Simulate each row of ``params`` (B, 9); see :class:`Simulator.simulate`."""
        x = self.parameter_space().check(np.atleast_2d(np.asarray(params, dtype=np.float64)))
        x = x.reshape(-1, self.parameter_space().dim)
        scene, settings = self.scene, self.step_settings()
        materials = materials_from_params(x)
        order = np.argsort(estimated_substeps(materials, scene, self.frames, self.preset.fps, settings),
                           kind="stable")
        results: list[SimulationResult | None] = [None] * len(x)
        bs = self.config.batch_size
        for start in range(0, len(order), bs):
            idx = order[start:start + bs]
            backend = self._backend(len(idx))
            records, wall = run_batch(backend, scene, materials.take(idx), self.frames, self.preset.fps,
                                      self.record_every, settings)
            for j, (row, rec) in enumerate(zip(idx, records, strict=True)):
                stats = RunStats(substeps=rec.substeps + rec.settle_substeps, wall_time_s=wall / len(idx),
                                 backend=self.config.backend, device=backend.device, preset=self.preset.name,
                                 simulator=self.name, simulator_version=self.version)
                res = self._result(x[row], rec, stats, batch_wall=wall, batch_size=len(idx), slot=j)
                results[row] = res
                if on_result is not None:
                    on_result(int(row), res)
        return [r for r in results if r is not None]

    def _result(self, params: np.ndarray, rec: RunRecord, stats: RunStats, **extra: Any) -> SimulationResult:
        if rec.failure is not None:
            return SimulationResult(params=params, ok=False, stats=stats, failure=rec.failure)
        scene = self.scene
        frames = np.asarray(rec.frames, dtype=np.int64)
        fps = self.preset.fps
        traj = Trajectory(
            positions=np.stack(rec.positions).astype(np.float32),
            damage=np.stack(rec.damage).astype(np.float32),
            labels=scene.labels.astype(np.int8),
            frame_indices=frames,
            fps=fps,
            extra={
                "gripper_path": scene.gripper_position(frames / fps).astype(np.float32),
                "gripped": scene.gripped.copy(),
                "dx": scene.dx, "radius": scene.radius, "skin_thickness": scene.skin_thickness,
                "centre": scene.centre.copy(), "domain": scene.domain, "frames": self.frames,
                "record_every": self.record_every, "preset": self.preset.name,
                "max_speed": np.asarray(rec.max_speed, np.float32),
                "kinetic_energy": np.asarray(rec.kinetic_energy, np.float32),
                # every frame 0..frames (not only recorded ones): the smooth features read these
                "frame_separation": np.asarray(rec.separation, np.float64),
                "frame_mean_damage": np.asarray(rec.mean_damage, np.float64),
                "frame_work": np.asarray(rec.work, np.float64),
                "dt": rec.dt, "settle_substeps": rec.settle_substeps, "guard_frames": rec.guard_frames,
                **extra,
            },
        )
        return SimulationResult(params=params, ok=True, stats=stats, trajectory=traj)

    # -- rendering ----------------------------------------------------------------------------
    def render(self, trajectory: Trajectory, path: Any, *, max_frames: int = 60, animation: str = "gif",
               **options: Any) -> Any:
        """Paper Fig. 3 colours from a fixed orthographic camera (:func:`invphys_orange_peel.render.render_trajectory`).

        Options: ``azim``, ``elev`` (degrees), ``ply`` (write ``.ply`` files), ``size`` ((w, h) pixels),
        ``fps`` (animation speed).
        """
        from pathlib import Path

        from invphys.core.errors import InvphysError
        from invphys.core.results import Rendering
        from invphys_orange_peel.render import render_trajectory

        unknown = sorted(set(options) - {"azim", "elev", "ply", "size", "fps"})
        if unknown:
            raise InvphysError(f"unknown orange-peel render option(s) {', '.join(unknown)} "
                               "(known: azim, elev, ply, size, fps)")
        res = render_trajectory(trajectory, path, max_frames=max_frames, animation=animation, **options)
        return Rendering(images=[Path(p) for p in res["frames"]], files=[Path(p) for p in res["ply"]],
                         animation=Path(res["animation"]) if res.get("animation") else None)
