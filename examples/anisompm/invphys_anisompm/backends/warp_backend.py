"""NVIDIA Warp kernels of the engine: the same step as the Taichi backend, kernel for kernel.

The substep index lives on the device (``kstep``) and the last launch of a substep increments it, so a
substep has no host-side arguments: on CUDA, :meth:`WarpBackend.advance` replays captured CUDA graphs of
:data:`GRAPH_CHUNK` substeps instead of launching kernels one by one. On CPU, Warp runs each kernel
serially in launch-index order, so the particle-to-grid scatter sums in a fixed order and runs repeat
bit-for-bit. Warp arrays have at most 4 dimensions: per-grip grid masses are stored as
``(B * n_grips, G, G, G)``.
"""

from __future__ import annotations

import threading

import numpy as np
import warp as wp

from invphys.core.errors import DeviceUnavailableError
from invphys_anisompm.backends import quiet_library
from invphys_anisompm.failure import BODY0, n_stats
from invphys_anisompm.materials import M_ALPHA, M_DMG, M_ETA, M_KF, M_LAM, M_MU, M_RES, M_RHO, M_SC, N_MAT
from invphys_anisompm.scene import SURFACES

wp.config.log_level = wp.LOG_WARNING
wp.set_module_options({"enable_backward": False})

_init_lock = threading.Lock()
#: substeps per captured CUDA graph
GRAPH_CHUNK = 8
J_MIN = wp.constant(1.0e-6)
C_MU, C_LAM, C_KF, C_RHO, C_SC, C_ETA, C_RES, C_ALPHA, C_DMG = (wp.constant(c) for c in (
    M_MU, M_LAM, M_KF, M_RHO, M_SC, M_ETA, M_RES, M_ALPHA, M_DMG))
C_BODY0 = wp.constant(BODY0)


def cuda_available() -> bool:
    """Whether Warp sees a CUDA device here (initialises Warp)."""
    with _init_lock, quiet_library():
        wp.init()
    return wp.is_cuda_available()


def resolve_device(arch: str, allow_cpu_fallback: bool = False) -> str:
    """The Warp device for ``arch`` ("cpu", "cuda" or "auto"): "cpu" or "cuda:0"."""
    if arch == "cpu":
        with _init_lock, quiet_library():
            wp.init()
        return "cpu"
    if cuda_available():
        return "cuda:0"
    if arch == "cuda" and not allow_cpu_fallback:
        raise DeviceUnavailableError("arch='cuda' was requested but no CUDA GPU is available to Warp here; "
                                     "use arch='cpu' or 'auto', or set allow_cpu_fallback=true")
    return "cpu"


def device_name(device: str) -> str:
    if device.startswith("cuda"):
        return "cuda:" + wp.get_device(device).name
    import os
    import platform

    return f"cpu:{platform.processor() or platform.machine()}x{os.cpu_count()}"


@wp.func
def _weights(fx: wp.vec3):
    w0 = wp.cw_mul(wp.vec3(1.5) - fx, wp.vec3(1.5) - fx) * 0.5
    f1 = fx - wp.vec3(1.0)
    w1 = wp.vec3(0.75) - wp.cw_mul(f1, f1)
    f2 = fx - wp.vec3(0.5)
    w2 = wp.cw_mul(f2, f2) * 0.5
    return wp.matrix_from_rows(w0, w1, w2)


@wp.func
def _base(x: wp.vec3, inv_dx: float, G: int):
    Xp = x * inv_dx
    return wp.vec3i(wp.clamp(int(Xp[0] - 0.5), 0, G - 3), wp.clamp(int(Xp[1] - 0.5), 0, G - 3),
                    wp.clamp(int(Xp[2] - 0.5), 0, G - 3))


@wp.func
def _collider_normal(kind: int, a: wp.vec3, bb: wp.vec3, p: wp.vec3):
    """(outward unit normal, inside flag) of point ``p`` for a collider shape in its own frame."""
    inside = 0
    n = wp.vec3(0.0, 1.0, 0.0)
    if kind == 0:
        if wp.dot(p - a, bb) <= 0.0:
            inside = 1
            n = bb
    elif kind == 1:
        c = 0.5 * (a + bb)
        e = 0.5 * (bb - a)
        r = p - c
        q = wp.vec3(wp.abs(r[0]) - e[0], wp.abs(r[1]) - e[1], wp.abs(r[2]) - e[2])
        if q[0] <= 0.0 and q[1] <= 0.0 and q[2] <= 0.0:
            inside = 1
            if q[0] >= q[1] and q[0] >= q[2]:
                n = wp.vec3(wp.where(r[0] >= 0.0, 1.0, -1.0), 0.0, 0.0)
            elif q[1] >= q[2]:
                n = wp.vec3(0.0, wp.where(r[1] >= 0.0, 1.0, -1.0), 0.0)
            else:
                n = wp.vec3(0.0, 0.0, wp.where(r[2] >= 0.0, 1.0, -1.0))
    else:
        ax = int(bb[1] + 0.5)
        e = wp.vec3(wp.where(ax == 0, 1.0, 0.0), wp.where(ax == 1, 1.0, 0.0), wp.where(ax == 2, 1.0, 0.0))
        r = p - a
        along = wp.dot(r, e)
        rad = r - along * e
        dist = wp.length(rad)
        if dist <= bb[0] and wp.abs(along) <= bb[2]:
            inside = 1
            if dist > 1.0e-9:
                n = rad / dist
    return n, inside


def _p2g(kstep: wp.array(dtype=wp.int32), dx: float, apic: float, ngrip: int, nsub: wp.array(dtype=wp.int32),
         dt: wp.array(dtype=wp.float32), mat: wp.array3d(dtype=wp.float32), body: wp.array(dtype=wp.int32),
         fibre: wp.array(dtype=wp.vec3), vol: wp.array(dtype=wp.float32), grip: wp.array(dtype=wp.int32),
         x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3), C: wp.array2d(dtype=wp.mat33),
         F: wp.array2d(dtype=wp.mat33), d: wp.array2d(dtype=wp.float32), dtil: wp.array2d(dtype=wp.float32),
         gv: wp.array4d(dtype=wp.vec3), gm: wp.array4d(dtype=wp.float32), gd: wp.array4d(dtype=wp.vec2),
         gg: wp.array4d(dtype=wp.float32)):
    b, p = wp.tid()
    if kstep[0] >= nsub[b]:
        return
    h = dt[b]
    inv_dx = 1.0 / dx
    G = gm.shape[1]
    base = _base(x[b, p], inv_dx, G)
    fx = x[b, p] * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    w = _weights(fx)
    Fp = F[b, p]
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(Fp, U, sig, V)
    J = sig[0] * sig[1] * sig[2]
    reg = body[p]
    dp = d[b, p]
    mu = mat[b, reg, C_MU]
    lam = mat[b, reg, C_LAM]
    res = mat[b, reg, C_RES]
    g = (1.0 - dp) * (1.0 - dp) * (1.0 - res) + res
    gvol = 1.0
    if J >= 1.0:
        gvol = g
    tau_d = wp.vec3()
    s_pos = wp.vec3()
    vol_t = lam * (J - 1.0) * J
    for a in range(3):
        dev = 2.0 * mu * (sig[a] - 1.0) * sig[a]
        tau_d[a] = g * dev + gvol * vol_t
        if J > J_MIN:
            s_pos[a] = wp.max((dev + vol_t) / J, 0.0)
    tau = U @ wp.diag(tau_d) @ wp.transpose(U)
    sigp = U @ wp.diag(s_pos) @ wp.transpose(U)
    A = wp.identity(n=3, dtype=wp.float32)
    a0 = fibre[p]
    if wp.dot(a0, a0) > 0.0:
        kf = mat[b, reg, C_KF]
        if kf > 0.0:
            fa = Fp @ a0
            lf = wp.length(fa)
            if lf > 1.0e-6:
                tau += (kf * (lf - 1.0) / lf) * wp.outer(fa, fa)
        ra = (U @ wp.transpose(V)) @ a0
        A += mat[b, reg, C_ALPHA] * wp.outer(ra, ra)
    M = A @ sigp
    sc = mat[b, reg, C_SC]
    phi = wp.ddot(M, wp.transpose(M)) / (sc * sc)
    dtil[b, p] = wp.max(phi - 1.0, 0.0)
    vp_ = vol[p]
    mass = mat[b, reg, C_RHO] * vp_
    affine = (-h * vp_ * 4.0 * inv_dx * inv_dx) * tau + (mass * apic) * C[b, p]
    vp = v[b, p]
    gp = grip[p]
    for i in range(3):
        for j in range(3):
            for q in range(3):
                dpos = (wp.vec3(float(i), float(j), float(q)) - fx) * dx
                weight = w[i, 0] * w[j, 1] * w[q, 2]
                ni = base[0] + i
                nj = base[1] + j
                nl = base[2] + q
                wp.atomic_add(gv, b, ni, nj, nl, weight * (mass * vp + affine @ dpos))
                wp.atomic_add(gm, b, ni, nj, nl, weight * mass)
                wp.atomic_add(gd, b, ni, nj, nl, weight * wp.vec2(dp, 1.0))
                if gp >= 0:
                    wp.atomic_add(gg, b * ngrip + gp, ni, nj, nl, weight * mass)


p2g_kernel = wp.kernel(_p2g, name="anisompm_p2g")
_P2G_DETERMINISTIC: list = []


def p2g_deterministic_kernel():
    """P2G compiled in Warp's RUN_TO_RUN deterministic mode (sorted grid atomics; CUDA runs repeat
    bit-for-bit, at a cost in speed)."""
    if not _P2G_DETERMINISTIC:
        _P2G_DETERMINISTIC.append(wp.kernel(
            _p2g, name="anisompm_p2g_deterministic", module="unique",
            module_options={"deterministic": wp.DeterministicMode.RUN_TO_RUN, "enable_backward": False}))
    return _P2G_DETERMINISTIC[0]


@wp.func
def _zero_node(b: int, i: int, j: int, q: int, ngrip: int, gv: wp.array4d(dtype=wp.vec3),
               gm: wp.array4d(dtype=wp.float32), gd: wp.array4d(dtype=wp.vec2), gg: wp.array4d(dtype=wp.float32)):
    gv[b, i, j, q] = wp.vec3(0.0)
    gm[b, i, j, q] = 0.0
    gd[b, i, j, q] = wp.vec2(0.0)
    for g in range(ngrip):
        gg[b * ngrip + g, i, j, q] = 0.0


@wp.kernel
def clear_kernel(kstep: wp.array(dtype=wp.int32), ngrip: int, nsub: wp.array(dtype=wp.int32),
                 gv: wp.array4d(dtype=wp.vec3), gm: wp.array4d(dtype=wp.float32), gd: wp.array4d(dtype=wp.vec2),
                 gg: wp.array4d(dtype=wp.float32)):
    # only the nodes the last scatter touched (a zero weight sum: every channel is zero; see the Taichi
    # backend's touched_node): one read per node instead of seven writes
    b, i, j, q = wp.tid()
    if kstep[0] >= nsub[b] or gd[b, i, j, q][1] == 0.0:
        return
    _zero_node(b, i, j, q, ngrip, gv, gm, gd, gg)


@wp.kernel
def wipe_grid_kernel(mask: wp.array(dtype=wp.int32), ngrip: int, gv: wp.array4d(dtype=wp.vec3),
                     gm: wp.array4d(dtype=wp.float32), gd: wp.array4d(dtype=wp.vec2), gg: wp.array4d(dtype=wp.float32)):
    # every node of runs mask[b] != 0 (a new run in a slot: nothing of the last run's grid survives)
    b, i, j, q = wp.tid()
    if mask[b] != 0:
        _zero_node(b, i, j, q, ngrip, gv, gm, gd, gg)


@wp.kernel
def grid_update_kernel(kstep: wp.array(dtype=wp.int32), dx: float, gravity: float, damp: wp.array(dtype=wp.float32),
                       bc: int, ngrip: int, ncol: int,
                       nsub: wp.array(dtype=wp.int32), dt: wp.array(dtype=wp.float32),
                       kin: wp.array4d(dtype=wp.float32), ctype: wp.array(dtype=wp.int32),
                       ca: wp.array(dtype=wp.vec3), cb: wp.array(dtype=wp.vec3), csurf: wp.array(dtype=wp.int32),
                       fric: wp.array2d(dtype=wp.float32), held: wp.array3d(dtype=wp.int32),
                       gv: wp.array4d(dtype=wp.vec3), gm: wp.array4d(dtype=wp.float32),
                       gg: wp.array4d(dtype=wp.float32), imp: wp.array2d(dtype=wp.vec3),
                       work: wp.array2d(dtype=wp.float32)):
    b, i, j, q = wp.tid()
    k = kstep[0]
    m = gm[b, i, j, q]
    if k >= nsub[b] or m <= 0.0:
        return
    G = gm.shape[1]
    vel = gv[b, i, j, q] / m
    vel = vel + wp.vec3(0.0, dt[b] * gravity, 0.0)
    vel = vel / (1.0 + damp[b] * dt[b])
    ngrip_ = ngrip
    for g in range(ngrip_):
        if gg[b * ngrip + g, i, j, q] > 0.5 * m:
            vk = wp.vec3(kin[b, k, g, 3], kin[b, k, g, 4], kin[b, k, g, 5])
            wp.atomic_add(imp, b, g, m * (vel - vk))
            wp.atomic_add(work, b, g, m * wp.dot(vk - vel, vk))
            vel = vk
    pos = wp.vec3(float(i), float(j), float(q)) * dx
    for c in range(ncol):
        kc = ngrip + c
        disp = wp.vec3(kin[b, k, kc, 0], kin[b, k, kc, 1], kin[b, k, kc, 2])
        vc = wp.vec3(kin[b, k, kc, 3], kin[b, k, kc, 4], kin[b, k, kc, 5])
        n, inside = _collider_normal(ctype[c], ca[c], cb[c], pos - disp)
        if inside != 0:
            old = vel
            rel = vel - vc
            if csurf[c] == 0:
                rel = wp.vec3(0.0)
            else:
                vn = wp.dot(rel, n)
                if csurf[c] == 1 or vn < 0.0:
                    rel_t = rel - vn * n
                    if vn < 0.0:
                        lt = wp.length(rel_t)
                        if lt > 1.0e-12:
                            rel_t = rel_t * wp.max(0.0, 1.0 + fric[b, c] * vn / lt)
                    rel = rel_t
            vel = vc + rel
            wp.atomic_add(imp, b, kc, m * (old - vel))
            wp.atomic_add(work, b, kc, m * wp.dot(vel - old, vc))
    if held[i, j, q] != 0:
        vel = wp.vec3(0.0)
    if i < bc and vel[0] < 0.0:
        vel[0] = 0.0
    if i > G - bc and vel[0] > 0.0:
        vel[0] = 0.0
    if j <= bc and vel[1] < 0.0:
        vel[1] = 0.0
    if j > G - bc and vel[1] > 0.0:
        vel[1] = 0.0
    if q < bc and vel[2] < 0.0:
        vel[2] = 0.0
    if q > G - bc and vel[2] > 0.0:
        vel[2] = 0.0
    gv[b, i, j, q] = vel


@wp.kernel
def g2p_kernel(kstep: wp.array(dtype=wp.int32), dx: float, l0sq: float, don: wp.array(dtype=wp.int32),
               nsub: wp.array(dtype=wp.int32), dt: wp.array(dtype=wp.float32), mat: wp.array3d(dtype=wp.float32),
               body: wp.array(dtype=wp.int32), grip: wp.array(dtype=wp.int32), x0: wp.array(dtype=wp.vec3),
               kin: wp.array4d(dtype=wp.float32), x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
               C: wp.array2d(dtype=wp.mat33), F: wp.array2d(dtype=wp.mat33), d: wp.array2d(dtype=wp.float32),
               dtil: wp.array2d(dtype=wp.float32), gv: wp.array4d(dtype=wp.vec3), gd: wp.array4d(dtype=wp.vec2)):
    b, p = wp.tid()
    k = kstep[0]
    if k >= nsub[b]:
        return
    h = dt[b]
    inv_dx = 1.0 / dx
    G = gv.shape[1]
    base = _base(x[b, p], inv_dx, G)
    fx = x[b, p] * inv_dx - wp.vec3(float(base[0]), float(base[1]), float(base[2]))
    w = _weights(fx)
    hs = wp.vec3(1.0, -2.0, 1.0)
    dp = d[b, p]
    new_v = wp.vec3()
    new_C = wp.mat33()
    lap = wp.float32(0.0)
    for i in range(3):
        for j in range(3):
            for q in range(3):
                weight = w[i, 0] * w[j, 1] * w[q, 2]
                ni = base[0] + i
                nj = base[1] + j
                nl = base[2] + q
                gvel = gv[b, ni, nj, nl]
                new_v += weight * gvel
                new_C += (4.0 * inv_dx * weight) * wp.outer(gvel, wp.vec3(float(i), float(j), float(q)) - fx)
                g2 = gd[b, ni, nj, nl]
                if g2[1] > 0.0:
                    hess = hs[i] * w[j, 1] * w[q, 2] + w[i, 0] * hs[j] * w[q, 2] + w[i, 0] * w[j, 1] * hs[q]
                    lap += (g2[0] / g2[1] - dp) * hess
    reg = body[p]
    if don[b] != 0 and mat[b, reg, C_DMG] > 0.5:
        Dc = dp - l0sq * lap
        rate = (1.0 - dp) * dtil[b, p] - Dc
        d[b, p] = wp.min(1.0, dp + h / mat[b, reg, C_ETA] * wp.max(rate, 0.0))
    F[b, p] = (wp.identity(n=3, dtype=wp.float32) + h * new_C) @ F[b, p]
    C[b, p] = new_C
    gp = grip[p]
    if gp >= 0:
        x[b, p] = x0[p] + wp.vec3(kin[b, k, gp, 0], kin[b, k, gp, 1], kin[b, k, gp, 2])
        v[b, p] = wp.vec3(kin[b, k, gp, 3], kin[b, k, gp, 4], kin[b, k, gp, 5])
    else:
        v[b, p] = new_v
        x[b, p] = x[b, p] + h * new_v


@wp.kernel
def reset_slots_kernel(mask: wp.array(dtype=wp.int32), x0: wp.array(dtype=wp.vec3), x: wp.array2d(dtype=wp.vec3),
                       v: wp.array2d(dtype=wp.vec3), C: wp.array2d(dtype=wp.mat33), F: wp.array2d(dtype=wp.mat33),
                       d: wp.array2d(dtype=wp.float32), dtil: wp.array2d(dtype=wp.float32)):
    b, p = wp.tid()
    if mask[b] == 0:
        return
    x[b, p] = x0[p]
    v[b, p] = wp.vec3(0.0)
    C[b, p] = wp.mat33(0.0)
    F[b, p] = wp.identity(n=3, dtype=wp.float32)
    d[b, p] = 0.0
    dtil[b, p] = 0.0


@wp.kernel
def gather_kernel(idx: wp.array(dtype=wp.int32), x: wp.array2d(dtype=wp.vec3), d: wp.array2d(dtype=wp.float32),
                  xo: wp.array2d(dtype=wp.vec3), dout: wp.array2d(dtype=wp.float32)):
    i, p = wp.tid()
    xo[i, p] = x[idx[i], p]
    dout[i, p] = d[idx[i], p]


@wp.kernel
def next_substep_kernel(kstep: wp.array(dtype=wp.int32)):
    kstep[0] = kstep[0] + 1


@wp.kernel
def frame_stats_kernel(lo: float, hi: float, mask: wp.array(dtype=wp.int32), mat: wp.array3d(dtype=wp.float32),
                       body: wp.array(dtype=wp.int32),
                       vol: wp.array(dtype=wp.float32), x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3),
                       F: wp.array2d(dtype=wp.mat33), d: wp.array2d(dtype=wp.float32),
                       out: wp.array2d(dtype=wp.float32)):
    b, p = wp.tid()
    if mask[b] == 0:
        return
    xp = x[b, p]
    vp = v[b, p]
    dp = d[b, p]
    s = wp.length(vp)
    Fp = F[b, p]
    fmax = wp.float32(0.0)
    for i in range(3):
        for j in range(3):
            fmax = wp.max(fmax, wp.abs(Fp[i, j]))
    bad = 0
    if not (s < 1.0e20) or not (wp.max(wp.abs(xp)) < 1.0e20) or not (fmax < 1.0e20) or not (wp.abs(dp) < 1.0e20):
        bad = 1
    if bad != 0:
        wp.atomic_add(out, b, 2, 1.0)
    else:
        reg = body[p]
        wp.atomic_max(out, b, 0, s)
        wp.atomic_add(out, b, 1, 0.5 * mat[b, reg, C_RHO] * vol[p] * s * s)
        if wp.min(xp) < lo or wp.max(xp) > hi:
            wp.atomic_add(out, b, 3, 1.0)
        col = C_BODY0 + 4 * reg
        for a in range(3):
            wp.atomic_add(out, b, col + a, xp[a])
        wp.atomic_add(out, b, col + 3, dp)


class WarpBackend:
    """Batched engine state and kernels on one Warp device (CPU or CUDA).

    ``use_graphs`` (default: on CUDA) replays captured CUDA graphs for the substeps;
    ``gpu_deterministic`` compiles the P2G scatter in Warp's deterministic mode.
    """

    name = "warp"

    def __init__(self, scene, batch: int, arch: str = "cpu", allow_cpu_fallback: bool = False,
                 use_graphs: bool | None = None, gpu_deterministic: bool = False):
        self.wp_device = resolve_device(arch, allow_cpu_fallback)
        self.arch = "cuda" if self.wp_device.startswith("cuda") else "cpu"
        self.device = device_name(self.wp_device)
        #: on the CPU ``numpy()`` is a view of the simulator's memory (the next substep changes it): copy
        self.reads_are_new = self.arch == "cuda"
        self.scene = scene
        o = scene.options
        self.options = o
        self.batch = int(batch)
        self.use_graphs = (self.arch == "cuda") if use_graphs is None else bool(use_graphs and self.arch == "cuda")
        self.gpu_deterministic = bool(gpu_deterministic and self.arch == "cuda")
        self._p2g_kernel = p2g_deterministic_kernel() if self.gpu_deterministic else p2g_kernel
        B, N, G = self.batch, scene.n_particles, o.grid
        self.ngrip = len(scene.grips)
        self.ncol = len(scene.colliders)
        NG1, NK1, NC1 = max(self.ngrip, 1), max(self.ngrip + self.ncol, 1), max(self.ncol, 1)
        self.nk1 = NK1
        self.nstats = n_stats(len(scene.bodies))
        enc = [c.encode() for c in scene.colliders] or [(0, np.zeros(3), np.array([0.0, 1.0, 0.0]))]
        with wp.ScopedDevice(self.wp_device):
            self.x = wp.zeros((B, N), dtype=wp.vec3)
            self.v = wp.zeros((B, N), dtype=wp.vec3)
            self.C = wp.zeros((B, N), dtype=wp.mat33)
            self.F = wp.zeros((B, N), dtype=wp.mat33)
            self.d = wp.zeros((B, N), dtype=wp.float32)
            self.dtil = wp.zeros((B, N), dtype=wp.float32)
            self.gv = wp.zeros((B, G, G, G), dtype=wp.vec3)
            self.gm = wp.zeros((B, G, G, G), dtype=wp.float32)
            self.gd = wp.zeros((B, G, G, G), dtype=wp.vec2)
            self.gg = wp.zeros((B * NG1, G, G, G), dtype=wp.float32)
            self.mat = wp.zeros((B, len(scene.bodies), N_MAT), dtype=wp.float32)
            self.fric = wp.zeros((B, NC1), dtype=wp.float32)
            self.nsub = wp.zeros(B, dtype=wp.int32)
            self.dt = wp.zeros(B, dtype=wp.float32)
            self.kstep = wp.zeros(1, dtype=wp.int32)
            self.stats_out = wp.zeros((B, self.nstats), dtype=wp.float32)
            self.imp = wp.zeros((B, NK1), dtype=wp.vec3)
            self.work = wp.zeros((B, NK1), dtype=wp.float32)
            self.body = wp.array(scene.body.astype(np.int32), dtype=wp.int32)
            self.fibre = wp.array(scene.fibres.astype(np.float32), dtype=wp.vec3)
            self.vol = wp.array(scene.volume.astype(np.float32), dtype=wp.float32)
            self.grip = wp.array(scene.grip.astype(np.int32), dtype=wp.int32)
            self.x0 = wp.array(scene.positions.astype(np.float32), dtype=wp.vec3)
            self.held = wp.array(scene.held.astype(np.int32), dtype=wp.int32)
            self.ctype = wp.array(np.array([e[0] for e in enc], np.int32), dtype=wp.int32)
            self.ca = wp.array(np.array([e[1] for e in enc], np.float32), dtype=wp.vec3)
            self.cb = wp.array(np.array([e[2] for e in enc], np.float32), dtype=wp.vec3)
            self.csurf = wp.array(np.array([SURFACES[c.surface] for c in scene.colliders] or [0], np.int32),
                                  dtype=wp.int32)
        self._kin_capacity = 0
        self.kin = None
        self._reserve_kin(max(GRAPH_CHUNK, 4 * o.min_substeps_per_frame))
        self._graphs: dict[int, object] = {}
        self.damp = wp.zeros(B, dtype=wp.float32, device=self.wp_device)
        self.don = wp.zeros(B, dtype=wp.int32, device=self.wp_device)
        self._mat_host = np.zeros((B, len(scene.bodies), N_MAT), np.float32)
        self._fric_host = np.zeros((B, NC1), np.float32)
        self._slot_mask = wp.zeros(B, dtype=wp.int32, device=self.wp_device)
        self._stats_mask = wp.zeros(B, dtype=wp.int32, device=self.wp_device)
        self._gather_bufs: dict[int, tuple] = {}
        self._x_init = np.ascontiguousarray(np.broadcast_to(scene.positions.astype(np.float32), (B, N, 3)))
        self._F_init = np.ascontiguousarray(np.broadcast_to(np.eye(3, dtype=np.float32), (B, N, 3, 3)))

    def _reserve_kin(self, k: int) -> None:
        """Make the kinematic table hold at least ``k`` substeps (a new buffer drops captured graphs)."""
        if k <= self._kin_capacity:
            return
        cap = max(k, 2 * self._kin_capacity)
        self.kin = wp.zeros((self.batch, cap, self.nk1, 6), dtype=wp.float32, device=self.wp_device)
        self._kin_capacity = cap
        self._graphs = {}

    def load(self, table: np.ndarray, friction: np.ndarray) -> None:
        """Reset every run to the initial state with its own materials and collider frictions."""
        self._mat_host[:] = table
        self._fric_host[:, :self.ncol] = friction
        self.mat.assign(self._mat_host)
        self.fric.assign(self._fric_host)
        self.imp.zero_()
        self.work.zero_()
        self.x.assign(self._x_init)
        self.v.zero_()
        self.C.zero_()
        self.F.assign(self._F_init)
        self.d.zero_()
        self.dtil.zero_()
        self._slot_mask.fill_(1)
        self._wipe_grid()

    def set_frame(self, dt: np.ndarray, nsub: np.ndarray, kin: np.ndarray, damage_on: bool,
                  damping: float = 0.0) -> None:
        """Per-run dt (B,), substep counts (B,), kinematic table (B, K, n_kinematic, 6) of the next frame,
        whether damage evolves, and the grid velocity damping rate (1/s; settling only)."""
        self.dt.assign(np.ascontiguousarray(dt, dtype=np.float32))
        self.nsub.assign(np.ascontiguousarray(nsub, dtype=np.int32))
        K = kin.shape[1]
        self._reserve_kin(K)
        table = np.zeros((self.batch, self._kin_capacity, self.nk1, 6), np.float32)
        table[:, :K, :kin.shape[2]] = kin
        self.kin.assign(table)
        B = self.batch
        self.damp.assign(np.broadcast_to(np.asarray(damping, np.float32), (B,)).copy())
        self.don.assign((np.broadcast_to(np.asarray(damage_on), (B,)) != 0).astype(np.int32)
                        * np.int32(self.options.damage))

    def _clear(self) -> None:
        B, G = self.batch, self.options.grid
        wp.launch(clear_kernel, dim=(B, G, G, G), device=self.wp_device,
                  inputs=[self.kstep, max(self.ngrip, 1), self.nsub, self.gv, self.gm, self.gd, self.gg])

    def _p2g(self) -> None:
        o = self.options
        wp.launch(self._p2g_kernel, dim=(self.batch, self.scene.n_particles), device=self.wp_device, inputs=[
            self.kstep, float(o.dx), float(o.apic_blend), max(self.ngrip, 1), self.nsub, self.dt, self.mat, self.body,
            self.fibre, self.vol, self.grip, self.x, self.v, self.C, self.F, self.d, self.dtil, self.gv, self.gm,
            self.gd, self.gg])

    def _grid_update(self) -> None:
        o, G = self.options, self.options.grid
        wp.launch(grid_update_kernel, dim=(self.batch, G, G, G), device=self.wp_device, inputs=[
            self.kstep, float(o.dx), float(o.gravity), self.damp, int(o.boundary_cells), self.ngrip, self.ncol, self.nsub,
            self.dt, self.kin, self.ctype, self.ca, self.cb, self.csurf, self.fric, self.held, self.gv, self.gm,
            self.gg, self.imp, self.work])

    def _g2p(self) -> None:
        o = self.options
        wp.launch(g2p_kernel, dim=(self.batch, self.scene.n_particles), device=self.wp_device, inputs=[
            self.kstep, float(o.dx), float(o.l0_cells) ** 2, self.don, self.nsub, self.dt,
            self.mat, self.body, self.grip, self.x0, self.kin, self.x, self.v, self.C, self.F, self.d, self.dtil,
            self.gv, self.gd])

    def _substep(self) -> None:
        self._clear()
        self._p2g()
        self._grid_update()
        self._g2p()
        wp.launch(next_substep_kernel, dim=1, device=self.wp_device, inputs=[self.kstep])

    def kernel_times(self, n_steps: int = 20) -> dict[str, float]:
        """Mean seconds per launch of each substep stage over ``n_steps`` synchronised substeps (profiling;
        advances the state of substep 0 of the current frame, so use a throw-away batch)."""
        import time

        stages = {"clear": self._clear, "p2g": self._p2g, "grid": self._grid_update, "g2p": self._g2p}
        total = dict.fromkeys(stages, 0.0)
        self.kstep.zero_()
        for _ in range(n_steps):
            for name, launch in stages.items():
                wp.synchronize_device(self.wp_device)
                t0 = time.perf_counter()
                launch()
                wp.synchronize_device(self.wp_device)
                total[name] += time.perf_counter() - t0
        return {k: v / n_steps for k, v in total.items()}

    def _graph(self, n: int):
        if n not in self._graphs:
            wp.load_module(device=self.wp_device)
            with wp.ScopedCapture(device=self.wp_device, force_module_load=False) as capture:
                for _ in range(n):
                    self._substep()
            self._graphs[n] = capture.graph
        return self._graphs[n]

    def advance(self, n_steps: int) -> None:
        """Run substeps 0..n_steps-1 of the current frame (runs past their own nsub idle)."""
        self.kstep.zero_()
        if not self.use_graphs:
            for _ in range(n_steps):
                self._substep()
            return
        chunks, rest = divmod(int(n_steps), GRAPH_CHUNK)
        for _ in range(chunks):
            wp.capture_launch(self._graph(GRAPH_CHUNK))
        for _ in range(rest):
            wp.capture_launch(self._graph(1))

    def load_slots(self, slots: np.ndarray, table: np.ndarray, friction: np.ndarray) -> None:
        """Reset only runs ``slots`` (indices) to the initial state with materials ``table``
        (len(slots), n_bodies, N_MAT) and frictions (len(slots), n_colliders); the others are untouched."""
        slots = np.asarray(slots, np.int64)
        self._mat_host[slots] = table
        self._fric_host[slots, :self.ncol] = friction
        self.mat.assign(self._mat_host)
        self.fric.assign(self._fric_host)
        mask = np.zeros(self.batch, np.int32)
        mask[slots] = 1
        self._slot_mask.assign(mask)
        wp.launch(reset_slots_kernel, dim=(self.batch, self.scene.n_particles), device=self.wp_device,
                  inputs=[self._slot_mask, self.x0, self.x, self.v, self.C, self.F, self.d, self.dtil])
        self._wipe_grid()

    def _wipe_grid(self) -> None:
        """Zero the whole grid of the runs in ``_slot_mask``."""
        G = self.options.grid
        wp.launch(wipe_grid_kernel, dim=(self.batch, G, G, G), device=self.wp_device,
                  inputs=[self._slot_mask, max(self.ngrip, 1), self.gv, self.gm, self.gd, self.gg])

    def read_slots(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, N, 3) and damage (n, N) of runs ``slots`` only (a device gather, then one copy)."""
        slots = np.asarray(slots, np.int32)
        n, N = len(slots), self.scene.n_particles
        if n not in self._gather_bufs:
            with wp.ScopedDevice(self.wp_device):
                self._gather_bufs[n] = (wp.zeros(n, dtype=wp.int32), wp.zeros((n, N), dtype=wp.vec3),
                                        wp.zeros((n, N), dtype=wp.float32))
        idx, xo, do = self._gather_bufs[n]
        idx.assign(slots)
        wp.launch(gather_kernel, dim=(n, N), device=self.wp_device, inputs=[idx, self.x, self.d, xo, do])
        return xo.numpy(), do.numpy()

    def frame_stats(self, lo: float, hi: float, slots: np.ndarray | None = None) -> np.ndarray:
        """(B, n_stats) statistics of the current state; with ``slots``, only those runs' rows."""
        mask = np.ones(self.batch, np.int32)
        if slots is not None:
            mask[:] = 0
            mask[np.asarray(slots, np.int64)] = 1
        self._stats_mask.assign(mask)
        self.stats_out.zero_()
        wp.launch(frame_stats_kernel, dim=(self.batch, self.scene.n_particles), device=self.wp_device,
                  inputs=[float(lo), float(hi), self._stats_mask, self.mat, self.body, self.vol, self.x, self.v, self.F, self.d,
                          self.stats_out])
        return self.stats_out.numpy().astype(np.float64)

    def frame_end(self, lo: float, hi: float, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``frame_stats(lo, hi, slots)`` and ``kinematic_sums(slots)`` (see the Taichi backend)."""
        imp, work = self.kinematic_sums(slots)
        return self.frame_stats(lo, hi, slots), imp, work

    def kinematic_sums(self, slots: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Impulse and work sums since the last call (see the Taichi backend); with ``slots``, only those
        runs' rows are returned and reset (the others keep accumulating)."""
        n = self.ngrip + self.ncol
        imp_all, work_all = self.imp.numpy().copy(), self.work.numpy().copy()  # on the CPU .numpy() is a view
        if slots is None:
            self.imp.zero_()
            self.work.zero_()
            return imp_all.astype(np.float64)[:, :n], work_all.astype(np.float64)[:, :n]
        slots = np.asarray(slots, np.int64)
        imp, work = imp_all[slots, :n].astype(np.float64), work_all[slots, :n].astype(np.float64)
        imp_all[slots] = 0.0
        work_all[slots] = 0.0
        self.imp.assign(imp_all)
        self.work.assign(work_all)
        return imp, work

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        return self.x.numpy(), self.d.numpy()

    def grid_mass(self) -> np.ndarray:
        return self.gm.numpy().astype(np.float64).reshape(self.batch, -1).sum(axis=1)

    def sync(self) -> None:
        wp.synchronize_device(self.wp_device)
