#version 300 es
// Final step of docs/reference/renderer.md: rgb = C + T * background, T = 1 - accumulated alpha, clamped to
// [0, 1] as the 8-bit image `ctgs render` writes. With u_map > 0, the picture of a map of ctgs/render/texel_map.py
// (compose) from the blended (R, G, A) = (sum w t h, sum w h, sum w), over black.
precision highp float;
precision highp sampler2D;

// ctgs/render/texel_map.py (tests/viewer checks these stay equal)
#define UNTEXTURED 0.35
#define MIN_WEIGHT 1e-6
const vec3 TURBO[17] = vec3[17](
  vec3(0.188, 0.071, 0.231), vec3(0.251, 0.251, 0.635), vec3(0.275, 0.420, 0.890), vec3(0.259, 0.580, 1.000),
  vec3(0.157, 0.737, 0.922), vec3(0.094, 0.867, 0.761), vec3(0.196, 0.949, 0.596), vec3(0.427, 0.996, 0.384),
  vec3(0.643, 0.988, 0.235), vec3(0.796, 0.929, 0.204), vec3(0.925, 0.820, 0.227), vec3(0.992, 0.682, 0.208),
  vec3(0.984, 0.506, 0.133), vec3(0.925, 0.325, 0.059), vec3(0.824, 0.192, 0.020), vec3(0.675, 0.090, 0.004),
  vec3(0.478, 0.016, 0.012));

uniform sampler2D u_accum;  // premultiplied colour and alpha, blended back to front (float)
uniform vec3 u_background;
uniform int u_map;

out vec4 o_color;

vec3 turbo(float t) {
  float x = clamp(t, 0.0, 1.0) * 16.0;
  int i = min(int(floor(x)), 15);
  return mix(TURBO[i], TURBO[i + 1], x - float(i));
}

void main() {
  vec4 acc = texelFetch(u_accum, ivec2(gl_FragCoord.xy), 0);
  if (u_map > 0) {
    vec3 c = acc.g > MIN_WEIGHT ? turbo(acc.r / acc.g) * acc.g : vec3(0.0);
    o_color = vec4(clamp(c + UNTEXTURED * max(acc.a - acc.g, 0.0), 0.0, 1.0), 1.0);
    return;
  }
  o_color = vec4(clamp(acc.rgb + (1.0 - acc.a) * u_background, 0.0, 1.0), 1.0);
}
