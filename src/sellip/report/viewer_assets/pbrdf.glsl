// The three-lobe polarimetric BRDF of sellip.pbrdf (docs/design.md §6), per fragment, as sellip.render shades a
// ray hit: exact incident and exitant Stokes frames (no coaxial shortcut), Fresnel transmission of the diffuse
// lobe (entry o depolarizer o exit about the normal), GGX specular and single-scattering lobes that share the
// Fresnel reflection about the half vector, shading S = cos_i / d^2. Linear Stokes (s0, s1, s2): s3 stays 0 for
// dielectrics. Each function names the Python one it mirrors (src/sellip/{polar,fresnel,microfacet,pbrdf}.py).
// GLSL mat3 are column-major: m[column][row].

const float PI = 3.141592653589793;

vec3 safeNormalize(vec3 v, vec3 fallback) {  // polar.safe_normalize
  float s = dot(v, v);
  return s > 1e-30 ? v * inversesqrt(s) : fallback;
}

vec2 frameRotation(vec3 forward, vec3 current, vec3 target) {  // polar.frame_rotation_terms: (cos 2t, sin 2t)
  float c = dot(current, target);
  float s = dot(forward, cross(current, target));
  return vec2(c * c - s * s, 2.0 * s * c);
}

mat3 rotator(vec2 cs) {  // polar.rotator_from_cos_sin, 3x3 linear block; rows (1,0,0), (0,c,s), (0,-s,c)
  return mat3(1.0, 0.0, 0.0,  0.0, cs.x, -cs.y,  0.0, cs.y, cs.x);
}

vec3 frameXAxis(vec3 forward, vec3 referenceY) {  // polar.frame_x_axis
  vec3 y = safeNormalize(referenceY - dot(referenceY, forward) * forward, vec3(0.0));
  return cross(y, forward);
}

vec3 orthogonalXAxis(vec3 forward, vec3 referenceX) {  // polar.orthogonal_x_axis
  return safeNormalize(referenceX - dot(referenceX, forward) * forward, vec3(0.0));
}

vec3 fresnelTerms(float cosTheta, float eta) {  // fresnel.fresnel -> (R+, R-, r_s r_p); T+ = 1 - R+, T- = -R-
  float ci = clamp(cosTheta, 0.0, 1.0);
  float sin2t = (1.0 - ci * ci) / (eta * eta);
  float ct = sqrt(1.0 - sin2t);
  float rs = (ci - eta * ct) / (ci + eta * ct);
  float rp = (eta * ci - ct) / (eta * ci + ct);
  return vec3(0.5 * (rs * rs + rp * rp), 0.5 * (rs * rs - rp * rp), rs * rp);
}

float ggxD(float cosH, float sigma) {  // microfacet.ggx_d
  float c = clamp(cosH, 0.0, 1.0);
  float s2 = sigma * sigma;
  float d = 1.0 + (s2 - 1.0) * c * c;
  return cosH > 0.0 ? s2 / (PI * d * d) : 0.0;
}

float smithG1(float cosTheta, float sigma) {  // microfacet.smith_g1
  float c = clamp(cosTheta, 0.0, 1.0);
  float s2 = sigma * sigma;
  return 2.0 * c / (c + sqrt(c * c + s2 * (1.0 - c * c)) + 1e-30);
}

struct Lobes {
  mat3 diffuse;     // unit-albedo diffuse Mueller block, light frame -> camera frame
  mat3 reflection;  // unit reflection block (Fresnel about the half vector), light frame -> camera frame
  float shading;    // S = cos_i / d^2, 0 where n.w_i <= 0 or n.w_o <= 0
  float cosI, cosO, cosH;
};

// pbrdf._unit_muellers + pbrdf._geometry: n, wi (to light), wo (to camera) unit world vectors, d metres.
Lobes pbrdfLobes(vec3 n, vec3 wi, vec3 wo, float d, vec3 lightAxis, vec3 cameraUp, float eta) {
  Lobes L;
  float cosI = dot(n, wi), cosO = dot(n, wo);
  bool lit = cosI > 0.0 && cosO > 0.0;
  vec3 h = safeNormalize(wi + wo, n);
  L.cosI = clamp(cosI, 0.0, 1.0);
  L.cosO = clamp(cosO, 0.0, 1.0);
  L.cosH = clamp(dot(n, h), 0.0, 1.0);
  float cosD = clamp(dot(h, wi), 0.0, 1.0);
  L.shading = lit ? cosI / (d * d) : 0.0;
  vec3 beamIn = -wi;
  vec3 xLight = orthogonalXAxis(beamIn, lightAxis);
  vec3 xCamera = frameXAxis(wo, cameraUp);
  vec3 diffuseIn = safeNormalize(cross(n, wi), xLight);
  vec3 diffuseOut = safeNormalize(cross(n, wo), xCamera);
  vec3 reflectionAxis = safeNormalize(cross(wo, wi), xLight);
  // Diffuse: only s0 survives the depolarizer: (exit column) x (entry row).
  vec3 fi = fresnelTerms(L.cosI, eta), fo = fresnelTerms(L.cosO, eta);
  vec2 entry = frameRotation(beamIn, xLight, diffuseIn);
  vec3 entryRow = vec3(1.0 - fi.x, -fi.y * entry.x, -fi.y * entry.y);
  vec2 exitRot = frameRotation(wo, diffuseOut, xCamera);
  vec3 exitColumn = vec3(1.0 - fo.x, -fo.y * exitRot.x, fo.y * exitRot.y);
  L.diffuse = mat3(exitColumn * entryRow.x, exitColumn * entryRow.y, exitColumn * entryRow.z);
  // Reflection in the s/p frame of the plane (w_i, w_o).
  vec3 fd = fresnelTerms(cosD, eta);
  mat3 F = mat3(fd.x, fd.y, 0.0,  fd.y, fd.x, 0.0,  0.0, 0.0, fd.z);
  L.reflection = rotator(frameRotation(wo, reflectionAxis, xCamera)) * F
               * rotator(frameRotation(beamIn, xLight, reflectionAxis));
  return L;
}

float lobeFactor(Lobes L, float sigma) {  // pbrdf.lobe_factor: D G / (4 cos_i cos_o), 0 where unlit
  if (L.shading <= 0.0) return 0.0;
  return ggxD(L.cosH, sigma) * smithG1(L.cosI, sigma) * smithG1(L.cosO, sigma) / (4.0 * L.cosI * L.cosO);
}
