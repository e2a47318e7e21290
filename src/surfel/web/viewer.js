// surfel's self-contained page: the `phong`, `deferred` and `gaussian` methods of surfel in WebGL2.
// The shaders are methods/splatting.glsl itself (with web/splat_attributes.glsl decoding the
// quantized columns), so the passes are surfel's: visibility (MIN blending into RG32F),
// attribute accumulation (additive blending into two RGBA32F targets), normalization with
// deferred shading; point sprites on a guard-banded target, or instanced quads where a
// splat could outgrow it (methods/splatting.py, use_point_sprites). Above the exporter's
// point budget the points are a sequential point tree (Dachsbacher et al. 2003, survey
// section 2.2.2): the CPU draws a prefix of the list and gl/lod.glsl's vertex test picks
// the cut, at a coarser error while the camera moves. The camera is surfel.camera's. Colour
// modes are surfel.colors' (gl/colors.glsl in the splat passes; categories through the
// category pass), the pinhole fill is pinholes.glsl's (surfel.pinholes), eye-dome lighting and
// the box filter are display.glsl's.
"use strict";
(() => {
  const META = JSON.parse(document.getElementById("surfel-meta").textContent);
  const SHADERS = JSON.parse(document.getElementById("surfel-shaders").textContent);
  const GUARD = 128, MAX_SPRITE = 255, FAR = 3.0e38;
  const KERNEL_SIZE = 256, GAUSSIAN_SHARPNESS = 3.0;
  const MOVING_LOD_FACTOR = 4, MOVING_DOWNSAMPLE = 2, SETTLE_MS = 250;
  const SHADING = { lambert: 0, phong: 1, none: 2, normals: 3, depth: 4 };
  const COLOR_MODE = { rgb: 0, continuous: 1, categorical: 2 };  // gl/colors.glsl
  const PAGE_MODE = { rgb: 0, value: 1, elevation: 2, code: 3 };  // web/splat_attributes.glsl
  const ATTRIBUTES = ["a_position", "a_normal", "a_radii", "a_angle", "a_color", "a_value", "a_lod", "a_field", "a_clip0",
                      "a_clip1", "a_thickness"];
  const LOC = Object.fromEntries(ATTRIBUTES.map((name, i) => [name, i]));
  const UNIT = { kernel: 0, visibility: 1, accumColor: 2, accumNormal: 3, shaded: 4, gnormal: 5, gdepth: 6,
                 category: 7, table: 8, scratch: 10 };  // scratch: where new textures are made

  const stats = window.surfelStats = { ready: false, frames: 0, frameMs: null, medianMs: null, history: [],
                                       drawn: 0, points: META.data.count, error: null };
  const status = document.getElementById("status");
  const fail = (message) => { stats.error = message; status.textContent = "surfel: " + message; throw new Error(message); };

  // ---- small linear algebra (row-major 4x4, float64) ----------------------------------
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => Math.sqrt(dot(a, a));
  const unit = (a) => scale(a, 1 / norm(a));
  const rotate = (v, axis, angle) => {  // Rodrigues
    const k = unit(axis), c = Math.cos(angle), s = Math.sin(angle);
    return add(add(scale(v, c), scale(cross(k, v), s)), scale(k, dot(k, v) * (1 - c)));
  };

  // ---- the camera: surfel.camera.Camera, relative to the cloud's local origin -----------
  const start = META.camera;
  const cam = {};
  const resetCamera = () => Object.assign(cam, { eye: start.eye.slice(), target: start.target.slice(),
                                                 up: start.up.slice(), ortho: start.ortho_height });
  resetCamera();
  const W = start.width, H = start.height;

  function viewMatrix() {  // camera.look_at
    const f = unit(sub(cam.target, cam.eye)), s = unit(cross(f, unit(cam.up))), u = cross(s, f);
    cam.up = u;
    const rows = [s, u, scale(f, -1)];
    const m = [];
    for (const r of rows) m.push(r[0], r[1], r[2], -dot(r, cam.eye));
    m.push(0, 0, 0, 1);
    return m;
  }

  function clipPlanes(view, radius) {  // Camera.fit_clip_planes around the framing sphere
    const c = META.sphere.center;
    const d = -(view[8] * c[0] + view[9] * c[1] + view[10] * c[2] + view[11]);
    const far = Math.max(d + radius * 1.05, 1e-6);
    const near = cam.ortho ? d - radius * 1.05 : Math.max(d - radius * 1.05, far * 1e-4);
    return [near, far, d];
  }

  function projectionMatrix(near, far) {  // Camera.projection_matrix
    const p = new Array(16).fill(0), w = W, h = H;
    if (cam.ortho) {
      const oh = cam.ortho, ow = oh * w / h;
      p[0] = 2 / ow; p[5] = 2 / oh; p[3] = 1 - 2 * start.cx / w; p[7] = 2 * start.cy / h - 1;
      p[10] = -2 / (far - near); p[11] = -(far + near) / (far - near); p[15] = 1;
    } else {
      p[0] = 2 * start.fx / w; p[2] = 1 - 2 * start.cx / w; p[5] = 2 * start.fy / h; p[6] = 2 * start.cy / h - 1;
      p[10] = -(far + near) / (far - near); p[11] = -2 * far * near / (far - near); p[14] = -1;
    }
    return p;
  }

  const pixelScale = () => cam.ortho ? H / cam.ortho : start.fy;

  // ---- settings (the UI's state) ------------------------------------------------------
  const S = Object.assign({}, META.settings);

  // ---- WebGL2 ------------------------------------------------------------------------
  const canvas = document.getElementById("view");
  canvas.width = W; canvas.height = H;
  canvas.style.width = W + "px"; canvas.style.height = H + "px";
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, stencil: false,
                                           preserveDrawingBuffer: true, powerPreference: "high-performance" });
  if (!gl) fail("this browser has no WebGL2");
  for (const ext of ["EXT_color_buffer_float", "EXT_float_blend"])
    if (!gl.getExtension(ext)) fail(`WebGL2 lacks ${ext} (float render targets and their blending)`);
  const maxPoint = gl.getParameter(gl.ALIASED_POINT_SIZE_RANGE)[1];
  const debugInfo = gl.getExtension("WEBGL_debug_renderer_info");
  stats.renderer = gl.getParameter(debugInfo ? debugInfo.UNMASKED_RENDERER_WEBGL : gl.RENDERER);

  const programs = new Map();
  function program(name, defines) {
    const key = name + JSON.stringify(defines);
    if (programs.has(key)) return programs.get(key);
    const header = (stage) => "#version 300 es\nprecision highp float;\nprecision highp int;\n" +
      "precision highp sampler2D;\n#define " + stage + "\n" +
      Object.entries(defines).filter(([, v]) => v !== false)
        .map(([k, v]) => v === true ? `#define ${k}\n` : `#define ${k} ${v}\n`).join("") + "#line 1\n";
    const p = gl.createProgram();
    for (const [type, stage] of [[gl.VERTEX_SHADER, "VERTEX_SHADER"], [gl.FRAGMENT_SHADER, "FRAGMENT_SHADER"]]) {
      const s = gl.createShader(type);
      gl.shaderSource(s, header(stage) + SHADERS[name]);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) fail(`${name} ${stage}: ${gl.getShaderInfoLog(s)}`);
      gl.attachShader(p, s);
    }
    for (const [attr, loc] of Object.entries(LOC)) gl.bindAttribLocation(p, loc, attr);
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) fail(`${name}: ${gl.getProgramInfoLog(p)}`);
    const entry = { p, uniforms: new Map() };
    programs.set(key, entry);
    return entry;
  }

  function setUniforms(entry, values) {
    gl.useProgram(entry.p);
    for (const [name, value] of Object.entries(values)) {
      if (!entry.uniforms.has(name)) entry.uniforms.set(name, gl.getUniformLocation(entry.p, name));
      const loc = entry.uniforms.get(name);
      if (loc === null) continue;
      if (typeof value === "number") {
        const info = gl.getActiveUniform(entry.p, activeIndex(entry, name));
        if (info.type === gl.FLOAT) gl.uniform1f(loc, value); else gl.uniform1i(loc, value);
      } else if (value.length === 16) gl.uniformMatrix4fv(loc, true, value);
      else [null, gl.uniform1fv, gl.uniform2fv, gl.uniform3fv, gl.uniform4fv][value.length].call(gl, loc, value);
    }
  }
  function activeIndex(entry, name) {
    if (!entry.indices) {
      entry.indices = new Map();
      const count = gl.getProgramParameter(entry.p, gl.ACTIVE_UNIFORMS);
      for (let i = 0; i < count; i++) entry.indices.set(gl.getActiveUniform(entry.p, i).name, i);
    }
    return entry.indices.get(name);
  }

  function texture(w, h, internal, format, type, data = null, filter = gl.NEAREST) {
    const t = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + UNIT.scratch);
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, data);
    for (const [k, v] of [[gl.TEXTURE_MIN_FILTER, filter], [gl.TEXTURE_MAG_FILTER, filter],
                          [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]])
      gl.texParameteri(gl.TEXTURE_2D, k, v);
    return t;
  }
  function framebuffer(textures) {
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    textures.forEach((t, i) => gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, gl.TEXTURE_2D, t, 0));
    gl.drawBuffers(textures.map((_, i) => gl.COLOR_ATTACHMENT0 + i));
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) fail("float render targets are incomplete");
    return fbo;
  }
  function tableTexture(rows) {  // RGBA8, 256 entries a row (gl/colors.glsl table_entry), from [[r, g, b] 0..255]
    const height = Math.max(1, Math.ceil(rows.length / 256)), width = height > 1 ? 256 : rows.length;
    const data = new Uint8Array(width * height * 4);
    rows.forEach((c, i) => data.set([c[0], c[1], c[2], 255], 4 * i));
    return texture(width, height, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, data);
  }

  // The Gaussian kernel table of splatting.py, indexed by squared distance (R16F filters linearly).
  const kernelData = new Float32Array(KERNEL_SIZE);
  for (let i = 0; i < KERNEL_SIZE; i++) kernelData[i] = Math.exp(-GAUSSIAN_SHARPNESS * (i + 0.5) / KERNEL_SIZE);
  const kernel = texture(KERNEL_SIZE, 1, gl.R16F, gl.RED, gl.FLOAT, kernelData, gl.LINEAR);
  const colormaps = Object.fromEntries(Object.entries(META.colormaps).map(([name, rows]) => [name, tableTexture(rows)]));

  let targets = null;
  function allocate(w, h, guard) {
    if (targets && targets.key === `${w}x${h}+${guard}`) return targets;
    if (targets) {
      for (const t of targets.textures) gl.deleteTexture(t);
      for (const f of targets.fbos) gl.deleteFramebuffer(f);
    }
    const tw = w + 2 * guard, th = h + 2 * guard;
    const vis = texture(tw, th, gl.RG32F, gl.RG, gl.FLOAT);
    const acc = [0, 1].map(() => texture(tw, th, gl.RGBA32F, gl.RGBA, gl.FLOAT));
    const cat = texture(tw, th, gl.R32F, gl.RED, gl.FLOAT);
    const gbuf = [0, 1, 2].map(() => texture(w, h, gl.RGBA32F, gl.RGBA, gl.FLOAT));
    const spare = [0, 1, 2].map(() => texture(w, h, gl.RGBA32F, gl.RGBA, gl.FLOAT));  // pinholes' other round
    const fbos = [framebuffer([vis]), framebuffer(acc), framebuffer([cat]), framebuffer(gbuf), framebuffer(spare)];
    targets = { key: `${w}x${h}+${guard}`, vis, acc, cat, gbuf, spare, fbos,
                textures: [vis, ...acc, cat, ...gbuf, ...spare],
                visFbo: fbos[0], accFbo: fbos[1], catFbo: fbos[2], gFbo: fbos[3], spareFbo: fbos[4] };
    return targets;
  }

  // ---- the point data ---------------------------------------------------------------------
  let columns = null;
  const buffers = {};
  async function loadData() {
    const text = document.getElementById("surfel-data").textContent.trim();
    let bytes;
    if (Uint8Array.fromBase64) bytes = Uint8Array.fromBase64(text);
    else {
      const binary = atob(text);
      bytes = new Uint8Array(binary.length);
      for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
    }
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
    const blob = await new Response(stream).arrayBuffer();
    columns = META.data.columns;
    if (columns.lod) nodes = decodeNodes(blob);
    for (const [name, c] of Object.entries(columns)) {
      const b = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, new Uint8Array(blob, c.offset, c.bytes), gl.STATIC_DRAW);
      buffers[name] = b;
    }
  }

  const GL_TYPES = () => ({ u2: [gl.UNSIGNED_SHORT, true], u1: [gl.UNSIGNED_BYTE, true], f2: [gl.HALF_FLOAT, false] });
  let vaos = {};
  function vertexArray(instanced) {
    const key = `${instanced}:${S.color}`;
    if (vaos[key]) return vaos[key];
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const types = GL_TYPES();
    const bind = (loc, column, width, offset = 0, stride = 0) => {
      const c = columns[column], [type, normalized] = types[c.dtype];
      gl.bindBuffer(gl.ARRAY_BUFFER, buffers[column]);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, width, type, normalized, stride, offset);
      gl.vertexAttribDivisor(loc, instanced ? 1 : 0);
    };
    bind(LOC.a_position, "position", 3);
    bind(LOC.a_normal, "normal", 2);
    bind(LOC.a_radii, "radii", 2);
    bind(LOC.a_angle, "angle", 1);
    if (columns.color) bind(LOC.a_color, "color", 3);
    if (columns.lod) bind(LOC.a_lod, "lod", 3);
    if (columns.field) bind(LOC.a_field, "field", 4);
    if (columns.clip) { bind(LOC.a_clip0, "clip", 3, 0, 12); bind(LOC.a_clip1, "clip", 3, 6, 12); }
    if (columns.thickness) bind(LOC.a_thickness, "thickness", 1);  // else the generic value 0: no cap
    if (columns["value:" + S.color]) bind(LOC.a_value, "value:" + S.color, 1);
    gl.bindVertexArray(null);
    vaos[key] = vao;
    return vao;
  }
  gl.vertexAttrib3f(LOC.a_color, 1, 1, 1);  // no colours: white (docs/conventions.md)

  // ---- the level of detail: surfel.lod.sequential's prefix and k ---------------------------
  // The CPU twin of the vertex test (lod.select_sequential) runs over the prefix, as the GL
  // path does, for the count of splats drawn and the largest of them (sprites or quads).
  const search = META.data.lod_search;
  let nodes = null;
  const HALF = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const e = (h >> 10) & 31, m = h & 1023, sign = h & 0x8000 ? -1 : 1;
    HALF[h] = sign * (e === 0 ? m * 2 ** -24 : e === 31 ? (m ? NaN : Infinity) : (1 + m / 1024) * 2 ** (e - 15));
  }
  function decodeNodes(blob) {
    const c = columns, n = META.data.count, unit = META.data.length_unit;
    const lod = new Uint16Array(blob, c.lod.offset, 3 * n), radii = new Uint16Array(blob, c.radii.offset, 2 * n);
    const out = { position: new Uint16Array(blob, c.position.offset, 3 * n), emin: new Float32Array(n),
                  emax: new Float32Array(n), dparent: new Float32Array(n), radius: new Float32Array(n) };
    for (let i = 0; i < n; i++) {
      out.emin[i] = HALF[lod[3 * i]] * unit; out.emax[i] = HALF[lod[3 * i + 1]] * unit;
      out.dparent[i] = HALF[lod[3 * i + 2]] * unit;
      out.radius[i] = Math.max(Math.abs(HALF[radii[2 * i]]), HALF[radii[2 * i + 1]]) * unit;  // negated: faces the camera
    }
    return out;
  }
  function selectedRadius(prefix, k) {  // (largest radius, count) of the nodes the vertex test passes
    const lo = META.data.box_lo, size = META.data.box_size, p = nodes.position, eye = cam.eye;
    const sx = size[0] / 65535, sy = size[1] / 65535, sz = size[2] / 65535;
    let largest = 0, count = 0;
    for (let i = 0; i < prefix; i++) {
      let r = 1, d = 0;
      if (!cam.ortho) {
        const x = lo[0] + p[3 * i] * sx - eye[0], y = lo[1] + p[3 * i + 1] * sy - eye[1], z = lo[2] + p[3 * i + 2] * sz - eye[2];
        r = Math.sqrt(x * x + y * y + z * z); d = nodes.dparent[i];
      }
      if (nodes.emin[i] * k <= r && r - d < nodes.emax[i] * k) {
        count++;
        if (nodes.radius[i] > largest) largest = nodes.radius[i];
      }
    }
    return [largest, count];
  }
  function lodFrame(eps) {
    if (!search || !(eps > 0)) return { k: 0, prefix: META.data.count, drawn: META.data.count,
                                        maxRadius: META.data.max_radius };
    const k = pixelScale() / eps;
    const rNear = cam.ortho ? 1 : Math.max(norm(sub(cam.eye, META.sphere.center)) - META.sphere.radius, 0);
    let lo = 0, hi = search.bound.length;
    while (lo < hi) {  // first sample whose bound f(j) <= r_near (f is non-increasing)
      const mid = (lo + hi) >> 1;
      const f = search.bound[mid] * k + (cam.ortho ? 0 : search.dsuffix[mid]);
      if (f <= rNear) hi = mid; else lo = mid + 1;
    }
    const prefix = Math.min(lo * search.stride, META.data.count);
    const [maxRadius, drawn] = selectedRadius(prefix, k);
    return { k, prefix, drawn, maxRadius };
  }

  function useSprites(view, near, maxRadius, ss, lowpass) {  // splatting.use_point_sprites
    const r = maxRadius * S.radius_scale;
    let pixels;
    if (cam.ortho) pixels = r * H * ss / cam.ortho;
    else {
      const c = META.sphere.center;
      const distance = -(view[8] * c[0] + view[9] * c[1] + view[10] * c[2] + view[11]);
      const nearest = distance - META.sphere.radius - r;
      if (nearest <= near) return false;
      pixels = r * start.fy * ss / nearest * 1.5;
    }
    return 2 * (pixels + lowpass) + 2 <= Math.min(2 * GUARD, MAX_SPRITE, maxPoint);
  }

  // ---- one frame ------------------------------------------------------------------------
  let moving = false, settleTimer = null;
  function render(coarse = moving) {  // coarse: a frame of a moving camera
    const t0 = performance.now();
    // samples per pixel side: the supersampling, or half a sample while the camera moves
    const ss = coarse ? 1 : S.supersample, down = coarse ? MOVING_DOWNSAMPLE : 1, factor = ss / down;
    const w = Math.ceil(W * factor), h = Math.ceil(H * factor);
    const method = S.method;
    const ewa = S.ewa_filter;
    const mode = META.modes.find((m) => m.name === S.color);
    const categorical = mode.kind === "categorical";
    const edl = S.shading === "edl";
    const shading = SHADING[edl ? "none" : S.shading];
    const view = viewMatrix();
    // a point tree is never drawn whole: LOD error 0 means one pixel there
    const eps = (S.lod_error > 0 ? S.lod_error : search ? 1 : 0) * (coarse ? MOVING_LOD_FACTOR : 1);
    const lod = lodFrame(eps);
    const [near, far] = clipPlanes(view, META.sphere.radius + META.data.max_radius * S.radius_scale);
    const lowpassRadius = S.lowpass_radius * Math.max(factor, 1);
    const sprites = useSprites(view, near, lod.maxRadius, factor, ewa ? lowpassRadius : 0);
    const guard = sprites ? GUARD : 0;
    const t = allocate(w, h, guard);
    const variant = { PER_SPLAT_SHADING: method === "gaussian", EWA_FILTER: ewa, POINT_SPRITES: sprites,
                      CURVED_SPLATS: method !== "gaussian" && !!columns.field,
                      NORMAL_FIELD: (method === "phong" || (method === "deferred" && S.phong_normals)) && !!columns.field,
                      CLIP_LINES: !!columns.clip };
    let pageMode = PAGE_MODE.rgb, range = [0, 1];
    if (mode.kind === "continuous") {
      pageMode = mode.name === "elevation" ? PAGE_MODE.elevation : PAGE_MODE.value;
      const [qlo, qhi] = mode.name === "elevation" ? [0, 1] : mode.quantized;
      const span = Math.max(qhi - qlo, 1e-30);
      range = mode.name === "elevation" ? S.range.map((v) => v - mode.offset)
                                        : [(S.range[0] - qlo) / span, (S.range[1] - qlo) / span];
    } else if (categorical) pageMode = PAGE_MODE.code;
    if (categorical && !mode.texture) mode.texture = tableTexture(mode.palette);
    const common = {
      u_view: view, u_projection: projectionMatrix(near, far), u_viewport: [w, h], u_guard: guard,
      u_intrinsics: [start.fx * factor, start.fy * factor, start.cx * factor, start.cy * factor],
      u_ortho: cam.ortho ? H * factor / cam.ortho : 0, u_shading: shading, u_depth_range: [near, far],
      u_radius_scale: S.radius_scale, u_depth_offset: S.depth_offset, u_lowpass_radius: lowpassRadius,
      u_backface_culling: S.backface_culling ? 1 : 0, u_kernel: UNIT.kernel, u_lod_k: lod.k,
      u_visibility: UNIT.visibility, u_accum_color: UNIT.accumColor, u_accum_normal: UNIT.accumNormal,
      u_box_lo: META.data.box_lo, u_box_size: META.data.box_size, u_length_unit: META.data.length_unit,
      u_page_mode: pageMode, u_value_range: range, u_up: META.up, u_color_mode: COLOR_MODE[mode.kind],
      u_color_table: UNIT.table, u_neutral: META.neutral, u_code_levels: mode.code_levels || 2,
      u_category: UNIT.category,
    };
    const bindTexture = (unit, tex) => { gl.activeTexture(gl.TEXTURE0 + unit); gl.bindTexture(gl.TEXTURE_2D, tex); };
    bindTexture(UNIT.kernel, kernel);
    bindTexture(UNIT.table, categorical ? mode.texture : colormaps[S.colormap]);
    const vao = vertexArray(!sprites);
    const draw = (entry, values) => {
      setUniforms(entry, { ...common, ...values });
      gl.bindVertexArray(vao);
      if (sprites) gl.drawArrays(gl.POINTS, 0, lod.prefix);
      else gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, lod.prefix);
    };
    gl.disable(gl.DEPTH_TEST); gl.disable(gl.CULL_FACE);
    gl.viewport(0, 0, w + 2 * guard, h + 2 * guard);
    // 1. visibility: nearest depth + z_t and 1 - coverage, MIN-blended
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.visFbo);
    gl.clearBufferfv(gl.COLOR, 0, [FAR, 1, 0, 0]);
    gl.enable(gl.BLEND); gl.blendEquation(gl.MIN);
    draw(program("splat", { ...variant, PASS_VISIBILITY: true }), {});
    bindTexture(UNIT.visibility, t.vis);
    // 2. attributes: (w rgb, w) and (w n, w z), added
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.accFbo);
    gl.clearBufferfv(gl.COLOR, 0, [0, 0, 0, 0]); gl.clearBufferfv(gl.COLOR, 1, [0, 0, 0, 0]);
    gl.blendEquation(gl.FUNC_ADD); gl.blendFunc(gl.ONE, gl.ONE);
    draw(program("splat", { ...variant, PASS_ATTRIBUTE: true }), {});
    // categorical colours: the heaviest splat's packed category, MAX-blended (gl/colors.glsl)
    if (categorical) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, t.catFbo);
      gl.clearBufferfv(gl.COLOR, 0, [-1, 0, 0, 0]);
      gl.blendEquation(gl.MAX);
      draw(program("splat", { ...variant, PASS_CATEGORY: true }), {});
    }
    bindTexture(UNIT.category, t.cat);
    // 3. normalization and deferred shading into the G-buffer
    gl.disable(gl.BLEND);
    gl.bindVertexArray(null);
    gl.bindFramebuffer(gl.FRAMEBUFFER, t.gFbo);
    gl.viewport(0, 0, w, h);
    bindTexture(UNIT.accumColor, t.acc[0]); bindTexture(UNIT.accumNormal, t.acc[1]);
    setUniforms(program("splat", { ...variant, PASS_NORMALIZE: true }), common);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    // pinholes (surfel.pinholes): two rounds, into the spare G-buffer and back; supersampled, two
    // more between the samples a pixel apart
    for (const step of factor > 1 ? [1, Math.round(factor)] : [1]) {
      for (const [from, into] of [[t.gbuf, t.spareFbo], [t.spare, t.gFbo]]) {
        gl.bindFramebuffer(gl.FRAMEBUFFER, into);
        bindTexture(UNIT.shaded, from[0]); bindTexture(UNIT.gnormal, from[1]); bindTexture(UNIT.gdepth, from[2]);
        setUniforms(program("pinholes", {}), { u_shaded: UNIT.shaded, u_gnormal: UNIT.gnormal,
                                               u_gdepth: UNIT.gdepth, u_categorical: categorical ? 1 : 0,
                                               u_step: step });
        gl.drawArrays(gl.TRIANGLES, 0, 3);
      }
    }
    // the canvas: supersamples filtered, categories coloured, eye-dome lighting, background
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, W, H);
    bindTexture(UNIT.shaded, t.gbuf[0]); bindTexture(UNIT.gnormal, t.gbuf[1]); bindTexture(UNIT.gdepth, t.gbuf[2]);
    setUniforms(program("display", {}), {
      u_shaded: UNIT.shaded, u_gnormal: UNIT.gnormal, u_gdepth: UNIT.gdepth, u_categorical: categorical ? 1 : 0,
      u_edl: edl ? 1 : 0, u_edl_strength: S.edl_strength, u_edl_radius: S.edl_radius * factor, u_supersample: ss,
      u_downsample: down, u_background: S.background,
    });
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4));  // waits for the frame
    const ms = performance.now() - t0;
    stats.frames += 1;
    stats.frameMs = ms;
    stats.history.push(ms);
    if (stats.history.length > 20) stats.history.shift();
    const sorted = stats.history.slice().sort((a, b) => a - b);
    stats.medianMs = sorted[sorted.length >> 1];
    Object.assign(stats, { drawn: lod.drawn, prefix: lod.prefix, lodError: lod.k > 0 ? eps : null, primitive: sprites ? "point sprites" : "quads",
                           method, color: S.color, shading: S.shading, width: W, height: H, moving: coarse });
    const rangeText = mode.kind === "continuous" ? ` [${S.range.map((v) => +v.toPrecision(4)).join(", ")}]` : "";
    status.textContent = `${ms.toFixed(1)} ms/frame (median ${stats.medianMs.toFixed(1)}) · ` +
      `${lod.drawn.toLocaleString()} of ${META.data.count.toLocaleString()} splats` +
      (lod.k > 0 ? ` · LOD ${eps} px` : "") + ` · ${method} · ${S.color}${rangeText} · ${S.shading}`;
    stats.ready = !moving && !coarse;
  }

  let pending = false;
  function requestRender() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; render(moving); });
  }
  function settleLater() {  // a full frame once the camera has rested a while
    clearTimeout(settleTimer);
    settleTimer = setTimeout(() => { moving = false; requestRender(); }, SETTLE_MS);
  }
  function touch() {  // the camera moved: coarse frames while it moves
    moving = true;
    stats.ready = false;
    if (drag) clearTimeout(settleTimer); else settleLater();
    requestRender();
  }

  // ---- mouse: left drag orbits, right (or shift) drag pans, the wheel zooms ----------------
  function orbit(dx, dy) {
    let offset = sub(cam.eye, cam.target);
    const right = unit(cross(sub(cam.target, cam.eye), cam.up));
    const yaw = -dx * 0.008, pitch = -dy * 0.008;
    offset = rotate(rotate(offset, META.up, yaw), rotate(right, META.up, yaw), pitch);
    cam.up = rotate(rotate(cam.up, META.up, yaw), rotate(right, META.up, yaw), pitch);
    cam.eye = add(cam.target, offset);
  }
  function pan(dx, dy) {
    const f = sub(cam.target, cam.eye), right = unit(cross(f, cam.up)), up = unit(cross(right, f));
    const perPixel = cam.ortho ? cam.ortho / H : norm(f) / start.fy;
    const move = add(scale(right, -dx * perPixel), scale(up, dy * perPixel));
    cam.eye = add(cam.eye, move); cam.target = add(cam.target, move);
  }
  function zoom(factor) {
    if (cam.ortho) cam.ortho *= factor;
    else cam.eye = add(cam.target, scale(sub(cam.eye, cam.target), factor));
  }
  let drag = null;
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) pan(dx, dy); else orbit(dx, dy);
    touch();
  });
  canvas.addEventListener("pointerup", () => { drag = null; if (moving) settleLater(); });
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); zoom(Math.exp(e.deltaY * 0.001)); touch(); },
                          { passive: false });

  // ---- the controls --------------------------------------------------------------------
  function control(id, values, current, onChange) {
    const el = document.getElementById(id);
    if (values) for (const v of values) el.add(new Option(v, v));
    if (el.type === "checkbox") el.checked = current; else el.value = current;
    el.addEventListener("change", () => { onChange(el.type === "checkbox" ? el.checked : el.value); requestRender(); });
    return el;
  }
  const ewaBox = control("ewa", null, S.ewa_filter, (v) => { S.ewa_filter = v; });
  // the exporter's methods, in its order: those it gives an EWA default
  control("method", Object.keys(META.settings.ewa_defaults), S.method, (v) => {
    S.method = v;
    if (!META.settings.ewa_given) { S.ewa_filter = META.settings.ewa_defaults[v]; ewaBox.checked = S.ewa_filter; }
    if (!META.settings.supersample_given) S.supersample = META.settings.supersample_defaults[v];
  });
  control("color", META.modes.map((m) => m.name), S.color, (v) => {
    S.color = v;
    const mode = META.modes.find((m) => m.name === v);
    if (mode.range) S.range = mode.range.slice();
  });
  control("colormap", Object.keys(META.colormaps), S.colormap, (v) => { S.colormap = v; });
  control("shading", ["phong", "lambert", "none", "normals", "depth", "edl"], S.shading, (v) => { S.shading = v; });
  control("edl-strength", null, S.edl_strength, (v) => { S.edl_strength = +v; });
  const lodInput = control("lod", null, S.lod_error, (v) => { S.lod_error = Math.max(+v, 0); });
  if (!search) lodInput.parentElement.style.display = "none";
  document.getElementById("reset").addEventListener("click", () => { resetCamera(); requestRender(); });

  window.surfelView = { render, orbit: (dx, dy) => { orbit(dx, dy); touch(); }, pan: (dx, dy) => { pan(dx, dy); touch(); },
                        zoom: (f) => { zoom(f); touch(); }, settings: S, camera: cam };

  if (location.hash === "#capture") document.body.classList.add("capture");
  loadData().then(() => { render(false); }).catch((e) => { if (!stats.error) fail(String(e)); });
})();
