"""Datasets made through plugins, above the registry: generation (:mod:`invphys.data.generate`) and
adaptive design (:mod:`invphys.data.adaptive`). The store and the spec models they use are in :mod:`invphys.core`."""
