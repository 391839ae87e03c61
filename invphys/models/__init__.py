"""Shared helpers of the learned models (surrogates and latent models).

The light modules (:mod:`invphys.models.data`, :mod:`invphys.models.base`) import only NumPy; the
torch modules (:mod:`invphys.models.torch_utils`, :mod:`invphys.models.nets`) are imported inside the
plugins' methods so that listing plugins stays fast.
"""
