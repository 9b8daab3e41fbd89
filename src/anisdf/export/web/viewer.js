"use strict";
// What every anisdf asset page shares (inlined before the page's own script by anisdf.export.web_page): the glb
// reader, the camera (orbit controls, or an exact OpenCV camera set by window.anisdf.setCamera), the WebGL2 helpers
// and the supersampling resolve pass that anisdf.export.reference_renderer.resolve computes in Python.
// A page defines draw() (its mesh pass, through drawFrame) and calls startViewer(load).

// supersampling: the scene is drawn s times larger; each pixel is then the mean of its own s x s samples (uSigma 0)
// or a Gaussian-weighted mean (sigma uSigma pixels) of the samples within 3 sigma of its centre in x and in y
const RESOLVE_VS = `#version 300 es
void main() { vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0); gl_Position = vec4(p, 0.0, 1.0); }`;
const RESOLVE_FS = `#version 300 es
precision highp float; precision highp int; precision highp sampler2D;
uniform sampler2D uImage; uniform int uS; uniform float uSigma;
out vec4 outColor;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  vec3 c = vec3(0.0);
  if (uSigma <= 0.0) {
    for (int y = 0; y < uS; y++) for (int x = 0; x < uS; x++) c += texelFetch(uImage, p * uS + ivec2(x, y), 0).rgb;
    outColor = vec4(c / float(uS * uS), 1.0);
    return;
  }
  float s = float(uS), reach = 3.0 * uSigma, k = -0.5 / (uSigma * uSigma);
  vec2 centre = vec2(p) + 0.5;
  ivec2 lo = max(ivec2(ceil((centre - reach) * s - 0.5)), ivec2(0));
  ivec2 hi = min(ivec2(floor((centre + reach) * s - 0.5)), textureSize(uImage, 0) - 1);
  float total = 0.0;
  for (int y = lo.y; y <= hi.y; y++) {
    float dy = (float(y) + 0.5) / s - centre.y, wy = exp(k * dy * dy);
    for (int x = lo.x; x <= hi.x; x++) {
      float dx = (float(x) + 0.5) / s - centre.x, w = wy * exp(k * dx * dx);
      c += w * texelFetch(uImage, ivec2(x, y), 0).rgb;
      total += w;
    }
  }
  outColor = vec4(c / total, 1.0);
}`;

const data = JSON.parse(document.getElementById("anisdf-data").textContent);
const man = data.manifest;
const canvas = document.getElementById("view");
const hud = { fps: document.getElementById("fps"), info: document.getElementById("info"),
              ss: document.getElementById("ss") };
const query = new URLSearchParams(location.search);
hud.ss.value = String(Math.max(1, Math.min(4, parseInt(query.get("ss") || man.supersample || 1, 10) || 1)));
window.anisdf = { ready: false, frames: 0, error: null, fps: 0 };

function fail(msg) {
  window.anisdf.error = msg;
  hud.fps.textContent = "error: " + msg;
  throw new Error(msg);
}
function b64(s) {
  const bin = atob(s), out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}
function b64floats(s) { const b = b64(s); return new Float32Array(b.buffer, b.byteOffset, b.byteLength / 4); }
// the first primitive of a glb (tightly packed views, as anisdf writes them); images: the PNG bytes of the material's
// textures by glTF name (baseColorTexture, metallicRoughnessTexture)
function parseGlb(bytes) {
  const dv = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  if (dv.getUint32(0, true) !== 0x46546C67) fail("model.glb: not a glb");
  let off = 12, json = null, bin = null;
  while (off < bytes.byteLength) {
    const len = dv.getUint32(off, true), type = dv.getUint32(off + 4, true);
    const chunk = bytes.subarray(off + 8, off + 8 + len);
    if (type === 0x4E4F534A) json = JSON.parse(new TextDecoder().decode(chunk));
    else if (type === 0x004E4942) bin = chunk;
    off += 8 + len;
  }
  const view = (i) => { const v = json.bufferViews[i]; return bin.slice(v.byteOffset || 0, (v.byteOffset || 0) + v.byteLength); };
  const accessor = (i, T) => { const a = json.accessors[i]; const b = view(a.bufferView);
    return new T(b.buffer, b.byteOffset + (a.byteOffset || 0), a.count * { SCALAR: 1, VEC2: 2, VEC3: 3 }[a.type]); };
  const prim = json.meshes[0].primitives[0], at = prim.attributes;
  const pbr = json.materials[prim.material].pbrMetallicRoughness, images = {};
  for (const name of ["baseColorTexture", "metallicRoughnessTexture"]) {
    if (pbr[name]) images[name] = view(json.images[json.textures[pbr[name].index].source].bufferView);
  }
  return { pos: accessor(at.POSITION, Float32Array), normal: accessor(at.NORMAL, Float32Array),
           uv: accessor(at.TEXCOORD_0, Float32Array), index: accessor(prim.indices, Uint32Array),
           images, min: json.accessors[at.POSITION].min, max: json.accessors[at.POSITION].max };
}
const bitmap = (bytes) => createImageBitmap(new Blob([bytes], { type: "image/png" }),
                                            { premultiplyAlpha: "none", colorSpaceConversion: "none" });

// ---------------------------------------------------------------------------------------------- small vector maths
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => mul(a, 1 / Math.hypot(a[0], a[1], a[2]));

// ---------------------------------------------------------------------------------------------- camera
// OpenCV convention (x right, y down, z forward), pixel centres at i + 0.5, like anisdf's cameras.
const cam = { target: [0, 0, 0], radius: 1, up: [0, 0, 1], dist: 3, az: 0, el: 0, fovy: 0.7, pan: [0, 0, 0],
              exact: null };
function orbitBasis() {
  const u = cam.up, h = Math.abs(u[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const e1 = norm(cross(h, u));
  return [e1, cross(u, e1), u];
}
function orbitFrom(eye) {
  const [e1, e2, u] = orbitBasis(), v = sub(eye, cam.target);
  cam.dist = Math.hypot(v[0], v[1], v[2]);
  cam.az = Math.atan2(dot(v, e2), dot(v, e1));
  cam.el = Math.asin(Math.max(-1, Math.min(1, dot(v, u) / cam.dist)));
}
function currentView() {
  const w = canvas.width, h = canvas.height;
  if (cam.exact) {
    const m = cam.exact.c2w;
    return { R: [[m[0][0], m[0][1], m[0][2]], [m[1][0], m[1][1], m[1][2]], [m[2][0], m[2][1], m[2][2]]],
             eye: [m[0][3], m[1][3], m[2][3]], fx: cam.exact.fx, fy: cam.exact.fy, cx: cam.exact.cx, cy: cam.exact.cy };
  }
  const [e1, e2, u] = orbitBasis();
  const dir = add(mul(add(mul(e1, Math.cos(cam.az)), mul(e2, Math.sin(cam.az))), Math.cos(cam.el)), mul(u, Math.sin(cam.el)));
  const target = add(cam.target, cam.pan), eye = add(target, mul(dir, cam.dist));
  const z = norm(sub(target, eye)), x = norm(cross(z, cam.up)), y = cross(z, x);
  const fy = 0.5 * h / Math.tan(0.5 * cam.fovy);
  return { R: [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]], eye, fx: fy, fy, cx: w / 2, cy: h / 2 };
}
function viewProj(v, s) {
  const w = canvas.width * s, h = canvas.height * s, R = v.R;
  const zc = (R[0][2] * (cam.target[0] - v.eye[0]) + R[1][2] * (cam.target[1] - v.eye[1]) + R[2][2] * (cam.target[2] - v.eye[2]));
  const far = zc + 2 * cam.radius + Math.hypot(...cam.pan), near = Math.max(far * 1e-4, zc - 2 * cam.radius - Math.hypot(...cam.pan));
  const A = (far + near) / (far - near), B = -2 * far * near / (far - near);
  // rows of the projection applied to camera coordinates (see anisdf.export.reference_renderer for the pixel
  // convention); an s-times larger image: focal lengths and principal point scale by s (pixel centres at (i + 0.5) / s)
  const P = [[2 * s * v.fx / w, 0, 2 * s * v.cx / w - 1, 0], [0, -2 * s * v.fy / h, 1 - 2 * s * v.cy / h, 0],
             [0, 0, A, B], [0, 0, 1, 0]];
  const V = [[R[0][0], R[1][0], R[2][0], 0], [R[0][1], R[1][1], R[2][1], 0], [R[0][2], R[1][2], R[2][2], 0], [0, 0, 0, 1]];
  for (let i = 0; i < 3; i++) V[i][3] = -(V[i][0] * v.eye[0] + V[i][1] * v.eye[1] + V[i][2] * v.eye[2]);
  const out = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0; for (let k = 0; k < 4; k++) s += P[r][k] * V[k][c];
    out[c * 4 + r] = s;  // column-major
  }
  return out;
}

// ---------------------------------------------------------------------------------------------- WebGL2
const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, preserveDrawingBuffer: true });
if (!gl) fail("this browser has no WebGL2");
function shader(type, src) {
  const s = gl.createShader(type); gl.shaderSource(s, src); gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) fail(gl.getShaderInfoLog(s));
  return s;
}
function program(vs, fs) {
  const p = gl.createProgram();
  gl.attachShader(p, shader(gl.VERTEX_SHADER, vs)); gl.attachShader(p, shader(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) fail(gl.getProgramInfoLog(p));
  return p;
}
const resolveProg = program(RESOLVE_VS, RESOLVE_FS);
const RESOLVE_UNIT = 7;  // the texture unit of the supersampled image (pages keep their own textures below it)
const fbo = { fb: gl.createFramebuffer(), tex: gl.createTexture(), depth: gl.createRenderbuffer(), w: 0, h: 0 };
function texParams(target) {
  gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, gl.NEAREST); gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.texParameteri(target, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE); gl.texParameteri(target, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
}
function renderTarget(w, h) {
  if (fbo.w !== w || fbo.h !== h) {
    gl.activeTexture(gl.TEXTURE0 + RESOLVE_UNIT); gl.bindTexture(gl.TEXTURE_2D, fbo.tex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, w, h, 0, gl.RGBA, gl.UNSIGNED_BYTE, null); texParams(gl.TEXTURE_2D);
    gl.bindRenderbuffer(gl.RENDERBUFFER, fbo.depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo.fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, fbo.tex, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, fbo.depth);
    fbo.w = w; fbo.h = h;
  }
  gl.bindFramebuffer(gl.FRAMEBUFFER, fbo.fb);
}
// the mesh's vertex array (positions, normals, UVs at locations 0, 1, 2) and index count
const mesh = { vao: null, count: 0 };
function uploadMesh(glb) {
  mesh.vao = gl.createVertexArray(); gl.bindVertexArray(mesh.vao);
  [[glb.pos, 3], [glb.normal, 3], [glb.uv, 2]].forEach(([arr, n], i) => {
    gl.bindBuffer(gl.ARRAY_BUFFER, gl.createBuffer()); gl.bufferData(gl.ARRAY_BUFFER, arr, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(i); gl.vertexAttribPointer(i, n, gl.FLOAT, false, 0, 0);
  });
  gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, gl.createBuffer()); gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, glb.index, gl.STATIC_DRAW);
  mesh.count = glb.index.length;
  gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false); gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
  gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE); gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  cam.target = [0, 1, 2].map((i) => 0.5 * (glb.min[i] + glb.max[i]));
  cam.radius = 0.5 * Math.hypot(...[0, 1, 2].map((i) => glb.max[i] - glb.min[i]));
  if (man.up) cam.up = norm(man.up);
}
function texture2d(unit, internal, w, h, format, type, pixels) {
  gl.activeTexture(gl.TEXTURE0 + unit); gl.bindTexture(gl.TEXTURE_2D, gl.createTexture());
  gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, pixels);
  texParams(gl.TEXTURE_2D);
}

function reset() {
  cam.exact = null; cam.pan = [0, 0, 0];
  const c = man.camera;
  if (c) {
    cam.fovy = 2 * Math.atan(0.5 * c.height / c.fy);
    orbitFrom([c.c2w[0][3], c.c2w[1][3], c.c2w[2][3]]);
  } else { cam.dist = 3 * cam.radius; cam.az = 0.5; cam.el = 0.4; }
}
function resize() {
  if (cam.exact) return;
  const w = Math.max(1, Math.round(window.innerWidth * devicePixelRatio)), h = Math.max(1, Math.round(window.innerHeight * devicePixelRatio));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  canvas.style.width = window.innerWidth + "px"; canvas.style.height = window.innerHeight + "px";
}
// one frame: the page's mesh pass drawMesh(view, s, prog) into an s-times larger target, cleared to background
// (sRGB-encoded, as the samples), then resolved into the canvas
function drawFrame(prog, drawMesh, background = [1, 1, 1]) {
  resize();
  const v = currentView(), w = canvas.width, h = canvas.height;
  const limit = Math.min(gl.getParameter(gl.MAX_TEXTURE_SIZE), gl.getParameter(gl.MAX_RENDERBUFFER_SIZE));
  const s = Math.max(1, Math.min(parseInt(hud.ss.value, 10), Math.floor(limit / Math.max(w, h))));
  const sigma = Number(man.pixel_filter || 0), resolved = s > 1 || sigma > 0;
  if (resolved) renderTarget(w * s, h * s); else gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  gl.useProgram(prog); gl.bindVertexArray(mesh.vao);
  gl.enable(gl.DEPTH_TEST);
  gl.viewport(0, 0, w * s, h * s);
  gl.clearColor(background[0], background[1], background[2], 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  gl.uniformMatrix4fv(gl.getUniformLocation(prog, "uViewProj"), false, viewProj(v, s));
  gl.uniform3f(gl.getUniformLocation(prog, "uEye"), v.eye[0], v.eye[1], v.eye[2]);
  drawMesh(v, s);
  gl.drawElements(gl.TRIANGLES, mesh.count, gl.UNSIGNED_INT, 0);
  if (resolved) {
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, w, h); gl.disable(gl.DEPTH_TEST);
    gl.useProgram(resolveProg); gl.bindVertexArray(null);
    gl.activeTexture(gl.TEXTURE0 + RESOLVE_UNIT); gl.bindTexture(gl.TEXTURE_2D, fbo.tex);
    gl.uniform1i(gl.getUniformLocation(resolveProg, "uImage"), RESOLVE_UNIT);
    gl.uniform1i(gl.getUniformLocation(resolveProg, "uS"), s);
    gl.uniform1f(gl.getUniformLocation(resolveProg, "uSigma"), sigma);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }
}

// ---------------------------------------------------------------------------------------------- frame loop, controls
function startViewer(load) {
  let fpsStart = performance.now(), fpsFrames = 0;
  function frame(now) {
    draw();
    window.anisdf.frames++; fpsFrames++;
    if (now - fpsStart >= 500) {
      window.anisdf.fps = 1000 * fpsFrames / (now - fpsStart);
      hud.fps.textContent = `${window.anisdf.fps.toFixed(1)} fps`;
      fpsStart = now; fpsFrames = 0;
    }
    requestAnimationFrame(frame);
  }
  // an exact camera (c2w: 4x4 or 3x4 rows, OpenCV, the asset's frame; intrinsics in pixels); the canvas takes its size
  window.anisdf.setCamera = (c) => {
    cam.exact = c;
    canvas.width = c.width; canvas.height = c.height;
    canvas.style.width = c.width + "px"; canvas.style.height = c.height + "px";
    draw();
  };
  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    if (cam.exact) { const v = currentView(); cam.exact = null; orbitFrom(v.eye); }
    drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) {
      const v = currentView(), s = cam.dist * Math.tan(0.5 * cam.fovy) * 2 / window.innerHeight;
      const right = [v.R[0][0], v.R[1][0], v.R[2][0]], down = [v.R[0][1], v.R[1][1], v.R[2][1]];
      cam.pan = add(cam.pan, add(mul(right, -dx * s), mul(down, -dy * s)));
    } else {
      cam.az -= dx * 0.008;
      cam.el = Math.max(-1.55, Math.min(1.55, cam.el + dy * 0.008));
    }
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    if (cam.exact) { const v = currentView(); cam.exact = null; orbitFrom(v.eye); }
    cam.dist *= Math.exp(e.deltaY * 0.001);
  }, { passive: false });
  canvas.addEventListener("dblclick", reset);
  load().then(() => {
    reset();
    window.anisdf.ready = true;
    requestAnimationFrame(frame);
  }).catch((e) => { window.anisdf.error = String(e); hud.fps.textContent = "error: " + e; });
}
