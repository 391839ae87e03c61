"""A small two-body test scene for the engine's own tests and for plugin authors' checks (grid 16, CPU-sized):
rind over paste on a sticky board, a wire cutting down, a gripped tab, a held patch."""

from __future__ import annotations

from typing import Any

import numpy as np

from invphys_anisompm import Box, Cylinder, EngineOptions, HalfSpace, MaterialSpec, SceneBuilder, linear_cut

DX = 0.008
FLOOR = 3 * DX


def build_scene(settle_seconds: float, reductions: dict[str, Any] | None = None, **options: Any) -> Any:
    """Rind over paste on a sticky board, a wire cutting down, a gripped tab, a held patch (grid 16, CPU-sized)."""
    opts = EngineOptions(dx=DX, grid=16, fps=50.0, gravity=-9.81, settle_seconds=settle_seconds, **options)
    b = SceneBuilder(opts)
    b.add_body("rind", Box((0.04, FLOOR + 0.032, 0.04), (0.088, FLOOR + 0.04, 0.072)),
               MaterialSpec(E=8e4, nu=0.3, rho=1000.0, fracture_stretch=0.1, eta=0.02, fibre_ratio=3.0,
                            fibre_alpha=-1.0),
               fibres=lambda p: np.tile([1.0, 0.0, 0.0], (len(p), 1)))
    b.add_body("paste", Box((0.04, FLOOR, 0.04), (0.088, FLOOR + 0.04, 0.072)),
               MaterialSpec(E=3e4, nu=0.3, rho=1100.0, fracture_stretch=0.08, eta=0.02))
    b.add_collider("board", HalfSpace((0, FLOOR, 0), (0, 1, 0)), surface="sticky")
    b.add_collider("wire", Cylinder((0.064, FLOOR + 0.05, 0.056), 0.006, axis=2, half_length=0.1),
                   friction=0.3, path=linear_cut((0, -1, 0), 0.035, 0.25, t_start=0.02))
    b.add_grip("tab", Box((0.04, FLOOR + 0.016, 0.04), (0.045, FLOOR + 0.04, 0.072)),
               linear_cut((-1, 0, 0), 0.01, 0.1), bodies=("paste",))
    b.hold(Box((0.08, 0.0, 0.0), (0.2, FLOOR + 0.012, 0.2)))
    for name, fn in (reductions or {}).items():
        b.add_reduction(name, fn)
    return b.build()


def has_warp() -> bool:
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


__all__ = ["DX", "FLOOR", "build_scene", "has_warp"]
