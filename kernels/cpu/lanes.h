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

// The lane sums of several vectors, out[j] = hsum(v[j]) bit for bit (each in lane order): float vectors eight
// at a time by an 8x8 transpose and seven vertical adds (31 vector operations for eight sums instead of
// eight chains of seven scalar adds and extracts); double vectors one by one (the test path).
CTGS_INLINE void hsums(const Lanes<float>::V* v, int n, float* out) {
  using V = Lanes<float>::V;
  int j = 0;
  for (; j + 8 <= n; j += 8) {
    const V* a = v + j;
    const V t0 = __builtin_shufflevector(a[0], a[1], 0, 8, 1, 9, 4, 12, 5, 13);
    const V t1 = __builtin_shufflevector(a[0], a[1], 2, 10, 3, 11, 6, 14, 7, 15);
    const V t2 = __builtin_shufflevector(a[2], a[3], 0, 8, 1, 9, 4, 12, 5, 13);
    const V t3 = __builtin_shufflevector(a[2], a[3], 2, 10, 3, 11, 6, 14, 7, 15);
    const V t4 = __builtin_shufflevector(a[4], a[5], 0, 8, 1, 9, 4, 12, 5, 13);
    const V t5 = __builtin_shufflevector(a[4], a[5], 2, 10, 3, 11, 6, 14, 7, 15);
    const V t6 = __builtin_shufflevector(a[6], a[7], 0, 8, 1, 9, 4, 12, 5, 13);
    const V t7 = __builtin_shufflevector(a[6], a[7], 2, 10, 3, 11, 6, 14, 7, 15);
    const V s0 = __builtin_shufflevector(t0, t2, 0, 1, 8, 9, 4, 5, 12, 13);
    const V s1 = __builtin_shufflevector(t0, t2, 2, 3, 10, 11, 6, 7, 14, 15);
    const V s2 = __builtin_shufflevector(t1, t3, 0, 1, 8, 9, 4, 5, 12, 13);
    const V s3 = __builtin_shufflevector(t1, t3, 2, 3, 10, 11, 6, 7, 14, 15);
    const V s4 = __builtin_shufflevector(t4, t6, 0, 1, 8, 9, 4, 5, 12, 13);
    const V s5 = __builtin_shufflevector(t4, t6, 2, 3, 10, 11, 6, 7, 14, 15);
    const V s6 = __builtin_shufflevector(t5, t7, 0, 1, 8, 9, 4, 5, 12, 13);
    const V s7 = __builtin_shufflevector(t5, t7, 2, 3, 10, 11, 6, 7, 14, 15);
    // r_k holds lane k of the eight vectors; summed r_0 + r_1 + ... in order, as hsum sums the lanes.
    V acc = __builtin_shufflevector(s0, s4, 0, 1, 2, 3, 8, 9, 10, 11);
    acc = acc + __builtin_shufflevector(s1, s5, 0, 1, 2, 3, 8, 9, 10, 11);
    acc = acc + __builtin_shufflevector(s2, s6, 0, 1, 2, 3, 8, 9, 10, 11);
    acc = acc + __builtin_shufflevector(s3, s7, 0, 1, 2, 3, 8, 9, 10, 11);
    acc = acc + __builtin_shufflevector(s0, s4, 4, 5, 6, 7, 12, 13, 14, 15);
    acc = acc + __builtin_shufflevector(s1, s5, 4, 5, 6, 7, 12, 13, 14, 15);
    acc = acc + __builtin_shufflevector(s2, s6, 4, 5, 6, 7, 12, 13, 14, 15);
    acc = acc + __builtin_shufflevector(s3, s7, 4, 5, 6, 7, 12, 13, 14, 15);
    vstore(out + j, acc);
  }
  for (; j < n; ++j) out[j] = hsum<float>(v[j]);
}
CTGS_INLINE void hsums(const Lanes<double>::V* v, int n, double* out) {
  for (int j = 0; j < n; ++j) out[j] = hsum<double>(v[j]);
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
