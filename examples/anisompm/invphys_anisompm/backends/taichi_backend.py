"""Taichi kernels of the engine: batched explicit MLS-MPM with anisotropic phase-field damage.

The step (``docs/anisompm.md``): P2G with the degraded fixed-corotated + fibre stress and the crack
driving force; a grid update with gravity, grips, colliders (grid hooks), held nodes and walls; G2P with
the damage Laplacian and the damage update. Every array carries a leading run index ``b``: one launch
advances a whole batch; a run whose substep index ``k`` is past its own ``nsub[b]`` idles.
"""


import contextlib
import importlib.util
import threading

import numpy as np
import taichi as ti

from invphys.core.errors import DeviceUnavailableError, InvphysError
from invphys_anisompm.backends import quiet_library
from invphys_anisompm.backends.particle_order import ORDERS
from invphys_anisompm.backends.taichi_common import _element_type, load_mat3, matrix_nd, store_mat3
from invphys_anisompm.backends.taichi_host_copy import HostCopy, HostUpload, LaterCopies
from invphys_anisompm.failure import BODY0, n_stats
from invphys_anisompm.materials import M_ALPHA, M_DMG, M_ETA, M_KF, M_LAM, M_MU, M_RES, M_RHO, M_SC, N_MAT

_init_lock = threading.Lock()
_initialised_arch: str | None = None
#: below this volume ratio a particle is treated as inverted: no tensile driving force
J_MIN = 1e-6
#: tiled P2G (CUDA): particles per thread block and the most nodes a tile sums in shared memory
TILE = 256
TILE_NODES = 1024
#: the bit pattern of float +infinity: a tile bound at or above it is not finite
F32_INF_BITS = 0x7F800000
#: 1.5 * 2**23 and its bit pattern: adding it to |x| <= 2**22 rounds x to an integer (``_round_to_int``)
ROUND_MAGIC = 12582912.0
ROUND_MAGIC_BITS = 0x4B400000
#: the tiled scatter's fixed-point unit of a B-spline weight (2**-23): a share (<= 0.75**3) stays below 2**22
#: (``_round_to_int``) and a node's sum of TILE shares below ``256 * 0.42 * 2**23 < 2**31``
WEIGHT_SCALE = 8388608.0
#: the tiled scatter's shared sums per node, all fixed-point integers: momentum (3 channels, the tile's momentum
#: scale), mass (mass scale), the weight sum and the damage sum ``w d`` (``WEIGHT_SCALE``: ``d`` in [0, 1]; a tile
#: with a damage outside scatters globally) and the grip mass (mass scale)
ACC_CHANNELS = 7
#: the particle matrices: on CUDA stored component-major, ``(B, 9, N)`` (entry ``3 i + j`` of particle ``p`` at
#: ``[b, 3 i + j, p]``), so that a warp's threads read and write consecutive words of each entry; as ``(B, N)``
#: arrays of 3x3 matrices (36 bytes apart, the CPU's layout) every store of one entry by a warp touches 32
#: sectors of the L2 for 128 bytes (g2p writes F and C every substep). The CPU keeps its layout: the same
#: arithmetic compiles differently with it, so its results would change at float rounding.
#: ``TaichiBackend.particle_array`` returns either as ``(B, N, 3, 3)``.
MATRIX_STATE = ("C", "F")
#: each run's two boxes of grid nodes (``TaichiBackend.box``): the last scatter's, which the next clear zeroes,
#: and the one the scatter under way grows; g2p moves the second into the first. The clear and the grid update
#: read only the nodes of their box: most of a run's grid is empty
BOX_LAST, BOX_NEXT = 0, 1
#: substeps between re-sorts of each run's particles (tiled scatter; ``TaichiBackend``'s ``resort_every``)
RESORT_EVERY = 128
#: the fused substep's (``TaichiBackend``'s ``fused``) node boxes per run: substep ``k`` scatters into grid
#: buffer ``k & 1`` and grows box slot ``k % FUSED_SLOTS``; the grid kernel of ``k`` zeroes the other buffer within
#: slot ``(k - 1) % FUSED_SLOTS``, and the fused kernel of ``k + 1`` empties that slot (no kernel reads it then)
#: before substep ``k + 2`` grows it again. Two slots would leave no kernel to empty a box nobody reads.
FUSED_SLOTS = 3


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


def cuda_available() -> bool:
    """Whether this Taichi build can run on CUDA here (probe without initialising Taichi)."""
    try:
        from taichi._lib import core as _ti_core

        return bool(_ti_core.with_cuda()) and _cuda_device_present()
    except Exception:
        return False


def ensure_taichi(arch: str, allow_cpu_fallback: bool = False) -> str:
    """Initialise Taichi once per process on ``arch`` ("cpu", "cuda" or "auto"); return the arch used."""
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
        if _initialised_arch is None:
            with contextlib.suppress(Exception):
                from taichi.lang import impl

                if impl.get_runtime().prog is not None:  # initialised by someone else in this process
                    cur = impl.current_cfg().arch
                    _initialised_arch = "cuda" if cur == ti.cuda else "cpu"
        if _initialised_arch is not None:
            if want != _initialised_arch:
                raise InvphysError(f"Taichi is already initialised on {_initialised_arch!r} in this process "
                                   f"and cannot switch to {want!r}; use one arch per process")
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


@ti.func
def _weights(fx):
    return [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]


@ti.func
def _collider_normal(kind: ti.i32, a: vec3, bb: vec3, p: vec3):
    """(inside, outward unit normal) of point ``p`` for a collider shape in its own frame."""
    inside = 0
    n = vec3(0.0, 1.0, 0.0)
    if kind == 0:  # half-space: a = point, bb = unit normal; inside where (p - a) . n <= 0
        if (p - a).dot(bb) <= 0.0:
            inside = 1
            n = bb
    elif kind == 1:  # box: a = lo, bb = hi; normal along the axis of least penetration
        c = 0.5 * (a + bb)
        e = 0.5 * (bb - a)
        r = p - c
        q = ti.abs(r) - e
        if q[0] <= 0.0 and q[1] <= 0.0 and q[2] <= 0.0:
            inside = 1
            if q[0] >= q[1] and q[0] >= q[2]:
                n = vec3(1.0 if r[0] >= 0.0 else -1.0, 0.0, 0.0)
            elif q[1] >= q[2]:
                n = vec3(0.0, 1.0 if r[1] >= 0.0 else -1.0, 0.0)
            else:
                n = vec3(0.0, 0.0, 1.0 if r[2] >= 0.0 else -1.0)
    else:  # cylinder: a = centre, bb = (radius, axis, half_length)
        ax = ti.cast(bb[1] + 0.5, ti.i32)
        e = vec3(1.0 if ax == 0 else 0.0, 1.0 if ax == 1 else 0.0, 1.0 if ax == 2 else 0.0)
        r = p - a
        along = r.dot(e)
        rad = r - along * e
        dist = rad.norm()
        if dist <= bb[0] and ti.abs(along) <= bb[2]:
            inside = 1
            if dist > 1e-9:
                n = rad / dist
    return inside, n


P2GTerms = ti.types.struct(affine=mat3, mv=vec3, mass=ti.f32)
StressTerms = ti.types.struct(tau=mat3, dtil=ti.f32, reg=ti.i32)
#: one particle's state as g2p leaves it and the scatter reads it
ParticleState = ti.types.struct(x=vec3, v=vec3, C=mat3, F=mat3, d=ti.f32)


@ti.func
def _load_state(b, p, x: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(), d: ti.template()):
    """Particle ``p`` of run ``b``'s state from the particle arrays."""
    return ParticleState(x=x[b, p], v=v[b, p], C=load_mat3(C, b, p), F=load_mat3(F, b, p), d=d[b, p])


@ti.func
def _stress_terms(b, s, Fp, dp, mat: ti.template(), body: ti.template(), fibre: ti.template()) -> StressTerms:
    """A particle of run ``b`` with deformation gradient ``Fp`` and damage ``dp`` (scene particle ``s``, whose
    constants ``body`` and ``fibre`` it reads): its Kirchhoff stress (degraded fixed-corotated + fibre) and its
    crack driving force ``dtil``."""
    U, sig, V = ti.svd(Fp)
    J = sig[0, 0] * sig[1, 1] * sig[2, 2]
    reg = body[s]
    mu = mat[b, reg, M_MU]
    lam = mat[b, reg, M_LAM]
    res = mat[b, reg, M_RES]
    g = (1.0 - dp) * (1.0 - dp) * (1.0 - res) + res
    gvol = g if J >= 1.0 else 1.0
    tau_d = vec3(0.0)
    s_pos = vec3(0.0)
    vol_t = lam * (J - 1.0) * J
    for a in ti.static(range(3)):
        dev = 2.0 * mu * (sig[a, a] - 1.0) * sig[a, a]
        tau_d[a] = g * dev + gvol * vol_t
        if J > J_MIN:  # an inverted or collapsed particle has no tensile driving force
            s_pos[a] = ti.max((dev + vol_t) / J, 0.0)
    tau = U @ ti.Matrix([[tau_d[0], 0.0, 0.0], [0.0, tau_d[1], 0.0], [0.0, 0.0, tau_d[2]]]) @ U.transpose()
    sigp = U @ ti.Matrix([[s_pos[0], 0.0, 0.0], [0.0, s_pos[1], 0.0], [0.0, 0.0, s_pos[2]]]) @ U.transpose()
    A = ti.Matrix.identity(ti.f32, 3)
    a0 = fibre[s]
    if a0.norm_sqr() > 0.0:
        kf = mat[b, reg, M_KF]
        if kf > 0.0:
            fa = Fp @ a0
            lf = fa.norm()
            if lf > 1e-6:
                tau += kf * (lf - 1.0) / lf * fa.outer_product(fa)
        ra = (U @ V.transpose()) @ a0
        A += mat[b, reg, M_ALPHA] * ra.outer_product(ra)
    M = A @ sigp
    sc = mat[b, reg, M_SC]
    phi = (M * M.transpose()).sum() / (sc * sc)
    return StressTerms(tau=tau, dtil=ti.max(phi - 1.0, 0.0), reg=reg)


@ti.func
def _p2g_terms(b, p, s, h, inv_dx, apic, mat: ti.template(), body: ti.template(), fibre: ti.template(),
               vol: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(), d: ti.template(),
               dtil: ti.template()) -> P2GTerms:
    """Particle ``p`` of run ``b`` (scene particle ``s``, whose constants ``body``, ``fibre``, ``vol`` it
    reads): its APIC affine matrix (stress included), momentum and mass, as both scatters add them to its
    27 nodes; writes its crack driving force ``dtil``."""
    sd = _stress_terms(b, s, load_mat3(F, b, p), d[b, p], mat, body, fibre)
    dtil[b, p] = sd.dtil
    vp_ = vol[s]
    mass = mat[b, sd.reg, M_RHO] * vp_
    affine = (-h * vp_ * 4.0 * inv_dx * inv_dx) * sd.tau + (mass * apic) * load_mat3(C, b, p)
    return P2GTerms(affine=affine, mv=mass * v[b, p], mass=mass)


@ti.func
def _p2g_terms_of(b, p, s, h, inv_dx, apic, st, mat: ti.template(), body: ti.template(), fibre: ti.template(),
                  vol: ti.template(), dtil: ti.template()) -> P2GTerms:
    """``_p2g_terms`` of a particle in state ``st`` (``ParticleState``: the fused substep's g2p result)."""
    sd = _stress_terms(b, s, st.F, st.d, mat, body, fibre)
    dtil[b, p] = sd.dtil
    vp_ = vol[s]
    mass = mat[b, sd.reg, M_RHO] * vp_
    affine = (-h * vp_ * 4.0 * inv_dx * inv_dx) * sd.tau + (mass * apic) * st.C
    return P2GTerms(affine=affine, mv=mass * st.v, mass=mass)


@ti.func
def touched_node(g2):
    """Whether a scatter added to a grid node, from its damage sums ``(sum w d, sum w)``.

    Every contribution to any channel of a node carries a B-spline weight ``w``, and ``sum w`` (positive terms)
    is nonzero as soon as one ``w`` is (a NaN sum counts as touched). A node with ``sum w == 0`` holds zeros in
    every channel, so the substep's clear can skip it; a slot that gets a new run is wiped whole
    (``wipe_grid``), in case a blown-up run left a NaN beside a zero weight. (The tiled scatter sums a tile's
    weights in units of ``1 / WEIGHT_SCALE``: a node that a tile reaches only with weights below ~6e-8 gets
    nothing from that tile in any channel, its momentum and mass shares rounding to zero as well.)
    """
    return g2[1] != 0.0


@ti.func
def _momentum_bound_bits(mv, affine, dx):
    """The bit pattern of a bound on every component a particle adds to a node's momentum,
    ``w (mv + affine @ dpos)`` with ``w <= 1`` and ``|dpos| <= 1.5 dx`` per axis. Non-negative floats order as
    their bits do (a NaN above infinity), so a tile's bound is an integer ``atomic_max``."""
    bound = ti.abs(mv) + (1.5 * dx) * (ti.abs(affine) @ vec3(1.0))
    return ti.max(ti.bit_cast(bound[0], ti.i32), ti.bit_cast(bound[1], ti.i32), ti.bit_cast(bound[2], ti.i32))


@ti.func
def _fixed_point_scale(bound_bits):
    """The power of two ``s`` (and ``1/s``) by which a tile's shares become integers that cannot overflow.

    A tile's largest share is below ``2**(e - 126)`` (``e`` the biased exponent of its bound), so with
    ``s = 2**(148 - e)`` every scaled share is below ``2**22`` (as ``_round_to_int`` needs) and a node's
    at most TILE shares of weight <= 0.75**3 sum below ``TILE * 0.42 * 2**22 < 2**31``. Each share is
    rounded to ``1/s``, i.e. to ``2**-22`` of the tile's largest bound.
    """
    e = ti.max(bound_bits >> 23, 24)  # a zero bound (tile at rest) still gives a normal scale
    return ti.bit_cast((275 - e) << 23, ti.f32), ti.bit_cast((e - 21) << 23, ti.f32)


@ti.func
def _round_to_int(x):
    """``x`` (``|x| <= 2**22``) rounded to the nearest integer (ties to even), as an int32.

    Adding ``1.5 * 2**23`` puts the sum where a float's last bit is 1, so the add itself rounds ``x`` and
    the integer sits in the sum's low mantissa bits: one add and one integer subtract, where ``ti.round``
    (libdevice ``roundf``, ties away from zero) and the conversion cost ten instructions per value
    (Nsight Compute's SASS of the scatter: ~40 of its ~100 instructions per particle and node).
    """
    return ti.bit_cast(x + ROUND_MAGIC, ti.i32) - ROUND_MAGIC_BITS


@ti.func
def _w1(f, i):
    """The quadratic B-spline weight of node offset ``i`` (0, 1, 2) at fractional position ``f``."""
    return ti.select(i == 0, 0.5 * (1.5 - f) ** 2, ti.select(i == 1, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2))


@ti.func
def _g2p_node(b, base, off, fx, inv_dx, dp, wx, wy, wz, hx, hy, hz, gv: ti.template(), gd: ti.template(),
              new_v: ti.template(), new_C: ti.template(), lap: ti.template()):
    """Add node ``base + off``'s share to a particle's g2p sums: velocity, APIC matrix, damage Laplacian
    (``w*``: the node's B-spline weights per axis, ``h*``: their second-difference factors)."""
    weight = wx * wy * wz
    node = base + off
    gvel = gv[b, node[0], node[1], node[2]]
    new_v += weight * gvel
    new_C += (4.0 * inv_dx * weight) * gvel.outer_product(ti.cast(off, ti.f32) - fx)
    g2 = gd[b, node[0], node[1], node[2]]
    if g2[1] > 0.0:
        hess = hx * wy * wz + wx * hy * wz + wx * wy * hz
        lap += (g2[0] / g2[1] - dp) * hess


@ti.func
def _scatter_global(b, node, weight, mom, mass, dp, gp, ngrip, gv: ti.template(), gm: ti.template(),
                    gd: ti.template(), gg: ti.template()):
    """Add one particle's share ``weight`` (momentum ``mom`` already weighted) to grid node ``node``."""
    gv[b, node[0], node[1], node[2]] += mom
    gm[b, node[0], node[1], node[2]] += weight * mass
    gd[b, node[0], node[1], node[2]] += weight * vec2(dp, 1.0)
    if gp >= 0:
        gg[b * ngrip + gp, node[0], node[1], node[2]] += weight * mass


@ti.func
def _in_box(box: ti.template(), b, w, i, j, q):
    """Whether node ``(i, j, q)`` of run ``b`` lies in the run's node box ``box[b, w]`` (lo xyz, hi xyz)."""
    return box[b, w, 0] <= i <= box[b, w, 3] and box[b, w, 1] <= j <= box[b, w, 4] and box[b, w, 2] <= q <= box[b, w, 5]


@ti.func
def _in_columns(box: ti.template(), b, w, i, q):
    """Whether the column of nodes ``(i, ., q)`` of run ``b`` crosses the run's node box ``box[b, w]``."""
    return box[b, w, 0] <= i <= box[b, w, 3] and box[b, w, 2] <= q <= box[b, w, 5]


@ti.func
def _set_box(box: ti.template(), b, w, lo, hi):
    """Set run ``b``'s node box ``box[b, w]`` to nodes ``lo .. hi`` on every axis (``G, -1``: empty)."""
    for a in ti.static(range(3)):
        box[b, w, a] = lo
        box[b, w, 3 + a] = hi


@ti.func
def _grow_box(box: ti.template(), b, w, lo, hi):
    """Widen run ``b``'s box of the scatter under way (``box[b, w]``: ``BOX_NEXT``, or the fused substep's
    slot) to nodes ``lo .. hi`` (per axis)."""
    for a in ti.static(range(3)):
        ti.atomic_min(box[b, w, a], lo[a])
        ti.atomic_max(box[b, w, 3 + a], hi[a])


@ti.func
def _zero_node(b, i, j, q, ngrip, gv: ti.template(), gm: ti.template(), gd: ti.template(), gg: ti.template()):
    """Zero every channel of grid node ``(i, j, q)`` of run ``b``."""
    gv[b, i, j, q] = vec3(0.0)
    gm[b, i, j, q] = 0.0
    gd[b, i, j, q] = vec2(0.0)
    for g in range(ngrip):
        gg[b * ngrip + g, i, j, q] = 0.0


def _build_grid_kernels(serial_p2g: bool, G: int):
    """The grid's clear and update for grid size ``G`` (a compile-time constant: no integer divisions for a
    node's indices; a closure constant, not a template argument, so that a Taichi graph can hold them);
    ``serial_p2g`` makes the CPU's force and work sums' order deterministic.

    Both visit only the nodes of each run's scatter box (``BOX_*``), with one thread per (run, x, z) column
    walking y: a G-th of the threads of a loop over every node, each of which cost its indices and a read even
    for an empty node (the CPU's serialised update keeps its loop over nodes, and with it the order of its
    sums)."""

    @ti.kernel
    def clear_grid(k: ti.i32, ngrip: ti.i32, nsub: ND(ti.i32, 1), box: ND(ti.i32, 3), gv: ND(vec3, 4),
                   gm: ND(ti.f32, 4), gd: ND(vec2, 4), gg: ND(ti.f32, 4)):
        # only the nodes the last scatter touched (box[b, BOX_LAST]; see touched_node): one read per node
        # of the box instead of 7 writes per node of the grid
        for b, i, q in ti.ndrange(gm.shape[0], G, G):
            if k < nsub[b] and _in_columns(box, b, BOX_LAST, i, q):   # (Taichi's `and` evaluates both sides)
                for j in range(box[b, BOX_LAST, 1], box[b, BOX_LAST, 4] + 1):
                    if touched_node(gd[b, i, j, q]):
                        _zero_node(b, i, j, q, ngrip, gv, gm, gd, gg)

    @ti.func
    def _update_node(b, gb, i, j, q, m, k, dx, gravity, damp: ti.template(), bc, ngrip, ncol, dt: ti.template(),
                     kin: ti.template(), ctype: ti.template(), ca: ti.template(), cb: ti.template(),
                     csurf: ti.template(), fric: ti.template(), held: ti.template(), gv: ti.template(),
                     gg: ti.template(), imp: ti.template(), work: ti.template()):
        """Node (i, j, q) of run b (grid index gb: b, or the fused substep's buffer of it), holding mass m > 0:
        its velocity after gravity, damping, grips, colliders, held nodes and walls; the grips' and
        colliders' impulse and work."""
        vel = gv[gb, i, j, q] / m
        vel[1] += dt[b] * gravity
        vel /= 1.0 + damp[b] * dt[b]
        for g in range(ngrip):
            if gg[gb * ngrip + g, i, j, q] > 0.5 * m:
                vk = vec3(kin[b, k, g, 3], kin[b, k, g, 4], kin[b, k, g, 5])
                imp[b, g] += m * (vel - vk)
                work[b, g] += m * (vk - vel).dot(vk)
                vel = vk
        pos = vec3(ti.cast(i, ti.f32), ti.cast(j, ti.f32), ti.cast(q, ti.f32)) * dx
        for c in range(ncol):
            kc = ngrip + c
            disp = vec3(kin[b, k, kc, 0], kin[b, k, kc, 1], kin[b, k, kc, 2])
            vc = vec3(kin[b, k, kc, 3], kin[b, k, kc, 4], kin[b, k, kc, 5])
            inside, n = _collider_normal(ctype[c], ca[c], cb[c], pos - disp)
            if inside != 0:
                old = vel
                rel = vel - vc
                if csurf[c] == 0:
                    rel = vec3(0.0)
                else:
                    vn = rel.dot(n)
                    if csurf[c] == 1 or vn < 0.0:
                        rel_t = rel - vn * n
                        if vn < 0.0:
                            lt = rel_t.norm()
                            if lt > 1e-12:
                                rel_t *= ti.max(0.0, 1.0 + fric[b, c] * vn / lt)
                        rel = rel_t
                vel = vc + rel
                imp[b, kc] += m * (old - vel)
                work[b, kc] += m * (vel - old).dot(vc)
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
        gv[gb, i, j, q] = vel

    @ti.kernel
    def grid_update(k: ti.i32, dx: ti.f32, gravity: ti.f32, damp: ND(ti.f32, 1), bc: ti.i32, ngrip: ti.i32, ncol: ti.i32,
                    nsub: ND(ti.i32, 1), dt: ND(ti.f32, 1), kin: ND(ti.f32, 4), ctype: ND(ti.i32, 1),
                    ca: ND(vec3, 1), cb: ND(vec3, 1), csurf: ND(ti.i32, 1), fric: ND(ti.f32, 2),
                    held: ND(ti.i32, 3), box: ND(ti.i32, 3), gv: ND(vec3, 4), gm: ND(ti.f32, 4), gg: ND(ti.f32, 4),
                    imp: ND(vec3, 2), work: ND(ti.f32, 2)):
        # only the nodes of this substep's scatter box (box[b, BOX_NEXT]): outside it no node holds mass
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)  # the force and work sums, like the scatter, in a fixed order
            for b, i, j, q in ti.ndrange(gm.shape[0], G, G, G):  # a range-for: serialize applies
                if k < nsub[b] and _in_box(box, b, BOX_NEXT, i, j, q):
                    m = gm[b, i, j, q]
                    if m > 0.0:
                        _update_node(b, b, i, j, q, m, k, dx, gravity, damp, bc, ngrip, ncol, dt, kin, ctype, ca,
                                     cb, csurf, fric, held, gv, gg, imp, work)
        else:
            for b, i, q in ti.ndrange(gm.shape[0], G, G):
                if k < nsub[b] and _in_columns(box, b, BOX_NEXT, i, q):
                    for j in range(box[b, BOX_NEXT, 1], box[b, BOX_NEXT, 4] + 1):
                        m = gm[b, i, j, q]
                        if m > 0.0:
                            _update_node(b, b, i, j, q, m, k, dx, gravity, damp, bc, ngrip, ncol, dt, kin, ctype,
                                         ca, cb, csurf, fric, held, gv, gg, imp, work)

    fused_clear, fused_grid = _build_fused_grid(serial_p2g, G, _update_node)
    return clear_grid, grid_update, fused_clear, fused_grid


@ti.func
def _clear_column(b, gb, w, i, q, ngrip, box: ti.template(), gv: ti.template(), gm: ti.template(), gd: ti.template(),
                  gg: ti.template()):
    """Zero the touched nodes (``touched_node``) of grid run ``gb``'s column ``(i, ., q)`` within run ``b``'s
    node box ``box[b, w]``."""
    for j in range(box[b, w, 1], box[b, w, 4] + 1):
        if touched_node(gd[gb, i, j, q]):
            _zero_node(gb, i, j, q, ngrip, gv, gm, gd, gg)


def _build_fused_grid(serial_p2g: bool, G: int, update_node):
    """The fused substep's grid kernels (``TaichiBackend``'s ``fused``; ``FUSED_SLOTS``): ``fused_clear``, once
    per ``advance`` before its first substep, zeroes both grid buffers of the runs with substeps within every
    box slot and empties the slots; ``fused_grid(k)`` updates the nodes of substep ``k``'s scatter (buffer
    ``k & 1``, slot ``k % FUSED_SLOTS``) and, in the same pass over columns, zeroes the other buffer (the grid
    the fused kernel gathered from at ``k``) within its slot, when substep ``k + 1`` will scatter into it (a
    run's last grid stays until the next advance: ``grid_mass`` reads it)."""

    @ti.kernel
    def fused_clear(ngrip: ti.i32, nsub: ND(ti.i32, 1), box: ND(ti.i32, 3), gv: ND(vec3, 4), gm: ND(ti.f32, 4),
                    gd: ND(vec2, 4), gg: ND(ti.f32, 4)):
        # runs with substeps in this advance (an idle run keeps its last grid, as on the plain path)
        B = box.shape[0]
        for b, i, q in ti.ndrange(B, G, G):
            for s in ti.static(range(FUSED_SLOTS)):
                if nsub[b] > 0 and _in_columns(box, b, s, i, q):
                    for w in ti.static(range(2)):
                        _clear_column(b, b + w * B, s, i, q, ngrip, box, gv, gm, gd, gg)
        for b, s in ti.ndrange(B, FUSED_SLOTS):
            if nsub[b] > 0:
                _set_box(box, b, s, G, -1)

    @ti.kernel
    def fused_grid(k: ti.i32, dx: ti.f32, gravity: ti.f32, damp: ND(ti.f32, 1), bc: ti.i32, ngrip: ti.i32,
                   ngrip1: ti.i32, ncol: ti.i32, nsub: ND(ti.i32, 1), dt: ND(ti.f32, 1), kin: ND(ti.f32, 4),
                   ctype: ND(ti.i32, 1), ca: ND(vec3, 1), cb: ND(vec3, 1), csurf: ND(ti.i32, 1), fric: ND(ti.f32, 2),
                   held: ND(ti.i32, 3), box: ND(ti.i32, 3), gv: ND(vec3, 4), gm: ND(ti.f32, 4), gd: ND(vec2, 4),
                   gg: ND(ti.f32, 4), imp: ND(vec3, 2), work: ND(ti.f32, 2)):
        B = box.shape[0]
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)  # the force and work sums in the plain update's order
            for b, i, j, q in ti.ndrange(B, G, G, G):
                if k < nsub[b] and _in_box(box, b, k % FUSED_SLOTS, i, j, q):
                    gb = b + (k & 1) * B
                    m = gm[gb, i, j, q]
                    if m > 0.0:
                        update_node(b, gb, i, j, q, m, k, dx, gravity, damp, bc, ngrip, ncol, dt, kin, ctype, ca, cb,
                                    csurf, fric, held, gv, gg, imp, work)
            for b, i, q in ti.ndrange(B, G, G):
                last = (k + FUSED_SLOTS - 1) % FUSED_SLOTS
                if 1 <= k < nsub[b] and _in_columns(box, b, last, i, q):
                    _clear_column(b, b + (1 - (k & 1)) * B, last, i, q, ngrip1, box, gv, gm, gd, gg)
        else:
            for b, i, q in ti.ndrange(B, G, G):
                slot = k % FUSED_SLOTS
                if k < nsub[b] and _in_columns(box, b, slot, i, q):
                    gb = b + (k & 1) * B
                    for j in range(box[b, slot, 1], box[b, slot, 4] + 1):
                        m = gm[gb, i, j, q]
                        if m > 0.0:
                            update_node(b, gb, i, j, q, m, k, dx, gravity, damp, bc, ngrip, ncol, dt, kin, ctype,
                                        ca, cb, csurf, fric, held, gv, gg, imp, work)
                last = (k + FUSED_SLOTS - 1) % FUSED_SLOTS
                if 1 <= k < nsub[b] and _in_columns(box, b, last, i, q):
                    _clear_column(b, b + (1 - (k & 1)) * B, last, i, q, ngrip1, box, gv, gm, gd, gg)

    return fused_clear, fused_grid


def _g2p_particle_func(unrolled: bool, store: bool):
    """The grid-to-particle update of one particle in one of its forms (see ``TaichiBackend.g2p``): a Taichi
    function shared by the g2p kernel (``store``: it writes the particle's new state as it goes, in the order
    the g2p kernel always has) and the fused substep (``_build_scatter``: it returns the new state)."""

    @ti.func
    def g2p_particle(b, gb, p, k, h, inv_dx, G, l0sq, don: ti.template(), mat: ti.template(), body: ti.template(),
                     grip: ti.template(), x0: ti.template(), kin: ti.template(), sid: ti.template(), x: ti.template(),
                     v: ti.template(), C: ti.template(), F: ti.template(), d: ti.template(), dtil: ti.template(),
                     gv: ti.template(), gd: ti.template()):
        """Particle ``p`` of run ``b`` at substep ``k`` (step ``h``), gathering from grid run ``gb``: its new state
        (``ParticleState``; without ``store``, ``_store_g2p`` writes it)."""
        xp = x[b, p]
        Xp = xp * inv_dx   # (the g2p kernel's x[b, p] += h * v reads it again: the same value)
        base = ti.math.clamp(ti.cast(Xp - 0.5, ti.i32), 0, G - 3)
        fx = Xp - ti.cast(base, ti.f32)
        w = _weights(fx)
        hs = [1.0, -2.0, 1.0]
        dp = d[b, p]
        new_v = vec3(0.0)
        new_C = mat3(0.0)
        lap = 0.0
        if ti.static(unrolled):   # all 27 nodes unrolled (215 registers on CUDA: 12 % occupancy)
            for i, j, q in ti.static(ti.ndrange(3, 3, 3)):
                _g2p_node(gb, base, ti.Vector([i, j, q]), fx, inv_dx, dp, w[i][0], w[j][1], w[q][2], hs[i],
                          hs[j], hs[q], gv, gd, new_v, new_C, lap)
        else:   # the same sums in the same order, i and j as loops (117 registers: 24 %)
            for i in range(3):
                wi = _w1(fx[0], i)
                hi = ti.select(i == 1, -2.0, 1.0)
                for j in range(3):
                    wj = _w1(fx[1], j)
                    hj = ti.select(j == 1, -2.0, 1.0)
                    for q in ti.static(range(3)):
                        _g2p_node(gb, base, ti.Vector([i, j, q]), fx, inv_dx, dp, wi, wj, w[q][2], hi, hj,
                                  hs[q], gv, gd, new_v, new_C, lap)
        s = sid[b, p]
        reg = body[s]
        out = ParticleState(x=vec3(0.0), v=vec3(0.0), C=mat3(0.0), F=mat3(0.0), d=0.0)
        if ti.static(store):
            if don[b] != 0 and mat[b, reg, M_DMG] > 0.5:
                Dc = dp - l0sq * lap
                rate = (1.0 - dp) * dtil[b, p] - Dc
                d[b, p] = ti.min(1.0, dp + h / mat[b, reg, M_ETA] * ti.max(rate, 0.0))
            store_mat3(F, b, p, (ti.Matrix.identity(ti.f32, 3) + h * new_C) @ load_mat3(F, b, p))
            store_mat3(C, b, p, new_C)
            gp = grip[s]
            if gp >= 0:
                x[b, p] = x0[s] + vec3(kin[b, k, gp, 0], kin[b, k, gp, 1], kin[b, k, gp, 2])
                v[b, p] = vec3(kin[b, k, gp, 3], kin[b, k, gp, 4], kin[b, k, gp, 5])
            else:
                v[b, p] = new_v
                x[b, p] += h * new_v
        else:
            dn = dp
            if don[b] != 0 and mat[b, reg, M_DMG] > 0.5:
                Dc = dp - l0sq * lap
                rate = (1.0 - dp) * dtil[b, p] - Dc
                dn = ti.min(1.0, dp + h / mat[b, reg, M_ETA] * ti.max(rate, 0.0))
            Fn = (ti.Matrix.identity(ti.f32, 3) + h * new_C) @ load_mat3(F, b, p)
            gp = grip[s]
            xn = xp + h * new_v
            vn = new_v
            if gp >= 0:
                xn = x0[s] + vec3(kin[b, k, gp, 0], kin[b, k, gp, 1], kin[b, k, gp, 2])
                vn = vec3(kin[b, k, gp, 3], kin[b, k, gp, 4], kin[b, k, gp, 5])
            out = ParticleState(x=xn, v=vn, C=new_C, F=Fn, d=dn)
        return out

    return g2p_particle


@ti.func
def _store_g2p(b, p, st, dp, with_vc, x: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(),
               d: ti.template()):
    """Write g2p's new state ``st`` of particle ``p`` of run ``b`` (its damage only if it changed from ``dp``;
    its velocity and APIC matrix only ``with_vc``: the fused substep's scatter takes them from registers, and
    only a run's last g2p of an ``advance`` leaves them for later reads and the next advance)."""
    if st.d != dp:
        d[b, p] = st.d
    store_mat3(F, b, p, st.F)
    x[b, p] = st.x
    if with_vc:
        store_mat3(C, b, p, st.C)
        v[b, p] = st.v


def _build_g2p(unrolled: bool, component_major: bool):
    """The grid-to-particle kernel in one of its forms (see ``TaichiBackend.g2p``), for particle matrices in
    either layout (``MATRIX_STATE``)."""
    MND = matrix_nd(component_major)
    g2p_particle = _g2p_particle_func(unrolled, True)

    @ti.kernel
    def g2p(k: ti.i32, dx: ti.f32, l0sq: ti.f32, don: ND(ti.i32, 1), nsub: ND(ti.i32, 1), dt: ND(ti.f32, 1),
            mat: ND(ti.f32, 3), body: ND(ti.i32, 1), grip: ND(ti.i32, 1), x0: ND(vec3, 1), kin: ND(ti.f32, 4),
            sid: ND(ti.i32, 2), x: ND(vec3, 2), v: ND(vec3, 2), C: MND, F: MND, d: ND(ti.f32, 2),
            dtil: ND(ti.f32, 2), gv: ND(vec3, 4), gd: ND(vec2, 4), box: ND(ti.i32, 3)):
        inv_dx = 1.0 / dx
        G = gv.shape[1]
        for b, p in x:
            if k < nsub[b]:
                if p == 0:   # this substep's scatter box is what the next substep's clear zeroes
                    for a in ti.static(range(6)):
                        box[b, BOX_LAST, a] = box[b, BOX_NEXT, a]
                    _set_box(box, b, BOX_NEXT, G, -1)
                g2p_particle(b, b, p, k, dt[b], inv_dx, G, l0sq, don, mat, body, grip, x0, kin, sid, x, v, C, F, d,
                             dtil, gv, gd)

    return g2p


def _build_scatter(serial_p2g: bool, component_major: bool, fused: bool, unrolled: bool, registers: bool):
    """The particle-to-grid kernels, ``p2g`` (atomic) and ``p2g_tiled`` (see ``TaichiBackend.p2g``), for particle
    matrices in either layout (``MATRIX_STATE``); ``serial_p2g`` makes the CPU's scatter order deterministic.

    With ``fused`` (``TaichiBackend``'s ``fused``), each is a whole substep's particle work in one launch
    (G2P2G): for each particle, substep ``k - 1``'s g2p (in form ``unrolled``), gathering from grid buffer
    ``(k - 1) & 1``, then substep ``k``'s scatter of the updated particle into buffer ``k & 1`` (box slot
    ``k % FUSED_SLOTS``; the grids are ``(2 B, G, G, G)``, buffer ``w`` of run ``b`` at ``w B + b``): one read and
    one write of the particle state per substep instead of two. With ``registers`` the scatter takes the g2p's
    new state from registers (and the velocity and APIC matrix are written only at a run's last g2p of an
    advance); without, g2p writes it whole and the scatter reads it back, as the plain path's kernels do
    (a GPU comparison; on the CPU the compiler forwards the stores either way). The fused path's results
    agree with the plain path's to float rounding, not bit for bit: the same arithmetic, compiled in
    another kernel with fast math, rounds differently (``tests/test_taichi_fused.py``). Both forms take the
    g2p's arguments too (unused without ``fused``), so that a substep's stages name one argument list."""
    MND = matrix_nd(component_major)
    g2p_particle = _g2p_particle_func(unrolled, False)

    # what the scatter reads of a particle: the fused substep's g2p state ``st``, or (plain) the particle arrays,
    # read where the plain kernels always read them
    @ti.func
    def position(b, p, st, x: ti.template()):
        return st.x if ti.static(fused) else x[b, p]

    @ti.func
    def damage(b, p, st, d: ti.template()):
        return st.d if ti.static(fused) else d[b, p]

    @ti.func
    def terms(b, p, s, h, inv_dx, apic, st, mat: ti.template(), body: ti.template(), fibre: ti.template(),
              vol: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(), d: ti.template(),
              dtil: ti.template()) -> P2GTerms:
        t = P2GTerms(affine=mat3(0.0), mv=vec3(0.0), mass=0.0)
        if ti.static(fused):
            t = _p2g_terms_of(b, p, s, h, inv_dx, apic, st, mat, body, fibre, vol, dtil)
        else:
            t = _p2g_terms(b, p, s, h, inv_dx, apic, mat, body, fibre, vol, v, C, F, d, dtil)
        return t

    @ti.func
    def fused_g2p(b, p, k, inv_dx, G, l0sq, don: ti.template(), nsub: ti.template(), dt: ti.template(),
                  mat: ti.template(), body: ti.template(), grip: ti.template(), x0: ti.template(), kin: ti.template(),
                  sid: ti.template(), x: ti.template(), v: ti.template(), C: ti.template(), F: ti.template(),
                  d: ti.template(), dtil: ti.template(), gv: ti.template(), gd: ti.template(), box: ti.template()):
        """The state substep ``k``'s scatter takes of particle ``p`` of run ``b``: after substep ``k - 1``'s g2p
        (when the run had that substep; written back by ``_store_g2p``, with ``registers`` the velocity and APIC
        matrix only at the run's last g2p of the advance), else from the particle arrays (``k = 0``).
        Particle 0 empties box slot ``(k + 1) % FUSED_SLOTS``, whose buffer region ``fused_grid(k - 1)``
        zeroed."""
        st = ParticleState(x=vec3(0.0), v=vec3(0.0), C=mat3(0.0), F=mat3(0.0), d=0.0)
        if k >= 1 and k - 1 < nsub[b]:
            dp = d[b, p]
            st = g2p_particle(b, b + ((k - 1) & 1) * x.shape[0], p, k - 1, dt[b], inv_dx, G, l0sq, don, mat, body,
                              grip, x0, kin, sid, x, v, C, F, d, dtil, gv, gd)
            if ti.static(registers):
                _store_g2p(b, p, st, dp, k >= nsub[b], x, v, C, F, d)
            else:
                _store_g2p(b, p, st, dp, True, x, v, C, F, d)
                st = _load_state(b, p, x, v, C, F, d)
            if p == 0 and k >= 2:
                _set_box(box, b, (k + 1) % FUSED_SLOTS, G, -1)
        elif k < nsub[b]:
            st = _load_state(b, p, x, v, C, F, d)
        return st

    @ti.kernel
    def p2g(k: ti.i32, dx: ti.f32, apic: ti.f32, l0sq: ti.f32, ngrip: ti.i32, don: ND(ti.i32, 1), nsub: ND(ti.i32, 1),
            dt: ND(ti.f32, 1), mat: ND(ti.f32, 3), body: ND(ti.i32, 1), fibre: ND(vec3, 1), vol: ND(ti.f32, 1),
            grip: ND(ti.i32, 1), x0: ND(vec3, 1), kin: ND(ti.f32, 4), sid: ND(ti.i32, 2), x: ND(vec3, 2),
            v: ND(vec3, 2), C: MND, F: MND, d: ND(ti.f32, 2), dtil: ND(ti.f32, 2), gv: ND(vec3, 4),
            gm: ND(ti.f32, 4), gd: ND(vec2, 4), gg: ND(ti.f32, 4), box: ND(ti.i32, 3)):
        inv_dx = 1.0 / dx
        G = gm.shape[1]
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)
        for b, p in ti.ndrange(x.shape[0], x.shape[1]):
            st = ParticleState(x=vec3(0.0), v=vec3(0.0), C=mat3(0.0), F=mat3(0.0), d=0.0)
            if ti.static(fused):
                st = fused_g2p(b, p, k, inv_dx, G, l0sq, don, nsub, dt, mat, body, grip, x0, kin, sid, x, v, C, F, d,
                               dtil, gv, gd, box)
            if k < nsub[b]:
                gb, wb = b, BOX_NEXT   # the grid run and box slot scattered into
                if ti.static(fused):
                    gb, wb = b + (k & 1) * x.shape[0], k % FUSED_SLOTS
                Xp = position(b, p, st, x) * inv_dx
                base = ti.math.clamp(ti.cast(Xp - 0.5, ti.i32), 0, G - 3)
                fx = Xp - ti.cast(base, ti.f32)
                w = _weights(fx)
                s = sid[b, p]
                t = terms(b, p, s, dt[b], inv_dx, apic, st, mat, body, fibre, vol, v, C, F, d, dtil)
                if ti.static(serial_p2g):
                    _grow_box(box, b, wb, base, base + 2)
                elif p == 0:   # a run's particles all growing one box would contend for six addresses
                    _set_box(box, b, wb, 0, G - 1)
                dp = damage(b, p, st, d)
                gp = grip[s]
                for i, j, q in ti.static(ti.ndrange(3, 3, 3)):
                    off = ti.Vector([i, j, q])
                    dpos = (ti.cast(off, ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[q][2]
                    _scatter_global(gb, base + off, weight, weight * (t.mv + t.affine @ dpos), t.mass, dp, gp,
                                    ngrip, gv, gm, gd, gg)

    @ti.kernel
    def p2g_tiled(k: ti.i32, dx: ti.f32, apic: ti.f32, l0sq: ti.f32, ngrip: ti.i32, don: ND(ti.i32, 1),
                  nsub: ND(ti.i32, 1), dt: ND(ti.f32, 1), mat: ND(ti.f32, 3), body: ND(ti.i32, 1),
                  fibre: ND(vec3, 1), vol: ND(ti.f32, 1), grip: ND(ti.i32, 1), x0: ND(vec3, 1), kin: ND(ti.f32, 4),
                  sid: ND(ti.i32, 2), x: ND(vec3, 2), v: ND(vec3, 2), C: MND, F: MND, d: ND(ti.f32, 2),
                  dtil: ND(ti.f32, 2), gv: ND(vec3, 4), gm: ND(ti.f32, 4), gd: ND(vec2, 4), gg: ND(ti.f32, 4),
                  box: ND(ti.i32, 3)):
        # CUDA only. One thread block per TILE consecutive particles of a run (spatially coherent along a
        # space-filling curve, particle_order.py): their 27-node contributions are summed in shared memory over
        # the tile's bounding box of nodes, then added to the grid once per node, instead of 6 global
        # float atomics per particle and node (the L2 atomics bound the plain scatter). A tile whose box
        # exceeds TILE_NODES nodes (or a scene with more than one grip) scatters globally, as p2g does.
        inv_dx = 1.0 / dx
        G = gm.shape[1]
        N = x.shape[1]
        ntile = (N + TILE - 1) // TILE
        ti.loop_config(block_dim=TILE)
        for t in range(x.shape[0] * ntile * TILE):
            tid = t % TILE
            b = t // (ntile * TILE)
            # lanes of a warp take particles TILE/32 apart, so that they rarely share a base cell: lanes
            # adding to the same shared address in one instruction would serialise
            p = (t // TILE) % ntile * TILE + (tid % 32) * (TILE // 32) + tid // 32
            st = ParticleState(x=vec3(0.0), v=vec3(0.0), C=mat3(0.0), F=mat3(0.0), d=0.0)
            if ti.static(fused):
                if p < N:
                    st = fused_g2p(b, p, k, inv_dx, G, l0sq, don, nsub, dt, mat, body, grip, x0, kin, sid, x, v, C, F,
                                   d, dtil, gv, gd, box)
            gb, wb = b, BOX_NEXT   # the grid run and box slot scattered into
            if ti.static(fused):
                gb, wb = b + (k & 1) * x.shape[0], k % FUSED_SLOTS
            lo = ti.simt.block.SharedArray((3,), ti.i32)
            hi = ti.simt.block.SharedArray((3,), ti.i32)
            big = ti.simt.block.SharedArray((3,), ti.i32)
            # channel-major sums over the tile's nodes, all as fixed-point integers (a shared integer add is one
            # instruction; a float add is a compare-and-swap loop, which lanes of the block's warps adding to one
            # node at once make retry): momentum (3), mass, the weight sum, the damage sum and the grip mass
            # (ACC_CHANNELS; see _fixed_point_scale, WEIGHT_SCALE)
            acc = ti.simt.block.SharedArray((ACC_CHANNELS * TILE_NODES,), ti.i32)
            if tid < 3:
                lo[tid] = G
                hi[tid] = -1
                big[tid] = 0
            ti.simt.block.sync()
            active = p < N and k < nsub[b]
            base = ti.Vector([0, 0, 0])
            fx = vec3(0.0)
            affine = mat3(0.0)
            mv = vec3(0.0)
            mass = 0.0
            dp = 0.0
            s = 0
            if active:
                Xp = position(b, p, st, x) * inv_dx
                base = ti.math.clamp(ti.cast(Xp - 0.5, ti.i32), 0, G - 3)
                fx = Xp - ti.cast(base, ti.f32)
                for a in ti.static(range(3)):
                    ti.atomic_min(lo[a], base[a])
                    ti.atomic_max(hi[a], base[a] + 2)
                s = sid[b, p]
                tm = terms(b, p, s, dt[b], inv_dx, apic, st, mat, body, fibre, vol, v, C, F, d, dtil)
                affine = tm.affine
                mv = tm.mv
                mass = tm.mass
                ti.atomic_max(big[0], _momentum_bound_bits(mv, affine, dx))
                ti.atomic_max(big[1], ti.bit_cast(ti.abs(mass), ti.i32))
                dp = damage(b, p, st, d)
                if not (dp >= 0.0 and dp <= 1.0):  # the damage sum's units need d in [0, 1] (NaN included)
                    big[2] = 1
            ti.simt.block.sync()
            o0, o1, o2 = lo[0], lo[1], lo[2]
            if tid == 0 and hi[0] >= 0:   # the run's scatter box takes in the tile's
                _grow_box(box, b, wb, ti.Vector([o0, o1, o2]), ti.Vector([hi[0], hi[1], hi[2]]))
            sy = hi[1] - o1 + 1
            sz = hi[2] - o2 + 1
            n_nodes = (hi[0] - o0 + 1) * sy * sz
            # a tile with a non-finite particle (or a damage outside [0, 1]) scatters globally, so that its NaN
            # reaches the grid as before
            finite = big[0] < F32_INF_BITS and big[1] < F32_INF_BITS and big[2] == 0
            tiled = hi[0] >= 0 and n_nodes <= TILE_NODES and ngrip <= 1 and finite
            s_mom, inv_mom = _fixed_point_scale(big[0])
            s_mass, inv_mass = _fixed_point_scale(big[1])
            if tiled:
                c = tid
                while c < n_nodes:
                    for ch in ti.static(range(ACC_CHANNELS)):
                        acc[ch * TILE_NODES + c] = 0
                    c += TILE
            ti.simt.block.sync()
            if active:
                w = _weights(fx)
                gp = grip[s]
                for i, j, q in ti.static(ti.ndrange(3, 3, 3)):
                    off = ti.Vector([i, j, q])
                    dpos = (ti.cast(off, ti.f32) - fx) * dx
                    weight = w[i][0] * w[j][1] * w[q][2]
                    node = base + off
                    mom = weight * (mv + affine @ dpos)
                    if tiled:
                        c = ((node[0] - o0) * sy + node[1] - o1) * sz + node[2] - o2
                        for a in ti.static(range(3)):
                            ti.atomic_add(acc[a * TILE_NODES + c], _round_to_int(mom[a] * s_mom))
                        ti.atomic_add(acc[3 * TILE_NODES + c], _round_to_int(weight * mass * s_mass))
                        ti.atomic_add(acc[4 * TILE_NODES + c], _round_to_int(weight * WEIGHT_SCALE))
                        if dp != 0.0:  # adding zero changes no sum: most particles are undamaged
                            ti.atomic_add(acc[5 * TILE_NODES + c], _round_to_int(weight * dp * WEIGHT_SCALE))
                        if gp >= 0:
                            ti.atomic_add(acc[6 * TILE_NODES + c], _round_to_int(weight * mass * s_mass))
                    else:
                        _scatter_global(gb, node, weight, mom, mass, dp, gp, ngrip, gv, gm, gd, gg)
            ti.simt.block.sync()
            if tiled:
                c = tid
                while c < n_nodes:
                    sw_units = acc[4 * TILE_NODES + c]
                    if sw_units != 0:  # a node some particle touched (touched_node)
                        i = c // (sy * sz) + o0
                        j = (c // sz) % sy + o1
                        q = c % sz + o2
                        gv[gb, i, j, q] += inv_mom * vec3(ti.cast(acc[c], ti.f32),
                                                         ti.cast(acc[TILE_NODES + c], ti.f32),
                                                         ti.cast(acc[2 * TILE_NODES + c], ti.f32))
                        gm[gb, i, j, q] += inv_mass * ti.cast(acc[3 * TILE_NODES + c], ti.f32)
                        gd[gb, i, j, q] += (1.0 / WEIGHT_SCALE) * vec2(ti.cast(acc[5 * TILE_NODES + c], ti.f32),
                                                                      ti.cast(sw_units, ti.f32))
                        if ngrip > 0 and acc[6 * TILE_NODES + c] != 0:
                            gg[gb * ngrip, i, j, q] += inv_mass * ti.cast(acc[6 * TILE_NODES + c], ti.f32)
                    c += TILE
            ti.simt.block.sync()  # the next tile of this thread block (grid-stride loop) reuses the arrays

    return p2g, p2g_tiled


def _build_kernels(serial_p2g: bool, component_major: bool):
    """The kernels that depend only on ``serial_p2g`` (it makes the CPU's scatter order deterministic) and on
    the particle matrices' layout (``MATRIX_STATE``)."""
    MND = matrix_nd(component_major)

    @ti.kernel
    def wipe_grid(mask: ND(ti.i32, 1), ngrip: ti.i32, gv: ND(vec3, 4), gm: ND(ti.f32, 4), gd: ND(vec2, 4),
                  gg: ND(ti.f32, 4), box: ND(ti.i32, 3)):
        # every node of runs mask[b] != 0 (a new run in a slot: nothing of the last run's grid survives; with
        # the fused substep, grid run gb is buffer gb // B of run gb % B)
        for gb, i, j, q in gm:
            if mask[gb % mask.shape[0]] != 0:
                _zero_node(gb, i, j, q, ngrip, gv, gm, gd, gg)
        for b, w in ti.ndrange(box.shape[0], box.shape[1]):   # and every node box empty
            if mask[b] != 0:
                _set_box(box, b, w, gm.shape[1], -1)

    @ti.func
    def _particle_stats(b: ti.i32, r: ti.i32, p: ti.i32, lo: ti.f32, hi: ti.f32, mat: ti.template(),
                        body: ti.template(), vol: ti.template(), sid: ti.template(), x: ti.template(),
                        v: ti.template(), F: ti.template(), d: ti.template(), acc: ti.template()):
        xp = x[b, p]
        vp = v[b, p]
        dp = d[b, p]
        s = vp.norm()
        bad = 0
        if not (s < 1e20) or not (ti.abs(xp).max() < 1e20) or not (ti.abs(load_mat3(F, b, p)).max() < 1e20) \
                or not (ti.abs(dp) < 1e20):
            bad = 1
        if bad != 0:
            ti.atomic_add(acc[b, r, 2], 1.0)
        else:
            q = sid[b, p]
            reg = body[q]
            ti.atomic_max(acc[b, r, 0], s)
            ti.atomic_add(acc[b, r, 1], 0.5 * mat[b, reg, M_RHO] * vol[q] * s * s)
            if xp.min() < lo or xp.max() > hi:
                ti.atomic_add(acc[b, r, 3], 1.0)
            col = BODY0 + 4 * reg
            for a in ti.static(range(3)):
                ti.atomic_add(acc[b, r, col + a], xp[a])
            ti.atomic_add(acc[b, r, col + 3], dp)

    @ti.func
    def _reduce_stats(mask: ti.template(), acc: ti.template(), out: ti.template()):
        """out[b, c] = max (column 0) or sum over the partial rows acc[b, :, c], masked runs only."""
        for b, c in ti.ndrange(acc.shape[0], acc.shape[2]):
            if mask[b] != 0:
                t = 0.0
                for r in range(acc.shape[1]):
                    if c == 0:
                        t = ti.max(t, acc[b, r, c])
                    else:
                        t += acc[b, r, c]
                out[b, c] = t

    # Frame statistics: each run's particles add into ``acc.shape[1]`` partial rows (particle p into row
    # p % R), then the rows are reduced. On a GPU R = 256 spreads the atomics of 50k particles over 256
    # addresses per column instead of one (same-address float atomics serialise); on the CPU R = 1.
    @ti.kernel
    def frame_stats(lo: ti.f32, hi: ti.f32, mask: ND(ti.i32, 1), mat: ND(ti.f32, 3), body: ND(ti.i32, 1),
                    vol: ND(ti.f32, 1), sid: ND(ti.i32, 2), x: ND(vec3, 2), v: ND(vec3, 2), F: MND, d: ND(ti.f32, 2),
                    acc: ND(ti.f32, 3), out: ND(ti.f32, 2)):
        for b, r, c in ti.ndrange(acc.shape[0], acc.shape[1], acc.shape[2]):
            if mask[b] != 0:
                acc[b, r, c] = 0.0
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)  # float sums in a fixed order: features repeat bit for bit
        for b, p in ti.ndrange(x.shape[0], x.shape[1]):  # a range-for: serialize applies
            if mask[b] != 0:
                _particle_stats(b, p % acc.shape[1], p, lo, hi, mat, body, vol, sid, x, v, F, d, acc)
        _reduce_stats(mask, acc, out)

    @ti.kernel
    def frame_end(lo: ti.f32, hi: ti.f32, mask: ND(ti.i32, 1), nstats: ti.i32, nk: ti.i32, mat: ND(ti.f32, 3),
                  body: ND(ti.i32, 1), vol: ND(ti.f32, 1), sid: ND(ti.i32, 2), x: ND(vec3, 2), v: ND(vec3, 2),
                  F: MND, d: ND(ti.f32, 2), imp: ND(vec3, 2), work: ND(ti.f32, 2), acc: ND(ti.f32, 3), out: ND(ti.f32, 2)):
        """One launch at the end of a chunk: zero ``out``, the statistics of the masked runs (as
        ``frame_stats``), then their force and work sums moved into ``out`` (4 columns per object after
        the statistics) and reset on the device."""
        for b, c in ti.ndrange(out.shape[0], out.shape[1]):
            out[b, c] = 0.0
        for b, r, c in ti.ndrange(acc.shape[0], acc.shape[1], acc.shape[2]):
            if mask[b] != 0:
                acc[b, r, c] = 0.0
        if ti.static(serial_p2g):
            ti.loop_config(serialize=True)
        for b, p in ti.ndrange(x.shape[0], x.shape[1]):
            if mask[b] != 0:
                _particle_stats(b, p % acc.shape[1], p, lo, hi, mat, body, vol, sid, x, v, F, d, acc)
        _reduce_stats(mask, acc, out)
        for b, c in ti.ndrange(imp.shape[0], nk):
            if mask[b] != 0:
                for a in ti.static(range(3)):
                    out[b, nstats + 4 * c + a] = imp[b, c][a]
                out[b, nstats + 4 * c + 3] = work[b, c]
                imp[b, c] = vec3(0.0)
                work[b, c] = 0.0

    @ti.kernel
    def reset_slots(mask: ND(ti.i32, 1), perm0: ND(ti.i32, 1), x0: ND(vec3, 1), sid: ND(ti.i32, 2), x: ND(vec3, 2),
                    v: ND(vec3, 2), C: MND, F: MND, d: ND(ti.f32, 2), dtil: ND(ti.f32, 2)):
        # a new run starts in the initial device order perm0 (scene particle perm0[p] at device index p)
        for b, p in x:
            if mask[b] != 0:
                s = perm0[p]
                sid[b, p] = s
                x[b, p] = x0[s]
                v[b, p] = vec3(0.0)
                store_mat3(C, b, p, mat3(0.0))
                store_mat3(F, b, p, ti.Matrix.identity(ti.f32, 3))
                d[b, p] = 0.0
                dtil[b, p] = 0.0

    @ti.kernel
    def gather(idx: ND(ti.i32, 1), sid: ND(ti.i32, 2), x: ND(vec3, 2), d: ND(ti.f32, 2), xo: ND(vec3, 2),
               do: ND(ti.f32, 2)):
        # runs idx[i] back in the scene's order (device particle p is scene particle sid[b, p]): the reorder
        # happens here, not in numpy on the host (~85 ms per read of 64 paper runs on a 2-core CPU)
        for i, p in xo:
            b = idx[i]
            s = sid[b, p]
            xo[i, s] = x[b, p]
            do[i, s] = d[b, p]

    return frame_stats, reset_slots, gather, frame_end, wipe_grid


_KERNELS: dict[tuple, object] = {}


def _kernels(build, *config):
    """``build(*config)``'s kernels, built once per process (each new kernel object compiles anew)."""
    key = (build.__name__, *config)
    if key not in _KERNELS:
        _KERNELS[key] = build(*config)
    return _KERNELS[key]


#: the scatter's arguments (either form, plain or fused: ``_build_scatter``)
_P2G_ARGS = ("k", "dx", "apic", "l0sq", "ngrip1", "don", "nsub", "dt", "mat", "body", "fibre", "vol", "grip", "x0",
             "kin", "sid", "x", "v", "C", "F", "d", "dtil", "gv", "gm", "gd", "gg", "box")
#: a substep's kernels in order and their arguments: ``k`` (the substep), a scalar of the backend's
#: ``_scalars`` or one of its arrays
_STAGE_ARGS = {
    "clear": ("k", "ngrip1", "nsub", "box", "gv", "gm", "gd", "gg"),
    "p2g": _P2G_ARGS,
    "grid": ("k", "dx", "gravity", "damp", "bc", "ngrip", "ncol", "nsub", "dt", "kin", "ctype", "ca", "cb", "csurf",
             "fric", "held", "box", "gv", "gm", "gg", "imp", "work"),
    "g2p": ("k", "dx", "l0sq", "don", "nsub", "dt", "mat", "body", "grip", "x0", "kin", "sid", "x", "v", "C", "F", "d",
            "dtil", "gv", "gd", "box"),
}
#: the fused substep's stages (``TaichiBackend``'s ``fused``): ``fclear`` once per ``advance``, then per substep ``k``
#: the G2P2G kernel (g2p of ``k - 1``, scatter of ``k``) and the grid update of ``k`` with the other buffer's clear;
#: a last ``fused`` at ``k = n`` does the g2p of substep ``n - 1``
_FUSED_STAGE_ARGS = {
    "fclear": ("ngrip1", "nsub", "box", "gv", "gm", "gd", "gg"),
    "fused": _P2G_ARGS,
    "fgrid": ("k", "dx", "gravity", "damp", "bc", "ngrip", "ngrip1", "ncol", "nsub", "dt", "kin", "ctype", "ca", "cb",
              "csurf", "fric", "held", "box", "gv", "gm", "gd", "gg", "imp", "work"),
}
#: substeps per graph launch in ``advance`` (a frame's remainder goes one substep at a time)
GRAPH_SUBSTEPS = 8


class TaichiBackend:
    """Batched engine state and kernels on one Taichi arch (see :mod:`invphys_anisompm.backends`)."""

    name = "taichi"
    #: ``read``/``read_slots`` return new host arrays (``host_copy``): records may keep views of them
    reads_are_new = True

    def __init__(self, scene, batch: int, arch: str = "cpu", allow_cpu_fallback: bool = False,
                 stats_partials: int | None = None, p2g: str = "atomic", particle_order: str | None = None,
                 g2p: str = "auto", resort_every: int | None = None, component_major: bool | None = None,
                 fused: bool = False, fused_registers: bool | None = None, **_: object):
        if p2g not in ("auto", "atomic", "tiled"):
            raise InvphysError(f"p2g must be 'auto', 'atomic' or 'tiled', got {p2g!r}")
        if g2p not in ("auto", "unrolled", "loop"):
            raise InvphysError(f"g2p must be 'auto', 'unrolled' or 'loop', got {g2p!r}")
        if particle_order not in (None, "scene", *ORDERS):
            raise InvphysError(f"particle_order must be 'scene' or one of {sorted(ORDERS)}, got {particle_order!r}")
        if resort_every is not None and (isinstance(resort_every, bool) or int(resort_every) < 0):
            raise InvphysError(f"resort_every must be a number of substeps >= 0 (0: never), got {resort_every!r}")
        self.arch = ensure_taichi(arch, allow_cpu_fallback)
        if p2g == "auto":
            p2g = "tiled" if self.arch == "cuda" else "atomic"
        if p2g == "tiled" and self.arch != "cuda":
            raise InvphysError("p2g='tiled' needs CUDA (it sums tiles in GPU shared memory); use 'atomic' or 'auto'")
        #: the scatter in use: "atomic" (global float atomics; serialised on the CPU) or "tiled" (CUDA)
        self.p2g = p2g
        #: g2p's form: "unrolled" (27 nodes; the CPU's, bit for bit as before) or "loop" (loops over two
        #: axes: half the registers, 1.23x faster on an H100; the same sums to float rounding)
        self.g2p = g2p if g2p != "auto" else ("loop" if self.arch == "cuda" else "unrolled")
        self.device = device_name(self.arch)
        #: device arrays to new host arrays in one copy (``taichi_host_copy.py``); ``.fallback`` says why not
        self.host_copy = HostCopy(self.arch)
        #: host arrays into device arrays in one copy (the uploads between a stream's chunks)
        self.upload = HostUpload(self.arch, self.host_copy)
        self.scene = scene
        o = scene.options
        self.options = o
        self.batch = int(batch)
        #: particle reads copied back while the next chunk runs (``read_slots_later``; CUDA), into a pinned buffer
        #: of a whole batch's positions and damage
        self.later = LaterCopies(self.arch, self.host_copy, capacity=self.batch * scene.n_particles * 16)
        serial = bool(o.deterministic and self.arch == "cpu")
        #: particle matrices component-major (``MATRIX_STATE``): on CUDA unless asked otherwise
        self.component_major = bool(self.arch == "cuda" if component_major is None else component_major)
        (self._stats, self._reset, self._gather, self._frame_end,
         self._wipe) = _kernels(_build_kernels, serial, self.component_major)
        #: one G2P2G kernel and one grid kernel per substep on two grid buffers (``_build_scatter``,
        #: ``_build_fused_grid``) instead of clear, p2g, grid update and g2p on one grid
        self.fused = bool(fused)
        #: the fused scatter takes g2p's new state from registers (``_build_scatter``; off: written and read back)
        self.fused_registers = bool(self.fused and (fused_registers is None or fused_registers))
        unrolled = self.g2p == "unrolled"
        scatter = _kernels(_build_scatter, serial, self.component_major, self.fused, unrolled and self.fused,
                           self.fused_registers)
        self._p2g = scatter[1] if p2g == "tiled" else scatter[0]
        self._clear, self._grid, fused_clear, fused_grid = _kernels(_build_grid_kernels, serial, int(o.grid))
        if self.fused:
            self._stage_args = _FUSED_STAGE_ARGS
            self._kernel_of = {"fclear": fused_clear, "fused": self._p2g, "fgrid": fused_grid}
        else:
            self._g2p = _kernels(_build_g2p, unrolled, self.component_major)
            self._stage_args = _STAGE_ARGS
            self._kernel_of = {"clear": self._clear, "p2g": self._p2g, "grid": self._grid, "g2p": self._g2p}
        #: the substep's scalar arguments (dtype, value): fixed by the scene's options
        self._scalars = {"dx": (ti.f32, float(o.dx)), "apic": (ti.f32, float(o.apic_blend)),
                         "ngrip1": (ti.i32, max(len(scene.grips), 1)), "gravity": (ti.f32, float(o.gravity)),
                         "bc": (ti.i32, int(o.boundary_cells)), "ngrip": (ti.i32, len(scene.grips)),
                         "ncol": (ti.i32, len(scene.colliders)), "l0sq": (ti.f32, float(o.l0_cells) ** 2)}
        self._graphs: dict[tuple, object] = {}
        self._bound: dict[tuple[str, ...], tuple[tuple[str, ...], bool]] = {}
        self._plain_stages = tuple(self._stage_args)
        self._nsub_max = 0
        #: particle order on the device: the Hilbert order of the initial cells for the tiled scatter (tiles
        #: of consecutive particles stay compact; ``particle_order.py``), else the scene's; every read
        #: returns the scene's order
        order = particle_order or ("hilbert" if p2g == "tiled" or resort_every else "scene")
        self.particle_order = order
        self._perm = ORDERS[order](scene.positions, o.dx, o.grid) if order != "scene" else None
        B, N, G = self.batch, scene.n_particles, o.grid
        #: substeps between re-sorts of each run's particles into the curve order of their current cells
        #: (``taichi_resort.py``; 0: never): RESORT_EVERY for the tiled scatter when PyTorch (the sort) is
        #: installed, else never (the CPU's serialised scatter keeps the scene's order, and its results bit for bit)
        has_torch = importlib.util.find_spec("torch") is not None
        if resort_every is None:
            resort_every = RESORT_EVERY if p2g == "tiled" and has_torch else 0
        if resort_every and order == "scene":
            raise InvphysError("resort_every needs a particle_order curve ('hilbert' or 'morton'), not 'scene'")
        if resort_every and not has_torch:
            raise InvphysError("resort_every needs PyTorch (it sorts each run's particles on the device): "
                               "pip install torch, or set resort_every=0")
        self.resort_every = int(resort_every)
        self.resorter = None
        if self.resort_every:
            from invphys_anisompm.backends.taichi_resort import ParticleResorter

            self.resorter = ParticleResorter(self, order, self.resort_every)
        self.ngrip = len(scene.grips)
        self.ncol = len(scene.colliders)
        NG1, NK1, NC1 = max(self.ngrip, 1), max(self.ngrip + self.ncol, 1), max(self.ncol, 1)
        self.nk1 = NK1
        self.nstats = n_stats(len(scene.bodies))
        self.x = ti.ndarray(vec3, (B, N))
        self.v = ti.ndarray(vec3, (B, N))
        # the APIC matrix C and the deformation gradient F, in the layout of MATRIX_STATE
        self.C = ti.ndarray(ti.f32, (B, 9, N)) if self.component_major else ti.ndarray(mat3, (B, N))
        self.F = ti.ndarray(ti.f32, (B, 9, N)) if self.component_major else ti.ndarray(mat3, (B, N))
        self.d = ti.ndarray(ti.f32, (B, N))
        self.dtil = ti.ndarray(ti.f32, (B, N))
        #: device particle p of run b is scene particle sid[b, p] (runs are re-sorted one by one)
        self.sid = ti.ndarray(ti.i32, (B, N))
        # the grid; with the fused substep two buffers of it, buffer w of run b at grid run w B + b
        GB = 2 * B if self.fused else B
        self.gv = ti.ndarray(vec3, (GB, G, G, G))
        self.gm = ti.ndarray(ti.f32, (GB, G, G, G))
        self.gd = ti.ndarray(vec2, (GB, G, G, G))
        self.gg = ti.ndarray(ti.f32, (GB * NG1, G, G, G))
        #: per run, the node boxes (lo xyz, hi xyz) of the last scatter and of the one under way (BOX_*); with
        #: the fused substep, its FUSED_SLOTS box slots
        nbox = FUSED_SLOTS if self.fused else 2
        self.box = ti.ndarray(ti.i32, (B, nbox, 6))
        self.box.from_numpy(np.broadcast_to(np.array([G] * 3 + [-1] * 3, np.int32), (B, nbox, 6)).copy())
        self.mat = ti.ndarray(ti.f32, (B, len(scene.bodies), N_MAT))
        self.fric = ti.ndarray(ti.f32, (B, NC1))
        self.nsub = ti.ndarray(ti.i32, (B,))
        self.dt = ti.ndarray(ti.f32, (B,))
        self.kin = ti.ndarray(ti.f32, (B, 1, NK1, 6))
        self.stats_out = ti.ndarray(ti.f32, (B, self.nstats))
        # partial rows of the frame statistics (see the kernels): 256 on a GPU, 1 (the plain sum) on the CPU
        R = int(stats_partials or (256 if self.arch == "cuda" else 1))
        self.stats_acc = ti.ndarray(ti.f32, (B, R, self.nstats))
        self.end_out = ti.ndarray(ti.f32, (B, self.nstats + 4 * NK1))
        self.imp = ti.ndarray(vec3, (B, NK1))
        self.work = ti.ndarray(ti.f32, (B, NK1))
        # per-particle constants in the scene's order, read through sid
        self.body = self._const(ti.i32, scene.body.astype(np.int32))
        self.fibre = self._const(vec3, scene.fibres.astype(np.float32))
        self.vol = self._const(ti.f32, scene.volume.astype(np.float32))
        self.grip = self._const(ti.i32, scene.grip.astype(np.int32))
        self.x0 = self._const(vec3, scene.positions.astype(np.float32))
        #: the initial device order: scene particle perm0[p] at device index p of every new run
        self._perm0_host = (np.arange(N) if self._perm is None else self._perm).astype(np.int32)
        self.perm0 = self._const(ti.i32, self._perm0_host)
        self.held = self._const(ti.i32, scene.held.astype(np.int32), (G, G, G))
        enc = [c.encode() for c in scene.colliders] or [(0, np.zeros(3), np.array([0.0, 1.0, 0.0]))]
        self.ctype = self._const(ti.i32, np.array([e[0] for e in enc], np.int32))
        self.ca = self._const(vec3, np.array([e[1] for e in enc], np.float32))
        self.cb = self._const(vec3, np.array([e[2] for e in enc], np.float32))
        from invphys_anisompm.scene import SURFACES

        self.csurf = self._const(ti.i32, np.array([SURFACES[c.surface] for c in scene.colliders] or [0], np.int32))
        self.damp = ti.ndarray(ti.f32, (B,))
        self.don = ti.ndarray(ti.i32, (B,))
        self._mat_host = np.zeros((B, len(scene.bodies), N_MAT), np.float32)
        self._fric_host = np.zeros((B, NC1), np.float32)
        self._gather_bufs: dict[int, tuple] = {}
        self._uploaded: dict[str, np.ndarray] = {}
        self._slot_mask = ti.ndarray(ti.i32, (B,))
        self._stats_mask = ti.ndarray(ti.i32, (B,))

    def _order(self, a: np.ndarray) -> np.ndarray:
        """A per-particle scene array in the device's particle order."""
        return a if self._perm is None else a[self._perm]

    @staticmethod
    def _const(dtype, values: np.ndarray, shape: tuple | None = None):
        shape = shape or (values.shape[0],)
        arr = ti.ndarray(dtype, shape)
        arr.from_numpy(values)
        return arr

    def load(self, table: np.ndarray, friction: np.ndarray) -> None:
        """Reset every run to the initial state with its own material table (B, n_bodies, N_MAT) and
        collider frictions (B, n_colliders)."""
        B, N = self.batch, self.scene.n_particles
        self._mat_host[:] = table
        self._fric_host[:, :self.ncol] = friction
        self.mat.from_numpy(self._mat_host)
        self.fric.from_numpy(self._fric_host)
        self.imp.fill(0.0)
        self.work.fill(0.0)
        self.sid.from_numpy(np.broadcast_to(self._perm0_host, (B, N)).copy())
        self.x.from_numpy(np.broadcast_to(self._order(self.scene.positions).astype(np.float32), (B, N, 3)).copy())
        self.v.from_numpy(np.zeros((B, N, 3), np.float32))
        self.set_particle_array("C", np.zeros((B, N, 3, 3), np.float32))
        self.set_particle_array("F", np.broadcast_to(np.eye(3, dtype=np.float32), (B, N, 3, 3)))
        self.d.from_numpy(np.zeros((B, N), np.float32))
        self.dtil.from_numpy(np.zeros((B, N), np.float32))
        self._slot_mask.from_numpy(np.ones(B, np.int32))
        self._wipe_grid()

    def set_frame(self, dt: np.ndarray, nsub: np.ndarray, kin: np.ndarray, damage_on: bool,
                  damping: float = 0.0) -> None:
        """Per-run dt (B,), substep counts (B,), kinematic table (B, K, n_kinematic, 6) of the next frame,
        whether damage evolves, and the grid velocity damping rate (1/s; settling only)."""
        B = self.batch
        # each host -> device copy costs a round trip on CUDA: per-run values that did not change since
        # the last frame or chunk (damping, damage switch, dt) are not sent again
        self._upload_if_changed("damp", np.broadcast_to(np.asarray(damping, np.float32), (B,)).copy())
        self._upload_if_changed("don", (np.broadcast_to(np.asarray(damage_on), (B,)) != 0).astype(np.int32)
                                * np.int32(self.options.damage))
        self._upload_if_changed("dt", dt.astype(np.float32))
        self.upload(self.nsub, nsub)
        self._nsub_max = int(np.max(nsub, initial=0))
        B, K = kin.shape[:2]
        table = np.zeros((B, K, self.nk1, 6), np.float32)
        table[:, :, :kin.shape[2]] = kin
        if self.kin.shape != table.shape:
            self.kin = ti.ndarray(ti.f32, table.shape)
        self.upload(self.kin, table)

    def particle_array(self, name: str) -> np.ndarray:
        """Particle array ``name`` (``x``, ``v``, ``C``, ``F``, ``d``, ``dtil``, ``sid``) on the host, run-major in
        the device's particle order: ``(B, N, ...)``, matrices ``(B, N, 3, 3)`` whatever their device layout."""
        values = self.host_copy(getattr(self, name))
        if name in MATRIX_STATE and self.component_major:
            B, _, N = values.shape
            return np.ascontiguousarray(values.transpose(0, 2, 1)).reshape(B, N, 3, 3)
        return values

    def set_particle_array(self, name: str, values: np.ndarray) -> None:
        """Write particle array ``name`` from host ``values`` shaped as :meth:`particle_array` returns them."""
        values = np.asarray(values, np.float32 if name != "sid" else np.int32)
        if name in MATRIX_STATE and self.component_major:
            values = values.reshape(values.shape[0], values.shape[1], 9).transpose(0, 2, 1)
        getattr(self, name).from_numpy(np.ascontiguousarray(values))

    def _upload_if_changed(self, name: str, values: np.ndarray) -> None:
        last = self._uploaded.get(name)
        if last is None or not np.array_equal(last, values):
            self.upload(getattr(self, name), values)
            self._uploaded[name] = values

    def _stage_value(self, name: str, k: int):
        """The value of substep argument ``name`` (``_STAGE_ARGS``) at substep ``k``."""
        if name == "k":
            return k
        scalar = self._scalars.get(name)
        return scalar[1] if scalar is not None else getattr(self, name)

    def _stages(self, k: int) -> dict[str, object]:
        """The substep's kernel launches in order, by stage name (each a no-argument callable); with ``fused``,
        ``fclear`` (once per advance), ``fused`` and ``fgrid``."""
        return {stage: (lambda kern=self._kernel_of[stage], names=names:
                        kern(*(self._stage_value(n, k) for n in names)))
                for stage, names in self._stage_args.items()}

    def _substep_graph(self, steps: int, stages: tuple[str, ...]):
        """A Taichi graph of ``steps`` substeps of ``stages`` each (substep ``s`` runs at ``k = k<s>``), compiled
        once per size and stages.

        A substep is four kernel launches of ~20 array arguments each; from Python they cost ~0.6-1.7 ms of host
        time per substep (measured on an H100 host), more than the GPU needs for a substep of <= 16 runs. A
        graph binds its arguments once per run and launches the same kernels in the same order from C++
        (~0.2 ms per substep). Whole lock-step batches did not get faster (the host queues a frame's tail while
        the GPU works on its full substeps); the host is freed for feature extraction and chunk round trips."""
        graph = self._graphs.get((steps, stages))
        if graph is None:
            from taichi import graph as tg

            symbols: dict[str, object] = {}

            def symbol(name: str, s: int):
                key = f"k{s}" if name == "k" else name
                if key not in symbols:
                    if name == "k" or name in self._scalars:
                        dtype = ti.i32 if name == "k" else self._scalars[name][0]
                        symbols[key] = tg.Arg(tg.ArgKind.SCALAR, key, dtype)
                    else:
                        arr = getattr(self, name)
                        symbols[key] = tg.Arg(tg.ArgKind.NDARRAY, key, dtype=_element_type(arr), ndim=len(arr.shape))
                return symbols[key]

            builder = tg.GraphBuilder()
            for s in range(steps):
                for stage in stages:
                    builder.dispatch(self._kernel_of[stage], *(symbol(n, s) for n in self._stage_args[stage]))
            graph = self._graphs[(steps, stages)] = builder.compile()
        return graph

    def _bound_args(self, stages: tuple[str, ...]) -> tuple[tuple[str, ...], bool]:
        """The arguments but ``k`` that a graph of ``stages`` binds, each once, and whether it takes ``k``
        (computed once per stages: a graph launch binds one precomputed tuple of names)."""
        bound = self._bound.get(stages)
        if bound is None:
            names = [n for st in stages for n in self._stage_args[st]]
            bound = self._bound[stages] = (tuple(dict.fromkeys(n for n in names if n != "k")), "k" in names)
        return bound

    def _run_graph(self, steps: int, k0: int, stages: tuple[str, ...] | None = None) -> None:
        stages = stages or self._plain_stages
        names, takes_k = self._bound_args(stages)
        values = {n: self._stage_value(n, k0) for n in names}
        if takes_k:
            values.update({f"k{s}": k0 + s for s in range(steps)})
        self._substep_graph(steps, stages).run(values)

    def advance(self, n_steps: int) -> None:
        """Run substeps 0..n_steps-1 of the current frame (runs past their own nsub idle): graphs of
        ``GRAPH_SUBSTEPS`` substeps, then single ones for the rest (re-sorting the particles first when
        ``resort_every`` substeps have passed since the last sort). With ``fused``, the grid buffers' clear
        first and a last g2p after them: the particles are whole substeps on when it returns."""
        if self.resorter is not None:
            self.resorter.count(n_steps)
        if n_steps <= 0:
            return
        if self.fused and n_steps < self._nsub_max:   # its last g2p would leave runs mid-substep
            raise InvphysError(f"the fused substep advances whole frames: advance({n_steps}) is short of the "
                               f"frame's {self._nsub_max} substeps")
        stages = ("fused", "fgrid") if self.fused else None
        if self.fused:
            self._run_graph(1, 0, ("fclear",))
        k = 0
        while n_steps - k >= GRAPH_SUBSTEPS:
            self._run_graph(GRAPH_SUBSTEPS, k, stages)
            k += GRAPH_SUBSTEPS
        for rest in range(k, n_steps):
            self._run_graph(1, rest, stages)
        if self.fused:
            self._run_graph(1, n_steps, ("fused",))

    def kernel_times(self, n_steps: int = 20) -> dict[str, float]:
        """Mean seconds per launch of each substep stage over ``n_steps`` synchronised substeps (profiling;
        advances the state, so use a throw-away batch). With ``fused``, substeps ``k = 1 .. 6`` over and over (a
        G2P2G each; the frame's ``nsub`` at least 7), after one ``fclear`` and the scatter of ``k = 0``."""
        import time

        total: dict[str, float] = {}
        if self.fused:
            for launch in self._stages(0).values():
                launch()
        for i in range(n_steps):
            k = 1 + i % 6 if self.fused else 0   # 6: both buffers' and all slots' cycles
            for name, launch in self._stages(k).items():
                if name == "fclear":
                    continue
                ti.sync()
                t0 = time.perf_counter()
                launch()
                ti.sync()
                total[name] = total.get(name, 0.0) + time.perf_counter() - t0
        return {k: v / n_steps for k, v in total.items()}

    def load_slots(self, slots: np.ndarray, table: np.ndarray, friction: np.ndarray) -> None:
        """Reset only runs ``slots`` (indices) to the initial state with materials ``table``
        (len(slots), n_bodies, N_MAT) and frictions (len(slots), n_colliders); the others are untouched."""
        slots = np.asarray(slots, np.int64)
        self._mat_host[slots] = table
        self._fric_host[slots, :self.ncol] = friction
        self.upload(self.mat, self._mat_host)
        self.upload(self.fric, self._fric_host)
        mask = np.zeros(self.batch, np.int32)
        mask[slots] = 1
        self.upload(self._slot_mask, mask)
        self._reset(self._slot_mask, self.perm0, self.x0, self.sid, self.x, self.v, self.C, self.F, self.d, self.dtil)
        self._wipe_grid()

    def _wipe_grid(self) -> None:
        """Zero the whole grid of the runs in ``_slot_mask``."""
        self._wipe(self._slot_mask, max(self.ngrip, 1), self.gv, self.gm, self.gd, self.gg, self.box)

    def read_slots(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions (n, N, 3) and damage (n, N) of runs ``slots`` only, in the scene's particle order (a
        device gather, then one copy into new host arrays)."""
        xo, do = self._gather_slots(slots)
        return self.host_copy(xo), self.host_copy(do)

    def read_slots_later(self, slots: np.ndarray):
        """:meth:`read_slots` as a handle whose ``result()`` gives ``(x, d)``: on CUDA the copy back runs on a
        stream of its own while the host launches the next chunk (``LaterCopies``); elsewhere it is read now."""
        xo, do = self._gather_slots(slots)
        return self.later.start((xo, do))

    def _gather_slots(self, slots: np.ndarray) -> tuple:
        """Gather runs ``slots``' positions and damage, in the scene's order, into the device buffers of that
        many runs (after the read in flight from them, if any, is complete)."""
        self.later.settle()
        slots = np.asarray(slots, np.int32)
        n, N = len(slots), self.scene.n_particles
        if n not in self._gather_bufs:
            self._gather_bufs[n] = (ti.ndarray(ti.i32, (n,)), ti.ndarray(vec3, (n, N)), ti.ndarray(ti.f32, (n, N)))
        idx, xo, do = self._gather_bufs[n]
        self.upload(idx, slots)
        self._gather(idx, self.sid, self.x, self.d, xo, do)
        return xo, do

    def frame_stats(self, lo: float, hi: float, slots: np.ndarray | None = None) -> np.ndarray:
        """(B, n_stats) statistics of the current state (columns: :mod:`invphys_anisompm.failure`); with
        ``slots``, only those runs' rows are computed (the others are zero)."""
        mask = np.ones(self.batch, np.int32)
        if slots is not None:
            mask[:] = 0
            mask[np.asarray(slots, np.int64)] = 1
        self.upload(self._stats_mask, mask)
        self.stats_out.fill(0.0)
        self._stats(lo, hi, self._stats_mask, self.mat, self.body, self.vol, self.sid, self.x, self.v, self.F, self.d,
                    self.stats_acc, self.stats_out)
        return self.host_copy(self.stats_out).astype(np.float64)

    def frame_end(self, lo: float, hi: float, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``frame_stats(lo, hi, slots)`` and ``kinematic_sums(slots)`` in one launch and one copy back:
        (stats (B, n_stats), impulse (len(slots), n_kin, 3), work (len(slots), n_kin))."""
        slots = np.asarray(slots, np.int64)
        mask = np.zeros(self.batch, np.int32)
        mask[slots] = 1
        self.upload(self._stats_mask, mask)
        n, ns = self.ngrip + self.ncol, self.nstats
        self._frame_end(lo, hi, self._stats_mask, ns, n, self.mat, self.body, self.vol, self.sid, self.x, self.v, self.F,
                        self.d, self.imp, self.work, self.stats_acc, self.end_out)
        out = self.host_copy(self.end_out).astype(np.float64)
        sums = out[slots, ns:ns + 4 * n].reshape(len(slots), n, 4)
        return out[:, :ns], sums[..., :3], sums[..., 3]

    def kinematic_sums(self, slots: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(impulse (B, n_kin, 3) the material gave each kinematic object, work (B, n_kin) the objects did
        on the material) since the last call; the accumulators are reset. With ``slots``, only those
        runs' rows are returned (len(slots), ...) and reset; the others keep accumulating on the device
        (continuous batching reads a run's sums once per frame, as the lock-step path does)."""
        n = self.ngrip + self.ncol
        imp_all, work_all = self.host_copy(self.imp), self.host_copy(self.work)
        if slots is None:
            self.imp.fill(0.0)
            self.work.fill(0.0)
            return imp_all.astype(np.float64)[:, :n], work_all.astype(np.float64)[:, :n]
        slots = np.asarray(slots, np.int64)
        imp, work = imp_all[slots, :n].astype(np.float64), work_all[slots, :n].astype(np.float64)
        imp_all[slots] = 0.0
        work_all[slots] = 0.0
        self.imp.from_numpy(imp_all)
        self.work.from_numpy(work_all)
        return imp, work

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions (B, N, 3) and damage (B, N), float32, in the scene's particle order (new host arrays)."""
        if self._perm is None:
            return self.host_copy(self.x), self.host_copy(self.d)
        return self.read_slots(np.arange(self.batch))

    def grid_mass(self) -> np.ndarray:
        """(B,) total grid mass deposited by the last P2G (equals the particle mass: a check)."""
        # with the fused substep, the other buffer holds no mass after ``advance`` (see ``fused_grid``)
        gm = self.host_copy(self.gm).astype(np.float64)
        return gm.reshape(-1, self.batch, gm[0].size).sum(axis=(0, 2))

    def sync(self) -> None:
        ti.sync()
