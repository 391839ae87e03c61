"""Built-in plugins of invphys (registered by :mod:`invphys.plugins.builtin`, the ``invphys`` entry point of invphys's own
``pyproject.toml``)."""
