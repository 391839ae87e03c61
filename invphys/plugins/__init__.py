"""Built-in plugins of invphys (registered by :mod:`invphys.plugins.builtin`)."""
