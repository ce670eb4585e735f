// The mesh `ctgs view --mesh` shows instead of the surfels (M toggles): bundle.json's `mesh` entry and mesh.bin
// (ctgs.formats.mesh.viewer_mesh), drawn with a depth test into its own framebuffer and copied to the canvas.

const ARRAYS = {positions: ["float32", 3], colors: ["uint8", 4], indices: ["uint32", 3]};
const TYPED = {float32: Float32Array, uint8: Uint8Array, uint32: Uint32Array};

// Fetch mesh.bin (the file name is fixed: bundle.json's entry only describes it) and view its arrays.
export async function loadMesh(base, info) {
  const r = await fetch(`${base}/mesh.bin`);
  if (!r.ok) throw new Error(`${base}/mesh.bin: HTTP ${r.status}`);
  const raw = await r.arrayBuffer();
  const arrays = {};
  for (const [name, [dtype, width]] of Object.entries(ARRAYS)) {
    const spec = info.arrays[name];
    const rows = name === "indices" ? info.triangles : info.vertices;
    if (!spec || spec.dtype !== dtype || spec.shape[0] !== rows || spec.shape[1] !== width ||
        spec.offset % 8 !== 0 || spec.offset + rows * width * TYPED[dtype].BYTES_PER_ELEMENT > raw.byteLength) {
      throw new Error(`mesh.bin: array ${name} does not match bundle.json's mesh entry`);
    }
    arrays[name] = new TYPED[dtype](raw, spec.offset, rows * width);
  }
  return arrays;
}

export class MeshLayer {
  constructor(gl, program, arrays, background) {
    this.gl = gl;
    this.prog = program;
    this.background = background;
    this.count = arrays.indices.length;
    const p = arrays.positions;
    this.lo = [Infinity, Infinity, Infinity];
    this.hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < p.length; i += 3) {
      for (let k = 0; k < 3; ++k) {
        this.lo[k] = Math.min(this.lo[k], p[i + k]);
        this.hi[k] = Math.max(this.hi[k], p[i + k]);
      }
    }
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const buffer = (target, data) => {
      const b = gl.createBuffer();
      gl.bindBuffer(target, b);
      gl.bufferData(target, data, gl.STATIC_DRAW);
    };
    buffer(gl.ARRAY_BUFFER, arrays.positions);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    buffer(gl.ARRAY_BUFFER, arrays.colors);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribPointer(1, 4, gl.UNSIGNED_BYTE, true, 0, 0);
    buffer(gl.ELEMENT_ARRAY_BUFFER, arrays.indices);
    gl.bindVertexArray(null);
    this.target = null;
  }

  // The canvas has no depth buffer (the surfels need none): the mesh is drawn into RGBA8 + depth renderbuffers.
  ensureTarget(width, height) {
    const gl = this.gl;
    if (this.target && this.target.width === width && this.target.height === height) return;
    if (this.target) {
      gl.deleteRenderbuffer(this.target.color);
      gl.deleteRenderbuffer(this.target.depth);
      gl.deleteFramebuffer(this.target.fbo);
    }
    const rb = (format) => {
      const r = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, r);
      gl.renderbufferStorage(gl.RENDERBUFFER, format, width, height);
      return r;
    };
    const color = rb(gl.RGBA8), depth = rb(gl.DEPTH_COMPONENT24);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.RENDERBUFFER, color);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
    const status = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    if (status !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`mesh framebuffer incomplete (0x${status.toString(16)})`);
    this.target = {fbo, color, depth, width, height};
  }

  // The far plane: just past the mesh's farthest bounding-box corner from the camera.
  far(cam) {
    let far = 0;
    for (let c = 0; c < 8; ++c) {
      const p = [c & 1 ? this.hi[0] : this.lo[0], c & 2 ? this.hi[1] : this.lo[1], c & 4 ? this.hi[2] : this.lo[2]];
      const v = cam.viewmat;
      far = Math.max(far, v[8] * p[0] + v[9] * p[1] + v[10] * p[2] + v[11]);
    }
    return Math.max(1.01 * far, 2 * cam.near);
  }

  // cam: as Renderer.draw's.
  draw(cam, shade) {
    const gl = this.gl, W = cam.width, H = cam.height;
    this.ensureTarget(W, H);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.target.fbo);
    gl.viewport(0, 0, W, H);
    gl.clearColor(this.background[0], this.background[1], this.background[2], 1);
    gl.clearDepth(1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    const {p, u} = this.prog;
    gl.useProgram(p);
    const vm = cam.viewmat;
    gl.uniformMatrix4fv(u.u_view, false, [vm[0], vm[4], vm[8], vm[12], vm[1], vm[5], vm[9], vm[13],
      vm[2], vm[6], vm[10], vm[14], vm[3], vm[7], vm[11], vm[15]]);
    gl.uniform4f(u.u_intr, cam.fx, cam.fy, cam.cx, cam.cy);
    gl.uniform2f(u.u_size, W, H);
    gl.uniform2f(u.u_clip, cam.near, this.far(cam));
    gl.uniform1i(u.u_shade, shade ? 1 : 0);
    gl.bindVertexArray(this.vao);
    gl.drawElements(gl.TRIANGLES, this.count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
    gl.disable(gl.DEPTH_TEST);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, this.target.fbo);
    gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
    gl.blitFramebuffer(0, 0, W, H, 0, 0, W, H, gl.COLOR_BUFFER_BIT, gl.NEAREST);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  }
}
