"""The posterior of a target observed with noise, under the bundle's surrogate as the forward model.

A target that gives a standard deviation ``s_k`` per feature is answered from

    p(theta | y_obs)  ∝  prior(theta) · Π_k N(y_obs,k ; f_k(theta), s_k² + m_k(theta)²)

over its given features, where ``f`` is the surrogate's mean and ``m`` its ensemble spread (the model's
own error; a feature given without a std counts as exact up to that error, floored at
:data:`FLOOR` of its scale). The prior is uniform on the normalised parameter box (the dataset's
sampling box, the NPE's prior). The draws come from a tempered sequential Monte Carlo sampler in
NumPy: :data:`PARTICLES` particles from the prior, the likelihood switched on in steps chosen so that
the effective sample size stays at half (systematic resampling), each step followed by :data:`MOVES`
random-walk Metropolis moves whose step follows the particles' covariance. It needs no retraining,
holds for any noise level and any shape of posterior the surrogate allows, and costs about
``PARTICLES x MOVES x steps`` surrogate rows per target (steps grow with the information the target
carries: 4 on a three-feature linear toy with 5-10 % noise). Run it with BLAS on one thread (the
inverter does): its many small products are ~20x slower on two contended threads. Each target's
draws come from its own seeded NumPy stream: they do not depend on the batch or on the other targets.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: particles of the sampler (the draws returned are its first n, more particles when n is larger)
PARTICLES = 1024
#: Metropolis moves after each tempering step
MOVES = 6
#: most tempering steps (a target past this is answered from where the sampler got; noted)
MAX_STEPS = 200
#: smallest noise of a feature, as a fraction of its scale (keeps an exact feature's likelihood finite)
FLOOR = 1e-3
#: rows of the surrogate per call (bounds memory)
CHUNK = 8192


@dataclass
class NoisyDraws:
    """Draws (n, d) in [0, 1]^d of one noisy target, the tempering ``steps`` taken, the Metropolis
    ``acceptance`` of the last step, and whether the sampler reached the full likelihood."""

    samples: np.ndarray
    steps: int
    acceptance: float
    complete: bool


def log_likelihood(surrogate: Any, theta: np.ndarray, values: np.ndarray, mask: np.ndarray, std: np.ndarray,
                   scales: np.ndarray) -> np.ndarray:
    """(P,) Gaussian log-likelihood of ``theta`` (P, d) over the given features (constants dropped)."""
    out = []
    sd = np.nan_to_num(np.asarray(std, dtype=np.float64), nan=0.0)[mask]
    floor = (FLOOR * np.asarray(scales, dtype=np.float64)[mask]) ** 2
    for a in range(0, len(theta), CHUNK):
        mean, spread = surrogate.predict_with_uncertainty(theta[a:a + CHUNK])
        var = sd**2 + spread[:, mask] ** 2 + floor
        r = mean[:, mask] - values[mask]
        out.append(-0.5 * np.sum(r * r / var + np.log(var), axis=1))
    ll = np.concatenate(out)
    return np.where(np.isfinite(ll), ll, -np.inf)


def _next_beta(ll: np.ndarray, beta: float) -> float:
    """The next temperature: the largest in (beta, 1] keeping the effective sample size >= half."""
    n = len(ll)

    def ess(b: float) -> float:
        lw = (b - beta) * ll
        lw = lw - lw.max()
        w = np.exp(lw)
        return float(w.sum() ** 2 / np.sum(w * w))

    if ess(1.0) >= n / 2:
        return 1.0
    lo, hi = beta, 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ess(mid) >= n / 2 else (lo, mid)
    return max(lo, beta + 1e-12)


def _resample(rng: np.random.Generator, lw: np.ndarray) -> np.ndarray:
    """Systematic resampling: indices (P,) of particles with log-weights ``lw``."""
    w = np.exp(lw - lw.max())
    c = np.cumsum(w / w.sum())
    c[-1] = 1.0
    u = (rng.random() + np.arange(len(w))) / len(w)
    return np.searchsorted(c, u)


def sample_noisy(surrogate: Any, dim: int, values: np.ndarray, mask: np.ndarray, std: np.ndarray,
                 scales: np.ndarray, seed: int, n: int) -> NoisyDraws:
    """``n`` draws of one target's noisy posterior (see the module docstring) over ``dim`` parameters;
    the step of the moves adapts between tempering steps (towards 15-30 % acceptance)."""
    rng = np.random.default_rng(seed)
    values = np.where(mask, values, 0.0)
    d = int(dim)
    p = max(PARTICLES, int(n))
    x = rng.random((p, d))

    def lik(t: np.ndarray) -> np.ndarray:
        return log_likelihood(surrogate, t, values, mask, std, scales)

    ll, beta, steps, acc = lik(x), 0.0, 0, 1.0
    scale = 2.38 / np.sqrt(d)
    while beta < 1.0 and steps < MAX_STEPS:
        new = _next_beta(ll, beta)
        idx = _resample(rng, (new - beta) * np.where(np.isfinite(ll), ll, -1e300))
        x, ll, beta, steps = x[idx], ll[idx], new, steps + 1
        cov = np.cov(x, rowvar=False).reshape(d, d) + 1e-12 * np.eye(d)
        chol = np.linalg.cholesky(cov)
        accepted = 0
        for _ in range(MOVES):
            prop = x + scale * rng.standard_normal((p, d)) @ chol.T
            inside = np.all((prop >= 0.0) & (prop <= 1.0), axis=1)
            lp = np.full(p, -np.inf)
            if inside.any():
                lp[inside] = lik(prop[inside])
            ok = np.log(rng.random(p)) < beta * (lp - ll)
            ok &= inside
            x[ok], ll[ok] = prop[ok], lp[ok]
            accepted += int(ok.sum())
        acc = accepted / (MOVES * p)
        scale *= 1.25 if acc > 0.3 else (0.7 if acc < 0.15 else 1.0)
    return NoisyDraws(samples=x[:n].copy(), steps=steps, acceptance=acc, complete=beta >= 1.0)


def noisy_rows(std: np.ndarray | None, n: int) -> np.ndarray:
    """(n,) True for the targets whose ``std`` (n, M; NaN: none) gives a noise > 0."""
    if std is None:
        return np.zeros(n, dtype=bool)
    return np.asarray(np.nan_to_num(std, nan=0.0).max(axis=1) > 0)


def posterior_draws(bundle: Any, plugin: Any, label: str, values: np.ndarray, masks: np.ndarray,
                    std: np.ndarray | None, seed: int, n: int) -> tuple[list[np.ndarray], Any]:
    """(conditions, :class:`~invphys.inverter.draws.PosteriorDraws`) of every target: the method's
    amortised posterior for a target without noise, :func:`sample_noisy` for one with noise (its
    ``raw_draws``: the sampler's particles; its condition: the target itself). Each from its own stream."""
    from invphys.inverter.draws import PosteriorDraws, completions, sample_posterior
    from invphys.inverter.seeds import target_seed

    noisy = noisy_rows(std, len(values))
    train_y = None if masks[~noisy].all() else bundle.data("train")[1]
    mean = np.asarray(bundle.manifest["features"]["mean"], dtype=np.float64)
    conds = [v[None, :] if z else completions(v, m, None if m.all() else train_y, mean, bundle.scales)
             for v, m, z in zip(values, masks, noisy, strict=True)]
    seeds = [target_seed(seed, label, v, m, "posterior") for v, m in zip(values, masks, strict=True)]
    plain = [i for i in range(len(values)) if not noisy[i]]
    rows: dict[int, tuple[np.ndarray, float, int, int, int]] = {}
    if plain:
        d = sample_posterior(plugin, [conds[i] for i in plain], [seeds[i] for i in plain], n)
        for j, i in enumerate(plain):
            rows[i] = (d.samples[j], float(d.outside_fraction[j]), int(d.clipped[j]), int(d.raw_draws[j]),
                       int(d.completions[j]))
    for k in np.flatnonzero(noisy):
        i = int(k)
        s = np.nan_to_num(std[i], nan=0.0) if std is not None else np.zeros(values.shape[1])
        nd = sample_noisy(bundle.surrogate, bundle.space.dim, values[i], masks[i], s, bundle.scales,
                          target_seed(seed, label, np.concatenate([values[i], s]), np.concatenate([masks[i], masks[i]]),
                                      "noise"), n)
        rows[i] = (nd.samples, 0.0, 0, max(PARTICLES, n) * (1 + MOVES * nd.steps), 1)
    order = [rows[i] for i in range(len(values))]
    return conds, PosteriorDraws(samples=np.stack([r[0] for r in order]),
                                 outside_fraction=np.array([r[1] for r in order], dtype=np.float64),
                                 clipped=np.array([r[2] for r in order], dtype=np.int64),
                                 raw_draws=np.array([r[3] for r in order], dtype=np.int64),
                                 completions=np.array([r[4] for r in order], dtype=np.int64))


def noise_warnings(noisy: bool, kind: str) -> list[str]:
    """What a user should know when a noisy target meets a method without a posterior."""
    if not noisy or kind == "posterior":
        return []
    what = "the nearest training rows" if kind == "neighbours" else "a point"
    return [f"the target's noise does not change this answer (the method answers with {what}, not a "
            f"posterior): use a posterior method (e.g. npe) for intervals under the noise"]

