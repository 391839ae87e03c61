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


_HINT = ("is the head running (`ray start --head`) and its port open from here? Do this process and the "
         "nodes share the cluster's auth token (RAY_AUTH_TOKEN or ~/.ray/auth_token)? See docs/ray-cluster.md")


def _check_listening(address: str, timeout_s: float = 5.0) -> None:
    """For a ``host:port`` address: one line at once when nothing listens there (Ray itself retries for
    minutes); other forms (``auto``, ``ray://...``) are left to Ray."""
    import socket

    host, sep, port = address.rpartition(":")
    if not sep or not host or "/" in address or not port.isdigit():
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise InvphysError(f"cannot reach Ray at {address!r}: nothing answers there ({exc}); {_HINT}") from None


def connect(ray: Any, address: str | None, num_cpus: int | None, num_gpus: int | None = None) -> bool:
    """Reach ``address`` or start a local instance (``num_cpus``/``num_gpus`` of it; None: all); True
    when this call started it. A process where Ray is already initialised keeps its instance."""
    if ray.is_initialized():
        return False
    local = address is None
    if address is not None:
        _check_listening(address)
    ray_error = getattr(getattr(ray, "exceptions", None), "RayError", RuntimeError)   # e.g. AuthenticationError
    try:
        ray.init(address=address, num_cpus=num_cpus if local else None, num_gpus=num_gpus if local else None,
                 include_dashboard=False, log_to_driver=False, configure_logging=False)
    except (ConnectionError, RuntimeError, ValueError, ray_error) as exc:
        hint = "" if local else f"; {_HINT}"
        raise InvphysError(f"cannot start or reach Ray (address={address!r}): {exc}{hint}") from exc
    return True
