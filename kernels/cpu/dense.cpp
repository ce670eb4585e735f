// Dense per-element training work on the CPU, one pass each instead of a chain of PyTorch ops (at 1-2M
// texels every [T, 3] pass and temporary of the optimiser and the texture regulariser showed in the
// profile):
//  - adam_step: Adam on one parameter tensor in place (p, m, v), counting non-finite results so the
//    trainer's NaN guard needs no scan of its own;
//  - texel_l1: sum over primitives of weight[i] x the sum over i's texels of |2 sigmoid(raw) - 1| (the
//    activated texel offsets, ctgs/model/surfels.py) and its gradient w.r.t. raw.
#include <omp.h>

#include <algorithm>
#include <cstring>
#include <cmath>

#include "dense.h"
#include "lanes.h"

namespace ctgs {
namespace cpu {

namespace {
// Elements per OpenMP chunk: large enough that scheduling costs nothing, small enough to balance.
constexpr int64_t CHUNK = 1 << 14;
}  // namespace

namespace {
// One chunk of Adam. The per-element lr is a template argument, not a test inside the loop: with the test
// there GCC left the loop scalar (4.5 ms for 2.4M texel values at 1 thread on the dev VM, against 1.1 ms
// like this, close to the 0.95 ms any pass over the same four arrays takes). Same expression, same order:
// the results are the scalar loop's, bit for bit (IEEE division and square root are exact per element).
template <typename S, bool LR_VEC>
CTGS_INLINE int64_t adam_range(S* p, const S* g, S* m, S* v, int64_t k0, int64_t k1, const S* lr_vec, S lr_s,
                               S b1, S b2, S c1, S c2, S ibc1, S ibc2, S e) {
  int64_t b = 0;
#pragma omp simd reduction(+ : b)
  for (int64_t k = k0; k < k1; ++k) {
    const S gk = g[k];
    const S mk = b1 * m[k] + c1 * gk;
    const S vk = b2 * v[k] + c2 * (gk * gk);
    m[k] = mk;
    v[k] = vk;
    const S step = (LR_VEC ? lr_vec[k] : lr_s) * (mk * ibc1) / (std::sqrt(vk * ibc2) + e);
    const S pk = p[k] - step;
    p[k] = pk;
    b += !(pk - pk == S(0));  // NaN or +-inf (x - x is NaN for both)
  }
  return b;
}

#define CTGS_ADAM_PART(S)                                                                                      \
  CTGS_LANE_CLONES int64_t adam_part(S* p, const S* g, S* m, S* v, int64_t k0, int64_t k1, const S* lr_vec, \
                                     S lr_s, S b1, S b2, S c1, S c2, S ibc1, S ibc2, S e) {                 \
    return lr_vec ? adam_range<S, true>(p, g, m, v, k0, k1, lr_vec, lr_s, b1, b2, c1, c2, ibc1, ibc2, e)   \
                  : adam_range<S, false>(p, g, m, v, k0, k1, lr_vec, lr_s, b1, b2, c1, c2, ibc1, ibc2, e); \
  }
CTGS_ADAM_PART(float)
CTGS_ADAM_PART(double)
#undef CTGS_ADAM_PART
}  // namespace

template <typename S>
int64_t adam_step(S* p, const S* g, S* m, S* v, int64_t n, const S* lr_vec, double lr, double beta1,
                  double beta2, double bc1, double bc2, double eps, int threads) {
  const S b1 = S(beta1), b2 = S(beta2), c1 = S(1 - beta1), c2 = S(1 - beta2);
  const S ibc1 = S(1) / S(bc1), ibc2 = S(1) / S(bc2), e = S(eps), lr_s = S(lr);
  int64_t bad = 0;
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads)) reduction(+ : bad)
  for (int64_t c0 = 0; c0 < n; c0 += CHUNK)
    bad += adam_part(p, g, m, v, c0, std::min(n, c0 + CHUNK), lr_vec, lr_s, b1, b2, c1, c2, ibc1, ibc2, e);
  return bad;
}

namespace {

// |tanh(x/2)| = |2 sigmoid(x) - 1| = (1 - e) / (1 + e) and d/dx = sign(x) 2e / (1 + e)^2 with
// e = exp(-|x|) in (0, 1]: no cancellation, exp's argument always <= 0 (lanes.h vexp's range).
// wgt: the primitive's weight; gradients are scaled by `scale` (= upstream gradient x wgt).
// Act: x are activated offsets already (y = tanh(raw / 2)): the value is |y|, the gradient sign(y).
template <typename S, bool Act>
CTGS_INLINE void l1_lanes(const S* x, S* grad, S wgt, S scale, typename Lanes<S>::V& acc) {
  using V = typename Lanes<S>::V;
  const V xv = vload<V>(x);
  if (Act) {
    const V one = splat(S(1));
    if (grad == nullptr) {
      acc += wgt * vabs<S>(xv);
    } else {
      const V sg = sel(xv > S(0), one, sel(xv < S(0), -one, splat(S(0))));
      vstore(grad, scale * sg);
    }
    return;
  }
  const V ax = vabs<S>(xv);
  const V arg = sel(ax < S(87), -ax, splat(S(-87)));  // exp(-87) ~ 1.6e-38: the rest rounds to 1 or 0 anyway
  const V e = vexp(arg);
  const V one = splat(S(1));
  if (grad == nullptr) {
    acc += wgt * ((one - e) / (one + e));
  } else {
    const V d = S(2) * e / ((one + e) * (one + e));
    const V s = sel(xv > S(0), one, sel(xv < S(0), -one, splat(S(0))));
    vstore(grad, scale * s * d);
  }
}

// For the primitives in [i0, i1): grad (if given) or the sum of weight[i] |tanh(raw/2)| over their texels.
template <typename S, bool Act>
CTGS_INLINE double texel_l1_range(const S* raw, const S* weight, const long long* tex_offset,
                                  const int* tex_res, int i0, int i1, S* grad, S scale) {
  using L = Lanes<S>;
  constexpr int W = L::W;
  typename L::V acc{};
  double total = 0.0;
  for (int i = i0; i < i1; ++i) {
    const int64_t cnt = 3 * int64_t(tex_res[2 * i]) * tex_res[2 * i + 1];
    if (cnt <= 0) continue;
    const int64_t off = 3 * tex_offset[i];
    const S wi = weight[i];
    if (wi == S(0)) {
      if (grad) std::fill(grad + off, grad + off + cnt, S(0));
      continue;
    }
    int64_t k = 0;
    const S gs_i = scale * wi;  // the gradient's factor for this primitive (w = 1: exactly `scale`)
    for (; k + W <= cnt; k += W) l1_lanes<S, Act>(raw + off + k, grad ? grad + off + k : nullptr, wi, gs_i, acc);
    if (k < cnt) {  // tail through a zero-padded copy (|tanh(0)| = 0, its gradient is dropped)
      alignas(32) S xs[W] = {}, gs[W];
      std::copy(raw + off + k, raw + off + cnt, xs);
      l1_lanes<S, Act>(xs, grad ? gs : nullptr, wi, gs_i, acc);
      if (grad) std::copy(gs, gs + (cnt - k), grad + off + k);
    }
    if (!grad && (i & 63) == 63) {  // flush to double now and then: float lanes would drift over 1e6 terms
      total += double(hsum<S>(acc));
      acc = typename L::V{};
    }
  }
  return total + double(hsum<S>(acc));
}

CTGS_LANE_CLONES double texel_l1_part(const float* raw, const float* weight, const long long* off, const int* res,
                                      int i0, int i1, float* grad, float scale, bool act) {
  return act ? texel_l1_range<float, true>(raw, weight, off, res, i0, i1, grad, scale)
             : texel_l1_range<float, false>(raw, weight, off, res, i0, i1, grad, scale);
}
CTGS_LANE_CLONES double texel_l1_part(const double* raw, const double* weight, const long long* off, const int* res,
                                      int i0, int i1, double* grad, double scale, bool act) {
  return act ? texel_l1_range<double, true>(raw, weight, off, res, i0, i1, grad, scale)
             : texel_l1_range<double, false>(raw, weight, off, res, i0, i1, grad, scale);
}

}  // namespace

template <typename S>
double texel_l1(const S* raw, const S* weight, const long long* tex_offset, const int* tex_res, int n_prims,
                S* grad, S scale, int threads, bool activated) {
  const int nt = std::max(1, threads);
  // Fixed blocks of primitives summed in block order: the result does not depend on the thread count.
  constexpr int BLOCK = 256;
  const int nb = (n_prims + BLOCK - 1) / BLOCK;
  std::vector<double> part(nb, 0.0);
#pragma omp parallel for schedule(dynamic, 4) num_threads(nt)
  for (int b = 0; b < nb; ++b)
    part[b] = texel_l1_part(raw, weight, tex_offset, tex_res, b * BLOCK, std::min(n_prims, (b + 1) * BLOCK), grad,
                            scale, activated);
  double total = 0.0;
  for (double v : part) total += v;
  return total;
}

namespace {

// y = sign(x) (1 - e) / (1 + e), e = exp(-|x|): tanh(|x| / 2) without cancellation.
template <typename S>
CTGS_INLINE typename Lanes<S>::V activation_lanes(typename Lanes<S>::V x) {
  using V = typename Lanes<S>::V;
  const V ax = vabs<S>(x);
  const V e = vexp(sel(ax < S(87), -ax, splat(S(-87))));
  const V one = splat(S(1));
  const V t = (one - e) / (one + e);
  return sel(x < S(0), -t, t);
}

template <typename S>
CTGS_INLINE void activation_range(const S* x, S* y, const S* gy, S* gx, int64_t k0, int64_t k1) {
  using V = typename Lanes<S>::V;
  constexpr int W = Lanes<S>::W;
  int64_t k = k0;
  for (; k + W <= k1; k += W) {
    if (gx == nullptr) {
      vstore(y + k, activation_lanes<S>(vload<V>(x + k)));
    } else {
      const V yv = vload<V>(y + k);
      vstore(gx + k, vload<V>(gy + k) * ((S(1) - yv) * (S(1) + yv) * S(0.5)));
    }
  }
  if (k < k1) {  // tail through zero-padded copies
    alignas(32) S a[W] = {}, b[W] = {};
    if (gx == nullptr) {
      std::copy(x + k, x + k1, a);
      vstore(b, activation_lanes<S>(vload<V>(a)));
      std::copy(b, b + (k1 - k), y + k);
    } else {
      std::copy(y + k, y + k1, a);
      std::copy(gy + k, gy + k1, b);
      const V yv = vload<V>(a);
      vstore(a, vload<V>(b) * ((S(1) - yv) * (S(1) + yv) * S(0.5)));
      std::copy(a, a + (k1 - k), gx + k);
    }
  }
}

CTGS_LANE_CLONES void activation_part(const float* x, float* y, const float* gy, float* gx, int64_t k0, int64_t k1) {
  activation_range<float>(x, y, gy, gx, k0, k1);
}
CTGS_LANE_CLONES void activation_part(const double* x, double* y, const double* gy, double* gx, int64_t k0,
                                      int64_t k1) {
  activation_range<double>(x, y, gy, gx, k0, k1);
}

}  // namespace

template <typename S>
void texel_activation(const S* x, S* y, int64_t n, int threads) {
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t c0 = 0; c0 < n; c0 += CHUNK) activation_part(x, y, static_cast<const S*>(nullptr),
                                                            static_cast<S*>(nullptr), c0, std::min(n, c0 + CHUNK));
}

template <typename S>
void texel_activation_backward(const S* y, const S* grad_y, S* grad_x, int64_t n, int threads) {
#pragma omp parallel for schedule(static) num_threads(std::max(1, threads))
  for (int64_t c0 = 0; c0 < n; c0 += CHUNK)
    activation_part(static_cast<const S*>(nullptr), const_cast<S*>(y), grad_y, grad_x, c0, std::min(n, c0 + CHUNK));
}

namespace {
template <typename S>
struct FloatBits;
template <>
struct FloatBits<float> {
  typedef uint32_t U;
  static constexpr U EXP = 0x7f800000u;
};
template <>
struct FloatBits<double> {
  typedef uint64_t U;
  static constexpr U EXP = 0x7ff0000000000000ull;
};

// Whether x[k0, k1) holds an infinite or NaN value (all exponent bits set). Multiversioned: the AVX2
// clone tests 8 floats per instruction (0.31 -> 0.16 ms for 2.4M texel values on the dev VM).
template <typename S>
CTGS_INLINE bool any_nonfinite_range(const S* x, int64_t k0, int64_t k1) {
  using U = typename FloatBits<S>::U;
  constexpr U E = FloatBits<S>::EXP;
  U hit = 0;
  for (int64_t k = k0; k < k1; ++k) {
    U b;
    std::memcpy(&b, x + k, sizeof(U));
    hit |= U((b & E) == E);
  }
  return hit != 0;
}
CTGS_LANE_CLONES bool any_nonfinite_part(const float* x, int64_t k0, int64_t k1) {
  return any_nonfinite_range(x, k0, k1);
}
CTGS_LANE_CLONES bool any_nonfinite_part(const double* x, int64_t k0, int64_t k1) {
  return any_nonfinite_range(x, k0, k1);
}
}  // namespace

template <typename S>
bool all_finite(const S* x, int64_t n, int threads) {
  int bad = 0;
#pragma omp parallel for schedule(static) reduction(| : bad) num_threads(std::max(1, threads))
  for (int64_t c0 = 0; c0 < n; c0 += CHUNK) bad |= int(any_nonfinite_part(x, c0, std::min(n, c0 + CHUNK)));
  return bad == 0;
}

namespace {
template <typename S>
CTGS_INLINE void act_l1_lanes(const S* y, const S* gy, S* gx, S gs, bool zero_w) {
  using V = typename Lanes<S>::V;
  const V yv = vload<V>(y), one = splat(S(1)), z = splat(S(0));
  // g_l1 exactly as texel_l1's backward writes it: +0 for a zero weight, else gs x sign(y).
  const V g_l1 = zero_w ? z : gs * sel(yv > S(0), one, sel(yv < S(0), -one, z));
  vstore(gx, (vload<V>(gy) + g_l1) * ((S(1) - yv) * (S(1) + yv) * S(0.5)));
}

template <typename S>
CTGS_INLINE void act_l1_range(const S* y, const S* gy, S* gx, const S* weight, const long long* tex_offset,
                              const int* tex_res, int i0, int i1, S scale) {
  constexpr int W = Lanes<S>::W;
  for (int i = i0; i < i1; ++i) {
    const int64_t cnt = 3 * int64_t(tex_res[2 * i]) * tex_res[2 * i + 1];
    if (cnt <= 0) continue;
    const int64_t off = 3 * tex_offset[i];
    const S wi = weight[i];
    const S gs = scale * wi;  // texel_l1_range's per-primitive factor
    const bool zero_w = wi == S(0);
    int64_t k = 0;
    for (; k + W <= cnt; k += W) act_l1_lanes<S>(y + off + k, gy + off + k, gx + off + k, gs, zero_w);
    if (k < cnt) {  // tail through zero-padded copies
      alignas(32) S a[W] = {}, b[W] = {}, c[W];
      std::copy(y + off + k, y + off + cnt, a);
      std::copy(gy + off + k, gy + off + cnt, b);
      act_l1_lanes<S>(a, b, c, gs, zero_w);
      std::copy(c, c + (cnt - k), gx + off + k);
    }
  }
}

CTGS_LANE_CLONES void act_l1_part(const float* y, const float* gy, float* gx, const float* w, const long long* off,
                                  const int* res, int i0, int i1, float scale) {
  act_l1_range<float>(y, gy, gx, w, off, res, i0, i1, scale);
}
CTGS_LANE_CLONES void act_l1_part(const double* y, const double* gy, double* gx, const double* w,
                                  const long long* off, const int* res, int i0, int i1, double scale) {
  act_l1_range<double>(y, gy, gx, w, off, res, i0, i1, scale);
}
}  // namespace

template <typename S>
void texel_activation_backward_l1(const S* y, const S* grad_y, S* grad_x, const S* weight,
                                  const long long* tex_offset, const int* tex_res, int n_prims, S scale, int threads) {
  constexpr int BLOCK = 256;
  const int nb = (n_prims + BLOCK - 1) / BLOCK;
#pragma omp parallel for schedule(dynamic, 4) num_threads(std::max(1, threads))
  for (int b = 0; b < nb; ++b)
    act_l1_part(y, grad_y, grad_x, weight, tex_offset, tex_res, b * BLOCK, std::min(n_prims, (b + 1) * BLOCK), scale);
}

template void texel_activation_backward_l1<float>(const float*, const float*, float*, const float*,
                                                  const long long*, const int*, int, float, int);
template void texel_activation_backward_l1<double>(const double*, const double*, double*, const double*,
                                                   const long long*, const int*, int, double, int);

template bool all_finite<float>(const float*, int64_t, int);
template bool all_finite<double>(const double*, int64_t, int);

template void texel_activation<float>(const float*, float*, int64_t, int);
template void texel_activation<double>(const double*, double*, int64_t, int);
template void texel_activation_backward<float>(const float*, const float*, float*, int64_t, int);
template void texel_activation_backward<double>(const double*, const double*, double*, int64_t, int);

template <typename S>
void jagged_remap(const S* old_buf, int64_t old_rows, S* new_buf, int C, const int* old_res,
                  const long long* old_off, const long long* src, const long long* shift, const int* new_res,
                  const long long* new_off, int64_t n_new, int threads) {
  auto floor_half = [](long long d) { return d >= 0 ? d / 2 : -((-d + 1) / 2); };
#pragma omp parallel for schedule(dynamic, 256) num_threads(std::max(1, threads))
  for (int64_t j = 0; j < n_new; ++j) {
    const long long s = src[j];
    const long long ru = old_res[2 * s], rv = old_res[2 * s + 1];
    const long long nu = new_res[2 * j], nv = new_res[2 * j + 1];
    const long long du = floor_half(ru - nu) + shift[2 * j], dv = floor_half(rv - nv) + shift[2 * j + 1];
    // Columns iu with 0 <= iu + du < ru.
    const long long u0 = std::min(nu, std::max(0LL, -du)), u1 = std::max(u0, std::min(nu, ru - du));
    for (long long iv = 0; iv < nv; ++iv) {
      S* dst = new_buf + C * (new_off[j] + iv * nu);
      const long long ov = iv + dv;
      if (old_rows == 0 || ov < 0 || ov >= rv || u0 >= u1) {
        std::fill(dst, dst + C * nu, S(0));
        continue;
      }
      std::fill(dst, dst + C * u0, S(0));
      const S* from = old_buf + C * (old_off[s] + ov * ru + u0 + du);
      std::copy(from, from + C * (u1 - u0), dst + C * u0);
      std::fill(dst + C * u1, dst + C * nu, S(0));
    }
  }
}

template void jagged_remap<float>(const float*, int64_t, float*, int, const int*, const long long*,
                                  const long long*, const long long*, const int*, const long long*, int64_t, int);
template void jagged_remap<double>(const double*, int64_t, double*, int, const int*, const long long*,
                                   const long long*, const long long*, const int*, const long long*, int64_t, int);
template int64_t adam_step<float>(float*, const float*, float*, float*, int64_t, const float*, double, double,
                                  double, double, double, double, int);
template int64_t adam_step<double>(double*, const double*, double*, double*, int64_t, const double*, double,
                                   double, double, double, double, double, int);
template double texel_l1<float>(const float*, const float*, const long long*, const int*, int, float*, float,
                                int, bool);
template double texel_l1<double>(const double*, const double*, const long long*, const int*, int, double*,
                                 double, int, bool);

template <typename S>
void accumulate_pairs(const int32_t* pix, const int32_t* prim, const S* w, int64_t n_pairs, const S* e,
                      int32_t* count, S* contrib, S* err, int64_t n_prims, int threads) {
  // Thread t sums the t-th contiguous chunk of pairs in pair order into its own buffers (thread 0: the
  // outputs); the chunks' sums are then added in thread order. One thread: the order of index_add_.
  const int nt = n_pairs >= (int64_t(1) << 16) ? std::max(1, threads) : 1;
  std::vector<int32_t> count_t(size_t(nt - 1) * n_prims);
  std::vector<S> contrib_t(size_t(nt - 1) * n_prims), err_t(size_t(nt - 1) * n_prims);
#pragma omp parallel num_threads(nt)
  {
    const int t = omp_get_thread_num(), got = omp_get_num_threads();
    int32_t* c = t == 0 ? count : count_t.data() + size_t(t - 1) * n_prims;
    S* s = t == 0 ? contrib : contrib_t.data() + size_t(t - 1) * n_prims;
    S* r = t == 0 ? err : err_t.data() + size_t(t - 1) * n_prims;
    if (t == 0) {  // the other threads' buffers start at 0 (and stay so for threads that did not start)
      std::fill(c, c + n_prims, 0);
      std::fill(s, s + n_prims, S(0));
      std::fill(r, r + n_prims, S(0));
    }
    // Chunks by the thread count actually granted.
    const int64_t k0 = n_pairs * t / got, k1 = n_pairs * (t + 1) / got;
    // The forward lists a primitive's pixels of one tile together: sum each run in registers (loaded from
    // and stored to the buffers at the run's ends, so every sum sees the same additions in the same order
    // as one read-modify-write per pair, without the store-to-load chain through memory).
    int64_t k = k0;
    while (k < k1) {
      const int32_t i = prim[k];
      int32_t ci = c[i];
      S si = s[i], ri = r[i];
      for (; k < k1 && prim[k] == i; ++k) {
        const S wk = w[k];
        ci += 1;
        si += wk;
        ri += e[pix[k]] * wk;
      }
      c[i] = ci;
      s[i] = si;
      r[i] = ri;
    }
  }
  if (nt > 1) {
#pragma omp parallel for schedule(static) num_threads(nt)
    for (int64_t i = 0; i < n_prims; ++i)
      for (int t = 0; t + 1 < nt; ++t) {
        count[i] += count_t[size_t(t) * n_prims + i];
        contrib[i] += contrib_t[size_t(t) * n_prims + i];
        err[i] += err_t[size_t(t) * n_prims + i];
      }
  }
}

template void accumulate_pairs<float>(const int32_t*, const int32_t*, const float*, int64_t, const float*, int32_t*,
                                      float*, float*, int64_t, int);
template void accumulate_pairs<double>(const int32_t*, const int32_t*, const double*, int64_t, const double*,
                                       int32_t*, double*, double*, int64_t, int);

}  // namespace cpu
}  // namespace ctgs
