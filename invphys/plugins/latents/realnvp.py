"""The paper's RealNVP flow latent model (sec. 3.3), built on zuko's coupling transforms."""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import Field, PositiveInt, field_validator

from invphys.core.interfaces import LatentModel
from invphys.models.latent import LatentConfig, LatentTorchModel


class RealNVPLatent(LatentTorchModel, LatentModel):
    """Projection d -> 64 -> k (ReLU), a RealNVP flow on R^k, projection k -> 64 -> d back, and a
    feature head on the flow's output z.

    The flow is ``n_couplings`` zuko affine coupling layers with alternating checkerboard masks,
    hypernetworks of ``coupling_hidden`` units and log-scales bounded as ``scale_bound * tanh``.
    Loss: ``||theta - theta_hat||^2 + alpha * (0.5 ||z||^2 - log|det J|) + gamma * ||y - y_hat||^2``,
    alpha warmed up linearly over ``warmup_epochs``; the reconstruction runs through the flow's
    inverse, exactly the :meth:`decode` path. :meth:`decode` clips to [0, 1].
    """

    name: ClassVar[str] = "realnvp"
    _reg_field = "alpha"

    class Config(LatentConfig):
        alpha: float = Field(0.1, ge=0, description="weight of the flow NLL after warm-up")
        projection_hidden: int = Field(64, ge=1, description="width of the d -> k and k -> d projections")
        n_couplings: int = Field(6, ge=1, description="number of affine coupling layers")
        coupling_hidden: tuple[PositiveInt, ...] = Field((64, 64), min_length=1,
                                                 description="hidden widths of each coupling's network")
        scale_bound: float = Field(1.0, gt=0, description="bound B of the log-scales, B * tanh(.)")

        @field_validator("latent_dim")
        @classmethod
        def _two_or_more(cls, value: int) -> int:
            if value < 2:
                raise ValueError("must be >= 2 for realnvp (each coupling splits z in two)")
            return value

    def __init__(self, config: Any = None, **settings: Any) -> None:
        super().__init__(config, **settings)
        self._init_state()

    def _build_net(self, d: int, m: int) -> Any:
        from invphys.models.nets import FlowNet

        c = self.config
        return FlowNet(d, m, c.latent_dim, c.projection_hidden, c.n_couplings, c.coupling_hidden,
                       c.scale_bound, c.head_hidden)

    def _loss(self, net: Any, theta: Any, ys: Any, reg_weight: float, train: bool) -> tuple[Any, dict[str, float]]:
        z, ladj = net.to_latent(theta)
        recon = self._reduce((net.from_latent(z) - theta) ** 2)
        sq = 0.5 * z ** 2
        nll = (sq.sum(dim=1) - ladj).mean()
        if self.config.loss_reduction == "mean":
            nll = nll / z.shape[1]
        pred = self._reduce((net.head(z) - ys) ** 2)
        loss = recon + reg_weight * nll + self.config.gamma * pred
        return loss, {"recon": float(recon.detach()), "nll": float(nll.detach()), "pred": float(pred.detach())}

    def _encode(self, x: Any) -> Any:
        return self._net.to_latent(x)[0]

    def _decode(self, z: Any) -> Any:
        return self._net.from_latent(z)
