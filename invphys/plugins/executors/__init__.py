"""Built-in executors: where batches of simulations run (``local``, ``process``, ``ray``, ``ray_actors``).

Import-cheap: the executor modules import Ray and the simulator backends inside their methods.
"""

from __future__ import annotations

from invphys.plugins.executors.local import LocalExecutor
from invphys.plugins.executors.process import ProcessExecutor
from invphys.plugins.executors.ray_actors import RayActorsExecutor
from invphys.plugins.executors.ray_tasks import RayExecutor

EXECUTORS: list[type] = [LocalExecutor, ProcessExecutor, RayExecutor, RayActorsExecutor]
