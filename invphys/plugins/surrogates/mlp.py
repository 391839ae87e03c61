"""The paper's MLP surrogate (sec. 3.2): theta in [0,1]^d -> features, with a skip connection."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, PositiveInt

from invphys.core.interfaces import Surrogate
from invphys.models.base import TorchModel, TrainingConfig, validation_split
from invphys.models.data import check_training_data, r2_scores


class MLPSurrogate(TorchModel, Surrogate):
    """MLP d -> 256 -> 256 -> (skip: concat of both, 512) -> 128 -> M with batch norm, ReLU, dropout.

    Trained with MSE on standardised features, Adam (lr 1e-3, weight decay 1e-4) and early stopping
    (patience 50) on a held-out set; the best epoch's weights are kept. Metrics (``r2``,
    ``r2_per_feature``, ``mse``) are measured on that held-out set. Predictions run through an
    inference form with batch norm folded into the linear layers (equal to float32 rounding).
    """

    name: ClassVar[str] = "mlp"

    class Config(TrainingConfig):
        hidden: tuple[PositiveInt, PositiveInt, PositiveInt] = Field(
            (256, 256, 128), description="widths of the three hidden layers")
        dropout: float = Field(0.1, ge=0, lt=1, description="dropout after every hidden layer")
        batch_norm: bool = Field(True, description="batch normalisation after every hidden linear layer")
        activation: Literal["relu", "silu"] = Field("relu", description="hidden-layer activation")
        optimizer: Literal["adam", "adamw"] = Field(
            "adam", description="adam (L2 weight decay, the paper's) or adamw (decoupled weight decay)")
        schedule: Literal["constant", "one_cycle"] = Field(
            "constant", description="learning rate: constant, or a one-cycle cosine schedule over max_epochs")

    #: settings a model saved before they existed was trained with (filled in on load)
    LEGACY: ClassVar[dict[str, Any]] = {"activation": "relu", "optimizer": "adam", "schedule": "constant"}

    def __init__(self, config: Any = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._init_state()

    def _build_net(self, d: int, m: int) -> Any:
        return self._build_member(d, m)

    def _build_member(self, d: int, m: int) -> Any:
        """One :class:`~invphys.models.nets.SkipMLP` of this config."""
        from invphys.models.nets import SkipMLP

        c = self.config
        return SkipMLP(d, m, hidden=c.hidden, dropout=c.dropout, batch_norm=c.batch_norm, activation=c.activation)

    def fit(self, theta: np.ndarray, y: np.ndarray, progress: bool = False,
            validation: tuple[np.ndarray, np.ndarray] | None = None, tracker: Any = None) -> dict[str, Any]:
        """Train on (N, d) normalised parameters and (N, M) features; return held-out metrics.

        ``validation=(theta_val, y_val)`` is the held-out set for early stopping and metrics; without
        it, ``val_fraction`` of the rows is held out (seeded). ``tracker`` receives the per-epoch
        ``train_loss`` and ``val_loss``.
        """
        theta, y = check_training_data(theta, y, f"surrogate {self.name!r}")
        tt, yt, tv, yv = validation_split(theta, y, validation, self.config.val_fraction, self.config.seed,
                                          f"surrogate {self.name!r}")
        self._net, hist = train_mlp(self, tt, yt, tv, yv, self.config.seed, progress, f"surrogate {self.name}",
                                    tracker)
        return self._record_fit(theta, y, len(tt), (tv, yv), hist.to_dict(), hist.epochs, hist.best_epoch,
                                hist.train_time_s)

    def predict(self, theta: np.ndarray) -> np.ndarray:
        """Predicted features (B, M) for (B, d) normalised parameters."""
        return self._member_predict(theta)[0]

    def _member_predict(self, theta: np.ndarray) -> np.ndarray:
        """(K, B, M) predictions of the K networks (K = 1 here), through the folded inference form."""
        import torch

        x = self._input(theta, "theta")
        with torch.inference_mode():
            return self._folded_net()(x).cpu().numpy().astype(np.float64)

    def _folded_net(self) -> Any:
        """The networks with batch norm folded into their linear layers (built once per fit/load)."""
        if getattr(self, "_folded", None) is None:
            from invphys.models.nets import FoldedMLPs

            net = self._net
            self._folded = FoldedMLPs(list(net.members) if hasattr(net, "members") else [net])
        return self._folded

    def evaluate(self, theta: np.ndarray, y: np.ndarray) -> dict[str, Any]:
        """R^2 (overall = mean over features, and per feature) and standardised MSE on (theta, y)."""
        pred = self.predict(theta)
        r2, per = r2_scores(y, pred)
        std = self._net.get_standardiser().std
        mse = float((((pred - y) / std) ** 2).mean())
        return {"r2": r2, "r2_per_feature": per, "mse": mse}



def train_mlp(model: Any, tt: np.ndarray, yt: np.ndarray, tv: np.ndarray, yv: np.ndarray, seed: int,
              progress: bool, description: str, tracker: Any = None) -> tuple[Any, Any]:
    """Build and train one :class:`~invphys.models.nets.SkipMLP` of ``model``'s config; (net, history)."""
    import torch

    from invphys.core.standardiser import Standardiser
    from invphys.models.torch_utils import fit_loop, seeded, to_tensor, torch_threads

    c = model.config
    dev = model.device
    with seeded(seed, dev), torch_threads(c.threads):
        net = model._build_member(tt.shape[1], yt.shape[1])
        net.set_standardiser(Standardiser.fit(yt))
        net = net.to(dev)
        train = (to_tensor(tt, dev), net.standardise(to_tensor(yt, dev)))
        val = (to_tensor(tv, dev), net.standardise(to_tensor(yv, dev)))

        def loss_fn(batch: tuple[Any, ...], epoch: int | None) -> tuple[Any, dict[str, float]]:
            x, ys = batch
            loss = torch.nn.functional.mse_loss(net(x), ys)
            return loss, {}

        hist = fit_loop(net, loss_fn, train, val, lr=c.lr, weight_decay=c.weight_decay,
                        batch_size=c.batch_size, max_epochs=c.max_epochs, patience=c.patience, seed=seed,
                        progress=progress, description=description, tracker=tracker,
                        optimizer=c.optimizer, schedule=c.schedule)
    return net, hist
