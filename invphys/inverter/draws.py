"""Posterior draws of a bundle's amortised posterior (sbi's NPE), truncated to the parameter box.

Each target is sampled alone, under its own seeded torch stream (:func:`~invphys.inverter.seeds.target_seed`),
in rounds of :data:`ROUND` raw draws per completion of the target: draws outside [0, 1]^d are rejected
(the box is the prior's support, so the truncated posterior is the posterior under that prior); after
:data:`CAP_FACTOR` x S raw draws without S inside, the missing draws are the outside ones clipped to
the box, and ``clipped`` says how many. Because the rounds have a fixed size, the first K of S draws are
the same for every S >= K, and no draw depends on other targets or on the batch.

Speed: for an nflows flow (sbi's maf/nsf), many targets are drawn together: each target's base noise
comes from its own generator, one round at a time (sbi's order: completion-major), and the flow runs
on the next rows of every unfinished target at once, in calls of up to :data:`CHUNK_ROUNDS` x
:data:`ROUND` rows that never end on a real row (:data:`PAD` rows of padding: the flow computes a
call's last rows otherwise, rarely, in the last bits). A row's arithmetic then does not depend on the other rows
of the call (checked by tests/test_inverter_pool.py and tests/test_pool_speed.py), so the draws are
bit-for-bit those of a target drawn alone, and the same as sbi's own ``sample`` under the target's
seed. Where nobody reads the outside fraction (``whole_rounds=False``: a pool's extra members) a
round's rows go through the flow only until the target has its draws: the same draws, fewer rows.
For sbi's ``nsf`` the flow's inverse is :class:`~invphys.plugins.baselines.spline_sampler.SplineSampler`'s: the
same operations on the same operands as nflows' inverse (so the same bits), without the log-determinant
and the spline's masked selections, each target's context gates computed once.
One torch thread (:data:`THREADS`): on a 2-core machine whose other core is busy, two threads ran
many times slower.

A partial target (missing features) is answered by the mixture over completions: the missing features
take the values of the :data:`COMPLETIONS` training rows nearest in the given features (scaled), each
completion getting an equal share of every round, which approximates p(theta | given features).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from invphys.core.errors import InvphysError

#: raw draws per round and completion (fixed, so that draws are prefix-stable in S)
ROUND = 256
#: give up rejecting after this many raw draws per requested draw
CAP_FACTOR = 50
#: rounds (blocks of ROUND rows) per call of the flow when targets are drawn together
CHUNK_ROUNDS = 16
#: completions of a partial target's missing features (training rows nearest in the given features)
COMPLETIONS = 16
#: torch threads while drawing; 1 because on a 2-core machine whose other core is busy two threads ran many
#: times slower (on an idle one, 1.5x faster). Two gave the same draws through the spline sampler (300 fresh
#: targets, the paper bundle's four nsf flows: its one elementwise transcendental call stays under a thread's
#: grain), not through nflows' inverse (its calls split across threads: 1 or 2 of 64 targets differed)
THREADS = 1
#: padding rows after the last real row of a flow call (its vector loops' scalar tail falls on them)
PAD = 16
#: the share of a target's raw draws expected inside the box before any was made (rounds in part only):
#: 1, the first pass asks for the draws (x 1.1, + 4) as if all fell inside (0.7 transformed rows past the
#: n-th draw inside on most targets: 15 % more time on the fresh uniform targets, the same draws)
FIRST_RATE = 1.0
_LOG = logging.getLogger("invphys.inverter")


@dataclass
class PosteriorDraws:
    """Draws for B targets: ``samples`` (B, S, d) in [0, 1]^d (normalised units, space order);
    ``outside_fraction`` (B,): share of raw draws that fell outside the box and were rejected;
    ``clipped`` (B,): draws that had to be clipped because the cap was hit (0 normally);
    ``raw_draws`` (B,): raw draws made; ``completions`` (B,): 1, or the completions of a partial target."""

    samples: np.ndarray
    outside_fraction: np.ndarray
    clipped: np.ndarray
    raw_draws: np.ndarray
    completions: np.ndarray

    def __len__(self) -> int:
        return len(self.samples)


def has_posterior(plugin: Any) -> bool:
    """True for a plugin holding a trained sbi posterior (its ``_posterior.posterior_estimator``)."""
    return getattr(getattr(plugin, "_posterior", None), "posterior_estimator", None) is not None


@contextlib.contextmanager
def _torch_stream(seed: int) -> Iterator[None]:
    """torch's global RNG seeded with ``seed`` inside, restored after; :data:`THREADS` CPU threads."""
    import torch

    threads = torch.get_num_threads()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        torch.set_num_threads(THREADS)
        try:
            yield
        finally:
            torch.set_num_threads(threads)


def completions(values: np.ndarray, mask: np.ndarray, train_y: np.ndarray | None, mean: np.ndarray,
                scales: np.ndarray) -> np.ndarray:
    """(K, M) conditions for one target: itself when complete; else K copies whose missing features
    come from the training rows nearest in the given features (the training mean without rows)."""
    values, mask = np.asarray(values, dtype=np.float64), np.asarray(mask, dtype=bool)
    if mask.all():
        return values[None, :]
    if train_y is None or not len(train_y):
        return np.where(mask, values, mean)[None, :]
    y = train_y[np.all(np.isfinite(train_y), axis=1)]
    z = (y[:, mask] - values[mask]) / np.maximum(scales[mask], 1e-12)
    d2 = (z * z).sum(axis=1)
    k = min(COMPLETIONS, len(y))
    idx = np.lexsort((np.arange(len(y)), d2))[:k]  # nearest first, ties by row (deterministic)
    return np.where(mask[None, :], values[None, :], y[idx])


def sample_posterior(plugin: Any, conditions: Sequence[np.ndarray], seeds: Sequence[int], n: int,
                     whole_rounds: bool = True) -> PosteriorDraws:
    """``n`` truncated draws per target; ``conditions[i]`` (K_i, M) from :func:`completions`.

    ``whole_rounds=False`` (an nflows flow only): a round's rows go through the flow only until the
    target has ``n`` draws inside, so the draws are the same, made faster, but ``outside_fraction``
    and ``raw_draws`` then count only the rows transformed (for draws whose fraction nobody reads)."""
    if not has_posterior(plugin):
        raise InvphysError(f"{getattr(plugin, 'name', plugin)!r} holds no posterior to draw from")
    if n < 1:
        raise InvphysError(f"posterior draws must be >= 1, got {n}")
    est = plugin._posterior.posterior_estimator
    logit = getattr(getattr(plugin, "config", None), "transform", "none") == "logit"
    net = _flow(est)
    if net is not None and all(len(np.atleast_2d(c)) <= ROUND for c in conditions):
        rows = _together(net, [np.atleast_2d(c) for c in conditions], [int(s) for s in seeds], n, logit,
                         whole_rounds)
    else:
        rows = [_one(est, c, int(s), n, logit) for c, s in zip(conditions, seeds, strict=True)]
    return PosteriorDraws(samples=np.stack([r[0] for r in rows]),
                          outside_fraction=np.array([r[1] for r in rows], dtype=np.float64),
                          clipped=np.array([r[2] for r in rows], dtype=np.int64),
                          raw_draws=np.array([r[3] for r in rows], dtype=np.int64),
                          completions=np.array([len(c) for c in conditions], dtype=np.int64))


def _one(est: Any, cond: np.ndarray, seed: int, n: int, logit: bool) -> tuple[np.ndarray, float, int, int]:
    """(draws (n, d), outside fraction, clipped, raw draws) for one target."""
    import torch

    x = torch.as_tensor(np.atleast_2d(cond), dtype=torch.float32)
    k = x.shape[0]
    per_round = max(1, ROUND // k)
    inside: list[np.ndarray] = []
    outside: list[np.ndarray] = []
    got = raw = 0
    with _torch_stream(seed), torch.no_grad():
        while got < n and raw < CAP_FACTOR * n:
            s = est.sample(torch.Size([per_round]), condition=x).numpy().astype(np.float64)  # (R, K, d)
            s = s.reshape(-1, s.shape[-1])
            if logit:
                s = 1.0 / (1.0 + np.exp(-s))
            ok = np.all((s >= 0.0) & (s <= 1.0), axis=1)
            inside.append(s[ok])
            outside.append(s[~ok])
            got += int(ok.sum())
            raw += len(s)
    return _finish(inside, outside, got, raw, n)


def _flow(est: Any) -> Any:
    """The nflows flow inside sbi's estimator when its base is a standard normal (else None: each
    target is drawn alone through sbi's ``sample``)."""
    net = getattr(est, "net", None)
    dist = getattr(net, "_distribution", None)
    if net is None or not hasattr(net, "_transform") or type(dist).__name__ != "StandardNormal":
        return None
    return net


@dataclass
class _Stream:
    """One target's draw state: its generator, its conditions' embedding (K, C), the current round's
    noise and how many of its ``per_round`` rows (per completion) went through the flow, draws so far."""

    gen: Any
    emb: Any
    k: int
    per_round: int
    inside: list[np.ndarray]
    outside: list[np.ndarray]
    got: int = 0
    raw: int = 0
    rounds: int = 0
    noise: Any = None
    done: int = 0
    #: the row of its first condition in the call's table of embedded conditions (:class:`_Fast`)
    first: int = 0

    def rows(self, n: int, whole: bool) -> int:
        """Rows (per completion) of the current round to run next: the rest of the round, or (not
        ``whole``) about as many as the draws still missing need at the rate seen so far."""
        left = self.per_round - self.done
        if whole:
            return left
        rate = self.got / self.raw if self.raw else FIRST_RATE
        want = int(np.ceil((n - self.got) / max(rate, 1.0 / ROUND) * 1.1)) + 4
        return max(1, min(left, -(-want // self.k)))


def _together(net: Any, conditions: Sequence[np.ndarray], seeds: Sequence[int], n: int, logit: bool,
              whole: bool = True) -> list[tuple[np.ndarray, float, int, int]]:
    """:func:`_one` for many targets at once: the next rows of every unfinished target in one flow pass
    (``whole``: whole rounds; else a round's rows only until the target has ``n`` draws inside)."""
    import torch

    d = int(net._distribution._shape[0])
    streams = []
    with _torch_stream(0), torch.no_grad():
        for c, seed in zip(conditions, seeds, strict=True):
            emb = net._embedding_net(torch.as_tensor(c, dtype=torch.float32))  # as sbi embeds them
            streams.append(_Stream(torch.Generator().manual_seed(seed), emb, len(c), max(1, ROUND // len(c)), [], []))
        fast = _Fast.of(net, streams)
        while True:
            plan = []
            for st in streams:
                if st.got >= n:
                    continue
                if st.noise is None or st.done == st.per_round:  # a new round, in sbi's order (completion-major)
                    if st.rounds * st.k * st.per_round >= CAP_FACTOR * n:
                        continue
                    st.noise = torch.randn(st.k * st.per_round, d, generator=st.gen)
                    st.rounds, st.done = st.rounds + 1, 0
                plan.append((st, st.rows(n, whole)))
            if not plan:
                break
            out = _run(net, plan, fast)
            a = 0
            for st, take in plan:
                s = out[a:a + st.k * take].reshape(st.k, take, d)
                a += st.k * take
                _keep(st, s.transpose(1, 0, 2).reshape(-1, d), logit)
                st.done += take
    return [_finish(st.inside, st.outside, st.got, st.raw, n) for st in streams]


def _padded(x: Any) -> Any:
    """``x`` with its first row repeated after it: at least :data:`PAD` rows more, a multiple of PAD
    rows and at least :data:`ROUND` in all. The flow's vector loops end in a scalar tail over a call's
    last elements, which computes them otherwise (rarely, in the last bits): no real row may be there."""
    import torch

    size = max(ROUND, -(-(len(x) + PAD) // PAD) * PAD)
    return torch.cat([x, x[:1].expand(size - len(x), -1)])


@dataclass
class _Fast:
    """What :class:`~invphys.plugins.baselines.spline_sampler.SplineSampler` needs for one :func:`_together`: the
    sampler, every stream's embedded conditions stacked (``table``, row ``first`` on: a stream's) and
    their residual blocks' gates (row for row)."""

    sampler: Any
    table: Any
    gates: list[Any]

    @classmethod
    def of(cls, net: Any, streams: list[_Stream]) -> _Fast | None:
        """For a flow the sampler computes (sbi's nsf), else None (nflows' own inverse)."""
        import torch

        from invphys.plugins.baselines.spline_sampler import spline_sampler

        sampler = spline_sampler(net)
        if sampler is None or not streams:
            return None
        first = 0
        for st in streams:
            st.first, first = first, first + st.k
        table = torch.cat([st.emb for st in streams])
        return cls(sampler, table, sampler.gates(_padded(table)))


def _run(net: Any, plan: list[tuple[_Stream, int]], fast: _Fast | None = None) -> np.ndarray:
    """The flow on the planned rows of every target (rows ``done .. done + take`` of each completion
    block of its round), in calls of :data:`CHUNK_ROUNDS` x :data:`ROUND` rows, each padded
    (:func:`_padded`); (rows, d) float64, completion-major per target. With ``fast``, the spline
    sampler draws them (the same bits as nflows' inverse, tests/test_npe_draw_speed.py)."""
    import torch

    noise = torch.cat([st.noise.view(st.k, st.per_round, -1)[:, st.done:st.done + take].reshape(st.k * take, -1)
                       for st, take in plan])
    step = CHUNK_ROUNDS * ROUND
    outs = []
    if fast is not None:  # each row's condition by its index into the table (and so its gates)
        rows = torch.cat([torch.arange(st.first, st.first + st.k).repeat_interleave(take) for st, take in plan])
        for a in range(0, len(noise), step):
            z, r = noise[a:a + step], _padded(rows[a:a + step, None])[:, 0]
            outs.append(fast.sampler.inverse(_padded(z), fast.table.index_select(0, r),
                                             [g.index_select(0, r) for g in fast.gates])[:len(z)])
        return torch.cat(outs).numpy().astype(np.float64)
    ctx = torch.cat([st.emb.repeat_interleave(take, dim=0) for st, take in plan])
    for a in range(0, len(noise), step):
        z, c = noise[a:a + step], ctx[a:a + step]
        outs.append(net._transform.inverse(_padded(z), context=_padded(c))[0][:len(z)])
    return torch.cat(outs).numpy().astype(np.float64)


def _keep(st: _Stream, s: np.ndarray, logit: bool) -> None:
    if logit:
        s = 1.0 / (1.0 + np.exp(-s))
    ok = np.all((s >= 0.0) & (s <= 1.0), axis=1)
    st.inside.append(s[ok])
    st.outside.append(s[~ok])
    st.got += int(ok.sum())
    st.raw += len(s)


def _finish(inside: list[np.ndarray], outside: list[np.ndarray], got: int, raw: int, n: int
            ) -> tuple[np.ndarray, float, int, int]:
    """(draws (n, d), outside fraction, clipped, raw draws): the first n inside, topped up by clipping."""
    draws = np.concatenate(inside)[:n]
    clipped = n - len(draws)
    if clipped:
        extra = np.clip(np.concatenate(outside)[:clipped], 0.0, 1.0)
        draws = np.concatenate([draws, extra])
        _LOG.info("posterior draws: %d of %d raw draws inside the box; %d draws clipped", got, raw, clipped)
    return draws, 1.0 - got / max(raw, 1), clipped, raw


def log_prob(plugin: Any, draws: np.ndarray, cond: np.ndarray) -> np.ndarray:
    """The posterior's log-density (K,) of ``draws`` (K, d) in [0, 1]^d given one condition (M,)
    (up to the truncation's constant, which does not change their order)."""
    import torch

    est = plugin._posterior.posterior_estimator
    u = np.asarray(draws, dtype=np.float64)
    logit = getattr(getattr(plugin, "config", None), "transform", "none") == "logit"
    z = np.log(np.clip(u, 1e-12, 1)) - np.log1p(-np.clip(u, 0, 1 - 1e-12)) if logit else u
    x = torch.as_tensor(np.atleast_2d(cond), dtype=torch.float32)
    with torch.no_grad():
        lp = est.log_prob(torch.as_tensor(z, dtype=torch.float32)[:, None, :], condition=x)
    out = lp.numpy().astype(np.float64).reshape(-1)
    if logit:
        out = out - np.log(np.clip(u * (1.0 - u), 1e-300, None)).sum(axis=1)
    return out
