"""NumPy inference forms of the bundle's networks, so that answering a target needs no torch.

A :class:`Program` is a list of operations over named float32 arrays, stored as one ``.npz`` (the
operation list is a JSON string inside it; nothing is pickled). Operations:

* ``linear`` (``x @ w + b``), ``relu``, ``tanh``, ``sigmoid``, ``clip``, ``affine`` (``x * scale + shift``);
* ``skip_mlp``: K stacked surrogate networks (batch norm folded) -> (K, B, M); hidden activation ``act``
  "relu" (the default, and all a program written before ``act`` existed holds) or "silu";
* ``coupling_inverse``: the inverse of RealNVP affine couplings (the flow's decoder).

:mod:`invphys.inverter.export` builds programs from trained torch models and keeps one only when it
reproduces the model's own outputs; the bundle falls back to the torch model otherwise.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

PROGRAM_KEY = "__program__"


class Program:
    """A sequence of array operations (see the module docstring); call it on a (B, n) array."""

    def __init__(self, ops: list[dict[str, Any]], arrays: dict[str, np.ndarray]) -> None:
        self.ops = ops
        self.arrays = {k: np.ascontiguousarray(v, dtype=np.float32) if v.dtype.kind == "f" else v
                       for k, v in arrays.items()}

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return run_ops(self.ops, self.arrays, np.asarray(x, dtype=np.float32))

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:  # np.savez on a handle keeps the name (no ".npz" appended)
            # numpy's stub types savez's `allow_pickle: bool` keyword, and mypy cannot tell that these
            # ** mappings (array names -> arrays) never hold that key: a third-party typing limitation
            np.savez(fh, **{PROGRAM_KEY: np.array(json.dumps(self.ops))}, **self.arrays)  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: str | Path) -> Program:
        with np.load(path, allow_pickle=False) as data:
            ops = json.loads(str(data[PROGRAM_KEY]))
            arrays = {k: data[k] for k in data.files if k != PROGRAM_KEY}
        return cls(ops, arrays)


def run_ops(ops: list[dict[str, Any]], arrays: dict[str, np.ndarray], x: np.ndarray) -> np.ndarray:
    """Apply ``ops`` to ``x`` (float32); works in place on arrays it made itself, never on ``x``."""
    owned = False
    for op in ops:
        kind = op["op"]
        if kind == "linear":
            x = x @ arrays[op["w"]]
            x += arrays[op["b"]]
            owned = True
            continue
        if kind in ("relu", "tanh", "sigmoid", "clip") and not owned:
            x, owned = x.copy(), True
        if kind == "relu":
            np.maximum(x, 0.0, out=x)
        elif kind == "tanh":
            np.tanh(x, out=x)
        elif kind == "sigmoid":
            x *= 0.5
            np.tanh(x, out=x)
            x += 1.0
            x *= 0.5
        elif kind == "clip":
            np.clip(x, op["low"], op["high"], out=x)
        elif kind == "affine":
            x, owned = x * arrays[op["scale"]] + arrays[op["shift"]], True
        elif kind == "skip_mlp":
            x, owned = _skip_mlp(arrays, op["prefix"], x, op.get("act", "relu")), True
        elif kind == "coupling_inverse":
            x, owned = _coupling_inverse(arrays, op, x), True
        else:
            raise ValueError(f"unknown inference operation {kind!r}")
    return x


def _silu(x: np.ndarray) -> None:
    """In place: x * sigmoid(x), with sigmoid(x) = (1 + tanh(x / 2)) / 2 (no overflow)."""
    s = np.tanh(x * 0.5)
    s += 1.0
    s *= 0.5
    x *= s


def _relu(x: np.ndarray) -> None:
    np.maximum(x, 0.0, out=x)


def _skip_mlp(arrays: dict[str, np.ndarray], p: str, x: np.ndarray, act: str = "relu") -> np.ndarray:
    """K folded SkipMLPs: a = f(x W1 + b1), c = f(a W2 + b2), h = f([a, c] W3 + b3), h Wo + bo.

    ``f`` is ReLU or SiLU (``act``). One 2-D (BLAS) product per layer and member; ``[a, c] W3`` is
    split as ``a W3[:h1] + c W3[h1:]``.
    """
    if act not in ("relu", "silu"):
        raise ValueError(f"unknown skip_mlp activation {act!r}")
    f = _relu if act == "relu" else _silu
    w1, b1, w2, b2, w3, b3, wo, bo = (arrays[f"{p}{k}"] for k in ("w1", "b1", "w2", "b2", "w3", "b3", "wo", "bo"))
    x = np.ascontiguousarray(x.reshape(-1, w1.shape[1]))
    h1 = w1.shape[2]
    out = np.empty((w1.shape[0], x.shape[0], wo.shape[2]), dtype=np.float32)
    for k in range(w1.shape[0]):
        a = x @ w1[k]
        a += b1[k]
        f(a)
        c = a @ w2[k]
        c += b2[k]
        f(c)
        h = a @ w3[k, :h1]
        h += c @ w3[k, h1:]
        h += b3[k]
        f(h)
        np.matmul(h, wo[k], out=out[k])
        out[k] += bo[k]
    return out


def _coupling_inverse(arrays: dict[str, np.ndarray], op: dict[str, Any], z: np.ndarray) -> np.ndarray:
    bound = float(op["bound"])
    for c in reversed(op["couplings"]):
        ia, ib, back = (arrays[c[k]] for k in ("ia", "ib", "back"))
        xa = z[:, ia]
        phi = run_ops(c["hyper"], arrays, xa).reshape(len(z), -1, 2)
        shift, log_scale = phi[..., 0], bound * np.tanh(phi[..., 1])
        yb = (z[:, ib] - shift) * np.exp(-log_scale)
        z = np.concatenate([xa, yb], axis=1)[:, back]
    return z
