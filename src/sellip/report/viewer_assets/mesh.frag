#version 300 es
// Modes: 0 relight (s0 or an analyzer at u_analyzer), 1 AoLP, 2 DoP, 3 one Mueller element (u_element),
// 4 a parameter map (u_map), 5 world position and 6 the colour-averaged Stokes vector (picking). Display values are exposure-scaled linear radiance,
// clipped to [0, 1] and sRGB-encoded when u_srgb (as sellip's tone mapping of its renders).
precision highp float;
in vec3 v_world;
in vec3 v_normal;
in float v_eta;
in vec3 v_rho_d;
in float v_rho_s;
in float v_sigma_s;
in vec3 v_rho_ss;
in float v_sigma_ss;
in float v_confidence;
in float v_model;
in float v_cluster;
uniform int u_mode;
uniform vec3 u_cameraCenter;
uniform vec3 u_cameraUp;      // world
uniform mat3 u_R;
uniform vec3 u_lightPosition; // world
uniform vec3 u_lightAxis;     // world: the light's polarizer axis
uniform vec3 u_lightStokes;   // incident linear Stokes in the light's frame: (1, 1, 0) flash, (1, 0, 0) unpolarized
uniform float u_exposure;
uniform bool u_srgb;
uniform bool u_useAnalyzer;
uniform float u_analyzer;     // radians, from image x towards image up
uniform ivec2 u_element;      // Mueller (row, column)
uniform int u_map;            // 0 eta 1 rho_d 2 rho_s 3 sigma_s 4 rho_ss 5 sigma_ss 6 normal 7 confidence 8 model 9 cluster
uniform int u_mapKind;        // 0 scalar 1 rgb 2 normal 3 category
uniform vec2 u_range;         // colour range of the map
uniform float u_dopMax;       // DoP shown full red at this value (1: the scale of Wilkie & Weidlich)
uniform float u_darkLevel;    // s0 below this (exposure-scaled) blanks AoLP, DoP and Mueller ratios
uniform bool u_shadows;       // shadow test against u_shadowMap (distances from the light, shadow.frag)
uniform sampler2D u_shadowMap;
uniform mat3 u_shadowR;       // the shadow map's camera: cam_from_world rotation, translation, intrinsics, size
uniform vec3 u_shadowT;
uniform vec4 u_shadowK;
uniform float u_shadowSize;
uniform float u_shadowBias;   // metres per shadow-map texel at the object: scales the bias that keeps a surface from
                              // shadowing itself (1.5 texels, more at grazing light, plus sellip.render's 0.1 mm)
out vec4 outColor;

#include "pbrdf.glsl"
#include "colormaps.glsl"

float lightVisibility(vec3 world, float distanceToLight, float cosI) {  // 1 lit, 0 in shadow (the renderer's shadow rays)
  if (!u_shadows) return 1.0;
  vec3 c = u_shadowR * world + u_shadowT;
  if (c.z <= 0.0) return 1.0;
  vec2 pixel = vec2(u_shadowK.x * c.x / c.z + u_shadowK.z, u_shadowK.y * c.y / c.z + u_shadowK.w);
  vec2 uv = vec2((pixel.x + 0.5) / u_shadowSize, 1.0 - (pixel.y + 0.5) / u_shadowSize);
  if (any(lessThan(uv, vec2(0.0))) || any(greaterThan(uv, vec2(1.0)))) return 1.0;
  float nearest = texture(u_shadowMap, uv).r;
  float bias = 1.5 * u_shadowBias * (1.0 + sqrt(max(1.0 - cosI * cosI, 0.0)) / max(cosI, 0.05)) + 1e-4;
  return distanceToLight <= nearest + bias ? 1.0 : 0.0;
}

vec3 encode(vec3 linear) {
  vec3 c = clamp(linear, 0.0, 1.0);
  if (!u_srgb) return c;
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}

void main() {
  if (u_mode == 5) { outColor = vec4(v_world, 1.0); return; }
  vec3 n = normalize(v_normal);
  if (u_mode == 4) {
    float value;
    vec3 color;
    if (u_map == 0) value = v_eta;
    else if (u_map == 2) value = v_rho_s;
    else if (u_map == 3) value = v_sigma_s;
    else if (u_map == 5) value = v_sigma_ss;
    else if (u_map == 7) value = v_confidence;
    else if (u_map == 8) value = v_model;
    else value = v_cluster;
    if (u_mapKind == 0) color = viridis((value - u_range.x) / (u_range.y - u_range.x));
    else if (u_mapKind == 1) color = clamp((u_map == 1 ? v_rho_d : v_rho_ss) / u_range.y, 0.0, 1.0);
    else if (u_mapKind == 2) {  // camera frame: x right, y up, z towards the camera (as docs/outputs.md)
      vec3 c = u_R * n;
      color = (vec3(c.x, -c.y, -c.z) + 1.0) * 0.5;
    } else color = category(int(floor(value + 0.5)));
    outColor = vec4(color, 1.0);
    return;
  }
  vec3 toCamera = u_cameraCenter - v_world;
  vec3 wo = normalize(toCamera);
  vec3 toLight = u_lightPosition - v_world;
  float d = length(toLight);
  vec3 wi = toLight / d;
  Lobes L = pbrdfLobes(n, wi, wo, d, u_lightAxis, u_cameraUp, v_eta);
  L.shading *= lightVisibility(v_world, d, L.cosI);
  vec3 w = lobeFactor(L, v_sigma_s) * v_rho_s + lobeFactor(L, v_sigma_ss) * v_rho_ss;  // reflection weight per colour
  vec3 sd = L.diffuse * u_lightStokes;
  vec3 sr = L.reflection * u_lightStokes;
  // Stokes per colour: s_k (rgb) = S (rho_d sd_k + w sr_k)
  vec3 s0 = L.shading * (v_rho_d * sd.x + w * sr.x);
  vec3 s1 = L.shading * (v_rho_d * sd.y + w * sr.y);
  vec3 s2 = L.shading * (v_rho_d * sd.z + w * sr.z);
  if (u_mode == 0) {
    vec3 radiance = u_useAnalyzer ? 0.5 * (s0 + s1 * cos(2.0 * u_analyzer) + s2 * sin(2.0 * u_analyzer)) : s0;
    outColor = vec4(encode(u_exposure * radiance), 1.0);
    return;
  }
  float m0 = (s0.r + s0.g + s0.b) / 3.0, m1 = (s1.r + s1.g + s1.b) / 3.0, m2 = (s2.r + s2.g + s2.b) / 3.0;
  if (u_mode == 6) { outColor = vec4(m0, m1, m2, 1.0); return; }  // picking: the colour-averaged Stokes vector
  bool dark = u_exposure * m0 < u_darkLevel;
  if (u_mode == 1) {  // AoLP: hue over 0..180 degrees (Wilkie & Weidlich), black where too dark
    if (dark) { outColor = vec4(0.0, 0.0, 0.0, 1.0); return; }
    float angle = 0.5 * atan(m2, m1);
    outColor = vec4(aolpColor(angle), 1.0);
    return;
  }
  if (u_mode == 2) {  // DoP: black (0) to red (1) (Wilkie & Weidlich's linear polarization)
    if (dark) { outColor = vec4(0.0, 0.0, 0.0, 1.0); return; }
    outColor = vec4(dopColor(sqrt(m1 * m1 + m2 * m2) / m0 / u_dopMax), 1.0);
    return;
  }
  // Mueller element (i, j), colour-averaged: M00 tone-mapped, the others Mij / M00 in [-1, 1] (blue - white - red).
  float rhoD = (v_rho_d.r + v_rho_d.g + v_rho_d.b) / 3.0, wm = (w.r + w.g + w.b) / 3.0;
  mat3 M = L.shading * (rhoD * L.diffuse + wm * L.reflection);
  float mij = M[u_element.y][u_element.x];
  if (u_element == ivec2(0, 0)) { outColor = vec4(encode(vec3(u_exposure * mij)), 1.0); return; }
  if (dark) { outColor = vec4(0.0, 0.0, 0.0, 1.0); return; }
  outColor = vec4(signedColor(mij / M[0][0]), 1.0);
}
