"""Is a posterior as sure as it should be? Coverage, TARP, SBC ranks and quantile recalibration.

Every function takes posterior draws ``draws`` (B, S, d) and the true parameters ``theta`` (B, d) of
B rows the posterior never trained on (normalised units, the prior's box [0, 1]^d):

* :func:`central_coverage`: per parameter, the share of rows whose truth lies in the central interval
  of the draws at each level (50/80/90/95 %), with percentile-bootstrap 95 % intervals over rows, and
  the intervals' mean width;
* :func:`tarp`: the joint check of Lemos et al. 2023 (sbi's ``run_tarp``/``check_tarp``): per row, the
  share of draws closer to a random reference point than the truth; its expected coverage at each level;
* :func:`sbc`: SBC ranks of the truth among the draws and a Kolmogorov-Smirnov p-value of their uniformity
  per parameter (sbi's ``check_uniformity_frequentist``), with the bias (mean PIT - 0.5: > 0, the
  posterior sits too low);
* :func:`fit_recalibration` / :func:`apply_recalibration`: per-parameter quantile recalibration
  (Kuleshov et al. 2018): a monotone map of the posterior CDF level (as a normal score, so that tails
  beyond the draws can widen) fitted on one set of rows, applied to each draw through its own marginal
  level, so the corrected draws keep the posterior's dependence;
* :func:`fit_posterior_recalibration` / :func:`apply_posterior_recalibration`: those maps, then the joint
  step of :mod:`~invphys.evaluation.joint_calibration` (each row's marginals moved by where its posterior
  sits), the whole stored as plain numbers; :func:`recalibrated_samples` applies a bundle's stored block.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from invphys.core.errors import InvphysError
from invphys.evaluation.joint_calibration import apply_location_shift, fit_location_shift
from invphys.evaluation.posterior_quantiles import check as _check
from invphys.evaluation.posterior_quantiles import extrap as _extrap
from invphys.evaluation.posterior_quantiles import move, pit_z
from invphys.evaluation.posterior_quantiles import row_levels as _row_levels

LEVELS: tuple[float, ...] = (0.5, 0.8, 0.9, 0.95)
#: knots of a stored recalibration map (levels in [0, 1])
KNOTS = 21
#: reference points per row of TARP's multi-reference estimate (``tarp(...)["levels_refs"]``)
TARP_REFS = 20


def boot_rate(hits: np.ndarray, n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
    """Mean of 0/1 ``hits`` (B,) or (B, k) over rows with a percentile-bootstrap 95 % interval."""
    h = np.asarray(hits, dtype=np.float64)
    h2 = h.reshape(len(h), -1)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(h2), size=(n_boot, len(h2)))
    means = h2[idx].mean(axis=1)  # (n_boot, k)
    lo, hi = np.quantile(means, [0.025, 0.975], axis=0)
    rate = h2.mean(axis=0)
    if h.ndim == 1:
        return {"rate": float(rate[0]), "ci95": [float(lo[0]), float(hi[0])]}
    return {"rate": rate.tolist(), "ci95": np.stack([lo, hi], axis=1).tolist()}


def central_coverage(draws: np.ndarray, theta: np.ndarray, levels: tuple[float, ...] = LEVELS,
                     n_boot: int = 1000, seed: int = 0) -> dict[str, Any]:
    """Per level: per-parameter hit rates with intervals and mean interval widths (lists in parameter order)."""
    draws, theta = _check(draws, theta)
    out: dict[str, Any] = {}
    for level in levels:
        lo, hi = np.quantile(draws, [(1 - level) / 2, (1 + level) / 2], axis=1)  # (B, d) each
        hits = (theta >= lo) & (theta <= hi)
        b = boot_rate(hits, n_boot, seed)
        out[f"{level:g}"] = {"coverage": b["rate"], "ci95": b["ci95"], "width": (hi - lo).mean(axis=0).tolist()}
    return out


def tarp_values(draws: np.ndarray, theta: np.ndarray, seed: int = 0, n_refs: int = 1) -> np.ndarray:
    """Per row: the share of draws closer (L2) to a reference point drawn uniformly in the box than the
    truth is; (B,) for one reference per row (sbi's TARP), (B, n_refs) for more. A calibrated posterior
    makes these uniform on [0, 1]. The first reference of each row is the one-reference estimate's."""
    draws, theta = _check(draws, theta)
    ref = np.random.default_rng(seed).uniform(0.0, 1.0, size=(n_refs, *theta.shape))  # (R, B, d)
    out = np.empty((len(theta), n_refs))
    for i in range(0, len(theta), 25):  # (rows, R, S) distances a chunk at a time
        r = np.swapaxes(ref[:, i:i + 25], 0, 1)  # (b, R, d)
        d_draws = np.linalg.norm(draws[i:i + 25, None, :, :] - r[:, :, None, :], axis=3)
        d_true = np.linalg.norm(theta[i:i + 25, None, :] - r, axis=2)
        out[i:i + 25] = (d_draws < d_true[:, :, None]).mean(axis=2)
    return out[:, 0] if n_refs == 1 else out


def tarp(draws: np.ndarray, theta: np.ndarray, levels: tuple[float, ...] = LEVELS, n_boot: int = 1000,
         seed: int = 0, n_refs: int = TARP_REFS) -> dict[str, Any]:
    """Joint expected coverage per level (with intervals), sbi's area to curve (``atc``: < 0 too narrow)
    and its KS p-value of the coverage curve against the diagonal, from one reference point per row
    (``levels``, as sbi's ``run_tarp``); ``levels_refs``: the same expected coverage averaged over
    ``n_refs`` reference points per row (the first being the one above), whose bootstrap over rows
    carries less of the reference points' own noise."""
    many = tarp_values(draws, theta, seed, n_refs).reshape(len(theta), n_refs)
    f = many[:, 0]
    out: dict[str, Any] = {"levels": {}, "levels_refs": {}, "n_refs": int(n_refs)}
    for level in levels:
        out["levels"][f"{level:g}"] = boot_rate(f < level, n_boot, seed)
        out["levels_refs"][f"{level:g}"] = boot_rate((many < level).mean(axis=1), n_boot, seed)
    alpha = np.linspace(0.0, 1.0, 101)
    ecp = np.array([np.mean(f < a) for a in alpha])
    out["curve"] = {"alpha": alpha.tolist(), "ecp": ecp.tolist()}
    try:
        import torch
        from sbi.diagnostics import check_tarp

        atc, ks = check_tarp(torch.as_tensor(ecp, dtype=torch.float32), torch.as_tensor(alpha, dtype=torch.float32))
        out["atc"], out["ks_pvalue"] = float(atc), float(ks)
    except ImportError:  # sbi is an extra: the same area without it
        mid = len(alpha) // 2
        out["atc"] = float(((ecp[mid:] - alpha[mid:]) * (alpha[1] - alpha[0])).sum())
    return out


def ranks(draws: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(B, d) SBC ranks: how many of the S draws lie below the truth (0 .. S), as sbi's ``run_sbc``."""
    draws, theta = _check(draws, theta)
    return (draws < theta[:, None, :]).sum(axis=1)


def pit(draws: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """(B, d) probability integral transform of the truth under each marginal, in (0, 1)."""
    return (ranks(draws, theta) + 0.5) / (np.asarray(draws).shape[1] + 1.0)


def uniformity_pvalues(r: np.ndarray, n_draws: int) -> list[float]:
    """KS p-value per column of ranks ``r`` (B, d) against the uniform on [0, n_draws]."""
    try:
        import torch
        from sbi.diagnostics.sbc import check_uniformity_frequentist

        return [float(p) for p in check_uniformity_frequentist(torch.as_tensor(r, dtype=torch.float32), n_draws)]
    except ImportError:
        from scipy.stats import kstest, uniform

        return [float(kstest(col, uniform(loc=0, scale=n_draws).cdf).pvalue) for col in np.asarray(r).T]


def sbc(draws: np.ndarray, theta: np.ndarray, bins: int = 20) -> dict[str, Any]:
    """Ranks' uniformity per parameter: KS p-values, bias (mean PIT - 0.5) and rank histograms."""
    r = ranks(draws, theta)
    s = np.asarray(draws).shape[1]
    u = pit(draws, theta)
    hist = [np.histogram(r[:, j], bins=bins, range=(0, s + 1))[0].tolist() for j in range(r.shape[1])]
    return {"ks_pvalue": uniformity_pvalues(r, s), "bias": (u.mean(axis=0) - 0.5).tolist(),
            "histograms": hist, "n_draws": int(s), "n_rows": len(r)}


def fit_recalibration(z: np.ndarray, knots: int = KNOTS) -> list[dict[str, list[float]]]:
    """Per parameter, a monotone map g of normal scores: g(z) = Phi^-1(P(score <= z)) over the truth's
    scores ``z`` (B, d) of :func:`pit_z` (smoothed by one pseudo-row on the diagonal), at ``knots``
    points of [-2.5, 2.5]; a calibrated posterior has g(z) = z."""
    from scipy.stats import norm

    z = np.asarray(z, dtype=np.float64)
    grid = np.linspace(-2.5, 2.5, knots)
    maps = []
    for j in range(z.shape[1]):
        col = np.sort(z[:, j])
        ecdf = (np.searchsorted(col, grid, side="right") + norm.cdf(grid)) / (len(col) + 1.0)
        g = norm.ppf(np.clip(ecdf, 1e-6, 1 - 1e-6))
        g = np.maximum.accumulate(g + np.arange(knots) * 1e-9)
        maps.append({"z": grid.tolist(), "g": g.tolist()})
    return maps


def _inverse(curve: dict[str, list[float]], g: np.ndarray) -> np.ndarray:
    """g^-1 of normal scores ``g`` under a stored map, continued linearly with its end slopes."""
    z, gv = np.asarray(curve["z"]), np.asarray(curve["g"])
    lo = max((z[2] - z[0]) / max(gv[2] - gv[0], 1e-9), 1e-3)
    hi = max((z[-1] - z[-3]) / max(gv[-1] - gv[-3], 1e-9), 1e-3)
    return _extrap(g, gv, z, lo, hi)


def apply_recalibration(draws: np.ndarray, maps: list[dict[str, list[float]] | None]) -> np.ndarray:
    """Draws whose marginals follow the recalibrated CDFs Phi(g(score)): each draw of parameter j moves to
    its row's quantile (:func:`pit_z`'s quantile function) at normal score g^-1(its own score), keeping
    the draws' order, hence their dependence. ``None`` keeps a parameter as it is; draws stay in the box."""
    draws = np.asarray(draws, dtype=np.float64)
    out = draws.copy()
    zl = _row_levels(draws.shape[1])
    for j, curve in enumerate(maps):
        if curve is not None:
            out[:, :, j] = move(draws[:, :, j], _inverse(curve, zl))
    return out


def worst_error(coverage: dict[str, Any], j: int) -> float:
    """Largest |coverage - level| of parameter ``j`` over the levels of :func:`central_coverage`."""
    return max(abs(v["coverage"][j] - float(k)) for k, v in coverage.items())


def fit_posterior_recalibration(draws: np.ndarray, theta: np.ndarray, keep: Any = None) -> dict[str, Any]:
    """The stored recalibration block fitted on rows ``draws`` (B, S, d) / ``theta`` (B, d): per-parameter
    quantile maps (``maps``), then the joint step (``location_shift``,
    :mod:`~invphys.evaluation.joint_calibration`) fitted on the mapped draws; a parameter not in ``keep``
    (when given) gets neither (``None``: the identity). Each parameter's map and shift read only its own
    draws, so ``keep`` changes no other parameter's numbers."""
    draws, theta = _check(draws, theta)
    maps: list[dict[str, list[float]] | None] = list(fit_recalibration(pit_z(draws, theta)))
    shift: list[dict[str, Any] | None] = list(fit_location_shift(apply_recalibration(draws, maps), theta))
    if keep is not None:
        maps = [m if k else None for m, k in zip(maps, keep, strict=True)]
        shift = [s if k else None for s, k in zip(shift, keep, strict=True)]
    return {"knots": KNOTS, "maps": maps, "location_shift": shift, "steps": ["maps", "location_shift"]}


def apply_posterior_recalibration(draws: np.ndarray, block: dict[str, Any]) -> np.ndarray:
    """Draws (B, S, d) corrected by a recalibration block: its ``maps``, then its ``location_shift`` when
    it holds one (blocks written before the joint step hold maps only)."""
    draws = np.asarray(draws, dtype=np.float64)
    maps = block.get("maps") or [None] * draws.shape[-1]
    if not isinstance(maps, list) or len(maps) != draws.shape[-1]:
        raise InvphysError(f"the stored recalibration has {len(maps) if isinstance(maps, list) else maps!r} "
                           f"parameters, the draws {draws.shape[-1]}")
    out = apply_recalibration(draws, maps) if any(m is not None for m in maps) else draws
    shift = block.get("location_shift")
    return apply_location_shift(out, shift) if shift else out


def has_recalibration(diagnostics: dict[str, Any] | None) -> bool:
    """Whether a bundle's stored diagnostics change its posterior draws."""
    block = ((diagnostics or {}).get("posterior") or {}).get("recalibration") or {}
    parts = [block.get("maps"), block.get("location_shift")]  # a malformed one counts: applying it says why
    return any(any(m is not None for m in p) if isinstance(p, list) else bool(p) for p in parts)


def recalibrated_samples(samples: np.ndarray, diagnostics: dict[str, Any] | None) -> np.ndarray:
    """Posterior draws (B, S, d) corrected by a bundle's stored recalibration (``diagnostics/calibration.json``,
    block ``posterior.recalibration``: its maps, then its location shift); unchanged when it holds none."""
    if not has_recalibration(diagnostics):
        return np.asarray(samples, dtype=np.float64)
    block = diagnostics["posterior"]["recalibration"]  # type: ignore[index]
    return apply_posterior_recalibration(samples, block)
