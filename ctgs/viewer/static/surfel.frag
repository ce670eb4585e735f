#version 300 es
// Per (pixel, surfel): docs/reference/renderer.md steps 1-6, written as kernels/include/ctgs/surfel.h
// (surfel_alpha, surfel_color) and texture.h (texture_taps, texture_fetch) so the browser matches the
// CPU renderer to float rounding. Output is premultiplied (alpha * c, alpha) for back-to-front blending.
precision highp float;
precision highp int;
precision highp sampler2DArray;

// kernels/include/ctgs/constants.h (tests/viewer checks these stay equal)
#define MAX_ALPHA 0.99
#define MIN_ALPHA (1.0 / 255.0)
#define CUTOFF_RHO 9.0
#define FILTER_INV_SQUARE 2.0
#define PARALLEL_EPS 1e-6

uniform sampler2DArray u_atlas;  // texel offsets in [-1, 1] (RGB8_SNORM or RGB16F), one layer per page
uniform bool u_textures;         // false: render as if every surfel had no texture
uniform vec4 u_intr;             // fx, fy, cx, cy (pixels)
uniform vec2 u_size;             // W, H (pixels)
uniform float u_near;
uniform int u_map;               // > 0: a map of ctgs/render/texel_map.py instead of the image

flat in vec4 v_mu_op;
flat in vec4 v_u_sx;
flat in vec4 v_v_sy;
flat in vec4 v_n_nmu;
flat in vec4 v_col_ku;
flat in vec4 v_m_kv;
flat in uvec4 v_tex;
flat in vec2 v_map;

out vec4 o_color;

// One tap of texture.h: outside the grid reads 0.
vec3 tap(int iu, int iv, ivec2 res, ivec3 base) {
  if (iu < 0 || iu >= res.x || iv < 0 || iv >= res.y) return vec3(0.0);
  return texelFetch(u_atlas, base + ivec3(iu, iv, 0), 0).rgb;
}

void main() {
  // gl_FragCoord is the pixel centre with a bottom-left origin; image rows count from the top.
  vec2 pix = vec2(gl_FragCoord.x, u_size.y - gl_FragCoord.y);
  vec3 d = vec3((pix.x - u_intr.z) / u_intr.x, (pix.y - u_intr.w) / u_intr.y, 1.0);
  float d_norm = sqrt(dot(d, d));
  vec3 mu = v_mu_op.xyz;
  // 1. plane hit
  float denom = dot(v_n_nmu.xyz, d);
  bool valid = abs(denom) > PARALLEL_EPS * d_norm;
  float rho3d = uintBitsToFloat(0x7f800000u);  // +inf
  float lx = 0.0, ly = 0.0;
  if (valid) {
    float t = v_n_nmu.w / denom;
    if (t < u_near) discard;
    vec3 q = t * d - mu;
    lx = dot(v_u_sx.xyz, q);
    ly = dot(v_v_sy.xyz, q);
    float ax = lx / v_u_sx.w, ay = ly / v_v_sy.w;
    rho3d = ax * ax + ay * ay;
  }
  // 2-4. screen-space fallback, cutoff, falloff, alpha
  float ex = pix.x - v_m_kv.x, ey = pix.y - v_m_kv.y;
  float rho2d = FILTER_INV_SQUARE * (ex * ex + ey * ey);
  bool use3d = rho3d <= rho2d;
  float rho = use3d ? rho3d : rho2d;
  if (!(rho <= CUTOFF_RHO)) discard;
  float G = exp(-0.5 * rho);
  float a = v_mu_op.w * G;
  float alpha = a < MAX_ALPHA ? a : MAX_ALPHA;
  if (alpha < MIN_ALPHA) discard;
  if (u_map > 0) {  // the map's colour (t h, h, 0), blended with the same weights (composite.frag makes the picture)
    o_color = vec4(alpha * v_map.x * v_map.y, alpha * v_map.y, 0.0, alpha);
    return;
  }
  // 5. texture, only where the 3D Gaussian won
  vec3 tex = vec3(0.0);
  ivec2 res = ivec2(v_tex.xy);
  if (u_textures && valid && use3d && res.x > 0 && res.y > 0) {
    float uu = lx / v_col_ku.w + 0.5 * float(res.x - 1);
    float vv = ly / v_m_kv.z + 0.5 * float(res.y - 1);
    if (uu > -1.0 && uu < float(res.x) && vv > -1.0 && vv < float(res.y)) {
      float fu0 = floor(uu), fv0 = floor(vv);
      int u0 = int(fu0), v0 = int(fv0);
      float fu = uu - fu0, fv = vv - fv0;
      ivec3 base = ivec3(int(v_tex.z & 0xffffu), int(v_tex.z >> 16), int(v_tex.w));
      tex += ((1.0 - fu) * (1.0 - fv)) * tap(u0, v0, res, base);
      tex += (fu * (1.0 - fv)) * tap(u0 + 1, v0, res, base);
      tex += ((1.0 - fu) * fv) * tap(u0, v0 + 1, res, base);
      tex += (fu * fv) * tap(u0 + 1, v0 + 1, res, base);
    }
  }
  // 6. colour clamp
  vec3 c = max(v_col_ku.rgb + tex, 0.0);
  o_color = vec4(alpha * c, alpha);
}
