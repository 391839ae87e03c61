"""Re-sorting a Taichi batch's particles, run by run, into the curve order of the cells they are in now.

The tiled scatter sums tiles of 256 consecutive particles over their bounding box of nodes. A run starts in
the Hilbert (or Morton) order of the initial cells (``particle_order.py``); as the orange deforms and tears,
a tile's particles drift apart and more tiles fall back to global atomics (16 % by frame 240 against 2 % at
rest; ``docs/gpu-throughput.md``). :class:`ParticleResorter` puts each run's particles back in the curve
order of their current base cells: a Taichi kernel writes every particle's curve index, PyTorch sorts each
run's indices on the device (stable), and a second kernel gathers the state (x, v, C, F, d, dtil) and the
scene index ``sid`` into spare arrays, which then swap with the live ones. The per-particle constants
(body, fibre, volume, grip, rest position) stay in the scene's order and are read through ``sid``, so a
sort moves only per-run state; reads return the scene's order whatever the sorts did.
"""


import taichi as ti

from invphys_anisompm.backends.taichi_common import _element_type, load_mat3, matrix_nd, store_mat3

vec3 = ti.math.vec3
ND = ti.types.ndarray
#: the per-run particle arrays a sort permutes (the backend's attribute names)
SORTED_ARRAYS = ("x", "v", "C", "F", "d", "dtil", "sid")


def _curve_index(curve: str, bits: int):
    """A Taichi function: the index of cell ``c`` (3 int32 coordinates below ``2**bits``) along ``curve``, as
    :func:`~invphys_anisompm.backends.particle_order.hilbert_index` or the Morton code computes it."""

    @ti.func
    def morton(c):
        code = ti.i64(0)
        for bit in ti.static(range(bits)):
            for a in ti.static(range(3)):
                code |= ti.cast((c[a] >> bit) & 1, ti.i64) << (3 * bit + a)
        return code

    @ti.func
    def hilbert(c):  # Skilling's transpose algorithm, unrolled over the bits
        x = c
        for level in ti.static(range(bits - 1, 0, -1)):
            q = ti.static(1 << level)
            for i in ti.static(range(3)):
                if x[i] & q != 0:
                    x[0] ^= q - 1
                else:
                    t = (x[0] ^ x[i]) & (q - 1)
                    x[0] ^= t
                    x[i] ^= t
        x[1] ^= x[0]
        x[2] ^= x[1]
        flip = 0
        for level in ti.static(range(bits - 1, 0, -1)):
            if x[2] & (1 << level) != 0:
                flip ^= (1 << level) - 1
        for i in ti.static(range(3)):
            x[i] ^= flip
        index = ti.i64(0)
        for bit in ti.static(range(bits - 1, -1, -1)):
            for i in ti.static(range(3)):
                index = (index << 1) | ti.cast((x[i] >> bit) & 1, ti.i64)
        return index

    return hilbert if curve == "hilbert" else morton


def _build_resort_kernels(grid: int, curve: str, component_major: bool = False):
    """The key and gather kernels for grid size ``grid``, ``curve`` and the particle matrices' layout
    (compile-time constants)."""
    curve_index = _curve_index(curve, int(grid).bit_length())
    MND = matrix_nd(component_major)

    @ti.kernel
    def curve_keys(inv_dx: ti.f32, x: ND(vec3, 2), keys: ND(ti.i64, 2)):
        for b, p in x:
            base = ti.math.clamp(ti.cast(x[b, p] * inv_dx - 0.5, ti.i32), 0, grid - 3)
            keys[b, p] = curve_index(base)

    @ti.kernel
    def gather_sorted(order: ND(ti.i32, 2), x: ND(vec3, 2), v: ND(vec3, 2), C: MND, F: MND,
                      d: ND(ti.f32, 2), dtil: ND(ti.f32, 2), sid: ND(ti.i32, 2), xo: ND(vec3, 2), vo: ND(vec3, 2),
                      Co: MND, Fo: MND, do: ND(ti.f32, 2), dtilo: ND(ti.f32, 2),
                      sido: ND(ti.i32, 2)):
        for b, p in xo:
            q = order[b, p]
            xo[b, p] = x[b, q]
            vo[b, p] = v[b, q]
            store_mat3(Co, b, p, load_mat3(C, b, q))
            store_mat3(Fo, b, p, load_mat3(F, b, q))
            do[b, p] = d[b, q]
            dtilo[b, p] = dtil[b, q]
            sido[b, p] = sid[b, q]

    return curve_keys, gather_sorted


_KERNELS: dict[tuple[int, str, bool], tuple] = {}


class ParticleResorter:
    """Re-sorts a :class:`~invphys_anisompm.backends.taichi_backend.TaichiBackend`'s runs every ``every``
    substeps (counted by :meth:`count`); :meth:`sort` does it now."""

    def __init__(self, backend, curve: str, every: int) -> None:
        self.backend = backend
        self.curve = curve
        self.every = int(every)
        self.since = 0
        self.sorts = 0
        key = (int(backend.options.grid), curve, bool(backend.component_major))
        if key not in _KERNELS:
            _KERNELS[key] = _build_resort_kernels(*key)
        self._keys_kernel, self._gather = _KERNELS[key]
        self._spare: dict[str, object] | None = None
        self._keys = None

    def count(self, steps: int) -> None:
        """Note ``steps`` substeps about to be launched; sort first if ``every`` substeps have passed."""
        if self.every > 0 and self.since >= self.every:
            self.sort()
        self.since += int(steps)

    def sort(self) -> None:
        """Put every run's particles in the curve order of their current base cells (device work only)."""
        import torch

        be = self.backend
        B, N = be.batch, be.scene.n_particles
        device = "cuda" if be.arch == "cuda" else "cpu"
        if self._spare is None:
            self._spare = {name: ti.ndarray(_element_type(getattr(be, name)), tuple(getattr(be, name).shape))
                           for name in SORTED_ARRAYS}
            self._keys = torch.empty((B, N), dtype=torch.int64, device=device)
        self._keys_kernel(1.0 / float(be.options.dx), be.x, self._keys)
        order = torch.sort(self._keys, dim=1, stable=True).indices.to(torch.int32).contiguous()
        live = [getattr(be, name) for name in SORTED_ARRAYS]
        spare = [self._spare[name] for name in SORTED_ARRAYS]
        self._gather(order, *live, *spare)
        for name, new, old in zip(SORTED_ARRAYS, spare, live, strict=True):
            setattr(be, name, new)
            self._spare[name] = old
        self.since = 0
        self.sorts += 1


__all__ = ["SORTED_ARRAYS", "ParticleResorter"]
