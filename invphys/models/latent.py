"""The common part of the latent models (VAE, RealNVP flow): settings, training and metrics.

Import-light (torch inside methods). A subclass builds its network and defines the training loss
through :meth:`LatentTorchModel._loss` and the deterministic maps ``_encode`` / ``_decode``.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import Field, PositiveInt

from invphys.core.standardiser import Standardiser
from invphys.models.base import TorchModel, TrainingConfig, validation_split
from invphys.models.data import check_training_data, r2_scores


class LatentConfig(TrainingConfig):
    """Settings shared by the latent models."""

    latent_dim: int = Field(4, ge=1, description="dimension k of the latent code")
    gamma: float = Field(1.0, ge=0, description="weight of the feature-prediction head's loss")
    warmup_epochs: int = Field(50, ge=0, description="epochs of linear warm-up of the regulariser's weight")
    head_hidden: tuple[PositiveInt, ...] = Field((64, 64), description="hidden widths of the feature head (z -> M)")
    loss_reduction: Literal["sum", "mean"] = Field(
        "sum", description="sum: squared norms over dimensions as in the paper's losses; mean: per-element")
    max_epochs: int = Field(500, ge=1, description="upper bound on training epochs")


class LatentTorchModel(TorchModel):
    """Mixin: fit loop, encode/decode/predict_features over numpy, and the metrics of a latent model."""

    #: the regulariser weight's config field (``beta`` for the VAE, ``alpha`` for the flow)
    _reg_field: str = "beta"

    @property
    def latent_dim(self) -> int:
        return int(self.config.latent_dim)

    def _loss(self, net: Any, theta: Any, ys: Any, reg_weight: float, train: bool) -> tuple[Any, dict[str, float]]:
        raise NotImplementedError

    def _reduce(self, sq: Any) -> Any:
        """Squared errors (B, D) -> a scalar: per-row sum (or mean) over D, mean over rows."""
        return sq.sum(dim=1).mean() if self.config.loss_reduction == "sum" else sq.mean()

    def fit(self, theta: np.ndarray, y: np.ndarray, progress: bool = False,
            validation: tuple[np.ndarray, np.ndarray] | None = None, tracker: Any = None) -> dict[str, Any]:
        """Train on (N, d) normalised parameters and (N, M) features; return held-out metrics.

        ``validation=(theta_val, y_val)`` is the held-out set for early stopping and metrics; without
        it, ``val_fraction`` of the rows is held out (seeded). Early stopping counts from the end of
        the warm-up; the validation loss always uses the final regulariser weight. ``tracker`` receives
        the per-epoch losses (``train_loss``, ``val_loss``, ``val_recon``, ...).
        """

        from invphys.models.torch_utils import fit_loop, seeded, to_tensor, torch_threads

        c = self.config
        label = f"latent model {self.name!r}"
        theta, y = check_training_data(theta, y, label)
        tt, yt, tv, yv = validation_split(theta, y, validation, c.val_fraction, c.seed, label)
        dev = self.device
        reg = float(getattr(c, self._reg_field))
        with seeded(c.seed, dev), torch_threads(c.threads):
            net = self._build_net(theta.shape[1], y.shape[1])
            net.set_standardiser(Standardiser.fit(yt))
            net = net.to(dev)
            train = (to_tensor(tt, dev), net.standardise(to_tensor(yt, dev)))
            val = (to_tensor(tv, dev), net.standardise(to_tensor(yv, dev)))

            def loss_fn(batch: tuple[Any, ...], epoch: int | None) -> tuple[Any, dict[str, float]]:
                if epoch is None:
                    w = reg
                else:
                    w = reg * min(1.0, (epoch + 1) / c.warmup_epochs) if c.warmup_epochs else reg
                return self._loss(net, batch[0], batch[1], w, epoch is not None)

            hist = fit_loop(net, loss_fn, train, val, lr=c.lr, weight_decay=c.weight_decay,
                            batch_size=c.batch_size, max_epochs=c.max_epochs, patience=c.patience,
                            min_epochs=c.warmup_epochs, seed=c.seed, progress=progress,
                            description=f"latent {self.name}", tracker=tracker)
        self._net = net.eval()
        return self._record_fit(theta, y, len(tt), (tv, yv), hist.to_dict(), hist.epochs, hist.best_epoch,
                                hist.train_time_s)

    # -- numpy API -------------------------------------------------------------------------------
    def encode(self, theta: np.ndarray) -> np.ndarray:
        """Deterministic latent codes (B, k) of (B, d) normalised parameters."""
        import torch

        x = self._input(theta, "theta")
        with torch.inference_mode():
            return self._encode(x).cpu().numpy().astype(np.float64)

    def decode(self, z: np.ndarray) -> np.ndarray:
        """Normalised parameters (B, d), clipped to [0, 1], of (B, k) latent codes."""
        import torch

        x = self._input(z, "z")
        with torch.inference_mode():
            return np.clip(self._decode(x).cpu().numpy().astype(np.float64), 0.0, 1.0)

    def predict_features(self, z: np.ndarray) -> np.ndarray:
        """The feature head's prediction (B, M), in feature units, for (B, k) latent codes."""
        import torch

        x = self._input(z, "z")
        with torch.inference_mode():
            return self._net.predict_features(x).cpu().numpy().astype(np.float64)

    def evaluate(self, theta: np.ndarray, y: np.ndarray) -> dict[str, Any]:
        """Reconstruction MSE of decode(encode(theta)), the head's R^2 on encode(theta), latent stats."""
        z = self.encode(theta)
        rec = self.decode(z)
        r2, per = r2_scores(y, self.predict_features(z))
        b = self.latent_bound
        return {
            "recon_mse": float(((rec - theta) ** 2).mean()),
            "recon_mse_per_param": [float(v) for v in ((rec - theta) ** 2).mean(axis=0)],
            "head_r2": r2, "head_r2_per_feature": per,
            "latent_mean": [float(v) for v in z.mean(axis=0)],
            "latent_std": [float(v) for v in z.std(axis=0)],
            "in_bounds_fraction": float((np.abs(z) <= b).all(axis=1).mean()),
        }
