// WebGL2 renderer of the web bundle: data textures per surfel, the texture atlas as a 2D array texture,
// one instanced quad per surfel blended back to front into a float buffer, then composited over the
// background into the canvas.

// Data textures are at most this wide (every WebGL2 supports 2048; wider means fewer rows).
const DATA_WIDTH = 4096;

function compile(gl, type, source, name) {
  const s = gl.createShader(type);
  gl.shaderSource(s, source);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`${name}: ${gl.getShaderInfoLog(s)}`);
  return s;
}

export function program(gl, vs, fs, names) {
  const p = gl.createProgram();
  gl.attachShader(p, compile(gl, gl.VERTEX_SHADER, vs, names[0]));
  gl.attachShader(p, compile(gl, gl.FRAGMENT_SHADER, fs, names[1]));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`link ${names}: ${gl.getProgramInfoLog(p)}`);
  const uniforms = {};
  const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; ++i) {
    const info = gl.getActiveUniform(p, i);
    uniforms[info.name] = gl.getUniformLocation(p, info.name);
  }
  return {p, u: uniforms};
}

function nearest(gl, target) {
  gl.texParameteri(target, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(target, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.texParameteri(target, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(target, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
}

export class Renderer {
  // accum: "auto" (RGBA32F where float blending is supported), or force "RGBA16F" (half the bandwidth).
  constructor(canvas, accum = "auto") {
    const gl = canvas.getContext("webgl2", {antialias: false, alpha: false, depth: false, stencil: false,
      premultipliedAlpha: false, preserveDrawingBuffer: true, powerPreference: "high-performance"});
    if (!gl) throw new Error("WebGL2 is not available in this browser (enable hardware acceleration, " +
      "or start Chromium with --use-angle=swiftshader --enable-unsafe-swiftshader)");
    this.gl = gl;
    this.canvas = canvas;
    const dbg = gl.getExtension("WEBGL_debug_renderer_info");
    this.glRenderer = dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER);
    // Blending many layers in 8 bits would round every step; float accumulation matches the CPU's
    // float32 sums. RGBA32F needs both extensions; half floats (11-bit mantissa) are the fallback.
    const cbf = gl.getExtension("EXT_color_buffer_float");
    const fblend = gl.getExtension("EXT_float_blend");
    const cbh = gl.getExtension("EXT_color_buffer_half_float");
    if (cbf && fblend && accum !== "RGBA16F") this.accumFormat = {internal: gl.RGBA32F, type: gl.FLOAT, name: "RGBA32F"};
    else if (cbf || cbh) this.accumFormat = {internal: gl.RGBA16F, type: gl.HALF_FLOAT, name: "RGBA16F"};
    else this.accumFormat = {internal: gl.RGBA8, type: gl.UNSIGNED_BYTE, name: "RGBA8"};
    this.count = 0;
    this.accum = null;
    this.tightQuads = true;  // coverage quads: projected 3-sigma rectangle grown by the fallback radius
  }

  init(bundle, arrays, pages, shaders) {
    const gl = this.gl;
    this.surfel = program(gl, shaders.surfelVert, shaders.surfelFrag, ["surfel.vert", "surfel.frag"]);
    this.composite = program(gl, shaders.compositeVert, shaders.compositeFrag, ["composite.vert", "composite.frag"]);
    this.emptyVao = gl.createVertexArray();
    this.setData(bundle, arrays, pages);
  }

  // Upload a bundle's surfels and atlas, replacing (and freeing) those drawn so far: a run's newer model.
  setData(bundle, arrays, pages) {
    const gl = this.gl;
    for (const t of [this.geomTex, this.layoutTex, this.shTex, this.atlasTex]) if (t) gl.deleteTexture(t);
    if (this.indexBuffer) gl.deleteBuffer(this.indexBuffer);
    if (this.vao) gl.deleteVertexArray(this.vao);
    this.count = 0;
    const n = bundle.num_surfels;
    this.n = n;
    this.shDegree = bundle.sh_degree;
    this.background = bundle.background;
    const maxTex = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    const width = Math.min(DATA_WIDTH, maxTex);
    const dataTexture = (texels, internal, format, type, data, Typed) => {
      const rows = Math.max(1, Math.ceil(texels / width));
      if (rows > maxTex) throw new Error(`${texels} data texels exceed this GPU's ${maxTex}^2 texture limit`);
      const comps = 4;
      const full = new Typed(rows * width * comps);
      full.set(data);
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, t);
      nearest(gl, gl.TEXTURE_2D);
      gl.texImage2D(gl.TEXTURE_2D, 0, internal, width, rows, 0, format, type, full);
      return t;
    };
    // geometry: (mean, opacity), quat, (sx, sy, ku, kv)
    const geom = new Float32Array(n * 12);
    for (let i = 0; i < n; ++i) {
      const o = 12 * i;
      geom[o] = arrays.means[3 * i]; geom[o + 1] = arrays.means[3 * i + 1]; geom[o + 2] = arrays.means[3 * i + 2];
      geom[o + 3] = arrays.opacities[i];
      for (let k = 0; k < 4; ++k) geom[o + 4 + k] = arrays.quats[4 * i + k];
      geom[o + 8] = arrays.scales[2 * i]; geom[o + 9] = arrays.scales[2 * i + 1];
      geom[o + 10] = arrays.texel_size[2 * i]; geom[o + 11] = arrays.texel_size[2 * i + 1];
    }
    this.geomTex = dataTexture(3 * n, gl.RGBA32F, gl.RGBA, gl.FLOAT, geom, Float32Array);
    const layout = new Uint32Array(n * 4);
    for (let i = 0; i < n; ++i) {
      layout[4 * i] = arrays.tex_res[2 * i];
      layout[4 * i + 1] = arrays.tex_res[2 * i + 1];
      layout[4 * i + 2] = arrays.atlas_pos[3 * i] | (arrays.atlas_pos[3 * i + 1] << 16);
      layout[4 * i + 3] = arrays.atlas_pos[3 * i + 2];
    }
    this.layoutTex = dataTexture(n, gl.RGBA32UI, gl.RGBA_INTEGER, gl.UNSIGNED_INT, layout, Uint32Array);
    // SH: K x 3 halves per surfel, padded to whole RGBA texels.
    const k3 = 3 * (this.shDegree + 1) ** 2;
    this.shTexels = Math.ceil(k3 / 4);
    const sh = new Uint16Array(n * this.shTexels * 4);
    for (let i = 0; i < n; ++i) sh.set(arrays.sh.subarray(k3 * i, k3 * (i + 1)), 4 * this.shTexels * i);
    this.shTex = dataTexture(n * this.shTexels, gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT, sh, Uint16Array);
    this.uploadAtlas(bundle.atlas, pages);

    this.indexBuffer = gl.createBuffer();
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    gl.bufferData(gl.ARRAY_BUFFER, 4 * Math.max(1, n), gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribIPointer(0, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(0, 1);
    gl.bindVertexArray(null);
  }

  uploadAtlas(atlas, pages) {
    const gl = this.gl;
    const size = atlas.page_size, layers = Math.max(1, pages.length);
    if (size > gl.getParameter(gl.MAX_TEXTURE_SIZE)) throw new Error(`atlas pages of ${size}^2 exceed MAX_TEXTURE_SIZE`);
    if (layers > gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS)) throw new Error(`${layers} atlas pages exceed MAX_ARRAY_TEXTURE_LAYERS`);
    const snorm = atlas.texel_format === "snorm8";
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
    nearest(gl, gl.TEXTURE_2D_ARRAY);
    const internal = snorm ? gl.RGB8_SNORM : gl.RGB16F, type = snorm ? gl.BYTE : gl.HALF_FLOAT;
    const w = pages.length ? size : 1, h = pages.length ? size : 1;
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, internal, w, h, layers);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);  // rows of 3-channel texels are not 4-byte aligned
    pages.forEach((data, p) => {
      const rows = atlas.pages[p].rows;
      if (rows > 0) gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, p, size, rows, 1, gl.RGB, type, data);
    });
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
    this.atlasTex = t;
  }

  setOrder(order, count) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuffer);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, order.subarray(0, count));
    this.count = count;
  }

  ensureAccum(width, height) {
    const gl = this.gl;
    if (this.accum && this.accum.width === width && this.accum.height === height) return;
    if (this.accum) { gl.deleteTexture(this.accum.tex); gl.deleteFramebuffer(this.accum.fbo); }
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    nearest(gl, gl.TEXTURE_2D);
    gl.texStorage2D(gl.TEXTURE_2D, 1, this.accumFormat.internal, width, height);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`${this.accumFormat.name} framebuffer incomplete (0x${status.toString(16)})`);
    this.accum = {tex, fbo, width, height};
  }

  // cam: {viewmat (16, row-major world->camera), campos, fx, fy, cx, cy, width, height, near}; map: 0 the image,
  // 1 texel size, 2 texture resolution (ctgs/render/texel_map.py)
  draw(cam, textures, map = 0) {
    const gl = this.gl, W = cam.width, H = cam.height;
    this.ensureAccum(W, H);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.accum.fbo);
    gl.viewport(0, 0, W, H);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.enable(gl.BLEND);
    gl.blendEquation(gl.FUNC_ADD);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);  // premultiplied "over", back to front
    const {p, u} = this.surfel;
    gl.useProgram(p);
    const vm = cam.viewmat;
    // column-major for GLSL
    gl.uniformMatrix4fv(u.u_view, false, [vm[0], vm[4], vm[8], vm[12], vm[1], vm[5], vm[9], vm[13],
      vm[2], vm[6], vm[10], vm[14], vm[3], vm[7], vm[11], vm[15]]);
    gl.uniform3fv(u.u_campos, cam.campos);
    gl.uniform4f(u.u_intr, cam.fx, cam.fy, cam.cx, cam.cy);
    gl.uniform2f(u.u_size, W, H);
    gl.uniform1f(u.u_near, cam.near);
    gl.uniform1i(u.u_sh_texels, this.shTexels);
    gl.uniform1i(u.u_sh_degree, this.shDegree);
    gl.uniform1i(u.u_textures, textures ? 1 : 0);
    gl.uniform1i(u.u_tight, this.tightQuads ? 1 : 0);
    gl.uniform1i(u.u_map, map);
    const bind = (unit, target, tex, loc) => {
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(target, tex);
      gl.uniform1i(loc, unit);
    };
    bind(0, gl.TEXTURE_2D, this.geomTex, u.u_geom);
    bind(1, gl.TEXTURE_2D, this.layoutTex, u.u_layout);
    bind(2, gl.TEXTURE_2D, this.shTex, u.u_sh);
    bind(3, gl.TEXTURE_2D_ARRAY, this.atlasTex, u.u_atlas);
    gl.bindVertexArray(this.vao);
    if (this.count > 0) gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, this.count);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);

    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, W, H);
    const c = this.composite;
    gl.useProgram(c.p);
    bind(0, gl.TEXTURE_2D, this.accum.tex, c.u.u_accum);
    gl.uniform3fv(c.u.u_background, this.background);
    gl.uniform1i(c.u.u_map, map);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindVertexArray(null);
  }

  // Block until the GPU has finished everything issued (reading one pixel back forces it).
  finish() {
    const gl = this.gl, px = new Uint8Array(4);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
  }
}
