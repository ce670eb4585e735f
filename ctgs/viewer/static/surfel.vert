#version 300 es
// One instanced quad per surfel (docs/renderer.md, "Per primitive" and "Screen bounds"): camera-space
// frame, SH colour, and the conservative pixel box of the CPU tiler (kernels/include/ctgs/bounds.h):
// projected 3-sigma corners united with the screen-space fallback disc, one pixel of margin, the whole
// image when a corner is behind the near plane. The fragment shader does the exact per-pixel test.
precision highp float;
precision highp int;
precision highp sampler2D;
precision highp usampler2D;

// kernels/include/ctgs/constants.h (tests/viewer checks these stay equal)
#define CUTOFF_RHO 9.0
#define FILTER_INV_SQUARE 2.0
#define MAX_SH_TEXELS 12  // 16 coefficients x 3 channels / 4 per texel

uniform sampler2D u_geom;     // RGBA32F, 3 texels per surfel: (mean, opacity), unit quat (w,x,y,z), (sx, sy, ku, kv)
uniform usampler2D u_layout;  // RGBA32UI, 1 texel per surfel: res_u, res_v, atlas x | y << 16, page
uniform sampler2D u_sh;       // RGBA16F, u_sh_texels texels per surfel: K x 3 coefficients, coefficient-major
uniform int u_sh_texels;
uniform int u_sh_degree;
uniform mat4 u_view;          // world -> camera (OpenCV: +z forward, y down)
uniform vec3 u_campos;        // camera centre, world
uniform vec4 u_intr;          // fx, fy, cx, cy (pixels)
uniform vec2 u_size;          // W, H (pixels)
uniform float u_near;

layout(location = 0) in uint a_index;  // surfel to draw (instanced, back to front)

flat out vec4 v_mu_op;   // mu_c (camera space), opacity
flat out vec4 v_u_sx;    // tangent u (camera space), sigma_u
flat out vec4 v_v_sy;    // tangent v, sigma_v
flat out vec4 v_n_nmu;   // normal, n . mu_c
flat out vec4 v_col_ku;  // SH colour + 0.5 (unclamped), texel size along u
flat out vec4 v_m_kv;    // projected centre (pixels), texel size along v, unused
flat out uvec4 v_tex;    // res_u, res_v, atlas x | y << 16, page

const float SH_C0 = 0.28209479177387814;
const float SH_C1 = 0.4886025119029199;
const float SH_C2[5] = float[5](1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                                -1.0925484305920792, 0.5462742152960396);
const float SH_C3[7] = float[7](-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                                0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                                -0.5900435899266435);

ivec2 texel_of(uint j, int width) {
  return ivec2(int(j % uint(width)), int(j / uint(width)));
}

// ctgs/render/sh.py sh_to_color, term by term in the same order.
vec3 sh_color(uint i, vec3 dir) {
  vec3 c[16];
  int w = textureSize(u_sh, 0).x;
  float s[4 * MAX_SH_TEXELS];
  for (int t = 0; t < MAX_SH_TEXELS; ++t) {
    if (t >= u_sh_texels) break;
    vec4 q = texelFetch(u_sh, texel_of(i * uint(u_sh_texels) + uint(t), w), 0);
    s[4 * t] = q.x; s[4 * t + 1] = q.y; s[4 * t + 2] = q.z; s[4 * t + 3] = q.w;
  }
  int k = (u_sh_degree + 1) * (u_sh_degree + 1);
  for (int j = 0; j < 16; ++j) c[j] = j < k ? vec3(s[3 * j], s[3 * j + 1], s[3 * j + 2]) : vec3(0.0);
  vec3 out_c = SH_C0 * c[0];
  if (u_sh_degree >= 1) {
    float x = dir.x, y = dir.y, z = dir.z;
    out_c = out_c - SH_C1 * y * c[1] + SH_C1 * z * c[2] - SH_C1 * x * c[3];
    if (u_sh_degree >= 2) {
      float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
      out_c = out_c + SH_C2[0] * xy * c[4] + SH_C2[1] * yz * c[5] + SH_C2[2] * (2.0 * zz - xx - yy) * c[6]
              + SH_C2[3] * xz * c[7] + SH_C2[4] * (xx - yy) * c[8];
      if (u_sh_degree >= 3) {
        out_c = out_c + SH_C3[0] * y * (3.0 * xx - yy) * c[9] + SH_C3[1] * xy * z * c[10]
                + SH_C3[2] * y * (4.0 * zz - xx - yy) * c[11]
                + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * c[12]
                + SH_C3[4] * x * (4.0 * zz - xx - yy) * c[13] + SH_C3[5] * z * (xx - yy) * c[14]
                + SH_C3[6] * x * (xx - 3.0 * yy) * c[15];
      }
    }
  }
  return out_c + 0.5;
}

// ctgs/render/preprocess.py quat_to_rotmat; columns: tangent u, tangent v, normal.
mat3 quat_to_rotmat(vec4 q) {
  q = q / length(q);
  float w = q.x, x = q.y, y = q.z, z = q.w;
  return mat3(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y),   // column 0
              2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x),   // column 1
              2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y));  // column 2
}

void cull() {
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // z > w: outside the clip volume, no fragments
}

void main() {
  uint i = a_index;
  int gw = textureSize(u_geom, 0).x;
  vec4 g0 = texelFetch(u_geom, texel_of(3u * i, gw), 0);
  vec4 g1 = texelFetch(u_geom, texel_of(3u * i + 1u, gw), 0);
  vec4 g2 = texelFetch(u_geom, texel_of(3u * i + 2u, gw), 0);
  vec3 mean = g0.xyz;
  mat3 Rv = mat3(u_view);
  vec3 mu = Rv * mean + u_view[3].xyz;
  if (mu.z < u_near) { cull(); return; }  // centre behind the near plane: contributes nowhere
  mat3 R = quat_to_rotmat(g1);
  vec3 U = Rv * R[0], V = Rv * R[1], N = Rv * R[2];
  float fx = u_intr.x, fy = u_intr.y, cx = u_intr.z, cy = u_intr.w;
  vec2 m = vec2(fx * mu.x / mu.z + cx, fy * mu.y / mu.z + cy);

  // bounds.h surfel_pixel_rect
  float r2 = sqrt(CUTOFF_RHO / FILTER_INV_SQUARE);
  vec2 lo = m - r2, hi = m + r2;
  bool whole = false;
  vec3 a = 3.0 * g2.x * U, b = 3.0 * g2.y * V;
  for (int k = 0; k < 4; ++k) {
    float su = (k & 1) != 0 ? 1.0 : -1.0, sv = (k & 2) != 0 ? 1.0 : -1.0;
    vec3 c = mu + su * a + sv * b;
    if (!(c.z >= u_near)) { whole = true; break; }
    vec2 p = vec2(fx * c.x / c.z + cx, fy * c.y / c.z + cy);
    lo = min(lo, p);
    hi = max(hi, p);
  }
  vec2 p0, p1;  // covered pixel range in continuous image coordinates (pixel edges)
  if (whole) {
    p0 = vec2(0.0);
    p1 = u_size;
  } else {
    if (hi.x < 0.0 || hi.y < 0.0 || lo.x > u_size.x || lo.y > u_size.y) { cull(); return; }
    p0 = max(floor(lo) - 1.0, vec2(0.0));
    p1 = min(ceil(hi) + 2.0, u_size);  // pixel_span's inclusive ceil + 1, plus 1 for the right edge
  }
  int vid = gl_VertexID;  // triangle strip: (0,0) (1,0) (0,1) (1,1)
  vec2 corner = vec2(float(vid & 1), float(vid >> 1));
  vec2 pix = mix(p0, p1, corner);
  gl_Position = vec4(2.0 * pix.x / u_size.x - 1.0, 1.0 - 2.0 * pix.y / u_size.y, 0.0, 1.0);

  vec3 d = mean - u_campos;
  float sq = dot(d, d);
  vec3 dir = sq > 0.0 ? d * inversesqrt(sq) : vec3(0.0);
  v_mu_op = vec4(mu, g0.w);
  v_u_sx = vec4(U, g2.x);
  v_v_sy = vec4(V, g2.y);
  v_n_nmu = vec4(N, dot(N, mu));
  v_col_ku = vec4(sh_color(i, dir), g2.z);
  v_m_kv = vec4(m, g2.w, 0.0);
  v_tex = texelFetch(u_layout, texel_of(i, textureSize(u_layout, 0).x), 0);
}
