// Fixed-width lane vectors for the CPU rasterizer: consecutive pixels of one tile row are processed
// together (the per-pixel blending state is independent across pixels). GCC/Clang generic vectors of 32
// bytes (8 floats or 4 doubles): the compiler lowers them to whatever the target has (two SSE2
// registers on baseline x86-64, one AVX2 register in the avx2 clone, NEON pairs on arm64). Every lane
// does the same IEEE operations in the same order whatever the lowering (the build disables FMA
// contraction), so results do not depend on the instruction set, and forward and backward, which call
// the same functions, recompute bit-identical alphas.
#pragma once

#include <math.h>

#include <cstdint>
#include <cstring>

// Passing 32-byte vectors by value changes the ABI between the baseline and AVX builds; every function
// here is inlined (CTGS_INLINE) and none crosses a translation unit, so the note does not apply.
#pragma GCC diagnostic ignored "-Wpsabi"

namespace ctgs {
namespace cpu {

template <typename S>
struct Lanes;

template <>
struct Lanes<float> {
  static constexpr int W = 8;
  typedef float V __attribute__((vector_size(32)));
  typedef int32_t I __attribute__((vector_size(32)));  // comparison masks (-1 / 0) and integers
  typedef int32_t Int;                                  // the lane integer type
};

template <>
struct Lanes<double> {
  static constexpr int W = 4;
  typedef double V __attribute__((vector_size(32)));
  typedef int64_t I __attribute__((vector_size(32)));
  typedef int64_t Int;
};

// The raster loops are compiled twice on x86-64 Linux (baseline and AVX2, chosen at run time by the
// loader): the same lane code, two lowerings, bit-identical results. Elsewhere one portable build.
#if defined(__x86_64__) && defined(__linux__) && (defined(__GNUC__) || defined(__clang__)) && \
    !defined(CTGS_NO_MULTIVERSION)
#define CTGS_LANE_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define CTGS_LANE_CLONES
#endif

#define CTGS_INLINE inline __attribute__((always_inline))

template <typename V>
CTGS_INLINE V vload(const void* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}

template <typename V>
CTGS_INLINE void vstore(void* p, V v) {
  std::memcpy(p, &v, sizeof(V));
}

template <typename S>
CTGS_INLINE typename Lanes<S>::V splat(S x) {
  return typename Lanes<S>::V{} + x;
}

// m ? a : b per lane, m a comparison mask (all bits set or clear).
template <typename V, typename I>
CTGS_INLINE V sel(I m, V a, V b) {
  return (V)((m & (I)a) | (~m & (I)b));
}

template <typename I>
CTGS_INLINE I seli(I m, I a, I b) {
  return (m & a) | (~m & b);
}

template <typename S>
CTGS_INLINE typename Lanes<S>::V vmin(typename Lanes<S>::V a, typename Lanes<S>::V b) {
  return sel(a < b, a, b);
}

template <typename S>
CTGS_INLINE typename Lanes<S>::V vmax(typename Lanes<S>::V a, typename Lanes<S>::V b) {
  return sel(a > b, a, b);
}

template <typename S>
CTGS_INLINE typename Lanes<S>::V vabs(typename Lanes<S>::V a) {
  return sel(a < S(0), -a, a);
}

template <typename I>
CTGS_INLINE bool any(I m) {
  I z{};
  return std::memcmp(&m, &z, sizeof(I)) != 0;
}

// Sum of the lanes, in lane order.
template <typename S>
CTGS_INLINE S hsum(typename Lanes<S>::V v) {
  S s = v[0];
  for (int k = 1; k < Lanes<S>::W; ++k) s += v[k];
  return s;
}

// floor() for |x| < 2^31 (callers clamp first): truncate, then step down where that rounded up.
template <typename S>
CTGS_INLINE typename Lanes<S>::V vfloor(typename Lanes<S>::V x) {
  using L = Lanes<S>;
  const typename L::V t = __builtin_convertvector(__builtin_convertvector(x, typename L::I), typename L::V);
  return t - sel(t > x, splat(S(1)), splat(S(0)));
}

// exp(x) for x in [-87, 0] (callers clamp: the rasterizer needs exp(-rho/2), rho in [0, CUTOFF_RHO]).
// float: Cody-Waite reduction x = k ln2 + r, |r| <= ln2/2, and the Cephes expf polynomial (max error
// ~1 ulp, like the vectorised exp PyTorch uses); double: the C library's exp per lane (the float64 path
// is the test path, where agreement with the reference to ~1e-15 matters more than speed).
CTGS_INLINE Lanes<float>::V vexp(Lanes<float>::V x) {
  using V = Lanes<float>::V;
  using I = Lanes<float>::I;
  const V fk = vfloor<float>(x * 1.44269504088896341f + 0.5f);
  V r = x - fk * 0.693359375f;
  r = r - fk * -2.12194440e-4f;
  V p = splat(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * (r * r) + r + 1.0f;
  const I e = (__builtin_convertvector(fk, I) + 127) << 23;  // 2^k, k in [-126, 0]
  return p * (V)e;
}

CTGS_INLINE Lanes<double>::V vexp(Lanes<double>::V x) {
  Lanes<double>::V out;
  for (int k = 0; k < Lanes<double>::W; ++k) out[k] = exp(x[k]);
  return out;
}

}  // namespace cpu
}  // namespace ctgs
