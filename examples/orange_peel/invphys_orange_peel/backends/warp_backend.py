"""All NVIDIA Warp kernels of the orange peel (explicit MLS-MPM + anisotropic phase-field damage).

The same step as :mod:`invphys_orange_peel.backends.taichi_backend`, kernel for kernel (the
algorithm is specified in docs/orange-peel/physics.md); only the kernels live here, the host-side
driver (:mod:`invphys_orange_peel.driver`) owns time stepping, recording and failure checks.
Every array carries a leading run index ``b``, so one launch advances every run of a batch; a run
whose substep index ``k`` is past its own ``nsub[b]`` for the current frame is idle.

The substep index lives on the device (``kstep``) and the last kernel of a substep increments it,
so a substep has no host-side arguments: on CUDA, :meth:`WarpBackend.advance` replays captured CUDA
graphs of :data:`GRAPH_CHUNK` substeps (and of one substep for the remainder) instead of launching
five kernels per substep. On CPU, Warp runs each kernel serially in launch-index order, so the
particle-to-grid scatter sums in a fixed order and runs repeat bit-for-bit.
"""

from __future__ import annotations

import threading

import numpy as np
import warp as wp

from invphys.core.errors import DeviceUnavailableError
from invphys_orange_peel.backends import quiet_library
from invphys_orange_peel.failure import N_STATS, STAT_WORK

wp.config.log_level = wp.LOG_WARNING  # no greeting, no per-module load lines
wp.set_module_options({"enable_backward": False})

_init_lock = threading.Lock()

#: substeps per captured CUDA graph (a frame replays ``nsub // GRAPH_CHUNK`` of those, then singles)
GRAPH_CHUNK = 8

# per-run material table columns (float32): same layout as the Taichi backend
M_MU, M_LAM, M_KF, M_MASS, M_SC0, M_SC1, M_ETA0, M_ETA1, M_RES0, M_RES1, M_GATE = range(11)
N_MAT = 11
#: below this volume ratio a particle is treated as inverted: no tensile driving force (audit item 7)
J_MIN = wp.constant(1.0e-6)


def cuda_available() -> bool:
    """Whether Warp sees a CUDA device here (initialises Warp)."""
    with _init_lock, quiet_library():
        wp.init()
    return wp.is_cuda_available()


def resolve_device(arch: str, allow_cpu_fallback: bool = False) -> str:
    """The Warp device for ``arch`` ("cpu", "cuda" or "auto"): "cpu" or "cuda:0".

    CUDA without a GPU raises :class:`DeviceUnavailableError` unless ``allow_cpu_fallback``.
    """
    if arch == "cpu":
        with _init_lock, quiet_library():
            wp.init()
        return "cpu"
    if cuda_available():
        return "cuda:0"
    if arch == "cuda" and not allow_cpu_fallback:
        raise DeviceUnavailableError(
            "arch='cuda' was requested but no CUDA GPU is available to Warp here; "
            "use arch='cpu' or 'auto', or set allow_cpu_fallback=true")
    return "cpu"


def device_name(device: str) -> str:
    """A readable device label recorded with each run, e.g. ``cuda:NVIDIA H100 80GB HBM3``."""
    if device.startswith("cuda"):
        return "cuda:" + wp.get_device(device).name
    import os
    import platform

    return f"cpu:{platform.processor() or platform.machine()}x{os.cpu_count()}"


# --------------------------------------------------------------------------------------------
# kernels
# --------------------------------------------------------------------------------------------

@wp.func
def _weights(fx: wp.vec3):
    """Quadratic B-spline weights, row ``i`` = weights of node offset ``i`` along x, y, z."""
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


def _p2g(kstep: wp.array(dtype=wp.int32), dx: float, vol: float, apic: float,
               nsub: wp.array(dtype=wp.int32), dt: wp.array(dtype=wp.float32),
               mat: wp.array2d(dtype=wp.float32), label: wp.array(dtype=wp.int32),
               fibre: wp.array(dtype=wp.vec3), gripped: wp.array(dtype=wp.int32),
               x: wp.array2d(dtype=wp.vec3), v: wp.array2d(dtype=wp.vec3), C: wp.array2d(dtype=wp.mat33),
               F: wp.array2d(dtype=wp.mat33), d: wp.array2d(dtype=wp.float32),
               dtil: wp.array2d(dtype=wp.float32), gv: wp.array4d(dtype=wp.vec3),
               gm: wp.array4d(dtype=wp.float32), gd: wp.array4d(dtype=wp.vec2),
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
    reg = label[p]
    dp = d[b, p]
    mu = mat[b, M_MU]
    lam = mat[b, M_LAM]
    res = mat[b, M_RES0 + reg]
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
        if J > J_MIN:  # an inverted or collapsed particle has no tensile driving force
            s_pos[a] = wp.max((dev + vol_t) / J, 0.0)
    tau = U @ wp.diag(tau_d) @ wp.transpose(U)
    sigp = U @ wp.diag(s_pos) @ wp.transpose(U)
    A = wp.identity(n=3, dtype=wp.float32)
    if reg == 0:
        a0 = fibre[p]
        fa = Fp @ a0
        lf = wp.length(fa)
        if lf > 1.0e-6:
            tau += (mat[b, M_KF] * (lf - 1.0) / lf) * wp.outer(fa, fa)
        ra = (U @ wp.transpose(V)) @ a0
        A -= wp.outer(ra, ra)
    M = A @ sigp
    sc = mat[b, M_SC0 + reg]
    phi = wp.ddot(M, wp.transpose(M)) / (sc * sc)
    dtil[b, p] = wp.max(phi - 1.0, 0.0)
    mass = mat[b, M_MASS]
    affine = (-h * vol * 4.0 * inv_dx * inv_dx) * tau + (mass * apic) * C[b, p]
    vp = v[b, p]
    gp = gripped[p]
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
                if gp != 0:
                    wp.atomic_add(gg, b, ni, nj, nl, weight * mass)


p2g_kernel = wp.kernel(_p2g, name="p2g_kernel")
_P2G_DETERMINISTIC: list = []


def p2g_deterministic_kernel():
    """The P2G kernel compiled in Warp's RUN_TO_RUN deterministic mode (its own module, built on first
    use): its grid atomics are recorded, sorted and reduced in a fixed order, so CUDA runs repeat
    bit-for-bit, at a cost in speed (see docs/orange-peel/warp.md)."""
    if not _P2G_DETERMINISTIC:
        _P2G_DETERMINISTIC.append(wp.kernel(
            _p2g, name="p2g_kernel_deterministic", module="unique",
            module_options={"deterministic": wp.DeterministicMode.RUN_TO_RUN, "enable_backward": False}))
    return _P2G_DETERMINISTIC[0]


@wp.kernel
def grid_update_kernel(kstep: wp.array(dtype=wp.int32), gravity: float, bc: int,
                       nsub: wp.array(dtype=wp.int32), dt: wp.array(dtype=wp.float32),
                       grip: wp.array3d(dtype=wp.float32), held: wp.array3d(dtype=wp.int32),
                       gv: wp.array4d(dtype=wp.vec3), gm: wp.array4d(dtype=wp.float32),
                       gg: wp.array4d(dtype=wp.float32), work: wp.array(dtype=wp.float32)):
    b, i, j, q = wp.tid()
    k = kstep[0]
    m = gm[b, i, j, q]
    if k >= nsub[b] or m <= 0.0:
        return
    G = gm.shape[1]
    vel = gv[b, i, j, q] / m
    vel[1] += dt[b] * gravity
    if gg[b, i, j, q] > 0.5 * m:
        vg = wp.vec3(grip[b, k, 3], grip[b, k, 4], grip[b, k, 5])
        # the gripper's impulse on this node, dotted with its velocity: work this substep
        wp.atomic_add(work, b, m * wp.dot(vg - vel, vg))
        vel = vg
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
def g2p_kernel(kstep: wp.array(dtype=wp.int32), dx: float, l0sq: float, damage_on: int,
               nsub: wp.array(dtype=wp.int32), dt: wp.array(dtype=wp.float32),
               mat: wp.array2d(dtype=wp.float32), label: wp.array(dtype=wp.int32),
               gripped: wp.array(dtype=wp.int32), x0: wp.array(dtype=wp.vec3),
               grip: wp.array3d(dtype=wp.float32), x: wp.array2d(dtype=wp.vec3),
               v: wp.array2d(dtype=wp.vec3), C: wp.array2d(dtype=wp.mat33), F: wp.array2d(dtype=wp.mat33),
               d: wp.array2d(dtype=wp.float32), dtil: wp.array2d(dtype=wp.float32),
               gv: wp.array4d(dtype=wp.vec3), gd: wp.array4d(dtype=wp.vec2)):
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
    if damage_on != 0 and mat[b, M_GATE] > 0.5:
        reg = label[p]
        Dc = dp - l0sq * lap
        rate = (1.0 - dp) * dtil[b, p] - Dc
        d[b, p] = wp.min(1.0, dp + h / mat[b, M_ETA0 + reg] * wp.max(rate, 0.0))
    F[b, p] = (wp.identity(n=3, dtype=wp.float32) + h * new_C) @ F[b, p]
    C[b, p] = new_C
    if gripped[p] != 0:
        x[b, p] = x0[p] + wp.vec3(grip[b, k, 0], grip[b, k, 1], grip[b, k, 2])
        v[b, p] = wp.vec3(grip[b, k, 3], grip[b, k, 4], grip[b, k, 5])
    else:
        v[b, p] = new_v
        x[b, p] = x[b, p] + h * new_v


@wp.kernel
def next_substep_kernel(kstep: wp.array(dtype=wp.int32)):
    kstep[0] = kstep[0] + 1


@wp.kernel
def frame_stats_kernel(lo: float, hi: float, ref: wp.vec3, mat: wp.array2d(dtype=wp.float32),
                       label: wp.array(dtype=wp.int32), x: wp.array2d(dtype=wp.vec3),
                       v: wp.array2d(dtype=wp.vec3), F: wp.array2d(dtype=wp.mat33),
                       d: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.float32)):
    b, p = wp.tid()
    xp = x[b, p]
    vp = v[b, p]
    dp = d[b, p]
    s = wp.length(vp)
    Fp = F[b, p]
    fmax = wp.float32(0.0)
    for i in range(3):
        for j in range(3):
            fmax = wp.max(fmax, wp.abs(Fp[i, j]))
    bad = wp.int32(0)
    if not (s < 1.0e20) or not (wp.max(wp.abs(xp)) < 1.0e20) or not (fmax < 1.0e20) or not (wp.abs(dp) < 1.0e20):
        bad = 1
    if bad != 0:
        wp.atomic_add(out, b, 2, 1.0)
    else:
        wp.atomic_max(out, b, 0, s)
        wp.atomic_add(out, b, 1, 0.5 * mat[b, M_MASS] * s * s)
        if wp.min(xp) < lo or wp.max(xp) > hi:
            wp.atomic_add(out, b, 3, 1.0)
        rel = xp - ref
        col = 4 + 3 * label[p]
        for a in range(3):
            wp.atomic_add(out, b, col + a, rel[a])
        wp.atomic_add(out, b, 10, dp)


# --------------------------------------------------------------------------------------------
# backend
# --------------------------------------------------------------------------------------------

class WarpBackend:
    """Batched AnisoMPM state and kernels on one Warp device (CPU or CUDA).

    Same interface as :class:`~invphys_orange_peel.backends.taichi_backend.TaichiBackend`:
    ``load``, ``set_frame``, ``advance``, ``frame_stats``, ``read``, ``sync`` (and ``grid_mass``,
    ``kernel_times`` for checks and profiling). ``settings`` is the
    driver's :class:`~invphys_orange_peel.driver.StepSettings`. ``use_graphs`` (default: on CUDA)
    replays captured CUDA graphs for the substeps; ``gpu_deterministic`` (default off) compiles the
    particle-to-grid scatter in Warp's deterministic mode so that CUDA runs repeat bit-for-bit.
    """

    name = "warp"

    def __init__(self, scene, batch: int, settings, arch: str = "cpu", allow_cpu_fallback: bool = False,
                 use_graphs: bool | None = None, gpu_deterministic: bool = False):
        self.wp_device = resolve_device(arch, allow_cpu_fallback)
        self.arch = "cuda" if self.wp_device.startswith("cuda") else "cpu"
        self.device = device_name(self.wp_device)
        self.scene = scene
        self.settings = settings
        self.batch = int(batch)
        self.use_graphs = (self.arch == "cuda") if use_graphs is None else bool(use_graphs and self.arch == "cuda")
        # CPU kernels already run serially (deterministic); on CUDA, opt in to sorted grid atomics
        self.gpu_deterministic = bool(gpu_deterministic and self.arch == "cuda")
        self._p2g_kernel = p2g_deterministic_kernel() if self.gpu_deterministic else p2g_kernel
        B, N, G = self.batch, scene.n_particles, scene.preset.grid
        dev = self.wp_device
        with wp.ScopedDevice(dev):
            self.x = wp.zeros((B, N), dtype=wp.vec3)
            self.v = wp.zeros((B, N), dtype=wp.vec3)
            self.C = wp.zeros((B, N), dtype=wp.mat33)
            self.F = wp.zeros((B, N), dtype=wp.mat33)
            self.d = wp.zeros((B, N), dtype=wp.float32)
            self.dtil = wp.zeros((B, N), dtype=wp.float32)
            self.gv = wp.zeros((B, G, G, G), dtype=wp.vec3)
            self.gm = wp.zeros((B, G, G, G), dtype=wp.float32)
            self.gd = wp.zeros((B, G, G, G), dtype=wp.vec2)
            self.gg = wp.zeros((B, G, G, G), dtype=wp.float32)
            self.mat = wp.zeros((B, N_MAT), dtype=wp.float32)
            self.nsub = wp.zeros(B, dtype=wp.int32)
            self.dt = wp.zeros(B, dtype=wp.float32)
            self.kstep = wp.zeros(1, dtype=wp.int32)
            self.stats_out = wp.zeros((B, N_STATS), dtype=wp.float32)
            self.work = wp.zeros(B, dtype=wp.float32)
            self.label = wp.array(scene.labels.astype(np.int32), dtype=wp.int32)
            self.fibre = wp.array(scene.fibres.astype(np.float32), dtype=wp.vec3)
            self.gripped = wp.array((scene.gripped & settings.gripper_on).astype(np.int32), dtype=wp.int32)
            self.x0 = wp.array(scene.positions.astype(np.float32), dtype=wp.vec3)
            self.held = wp.array(scene.held_node_mask().astype(np.int32), dtype=wp.int32)
        self._grip_capacity = 0
        self.grip = None
        self._reserve_grip(max(GRAPH_CHUNK, 4 * settings.min_substeps_per_frame))
        self._graphs: dict[int, object] = {}
        self._x_init = np.ascontiguousarray(
            np.broadcast_to(scene.positions.astype(np.float32), (B, N, 3)))
        self._F_init = np.ascontiguousarray(np.broadcast_to(np.eye(3, dtype=np.float32), (B, N, 3, 3)))

    # -- state --------------------------------------------------------------------------------
    def _reserve_grip(self, k: int) -> None:
        """Make the gripper table hold at least ``k`` substeps (a new buffer drops captured graphs)."""
        if k <= self._grip_capacity:
            return
        cap = max(k, 2 * self._grip_capacity)
        self.grip = wp.zeros((self.batch, cap, 6), dtype=wp.float32, device=self.wp_device)
        self._grip_capacity = cap
        self._graphs = {}

    def load(self, materials) -> None:
        """Reset every run to the initial state with its own material constants."""
        B = self.batch
        table = np.zeros((B, N_MAT), np.float32)
        table[:, M_MU] = materials.mu
        table[:, M_LAM] = materials.lam
        table[:, M_KF] = materials.kf
        table[:, M_MASS] = materials.rho * self.scene.volume
        table[:, M_SC0:M_SC1 + 1] = materials.sigma_c
        table[:, M_ETA0:M_ETA1 + 1] = materials.eta
        table[:, M_RES0:M_RES1 + 1] = materials.residual
        table[:, M_GATE] = 1.0
        self._table = table
        self.mat.assign(table)
        self.work.zero_()
        self.x.assign(self._x_init)
        self.v.zero_()
        self.C.zero_()
        self.F.assign(self._F_init)
        self.d.zero_()
        self.dtil.zero_()

    def set_damage_gate(self, on: bool) -> None:
        """Let damage evolve (``on``) or freeze it (settling) for every run of the batch."""
        self._table[:, M_GATE] = 1.0 if on else 0.0
        self.mat.assign(self._table)

    def set_frame(self, dt: np.ndarray, nsub: np.ndarray, grip: np.ndarray) -> None:
        """Per-run dt (B,), substep counts (B,) and gripper table (B, K, 6) for the next frame."""
        self.dt.assign(np.ascontiguousarray(dt, dtype=np.float32))
        self.nsub.assign(np.ascontiguousarray(nsub, dtype=np.int32))
        K = grip.shape[1]
        self._reserve_grip(K)
        table = np.zeros((self.batch, self._grip_capacity, 6), np.float32)
        table[:, :K] = grip
        self.grip.assign(table)

    # -- stepping -----------------------------------------------------------------------------
    def _clear(self) -> None:
        self.gv.zero_()
        self.gm.zero_()
        self.gd.zero_()
        self.gg.zero_()

    def _p2g(self) -> None:
        s = self.settings
        wp.launch(self._p2g_kernel, dim=(self.batch, self.scene.n_particles), device=self.wp_device, inputs=[
            self.kstep, float(self.scene.dx), float(self.scene.volume), float(s.apic_blend), self.nsub, self.dt,
            self.mat, self.label, self.fibre, self.gripped, self.x, self.v, self.C, self.F, self.d, self.dtil,
            self.gv, self.gm, self.gd, self.gg])

    def _grid(self) -> None:
        s, G = self.settings, self.scene.preset.grid
        wp.launch(grid_update_kernel, dim=(self.batch, G, G, G), device=self.wp_device, inputs=[
            self.kstep, float(s.gravity), int(s.boundary_cells), self.nsub, self.dt, self.grip, self.held,
            self.gv, self.gm, self.gg, self.work])

    def _g2p(self) -> None:
        s = self.settings
        wp.launch(g2p_kernel, dim=(self.batch, self.scene.n_particles), device=self.wp_device, inputs=[
            self.kstep, float(self.scene.dx), float(s.l0_cells) ** 2, int(s.damage_on), self.nsub, self.dt,
            self.mat, self.label, self.gripped, self.x0, self.grip, self.x, self.v, self.C, self.F, self.d,
            self.dtil, self.gv, self.gd])

    def _substep(self) -> None:
        """Launch one substep (reads the substep index from ``kstep`` and increments it)."""
        self._clear()
        self._p2g()
        self._grid()
        self._g2p()
        wp.launch(next_substep_kernel, dim=1, device=self.wp_device, inputs=[self.kstep])

    def _graph(self, n: int):
        """The captured CUDA graph of ``n`` substeps (captured on first use)."""
        if n not in self._graphs:
            # load the module outside the capture (compilation cannot be captured)
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

    def kernel_times(self, n_steps: int = 20) -> dict[str, float]:
        """Mean seconds per launch of each substep stage over ``n_steps`` synced substeps (profiling;
        advances the state as substep 0 of the current frame, so call it on a throw-away batch)."""
        import time

        calls = {"clear": self._clear, "p2g": self._p2g, "grid": self._grid, "g2p": self._g2p}
        total = dict.fromkeys(calls, 0.0)
        self.kstep.zero_()
        for _ in range(n_steps):
            for name, call in calls.items():
                wp.synchronize_device(self.wp_device)
                t0 = time.perf_counter()
                call()
                wp.synchronize_device(self.wp_device)
                total[name] += time.perf_counter() - t0
        return {k: v / n_steps for k, v in total.items()}

    # -- read-back ----------------------------------------------------------------------------
    def frame_stats(self, lo: float, hi: float, ref: np.ndarray) -> np.ndarray:
        """(B, N_STATS) statistics of the frame just simulated (columns: :mod:`..failure`); the
        gripper-work accumulator is read and reset."""
        self.stats_out.zero_()
        r = np.asarray(ref, np.float32)
        wp.launch(frame_stats_kernel, dim=(self.batch, self.scene.n_particles), device=self.wp_device,
                  inputs=[float(lo), float(hi), wp.vec3(float(r[0]), float(r[1]), float(r[2])), self.mat,
                          self.label, self.x, self.v, self.F, self.d, self.stats_out])
        out = self.stats_out.numpy().astype(np.float64)
        out[:, STAT_WORK] = self.work.numpy().astype(np.float64)
        self.work.zero_()
        return out

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions (B, N, 3) and damage (B, N), float32."""
        return self.x.numpy(), self.d.numpy()

    def grid_mass(self) -> np.ndarray:
        """(B,) total grid mass deposited by the last P2G (equals the particle mass: a check)."""
        return self.gm.numpy().astype(np.float64).reshape(self.batch, -1).sum(axis=1)

    def sync(self) -> None:
        wp.synchronize_device(self.wp_device)
