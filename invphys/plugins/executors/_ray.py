"""Ray for the ``ray`` and ``ray_actors`` executors: a clear error when it is missing, and one way to
start or reach an instance."""

from __future__ import annotations

from typing import Any

from invphys.core.errors import InvphysError


class RayUnavailableError(InvphysError, ImportError):
    """A Ray executor was asked for where Ray is not installed."""


def import_ray(executor: str) -> Any:
    """``import ray``, or one line saying how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise RayUnavailableError(
            f"the {executor!r} executor needs Ray, which is not installed here ({exc}): "
            "pip install 'invphys[ray]'") from None
    return ray


def connect(ray: Any, address: str | None, num_cpus: int | None, num_gpus: int | None = None) -> bool:
    """Reach ``address`` or start a local instance (``num_cpus``/``num_gpus`` of it; None: all); True
    when this call started it. A process where Ray is already initialised keeps its instance."""
    if ray.is_initialized():
        return False
    local = address is None
    try:
        ray.init(address=address, num_cpus=num_cpus if local else None, num_gpus=num_gpus if local else None,
                 include_dashboard=False, log_to_driver=False, configure_logging=False)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise InvphysError(f"cannot start or reach Ray (address={address!r}): {exc}") from exc
    return True
