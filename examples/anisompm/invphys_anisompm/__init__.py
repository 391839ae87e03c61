"""invphys-anisompm: a batched AnisoMPM engine (Taichi and Warp) with a scene API.

Import-cheap: nothing here imports taichi or warp until a backend is asked for. A scene::

    from invphys_anisompm import (Box, Cylinder, Engine, EngineOptions, HalfSpace, MaterialSpec,
                                  SceneBuilder, linear_cut)

    b = SceneBuilder(EngineOptions(dx=0.008, grid=16, fps=50.0, gravity=-9.81))
    b.add_body("block", Box((0.04, 0.024, 0.048), (0.088, 0.056, 0.08)), MaterialSpec(E=5e4, nu=0.3))
    b.add_collider("wire", Cylinder((0.064, 0.07, 0.064), 0.008), friction=0.2,
                   path=linear_cut((0, -1, 0), 0.04, 0.25))
    scene = b.build()
    model = scene.model(n_envs=2).set_material("block", E=[3e4, 1e5])
    records = Engine(scene, backend="taichi", arch="cpu").run(model, frames=10, record_every=5)
"""

from invphys_anisompm.engine import Engine, RunRecord
from invphys_anisompm.materials import MaterialSpec
from invphys_anisompm.model import Model
from invphys_anisompm.paths import FunctionPath, Path, Static, Waypoints, linear_cut
from invphys_anisompm.regions import Box, Cylinder, Ellipsoid, HalfSpace, Region, Shell, Sphere, lattice
from invphys_anisompm.scene import EngineOptions, Scene, SceneBuilder, SceneError
from invphys_anisompm.streaming import EngineBusyError

__version__ = "0.1.0"
#: bump when the engine's results change (scenes record it with their own version)
ENGINE_VERSION = "0.1.0"

__all__ = ["ENGINE_VERSION", "Box", "Cylinder", "Ellipsoid", "Engine", "EngineBusyError", "EngineOptions", "FunctionPath",
           "HalfSpace", "MaterialSpec", "Model", "Path", "Region", "RunRecord", "Scene", "SceneBuilder",
           "SceneError", "Shell", "Sphere", "Static", "Waypoints", "lattice", "linear_cut"]
