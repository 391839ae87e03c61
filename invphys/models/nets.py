"""The torch networks behind the model plugins (imported inside plugin methods only).

Every network carries its feature standardiser as buffers, so that a saved state dict is the whole
model: ``forward`` works on standardised features (training), ``predict_*`` returns physical ones.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import torch
from torch import nn
from zuko.transforms import MonotonicAffineTransform

from invphys.core.standardiser import Standardiser


def _mlp(sizes: Sequence[int], final_activation: nn.Module | None = None) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.ReLU())
    if final_activation is not None:
        layers.append(final_activation)
    return nn.Sequential(*layers)


class _Standardised(nn.Module):
    """Holds the features' :class:`~invphys.core.standardiser.Standardiser` (mean, std) as buffers."""

    def __init__(self, n_features: int) -> None:
        super().__init__()
        self.register_buffer("y_mean", torch.zeros(n_features))
        self.register_buffer("y_std", torch.ones(n_features))

    def set_standardiser(self, standardiser: Standardiser) -> None:
        self.y_mean.copy_(torch.as_tensor(standardiser.mean, dtype=torch.float32))
        self.y_std.copy_(torch.as_tensor(standardiser.std, dtype=torch.float32))

    def get_standardiser(self) -> Standardiser:
        """The buffers as a (float64) :class:`~invphys.core.standardiser.Standardiser`."""
        return Standardiser(mean=self.y_mean.detach().cpu().double().numpy(),
                            std=self.y_std.detach().cpu().double().numpy())

    def destandardise(self, y_std: torch.Tensor) -> torch.Tensor:
        return y_std * self.y_std + self.y_mean

    def standardise(self, y: torch.Tensor) -> torch.Tensor:
        return (y - self.y_mean) / self.y_std


#: hidden-layer activations a :class:`SkipMLP` can use (the NumPy inference form knows the same ones)
ACTIVATIONS = {"relu": nn.ReLU, "silu": nn.SiLU}


class SkipMLP(_Standardised):
    """The paper's surrogate: d -> h1 -> h2, concat(h1, h2) -> h3 -> M; batch norm, ReLU, dropout.

    ``activation`` "silu" swaps ReLU for SiLU (the parameter names and state dict are unchanged).
    """

    def __init__(self, d: int, m: int, hidden: Sequence[int] = (256, 256, 128), dropout: float = 0.1,
                 batch_norm: bool = True, activation: str = "relu") -> None:
        super().__init__(m)
        h1, h2, h3 = hidden
        act = ACTIVATIONS[activation]

        def block(i: int, o: int) -> nn.Sequential:
            parts: list[nn.Module] = [nn.Linear(i, o)]
            if batch_norm:
                parts.append(nn.BatchNorm1d(o))
            parts.append(act())
            if dropout > 0:
                parts.append(nn.Dropout(dropout))
            return nn.Sequential(*parts)

        self.b1 = block(d, h1)
        self.b2 = block(h1, h2)
        self.b3 = block(h1 + h2, h3)
        self.out = nn.Linear(h3, m)

    def forward(self, theta: torch.Tensor) -> torch.Tensor:
        a = self.b1(theta)
        b = self.b2(a)
        return self.out(self.b3(torch.cat([a, b], dim=-1)))

    def predict(self, theta: torch.Tensor) -> torch.Tensor:
        return self.destandardise(self.forward(theta))


class VAENet(_Standardised):
    """Encoder d -> 128 -> 64 -> (mu, logvar) in R^k, decoder k -> 64 -> 128 -> d (sigmoid), head k -> M."""

    def __init__(self, d: int, m: int, k: int, encoder: Sequence[int], decoder: Sequence[int],
                 head: Sequence[int]) -> None:
        super().__init__(m)
        self.encoder = nn.Sequential(_mlp([d, *encoder]), nn.ReLU())
        self.mu = nn.Linear(encoder[-1], k)
        self.logvar = nn.Linear(encoder[-1], k)
        self.decoder = _mlp([k, *decoder, d], nn.Sigmoid())
        self.head = _mlp([k, *head, m])

    def encode(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.encoder(theta)
        return self.mu(h), self.logvar(h).clamp(-20.0, 10.0)

    def predict_features(self, z: torch.Tensor) -> torch.Tensor:
        return self.destandardise(self.head(z))


class TanhAffineTransform(MonotonicAffineTransform):
    """zuko univariate transform x -> exp(s) x + t with the log-scale bounded as ``bound * tanh(raw)``."""

    def __init__(self, shift: torch.Tensor, scale: torch.Tensor, bound: float = 1.0, **kwargs) -> None:
        super(MonotonicAffineTransform, self).__init__(**kwargs)
        self.bound = bound
        self.shift = shift
        self.log_scale = bound * torch.tanh(scale)
        self.scale = self.log_scale.exp()

    def __repr__(self) -> str:
        return f"TanhAffineTransform(bound={self.bound})"


class FlowNet(_Standardised):
    """Projection d -> 64 -> k, a RealNVP flow on R^k (zuko affine couplings, alternating masks,
    tanh-bounded log-scales), projection k -> 64 -> d back, and a feature head on the flow's z.

    The couplings are zuko ``GeneralCouplingTransform`` modules (they own the masks and the
    hypernetworks). :attr:`evaluation` picks how :meth:`flow_forward` / :meth:`flow_inverse` run them:
    ``"direct"`` (the default) evaluates the same transform straight from those modules, ``"zuko"`` goes
    through zuko's own transform objects (:meth:`zuko_forward`, the reference the tests compare
    against). Both give the same numbers from the same weights; ``benchmarks/bench_flow.py`` measured
    the direct path 1.4x faster per training epoch and 1.6x faster on a one-row ``decode`` (what a
    latent-space optimiser pays per evaluation) on CPU (``benchmarks/results/flow_eval_cpu.json``).
    """

    #: "direct" (hand-written coupling evaluation) or "zuko" (zuko's transform objects)
    evaluation: str = "direct"

    def __init__(self, d: int, m: int, k: int, projection: int, n_couplings: int,
                 coupling_hidden: Sequence[int], scale_bound: float, head: Sequence[int]) -> None:
        super().__init__(m)
        from zuko.flows.coupling import GeneralCouplingTransform
        from zuko.lazy import LazyComposedTransform

        self.scale_bound = float(scale_bound)
        self.proj_in = _mlp([d, projection, k])
        self.proj_out = _mlp([k, projection, d])
        univariate = functools.partial(TanhAffineTransform, bound=float(scale_bound))
        base_mask = torch.arange(k) % 2 == 1
        self.flow = LazyComposedTransform(*[
            GeneralCouplingTransform(k, 0, mask=base_mask if i % 2 == 0 else ~base_mask,
                                     univariate=univariate, hidden_features=tuple(coupling_hidden))
            for i in range(n_couplings)
        ])
        self.head = _mlp([k, *head, m])

    def _couple(self, h: torch.Tensor, i: int, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        coupling = self.flow.transforms[i]
        ia, ib, back = self._index[i]
        xa, xb = h.index_select(1, ia), h.index_select(1, ib)
        phi = coupling.hyper(xa).unflatten(-1, (-1, 2))  # zuko's packing: (shift, scale) per feature
        shift, log_scale = phi[..., 0], self.scale_bound * torch.tanh(phi[..., 1])
        yb = (xb - shift) * torch.exp(-log_scale) if inverse else xb * torch.exp(log_scale) + shift
        return torch.cat([xa, yb], dim=1).index_select(1, back), log_scale.sum(dim=-1)

    @property
    def _index(self) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        """Per coupling: indices of the conditioning and transformed coordinates, and the inverse order."""
        cache = self.__dict__.get("_index_cache")
        device = self.flow.transforms[0].mask.device
        if cache is None or cache[0][0].device != device:
            cache = []
            for t in self.flow.transforms:
                ia, ib = torch.nonzero(t.mask).flatten(), torch.nonzero(~t.mask).flatten()
                cache.append((ia, ib, torch.argsort(torch.cat([ia, ib]))))
            self.__dict__["_index_cache"] = cache
        return cache

    def flow_forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(z, log|det dz/dh|) of the couplings applied in order."""
        if self.evaluation == "zuko":
            return self.zuko_forward(h)
        ladj = h.new_zeros(h.shape[0])
        for i in range(len(self.flow.transforms)):
            h, part = self._couple(h, i, inverse=False)
            ladj = ladj + part
        return h, ladj

    def flow_inverse(self, z: torch.Tensor) -> torch.Tensor:
        """h such that ``flow_forward(h)[0] == z``."""
        if self.evaluation == "zuko":
            return self.flow().inv(z)
        for i in reversed(range(len(self.flow.transforms))):
            z, _ = self._couple(z, i, inverse=True)
        return z

    def zuko_forward(self, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """zuko's own evaluation of the flow (reference for :meth:`flow_forward`)."""
        return self.flow().call_and_ladj(h)

    def to_latent(self, theta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(z, log|det J|) of the flow applied to the projected parameters."""
        return self.flow_forward(self.proj_in(theta))

    def from_latent(self, z: torch.Tensor) -> torch.Tensor:
        """Unclipped reconstructed parameters of latent codes."""
        return self.proj_out(self.flow_inverse(z))

    def predict_features(self, z: torch.Tensor) -> torch.Tensor:
        return self.destandardise(self.head(z))


class Ensemble(nn.Module):
    """K :class:`SkipMLP` members; ``predict_all`` stacks their physical-unit predictions (K, B, M)."""

    def __init__(self, members: Sequence[SkipMLP]) -> None:
        super().__init__()
        self.members = nn.ModuleList(members)

    def predict_all(self, theta: torch.Tensor) -> torch.Tensor:
        return torch.stack([m.predict(theta) for m in self.members])


class FoldedMLPs:
    """Inference-only form of K trained :class:`SkipMLP` networks (eval mode) as stacked matrices.

    Batch norm (running statistics) is folded into the preceding linear layer, dropout is the
    identity, and the K members run as one batched matrix product per layer: far fewer kernel
    calls than the modules, which is what a single-row ``predict`` (an optimiser's evaluation) pays for.
    """

    def __init__(self, members: Sequence[SkipMLP]) -> None:
        layers = []
        #: the hidden activation's name ("relu" or "silu"), from the members' first block
        self.act = next((n for n, cls in ACTIVATIONS.items() for mod in members[0].b1 if type(mod) is cls), "relu")
        self._act = torch.relu if self.act == "relu" else torch.nn.functional.silu
        with torch.no_grad():
            for name in ("b1", "b2", "b3"):
                ws, bs = [], []
                for m in members:
                    block = getattr(m, name)
                    lin = block[0]
                    w, b = lin.weight.detach().clone(), lin.bias.detach().clone()
                    bn = next((mod for mod in block if isinstance(mod, nn.BatchNorm1d)), None)
                    if bn is not None:
                        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
                        w = w * scale[:, None]
                        b = (b - bn.running_mean) * scale + bn.bias
                    ws.append(w.T)
                    bs.append(b[None, :])
                layers.append((torch.stack(ws), torch.stack(bs)))
            self.layers = layers
            self.w_out = torch.stack([m.out.weight.detach().T for m in members])
            self.b_out = torch.stack([m.out.bias.detach()[None, :] for m in members])
            self.y_std = torch.stack([m.y_std.detach()[None, :] for m in members])
            self.y_mean = torch.stack([m.y_mean.detach()[None, :] for m in members])
            # de-standardisation folded into the output layer
            self.w_out = self.w_out * self.y_std
            self.b_out = self.b_out * self.y_std + self.y_mean
        self.k = len(members)

    def __call__(self, theta: torch.Tensor) -> torch.Tensor:
        """(K, B, M) physical-unit predictions of (B, d) normalised parameters."""
        x = theta.unsqueeze(0).expand(self.k, -1, -1)
        (w1, b1), (w2, b2), (w3, b3) = self.layers
        act = self._act
        a = act(torch.baddbmm(b1, x, w1))
        c = act(torch.baddbmm(b2, a, w2))
        h = act(torch.baddbmm(b3, torch.cat([a, c], dim=-1), w3))
        return torch.baddbmm(self.b_out, h, self.w_out)
