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

    class Config(PluginConfig):
        estimator: Literal["maf", "nsf", "mdn"] = Field("maf", description="sbi density estimator")
        hidden_features: int = Field(50, ge=4)
        num_transforms: int = Field(5, ge=1, description="flow layers (maf/nsf)")
        training_batch_size: int = Field(64, ge=8)
        learning_rate: float = Field(1e-3, gt=0)
        max_num_epochs: int = Field(300, ge=1)
        stop_after_epochs: int = Field(20, ge=1, description="early-stopping patience on sbi's validation split")
        samples: int = Field(64, ge=1, description="posterior draws per target")
        answer: Literal["mean", "best_log_prob", "best_surrogate"] = Field("best_log_prob")
        uncertainty_penalty: float = Field(
            0.0, ge=0, description="best_surrogate: score = R - lambda x the ensemble's normalised std (0: plain R)")
        transform: Literal["none", "logit"] = Field(
            "none", description="logit: learn logit(theta), so samples stay in the box (on the tiny fixture: "
                                "no leakage but a larger error)")
        seed: int = 0
        torch_threads: int | None = Field(1, ge=1, description="torch CPU threads while training (None: torch's)")

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
            d = theta.shape[1]
            if c.transform == "logit":  # the prior of logit(U(0, 1)) is the standard logistic
                base = torch.distributions.Uniform(torch.zeros(d), torch.ones(d))
                prior = torch.distributions.Independent(torch.distributions.TransformedDistribution(
                    base, [torch.distributions.transforms.SigmoidTransform().inv]), 1)
            else:
                prior = sbi.utils.BoxUniform(torch.zeros(d), torch.ones(d))
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
        """(samples (B, S, d), log-probs (B, S)) of the posterior at each target (seeded).

        Samples outside [0, 1]^d are clipped to it; ``last_leakage`` is the fraction that was outside.
        """
        import torch

        n = int(n or self.config.samples)
        x = torch.as_tensor(np.atleast_2d(targets), dtype=torch.float32)
        torch.manual_seed(self.config.seed)
        with torch.no_grad(), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*outside the prior support.*")
            # no rejection (a poorly fitted flow can leak most of its mass outside the box, and rejection
            # then never ends) and no leakage normalisation (it only shifts each target's log-probs)
            s = self._posterior.sample_batched((n,), x=x, show_progress_bars=False,
                                               reject_outside_prior=False)  # (S, B, d)
            lp = self._posterior.log_prob_batched(s, x=x, norm_posterior=False)  # (S, B)
        samples = np.transpose(s.numpy().astype(np.float64), (1, 0, 2))
        logp = np.transpose(lp.numpy().astype(np.float64), (1, 0))
        if self.config.transform == "logit":  # back to theta, with the change of variables' Jacobian
            samples = 1.0 / (1.0 + np.exp(-samples))
            logp = logp - np.log(np.clip(samples * (1.0 - samples), 1e-300, None)).sum(axis=2)
        self.last_leakage = float(np.mean(np.any((samples < 0) | (samples > 1), axis=2)))
        return np.clip(samples, 0.0, 1.0), logp

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
        """Pickle the trained posterior and the config under ``directory``."""
        import torch

        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        torch.save({"posterior": self._posterior, "scales": self._scales, "metrics": self.metrics}, d / "npe.pt")
        (d / "npe.json").write_text(json.dumps({"config": self.config.model_dump()}, indent=1))
        return d

    @classmethod
    def load(cls, directory: str | Path) -> NPEBaseline:
        import torch

        d = Path(directory)
        if not (d / "npe.pt").is_file():
            raise InvphysError(f"no saved npe baseline in {d}")
        cls._imports()
        blob = torch.load(d / "npe.pt", weights_only=False)
        plugin = cls(json.loads((d / "npe.json").read_text())["config"])
        plugin._posterior, plugin._scales, plugin.metrics = blob["posterior"], blob["scales"], blob["metrics"]
        plugin.fitted = True
        return plugin


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
