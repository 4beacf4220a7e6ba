// sellip viewer: plain WebGL2, no library, no build step. Reads window.SELLIP_MODEL (model.js: metadata and the
// model's arrays as base64) and window.SELLIP_SHADERS (shaders.js: the GLSL of viewer_assets/*.glsl), both loaded by
// <script> tags so that the page works opened from disk (file://: no fetch of local files) and served.
// Camera model: OpenCV pinhole with COLMAP cam_from_world poses (x_cam = R x_world + t), as sellip's renderer.
// The test API is window.sellipViewer (bottom of this file).
"use strict";

(function () {
  const started = performance.now();
  const MODEL = window.SELLIP_MODEL;
  const SHADERS = window.SELLIP_SHADERS;
  const meta = MODEL.meta;
  const MAP_INDEX = { eta: 0, rho_d: 1, rho_s: 2, sigma_s: 3, rho_ss: 4, sigma_ss: 5, normal: 6, confidence: 7,
                      model: 8, cluster: 9 };
  const KIND_INDEX = { scalar: 0, rgb: 1, normal: 2, category: 3 };
  const MODES = { relight: 0, aolp: 1, dop: 2, mueller: 3, map: 4 };

  // ------------------------------------------------------------------ small linear algebra (3x3 row-major arrays)
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => Math.sqrt(dot(a, a));
  const unit = (a) => scale(a, 1 / (norm(a) || 1));
  const row = (R, i) => [R[3 * i], R[3 * i + 1], R[3 * i + 2]];
  const mulT = (R, v) => [R[0] * v[0] + R[3] * v[1] + R[6] * v[2], R[1] * v[0] + R[4] * v[1] + R[7] * v[2],
                          R[2] * v[0] + R[5] * v[1] + R[8] * v[2]];  // R^T v
  const mul = (R, v) => [dot(row(R, 0), v), dot(row(R, 1), v), dot(row(R, 2), v)];
  function axisRotation(axis, angle) {  // Rodrigues, row-major
    const [x, y, z] = unit(axis), c = Math.cos(angle), s = Math.sin(angle), C = 1 - c;
    return [c + x * x * C, x * y * C - z * s, x * z * C + y * s,
            y * x * C + z * s, c + y * y * C, y * z * C - x * s,
            z * x * C - y * s, z * y * C + x * s, c + z * z * C];
  }
  const center = (cam) => scale(mulT(cam.R, cam.t), -1);

  // ------------------------------------------------------------------ data
  async function decode(base64) {
    try {
      const response = await fetch("data:application/octet-stream;base64," + base64);
      return await response.arrayBuffer();
    } catch (error) {  // some browsers refuse data: fetches: decode by hand
      const text = atob(base64), bytes = new Uint8Array(text.length);
      for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
      return bytes.buffer;
    }
  }

  const canvas = document.getElementById("view");
  const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: true });
  const status = document.getElementById("status");
  if (!gl) { status.textContent = "This browser has no WebGL2: the viewer cannot run."; return; }
  const floatTargets = !!gl.getExtension("EXT_color_buffer_float");

  function compile(vertexSource, fragmentSource) {
    const program = gl.createProgram();
    for (const [type, source] of [[gl.VERTEX_SHADER, vertexSource], [gl.FRAGMENT_SHADER, fragmentSource]]) {
      const shader = gl.createShader(type);
      gl.shaderSource(shader, source);
      gl.compileShader(shader);
      if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
      gl.attachShader(program, shader);
    }
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    const uniforms = {};
    const count = gl.getProgramParameter(program, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < count; i++) {
      const name = gl.getActiveUniform(program, i).name;
      uniforms[name] = gl.getUniformLocation(program, name);
    }
    return { program, uniforms };
  }

  const state = {
    mode: "relight", map: "eta", element: [0, 0], exposure: meta.exposure, srgb: true, dopMax: 1, shadows: true,
    useAnalyzer: false, analyzer: 0, light: "flash", free: { azimuth: 0.6, elevation: 0.5, distance: meta.distance },
    freePolarized: true, frusta: false, view: null, size: [meta.intrinsics.width, meta.intrinsics.height],
    camera: null, target: meta.center.slice(), hover: null,
  };
  let arrays = null, mesh = null, lines = null, meshProgram = null, lineProgram = null, lineCount = 0;
  let pickTarget = null, positionBuffer = null, shadowProgram = null, shadow = null;
  const SHADOW_SIZE = 2048;  // texels: 0.08 mm at the demo owl (1024: 48.9 dB instead of 55.8 at its view v004)

  function capturedCamera(index) {
    const c = meta.cameras[index];
    return { R: c.R.slice(), t: c.t.slice() };
  }

  function defaultCamera() {  // the first captured view, or one looking at the object from its radius
    if (meta.cameras.length) return capturedCamera(0);
    const eye = add(meta.center, [0, -meta.distance, 0]);
    const forward = unit(sub(meta.center, eye)), down = scale(meta.up, -1);
    const right = unit(cross(down, forward)), y = cross(forward, right);
    const R = [...right, ...y, ...forward];
    return { R, t: scale(mul(R, eye), -1) };
  }

  // ------------------------------------------------------------------ GL resources
  function buildMesh() {
    meshProgram = compile(SHADERS.mesh_vert, SHADERS.mesh_frag);
    lineProgram = compile(SHADERS.line_vert, SHADERS.line_frag);
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const constants = { eta: [1.5], rho_d: [0.5, 0.5, 0.5], rho_s: [0], sigma_s: [0.3], rho_ss: [0, 0, 0],
                        sigma_ss: [0.5], confidence: [1], model: [0], cluster: [0] };
    for (const [name, size] of [["position", 3], ["normal", 3], ["eta", 1], ["rho_d", 3], ["rho_s", 1],
                                ["sigma_s", 1], ["rho_ss", 3], ["sigma_ss", 1], ["confidence", 1], ["model", 1],
                                ["cluster", 1]]) {
      const location = gl.getAttribLocation(meshProgram.program, "a_" + name);
      if (location < 0) continue;
      if (arrays[name]) {
        const buffer = gl.createBuffer();
        if (name === "position") positionBuffer = buffer;
        gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
        gl.bufferData(gl.ARRAY_BUFFER, arrays[name], gl.STATIC_DRAW);
        gl.enableVertexAttribArray(location);
        gl.vertexAttribPointer(location, size, gl.FLOAT, false, 0, 0);
      } else {
        gl.disableVertexAttribArray(location);
        const v = constants[name];
        if (size === 1) gl.vertexAttrib1f(location, v[0]); else gl.vertexAttrib3f(location, v[0], v[1], v[2]);
      }
    }
    const index = gl.createBuffer();
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, index);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, arrays.indices, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    mesh = { vao, count: arrays.indices.length };
    if (floatTargets) {  // the shadow pass: positions only, the same triangles
      shadowProgram = compile(SHADERS.shadow_vert, SHADERS.shadow_frag);
      const shadowVao = gl.createVertexArray();
      gl.bindVertexArray(shadowVao);
      const location = gl.getAttribLocation(shadowProgram.program, "a_position");
      gl.bindBuffer(gl.ARRAY_BUFFER, positionBuffer);
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, 3, gl.FLOAT, false, 0, 0);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, index);
      gl.bindVertexArray(null);
      const texture = gl.createTexture(), depth = gl.createRenderbuffer(), fb = gl.createFramebuffer();
      gl.bindTexture(gl.TEXTURE_2D, texture);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.R32F, SHADOW_SIZE, SHADOW_SIZE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, SHADOW_SIZE, SHADOW_SIZE);
      gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      shadow = { vao: shadowVao, fb, texture, key: null, camera: null };
    }
    lines = { vao: gl.createVertexArray(), position: gl.createBuffer(), color: gl.createBuffer() };
  }

  function buildLines() {  // camera frusta (the snapped one yellow) and the light (a cross)
    const points = [], colors = [];
    const segment = (a, b, color) => { points.push(...a, ...b); colors.push(...color, ...color); };
    const K = meta.intrinsics;
    if (state.frusta) {
      meta.cameras.forEach((c, i) => {
        const C = scale(mulT(c.R, c.t), -1), depth = 0.25 * meta.distance;
        const corner = (u, v) => add(C, mulT(c.R, [(u - K.cx) / K.fx * depth, (v - K.cy) / K.fy * depth, depth]));
        const q = [corner(0, 0), corner(K.width, 0), corner(K.width, K.height), corner(0, K.height)];
        const color = i === state.view ? [1, 0.85, 0.1] : [0.55, 0.6, 0.7];
        for (let k = 0; k < 4; k++) { segment(C, q[k], color); segment(q[k], q[(k + 1) % 4], color); }
        segment(q[0], add(q[0], scale(sub(q[1], q[0]), 0.5)), [1, 0.3, 0.3]);  // top edge half red: image up
      });
    }
    if (state.light === "free") {
      const p = lightSetup().position, r = 0.05 * meta.distance;
      for (const axis of [[1, 0, 0], [0, 1, 0], [0, 0, 1]]) segment(sub(p, scale(axis, r)), add(p, scale(axis, r)), [1, 1, 0.4]);
    }
    gl.bindVertexArray(lines.vao);
    for (const [name, data, buffer] of [["a_position", points, lines.position], ["a_color", colors, lines.color]]) {
      const location = gl.getAttribLocation(lineProgram.program, name);
      gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(data), gl.DYNAMIC_DRAW);
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, 3, gl.FLOAT, false, 0, 0);
    }
    gl.bindVertexArray(null);
    lineCount = points.length / 3;
  }

  // ------------------------------------------------------------------ light
  function lightSetup() {
    const cam = state.camera;
    if (state.light === "flash") {  // the rig's polarized flash riding on the virtual camera (sellip.render.flash_light)
      const p = meta.light.position_m, phi = meta.light.polarizer_deg * Math.PI / 180;
      return { position: mulT(cam.R, sub(p, cam.t)), axis: mulT(cam.R, [Math.cos(phi), -Math.sin(phi), 0]),
               stokes: [1, 1, 0] };
    }
    const up = meta.up, e1 = unit(Math.abs(up[0]) < 0.9 ? cross(up, [1, 0, 0]) : cross(up, [0, 1, 0]));
    const e2 = cross(up, e1), f = state.free;
    const direction = add(scale(add(scale(e1, Math.cos(f.azimuth)), scale(e2, Math.sin(f.azimuth))),
                                Math.cos(f.elevation)), scale(up, Math.sin(f.elevation)));
    return { position: add(state.target, scale(direction, f.distance)), axis: row(cam.R, 0),
             stokes: state.freePolarized ? [1, 1, 0] : [1, 0, 0] };
  }

  function freeLightFromCamera(dAzimuth, dElevation) {  // the free light where the camera is, turned by the offsets
    const up = meta.up, e1 = unit(Math.abs(up[0]) < 0.9 ? cross(up, [1, 0, 0]) : cross(up, [0, 1, 0]));
    const e2 = cross(up, e1), d = unit(sub(center(state.camera), state.target));
    state.free.azimuth = Math.atan2(dot(d, e2), dot(d, e1)) + dAzimuth;
    state.free.elevation = Math.max(-1.5, Math.min(1.5, Math.asin(Math.max(-1, Math.min(1, dot(d, up)))) + dElevation));
    state.free.distance = norm(sub(center(state.camera), state.target));
  }

  // ------------------------------------------------------------------ drawing
  function setCameraUniforms(uniforms, width, height) {
    const cam = state.camera, K = meta.intrinsics;
    const s = width / K.width;
    gl.uniformMatrix3fv(uniforms.u_R, true, new Float32Array(cam.R));
    gl.uniform3fv(uniforms.u_t, cam.t);
    gl.uniform4f(uniforms.u_K, K.fx * s, K.fy * s, (K.cx + 0.5) * s - 0.5, (K.cy + 0.5) * s - 0.5);
    gl.uniform2f(uniforms.u_size, width, height);
    gl.uniform2f(uniforms.u_depth, 0.01 * meta.distance, 100 * meta.distance);
  }

  function shadowCamera(position) {  // a pinhole at the light aimed at the object, its bounding sphere in view
    const forward = unit(sub(meta.center, position)), distance = norm(sub(meta.center, position));
    const helper = Math.abs(forward[2]) < 0.9 ? [0, 0, 1] : [1, 0, 0];
    const right = unit(cross(forward, helper)), down = cross(forward, right);
    const R = [...right, ...down, ...forward];
    const halfAngle = Math.asin(Math.min(0.99, 1.05 * meta.radius / distance));
    const f = (SHADOW_SIZE / 2) / Math.tan(halfAngle);
    return { R, t: scale(mul(R, position), -1), K: [f, f, SHADOW_SIZE / 2 - 0.5, SHADOW_SIZE / 2 - 0.5],
             texel: distance / f,  // metres per shadow-map texel at the object
             depth: [Math.max(1e-4, distance - 2 * meta.radius), distance + 2 * meta.radius] };
  }

  function updateShadowMap(light) {  // re-rendered only when the light moves
    const key = light.position.join(",");
    if (!shadow || shadow.key === key) return;
    const cam = shadowCamera(light.position), u = shadowProgram.uniforms;
    gl.bindFramebuffer(gl.FRAMEBUFFER, shadow.fb);
    gl.viewport(0, 0, SHADOW_SIZE, SHADOW_SIZE);
    gl.clearColor(1e30, 0, 0, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.useProgram(shadowProgram.program);
    gl.uniformMatrix3fv(u.u_R, true, new Float32Array(cam.R));
    gl.uniform3fv(u.u_t, cam.t);
    gl.uniform4fv(u.u_K, cam.K);
    gl.uniform2f(u.u_size, SHADOW_SIZE, SHADOW_SIZE);
    gl.uniform2fv(u.u_depth, cam.depth);
    gl.uniform3fv(u.u_lightPosition, light.position);
    gl.bindVertexArray(shadow.vao);
    gl.drawElements(gl.TRIANGLES, mesh.count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    shadow.key = key;
    shadow.camera = cam;
  }

  function drawMesh(mode, width, height, element) {
    const u = meshProgram.uniforms, light = lightSetup(), map = meta.maps[state.map] || {};
    const shadows = state.shadows && !!shadow && mode !== 4 && mode !== 5;
    if (shadows) updateShadowMap(light);
    gl.useProgram(meshProgram.program);
    setCameraUniforms(u, width, height);
    gl.uniform1i(u.u_mode, mode);
    gl.uniform3fv(u.u_cameraCenter, center(state.camera));
    gl.uniform3fv(u.u_cameraUp, scale(row(state.camera.R, 1), -1));
    gl.uniform3fv(u.u_lightPosition, light.position);
    gl.uniform3fv(u.u_lightAxis, light.axis);
    gl.uniform3fv(u.u_lightStokes, light.stokes);
    gl.uniform1f(u.u_exposure, state.exposure);
    gl.uniform1i(u.u_srgb, state.srgb ? 1 : 0);
    gl.uniform1i(u.u_useAnalyzer, state.useAnalyzer ? 1 : 0);
    gl.uniform1f(u.u_analyzer, state.analyzer * Math.PI / 180);
    gl.uniform2i(u.u_element, element[0], element[1]);
    gl.uniform1i(u.u_map, MAP_INDEX[state.map]);
    gl.uniform1i(u.u_mapKind, KIND_INDEX[map.kind || "scalar"]);
    gl.uniform2f(u.u_range, map.low ?? 0, map.high ?? 1);
    gl.uniform1f(u.u_darkLevel, meta.dark_level);
    gl.uniform1f(u.u_dopMax, state.dopMax);
    gl.uniform1i(u.u_shadows, shadows ? 1 : 0);
    if (shadows) {
      const cam = shadow.camera;
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, shadow.texture);
      gl.uniform1i(u.u_shadowMap, 0);
      gl.uniformMatrix3fv(u.u_shadowR, true, new Float32Array(cam.R));
      gl.uniform3fv(u.u_shadowT, cam.t);
      gl.uniform4fv(u.u_shadowK, cam.K);
      gl.uniform1f(u.u_shadowSize, SHADOW_SIZE);
      gl.uniform1f(u.u_shadowBias, cam.texel);
    }
    gl.bindVertexArray(mesh.vao);
    gl.drawElements(gl.TRIANGLES, mesh.count, gl.UNSIGNED_INT, 0);
  }

  function render() {
    const [width, height] = state.size;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, width, height);
    gl.clearColor(0, 0, 0, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.disable(gl.CULL_FACE);  // as the ray caster of sellip.render: the nearest surface, either side
    if (state.mode === "mueller") {  // the 3x3 block, one tile per element (row 0 on top)
      const w = Math.floor(width / 3), h = Math.floor(height / 3);
      for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) {
        gl.viewport(j * w, (2 - i) * h, w, h);
        drawMesh(MODES.mueller, w, h, [i, j]);
      }
    } else {
      drawMesh(MODES[state.mode], width, height, state.element);
      if (lineCount) {
        gl.useProgram(lineProgram.program);
        setCameraUniforms(lineProgram.uniforms, width, height);
        gl.bindVertexArray(lines.vao);
        gl.drawArrays(gl.LINES, 0, lineCount);
      }
    }
    gl.bindVertexArray(null);
  }

  let pending = false;
  function requestRender() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; render(); });
  }

  // ------------------------------------------------------------------ picking: world position under the cursor
  function pick(x, y) {
    if (!floatTargets || state.mode === "mueller") return null;
    const [width, height] = state.size;
    if (!pickTarget || pickTarget.width !== width || pickTarget.height !== height) {
      const texture = gl.createTexture(), depth = gl.createRenderbuffer(), fb = gl.createFramebuffer();
      gl.bindTexture(gl.TEXTURE_2D, texture);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, width, height);
      gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, width, height);
      gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
      pickTarget = { fb, width, height };
    }
    const px = Math.floor(x), py = height - 1 - Math.floor(y);
    const pass = (mode) => {  // one pixel of a float pass: 5 world position, 6 Stokes
      gl.bindFramebuffer(gl.FRAMEBUFFER, pickTarget.fb);
      gl.viewport(0, 0, width, height);
      gl.enable(gl.SCISSOR_TEST);
      gl.scissor(px, py, 1, 1);
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      drawMesh(mode, width, height, [0, 0]);
      const result = new Float32Array(4);
      gl.readPixels(px, py, 1, 1, gl.RGBA, gl.FLOAT, result);
      gl.disable(gl.SCISSOR_TEST);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      return result;
    };
    const out = pass(5);
    if (out[3] < 0.5) return null;
    const stokes = pass(6);
    const p = arrays.position;
    let best = -1, bestDistance = Infinity;
    for (let i = 0; i < meta.vertices; i++) {
      const dx = p[3 * i] - out[0], dy = p[3 * i + 1] - out[1], dz = p[3 * i + 2] - out[2];
      const d = dx * dx + dy * dy + dz * dz;
      if (d < bestDistance) { bestDistance = d; best = i; }
    }
    return { vertex: best, position: [out[0], out[1], out[2]], stokes: [stokes[0], stokes[1], stokes[2]] };
  }

  function describeStokes(st) {  // the light reaching the camera through this pixel (colour-averaged)
    const [s0, s1, s2] = st, dop = s0 > 0 ? Math.hypot(s1, s2) / s0 : 0;
    const aolp = (0.5 * Math.atan2(s2, s1) * 180 / Math.PI + 180) % 180, th = state.analyzer * Math.PI / 180;
    const analyzer = 0.5 * (s0 + s1 * Math.cos(2 * th) + s2 * Math.sin(2 * th));
    return `pixel: s0 ${s0.toPrecision(4)}, DoP ${dop.toFixed(3)}, AoLP ${aolp.toFixed(1)}°, ` +
           `I(${state.analyzer}°) ${analyzer.toPrecision(4)} (relative, ${state.light} light)`;
  }

  function describeVertex(i) {
    const fmt = (v, digits = 3) => (v === undefined || v === null || !isFinite(v)) ? "–" : Number(v).toFixed(digits);
    const std = (name) => arrays[name] && isFinite(arrays[name][i]) ? ` ± ${fmt(arrays[name][i])}` : "";
    const rgb = (name) => arrays[name] ? `${fmt(arrays[name][3 * i])}, ${fmt(arrays[name][3 * i + 1])}, ${fmt(arrays[name][3 * i + 2])}` : "–";
    const one = (name) => arrays[name] ? fmt(arrays[name][i]) : "–";
    let eta = `η ${one("eta")}`;
    if (arrays.eta_vertex) {
      const own = arrays.eta_source ? arrays.eta_source[i] > 0.5 : null;
      eta += own === null ? ` (own fit ${fmt(arrays.eta_vertex[i])}${std("eta_std")})`
        : own ? ` (its own fit${std("eta_std")})` : ` (its material's; own fit ${fmt(arrays.eta_vertex[i])}${std("eta_std")})`;
    } else eta += std("eta_std");
    const model = arrays.model ? (meta.model_names[String(Math.round(arrays.model[i]))] || arrays.model[i]) : "–";
    return [`vertex ${i}`, eta, `ρ_d ${rgb("rho_d")}`, `ρ_s ${one("rho_s")}`,
            `σ_s ${one("sigma_s")}${std("sigma_s_std")}`, `ρ_ss ${rgb("rho_ss")}`, `σ_ss ${one("sigma_ss")}`,
            `normal ${rgb("normal")}`, `confidence ${one("confidence")}`, `model ${model}`,
            `cluster ${arrays.cluster ? Math.round(arrays.cluster[i]) : "–"}`].join("\n");
  }

  // ------------------------------------------------------------------ camera control
  function orbit(dx, dy) {
    const cam = state.camera, C = center(cam), angle = 0.008;
    const Q1 = axisRotation(meta.up, -dx * angle), Q2 = axisRotation(row(cam.R, 0), -dy * angle);
    const rotate = (v) => mul(Q1, mul(Q2, v));
    const R = [...rotate(row(cam.R, 0)), ...rotate(row(cam.R, 1)), ...rotate(row(cam.R, 2))];
    const C2 = add(state.target, rotate(sub(C, state.target)));
    setCamera({ R, t: scale(mul(R, C2), -1) });
  }

  function pan(dx, dy) {
    const cam = state.camera, C = center(cam);
    const k = norm(sub(C, state.target)) / meta.intrinsics.fx * (meta.intrinsics.width / state.size[0]);
    const shift = add(scale(row(cam.R, 0), -dx * k), scale(row(cam.R, 1), -dy * k));
    state.target = add(state.target, shift);
    setCamera({ R: cam.R, t: scale(mul(cam.R, add(C, shift)), -1) });
  }

  function zoom(factor) {
    const cam = state.camera, C = center(cam);
    setCamera({ R: cam.R, t: scale(mul(cam.R, add(state.target, scale(sub(C, state.target), factor))), -1) });
  }

  function setCamera(camera) { state.camera = camera; buildLines(); requestRender(); }

  function snapToView(index) {
    state.view = index;
    const cam = capturedCamera(index), C = center(cam), forward = row(cam.R, 2);
    state.target = add(C, scale(forward, dot(sub(meta.center, C), forward)));  // the object's depth on the axis
    setCamera(cam);
    document.getElementById("view-select").value = String(index);
  }

  // ------------------------------------------------------------------ colour bar and page controls
  function viridisJS(t) {
    t = Math.min(Math.max(t, 0), 1);
    const c = [[0.2777273272234177, 0.005407344544966578, 0.3340998053353061],
               [0.1050930431085774, 1.404613529898575, 1.384590162594685],
               [-0.3308618287255563, 0.214847559468213, 0.09509516302823659],
               [-4.634230498983486, -5.799100973351585, -19.33244095627987],
               [6.228269936347081, 14.17993336680509, 56.69055260068105],
               [4.776384997670288, -13.74514537774601, -65.35303263337234],
               [-5.435455855934631, 4.645852612178535, 26.3124352495832]];
    return [0, 1, 2].map((k) => { let v = c[6][k]; for (let i = 5; i >= 0; i--) v = c[i][k] + t * v; return v; });
  }
  const TAB10 = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];

  function drawColorBar() {
    const bar = document.getElementById("colorbar"), ctx = bar.getContext("2d"), label = document.getElementById("bar-label");
    ctx.clearRect(0, 0, bar.width, bar.height);
    const W = bar.width, H = 16;
    const gradient = (f, low, high, title, unitText = "") => {
      for (let x = 0; x < W; x++) { const [r, g, b] = f(x / (W - 1)); ctx.fillStyle = `rgb(${r * 255},${g * 255},${b * 255})`; ctx.fillRect(x, 0, 1, H); }
      label.textContent = `${title}: ${low} … ${high}${unitText}`;
    };
    if (state.mode === "map") {
      const m = meta.maps[state.map];
      if (m.kind === "scalar") gradient(viridisJS, m.low.toPrecision(3), m.high.toPrecision(3), m.label);
      else if (m.kind === "rgb") gradient((t) => [t, t, t], 0, m.high.toPrecision(3), m.label + " (each channel)");
      else if (m.kind === "normal") gradient((t) => [t, t, t], -1, 1, m.label + " (each axis)");
      else {
        const n = Math.round(m.high) + 1;
        for (let k = 0; k < n; k++) { ctx.fillStyle = TAB10[k % 10]; ctx.fillRect(k * W / n, 0, W / n, H); }
        const names = state.map === "model" ? meta.model_names : null;
        label.textContent = m.label + ": " + [...Array(n).keys()].map((k) => names ? `${k} ${names[String(k)]}` : k).join(" | ");
      }
    } else if (state.mode === "aolp") {
      gradient((t) => { const h = t * 6, x = 1 - Math.abs(h % 2 - 1); const c = [[1, x, 0], [x, 1, 0], [0, 1, x], [0, x, 1], [x, 0, 1], [1, 0, x]][Math.min(5, Math.floor(h))]; return c; }, "0°", "180°", "AoLP (from image x towards image up)");
    } else if (state.mode === "dop") {
      gradient((t) => [t, 0, 0], 0, state.dopMax, "DoP (linear)");
    } else if (state.mode === "mueller") {
      gradient((t) => { const v = 2 * t - 1; return v < 0 ? [1 + v, 1 + v, 1] : [1, 1 - v, 1 - v]; }, -1, 1,
               "Mueller: M00 tone-mapped (top left); Mij / M00 (rows: exitant s0 s1 s2, camera frame; columns: incident, light frame)");
    } else {
      gradient((t) => [t, t, t], 0, (1 / state.exposure).toPrecision(3),
               state.useAnalyzer ? `I(${state.analyzer}°) (relative radiance)` : "s0 (relative radiance)");
    }
  }

  function syncControls() {  // the page's controls show the state (also after the API changed it)
    const $ = (id) => document.getElementById(id);
    const radio = $("mode-" + state.mode); if (radio) radio.checked = true;
    $("map-select").value = state.map;
    $("frusta").checked = state.frusta;
    $("analyzer-on").checked = state.useAnalyzer;
    $("analyzer").value = String(state.analyzer); $("analyzer-value").textContent = `${state.analyzer}°`;
    $("light-" + state.light).checked = true;
    $("free-polarized").checked = state.freePolarized;
    $("srgb").checked = state.srgb;
    $("dop-max").value = String(state.dopMax);
    $("shadows").checked = state.shadows && floatTargets;
    const ev = Math.log2(state.exposure / meta.exposure);
    $("exposure").value = String(ev); $("exposure-value").textContent = `${ev.toFixed(2)} EV`;
  }

  function updateAll() { buildLines(); drawColorBar(); syncControls(); requestRender(); }

  function setupControls() {
    const $ = (id) => document.getElementById(id);
    const mapSelect = $("map-select");
    for (const name of Object.keys(meta.map_names)) {
      const option = document.createElement("option");
      option.value = name;
      option.textContent = meta.map_names[name];
      if (!meta.maps[name]) { option.disabled = true; option.textContent += " — " + meta.missing[name]; }
      mapSelect.appendChild(option);
    }
    const missing = Object.entries(meta.missing);
    $("missing").textContent = missing.length ? "Disabled maps: " + missing.map(([k, v]) => `${k} (${v})`).join("; ") : "";
    const viewSelect = $("view-select");
    meta.cameras.forEach((c, i) => {
      const option = document.createElement("option");
      option.value = String(i); option.textContent = c.id;
      viewSelect.appendChild(option);
    });
    if (!meta.cameras.length) { viewSelect.disabled = true; $("frusta").disabled = true; }
    document.querySelectorAll("input[name=mode]").forEach((el) => el.addEventListener("change", () => {
      state.mode = el.value; updateAll();
    }));
    mapSelect.addEventListener("change", () => { state.map = mapSelect.value; state.mode = "map"; $("mode-map").checked = true; updateAll(); });
    viewSelect.addEventListener("change", () => snapToView(Number(viewSelect.value)));
    $("frusta").addEventListener("change", () => { state.frusta = $("frusta").checked; updateAll(); });
    $("reset").addEventListener("click", () => { state.target = meta.center.slice(); state.view = null; setCamera(defaultCamera()); if (meta.cameras.length) snapToView(0); });
    $("exposure").addEventListener("input", () => { state.exposure = meta.exposure * Math.pow(2, Number($("exposure").value)); $("exposure-value").textContent = `${$("exposure").value} EV`; updateAll(); });
    $("analyzer-on").addEventListener("change", () => { state.useAnalyzer = $("analyzer-on").checked; updateAll(); });
    $("analyzer").addEventListener("input", () => { state.analyzer = Number($("analyzer").value); $("analyzer-value").textContent = `${state.analyzer}°`; updateAll(); });
    document.querySelectorAll("input[name=light]").forEach((el) => el.addEventListener("change", () => {
      if (el.value === "free" && state.light !== "free") freeLightFromCamera(0.7, 0.3);  // start beside the camera
      state.light = el.value; updateAll();
    }));
    $("free-polarized").addEventListener("change", () => { state.freePolarized = $("free-polarized").checked; updateAll(); });
    $("srgb").addEventListener("change", () => { state.srgb = $("srgb").checked; updateAll(); });
    $("shadows").addEventListener("change", () => { state.shadows = $("shadows").checked; updateAll(); });
    if (!floatTargets) { $("shadows").disabled = true; $("shadows").checked = false; }
    $("dop-max").addEventListener("change", () => { state.dopMax = Number($("dop-max").value); updateAll(); });

    let drag = null;
    canvas.addEventListener("contextmenu", (e) => e.preventDefault());
    canvas.addEventListener("mousedown", (e) => { drag = { x: e.clientX, y: e.clientY, button: e.button, shift: e.shiftKey, ctrl: e.ctrlKey }; });
    window.addEventListener("mouseup", () => { drag = null; });
    window.addEventListener("mousemove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      if (drag.shift) {  // drag the free light around the object
        state.light = "free"; $("light-free").checked = true;
        state.free.azimuth -= dx * 0.01; state.free.elevation = Math.max(-1.5, Math.min(1.5, state.free.elevation - dy * 0.01));
        updateAll();
      } else if (drag.button === 2 || drag.ctrl) pan(dx, dy);
      else orbit(dx, dy);
      state.view = null;
    });
    canvas.addEventListener("wheel", (e) => { e.preventDefault(); zoom(Math.exp(e.deltaY * 0.001)); }, { passive: false });
    let hoverTimer = null;  // pick once the cursor rests (a pick pass draws the whole mesh: slow in software GL)
    canvas.addEventListener("mousemove", (e) => {
      if (drag) return;
      const rect = canvas.getBoundingClientRect();
      const x = (e.clientX - rect.left) * canvas.width / rect.width, y = (e.clientY - rect.top) * canvas.height / rect.height;
      clearTimeout(hoverTimer);
      hoverTimer = setTimeout(() => {
        const hit = pick(x, y);
        $("hover").textContent = hit ? describeStokes(hit.stokes) + "\n" + describeVertex(hit.vertex) : "(no surface under the cursor)";
      }, 60);
    });
  }

  function materialsTable() {
    const table = document.getElementById("materials");
    if (!meta.materials || !meta.materials.rows.length) { table.textContent = "no materials table"; return; }
    const columns = meta.materials.columns;
    const head = "<tr>" + columns.map((c) => `<th>${c}</th>`).join("") + "</tr>";
    const body = meta.materials.rows.map((r) => "<tr>" + r.map((v) => `<td>${typeof v === "number" && !Number.isInteger(v) ? v.toPrecision(4) : v}</td>`).join("") + "</tr>").join("");
    table.innerHTML = head + body;
  }

  function setSize(width, height) {
    state.size = [width, height];
    canvas.width = width; canvas.height = height;
    canvas.style.width = width + "px"; canvas.style.height = height + "px";
    requestRender();
  }

  // ------------------------------------------------------------------ start
  async function start() {
    const buffer = await decode(MODEL.data);
    arrays = {};
    for (const [name, spec] of Object.entries(meta.arrays)) {
      arrays[name] = spec.dtype === "uint32" ? new Uint32Array(buffer, spec.offset, spec.length)
                                             : new Float32Array(buffer, spec.offset, spec.length);
    }
    buildMesh();
    state.camera = defaultCamera();
    const K = meta.intrinsics;  // the capture's aspect, as large as the window allows (at most 4x the capture)
    const fit = Math.max(0.25, Math.min(4, (window.innerWidth - 380) / K.width, (window.innerHeight - 140) / K.height));
    setSize(Math.round(K.width * fit), Math.round(K.height * fit));
    setupControls();
    materialsTable();
    if (meta.cameras.length) snapToView(0);
    updateAll();
    render();
    gl.finish();
    const ready = performance.now();
    api.loadMs = ready;  // since navigation start: parsing model.js, decoding, uploading, first frame
    api.startMs = ready - started;
    status.textContent = `${meta.name}: ${meta.vertices} vertices, ${meta.faces} triangles; loaded in ${(ready / 1000).toFixed(2)} s`;
    api.ready = true;
  }

  // ------------------------------------------------------------------ API for tests and scripts
  const api = {
    ready: false, loadMs: null, meta,
    setSize(width, height) { setSize(width, height); render(); },
    snapToView(idOrIndex) {
      const index = typeof idOrIndex === "number" ? idOrIndex : meta.cameras.findIndex((c) => c.id === idOrIndex);
      if (index < 0) throw new Error(`no view ${idOrIndex}`);
      snapToView(index); render();
    },
    set(options) {  // mode, map, exposure, srgb, useAnalyzer, analyzer, light, frusta, freePolarized, element
      Object.assign(state, options);
      updateAll(); render();
    },
    state: () => JSON.parse(JSON.stringify({ ...state, camera: state.camera })),
    light: () => lightSetup(),  // world position, polarizer axis and incident Stokes of the current light
    orbit(dx, dy) { orbit(dx, dy); render(); },
    zoom(factor) { zoom(factor); render(); },
    freeLightFromCamera(dAzimuth, dElevation) { freeLightFromCamera(dAzimuth, dElevation); state.light = "free"; updateAll(); render(); },
    pick(x, y) { const hit = pick(x, y); render(); return hit && { ...hit, text: describeStokes(hit.stokes) + "\n" + describeVertex(hit.vertex) }; },
    benchmark(frames) {  // frames per second of full redraws (the pixel read waits for the GPU)
      const out = new Uint8Array(4);
      render(); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, out);
      const t0 = performance.now();
      for (let i = 0; i < frames; i++) { orbit(2, 0); render(); gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, out); }
      return frames * 1000 / (performance.now() - t0);
    },
  };
  window.sellipViewer = api;
  start().catch((error) => { status.textContent = "Error: " + error.message; api.error = String(error.stack || error); });
})();
