"""Named resolutions of the orange-peel scene: ``paper``, ``quick`` and ``tiny``.

Every preset simulates the same physical scene (an orange half of radius 0.15 m, 10 s of peeling);
presets differ in grid resolution, hence particle count and cost.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from invphys.core.errors import InvphysError, did_you_mean


class UnknownPresetError(InvphysError, ValueError):
    """A preset name that does not exist (a ValueError, so pydantic reports it at the `preset` field)."""


@dataclass(frozen=True)
class Preset:
    """One resolution of the scene.

    Attributes:
        name: preset name.
        grid: grid cells per side of the cubic domain.
        radius_cells: orange radius in grid cells (sets dx = orange_radius / radius_cells).
        skin_cells: skin thickness in grid cells.
        frames: number of simulated frames after the initial one.
        fps: frames per second (duration = frames / fps).
        record_every: default frame stride of recorded trajectories.
        description: what the preset is for.
    """

    name: str
    grid: int
    radius_cells: float
    skin_cells: float
    frames: int
    fps: float
    record_every: int
    description: str

    @property
    def duration(self) -> float:
        return self.frames / self.fps

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


#: physical radius of the orange half in metres (every preset)
ORANGE_RADIUS = 0.15

PRESETS: dict[str, Preset] = {
    "paper": Preset("paper", grid=64, radius_cells=14.5, skin_cells=2.0, frames=240, fps=24.0,
                    record_every=10, description="paper scale: ~51k particles, 240 frames (GPU)"),
    "quick": Preset("quick", grid=32, radius_cells=7.5, skin_cells=1.5, frames=240, fps=24.0,
                    record_every=10, description="quick start / CPU validation: ~7k particles"),
    "tiny": Preset("tiny", grid=24, radius_cells=5.0, skin_cells=1.5, frames=120, fps=12.0,
                   record_every=5, description="tests: ~2k particles, seconds on a CPU"),
}


def get_preset(name: str) -> Preset:
    """The preset called ``name``; unknown names raise :class:`UnknownPresetError` with a did-you-mean."""
    try:
        return PRESETS[name]
    except KeyError:
        raise UnknownPresetError(
            f"unknown orange-peel preset {name!r}.{did_you_mean(name, PRESETS)} "
            f"Presets: {', '.join(PRESETS)}"
        ) from None
