"""The engine's scene error (its own module, so that every module may raise it without importing the scene)."""


class SceneError(ValueError):
    """An inconsistent scene (duplicate names, empty bodies, particles outside the domain)."""


__all__ = ["SceneError"]
