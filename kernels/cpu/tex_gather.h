// The bilinear fetch of lane_texture (lane_math.h) for 8 float lanes with AVX2 gathers: 12 vector loads (four taps,
// three channels) instead of a scalar loop over lanes and taps, which cost a textured render twice an untextured one.
// The same products and sums in the same order as the scalar loop, so the same bits. Compiled for AVX2 whatever the
// build's baseline, and called only where the CPU has it (have_avx2_gather()); CTGS_CPU_GATHER=0 turns it off.
#pragma once

#include <cstdint>
#include <cstdlib>

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__)) && !defined(CTGS_NO_GATHER)
#define CTGS_AVX2_GATHER 1
#include <immintrin.h>
#endif

namespace ctgs {
namespace cpu {

#ifdef CTGS_AVX2_GATHER
// Whether the CPU has AVX2 and CTGS_CPU_GATHER=0 does not ask for the lane-by-lane fetch (read once per process).
inline bool have_avx2_gather() {
  static const bool yes = [] {
    const char* env = std::getenv("CTGS_CPU_GATHER");
    return __builtin_cpu_supports("avx2") && !(env != nullptr && env[0] == '0');
  }();
  return yes;
}

// flu, flv: floor of the texel coordinates (integral, in [-1, res - 1] where active; 0 elsewhere); act: -1 where the
// lookup is active; wt: [4][8] the taps' bilinear weights; tex_off, res_u, res_v: the primitive's texture block.
// Writes tex [3][8] (the fetched colour, 0 where inactive) and, if texel is not null, texel [4][3][8] (each tap's
// values, 0 outside the grid) and rows [4][8] (each tap's texel row, -1 outside the grid or where inactive).
__attribute__((target("avx2"), noinline)) inline void fetch_taps_avx2(
    const float* flu, const float* flv, const int32_t* act, const float* wt, int res_u, int res_v, long long tex_off,
    const float* textures, float* tex, float* texel, long long* rows) {
  const __m256i u0 = _mm256_cvttps_epi32(_mm256_load_ps(flu));  // integral values: exact
  const __m256i v0 = _mm256_cvttps_epi32(_mm256_load_ps(flv));
  const __m256i on = _mm256_load_si256(reinterpret_cast<const __m256i*>(act));
  const __m256i minus1 = _mm256_set1_epi32(-1);
  const __m256i in_u0 = _mm256_cmpgt_epi32(u0, minus1);                         // u0 >= 0
  const __m256i in_u1 = _mm256_cmpgt_epi32(_mm256_set1_epi32(res_u - 1), u0);   // u0 + 1 < res_u
  const __m256i in_v0 = _mm256_and_si256(on, _mm256_cmpgt_epi32(v0, minus1));
  const __m256i in_v1 = _mm256_and_si256(on, _mm256_cmpgt_epi32(_mm256_set1_epi32(res_v - 1), v0));
  const __m256i mask[4] = {_mm256_and_si256(in_u0, in_v0), _mm256_and_si256(in_u1, in_v0),
                           _mm256_and_si256(in_u0, in_v1), _mm256_and_si256(in_u1, in_v1)};
  const __m256i rel = _mm256_add_epi32(_mm256_mullo_epi32(v0, _mm256_set1_epi32(res_u)), u0);  // row - tex_off
  const int step[4] = {0, 1, res_u, res_u + 1};
  const float* base = textures + 3 * tex_off;
  const __m256 zero = _mm256_setzero_ps();
  __m256 sum[3];
  for (int t = 0; t < 4; ++t) {
    const __m256i r = _mm256_add_epi32(rel, _mm256_set1_epi32(step[t]));
    const __m256i idx = _mm256_add_epi32(_mm256_add_epi32(r, r), r);  // 3 r: the tap's first channel
    const __m256 m = _mm256_castsi256_ps(mask[t]);
    const __m256 w = _mm256_load_ps(wt + 8 * t);
    for (int c = 0; c < 3; ++c) {
      // masked-off lanes read nothing (their addresses may lie outside the block)
      const __m256 val = _mm256_mask_i32gather_ps(zero, base + c, idx, m, 4);
      const __m256 p = _mm256_mul_ps(w, val);
      sum[c] = t == 0 ? p : _mm256_add_ps(sum[c], p);
      if (texel) _mm256_store_ps(texel + 8 * (3 * t + c), val);
    }
    if (rows) {
      const __m256i off = _mm256_set1_epi64x(tex_off);
      const __m256i all = _mm256_set1_epi64x(-1);
      for (int h = 0; h < 2; ++h) {
        const __m128i r4 = h ? _mm256_extracti128_si256(r, 1) : _mm256_castsi256_si128(r);
        const __m128i m4 = h ? _mm256_extracti128_si256(mask[t], 1) : _mm256_castsi256_si128(mask[t]);
        const __m256i row = _mm256_add_epi64(_mm256_cvtepi32_epi64(r4), off);
        const __m256i m64 = _mm256_cvtepi32_epi64(m4);
        _mm256_storeu_si256(reinterpret_cast<__m256i*>(rows + 8 * t + 4 * h), _mm256_blendv_epi8(all, row, m64));
      }
    }
  }
  for (int c = 0; c < 3; ++c) _mm256_store_ps(tex + 8 * c, sum[c]);
}
#endif

}  // namespace cpu
}  // namespace ctgs
