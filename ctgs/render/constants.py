"""Renderer constants, mirroring kernels/include/ctgs/constants.h with the same names (reasons there)."""

MAX_ALPHA = 0.99  # keeps 1 - alpha >= 0.01 so backward can recover T by division
MIN_ALPHA = 1.0 / 255.0  # contributions below one 8-bit level are skipped
T_EPS = 1e-4  # stop blending before a step that would leave T < T_EPS
CUTOFF_RHO = 9.0  # 3 sigma (squared Mahalanobis distance)
FILTER_INV_SQUARE = 2.0  # screen-space fallback rho2d = FILTER_INV_SQUARE * |pix - m|^2, pixels^-2
PARALLEL_EPS = 1e-6  # ray/plane hit valid iff |n.d| > PARALLEL_EPS * |d|
T_RECOVER_EPS = 1e-6  # backward: T_i = T_{i+1} / max(T_RECOVER_EPS, 1 - alpha_i)
TILE_SIZE = 16  # tiles of TILE_SIZE x TILE_SIZE pixels
TILE_W = TILE_SIZE
TILE_H = TILE_SIZE
