// Colour maps of the viewer (the page's colour bars use the same functions, viewer.js).

vec3 viridis(float t) {  // matplotlib's viridis, polynomial fit (max error ~1/255)
  t = clamp(t, 0.0, 1.0);
  const vec3 c0 = vec3(0.2777273272234177, 0.005407344544966578, 0.3340998053353061);
  const vec3 c1 = vec3(0.1050930431085774, 1.404613529898575, 1.384590162594685);
  const vec3 c2 = vec3(-0.3308618287255563, 0.214847559468213, 0.09509516302823659);
  const vec3 c3 = vec3(-4.634230498983486, -5.799100973351585, -19.33244095627987);
  const vec3 c4 = vec3(6.228269936347081, 14.17993336680509, 56.69055260068105);
  const vec3 c5 = vec3(4.776384997670288, -13.74514537774601, -65.35303263337234);
  const vec3 c6 = vec3(-5.435455855934631, 4.645852612178535, 26.3124352495832);
  return c0 + t * (c1 + t * (c2 + t * (c3 + t * (c4 + t * (c5 + t * c6)))));
}

vec3 hsv2rgb(vec3 c) {
  vec3 p = abs(fract(c.xxx + vec3(0.0, 2.0 / 3.0, 1.0 / 3.0)) * 6.0 - 3.0);
  return c.z * mix(vec3(1.0), clamp(p - 1.0, 0.0, 1.0), c.y);
}

vec3 aolpColor(float angle) {  // angle in (-pi/2, pi/2]: the hue circle once over 180 degrees (0 deg red)
  float t = angle / 3.141592653589793;
  return hsv2rgb(vec3(fract(t + 1.0), 1.0, 1.0));
}

vec3 dopColor(float dop) {  // 0 black -> 1 red
  return vec3(clamp(dop, 0.0, 1.0), 0.0, 0.0);
}

vec3 signedColor(float v) {  // -1 blue, 0 white, +1 red
  float t = clamp(v, -1.0, 1.0);
  return t < 0.0 ? mix(vec3(1.0), vec3(0.0, 0.0, 1.0), -t) : mix(vec3(1.0), vec3(1.0, 0.0, 0.0), t);
}

vec3 category(int k) {  // matplotlib's tab10
  int i = k - 10 * (k / 10);
  if (i < 0) i += 10;
  vec3 table[10] = vec3[10](vec3(0.122, 0.467, 0.706), vec3(1.0, 0.498, 0.055), vec3(0.173, 0.627, 0.173),
                            vec3(0.839, 0.153, 0.157), vec3(0.580, 0.404, 0.741), vec3(0.549, 0.337, 0.294),
                            vec3(0.890, 0.467, 0.761), vec3(0.498, 0.498, 0.498), vec3(0.737, 0.741, 0.133),
                            vec3(0.090, 0.745, 0.812));
  return table[i];
}
