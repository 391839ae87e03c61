"""The ``orange_peel`` simulator plugin: batched AnisoMPM orange peeling on the ``invphys-anisompm`` engine."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

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
from invphys.core.results import RunStats, SimulationResult, TimeSeries, Trajectory
from invphys_orange_peel import SIMULATOR_VERSION
from invphys_orange_peel.engine_scene import (
    GRIPPER,
    INTERIOR_BODY,
    SKIN_BODY,
    OrangeScene,
    build_orange_scene,
    model_for,
)
from invphys_orange_peel.parameters import parameter_space
from invphys_orange_peel.presets import PRESETS, Preset, get_preset
from invphys_orange_peel.scene import Scene, build_scene

#: default gravity (m/s^2); see docs/orange-peel/physics.md for why it is not -9.81
GRAVITY = -0.3

#: the time series every ok run carries (every frame 0..frames): name -> (unit, description)
SERIES: dict[str, tuple[str, str]] = {
    "separation": ("m", "distance between the skin's and the interior's centroids"),
    "mean_damage": ("", "mean damage of all particles"),
    "gripper_work": ("J", "work done by the gripper on the orange since frame 0"),
    "gripper_force": ("N", "magnitude of the orange's mean force on the gripper over each frame"),
    "max_speed": ("m/s", "peak particle speed"),
    "kinetic_energy": ("J", "kinetic energy of all particles"),
}


class OrangeEngine(EngineSettings):
    """The engine's settings of the orange peel (its ``engine:`` block): the common ones with this food's
    defaults, and the scheduling and kernel knobs it tunes for GPUs."""

    batch_size: int | None = Field(None, ge=1, le=4096,
                                   description="runs advanced together by one launch (slots); None = 64 for "
                                               "Taichi on CUDA, else 16")
    min_substeps_per_frame: int = Field(4, ge=1, description="dt cap: at least this many substeps/frame")
    max_substeps_per_frame: int = Field(2000, ge=1, description="more than this fails the run")
    eta_dt_factor: float = Field(0.1, gt=0, le=1e6, description="dt <= this * min(eta_s, eta_i): damage "
                                                                "resolved in time")
    l0_cells: float = Field(0.5, gt=0, le=4, description="phase-field length scale l0 in grid cells")
    apic_blend: float = Field(0.0, ge=0, le=1, description="0 = PIC (damped), 1 = APIC")
    energy_factor: float = Field(4.0, gt=0, description="kinetic-energy blow-up bound factor")
    scheduling: Literal["auto", "lockstep", "continuous"] = Field(
        "auto", description="lockstep: batches of similar cost run together until the slowest ends; "
                            "continuous: batch_size slots stay full, a finished run's slot takes the "
                            "next run at once (results stream out as runs finish); auto = continuous for "
                            "Taichi on CUDA (768-run datasets 1.08x faster on an H100), else lockstep")
    queue_order: Literal["longest_first", "given"] = Field(
        "longest_first", description="continuous: order in which free slots take runs; longest_first "
                                     "starts the costliest (estimated substeps) of each window of 8 runs per "
                                     "slot at once, windows in row order (a time-limited session has run "
                                     "about the first rows), given keeps row order (results and their row "
                                     "indices are the same either way)")
    min_chunk: int | None = Field(None, ge=1, le=4096,
                                  description="continuous: fewest substeps per host round trip (larger: fewer "
                                              "round trips, slots idle past their frame end); None = 64 for "
                                              "Taichi on CUDA, else 1")
    warp_graphs: bool | None = Field(None, description="Warp on CUDA: replay substeps as CUDA graphs "
                                                       "(None: on for CUDA)")
    gpu_deterministic: bool = Field(False, description="Warp on CUDA: deterministic scatter atomics "
                                                       "(slower; runs repeat bit for bit)")
    taichi_p2g: Literal["auto", "atomic", "tiled"] = Field(
        "auto", description="Taichi scatter: atomic (global float atomics), tiled (CUDA only: tiles of "
                            "particles summed in shared memory first; 1.25x faster runs), auto = tiled on "
                            "CUDA, atomic on the CPU")
    taichi_g2p: Literal["auto", "unrolled", "loop"] = Field(
        "auto", description="Taichi g2p: 27 nodes unrolled, or loops over two axes (half the registers; "
                            "1.23x faster kernel on an H100), auto = loop on CUDA, unrolled on the CPU")
    taichi_resort_every: int | None = Field(
        None, ge=0, description="Taichi: substeps between re-sorts of each run's particles into the curve "
                                "order of their current cells (keeps the tiled scatter's tiles compact as "
                                "the orange tears); 0 = never, None = 128 with the tiled scatter, else never")
    taichi_fused: bool = Field(
        False, description="Taichi: one G2P2G kernel per substep (each particle's g2p, then its scatter into a "
                           "second grid buffer) and one grid kernel (update and the other buffer's clear), "
                           "instead of clear, p2g, grid update and g2p; results agree to float rounding")


class OrangePeelSimulator(EngineSimulator):
    """Half an orange peeled by a gripper along a fixed arc, simulated with AnisoMPM-style MPM.

    Each row of ``params`` is one run (9 parameters of paper Table 1, physical units). The scene is an
    ``invphys-anisompm`` engine scene (:mod:`invphys_orange_peel.engine_scene`); runs are sorted by cost
    and advanced ``batch_size`` at a time (or, with ``scheduling: continuous``, ``batch_size`` slots kept
    full), one kernel launch per substep for the whole batch. Each result carries a :class:`Trajectory`
    of every ``record_every``-th frame (labels 0 = skin, 1 = interior) and the series of :data:`SERIES`.
    """

    name: ClassVar[str] = "orange_peel"
    version: ClassVar[str] = SIMULATOR_VERSION
    #: settings that change where or how fast runs go, not their results: left out of a run's stored identity
    identity_ignores: ClassVar[tuple[str, ...]] = ("arch", "allow_cpu_fallback", "batch_size", "deterministic",
                                                   "scheduling", "warp_graphs", "gpu_deterministic",
                                                   "queue_order", "min_chunk", "taichi_p2g",
                                                   "taichi_g2p", "taichi_resort_every", "taichi_fused")

    class Config(OrangeEngine, EngineSimulatorConfig):
        """Settings of the orange-peel simulator; the engine's may also be given as one ``engine:`` block."""

        engine: OrangeEngine | None = Field(None, exclude=True, description=ENGINE_BLOCK_HELP)  # type: ignore[assignment]
        preset: str = Field("quick", description="scene resolution: paper, quick or tiny")
        record_every: int | None = Field(None, ge=1, description="frame stride of trajectories "
                                                                 "(default: the preset's)")
        frames: int | None = Field(None, ge=1, description="override the preset's frame count")
        gravity: float = Field(GRAVITY, le=0, description="vertical gravity in m/s^2 (<= 0)")
        settle_seconds: float = Field(0.5, ge=0, le=10, description="gravity-only settling before frame 0 "
                                                                    "(gripper at rest, damage frozen)")
        gripper: bool = Field(True, description="drive the gripper (False: no load at all)")

        @field_validator("preset")
        @classmethod
        def _known_preset(cls, value: str) -> str:
            if value not in PRESETS:
                get_preset(value)  # raises UnknownPresetError with a did-you-mean
            return value

    def __init__(self, config: PluginConfig | dict[str, Any] | None = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._scene: Scene | None = None
        self._scene_separation: float | None = None
        self._engine_scene: OrangeScene | None = None
        self._cuda_probed: bool | None = None   # arch "auto": whether a CUDA GPU was found (probed once)

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
        """The orange's geometry (particles in the orange's order, labels, fibres, gripped patch, arc)."""
        if self._scene is None:
            self._scene = build_scene(self.preset)
        return self._scene

    @property
    def scene_separation(self) -> float:
        """:meth:`Scene.separation` of :attr:`scene` (every run's features' baseline), computed once."""
        if self._scene_separation is None:
            self._scene_separation = self.scene.separation()
        return self._scene_separation

    @property
    def engine_scene(self) -> OrangeScene:
        """The engine scene built from :attr:`scene` and the config."""
        if self._engine_scene is None:
            self._engine_scene = build_orange_scene(self.scene, self.engine_options(), gripper=self.config.gripper)
        return self._engine_scene

    @property
    def on_cuda(self) -> bool:
        """Whether runs go to a CUDA GPU (``arch: auto``, or ``cuda`` with a CPU fallback, resolved by probing,
        without starting the engine)."""
        c = self.config
        if c.arch == "cpu" or (c.arch == "cuda" and not c.allow_cpu_fallback):
            return c.arch == "cuda"
        if self._cuda_probed is None:
            from invphys_anisompm.backends import quiet_library

            with quiet_library():  # the libraries' start-up banners: hidden unless INVPHYS_DEBUG=1
                if c.backend == "warp":
                    from invphys_anisompm.backends.warp_backend import cuda_available
                else:
                    from invphys_anisompm.backends.taichi_backend import cuda_available
                self._cuda_probed = bool(cuda_available())
        return self._cuda_probed

    @property
    def scheduling(self) -> str:
        """The scheduling in use: the config's, ``auto`` resolved (continuous for Taichi on CUDA)."""
        c = self.config
        if c.scheduling != "auto":
            return c.scheduling
        return "continuous" if self._taichi_on_cuda else "lockstep"

    @property
    def min_chunk(self) -> int:
        """Continuous batching's fewest substeps per host round trip: the config's, else 64 for Taichi on CUDA
        (longer than most paper-preset frames, so a chunk runs until every slot's frame ends: half the round
        trips of 16 and 512-run streams 2.5-3.5 % faster on an H100), else 1."""
        return self.config.min_chunk or (64 if self._taichi_on_cuda else 1)

    @property
    def batch_size(self) -> int:
        """Runs advanced together: the config's, else 64 for Taichi on CUDA (a 768-run dataset on an H100:
        196.5 s with 64, 189.9 s with 128), else 16."""
        return self.config.batch_size or (64 if self._taichi_on_cuda else 16)

    @property
    def _taichi_on_cuda(self) -> bool:
        """The case the ``auto`` defaults were measured for: the Taichi backend on a CUDA GPU."""
        return self.config.backend == "taichi" and self.on_cuda

    def engine_options(self) -> Any:
        """The engine's :class:`~invphys_anisompm.EngineOptions` of this config (no settling damping: the
        orange settles under gravity alone; the gripper is slow, so no kinematic CFL bound applies)."""
        from invphys_anisompm import EngineOptions

        c, p = self.config, self.preset
        return EngineOptions(dx=self.scene.dx, grid=p.grid, fps=p.fps, gravity=c.gravity,
                             settle_seconds=c.settle_seconds, cfl=c.cfl, velocity_cfl=c.velocity_cfl,
                             min_substeps_per_frame=c.min_substeps_per_frame,
                             max_substeps_per_frame=c.max_substeps_per_frame, eta_dt_factor=c.eta_dt_factor,
                             kinematic_cfl=1e9, apic_blend=c.apic_blend, l0_cells=c.l0_cells,
                             damage=c.damage, deterministic=c.deterministic, energy_factor=c.energy_factor)

    # -- the engine's hooks -----------------------------------------------------------------------
    def build_engine_scene(self) -> Any:
        return self.engine_scene.engine

    def model_for_params(self, x: np.ndarray) -> Any:
        return model_for(self.engine_scene, x)

    def backend_options(self) -> dict[str, Any]:
        c = self.config
        if c.backend == "warp":
            return {"use_graphs": c.warp_graphs, "gpu_deterministic": c.gpu_deterministic}
        return {"p2g": c.taichi_p2g, "g2p": c.taichi_g2p, "resort_every": c.taichi_resort_every,
                "fused": c.taichi_fused}

    def stream_options(self) -> dict[str, Any]:
        return {"min_chunk": self.min_chunk, "queue_order": self.config.queue_order}

    def record_result(self, params: np.ndarray, rec: Any, stats: RunStats) -> SimulationResult:
        return SimulationResult(params=params, ok=True, stats=stats, trajectory=self._trajectory(rec))

    def _trajectory(self, rec: Any) -> Trajectory:
        scene, es = self.scene, self.engine_scene
        counts = {b.name: b.count for b in es.engine.bodies}
        n_all = sum(counts.values())
        separation = np.linalg.norm(rec.series_array(f"centroid/{SKIN_BODY}")
                                    - rec.series_array(f"centroid/{INTERIOR_BODY}"), axis=1)
        mean_damage = (rec.series_array(f"mean_damage/{SKIN_BODY}") * counts[SKIN_BODY]
                       + rec.series_array(f"mean_damage/{INTERIOR_BODY}") * counts[INTERIOR_BODY]) / n_all
        n = len(separation)
        if self.config.gripper:
            work = rec.series_array(f"work/{GRIPPER}")
            force = np.linalg.norm(rec.series_array(f"force/{GRIPPER}"), axis=1)
        else:
            work, force = np.zeros(n), np.zeros(n)
        values = {"separation": separation, "mean_damage": mean_damage, "gripper_work": work,
                  "gripper_force": force, "max_speed": rec.series_array("max_speed"),
                  "kinetic_energy": rec.series_array("kinetic_energy")}
        fps = self.preset.fps
        times = np.arange(n) / fps
        series = {k: TimeSeries(times=times, values=v, unit=SERIES[k][0], description=SERIES[k][1])
                  for k, v in values.items()}
        frames = np.asarray(rec.frames, dtype=np.int64)
        return Trajectory(
            series=series,
            positions=es.frames_in_orange_order(rec.positions),
            damage=es.frames_in_orange_order(rec.damage),
            labels=scene.labels.astype(np.int8),
            frame_indices=frames,
            fps=fps,
            extra={
                "gripper_path": scene.gripper_position(frames / fps).astype(np.float32),
                "gripped": scene.gripped.copy(),
                "dx": scene.dx, "radius": scene.radius, "skin_thickness": scene.skin_thickness,
                # skin-interior centroid distance of the built scene, before settling (final_separation's baseline)
                "scene_separation": self.scene_separation,
                "centre": scene.centre.copy(), "domain": scene.domain, "frames": self.frames,
                "record_every": self.record_every, "preset": self.preset.name,
                # frames 1..frames, as before the engine (frame 0 is the settled state)
                "max_speed": values["max_speed"][1:].astype(np.float32),
                "kinetic_energy": values["kinetic_energy"][1:].astype(np.float32),
                # every frame 0..frames (not only recorded ones): the smooth features read these
                "frame_separation": separation, "frame_mean_damage": mean_damage, "frame_work": work,
                "dt": rec.dt, "settle_substeps": rec.settle_substeps, "guard_frames": rec.guard_frames,
            },
        )

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
