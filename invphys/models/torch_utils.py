"""Torch helpers shared by every learned model: device choice, seeding and the training loop.

This module imports torch at top level; plugins import it inside their methods only.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from invphys.core.errors import DeviceUnavailableError


def pick_device(name: str) -> torch.device:
    """``"cpu"``, ``"cuda"`` (error when there is no GPU) or ``"auto"`` (CUDA when available)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise DeviceUnavailableError("device 'cuda' was requested but torch sees no CUDA GPU; use 'cpu' or 'auto'")
    return torch.device(name)


@contextmanager
def seeded(seed: int, device: torch.device) -> Iterator[None]:
    """Run a block with torch's global RNG seeded, restoring the caller's RNG state afterwards."""
    devices = [device.index or 0] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        yield


@contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run a block with ``n`` intra-op torch threads (0 = leave torch's setting), then restore it.

    Small networks train several times faster on one thread than on a contended multi-core CPU.
    """
    if n <= 0:
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def to_tensor(x: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float32), device=device)


@dataclass
class History:
    """Per-epoch training curves and where early stopping settled."""

    train_loss: list[float] = field(default_factory=list)
    val_loss: list[float] = field(default_factory=list)
    parts: dict[str, list[float]] = field(default_factory=dict)
    best_epoch: int = 0
    best_val_loss: float = float("inf")
    epochs: int = 0
    stopped_early: bool = False
    train_time_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "train_loss": self.train_loss, "val_loss": self.val_loss, "parts": self.parts,
            "best_epoch": self.best_epoch, "best_val_loss": self.best_val_loss, "epochs": self.epochs,
            "stopped_early": self.stopped_early, "train_time_s": self.train_time_s,
        }


#: loss_fn(batch, epoch) -> (loss, parts); ``epoch=None`` means "validation: use the final weights"
LossFn = Callable[[tuple[torch.Tensor, ...], int | None], tuple[torch.Tensor, dict[str, float]]]


def fit_loop(module: nn.Module, loss_fn: LossFn, train: tuple[torch.Tensor, ...],
             val: tuple[torch.Tensor, ...], *, lr: float, weight_decay: float, batch_size: int,
             max_epochs: int, patience: int, min_epochs: int = 0, seed: int = 0,
             progress: bool = False, description: str = "training", tracker: Any = None,
             optimizer: str = "adam", schedule: str = "constant") -> History:
    """Adam with mini-batches and early stopping on the validation loss; restores the best weights.

    ``optimizer`` "adamw" uses decoupled weight decay; ``schedule`` "one_cycle" runs a one-cycle
    cosine learning-rate schedule over ``max_epochs`` (peak ``lr`` after 5 %, from lr/10 down to lr/1e4).

    ``tracker`` (a :class:`~invphys.tracking.Tracker`, already scoped to the model) receives
    ``train_loss``, ``val_loss`` and ``val_<part>`` for each loss part, every epoch.

    Early stopping counts from ``min_epochs`` (the end of a loss-weight warm-up), so that a loss
    whose weights still change is not compared with its final form.
    """
    start = time.perf_counter()
    opt, sched = _optimizer(module, train[0].shape[0], lr=lr, weight_decay=weight_decay, batch_size=batch_size,
                            max_epochs=max_epochs, optimizer=optimizer, schedule=schedule)
    gen = torch.Generator().manual_seed(seed)
    hist = History()
    best_state = copy.deepcopy(module.state_dict())
    since_best = 0
    bar = _Bar(progress, description, max_epochs)
    try:
        for epoch in range(max_epochs):
            train_loss = _train_epoch(module, loss_fn, train, opt, sched, gen, batch_size, epoch)
            module.eval()
            with torch.no_grad():
                vloss, parts = loss_fn(val, None)
            vloss_f = float(vloss)
            hist.train_loss.append(train_loss)
            hist.val_loss.append(vloss_f)
            for k, v in parts.items():
                hist.parts.setdefault(k, []).append(float(v))
            hist.epochs = epoch + 1
            if tracker is not None:
                tracker.log_scalars({"train_loss": hist.train_loss[-1], "val_loss": vloss_f,
                                     **{f"val_{k}": float(v) for k, v in parts.items()}}, epoch)
            if not np.isfinite(vloss_f) or not np.isfinite(hist.train_loss[-1]):
                raise FloatingPointError(f"{description}: loss became non-finite at epoch {epoch}")
            if vloss_f < hist.best_val_loss:
                hist.best_val_loss = vloss_f
                hist.best_epoch = epoch
                best_state = copy.deepcopy(module.state_dict())
                since_best = 0
            elif epoch >= min_epochs:
                since_best += 1
            bar.update(epoch, hist.train_loss[-1], vloss_f)
            if since_best >= patience:
                hist.stopped_early = True
                break
    finally:
        bar.close()
    module.load_state_dict(best_state)
    module.eval()
    if tracker is not None:
        tracker.flush()
    hist.train_time_s = time.perf_counter() - start
    return hist


def _optimizer(module: nn.Module, n: int, *, lr: float, weight_decay: float, batch_size: int, max_epochs: int,
               optimizer: str, schedule: str) -> tuple[Any, Any]:
    """The optimiser (Adam, or AdamW for ``"adamw"``) and the learning-rate schedule (None: constant)."""
    opt_cls = torch.optim.AdamW if optimizer == "adamw" else torch.optim.Adam
    opt = opt_cls(module.parameters(), lr=lr, weight_decay=weight_decay)
    sched = None
    if schedule == "one_cycle":
        steps = max_epochs * max(1, -(-n // batch_size))
        # 5 % warm-up; at least 2.5 steps of it, else torch's phase boundaries coincide (division by zero)
        warmup = min(0.5, max(0.05, 2.5 / steps))
        if steps >= 6:
            sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=warmup,
                                                        anneal_strategy="cos", div_factor=10, final_div_factor=1e3)
    return opt, sched


def _train_epoch(module: nn.Module, loss_fn: LossFn, train: tuple[torch.Tensor, ...], opt: Any, sched: Any,
                 gen: torch.Generator, batch_size: int, epoch: int) -> float:
    """One pass over ``train`` in shuffled mini-batches; the mean training loss per row."""
    module.train()
    n = train[0].shape[0]
    perm = torch.randperm(n, generator=gen).to(train[0].device)
    total, count = 0.0, 0
    for i in range(0, n, batch_size):
        idx = perm[i:i + batch_size]
        if idx.numel() < 2 and n >= 2:  # batch norm needs 2 rows; fold a lone row away
            continue
        batch = tuple(t[idx] for t in train)
        loss, _ = loss_fn(batch, epoch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if sched is not None:
            sched.step()
        total += float(loss.detach()) * idx.numel()
        count += idx.numel()
    return total / max(count, 1)


class _Bar:
    """A rich progress bar over epochs (no-op when ``enabled`` is False)."""

    def __init__(self, enabled: bool, description: str, total: int) -> None:
        self.progress = None
        if enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TextColumn("{task.fields[loss]}"), TimeElapsedColumn(), transient=False)
            self.progress.start()
            self.task = self.progress.add_task(description, total=total, loss="")

    def update(self, epoch: int, train_loss: float, val_loss: float) -> None:
        if self.progress is not None:
            self.progress.update(self.task, completed=epoch + 1,
                                 loss=f"train {train_loss:.4g} val {val_loss:.4g}")

    def close(self) -> None:
        if self.progress is not None:
            self.progress.stop()
