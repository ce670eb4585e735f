#version 300 es
// Final step of docs/reference/renderer.md: rgb = C + T * background, T = 1 - accumulated alpha, clamped to
// [0, 1] as the 8-bit image `ctgs render` writes.
precision highp float;
precision highp sampler2D;

uniform sampler2D u_accum;  // premultiplied colour and alpha, blended back to front (float)
uniform vec3 u_background;

out vec4 o_color;

void main() {
  vec4 acc = texelFetch(u_accum, ivec2(gl_FragCoord.xy), 0);
  o_color = vec4(clamp(acc.rgb + (1.0 - acc.a) * u_background, 0.0, 1.0), 1.0);
}
