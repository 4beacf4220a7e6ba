#version 300 es
// The model's vertices seen by an OpenCV pinhole camera (x right, y down, z forward; x_cam = R x_world + t).
// Pixel (u, v) = (fx x/z + cx, fy y/z + cy), pixel centres at integer coordinates as in sellip.render.
precision highp float;
in vec3 a_position;
in vec3 a_normal;
in float a_eta;
in vec3 a_rho_d;
in float a_rho_s;
in float a_sigma_s;
in vec3 a_rho_ss;
in float a_sigma_ss;
in float a_confidence;
in float a_model;
in float a_cluster;
uniform mat3 u_R;          // cam_from_world rotation (rows: camera axes in world)
uniform vec3 u_t;
uniform vec4 u_K;          // fx, fy, cx, cy in pixels of the viewport
uniform vec2 u_size;       // viewport width, height in pixels
uniform vec2 u_depth;      // near, far (metres)
out vec3 v_world;
out vec3 v_normal;
out float v_eta;
out vec3 v_rho_d;
out float v_rho_s;
out float v_sigma_s;
out vec3 v_rho_ss;
out float v_sigma_ss;
out float v_confidence;
out float v_model;
out float v_cluster;
void main() {
  vec3 c = u_R * a_position + u_t;
  float n = u_depth.x, f = u_depth.y;
  gl_Position = vec4(2.0 * u_K.x / u_size.x * c.x + (2.0 * (u_K.z + 0.5) / u_size.x - 1.0) * c.z,
                     -2.0 * u_K.y / u_size.y * c.y + (1.0 - 2.0 * (u_K.w + 0.5) / u_size.y) * c.z,
                     (f + n) / (f - n) * c.z - 2.0 * f * n / (f - n),
                     c.z);
  v_world = a_position;
  v_normal = a_normal;
  v_eta = a_eta; v_rho_d = a_rho_d; v_rho_s = a_rho_s; v_sigma_s = a_sigma_s;
  v_rho_ss = a_rho_ss; v_sigma_ss = a_sigma_ss;
  v_confidence = a_confidence; v_model = a_model; v_cluster = a_cluster;
}
