"""Fast draws of sbi's neural spline flow (``nsf``): nflows' inverse pass for sampling only, bit for bit the
same draws (:class:`SplineSampler`; :func:`spline_sampler` builds it for a flow it can compute, else None)."""

from __future__ import annotations

import warnings
import weakref
from typing import Any

import numpy as np


class SplineSampler:
    """Draws of sbi's neural spline flow (``nsf``: nflows' rational-quadratic coupling layers on residual
    nets, LU-linear mixing, a standardising affine) without sbi's and nflows' per-call work: the inverse
    pass alone, for sampling.

    Every value a draw is made of comes from the same torch operation on the same operands as in nflows'
    own ``Flow._transform.inverse``, so a row's draw is nflows' (and sbi's ``sample``'s) to the last bit
    (tests/test_npe_draw_speed.py). What it leaves out or does once:

    * every layer's log-determinant (sampling never reads it);
    * the spline's selection of the entries inside its tail bound (index, nonzero, index_put on every
      tensor): every entry is computed and those outside keep their input (``torch.where``); their bin
      index, meaningless, is clamped into range;
    * per entry, only the bin a draw lands in: its width, height and derivatives are gathered before the
      arithmetic that used all eleven (the same subtractions and softplus, on two bins instead of eleven);
    * the residual blocks' context gates: ``glu(cat(t, context_layer(c)))`` is ``t * glu(cat(1, context_layer(c)))``
      (the same sigmoid, multiplied the same way), and the gate is the target's, computed once per target
      (:meth:`gates`) instead of once per row.

    Elementwise kernels compute a call's last few entries in a scalar loop (transcendental ones, e.g.
    softplus, then differ in rare last bits), so a caller pads every call with rows it discards
    (:func:`invphys.inverter.draws._padded`), as it does for nflows. Build it with :func:`spline_sampler`.
    """

    def __init__(self, net: Any) -> None:
        from nflows.transforms.base import CompositeTransform
        from nflows.transforms.coupling import PiecewiseRationalQuadraticCouplingTransform as Spline
        from nflows.transforms.lu import LULinear
        from nflows.transforms.standard import PointwiseAffineTransform

        if type(net._transform) is not CompositeTransform:
            raise TypeError("not a composite transform")
        self._steps: list[tuple[str, Any]] = []
        for t in reversed(list(net._transform._transforms)):  # the inverse runs them backwards
            if type(t) is PointwiseAffineTransform:
                self._steps.append(("affine", t))
            elif type(t) is LULinear and not t.using_cache:
                self._steps.append(("lu", t))
            elif type(t) is Spline and _plain_spline(t):
                self._steps.append(("spline", t))
            else:
                raise TypeError(f"{type(t).__name__} is not a layer of sbi's nsf this sampler computes")
        self.blocks = [b for kind, layer in self._steps if kind == "spline" for b in layer.transform_net.blocks]

    def gates(self, emb: Any) -> list[Any]:
        """Per residual block (in :meth:`inverse`'s order), the gate of each row of ``emb`` (rows, C): the
        embedded conditions, one row per target (padded by the caller, as a flow call is)."""
        import torch
        import torch.nn.functional as F

        with torch.no_grad():
            out = []
            for block in self.blocks:
                c = block.context_layer(emb)
                out.append(F.glu(torch.cat((torch.ones_like(c), c), dim=1), dim=1))
            return out

    def inverse(self, noise: Any, ctx: Any, gates: list[Any]) -> Any:
        """The draws (rows, d) of base noise ``noise`` (rows, d) given each row's embedded condition ``ctx``
        (rows, C) and its :meth:`gates` (row for row)."""
        import torch

        x, g = noise, iter(gates)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*triangular_solve is deprecated.*")
            for kind, layer in self._steps:
                if kind == "affine":  # nflows' PointwiseAffineTransform.inverse
                    x = (x - layer._shift) / layer._scale
                elif kind == "lu":  # nflows' LULinear.inverse_no_cache
                    lower, upper = layer._create_lower_upper()
                    y, _ = torch.triangular_solve((x - layer.bias).t(), lower, upper=False, unitriangular=True)
                    y, _ = torch.triangular_solve(y, upper, upper=True, unitriangular=False)
                    x = y.t()
                else:
                    x = self._coupling(layer, x, ctx, [next(g) for _ in layer.transform_net.blocks])
        return x

    @staticmethod
    def _coupling(layer: Any, x: Any, ctx: Any, gates: list[Any]) -> Any:
        """nflows' CouplingTransform.inverse and ResidualNet.forward (no batch norm, no dropout)."""
        import torch

        net = layer.transform_net
        trans = x[:, layer.transform_features]
        h = net.initial_layer(torch.cat((x[:, layer.identity_features], ctx), dim=1))
        for block, gate in zip(net.blocks, gates, strict=True):
            t = block.linear_layers[0](block.activation(h))
            t = block.linear_layers[1](block.activation(t))
            h = h + t * gate
        params = net.final_layer(h).reshape(trans.shape[0], trans.shape[1], -1)
        out = x.clone()
        out[:, layer.transform_features] = _spline_inverse(layer, trans, params)
        return out


def _plain_spline(t: Any) -> bool:
    """A coupling layer as sbi's nsf builds it: linear tails, no unconditional transform, a residual net
    conditioned on the context, no batch norm and no dropout (or not training)."""
    from nflows.nn.nets.resnet import ResidualBlock, ResidualNet

    net = t.transform_net
    if t.tails != "linear" or t.unconditional_transform is not None or type(net) is not ResidualNet:
        return False
    if net.context_features is None or not hasattr(net, "hidden_features"):
        return False
    return all(type(b) is ResidualBlock and not b.use_batch_norm and hasattr(b, "context_layer")
               and (b.dropout.p == 0 or not b.training) for b in net.blocks)


def _spline_inverse(layer: Any, inputs: Any, params: Any) -> Any:
    """nflows' unconstrained_rational_quadratic_spline(inverse=True) outputs, every entry at once."""
    import torch
    import torch.nn.functional as F

    nb, bound = layer.num_bins, layer.tail_bound
    scale = np.sqrt(layer.transform_net.hidden_features)
    left, right, bottom, top = -bound, bound, -bound, bound
    min_w, min_h, min_d = layer.min_bin_width, layer.min_bin_height, layer.min_derivative
    inside = (inputs >= -bound) & (inputs <= bound)

    heights = F.softmax(params[..., nb:2 * nb] / scale, dim=-1)
    heights = min_h + (1 - min_h * nb) * heights
    cumheights = torch.cumsum(heights, dim=-1)
    cumheights = F.pad(cumheights, pad=(1, 0), mode="constant", value=0.0)
    cumheights = (top - bottom) * cumheights + bottom
    cumheights[..., 0] = bottom
    cumheights[..., -1] = top
    # nflows' searchsorted: sum(x >= edges) - 1 with the last edge moved up by 1e-6 (in its own copy here:
    # the heights are read from the unmoved one); the edges rise strictly (every bin >= min_bin_height), so
    # torch.searchsorted(right=True) counts the same edges
    locations = cumheights.clone()
    locations[..., -1] += 1e-6
    idx = (torch.searchsorted(locations, inputs[..., None], right=True) - 1).clamp_(0, nb - 1)
    nxt = idx + 1
    first, last = idx[..., 0] == 0, nxt[..., 0] == nb
    input_cumheights = cumheights.gather(-1, idx)[..., 0]
    input_heights = cumheights.gather(-1, nxt)[..., 0] - input_cumheights

    # the widths' edges at the bin and the next one only: nflows pads the cumulative sum with a 0 in front,
    # maps it affinely and sets the first edge to left, the last to right; here the same map on the two
    # gathered sums (an edge k >= 1 is sum k - 1)
    widths = F.softmax(params[..., :nb] / scale, dim=-1)
    widths = min_w + (1 - min_w * nb) * widths
    cum = torch.cumsum(widths, dim=-1)
    input_cumwidths = torch.where(first, left, (right - left) * cum.gather(-1, (idx - 1).clamp_(min=0))[..., 0] + left)
    next_cumwidths = torch.where(last, right, (right - left) * cum.gather(-1, idx)[..., 0] + left)
    input_bin_widths = next_cumwidths - input_cumwidths
    input_delta = input_heights / input_bin_widths

    # the derivatives at the bin's two edges: nflows pads the unnormalised ones with the linear tails'
    # constant at both ends (edge k >= 1 is entry k - 1), then softplus
    ud = params[..., 2 * nb:]
    constant = np.log(np.exp(1 - min_d) - 1)
    d0 = torch.where(first, constant, ud.gather(-1, (idx - 1).clamp_(min=0))[..., 0])
    d1 = torch.where(last, constant, ud.gather(-1, idx.clamp(max=nb - 2))[..., 0])
    input_derivatives = min_d + F.softplus(d0)
    input_derivatives_plus_one = min_d + F.softplus(d1)

    a = (inputs - input_cumheights) * (
        input_derivatives + input_derivatives_plus_one - 2 * input_delta
    ) + input_heights * (input_delta - input_derivatives)
    b = input_heights * input_derivatives - (inputs - input_cumheights) * (
        input_derivatives + input_derivatives_plus_one - 2 * input_delta
    )
    c = -input_delta * (inputs - input_cumheights)
    discriminant = b.pow(2) - 4 * a * c
    root = (2 * c) / (-b - torch.sqrt(discriminant))
    return torch.where(inside, root * input_bin_widths + input_cumwidths, inputs)


_SAMPLERS: weakref.WeakKeyDictionary[Any, SplineSampler | None] = weakref.WeakKeyDictionary()


def spline_sampler(net: Any) -> SplineSampler | None:
    """The :class:`SplineSampler` of an nflows flow (one per flow: it holds the flow's own layers, so it
    computes with their current weights), or None where the flow is not sbi's nsf as that sampler
    computes it (then nflows' own inverse draws)."""
    if net not in _SAMPLERS:
        try:
            _SAMPLERS[net] = SplineSampler(net)
        except (TypeError, AttributeError, ImportError):
            _SAMPLERS[net] = None
    return _SAMPLERS[net]
