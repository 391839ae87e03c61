"""The dataset store's parts; :mod:`invphys.core.dataset` puts them together and is where to import from."""
