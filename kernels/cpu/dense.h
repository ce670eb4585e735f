// Dense per-element training work (dense.cpp): fused Adam and the texel L1 regulariser.
#pragma once

#include <cstdint>
#include <vector>

namespace ctgs {
namespace cpu {

// One Adam step in place on n contiguous elements: m = b1 m + (1-b1) g, v = b2 v + (1-b2) g^2,
// p -= lr (m / bc1) / (sqrt(v / bc2) + eps), with lr per element (lr_vec, if not null) or lr. bc1, bc2:
// the bias corrections 1 - beta^t. Returns how many updated p are NaN or infinite.
template <typename S>
int64_t adam_step(S* p, const S* g, S* m, S* v, int64_t n, const S* lr_vec, double lr, double beta1,
                  double beta2, double bc1, double bc2, double eps, int threads);

// Texel L1 over the primitives i with vis[i] != 0 (texels of i: rows tex_offset[i] .. + res_u*res_v of
// raw [T, 3], packed): grad == null -> returns sum |2 sigmoid(raw) - 1|; else writes
// grad = scale * d/draw of that sum (0 for the texels of invisible primitives) and returns 0.
template <typename S>
double texel_l1(const S* raw, const uint8_t* vis, const long long* tex_offset, const int* tex_res, int n_prims,
                S* grad, S scale, int threads);

}  // namespace cpu
}  // namespace ctgs
