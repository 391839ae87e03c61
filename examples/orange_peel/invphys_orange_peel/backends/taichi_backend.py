"""All Taichi kernels of the orange peel (explicit MLS-MPM + anisotropic phase-field damage).

The step algorithm is specified in docs/orange-peel/physics.md; the host-side driver
(:mod:`invphys_orange_peel.driver`) owns time stepping, recording and failure checks and calls
the methods below. Every array is a Taichi ndarray with a leading run index ``b``, so one kernel
launch advances every run of a batch; a run whose substep index ``k`` is past its own ``nsub[b]``
for the current frame is idle.
"""


import threading

import numpy as np
import taichi as ti

from invphys.core.errors import DeviceUnavailableError, InvphysError
from invphys_orange_peel.backends import quiet_library
from invphys_orange_peel.failure import N_STATS, STAT_WORK

_init_lock = threading.Lock()
_initialised_arch: str | None = None


def cuda_available() -> bool:
    """Whether this Taichi build can run on CUDA here (probe without initialising Taichi)."""
    try:
        from taichi._lib import core as _ti_core

        return bool(_ti_core.with_cuda()) and _cuda_device_present()
    except Exception:
        return False


def _cuda_device_present() -> bool:
    import ctypes

    try:
        lib = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    if lib.cuInit(0) != 0:
        return False
    count = ctypes.c_int(0)
    return lib.cuDeviceGetCount(ctypes.byref(count)) == 0 and count.value > 0


def ensure_taichi(arch: str, allow_cpu_fallback: bool = False) -> str:
    """Initialise Taichi once per process on ``arch`` ("cpu", "cuda" or "auto"); return the arch used.

    Asking again for the arch in use is free; asking for another one raises, since Taichi cannot
    switch devices in a live process. CUDA without a GPU raises :class:`DeviceUnavailableError`
    unless ``allow_cpu_fallback``.
    """
    global _initialised_arch
    with _init_lock:
        want = arch
        if arch in ("cuda", "auto"):
            if cuda_available():
                want = "cuda"
            elif arch == "cuda" and not allow_cpu_fallback:
                raise DeviceUnavailableError(
                    "arch='cuda' was requested but no CUDA GPU is available to Taichi here; "
                    "use arch='cpu' or 'auto', or set allow_cpu_fallback=true")
            else:
                want = "cpu"
        if _initialised_arch is not None:
            if want != _initialised_arch:
                raise InvphysError(
                    f"Taichi is already initialised on {_initialised_arch!r} in this process and cannot "
                    f"switch to {want!r}; use one arch per process")
            return want
        with quiet_library():  # Taichi's start-up lines: hidden unless INVPHYS_DEBUG=1
            ti.init(arch=ti.cuda if want == "cuda" else ti.cpu, default_fp=ti.f32, random_seed=0,
                    offline_cache=True, log_level=ti.WARN)
        _initialised_arch = want
        return want


def device_name(arch: str) -> str:
    if arch == "cuda":
        try:
            import ctypes

            lib = ctypes.CDLL("libcuda.so.1")
            buf = ctypes.create_string_buffer(256)
            dev = ctypes.c_int(0)
            lib.cuDeviceGet(ctypes.byref(dev), 0)
            lib.cuDeviceGetName(buf, 256, dev)
            return "cuda:" + buf.value.decode()
        except Exception:
            return "cuda"
    import os
    import platform

    return f"cpu:{platform.processor() or platform.machine()}x{os.cpu_count()}"


vec2 = ti.math.vec2
vec3 = ti.math.vec3
mat3 = ti.math.mat3
ND = ti.types.ndarray

# per-run material table columns (float32): see TaichiBackend.load
M_MU, M_LAM, M_KF, M_MASS, M_SC0, M_SC1, M_ETA0, M_ETA1, M_RES0, M_RES1, M_GATE = range(11)
N_MAT = 11


@ti.func
def _weights(fx):
    w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
    return w


def _build_kernels(serial_p2g: bool):
    """Compile-time configured kernels (``serial_p2g`` makes CPU scatter order deterministic)."""

    @ti.kernel
    def clear_grid(k: ti.i32, nsub: ND(ti.i32, 1), gv: ND(vec3, 4), gm: ND(ti.f32, 4),
                   gd: ND(vec2, 4), gg: ND(ti.f32, 4)):
        for b, i, j, q in gm:
            if k < nsub[b]:
                gv[b, i, j, q] = vec3(0.0)
                gm[b, i, j, q] = 0.0
                gd[b, i, j, q] = vec2(0.0)
                gg[b, i, j, q] = 0.0

    @ti.kernel
    def p2g(k: ti.i32, dx: ti.f32, vol: ti.f32, apic: ti.f32, nsub: ND(ti.i32, 1), dt: ND(ti.f32, 1),
            mat: ND(ti.f32, 2), label: ND(ti.i32, 1), fibre: ND(vec3, 1), gripped: ND(ti.i32, 1),
            x: ND(vec3, 2), v: ND(vec3, 2), C: ND(mat3, 2), F: ND(mat3, 2), d: ND(ti.f32, 2),
            dtil: ND(ti.f32, 2), gv: ND(vec3, 4), gm: ND(ti.f32, 4), gd: ND(vec2, 4), gg: ND(ti.f32, 4)):
        inv_dx = 1.0 / dx
        G = gm.shape[1]
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)
        for b, p in ti.ndrange(x.shape[0], x.shape[1]):
            if k < nsub[b]:
                h = dt[b]
                Xp = x[b, p] * inv_dx
                base = ti.math.clamp(ti.cast(Xp - 0.5, ti.i32), 0, G - 3)
                fx = Xp - ti.cast(base, ti.f32)
                w = _weights(fx)
                Fp = F[b, p]
                U, sig, V = ti.svd(Fp)
                J = sig[0, 0] * sig[1, 1] * sig[2, 2]
                reg = label[p]
                dp = d[b, p]
                mu = mat[b, M_MU]
                lam = mat[b, M_LAM]
                res = mat[b, M_RES0 + reg]
                g = (1.0 - dp) * (1.0 - dp) * (1.0 - res) + res
                gvol = g if J >= 1.0 else 1.0
                tau_d = vec3(0.0)
                s_pos = vec3(0.0)
                for a in ti.static(range(3)):
                    dev = 2.0 * mu * (sig[a, a] - 1.0) * sig[a, a]
                    vol_t = lam * (J - 1.0) * J
                    tau_d[a] = g * dev + gvol * vol_t
                    if J > J_MIN:  # an inverted or collapsed particle has no tensile driving force
                        s_pos[a] = ti.max((dev + vol_t) / J, 0.0)
                tau = U @ ti.Matrix([[tau_d[0], 0.0, 0.0], [0.0, tau_d[1], 0.0], [0.0, 0.0, tau_d[2]]]) \
                    @ U.transpose()
                sigp = U @ ti.Matrix([[s_pos[0], 0.0, 0.0], [0.0, s_pos[1], 0.0], [0.0, 0.0, s_pos[2]]]) \
                    @ U.transpose()
                A = ti.Matrix.identity(ti.f32, 3)
                if reg == 0:
                    a0 = fibre[p]
                    fa = Fp @ a0
                    lf = fa.norm()
                    if lf > 1e-6:
                        tau += mat[b, M_KF] * (lf - 1.0) / lf * fa.outer_product(fa)
                    ra = (U @ V.transpose()) @ a0
                    A -= ra.outer_product(ra)
                M = A @ sigp
                sc = mat[b, M_SC0 + reg]
                phi = (M * M.transpose()).sum() / (sc * sc)
                dtil[b, p] = ti.max(phi - 1.0, 0.0)
                mass = mat[b, M_MASS]
                affine = (-h * vol * 4.0 * inv_dx * inv_dx) * tau + (mass * apic) * C[b, p]
                vp = v[b, p]
                gp = gripped[p]
                for i, j, q in ti.static(ti.ndrange(3, 3, 3)):
                    off = ti.Vector([i, j, q])
                    dpos = (ti.cast(off, ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[q][2]
                    node = base + off
                    gv[b, node[0], node[1], node[2]] += weight * (mass * vp + affine @ dpos)
                    gm[b, node[0], node[1], node[2]] += weight * mass
                    gd[b, node[0], node[1], node[2]] += weight * vec2(dp, 1.0)
                    if gp != 0:
                        gg[b, node[0], node[1], node[2]] += weight * mass

    @ti.kernel
    def grid_update(k: ti.i32, gravity: ti.f32, bc: ti.i32, nsub: ND(ti.i32, 1), dt: ND(ti.f32, 1),
                    grip: ND(ti.f32, 3), held: ND(ti.i32, 3), gv: ND(vec3, 4), gm: ND(ti.f32, 4),
                    gg: ND(ti.f32, 4), work: ND(ti.f32, 1)):
        G = gm.shape[1]
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)  # the work sum, like the scatter, in a fixed order
        for b, i, j, q in ti.ndrange(gm.shape[0], G, gm.shape[2], gm.shape[3]):  # a range-for: serialize applies
            m = gm[b, i, j, q]
            if k < nsub[b] and m > 0.0:
                vel = gv[b, i, j, q] / m
                vel[1] += dt[b] * gravity
                if gg[b, i, j, q] > 0.5 * m:
                    vg = vec3(grip[b, k, 3], grip[b, k, 4], grip[b, k, 5])
                    # the gripper's impulse on this node, dotted with its velocity: work this substep
                    work[b] += m * (vg - vel).dot(vg)
                    vel = vg
                if held[i, j, q] != 0:
                    vel = vec3(0.0)
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

    @ti.kernel
    def g2p(k: ti.i32, dx: ti.f32, l0sq: ti.f32, damage_on: ti.i32, nsub: ND(ti.i32, 1), dt: ND(ti.f32, 1),
            mat: ND(ti.f32, 2), label: ND(ti.i32, 1), gripped: ND(ti.i32, 1), x0: ND(vec3, 1),
            grip: ND(ti.f32, 3), x: ND(vec3, 2), v: ND(vec3, 2), C: ND(mat3, 2), F: ND(mat3, 2),
            d: ND(ti.f32, 2), dtil: ND(ti.f32, 2), gv: ND(vec3, 4), gd: ND(vec2, 4)):
        inv_dx = 1.0 / dx
        G = gv.shape[1]
        for b, p in x:
            if k < nsub[b]:
                h = dt[b]
                Xp = x[b, p] * inv_dx
                base = ti.math.clamp(ti.cast(Xp - 0.5, ti.i32), 0, G - 3)
                fx = Xp - ti.cast(base, ti.f32)
                w = _weights(fx)
                hs = [1.0, -2.0, 1.0]
                dp = d[b, p]
                new_v = vec3(0.0)
                new_C = mat3(0.0)
                lap = 0.0
                for i, j, q in ti.static(ti.ndrange(3, 3, 3)):
                    off = ti.Vector([i, j, q])
                    weight = w[i][0] * w[j][1] * w[q][2]
                    node = base + off
                    gvel = gv[b, node[0], node[1], node[2]]
                    new_v += weight * gvel
                    new_C += (4.0 * inv_dx * weight) * gvel.outer_product(ti.cast(off, ti.f32) - fx)
                    g2 = gd[b, node[0], node[1], node[2]]
                    if g2[1] > 0.0:
                        hess = hs[i] * w[j][1] * w[q][2] + w[i][0] * hs[j] * w[q][2] \
                            + w[i][0] * w[j][1] * hs[q]
                        lap += (g2[0] / g2[1] - dp) * hess
                if damage_on != 0 and mat[b, M_GATE] > 0.5:
                    reg = label[p]
                    Dc = dp - l0sq * lap
                    rate = (1.0 - dp) * dtil[b, p] - Dc
                    d[b, p] = ti.min(1.0, dp + h / mat[b, M_ETA0 + reg] * ti.max(rate, 0.0))
                F[b, p] = (ti.Matrix.identity(ti.f32, 3) + h * new_C) @ F[b, p]
                C[b, p] = new_C
                if gripped[p] != 0:
                    x[b, p] = x0[p] + vec3(grip[b, k, 0], grip[b, k, 1], grip[b, k, 2])
                    v[b, p] = vec3(grip[b, k, 3], grip[b, k, 4], grip[b, k, 5])
                else:
                    v[b, p] = new_v
                    x[b, p] += h * new_v

    @ti.kernel
    def frame_stats(lo: ti.f32, hi: ti.f32, ref: vec3, mat: ND(ti.f32, 2), label: ND(ti.i32, 1),
                    x: ND(vec3, 2), v: ND(vec3, 2), F: ND(mat3, 2), d: ND(ti.f32, 2), out: ND(ti.f32, 2)):
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)  # float sums in a fixed order: features repeat bit for bit
        for b, p in ti.ndrange(x.shape[0], x.shape[1]):  # a range-for: serialize applies
            xp = x[b, p]
            vp = v[b, p]
            dp = d[b, p]
            s = vp.norm()
            bad = 0
            if not (s < 1e20) or not (ti.abs(xp).max() < 1e20) or not (ti.abs(F[b, p]).max() < 1e20) \
                    or not (ti.abs(dp) < 1e20):
                bad = 1
            if bad != 0:
                ti.atomic_add(out[b, 2], 1.0)
            else:
                ti.atomic_max(out[b, 0], s)
                ti.atomic_add(out[b, 1], 0.5 * mat[b, M_MASS] * s * s)
                if xp.min() < lo or xp.max() > hi:
                    ti.atomic_add(out[b, 3], 1.0)
                rel = xp - ref
                col = 4 + 3 * label[p]
                for a in ti.static(range(3)):
                    ti.atomic_add(out[b, col + a], rel[a])
                ti.atomic_add(out[b, 10], dp)

    return clear_grid, p2g, grid_update, g2p, frame_stats


_KERNELS: dict[bool, tuple] = {}
#: below this volume ratio a particle is treated as inverted: no tensile driving force (audit item 7)
J_MIN = 1e-6


class TaichiBackend:
    """Batched AnisoMPM state and kernels on one Taichi arch.

    ``settings`` is the driver's :class:`~invphys_orange_peel.driver.StepSettings`.
    """

    name = "taichi"

    def __init__(self, scene, batch: int, settings, arch: str = "cpu", allow_cpu_fallback: bool = False):
        self.arch = ensure_taichi(arch, allow_cpu_fallback)
        self.device = device_name(self.arch)
        self.scene = scene
        self.settings = settings
        self.batch = int(batch)
        serial = bool(settings.deterministic and self.arch == "cpu")
        if serial not in _KERNELS:
            _KERNELS[serial] = _build_kernels(serial)
        (self._clear, self._p2g, self._grid, self._g2p, self._stats) = _KERNELS[serial]
        B, N, G = self.batch, scene.n_particles, scene.preset.grid
        self.x = ti.ndarray(vec3, (B, N))
        self.v = ti.ndarray(vec3, (B, N))
        self.C = ti.ndarray(mat3, (B, N))
        self.F = ti.ndarray(mat3, (B, N))
        self.d = ti.ndarray(ti.f32, (B, N))
        self.dtil = ti.ndarray(ti.f32, (B, N))
        self.gv = ti.ndarray(vec3, (B, G, G, G))
        self.gm = ti.ndarray(ti.f32, (B, G, G, G))
        self.gd = ti.ndarray(vec2, (B, G, G, G))
        self.gg = ti.ndarray(ti.f32, (B, G, G, G))
        self.mat = ti.ndarray(ti.f32, (B, N_MAT))
        self.nsub = ti.ndarray(ti.i32, (B,))
        self.dt = ti.ndarray(ti.f32, (B,))
        self.grip = ti.ndarray(ti.f32, (B, 1, 6))
        self.stats_out = ti.ndarray(ti.f32, (B, N_STATS))
        self.work = ti.ndarray(ti.f32, (B,))
        self.label = ti.ndarray(ti.i32, (N,))
        self.label.from_numpy(scene.labels.astype(np.int32))
        self.fibre = ti.ndarray(vec3, (N,))
        self.fibre.from_numpy(scene.fibres.astype(np.float32))
        self.gripped = ti.ndarray(ti.i32, (N,))
        self.gripped.from_numpy((scene.gripped & settings.gripper_on).astype(np.int32))
        self.x0 = ti.ndarray(vec3, (N,))
        self.x0.from_numpy(scene.positions.astype(np.float32))
        self.held = ti.ndarray(ti.i32, (G, G, G))
        self.held.from_numpy(scene.held_node_mask().astype(np.int32))

    def load(self, materials) -> None:
        """Reset every run to the initial state with its own material constants."""
        B, N = self.batch, self.scene.n_particles
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
        self.mat.from_numpy(table)
        self.work.fill(0.0)
        self.x.from_numpy(np.broadcast_to(self.scene.positions.astype(np.float32), (B, N, 3)).copy())
        zeros3 = np.zeros((B, N, 3), np.float32)
        self.v.from_numpy(zeros3)
        self.C.from_numpy(np.zeros((B, N, 3, 3), np.float32))
        self.F.from_numpy(np.broadcast_to(np.eye(3, dtype=np.float32), (B, N, 3, 3)).copy())
        self.d.from_numpy(np.zeros((B, N), np.float32))
        self.dtil.from_numpy(np.zeros((B, N), np.float32))

    def set_damage_gate(self, on: bool) -> None:
        """Let damage evolve (``on``) or freeze it (settling) for every run of the batch."""
        self._table[:, M_GATE] = 1.0 if on else 0.0
        self.mat.from_numpy(self._table)

    def set_frame(self, dt: np.ndarray, nsub: np.ndarray, grip: np.ndarray) -> None:
        """Per-run dt (B,), substep counts (B,) and gripper table (B, K, 6) for the next frame."""
        self.dt.from_numpy(dt.astype(np.float32))
        self.nsub.from_numpy(nsub.astype(np.int32))
        if self.grip.shape != grip.shape:
            self.grip = ti.ndarray(ti.f32, grip.shape)
        self.grip.from_numpy(grip.astype(np.float32))

    def advance(self, n_steps: int) -> None:
        """Run substeps 0..n_steps-1 of the current frame (runs past their own nsub idle)."""
        s = self.settings
        dx = float(self.scene.dx)
        vol = float(self.scene.volume)
        for k in range(n_steps):
            self._clear(k, self.nsub, self.gv, self.gm, self.gd, self.gg)
            self._p2g(k, dx, vol, s.apic_blend, self.nsub, self.dt, self.mat, self.label, self.fibre,
                      self.gripped, self.x, self.v, self.C, self.F, self.d, self.dtil,
                      self.gv, self.gm, self.gd, self.gg)
            self._grid(k, s.gravity, s.boundary_cells, self.nsub, self.dt, self.grip, self.held,
                       self.gv, self.gm, self.gg, self.work)
            self._g2p(k, dx, s.l0_cells ** 2, int(s.damage_on), self.nsub, self.dt, self.mat, self.label,
                      self.gripped, self.x0, self.grip, self.x, self.v, self.C, self.F, self.d, self.dtil,
                      self.gv, self.gd)

    def kernel_times(self, n_steps: int = 20) -> dict[str, float]:
        """Mean seconds per launch of each substep kernel over ``n_steps`` synced substeps (profiling;
        advances the state, so call it on a throw-away batch)."""
        import time

        s = self.settings
        dx, vol = float(self.scene.dx), float(self.scene.volume)
        calls = {
            "clear": lambda k: self._clear(k, self.nsub, self.gv, self.gm, self.gd, self.gg),
            "p2g": lambda k: self._p2g(k, dx, vol, s.apic_blend, self.nsub, self.dt, self.mat, self.label,
                                       self.fibre, self.gripped, self.x, self.v, self.C, self.F, self.d,
                                       self.dtil, self.gv, self.gm, self.gd, self.gg),
            "grid": lambda k: self._grid(k, s.gravity, s.boundary_cells, self.nsub, self.dt, self.grip,
                                         self.held, self.gv, self.gm, self.gg, self.work),
            "g2p": lambda k: self._g2p(k, dx, s.l0_cells ** 2, int(s.damage_on), self.nsub, self.dt, self.mat,
                                       self.label, self.gripped, self.x0, self.grip, self.x, self.v, self.C,
                                       self.F, self.d, self.dtil, self.gv, self.gd),
        }
        total = dict.fromkeys(calls, 0.0)
        for _ in range(n_steps):
            for name, call in calls.items():
                ti.sync()
                t0 = time.perf_counter()
                call(0)
                ti.sync()
                total[name] += time.perf_counter() - t0
        return {k: v / n_steps for k, v in total.items()}

    def frame_stats(self, lo: float, hi: float, ref: np.ndarray) -> np.ndarray:
        """(B, N_STATS) statistics of the frame just simulated (columns: :mod:`..failure`); the
        gripper-work accumulator is read and reset."""
        self.stats_out.fill(0.0)
        r = np.asarray(ref, np.float32)
        self._stats(lo, hi, vec3(float(r[0]), float(r[1]), float(r[2])), self.mat, self.label, self.x, self.v,
                    self.F, self.d, self.stats_out)
        out = self.stats_out.to_numpy().astype(np.float64)
        out[:, STAT_WORK] = self.work.to_numpy().astype(np.float64)
        self.work.fill(0.0)
        return out

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions (B, N, 3) and damage (B, N), float32."""
        return self.x.to_numpy(), self.d.to_numpy()

    def grid_mass(self) -> np.ndarray:
        """(B,) total grid mass deposited by the last P2G (equals the particle mass: a check)."""
        return self.gm.to_numpy().astype(np.float64).reshape(self.batch, -1).sum(axis=1)

    def sync(self) -> None:
        ti.sync()
