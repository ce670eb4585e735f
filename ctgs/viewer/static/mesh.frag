#version 300 es
// Vertex colours as they are, or shaded by a light at the camera (the triangle's own normal) to show the shape.
precision highp float;

uniform bool u_shade;

in vec3 v_col;
in vec3 v_cam;

out vec4 o_color;

void main() {
  vec3 c = v_col;
  if (u_shade) {
    vec3 n = normalize(cross(dFdx(v_cam), dFdy(v_cam)));
    c *= 0.3 + 0.7 * abs(dot(n, normalize(v_cam)));
  }
  o_color = vec4(c, 1.0);
}
