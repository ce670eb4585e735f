#version 300 es
// One instanced quad per surfel (docs/reference/renderer.md, "Per primitive" and "Screen bounds"): camera-space
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
// ctgs/render/texel_map.py (tests/viewer checks these stay equal): the maps' log2 scales
#define TEXEL_PX_LOG2_LO -1.0
#define TEXEL_PX_LOG2_HI 7.0
#define TEXRES_LOG2_LO 0.0
#define TEXRES_LOG2_HI 16.0

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
uniform bool u_tight;         // false: bounds.h's pixel boxes throughout (to measure what the tight quads save)
uniform int u_map;            // 0: the image; 1: texel size in pixels; 2: texture resolution (ctgs/render/texel_map.py)

layout(location = 0) in uint a_index;  // surfel to draw (instanced, back to front)

flat out vec4 v_mu_op;   // mu_c (camera space), opacity
flat out vec4 v_u_sx;    // tangent u (camera space), sigma_u
flat out vec4 v_v_sy;    // tangent v, sigma_v
flat out vec4 v_n_nmu;   // normal, n . mu_c
flat out vec4 v_col_ku;  // SH colour + 0.5 (unclamped), texel size along u
flat out vec4 v_m_kv;    // projected centre (pixels), texel size along v, unused
flat out uvec4 v_tex;    // res_u, res_v, atlas x | y << 16, page
flat out vec2 v_map;     // u_map > 0: the surfel's value t on the map's scale, 1 if it is textured (else 0)

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

  // Coverage, conservative w.r.t. the fragment test (rho <= CUTOFF_RHO): the projected 3-sigma
  // rectangle (a convex quad: the plane's corners are all in front) grown by the fallback disc's radius
  // plus one pixel, i.e. each edge pushed out by `grow`; the projected centre lies inside the rectangle, so
  // the disc around it is covered too. Where that offset quad would be needle-like (near edge-on
  // surfels) or larger than it (small surfels), the pixel box of bounds.h; where the rectangle crosses
  // the near plane, the pixel box of the part in front (a hit with t >= near inside 3 sigma lies there;
  // bounds.h takes the whole image).
  float r2 = sqrt(CUTOFF_RHO / FILTER_INV_SQUARE);
  float grow = r2 + 1.0;  // pixels
  vec2 lo = m - r2, hi = m + r2;
  vec3 a = 3.0 * g2.x * U, b = 3.0 * g2.y * V;
  vec3 C[4];  // 3-sigma corners, camera space, index bit 0: +-u, bit 1: +-v
  bool front = true, finite = true;
  for (int k = 0; k < 4; ++k) {
    C[k] = mu + ((k & 1) != 0 ? a : -a) + ((k & 2) != 0 ? b : -b);
    front = front && C[k].z >= u_near;
    finite = finite && !any(isnan(C[k])) && !any(isinf(C[k]));
  }
  bool whole = !finite || (!front && !u_tight);  // u_tight false: exactly bounds.h
  vec2 P[4];  // projected corners (when all are in front)
  if (front && finite) {
    for (int k = 0; k < 4; ++k) {
      P[k] = vec2(fx * C[k].x / C[k].z + cx, fy * C[k].y / C[k].z + cy);
      lo = min(lo, P[k]);
      hi = max(hi, P[k]);
    }
  } else if (finite) {  // clip the rectangle (ring -u-v, +u-v, +u+v, -u+v) to z >= near
    const int ring[4] = int[4](0, 1, 3, 2);
    for (int e = 0; e < 4; ++e) {
      vec3 p = C[ring[e]], q = C[ring[(e + 1) & 3]];
      bool pin = p.z >= u_near, qin = q.z >= u_near;
      if (pin) {
        vec2 s = vec2(fx * p.x / p.z + cx, fy * p.y / p.z + cy);
        lo = min(lo, s);
        hi = max(hi, s);
      }
      if (pin != qin) {
        vec3 x = mix(p, q, (u_near - p.z) / (q.z - p.z));
        x.z = max(x.z, u_near);
        vec2 s = vec2(fx * x.x / x.z + cx, fy * x.y / x.z + cy);
        lo = min(lo, s);
        hi = max(hi, s);
      }
    }
  }
  if (!whole && (hi.x < 0.0 || hi.y < 0.0 || lo.x > u_size.x || lo.y > u_size.y)) { cull(); return; }
  // Offset corner k = P[k] + grow (n1 + n2) / (1 + n1.n2), n1, n2 the outward unit normals of its edges.
  vec2 grown[4];
  bool tight = u_tight && front && finite;
  for (int k = 0; k < 4 && tight; ++k) {
    vec2 e1 = P[k ^ 1] - P[k], e2 = P[k ^ 2] - P[k];
    float l1 = length(e1), l2 = length(e2);
    if (!(l1 > 1e-3 && l2 > 1e-3)) { tight = false; break; }
    vec2 n1 = vec2(e1.y, -e1.x) / l1, n2 = vec2(e2.y, -e2.x) / l2;
    n1 = dot(n1, e2) > 0.0 ? -n1 : n1;  // away from the other edge
    n2 = dot(n2, e1) > 0.0 ? -n2 : n2;
    float den = 1.0 + dot(n1, n2);  // 1 - cos(interior angle)
    if (!(den > 0.1)) { tight = false; break; }  // interior angle under ~25 degrees
    grown[k] = P[k] + grow * (n1 + n2) / den;
  }
  if (tight) {  // whichever covers fewer pixels: small surfels' margins make the offset quad the larger
    vec2 d1 = grown[3] - grown[0], d2 = grown[2] - grown[1];  // the diagonals (ring 0, 1, 3, 2)
    float quad = 0.5 * abs(d1.x * d2.y - d1.y * d2.x);
    vec2 box = ceil(hi) + 2.0 - (floor(lo) - 1.0);
    tight = quad < box.x * box.y;
  }
  int vid = gl_VertexID;  // triangle strip: (0,0) (1,0) (0,1) (1,1), i.e. corners -u-v, +u-v, -u+v, +u+v
  vec2 pix;
  if (tight) {
    pix = grown[vid];
  } else {  // bounds.h surfel_pixel_rect: pixel range in continuous image coordinates (pixel edges)
    vec2 p0 = whole ? vec2(0.0) : max(floor(lo) - 1.0, vec2(0.0));
    vec2 p1 = whole ? u_size : min(ceil(hi) + 2.0, u_size);  // pixel_span's inclusive ceil + 1, + 1 for the edge
    pix = mix(p0, p1, vec2(float(vid & 1), float(vid >> 1)));
  }
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
  if (u_map > 0) {  // texel_map.surfel_values
    float value = u_map == 1 ? log2(max(0.5 * (g2.z + g2.w) * fx / mu.z, 1e-30))
                             : log2(max(float(v_tex.x * v_tex.y), 1.0));
    float lo = u_map == 1 ? TEXEL_PX_LOG2_LO : TEXRES_LOG2_LO, hi = u_map == 1 ? TEXEL_PX_LOG2_HI : TEXRES_LOG2_HI;
    v_map = vec2(clamp((value - lo) / (hi - lo), 0.0, 1.0), v_tex.x > 0u && v_tex.y > 0u ? 1.0 : 0.0);
  } else {
    v_map = vec2(0.0);
  }
}
