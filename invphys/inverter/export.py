"""Build NumPy :class:`~invphys.inverter.numeric.Program` forms of trained models, verified on export.

Each ``*_program`` function returns a program, or None when the model has a structure it does not know
(a third-party plugin): the bundle then serves that part through the plugin's own (torch) ``load``.
A program is kept only if it reproduces the model on random inputs (:data:`RTOL`, :data:`ATOL`
relative to the outputs' spread), so the fast path never silently disagrees with the model.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from invphys.inverter.numeric import Program

RTOL = 1e-4
ATOL = 1e-4


class NotExportable(Exception):
    """A module the exporter has no NumPy form for."""


def _np(t: Any) -> np.ndarray:
    return t.detach().cpu().double().numpy().astype(np.float32)


def sequential_ops(module: Any, prefix: str, arrays: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """Ops of a chain of Linear / ReLU / Tanh / Sigmoid / Identity / Dropout modules (nested Sequentials)."""
    from torch import nn

    ops: list[dict[str, Any]] = []
    mods = list(module) if isinstance(module, nn.Sequential) else [module]
    for i, m in enumerate(mods):
        key = f"{prefix}{i}"
        if isinstance(m, nn.Sequential):
            ops += sequential_ops(m, f"{key}.", arrays)
        elif isinstance(m, nn.Linear) or _is_plain_linear(m):
            arrays[f"{key}.w"] = _np(m.weight).T.copy()
            arrays[f"{key}.b"] = _np(m.bias) if m.bias is not None else np.zeros(m.out_features, np.float32)
            ops.append({"op": "linear", "w": f"{key}.w", "b": f"{key}.b"})
        elif isinstance(m, nn.ReLU):
            ops.append({"op": "relu"})
        elif isinstance(m, nn.Tanh):
            ops.append({"op": "tanh"})
        elif isinstance(m, nn.Sigmoid):
            ops.append({"op": "sigmoid"})
        elif isinstance(m, (nn.Identity, nn.Dropout)):
            continue
        else:
            raise NotExportable(type(m).__name__)
    return ops


def _is_plain_linear(m: Any) -> bool:
    """zuko's ``Linear`` (not an ``nn.Linear`` subclass) without a stack dimension."""
    return (type(m).__name__ == "Linear" and type(m).__module__.startswith("zuko")
            and getattr(m, "weight", None) is not None and m.weight.dim() == 2)


def _close(a: np.ndarray, b: np.ndarray, scale: np.ndarray | None = None) -> bool:
    """``a`` equals ``b`` within RTOL, or ATOL times the per-column magnitude of ``scale`` (default ``b``)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or not np.all(np.isfinite(a)):
        return False
    ref = b if scale is None else np.asarray(scale, dtype=np.float64)
    spread = np.maximum(np.abs(ref).max(axis=tuple(range(ref.ndim - 1))), 1e-12)
    return bool(np.all(np.abs(a - b) <= ATOL * spread + RTOL * np.abs(b)))


# -- surrogate -----------------------------------------------------------------------------------
def surrogate_program(surrogate: Any, d: int, seed: int = 0) -> Program | None:
    """The folded SkipMLP member stack of an ``mlp``/``ensemble`` surrogate: x (B, d) -> (K, B, M)."""
    folded_fn = getattr(surrogate, "_folded_net", None)
    if folded_fn is None:
        return None
    try:
        folded = folded_fn()
        (w1, b1), (w2, b2), (w3, b3) = folded.layers
        arrays = {"s.w1": _np(w1), "s.b1": _np(b1), "s.w2": _np(w2), "s.b2": _np(b2), "s.w3": _np(w3),
                  "s.b3": _np(b3), "s.wo": _np(folded.w_out), "s.bo": _np(folded.b_out)}
    except (AttributeError, ValueError, TypeError):
        return None
    act = getattr(folded, "act", "relu")
    prog = Program([{"op": "skip_mlp", "prefix": "s.", **({"act": act} if act != "relu" else {})}], arrays)
    x = np.random.default_rng(seed).uniform(0, 1, (64, d))
    mean, std = surrogate.predict_with_uncertainty(x)
    out = prog(x).astype(np.float64)
    if not (_close(out.mean(axis=0), mean) and _close(out.std(axis=0), std, scale=mean)):
        return None
    return prog


# -- latent models -------------------------------------------------------------------------------
def decoder_program(latent: Any, seed: int = 0) -> Program | None:
    """z (B, k) -> theta (B, d) clipped to [0, 1], for the ``vae`` (decoder MLP) and ``realnvp`` models."""
    net = getattr(latent, "_net", None)
    if net is None:
        return None
    arrays: dict[str, np.ndarray] = {}
    try:
        if hasattr(net, "decoder"):
            ops = sequential_ops(net.decoder, "dec.", arrays)
        elif hasattr(net, "proj_out") and hasattr(net, "flow"):
            ops = [_flow_inverse_op(net, arrays), *sequential_ops(net.proj_out, "proj.", arrays)]
        else:
            return None
    except (NotExportable, AttributeError):
        return None
    prog = Program([*ops, {"op": "clip", "low": 0.0, "high": 1.0}], arrays)
    b = float(latent.latent_bound)
    z = np.random.default_rng(seed).uniform(-b, b, (64, latent.latent_dim))
    return prog if _close(prog(z), latent.decode(z)) else None


def _flow_inverse_op(net: Any, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    import torch

    couplings = []
    for i, t in enumerate(net.flow.transforms):
        ia, ib = torch.nonzero(t.mask).flatten(), torch.nonzero(~t.mask).flatten()
        back = torch.argsort(torch.cat([ia, ib]))
        key = f"flow{i}."
        arrays[f"{key}ia"], arrays[f"{key}ib"], arrays[f"{key}back"] = (v.numpy().astype(np.int64)
                                                                       for v in (ia, ib, back))
        couplings.append({"ia": f"{key}ia", "ib": f"{key}ib", "back": f"{key}back",
                          "hyper": sequential_ops(t.hyper, f"{key}h.", arrays)})
    return {"op": "coupling_inverse", "bound": float(net.scale_bound), "couplings": couplings}


def head_program(latent: Any, seed: int = 0) -> Program | None:
    """z (B, k) -> features (B, M) through a latent model's own head (the ``own_head`` evaluator)."""
    net = getattr(latent, "_net", None)
    if net is None or not hasattr(net, "head") or not hasattr(net, "y_mean"):
        return None
    arrays: dict[str, np.ndarray] = {}
    try:
        ops = sequential_ops(net.head, "head.", arrays)
    except NotExportable:
        return None
    arrays["head.scale"], arrays["head.shift"] = _np(net.y_std), _np(net.y_mean)
    prog = Program([*ops, {"op": "affine", "scale": "head.scale", "shift": "head.shift"}], arrays)
    b = float(latent.latent_bound)
    z = np.random.default_rng(seed).uniform(-b, b, (64, latent.latent_dim))
    try:
        ref = latent.predict_features(z)
    except NotImplementedError:
        return None
    return prog if _close(prog(z), ref) else None


# -- policies --------------------------------------------------------------------------------------
def actor_program(model: Any, obs_dim: int, seed: int = 0) -> tuple[Program, np.ndarray] | None:
    """(program obs -> mean action, log_std) of a stable-baselines3 PPO ``MlpPolicy`` (shared extractor).

    Checked against ``model.predict(obs, deterministic=True)``.
    """
    policy = getattr(model, "policy", None)
    try:
        from torch import nn

        if policy is None:  # not a stable-baselines3 model
            return None
        if not isinstance(policy.features_extractor, nn.Flatten) and \
                type(policy.features_extractor).__name__ != "FlattenExtractor":
            return None
        arrays: dict[str, np.ndarray] = {}
        ops = sequential_ops(policy.mlp_extractor.policy_net, "pi.", arrays)
        ops += sequential_ops(policy.action_net, "act.", arrays)
        log_std = _np(policy.log_std)
    except (NotExportable, AttributeError):
        return None
    prog = Program(ops, arrays)
    obs = np.random.default_rng(seed).normal(0, 1, (64, obs_dim)).astype(np.float32)
    ref, _ = model.predict(obs, deterministic=True)
    mine = np.clip(prog(obs), -1.0, 1.0)
    return (prog, log_std) if _close(mine, np.asarray(ref)) else None
