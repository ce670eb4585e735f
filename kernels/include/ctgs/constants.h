// Magic numbers of the textured 2D Gaussian surfel renderer, each with its reason (docs/reference/renderer.md).
// Mirrored with the same names in ctgs/render/constants.py. No torch here: shared by CPU and CUDA.
#pragma once

#ifdef __CUDACC__
#define HOST_DEVICE __host__ __device__
#else
#define HOST_DEVICE
#endif

namespace ctgs {

// alpha = min(MAX_ALPHA, o*G): keeps 1 - alpha >= 0.01, so T can be recovered by division in backward.
constexpr double MAX_ALPHA = 0.99;
// Contributions below one 8-bit level are invisible; skipping them bounds the work per pixel (3DGS).
constexpr double MIN_ALPHA = 1.0 / 255.0;
// Stop blending once the transmittance left would drop below this (3DGS): the rest is invisible.
constexpr double T_EPS = 1e-4;
// rho = squared Mahalanobis distance; 9 = 3 sigma, where the Gaussian has fallen to exp(-4.5) ~ 1.1%.
constexpr double CUTOFF_RHO = 9.0;
// 2DGS screen-space low-pass: rho2d = FILTER_INV_SQUARE * |pix - m|^2 (a Gaussian of std 1/sqrt(2) px),
// so a surfel seen edge-on (or smaller than a pixel) still covers about one pixel.
constexpr double FILTER_INV_SQUARE = 2.0;
// The ray/plane hit is valid iff |n.d| > PARALLEL_EPS * |d|: relative, so it does not depend on how d
// is scaled; below it the ray is (numerically) parallel to the plane and t would blow up.
constexpr double PARALLEL_EPS = 1e-6;
// Backward recovers T_i = T_{i+1} / max(T_RECOVER_EPS, 1 - alpha_i): never divides by 0.
constexpr double T_RECOVER_EPS = 1e-6;
// Screen tiles of TILE_SIZE x TILE_SIZE pixels: 256 pixels amortise one per-tile depth-sorted list and
// map onto one CUDA block.
constexpr int TILE_SIZE = 16;
constexpr int TILE_W = TILE_SIZE;
constexpr int TILE_H = TILE_SIZE;

}  // namespace ctgs
