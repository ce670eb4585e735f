#version 300 es
// The mesh of `ctgs view --mesh`: the camera of the surfels (OpenCV: +z forward, y down; pixel (u, v) at
// u = fx x / z + cx, v = fy y / z + cy), image row 0 at the top, depth from near to far.
precision highp float;

uniform mat4 u_view;  // world -> camera
uniform vec4 u_intr;  // fx, fy, cx, cy (pixels)
uniform vec2 u_size;  // W, H (pixels)
uniform vec2 u_clip;  // near, far (camera-space z)

layout(location = 0) in vec3 a_pos;
layout(location = 1) in vec4 a_col;  // sRGB, as the renders

out vec3 v_col;
out vec3 v_cam;

void main() {
  vec4 pc = u_view * vec4(a_pos, 1.0);
  float n = u_clip.x, f = u_clip.y;
  v_col = a_col.rgb;
  v_cam = pc.xyz;
  gl_Position = vec4(2.0 * u_intr.x / u_size.x * pc.x + (2.0 * u_intr.z / u_size.x - 1.0) * pc.z,
                     -2.0 * u_intr.y / u_size.y * pc.y + (1.0 - 2.0 * u_intr.w / u_size.y) * pc.z,
                     (f + n) / (f - n) * pc.z - 2.0 * f * n / (f - n), pc.z);
}
