// WebGL2 renderer: env background, actors, surfels (back-to-front, premultiplied "over") into a
// float target, then exposure + tone map + sRGB into the canvas, then overlays.
import * as S from "./shaders.js";

export const PER_ROW = 1024; // surfels per texture row of the pool
const BATCH = 16384;        // quads per draw call (u16 indices)
const ORDER_ROW = 4096;     // entries per row of the order texture

function compile(gl, vs, fs) {
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const sh = gl.createShader(type);
    gl.shaderSource(sh, src);
    gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error("shader: " + gl.getShaderInfoLog(sh));
    gl.attachShader(prog, sh);
  }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error("program: " + gl.getProgramInfoLog(prog));
  const uniforms = {};
  const count = gl.getProgramParameter(prog, gl.ACTIVE_UNIFORMS);
  for (let k = 0; k < count; k++) {
    const name = gl.getActiveUniform(prog, k).name.replace(/\[0\]$/, "");
    uniforms[name] = gl.getUniformLocation(prog, name);
  }
  return { prog, uniforms, attrib: (name) => gl.getAttribLocation(prog, name) };
}

// Rows of the surfel texture handed out to chunks (first fit); the texture grows by doubling.
class RowPool {
  constructor(rows) { this.rows = rows; this.free = [[0, rows]]; }
  alloc(n) {
    for (let k = 0; k < this.free.length; k++) {
      const [start, len] = this.free[k];
      if (len >= n) {
        if (len === n) this.free.splice(k, 1); else this.free[k] = [start + n, len - n];
        return start;
      }
    }
    return -1;
  }
  release(start, n) {
    this.free.push([start, n]);
    this.free.sort((a, b) => a[0] - b[0]);
    const merged = [];
    for (const r of this.free) {
      const last = merged[merged.length - 1];
      if (last && last[0] + last[1] === r[0]) last[1] += r[1]; else merged.push([...r]);
    }
    this.free = merged;
  }
  grow(rows) { this.release(this.rows, rows - this.rows); this.rows = rows; }
}

export class Renderer {
  constructor(gl, tps) {
    this.gl = gl;
    this.tps = tps;
    if (!gl.getExtension("EXT_color_buffer_float")) {
      this.hdrFormat = [gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE];
      this.note = "no float render targets: colours are clipped to 8 bits before tone mapping";
    } else if (gl.getExtension("EXT_float_blend")) {
      this.hdrFormat = [gl.RGBA32F, gl.RGBA, gl.FLOAT];
    } else {
      this.hdrFormat = [gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT];
    }
    this.surfel = compile(gl, S.SURFEL_VS, S.SURFEL_FS);
    this.env = compile(gl, S.FULLSCREEN_VS, S.ENV_FS);
    this.tonemap = compile(gl, S.FULLSCREEN_VS, S.TONEMAP_FS);
    this.actor = compile(gl, S.ACTOR_VS, S.ACTOR_FS);
    this.overlay = compile(gl, S.OVERLAY_VS, S.OVERLAY_FS);
    this.maxRows = Math.floor(Math.min(gl.getParameter(gl.MAX_TEXTURE_SIZE), 16384));
    this.maxPointSize = gl.getParameter(gl.ALIASED_POINT_SIZE_RANGE)[1];
    this.pool = null;
    this.data = null;
    this.chunks = new Map(); // key -> {startRow, rows, n, gpu}
    this.emptyVao = gl.createVertexArray();

    // surfels: batches of BATCH quads drawn from one static u16 index buffer (4 vertices, 6
    // indices per quad); the sorted order lives in an R32UI texture, 4096 entries per row.
    this.surfelVao = gl.createVertexArray();
    gl.bindVertexArray(this.surfelVao);
    const quads = new Uint16Array(BATCH * 6);
    for (let q = 0; q < BATCH; q++) quads.set([4 * q, 4 * q + 1, 4 * q + 2, 4 * q + 2, 4 * q + 1, 4 * q + 3], 6 * q);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, gl.createBuffer());
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, quads, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    this.orderTex = null;
    this.orderRows = 0;
    this.count = 0;

    this.envTex = null;
    this.envMeta = null;
    this.actorMeshes = [];
    this.proxy = new Map();
    this.lines = null;
    this.highlight = null;
    this.size = [0, 0];
  }

  // ------------------------------------------------------------------ surfel pool
  _makeTexture(rows) {
    const gl = this.gl;
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32UI, PER_ROW * this.tps, rows);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    return tex;
  }

  _upload(startRow, gpu, n) {
    const gl = this.gl;
    gl.bindTexture(gl.TEXTURE_2D, this.data);
    const width = PER_ROW * this.tps;
    const full = Math.floor(n / PER_ROW);
    if (full > 0) {
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, startRow, width, full, gl.RGBA_INTEGER, gl.UNSIGNED_INT,
        gpu.subarray(0, full * width * 4));
    }
    const rest = n - full * PER_ROW;
    if (rest > 0) {
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, startRow + full, rest * this.tps, 1, gl.RGBA_INTEGER, gl.UNSIGNED_INT,
        gpu.subarray(full * width * 4, n * this.tps * 4));
    }
  }

  // Place a decoded chunk in the pool; returns the global index of its first surfel.
  addChunk(key, gpu, n) {
    const rows = Math.max(1, Math.ceil(n / PER_ROW));
    if (!this.pool) {
      let initial = 64;
      while (initial < rows) initial *= 2;
      this.pool = new RowPool(Math.min(initial, this.maxRows));
      this.data = this._makeTexture(this.pool.rows);
    }
    let start = this.pool.alloc(rows);
    while (start < 0) {
      const grown = Math.min(this.pool.rows * 2, this.maxRows);
      if (grown === this.pool.rows) throw new Error("surfel pool full: lower the view distance");
      this.gl.deleteTexture(this.data);
      this.pool.grow(grown);
      this.data = this._makeTexture(grown);
      for (const c of this.chunks.values()) this._upload(c.startRow, c.gpu, c.n);
      start = this.pool.alloc(rows);
    }
    this._upload(start, gpu, n);
    this.chunks.set(key, { startRow: start, rows, n, gpu });
    return start * PER_ROW;
  }

  removeChunk(key) {
    const c = this.chunks.get(key);
    if (!c) return;
    this.pool.release(c.startRow, c.rows);
    this.chunks.delete(key);
  }

  capacity() { return this.pool ? this.pool.rows * PER_ROW : 0; }

  setOrder(order, count) {
    const gl = this.gl;
    const rows = Math.max(1, Math.ceil(count / ORDER_ROW));
    if (!this.orderTex || rows > this.orderRows) {
      if (this.orderTex) gl.deleteTexture(this.orderTex);
      this.orderRows = Math.max(rows, 2 * this.orderRows, 16);
      this.orderTex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.R32UI, ORDER_ROW, this.orderRows);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    }
    gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
    const full = Math.floor(count / ORDER_ROW);
    if (full) gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, ORDER_ROW, full, gl.RED_INTEGER, gl.UNSIGNED_INT, order.subarray(0, full * ORDER_ROW));
    const rest = count - full * ORDER_ROW;
    if (rest) gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, full, rest, 1, gl.RED_INTEGER, gl.UNSIGNED_INT, order.subarray(full * ORDER_ROW, count));
    this.count = count;
  }

  // --------------------------------------------------------------------- env map
  setEnv(env, meta) {
    const gl = this.gl;
    if (this.envTex) gl.deleteTexture(this.envTex);
    this.envTex = null;
    this.envMeta = meta;
    if (!env) return;
    this.envTex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.envTex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, env.width, env.height, 0, gl.RGBA, gl.HALF_FLOAT, env.texels);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  }

  // ----------------------------------------------------------------------- meshes
  setActorMeshes(meshes) {
    const gl = this.gl;
    for (const m of this.actorMeshes) { gl.deleteVertexArray(m.vao); gl.deleteBuffer(m.pos); gl.deleteBuffer(m.col); }
    this.actorMeshes = meshes.map((m) => {
      const vao = gl.createVertexArray();
      gl.bindVertexArray(vao);
      const pos = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, pos);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(m.positions), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(this.actor.attrib("a_pos"));
      gl.vertexAttribPointer(this.actor.attrib("a_pos"), 3, gl.FLOAT, false, 0, 0);
      const col = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, col);
      gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(m.colors), gl.STATIC_DRAW);
      gl.enableVertexAttribArray(this.actor.attrib("a_color"));
      gl.vertexAttribPointer(this.actor.attrib("a_color"), 3, gl.FLOAT, false, 0, 0);
      gl.bindVertexArray(null);
      return { vao, pos, col, count: m.positions.length / 3 };
    });
  }

  _overlayVao(positions, colors, indices) {
    const gl = this.gl;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const bufs = [];
    const pos = gl.createBuffer(); bufs.push(pos);
    gl.bindBuffer(gl.ARRAY_BUFFER, pos);
    gl.bufferData(gl.ARRAY_BUFFER, positions, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(this.overlay.attrib("a_pos"));
    gl.vertexAttribPointer(this.overlay.attrib("a_pos"), 3, gl.FLOAT, false, 0, 0);
    const col = gl.createBuffer(); bufs.push(col);
    gl.bindBuffer(gl.ARRAY_BUFFER, col);
    gl.bufferData(gl.ARRAY_BUFFER, colors, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(this.overlay.attrib("a_color"));
    gl.vertexAttribPointer(this.overlay.attrib("a_color"), 4, gl.UNSIGNED_BYTE, true, 0, 0);
    let count = positions.length / 3;
    if (indices) {
      const ib = gl.createBuffer(); bufs.push(ib);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
      count = indices.length;
    }
    gl.bindVertexArray(null);
    return { vao, bufs, count, indexed: !!indices };
  }

  _dropVao(o) {
    if (!o) return;
    this.gl.deleteVertexArray(o.vao);
    for (const b of o.bufs) this.gl.deleteBuffer(b);
  }

  addProxy(key, mesh) { this.removeProxy(key); this.proxy.set(key, this._overlayVao(mesh.positions, mesh.colors, mesh.indices)); }
  removeProxy(key) { this._dropVao(this.proxy.get(key)); this.proxy.delete(key); }

  // Line segments (pairs of points) with RGBA8 colours.
  setLines(positions, colors) { this._dropVao(this.lines); this.lines = positions.length ? this._overlayVao(positions, colors) : null; }
  setHighlight(positions, colors) { this._dropVao(this.highlight); this.highlight = positions && positions.length ? this._overlayVao(positions, colors) : null; }

  // ----------------------------------------------------------------------- frame
  _target(w, h) {
    const gl = this.gl;
    if (this.size[0] === w && this.size[1] === h && this.fbo) return;
    if (this.fbo) { gl.deleteFramebuffer(this.fbo); gl.deleteTexture(this.hdr); gl.deleteRenderbuffer(this.depth); }
    this.hdr = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.hdr);
    const [internal, format, type] = this.hdrFormat;
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    this.depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, this.depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
    this.fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.hdr, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, this.depth);
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) throw new Error("float render target incomplete");
    this.size = [w, h];
  }

  _camera(p, cam) {
    const gl = this.gl;
    const u = p.uniforms;
    if (u.u_rot) gl.uniformMatrix3fv(u.u_rot, false, cam.rotColumns);
    if (u.u_eye) gl.uniform3fv(u.u_eye, cam.eye);
    if (u.u_K) gl.uniform4f(u.u_K, cam.fx, cam.fy, cam.cx, cam.cy);
    if (u.u_size) gl.uniform2f(u.u_size, cam.width, cam.height);
    if (u.u_clip) gl.uniform2f(u.u_clip, cam.near, cam.far);
  }

  // frame: {camera, actors: [{mesh, model (16, column-major)}], lighting, exposure, tonemap,
  //         shDegree, colorMode, classColors, proxy (bool), proxyAlpha, lines (bool)}
  render(frame) {
    const gl = this.gl;
    const cam = frame.camera;
    const w = cam.width, h = cam.height;
    this._target(w, h);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
    gl.viewport(0, 0, w, h);
    gl.disable(gl.BLEND);
    gl.disable(gl.DEPTH_TEST);
    gl.depthMask(true);
    gl.clearColor(0, 0, 0, 1);
    gl.clearDepth(1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);

    // env
    gl.useProgram(this.env.prog);
    this._camera(this.env, cam);
    const eu = this.env.uniforms;
    gl.uniform1i(eu.u_hasEnv, this.envTex ? 1 : 0);
    if (this.envTex) {
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.envTex);
      gl.uniform1i(eu.u_env, 0);
      gl.uniformMatrix3fv(eu.u_domeFromWorld, false, this.envMeta.worldFromDome.flat());
      gl.uniform1i(eu.u_poleY, this.envMeta.poleAxis === "Y" ? 1 : 0);
      // the ground beyond the scene (env/farfield.py), seen from the camera centre (u_eye)
      const ff = this.envMeta.farField;
      gl.uniform1i(eu.u_farField, ff ? 1 : 0);
      if (ff) {
        gl.uniform1f(eu.u_farHeight, ff.height);
        gl.uniform3fv(eu.u_farRadiance, ff.radiance);
        gl.uniform3fv(eu.u_farGround, ff.ground);
        gl.uniform1f(eu.u_farFog, ff.fogDensity);
      }
    }
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);

    // actors: opaque, depth-tested
    if (frame.actors && frame.actors.length) {
      gl.enable(gl.DEPTH_TEST);
      gl.depthFunc(gl.LESS);
      gl.useProgram(this.actor.prog);
      this._camera(this.actor, cam);
      const au = this.actor.uniforms;
      const L = frame.lighting;
      gl.uniform3fv(au.u_sh, L.sh.flat());
      gl.uniform3fv(au.u_sunDir, L.sunDir);
      gl.uniform3fv(au.u_sunResidual, L.sunResidual);
      gl.uniform1f(au.u_reference, L.reference);
      for (const a of frame.actors) {
        const m = this.actorMeshes[a.mesh];
        if (!m) continue;
        gl.uniformMatrix4fv(au.u_model, false, a.model);
        gl.bindVertexArray(m.vao);
        gl.drawArrays(gl.TRIANGLES, 0, m.count);
      }
    }

    // surfels: back-to-front, premultiplied over, tested against actors, no depth writes
    if (this.count > 0 && this.data && this.orderTex) {
      gl.enable(gl.DEPTH_TEST);
      gl.depthFunc(gl.LEQUAL);
      gl.depthMask(false);
      gl.enable(gl.BLEND);
      gl.blendEquation(gl.FUNC_ADD);
      gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
      gl.useProgram(this.surfel.prog);
      this._camera(this.surfel, cam);
      const su = this.surfel.uniforms;
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.data);
      gl.uniform1i(su.u_data, 0);
      gl.uniform1i(su.u_tps, this.tps);
      gl.uniform1i(su.u_perRow, PER_ROW);
      gl.uniform1i(su.u_shDegree, frame.shDegree);
      gl.uniform1i(su.u_colorMode, frame.colorMode);
      if (su.u_classColors) gl.uniform3fv(su.u_classColors, frame.classColors);
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
      gl.uniform1i(su.u_order, 1);
      gl.bindVertexArray(this.surfelVao);
      // One point sprite per surfel when any screen rectangle fits the largest point size (its
      // side is at most the image's): a quarter of the vertex work of quads, the same pixels
      // (the fragment shader clips the square sprite to the rectangle). Else indexed quads.
      const points = Math.max(w, h) <= this.maxPointSize;
      gl.uniform1i(su.u_points, points ? 1 : 0);
      if (points) gl.drawArrays(gl.POINTS, 0, this.count);
      else for (let base = 0; base < this.count; base += BATCH) {
        gl.uniform1i(su.u_base, base);
        gl.drawElements(gl.TRIANGLES, 6 * Math.min(BATCH, this.count - base), gl.UNSIGNED_SHORT, 0);
      }
      gl.activeTexture(gl.TEXTURE0);
      gl.depthMask(true);
    }

    // tone map into the canvas
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, w, h);
    gl.disable(gl.BLEND);
    gl.disable(gl.DEPTH_TEST);
    gl.useProgram(this.tonemap.prog);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.hdr);
    gl.uniform1i(this.tonemap.uniforms.u_hdr, 0);
    gl.uniform1f(this.tonemap.uniforms.u_gain, Math.pow(2, frame.exposure));
    gl.uniform1i(this.tonemap.uniforms.u_method, { aces: 0, reinhard: 1, clamp: 2 }[frame.tonemap] ?? 0);
    gl.bindVertexArray(this.emptyVao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);

    // overlays
    gl.useProgram(this.overlay.prog);
    this._camera(this.overlay, cam);
    const ou = this.overlay.uniforms;
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    if (frame.proxy && this.proxy.size) {
      gl.clear(gl.DEPTH_BUFFER_BIT);
      gl.enable(gl.DEPTH_TEST);
      gl.depthFunc(gl.LESS);
      gl.uniform1i(ou.u_shade, 1);
      gl.uniform1f(ou.u_alpha, frame.proxyAlpha);
      for (const o of this.proxy.values()) {
        gl.bindVertexArray(o.vao);
        gl.drawElements(gl.TRIANGLES, o.count, gl.UNSIGNED_INT, 0);
      }
      gl.disable(gl.DEPTH_TEST);
    }
    gl.uniform1i(ou.u_shade, 0);
    gl.uniform1f(ou.u_alpha, 1.0);
    for (const o of [this.lines, this.highlight]) {
      if (!o) continue;
      gl.bindVertexArray(o.vao);
      gl.drawArrays(gl.LINES, 0, o.count);
    }
    gl.bindVertexArray(null);
  }
}
