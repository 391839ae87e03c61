"""Named resolutions of the cheese-cutting scene: ``full``, ``quick`` and ``tiny``.

``full`` and ``quick`` simulate the same physical test (a 60 x 40 x 20 mm block, a 4 mm-radius wire
pressed down at 0.2 m/s while sliding along its axis at 0.2 m/s); ``tiny`` (tests only) is coarser, its wire thicker (6 mm radius, so that it always covers a grid
node) and faster (0.4 m/s, half the simulated time).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from invphys.core.errors import InvphysError, did_you_mean


class UnknownPresetError(InvphysError, ValueError):
    """A preset name that does not exist."""


@dataclass(frozen=True)
class Preset:
    """One resolution of the scene.

    Attributes:
        name: preset name.
        dx: grid spacing (m); particles sit 2 per cell side (8 per cell).
        grid: grid cells per side of the cubic domain.
        wire_radius: radius of the wire (m).
        wire_speed: downward speed of the wire (m/s).
        slice_ratio: the wire also slides along its own axis (z) at ``slice_ratio * wire_speed`` (a
            press-and-slice cut; its drag along the wire measures friction).
        fps: frames per second.
        frames: frames after the settled frame 0.
        settle_seconds: gravity-only settling before frame 0.
        record_every: frame stride of recorded particle frames.
        description: what the preset is for.
    """

    name: str
    dx: float
    grid: int
    wire_radius: float
    wire_speed: float
    slice_ratio: float
    fps: float
    frames: int
    settle_seconds: float
    record_every: int
    description: str

    def to_dict(self) -> dict[str, object]:
        return asdict(self)


PRESETS: dict[str, Preset] = {
    "full": Preset("full", dx=0.0025, grid=45, wire_radius=0.004, wire_speed=0.2, slice_ratio=1.0, fps=100.0, frames=25,
                   settle_seconds=0.05, record_every=5, description="~25k particles (GPU)"),
    "quick": Preset("quick", dx=0.004, grid=28, wire_radius=0.004, wire_speed=0.2, slice_ratio=1.0, fps=100.0, frames=25,
                    settle_seconds=0.05, record_every=5, description="~6k particles: datasets (GPU), CPU checks"),
    "tiny": Preset("tiny", dx=0.008, grid=16, wire_radius=0.006, wire_speed=0.4, slice_ratio=1.0, fps=100.0, frames=12,
                   settle_seconds=0.05, record_every=4, description="tests: ~750 particles, seconds on a CPU"),
}


def get_preset(name: str) -> Preset:
    """The preset called ``name``; unknown names raise :class:`UnknownPresetError` with a did-you-mean."""
    try:
        return PRESETS[name]
    except KeyError:
        raise UnknownPresetError(f"unknown cheese-cut preset {name!r}.{did_you_mean(name, PRESETS)} "
                                 f"Presets: {', '.join(PRESETS)}") from None
