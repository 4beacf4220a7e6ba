#version 300 es
// The shadow map: the model seen from the light by a pinhole camera aimed at the object (same projection as
// mesh.vert); each texel keeps the distance from the light to the nearest surface.
precision highp float;
in vec3 a_position;
uniform mat3 u_R;
uniform vec3 u_t;
uniform vec4 u_K;
uniform vec2 u_size;
uniform vec2 u_depth;
out vec3 v_world;
void main() {
  vec3 c = u_R * a_position + u_t;
  float n = u_depth.x, f = u_depth.y;
  gl_Position = vec4(2.0 * u_K.x / u_size.x * c.x + (2.0 * (u_K.z + 0.5) / u_size.x - 1.0) * c.z,
                     -2.0 * u_K.y / u_size.y * c.y + (1.0 - 2.0 * (u_K.w + 0.5) / u_size.y) * c.z,
                     (f + n) / (f - n) * c.z - 2.0 * f * n / (f - n),
                     c.z);
  v_world = a_position;
}
