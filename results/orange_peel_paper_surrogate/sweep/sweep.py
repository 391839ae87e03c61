"""GPU sweep of surrogate settings on the orange-peel paper data (numpy + torch only).

Each config trains K=5 members at once (batched weights); member k early-stops on its own 10 %
carve of the TRAIN rows (never the held-out 400). R^2 is measured on the held-out rows in raw units.
Writes one JSON per config (member and ensemble R^2, per feature) into OUT.
"""
import json
import math
import os
import sys
import time

import numpy as np
import torch

OUT = sys.argv[2]
D = np.load(sys.argv[1])
TT, YT, TV, YV = D["tt"], D["yt"], D["tv"], D["yv"]
LOW, HIGH, LOG = D["low"], D["high"], D["log"]


def r2(y, p):
    ss_res = ((y - p) ** 2).sum(0)
    ss_tot = ((y - y.mean(0)) ** 2).sum(0)
    per = 1 - ss_res / ss_tot
    return float(per.mean()), per.tolist()


# ---- output transforms (fit on train rows) ----------------------------------------------------
def yj(x, lam):
    out = np.empty_like(x)
    pos = x >= 0
    for j in range(x.shape[1]):
        l, p = lam[j], pos[:, j]
        xp, xn = x[p, j], x[~p, j]
        out[p, j] = np.log1p(xp) if abs(l) < 1e-8 else ((xp + 1) ** l - 1) / l
        out[~p, j] = -np.log1p(-xn) if abs(l - 2) < 1e-8 else -(((1 - xn) ** (2 - l)) - 1) / (2 - l)
    return out


def yj_inv(t, lam):
    out = np.empty_like(t)
    pos = t >= 0
    for j in range(t.shape[1]):
        l, p = lam[j], pos[:, j]
        tp, tn = t[p, j], t[~p, j]
        out[p, j] = np.expm1(tp) if abs(l) < 1e-8 else np.maximum(tp * l + 1, 1e-12) ** (1 / l) - 1
        out[~p, j] = -np.expm1(-tn) if abs(l - 2) < 1e-8 else 1 - np.maximum(1 - (2 - l) * tn, 1e-12) ** (1 / (2 - l))
    return out


def yj_fit(x):
    from scipy import optimize, stats
    lam = []
    for j in range(x.shape[1]):
        def nll(l):
            t = yj(x[:, j:j + 1], [l])[:, 0]
            v = t.var()
            if not np.isfinite(v) or v <= 0:
                return 1e30
            return 0.5 * len(t) * np.log(v) - (l - 1) * (np.sign(x[:, j]) * np.log1p(np.abs(x[:, j]))).sum()
        lam.append(optimize.brent(nll, brack=(-2, 2)))
    return np.array(lam)


class Transform:
    def __init__(self, kind, y):
        self.kind = kind
        self.m0, self.s0 = y.mean(0), y.std(0)
        yspan = y.max(0) - y.min(0)
        self.ylo, self.yhi = y.min(0) - 0.5 * yspan, y.max(0) + 0.5 * yspan
        z = (y - self.m0) / self.s0
        if kind == "yj":
            self.lam = yj_fit(z)
            z = yj(z, self.lam)
        elif kind == "quantile":
            self.q = np.quantile(y, np.linspace(0, 1, 1001), axis=0)
            from scipy.stats import norm
            self.zq = norm.ppf(np.clip(np.linspace(0, 1, 1001), 1e-4, 1 - 1e-4))
            z = self._q(y)
        self.m1, self.s1 = z.mean(0), z.std(0)
        t = (z - self.m1) / self.s1
        span = t.max(0) - t.min(0)
        self.lo, self.hi = t.min(0) - 0.25 * span, t.max(0) + 0.25 * span

    def _q(self, y):
        return np.stack([np.interp(y[:, j], self.q[:, j], self.zq) for j in range(y.shape[1])], 1)

    def fwd(self, y):
        if self.kind == "quantile":
            z = self._q(y)
        else:
            z = (y - self.m0) / self.s0
            if self.kind == "yj":
                z = yj(z, self.lam)
        return (z - self.m1) / self.s1

    def inv(self, t):
        z = np.clip(t, self.lo, self.hi) * self.s1 + self.m1
        if self.kind == "quantile":
            return np.stack([np.interp(z[:, j], self.zq, self.q[:, j]) for j in range(z.shape[1])], 1)
        if self.kind == "yj":
            z = yj_inv(z, self.lam)
        return np.clip(np.nan_to_num(z * self.s0 + self.m0, nan=0.0), self.ylo, self.yhi)


def inputs(theta, kind):
    if kind == "theta":
        return theta
    # log-physical for the linear-scale parameters, renormalised to [0, 1]
    out = theta.copy()
    for j in range(theta.shape[1]):
        if not LOG[j]:
            p = LOW[j] + theta[:, j] * (HIGH[j] - LOW[j])
            out[:, j] = (np.log(p) - np.log(LOW[j])) / (np.log(HIGH[j]) - np.log(LOW[j]))
    return out


# ---- batched K-member skip MLP ----------------------------------------------------------------
class Net(torch.nn.Module):
    def __init__(self, K, d, m, hidden, act, bn, dropout, residual_blocks=0):
        super().__init__()
        h1, h2, h3 = hidden
        def lin(i, o):
            w = torch.empty(K, i, o)
            for k in range(K):
                torch.nn.init.kaiming_uniform_(w[k].T, a=math.sqrt(5))
            b = torch.empty(K, 1, o).uniform_(-1 / math.sqrt(i), 1 / math.sqrt(i))
            return torch.nn.Parameter(w), torch.nn.Parameter(b)
        self.w1, self.b1 = lin(d, h1)
        self.w2, self.b2 = lin(h1, h2)
        self.w3, self.b3 = lin(h1 + h2, h3)
        self.wo, self.bo = lin(h3, m)
        self.act = {"relu": torch.relu, "silu": torch.nn.functional.silu, "gelu": torch.nn.functional.gelu}[act]
        self.bn, self.dropout = bn, dropout
        if bn:
            self.g = torch.nn.ParameterList([torch.nn.Parameter(torch.ones(K, 1, h)) for h in hidden])
            self.be = torch.nn.ParameterList([torch.nn.Parameter(torch.zeros(K, 1, h)) for h in hidden])
            for i, h in enumerate(hidden):
                self.register_buffer(f"rm{i}", torch.zeros(K, 1, h))
                self.register_buffer(f"rv{i}", torch.ones(K, 1, h))

    def block(self, x, w, b, i):
        x = torch.baddbmm(b, x, w)
        if self.bn:
            rm, rv = getattr(self, f"rm{i}"), getattr(self, f"rv{i}")
            if self.training:
                mu, var = x.mean(1, keepdim=True), x.var(1, keepdim=True, unbiased=False)
                with torch.no_grad():
                    n = x.shape[1]
                    rm.mul_(0.9).add_(0.1 * mu)
                    rv.mul_(0.9).add_(0.1 * var * n / (n - 1))
            else:
                mu, var = rm, rv
            x = (x - mu) / torch.sqrt(var + 1e-5) * self.g[i] + self.be[i]
        x = self.act(x)
        if self.dropout > 0 and self.training:
            x = torch.nn.functional.dropout(x, self.dropout)
        return x

    def forward(self, x):
        a = self.block(x, self.w1, self.b1, 0)
        c = self.block(a, self.w2, self.b2, 1)
        h = self.block(torch.cat([a, c], -1), self.w3, self.b3, 2)
        return torch.baddbmm(self.bo, h, self.wo)


DEV = "cuda" if torch.cuda.is_available() else "cpu"


def train(cfg, tt, yt, K=5, dev=DEV):
    torch.manual_seed(cfg.get("seed", 0))
    rng = np.random.default_rng(cfg.get("seed", 0))
    tf = Transform(cfg["transform"], yt)
    X = torch.tensor(inputs(tt, cfg["input"]), dtype=torch.float32, device=dev)
    Y = torch.tensor(tf.fwd(yt), dtype=torch.float32, device=dev)
    n = len(tt)
    nv = max(1, round(cfg.get("val", 0.1) * n))
    tr_idx, va_idx = [], []
    for k in range(K):
        p = rng.permutation(n)
        va_idx.append(np.sort(p[:nv]))
        tr_idx.append(np.sort(p[nv:]))
    tr_idx = torch.tensor(np.stack(tr_idx), device=dev)
    va_idx = torch.tensor(np.stack(va_idx), device=dev)
    ntr = tr_idx.shape[1]
    net = Net(K, X.shape[1], Y.shape[1], cfg["hidden"], cfg["act"], cfg["bn"], cfg["dropout"]).to(dev)
    if cfg["opt"] == "adam":
        opt = torch.optim.Adam(net.parameters(), lr=cfg["lr"], weight_decay=cfg["wd"])
    else:
        opt = torch.optim.AdamW(net.parameters(), lr=cfg["lr"], weight_decay=cfg["wd"])
    bs = cfg["batch"]
    spe = math.ceil(ntr / bs)
    E = int(os.environ.get("SMOKE_EPOCHS", cfg["epochs"]))
    sched = None
    if cfg.get("schedule") == "cosine":
        sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg["lr"], total_steps=E * spe, pct_start=0.05,
                                                    anneal_strategy="cos", div_factor=10, final_div_factor=1e3)
    best = torch.full((K,), float("inf"), device=dev)
    best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
    since = torch.zeros(K, device=dev)
    Xv, Yv = X[va_idx], Y[va_idx]
    patience = cfg.get("patience", 10 ** 9)
    ep_run = 0
    for ep in range(E):
        net.train()
        perm = torch.argsort(torch.rand(K, ntr, device=dev), 1)
        order = tr_idx.gather(1, perm)
        for s in range(spe):
            idx = order[:, s * bs:(s + 1) * bs]
            if idx.shape[1] < 2:
                continue
            loss = ((net(X[idx]) - Y[idx]) ** 2).mean(dim=(1, 2)).sum()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if sched is not None:
                sched.step()
        net.eval()
        with torch.no_grad():
            vl = ((net(Xv) - Yv) ** 2).mean(dim=(1, 2))
        imp = vl < best
        best = torch.where(imp, vl, best)
        since = torch.where(imp, torch.zeros_like(since), since + 1)
        if imp.any():
            sd = net.state_dict()
            for key, v in sd.items():
                if v.dim() >= 1 and v.shape[0] == K:
                    m = imp.view(K, *([1] * (v.dim() - 1)))
                    best_state[key] = torch.where(m, v.detach(), best_state[key])
        ep_run = ep + 1
        if (since > patience).all():
            break
    net.load_state_dict(best_state)
    net.eval()
    return net, tf, ep_run


def predict(net, tf, cfg, theta, dev=DEV):
    with torch.no_grad():
        x = torch.tensor(inputs(theta, cfg["input"]), dtype=torch.float32, device=dev)
        t = net(x.unsqueeze(0).expand(net.w1.shape[0], -1, -1)).double().cpu().numpy()
    return np.stack([tf.inv(t[k]) for k in range(len(t))])


PAPER = dict(transform="none", input="theta", hidden=(256, 256, 128), act="relu", bn=True, dropout=0.1,
             opt="adam", lr=1e-3, wd=1e-4, batch=64, epochs=1000, patience=50)
MODERN = dict(transform="yj", input="theta", hidden=(256, 256, 128), act="silu", bn=False, dropout=0.0,
              opt="adamw", lr=3e-3, wd=1e-4, batch=64, epochs=600, schedule="cosine")


def configs():
    c = {
        "paper": PAPER,
        "paper_yj": {**PAPER, "transform": "yj"},
        "paper_quantile": {**PAPER, "transform": "quantile"},
        "paper_nodrop": {**PAPER, "dropout": 0.0},
        "modern_none": {**MODERN, "transform": "none"},
        "modern_yj": MODERN,
        "modern_quantile": {**MODERN, "transform": "quantile"},
        "modern_yj_relu": {**MODERN, "act": "relu"},
        "modern_yj_gelu": {**MODERN, "act": "gelu"},
        "modern_yj_bn": {**MODERN, "bn": True},
        "modern_yj_wide": {**MODERN, "hidden": (512, 512, 256)},
        "modern_yj_logphys": {**MODERN, "input": "logphys"},
        "modern_yj_long": {**MODERN, "epochs": 1500},
        "modern_yj_lr1e3": {**MODERN, "lr": 1e-3},
        "modern_yj_b32": {**MODERN, "batch": 32, "epochs": 400},
        "modern_yj_wd1e3": {**MODERN, "wd": 1e-3},
        "modern_yj_drop05": {**MODERN, "dropout": 0.05},
        "modern_none_logphys": {**MODERN, "transform": "none", "input": "logphys"},
    }
    return c


PREDS = {}


def run_one(name, cfg, sizes):
    t0 = time.time()
    res = {"config": {k: list(v) if isinstance(v, tuple) else v for k, v in cfg.items()}, "curve": []}
    for size in sizes:
        idx = np.arange(len(TT)) if size >= len(TT) else np.random.default_rng(100).permutation(len(TT))[:size]
        net, tf, ep = train(cfg, TT[idx], YT[idx])
        P = predict(net, tf, cfg, TV)
        members = [r2(YV, P[k]) for k in range(len(P))]
        ens = r2(YV, P.mean(0))
        row = {"n_train": int(len(idx)), "epochs": ep, "member_r2": [m[0] for m in members],
               "member0_per_feature": members[0][1], "ensemble_r2": ens[0], "ensemble_per_feature": ens[1],
               "member_mean_per_feature": np.mean([m[1] for m in members], 0).tolist()}
        res["curve"].append(row)
        with open(os.path.join(OUT, f"cfg_{name}{SUFFIX}.json"), "w") as f:
            json.dump(res, f)
        if size >= len(TT):
            PREDS[name] = P.astype(np.float32)
            np.savez_compressed(os.path.join(OUT, f"pred_{name}{SUFFIX}.npz"), P=P.astype(np.float32))
        print(f"{name} n={len(idx)} ep={ep} member0 {members[0][0]:.4f} mean-member "
              f"{np.mean([m[0] for m in members]):.4f} ens {ens[0]:.4f} min {min(ens[1]):.3f} "
              f"({time.time() - t0:.0f}s)", flush=True)
    res["time_s"] = time.time() - t0
    with open(os.path.join(OUT, f"cfg_{name}{SUFFIX}.json"), "w") as f:
        json.dump(res, f)


if __name__ == "__main__":
    name = sys.argv[3]
    cfgs = configs()
    SUFFIX = "_lc" if len(sys.argv) > 4 else ""
    sizes = [int(s) for s in sys.argv[4].split(",")] if len(sys.argv) > 4 else [len(TT)]
    run_one(name, cfgs[name], sizes)
