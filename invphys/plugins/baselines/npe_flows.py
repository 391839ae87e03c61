"""sbi's nflows density estimators (``maf``, ``nsf``) rebuilt for loading, without importing sbi.

A saved NPE holds only tensors (``npe_weights.npz``); rebuilding its network through sbi's builder imports
``sbi``, whose package import pulls scikit-learn and scipy.stats (about 3.6 s of a one-target ``invphys invert``
on a 2-core CPU, more than the answer itself). The networks are plain nflows modules, so :func:`build_estimator`
builds them the way sbi 0.27's ``build_maf`` and ``build_nsf`` do (the same classes, in the same order, with the
same state-dict keys), and :class:`FlowEstimator` samples and evaluates them as sbi's ``NFlowsFlow`` does (the same
calls on the same tensors, so the same bits; tests/test_npe_flows.py checks both against sbi). A save whose
layout differs (another sbi release, ``mdn``) is rebuilt through sbi instead
(:meth:`~invphys.plugins.baselines.npe.NPEBaseline.load`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn

#: the estimators built here; others (``mdn``) go through sbi's builder
ESTIMATORS = ("maf", "nsf")
#: sbi's defaults for both builders: residual blocks per conditioner, spline bins and tail bound (nsf)
NUM_BLOCKS, NUM_BINS, TAIL_BOUND = 2, 10, 3.0


class Standardize(nn.Module):
    """The condition's z-scoring (sbi's ``Standardize``: buffers ``_mean`` and ``_std``)."""

    _mean: torch.Tensor
    _std: torch.Tensor

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.register_buffer("_mean", torch.zeros(dim))
        self.register_buffer("_std", torch.ones(dim))

    def forward(self, tensor: torch.Tensor) -> torch.Tensor:
        return (tensor - self._mean) / self._std


class FlowEstimator(nn.Module):
    """A conditional nflows flow q(theta | x) with sbi ``NFlowsFlow``'s shapes: ``sample`` gives
    (*sample_shape, B, d), ``log_prob`` takes (S, B, d) or (B, d) inputs and gives (S, B)."""

    def __init__(self, net: Any, theta_dim: int, x_dim: int) -> None:
        super().__init__()
        self.net = net
        self.input_shape = torch.Size([theta_dim])
        self.condition_shape = torch.Size([x_dim])

    def sample(self, sample_shape: Any, condition: torch.Tensor) -> torch.Tensor:
        batch = condition.shape[0]
        samples = self.net.sample(torch.Size(sample_shape).numel(), context=condition)  # (B, S, d)
        return samples.transpose(0, 1).reshape((*sample_shape, batch, *self.input_shape))

    def log_prob(self, input: torch.Tensor, condition: torch.Tensor) -> torch.Tensor:
        if input.dim() <= len(self.input_shape) + 1:
            input = input.unsqueeze(0)
        samples = input.shape[0]
        batch = torch.broadcast_shapes((input.shape[1],), (condition.shape[0],))[0]
        input = input.expand(samples, batch, *self.input_shape)
        condition = (condition.expand(batch, *self.condition_shape).unsqueeze(0)
                     .expand(samples, batch, *self.condition_shape))
        log_probs = self.net.log_prob(input.reshape(samples * batch, -1),
                                      context=condition.reshape(samples * batch, *self.condition_shape))
        return log_probs.reshape(samples, batch)


class LoadedPosterior:
    """A loaded estimator and its prior: the two attributes of sbi's ``DirectPosterior`` that
    :class:`~invphys.plugins.baselines.npe.NPEBaseline` and the inverter's draws read."""

    def __init__(self, posterior_estimator: Any, prior: Any) -> None:
        self.posterior_estimator = posterior_estimator
        self.prior = prior


def build_estimator(estimator: str, hidden_features: int, num_transforms: int, theta_dim: int,
                    x_dim: int) -> FlowEstimator:
    """The untrained network of sbi's ``posterior_nn(model=estimator, ...)`` for these shapes (its
    z-scoring buffers and weights are the caller's to load)."""
    from nflows import distributions, flows, transforms

    if estimator not in ESTIMATORS:
        raise ValueError(f"no light builder for the {estimator!r} estimator (only {', '.join(ESTIMATORS)})")
    layers = (_nsf_layers if estimator == "nsf" else _maf_layers)(theta_dim, x_dim, hidden_features, num_transforms)
    standardise = transforms.PointwiseAffineTransform(shift=torch.zeros(theta_dim), scale=torch.ones(theta_dim))
    base = distributions.StandardNormal((theta_dim,))
    base._log_z = base._log_z.to(torch.float32)  # as sbi's get_base_dist
    embedding = nn.Sequential(Standardize(x_dim), nn.Identity())
    net = flows.Flow(transforms.CompositeTransform([standardise, *layers]), base, embedding)
    return FlowEstimator(net, theta_dim, x_dim)


def _nsf_layers(d: int, m: int, hidden: int, count: int) -> list[Any]:
    """sbi's nsf: per layer a rational-quadratic coupling on a residual net, then an LU-linear mixing."""
    from functools import partial

    from nflows import transforms
    from nflows.nn import nets

    if d < 2:
        raise ValueError("the light nsf builder needs >= 2 parameters")
    conditioner = partial(nets.ResidualNet, hidden_features=hidden, context_features=m, num_blocks=NUM_BLOCKS,
                          activation=torch.relu, dropout_probability=0.0, use_batch_norm=False)
    layers: list[Any] = []
    for i in range(count):
        mask = torch.zeros(d).byte()
        mask[(0 if i % 2 == 0 else 1)::2] += 1  # sbi's alternating binary mask
        layers.append(transforms.PiecewiseRationalQuadraticCouplingTransform(
            mask=mask, transform_net_create_fn=conditioner, num_bins=NUM_BINS, tails="linear",
            tail_bound=TAIL_BOUND, apply_unconditional_transform=False))
        layers.append(transforms.LULinear(d, identity_init=True))
    return layers


def _maf_layers(d: int, m: int, hidden: int, count: int) -> list[Any]:
    """sbi's maf: per layer a masked affine autoregressive transform, then a (saved) permutation."""
    from nflows import transforms

    layers: list[Any] = []
    for _ in range(count):
        layers.append(transforms.MaskedAffineAutoregressiveTransform(
            features=d, hidden_features=hidden, context_features=m, num_blocks=NUM_BLOCKS,
            use_residual_blocks=False, random_mask=False, activation=torch.tanh, dropout_probability=0.0,
            use_batch_norm=False))
        layers.append(transforms.RandomPermutation(features=d))
    return layers


def load_estimator(estimator: str, hidden_features: int, num_transforms: int, theta_dim: int, x_dim: int,
                   state: dict[str, np.ndarray]) -> FlowEstimator | None:
    """The saved network rebuilt here, or None where this builder does not make exactly the saved layout
    (another estimator, or keys or shapes of another sbi release: the caller then uses sbi's builder)."""
    if estimator not in ESTIMATORS or (estimator == "nsf" and theta_dim < 2):
        return None
    rng = torch.get_rng_state()  # building draws initial weights and permutations: keep the caller's stream
    try:
        est = build_estimator(estimator, hidden_features, num_transforms, theta_dim, x_dim)
    finally:
        torch.set_rng_state(rng)
    own = est.state_dict()
    if set(own) != set(state) or any(tuple(own[k].shape) != tuple(np.shape(v)) for k, v in state.items()):
        return None
    est.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()}, strict=True)
    return est.eval()
