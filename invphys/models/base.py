"""The common part of the torch-backed model plugins: training settings, save/load and metadata.

Import-light: torch is imported inside methods. A saved model is a directory holding

* ``model.json``: plugin name and kind, config, input/output sizes, the training data's fingerprint,
  metrics and free-form ``info`` (feature and parameter names, dataset fingerprint, ...);
* ``weights.pt``: the network's state dict (standardisers included);
* ``history.json``: per-epoch training curves.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field, ValidationError

from invphys.core.atomic import write_json
from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig
from invphys.models.data import ModelLoadError, NotFittedError, check_input

FORMAT_VERSION = 1
MODEL_FILE = "model.json"
WEIGHTS_FILE = "weights.pt"
HISTORY_FILE = "history.json"
#: largest input or output size a saved model may declare
MAX_DIM = 100_000


class TrainingConfig(PluginConfig):
    """Training settings shared by every learned model."""

    seed: int = Field(0, description="seed of weight init, batching, dropout and the validation split")
    device: Literal["auto", "cpu", "cuda"] = Field("cpu", description="torch device; auto = CUDA if available")
    lr: float = Field(1e-3, gt=0, description="Adam learning rate")
    weight_decay: float = Field(1e-4, ge=0, description="Adam weight decay")
    batch_size: int = Field(64, ge=2, description="mini-batch size")
    max_epochs: int = Field(1000, ge=1, description="upper bound on training epochs")
    patience: int = Field(50, ge=1, description="early stopping: epochs without a better validation loss")
    threads: int = Field(
        1, ge=0, description="torch CPU threads while training (0 = torch's default); small nets train fastest on 1")
    val_fraction: float = Field(
        0.2, gt=0, lt=1,
        description="held-out fraction used for early stopping and metrics when fit() gets no validation set")


class TorchModel:
    """Mixin for plugins backed by one torch module in ``self._net``.

    Subclasses set ``self._net``, ``self.dims`` (d, M) and ``self.metrics`` in ``fit`` and implement
    :meth:`_build_net`.
    """

    name: ClassVar[str]
    kind: ClassVar[str]
    config: Any

    def _init_state(self) -> None:
        self._net: Any = None
        self.dims: tuple[int, int] | None = None
        self.metrics: dict[str, Any] = {}
        self.history: dict[str, Any] = {}
        self.data_fingerprint: str | None = None
        #: free-form provenance saved with the model (feature_names, param_names, dataset fingerprint, ...)
        self.info: dict[str, Any] = {}
        self._device: Any = None
        self._folded: Any = None

    def _record_fit(self, theta: np.ndarray, y: np.ndarray, n_train: int, val: tuple[np.ndarray, np.ndarray],
                    history: dict[str, Any], epochs: Any, best_epoch: Any, train_time_s: float,
                    **extra: Any) -> dict[str, Any]:
        """Store what a finished ``fit`` leaves behind (dims, data fingerprint, history, metrics)."""
        from invphys.models.data import array_fingerprint

        self._folded = None
        self.dims = (theta.shape[1], y.shape[1])
        self.data_fingerprint = array_fingerprint(theta, y)
        self.history = history
        tv, yv = val
        self.metrics = {**self.evaluate(tv, yv), **extra, "n_train": n_train, "n_val": len(tv),  # type: ignore[attr-defined]
                        "epochs": epochs, "best_epoch": best_epoch, "train_time_s": round(train_time_s, 3)}
        return self.metrics

    # -- to implement ----------------------------------------------------------------------------
    def _build_net(self, d: int, m: int) -> Any:
        raise NotImplementedError

    # -- helpers ---------------------------------------------------------------------------------
    @property
    def fitted(self) -> bool:
        return self._net is not None

    def _require_fitted(self) -> None:
        if self._net is None:
            raise NotFittedError(f"{self.kind} {self.name!r} is not fitted: call fit() or load() first")

    @property
    def device(self) -> Any:
        if self._device is None:
            from invphys.models.torch_utils import pick_device

            self._device = pick_device(self.config.device)
        return self._device

    def _input(self, x: Any, label: str = "theta") -> Any:
        """``x`` as a float32 tensor on the model's device; ``label`` "theta" (B, d) or "z" (B, k)."""
        import torch

        self._require_fitted()
        dim = self.dims[0] if label == "theta" else self.latent_dim  # type: ignore[index, attr-defined]
        arr = check_input(x, dim, label, f"{self.kind} {self.name!r}")
        return torch.from_numpy(arr).to(self.device)

    # -- persistence -----------------------------------------------------------------------------
    def save(self, directory: str | Path) -> Path:
        """Write ``model.json``, ``weights.pt`` and ``history.json`` under ``directory``; return it."""
        import torch

        self._require_fitted()
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        meta = {
            "format": FORMAT_VERSION, "plugin": self.name, "kind": self.kind,
            "config": self.config.model_dump(mode="json"),
            "dims": {"d": self.dims[0], "m": self.dims[1]},  # type: ignore[index]
            "data_fingerprint": self.data_fingerprint, "metrics": self.metrics, "info": self.info,
            "saved_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        state = {k: v.detach().cpu() for k, v in self._net.state_dict().items()}
        tmp = directory / f".{WEIGHTS_FILE}.tmp{os.getpid()}"
        torch.save(state, tmp)
        os.replace(tmp, directory / WEIGHTS_FILE)
        write_json(directory / HISTORY_FILE, self.history)
        write_json(directory / MODEL_FILE, meta)  # written last: its presence marks a complete save
        return directory

    @classmethod
    def load(cls, directory: str | Path, device: str | None = None) -> Any:
        """Rebuild a model saved by :meth:`save` (same predictions); ``device`` overrides the saved one."""

        directory = Path(directory)
        meta_path = directory / MODEL_FILE
        if not meta_path.is_file() or not (directory / WEIGHTS_FILE).is_file():
            raise ModelLoadError(f"no saved model in {directory} (expected {MODEL_FILE} and {WEIGHTS_FILE})")
        meta = read_json_mapping(meta_path)
        if meta.get("plugin") != cls.name or meta.get("kind") != cls.kind:
            raise ModelLoadError(
                f"{directory} holds a {meta.get('kind')} {meta.get('plugin')!r}, not a {cls.kind} {cls.name!r}")
        if not isinstance(meta.get("config"), dict):
            raise ModelLoadError(f"{meta_path}: no config mapping")
        config = {**getattr(cls, "LEGACY", {}), **meta["config"]}
        if device is not None:
            config["device"] = device
        try:
            model = cls(config)  # type: ignore[call-arg]
        except ValidationError as exc:
            err = exc.errors()[0]
            key = ".".join(str(k) for k in err.get("loc", ())) or "config"
            raise ModelLoadError(f"{meta_path}: saved config no longer valid (config.{key}: "
                                 f"{err.get('msg', 'invalid')})") from None
        dims = meta.get("dims") if isinstance(meta.get("dims"), dict) else {}
        d, m = dims.get("d"), dims.get("m")
        if not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_DIM for v in (d, m)):
            raise ModelLoadError(f"{meta_path}: dims.d and dims.m must be integers from 1 to {MAX_DIM:,}")
        assert isinstance(d, int) and isinstance(m, int)
        model.dims = (d, m)
        state = load_torch_weights(directory / WEIGHTS_FILE)
        shapes = _meta_shapes(model, d, m)  # sizes first, allocating nothing: a hostile config builds no giant net
        if shapes is not None:
            check_state(shapes, state, directory / WEIGHTS_FILE, "the saved config")
        net = model._build_net(d, m)
        check_state(net.state_dict(), state, directory / WEIGHTS_FILE, "the saved config")
        try:
            net.load_state_dict(state)
        except RuntimeError as exc:
            reason = str(exc).strip().splitlines()[-1].strip()
            raise ModelLoadError(f"{directory / WEIGHTS_FILE}: weights do not fit the saved config ({reason})") from None
        model._net = net.to(model.device).eval()
        model.metrics = meta.get("metrics", {})
        model.data_fingerprint = meta.get("data_fingerprint")
        model.info = meta.get("info", {})
        hist = directory / HISTORY_FILE
        model.history = read_json_mapping(hist) if hist.is_file() else {}
        return model


def _meta_shapes(model: Any, d: int, m: int) -> dict[str, Any] | None:
    """The state dict ``model._build_net(d, m)`` would have, built on torch's meta device (no memory);
    None when the network cannot be built there (then the real build is checked instead)."""
    import torch

    if min(d, m) < 1:
        raise ModelLoadError(f"{model.kind} {model.name!r}: saved dims d={d}, m={m} must be >= 1")
    try:
        with torch.device("meta"):
            return dict(model._build_net(d, m).state_dict())
    except Exception:  # a plugin whose build computes on data: no pre-check
        return None


# -- weight files: read without running code ----------------------------------------------------
class LegacyPickleError(ModelLoadError):
    """A saved part in an older format that only unpickling (running code stored in the file) could load."""

    def __init__(self, path: Path) -> None:
        self.path = path
        super().__init__(f"{path} is a pickled object from an older invphys; loading it would run code stored "
                         f"in the file, so it is refused")


def first_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


def read_json_mapping(path: Path) -> dict[str, Any]:
    """A JSON object from ``path``, or a :class:`ModelLoadError` naming the file."""
    from invphys.core.safe_read import load_user_json

    try:
        data = load_user_json(path, what="saved model description")
    except InvphysError as exc:
        raise ModelLoadError(str(exc)) from None
    except RecursionError:
        raise ModelLoadError(f"{path}: JSON nested too deeply") from None
    if not isinstance(data, dict):
        raise ModelLoadError(f"{path}: not a JSON object")
    return data


def load_torch_weights(path: Path) -> dict[str, Any]:
    """A state dict saved with ``torch.save``, read with ``weights_only=True`` (tensors and plain containers
    only: a pickle that would run code is refused by torch); every failure is one line naming the file."""
    import torch

    from invphys.core.safe_read import NPZ_MAX_BYTES, check_regular_file

    try:
        check_regular_file(path, what="weights file", max_bytes=NPZ_MAX_BYTES)
    except InvphysError as exc:
        raise ModelLoadError(str(exc)) from None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ... for foreign files
        raise ModelLoadError(f"{path}: not a weights file invphys loads without running code ({first_line(exc)})") from None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ModelLoadError(f"{path}: not a state dict of tensors")
    return state


def read_weights_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of a weights ``.npz``, read with ``allow_pickle=False``; anything else (a pickle, an
    object array, a damaged archive) is a :class:`ModelLoadError` naming the file."""
    from invphys.core.safe_read import UserFileError, load_user_npz

    try:
        arrays = load_user_npz(path, what="weights archive")
    except UserFileError as exc:
        raise ModelLoadError(f"{path}: not a weights archive invphys loads without running code ({exc.problem})") \
            from None
    bad = [k for k, v in arrays.items() if v.dtype.kind not in "fiub"]
    if bad:
        raise ModelLoadError(f"{path}: array {bad[0]} holds {arrays[bad[0]].dtype}, not numbers")
    return arrays


def check_state(expected: dict[str, Any], saved: dict[str, Any], where: Path, what: str = "the network") -> None:
    """Refuse saved weights whose names or shapes differ from the rebuilt network's, in one line that names
    the first differing tensor."""
    missing = [k for k in expected if k not in saved]
    extra = [k for k in saved if k not in expected]
    if missing or extra:
        part = f"lacks {missing[0]}" if missing else f"has an unexpected tensor {extra[0]}"
        raise ModelLoadError(f"{where}: the weights do not fit {what} ({part})")
    for k, t in expected.items():
        if tuple(t.shape) != tuple(saved[k].shape):
            raise ModelLoadError(f"{where}: the weights do not fit {what} ({k} has shape {tuple(saved[k].shape)}, "
                                 f"the network needs {tuple(t.shape)})")


def validation_split(theta: np.ndarray, y: np.ndarray, validation: tuple[np.ndarray, np.ndarray] | None,
                     val_fraction: float, seed: int, name: str) -> tuple[np.ndarray, ...]:
    """(theta_train, y_train, theta_val, y_val): the given validation set, or a seeded split."""
    from invphys.models.data import check_training_data, split_indices

    if validation is not None:
        tv, yv = np.asarray(validation[0], dtype=np.float64), np.asarray(validation[1], dtype=np.float64)
        if tv.ndim != 2 or yv.ndim != 2 or tv.shape[1] != theta.shape[1] or yv.shape[1] != y.shape[1] \
                or len(tv) != len(yv) or len(tv) == 0:
            raise InvphysError(f"{name}: validation arrays must have shapes (n, {theta.shape[1]}) and "
                               f"(n, {y.shape[1]}), got {tv.shape} and {yv.shape}")
        if not (np.isfinite(tv).all() and np.isfinite(yv).all()):
            raise InvphysError(f"{name}: validation arrays have non-finite values")
        return theta, y, tv, yv
    check_training_data(theta, y, name)
    tr, va = split_indices(len(theta), val_fraction, seed)
    return theta[tr], y[tr], theta[va], y[va]
