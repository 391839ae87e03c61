"""The few methods that :mod:`invphys.core.spaces` calls on models, as structural types.

The search-space helpers (:func:`~invphys.core.spaces.latent_space`,
:func:`~invphys.core.spaces.make_predict`, :func:`~invphys.core.spaces.build_problem`) need neither
training nor persistence, so they take these Protocols rather than the plugin ABCs
:class:`~invphys.core.interfaces.Surrogate` / :class:`~invphys.core.interfaces.LatentModel`, which
satisfy them; so do the NumPy inference forms of a bundle (``invphys.inverter.bundle``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

if TYPE_CHECKING:
    from invphys.core.interfaces import LatentModel, Surrogate


class Predictor(Protocol):
    """Predicts features (B, M) from normalised parameters (B, d): what a search uses of a surrogate."""

    def predict(self, theta: np.ndarray) -> np.ndarray: ...


class LatentCodec(Protocol):
    """A latent box [-latent_bound, latent_bound]^latent_dim with its encoder and decoder."""

    @property
    def latent_dim(self) -> int: ...

    @property
    def latent_bound(self) -> float: ...

    def encode(self, theta: np.ndarray) -> np.ndarray: ...

    def decode(self, z: np.ndarray) -> np.ndarray: ...


class FeatureHead(Protocol):
    """Predicts features (B, M) from latent codes (B, k): a latent model's own head."""

    def predict_features(self, z: np.ndarray) -> np.ndarray: ...


if TYPE_CHECKING:
    # mypy checks here that the plugin ABCs still satisfy the Protocols (nothing runs).
    def _plugins_conform(surrogate: Surrogate, latent: LatentModel) -> tuple[Predictor, LatentCodec, FeatureHead]:
        return surrogate, latent, latent
