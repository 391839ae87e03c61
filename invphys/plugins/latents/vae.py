"""The paper's VAE latent model (sec. 3.3) with an auxiliary feature-prediction head."""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import Field, PositiveInt

from invphys.core.interfaces import LatentModel
from invphys.models.latent import LatentConfig, LatentTorchModel


class VAELatent(LatentTorchModel, LatentModel):
    """Variational autoencoder: encoder d -> 128 -> 64 -> (mu, log var) of a k-D Gaussian, decoder
    k -> 64 -> 128 -> d (sigmoid), and a head z -> features.

    Loss: ``||theta - theta_hat||^2 + beta * KL(q(z|theta) || N(0, I)) + gamma * ||y - y_hat||^2``
    (standardised features), beta warmed up linearly over ``warmup_epochs``. During training z is
    sampled (reparameterisation) for both the decoder and the head; :meth:`encode` returns the mean.
    """

    name: ClassVar[str] = "vae"
    _reg_field = "beta"

    class Config(LatentConfig):
        beta: float = Field(0.1, ge=0, description="weight of the KL term after warm-up")
        encoder_hidden: tuple[PositiveInt, ...] = Field((128, 64), min_length=1, description="encoder widths")
        decoder_hidden: tuple[PositiveInt, ...] = Field((64, 128), min_length=1, description="decoder widths")

    def __init__(self, config: Any = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._init_state()

    def _build_net(self, d: int, m: int) -> Any:
        from invphys.models.nets import VAENet

        c = self.config
        return VAENet(d, m, c.latent_dim, c.encoder_hidden, c.decoder_hidden, c.head_hidden)

    def _loss(self, net: Any, theta: Any, ys: Any, reg_weight: float, train: bool) -> tuple[Any, dict[str, float]]:
        import torch

        mu, logvar = net.encode(theta)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if train else mu
        recon = self._reduce((net.decoder(z) - theta) ** 2)
        kl = self._reduce(0.5 * (mu ** 2 + logvar.exp() - 1.0 - logvar))
        pred = self._reduce((net.head(z) - ys) ** 2)
        loss = recon + reg_weight * kl + self.config.gamma * pred
        return loss, {"recon": float(recon.detach()), "kl": float(kl.detach()), "pred": float(pred.detach())}

    def _encode(self, x: Any) -> Any:
        return self._net.encode(x)[0]

    def _decode(self, z: Any) -> Any:
        return self._net.decoder(z)
