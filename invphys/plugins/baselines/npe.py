"""The amortised posterior baseline: neural posterior estimation with the ``sbi`` library."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import Field

from invphys.core.errors import InvphysError
from invphys.core.interfaces import PluginConfig
from invphys.models.base import (
    LegacyPickleError,
    check_state,
    first_line,
    read_json_mapping,
    read_weights_npz,
)
from invphys.plugins.baselines._base import PRIOR_STD, BaselineAnswers, DatasetBaseline, best_by_surrogate


class NPEBaseline(DatasetBaseline):
    """sbi's NPE: a conditional density estimator q(theta | y) trained on the training rows.

    The prior is uniform on [0, 1]^d (the normalised parameter box the data was sampled from) and sbi
    z-scores the features. Samples outside the box (a flow's leakage: 43 % on the tiny orange-peel
    fixture) are clipped to it, and the fraction is reported as ``leakage``. With ``transform: logit``
    the estimator learns the density of logit(theta) instead, so every sample lies in the box (its
    log-probs include the Jacobian); on the tiny fixture that fitted worse (mean |error| 0.20 vs 0.18). Each target gets ``samples`` posterior draws; the answer is their ``mean``,
    the draw of highest posterior log-prob (``best_log_prob``), or the draw the surrogate scores best
    (``best_surrogate``: ``samples`` surrogate evaluations). Each parameter's posterior std, in units of
    the prior's std, says how well the features pin it down (about 1: not at all).
    """

    name: ClassVar[str] = "npe"
    extra: ClassVar[str] = "sbi"
    #: config keys that change answers but not the trained estimator
    answer_keys: ClassVar[tuple[str, ...]] = ("samples", "answer", "uncertainty_penalty")
    #: the trained sbi posterior and the feature scales (set by fitting or loading)
    _posterior: Any
    _scales: Any  # np.ndarray (M,), or None for a save without scales

    class Config(PluginConfig):
        estimator: Literal["maf", "nsf", "mdn"] = Field("maf", description="sbi density estimator")
        hidden_features: int = Field(50, ge=4)
        num_transforms: int = Field(5, ge=1, description="flow layers (maf/nsf)")
        training_batch_size: int = Field(64, ge=8)
        learning_rate: float = Field(1e-3, gt=0)
        max_num_epochs: int = Field(300, ge=1)
        stop_after_epochs: int = Field(20, ge=1, description="early-stopping patience on sbi's validation split")
        samples: int = Field(64, ge=1, le=100_000, description="posterior draws per target")
        answer: Literal["mean", "best_log_prob", "best_surrogate"] = Field("best_log_prob")
        uncertainty_penalty: float = Field(
            0.0, ge=0, description="best_surrogate: score = R - lambda x the ensemble's normalised std (0: plain R)")
        transform: Literal["none", "logit"] = Field(
            "none", description="logit: learn logit(theta), so samples stay in the box (on the tiny fixture: "
                                "no leakage but a larger error)")
        seed: int = 0
        torch_threads: int | None = Field(1, ge=1, le=1024, description="torch CPU threads while training (None: torch's)")

    @property
    def evaluation_budget(self) -> int:
        return self.config.samples if self.config.answer == "best_surrogate" else 1

    def fit_key(self) -> str:
        """Identifies the trained estimator: baselines with equal keys can share one fit."""
        cfg = {k: v for k, v in self.config.model_dump().items() if k not in self.answer_keys}
        return json.dumps({"type": self.name, **cfg}, sort_keys=True)

    def adopt(self, other: NPEBaseline) -> NPEBaseline:
        """Use ``other``'s trained posterior (same :meth:`fit_key`) instead of training again."""
        self._posterior, self._scales = other._posterior, other._scales
        self.metrics, self.fitted = {**other.metrics, "shared_fit": True}, True
        return self

    @staticmethod
    def _imports() -> Any:
        try:
            import sbi.inference
            import sbi.neural_nets
            import sbi.utils
        except ImportError as exc:
            raise InvphysError(f"the npe baseline needs the sbi library: pip install 'invphys[sbi]' ({exc})") from exc
        return sbi

    def _fit(self, theta: np.ndarray, y: np.ndarray, scales: np.ndarray, progress: bool) -> dict[str, Any]:
        import torch

        sbi = self._imports()
        c = self.config
        old_threads = torch.get_num_threads()
        if c.torch_threads:
            torch.set_num_threads(c.torch_threads)
        try:
            torch.manual_seed(c.seed)
            prior = self._prior(theta.shape[1])
            kwargs = {"hidden_features": c.hidden_features}
            if c.estimator != "mdn":
                kwargs["num_transforms"] = c.num_transforms
            net = sbi.neural_nets.posterior_nn(model=c.estimator, **kwargs)
            inference = sbi.inference.NPE(prior=prior, density_estimator=net, show_progress_bars=progress,
                                          tracker=_NoTracker())  # sbi's default writes ./sbi-logs
            inference.append_simulations(torch.as_tensor(self._to_u(theta), dtype=torch.float32),
                                         torch.as_tensor(y, dtype=torch.float32))
            inference.train(training_batch_size=c.training_batch_size, learning_rate=c.learning_rate,
                            max_num_epochs=c.max_num_epochs, stop_after_epochs=c.stop_after_epochs,
                            show_train_summary=False)
            self._posterior = inference.build_posterior()
        finally:
            torch.set_num_threads(old_threads)
        self._scales = scales
        summary = getattr(inference, "_summary", {})
        return {"epochs": int(summary.get("epochs_trained", [0])[-1]),
                "best_validation_log_prob": float(summary.get("best_validation_loss", [np.nan])[-1])}

    _EPS = 1e-6

    def _to_u(self, theta: np.ndarray) -> np.ndarray:
        t = np.clip(np.asarray(theta, dtype=np.float64), 0.0, 1.0)
        if self.config.transform != "logit":
            return t
        t = np.clip(t, self._EPS, 1.0 - self._EPS)
        return np.log(t) - np.log1p(-t)

    def posterior_samples(self, targets: np.ndarray, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(samples (B, S, d), log-probs (B, S)) of the posterior at each target.

        Each target is drawn alone under a torch stream seeded from ``config.seed`` and its own values
        (:func:`~invphys.evaluators.simulator_loop.row_seed`), so its draws do not depend on its position
        or on the other targets of the batch. Samples outside [0, 1]^d are clipped to it;
        ``last_leakage`` is the fraction that was outside.
        """
        from invphys.evaluators.simulator_loop import row_seed

        n = int(n or self.config.samples)
        rows = np.atleast_2d(np.asarray(targets, dtype=np.float64))
        drawn = [self._draw_one(row, n, row_seed(self.config.seed, row, "npe")) for row in rows]
        samples = np.stack([s for s, _ in drawn]) if drawn else np.empty((0, n, self._dim()))
        logp = np.stack([lp for _, lp in drawn]) if drawn else np.empty((0, n))
        self.last_leakage = float(np.mean(np.any((samples < 0) | (samples > 1), axis=2))) if drawn else 0.0
        return np.clip(samples, 0.0, 1.0), logp

    def _dim(self) -> int:
        return int(self._posterior.posterior_estimator.input_shape[0])

    def _draw_one(self, target: np.ndarray, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """(S, d) unclipped draws and their (S,) log-probs at one target, under torch stream ``seed``: the
        estimator's own draws and densities, as sbi's ``DirectPosterior.sample_batched`` and
        ``log_prob_batched`` give them without rejection or leakage normalisation (a poorly fitted flow can
        leak most of its mass outside the box, and rejection then never ends), -inf outside the prior's support."""
        import torch

        est = self._posterior.posterior_estimator
        x = torch.as_tensor(target[None, :], dtype=torch.float32)
        with torch.random.fork_rng(devices=[]), torch.no_grad():
            torch.manual_seed(seed)
            s = est.sample(torch.Size([n]), condition=x)  # (S, 1, d)
            lp = est.log_prob(s, condition=x)  # (S, 1)
        inside = ~torch.isnan(s).any(dim=-1) if self.config.transform == "logit" else ((s >= 0) & (s <= 1)).all(dim=-1)
        lp = torch.where(inside, lp, torch.tensor(float("-inf"), dtype=torch.float32))
        samples = s.numpy().astype(np.float64)[:, 0, :]
        logp = lp.numpy().astype(np.float64)[:, 0]
        if self.config.transform == "logit":  # back to theta, with the change of variables' Jacobian
            samples = 1.0 / (1.0 + np.exp(-samples))
            logp = logp - np.log(np.clip(samples * (1.0 - samples), 1e-300, None)).sum(axis=1)
        return samples, logp

    def _answer(self, targets: np.ndarray, predict_theta: Any) -> BaselineAnswers:
        samples, logp = self.posterior_samples(targets)
        b = len(targets)
        evals = np.zeros(b, dtype=np.int64)
        if self.config.answer == "mean":
            theta = samples.mean(axis=1)
        elif self.config.answer == "best_log_prob":
            theta = samples[np.arange(b), np.argmax(logp, axis=1)]
        else:
            best, _ = best_by_surrogate(samples, targets, self._scales, predict_theta, self.penalty_fn)
            theta = samples[np.arange(b), best]
            evals[:] = samples.shape[1]
        return BaselineAnswers(theta=np.clip(theta, 0.0, 1.0), candidates=samples,
                               spread=samples.std(axis=1) / PRIOR_STD, evaluations=evals, wall_time_s=0.0,
                               info={"answer": self.config.answer, "samples": self.config.samples,
                                     "leakage": self.last_leakage,
                                     "uncertainty_penalty": self.config.uncertainty_penalty})

    def save(self, directory: str | Path) -> Path:
        """Write the trained flow as tensors (``npe_weights.npz``) and ``npe.json`` (config, architecture,
        feature scales, metrics) under ``directory``; nothing is pickled (see :meth:`load`)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        est = self._posterior.posterior_estimator
        arrays = {k: v.detach().cpu().numpy() for k, v in est.state_dict().items()}
        with open(d / WEIGHTS_FILE, "wb") as fh:  # a handle keeps the name (np.savez appends no ".npz")
            np.savez(fh, **arrays)  # type: ignore[arg-type]
        arch = {"estimator": self.config.estimator, "hidden_features": self.config.hidden_features,
                "num_transforms": self.config.num_transforms, "transform": self.config.transform,
                "theta_dim": int(est.input_shape[0]), "x_dim": int(est.condition_shape[0]),
                "sbi_version": _sbi_version()}
        meta = {"format": SAVE_FORMAT, "config": self.config.model_dump(), "architecture": arch,
                "scales": None if self._scales is None else np.asarray(self._scales, np.float64).tolist(),
                "metrics": self.metrics}
        (d / CONFIG_FILE).write_text(json.dumps(meta, indent=1))
        legacy = d / LEGACY_FILE
        if legacy.exists():  # a re-save over an older (pickled) save
            legacy.unlink()
        return d

    @classmethod
    def load(cls, directory: str | Path) -> NPEBaseline:
        """Rebuild a posterior saved by :meth:`save`: the network from code (the saved architecture; maf and
        nsf without importing sbi, :mod:`~invphys.plugins.baselines.npe_flows`), its weights from
        ``npe_weights.npz`` (``allow_pickle=False``, strict shapes), the prior from the config. Nothing is
        unpickled; an older pickled save is refused."""
        d = Path(directory)
        if not (d / CONFIG_FILE).is_file():
            raise InvphysError(f"no saved npe baseline in {d}")
        meta = read_json_mapping(d / CONFIG_FILE)
        if not (d / WEIGHTS_FILE).is_file():
            if (d / LEGACY_FILE).is_file():
                raise LegacyPickleError(d / LEGACY_FILE)
            raise InvphysError(f"no saved npe baseline in {d} (no {WEIGHTS_FILE})")
        try:
            plugin = cls(cls.Config(**meta["config"]))
            arch = meta["architecture"]
            dims = int(arch["theta_dim"]), int(arch["x_dim"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InvphysError(f"{d / CONFIG_FILE}: not an npe save this invphys reads ({first_line(exc)})") from None
        state = read_weights_npz(d / WEIGHTS_FILE)
        plugin._check_size(*dims, state, d / WEIGHTS_FILE)
        plugin._posterior = plugin._rebuild(*dims, state, d / WEIGHTS_FILE)
        try:
            scales = meta.get("scales")
            plugin._scales = None if scales is None else np.asarray(scales, dtype=np.float64).reshape(dims[1])
        except (TypeError, ValueError):
            raise InvphysError(f"{d / CONFIG_FILE}: scales must be {dims[1]} numbers, one per feature") from None
        metrics = meta.get("metrics")
        plugin.metrics = dict(metrics) if isinstance(metrics, dict) else {}
        plugin.fitted = True
        return plugin

    def _check_size(self, theta_dim: int, x_dim: int, state: dict[str, np.ndarray], where: Path) -> None:
        """Refuse, before building anything, an architecture larger than the saved weights can fill: every
        flow layer holds at least hidden_features^2 numbers (a hostile description cannot make the
        builder allocate more than the file holds)."""
        c, size = self.config, sum(int(v.size) for v in state.values())
        h, t = c.hidden_features, 1 if c.estimator == "mdn" else c.num_transforms
        if min(theta_dim, x_dim) < 1 or t * h * h > size or (theta_dim + x_dim) * h > size:
            raise InvphysError(f"{where}: the saved architecture ({c.estimator}, hidden_features {h}, num_transforms "
                               f"{t}, {theta_dim} parameters, {x_dim} features) does not fit the {size:,} saved "
                               f"numbers; refusing to build it")

    def _rebuild(self, theta_dim: int, x_dim: int, state: dict[str, np.ndarray], where: Path) -> Any:
        """The posterior of a saved flow: its network built here without sbi where this builder makes the
        saved layout (:mod:`~invphys.plugins.baselines.npe_flows`: maf and nsf), else by sbi's builder on dummy
        data of the saved shapes; the saved weights loaded strictly, and the prior the estimator was trained with."""
        from invphys.plugins.baselines.npe_flows import LoadedPosterior, load_estimator

        c = self.config
        est = load_estimator(c.estimator, c.hidden_features, c.num_transforms, theta_dim, x_dim, state)
        if est is not None:
            return LoadedPosterior(est, self._prior(theta_dim, light=True))
        return self._rebuild_with_sbi(theta_dim, x_dim, state, where)

    def _rebuild_with_sbi(self, theta_dim: int, x_dim: int, state: dict[str, np.ndarray], where: Path) -> Any:
        """:meth:`_rebuild` through sbi's builder (``mdn``, or a layout of another sbi release)."""
        import torch

        sbi = self._imports()
        c = self.config
        kwargs = {"hidden_features": c.hidden_features}
        if c.estimator != "mdn":
            kwargs["num_transforms"] = c.num_transforms
        gen = torch.Generator().manual_seed(0)  # dummy data for the builder; its z-scores are overwritten
        dummy_theta = torch.randn(64, theta_dim, generator=gen)
        dummy_x = torch.randn(64, x_dim, generator=gen)
        rng_state = torch.get_rng_state()  # building draws permutations and prior samples: keep the caller's RNG
        try:
            est = sbi.neural_nets.posterior_nn(model=c.estimator, **kwargs)(dummy_theta, dummy_x)
            check_state(est.state_dict(), state, where, "the saved architecture")
            est.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()}, strict=True)
            est.eval()
            with warnings.catch_warnings():  # the logistic prior's moments are estimated (for MAP only)
                warnings.filterwarnings("ignore", message=".*no mean or stddev attribute.*")
                return sbi.inference.posteriors.DirectPosterior(posterior_estimator=est,
                                                                prior=self._prior(theta_dim))
        finally:
            torch.set_rng_state(rng_state)

    def _prior(self, d: int, light: bool = False) -> Any:
        """The prior of the trained variable: U(0, 1)^d (sbi's ``BoxUniform``, or the same distribution from
        torch alone with ``light``), or its logit (the standard logistic) for ``logit``."""
        import torch

        if self.config.transform == "logit":
            base = torch.distributions.Uniform(torch.zeros(d), torch.ones(d))
            return torch.distributions.Independent(torch.distributions.TransformedDistribution(
                base, [torch.distributions.transforms.SigmoidTransform().inv]), 1)
        if light:
            return torch.distributions.Independent(torch.distributions.Uniform(torch.zeros(d), torch.ones(d)), 1)
        return self._imports().utils.BoxUniform(torch.zeros(d), torch.ones(d))

    @classmethod
    def load_legacy_pickle(cls, directory: str | Path) -> NPEBaseline:
        """Load an older save (``npe.pt``, a pickled sbi posterior). RUNS CODE stored in the file: only
        for files you trust (``invphys export --upgrade ... --trust-pickles`` calls this once and writes
        the tensor format)."""
        import torch

        d = Path(directory)
        cls._imports()
        blob = torch.load(d / LEGACY_FILE, weights_only=False)
        plugin = cls(read_json_mapping(d / CONFIG_FILE)["config"])
        plugin._posterior, plugin._scales, plugin.metrics = blob["posterior"], blob["scales"], blob["metrics"]
        plugin.fitted = True
        return plugin


WEIGHTS_FILE = "npe_weights.npz"
CONFIG_FILE = "npe.json"
LEGACY_FILE = "npe.pt"
#: 2: weights as tensors + architecture (no pickle); 1 (no "format" key): a pickled posterior in npe.pt
SAVE_FORMAT = 2


def _sbi_version() -> str:
    from importlib import metadata

    try:
        return metadata.version("sbi")
    except metadata.PackageNotFoundError:
        return ""


class _NoTracker:
    """An sbi tracker that records nothing (the default one writes TensorBoard logs into ./sbi-logs)."""

    log_dir = None

    def log_metric(self, name: str, value: float, step: int | None = None) -> None:
        pass

    def log_metrics(self, metrics: dict[str, float], step: int | None = None) -> None:
        pass

    def log_params(self, params: dict[str, Any]) -> None:
        pass

    def add_figure(self, name: str, figure: Any, step: int | None = None) -> None:
        pass

    def flush(self) -> None:
        pass
