// Arithmetic the compiler may not contract into fused multiply-adds, for the math whose result decides which
// (pixel, primitive) pairs blend: the forward and the backward kernel each recompute alpha (ctgs::surfel_alpha),
// and with FMA contraction allowed the same source line can be contracted one way in one kernel and another way in
// the other. On the GPU these are CUDA's round-to-nearest intrinsics, which are never contracted; on the CPU,
// plain operators (the CPU backend builds with -ffp-contract=off). Without contraction (-fmad=false) they equal the
// plain operators bit for bit.
#pragma once

#include "ctgs/vec3.h"

namespace ctgs {

#if defined(__CUDA_ARCH__)
__device__ inline float xmul(float a, float b) { return __fmul_rn(a, b); }
__device__ inline float xadd(float a, float b) { return __fadd_rn(a, b); }
__device__ inline float xsub(float a, float b) { return __fsub_rn(a, b); }
__device__ inline double xmul(double a, double b) { return __dmul_rn(a, b); }
__device__ inline double xadd(double a, double b) { return __dadd_rn(a, b); }
__device__ inline double xsub(double a, double b) { return __dsub_rn(a, b); }
#else
template <typename S>
inline S xmul(S a, S b) { return a * b; }
template <typename S>
inline S xadd(S a, S b) { return a + b; }
template <typename S>
inline S xsub(S a, S b) { return a - b; }
#endif

// a.x b.x + a.y b.y + a.z b.z, summed left to right as dot() does.
template <typename S>
HOST_DEVICE inline S xdot(const Vec3<S>& a, const Vec3<S>& b) {
  return xadd(xadd(xmul(a.x, b.x), xmul(a.y, b.y)), xmul(a.z, b.z));
}

}  // namespace ctgs
