#!/usr/bin/env bash
# Device check (issue 16): what a float atomic add to shared memory compiles to on this GPU. The tiled P2G sums
# each particle's 27-node contributions with shared-memory float atomics (Taichi emits `atom.shared.add.f32`);
# if the SASS is a compare-and-swap loop (ATOMS.CAST.SPIN) rather than one instruction, each of those adds
# costs a load, an add, a CAS and a branch. Needs ptxas and cuobjdump (CUDA toolkit). Output: $OUT/shared_atomic_sass.txt
set -e
OUTDIR=${OUT:-/tmp}; CUDA=${CUDA_HOME:-/usr/local/cuda}
cc=$(nvidia-smi --query-gpu=compute_cap --format=csv,noheader | head -1 | tr -d .)
tmp=$(mktemp -d)
for ty in f32 u32; do
cat > "$tmp/k_$ty.ptx" <<PTX
.version 7.8
.target sm_$cc
.address_size 64
.visible .entry k(.param .u64 p, .param .$ty v)
{
  .shared .align 4 .b8 s[4096];
  .reg .b32 %r<6>;
  .reg .$ty %f<3>;
  .reg .b64 %rd<4>;
  mov.u32 %r1, %tid.x;
  and.b32 %r1, %r1, 1023;
  shl.b32 %r2, %r1, 2;
  mov.u32 %r3, s;
  add.u32 %r4, %r3, %r2;
  ld.param.$ty %f1, [v];
  red.shared.add.$ty [%r4], %f1;
  bar.sync 0;
  ld.shared.$ty %f2, [%r4];
  ld.param.u64 %rd1, [p];
  cvta.to.global.u64 %rd2, %rd1;
  mul.wide.u32 %rd3, %r1, 4;
  add.u64 %rd2, %rd2, %rd3;
  st.global.$ty [%rd2], %f2;
  ret;
}
PTX
"$CUDA/bin/ptxas" -arch=sm_$cc "$tmp/k_$ty.ptx" -o "$tmp/k_$ty.cubin"
echo "== red.shared.add.$ty on sm_$cc ($(nvidia-smi --query-gpu=name --format=csv,noheader | head -1))"
"$CUDA/bin/cuobjdump" -sass "$tmp/k_$ty.cubin" | grep -E "ATOMS|BRA|LDS|STS|BAR" || true
done | tee "$OUTDIR/shared_atomic_sass.txt"
