// ctgs viewer: UI, camera state, the sort worker and the render loop. `window.viewer` is also the
// scripting interface the tests use (ready, show, benchmark, info, cameraPath). Served for a run folder
// (`ctgs view RUN_DIR`), it polls the run's status and shows each newer model as it lands (live.js).

import {loadBundle} from "./bundle.js";
import {Controls, MOVE_CODES, typesText, lookAt, poseFromViewmat, sceneUp, viewmatFromPose, add, sub, scale, norm,
  column} from "./camera.js";
import {Renderer, program} from "./renderer.js";
import {loadMesh, MeshLayer} from "./mesh.js";
import {cameraPathJson, splinePoses} from "./camera_path.js";
import {liveStatus, RunPanel, drawLegend, POLL_MS} from "./live.js";

const $ = (id) => document.getElementById(id);
const SHADERS = {surfelVert: "surfel.vert", surfelFrag: "surfel.frag", compositeVert: "composite.vert",
  compositeFrag: "composite.frag"};
// Smoothing of the frame-time readout (exponential moving average weight of a new frame).
const READOUT_EMA = 0.2;
// What the surfels show (renderer.draw's map): the image, or a map of ctgs/render/texel_map.py.
const MAPS = ["image", "texel_size", "texture_res"];
// The most of its time the page spends loading and drawing a run's newer models (see pace()).
const RELOAD_SHARE = 0.02;
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

// `?bundle=` names a folder on this server only: the page runs on 127.0.0.1 next to the user's files, so a link
// must not make it load (and display) a bundle from anywhere else.
function sameOriginBase(param) {
  let url;
  try {
    url = new URL(param, location.href);
  } catch (err) {
    throw new Error(`?bundle=${param}: not a valid address`);
  }
  if (url.origin !== location.origin) {
    throw new Error(`?bundle=${param}: the viewer only loads bundles served by its own server (${location.origin})`);
  }
  return url.pathname.replace(/\/+$/, "");
}

async function fetchText(url) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return r.text();
}

class Viewer {
  constructor() {
    this.params = new URLSearchParams(location.search);
    this.textures = this.params.get("textures") !== "0";
    this.fit = this.params.get("fit") === "1";
    this.showMesh = this.params.get("mesh") === "1";  // the mesh (`ctgs view --mesh`) instead of the surfels
    this.shadeMesh = this.params.get("shade") !== "0";
    this.camIndex = -1;
    this.dirty = true;
    this.sortId = 0;
    this.sortInFlight = null;  // {id, key}
    this.sortedKey = null;
    this.sortWaiters = [];
    this.readout = {frame: null, sort: null};  // ms
    this.pendingFences = [];
    this.map = Math.max(0, MAPS.indexOf(this.params.get("map") || "image"));
    this.gen = 0;  // the model's generation: a sort of an earlier model is not applied to a newer one
    this.modelVersion = 0;  // a run folder's: the version of the model shown
    this.reloadAfter = 0;  // performance.now() before which no newer model is loaded (pace())
    this.keyframes = [];  // the user's camera path
    this.ready = this.start().catch((err) => { this.fail(err); throw err; });
  }

  fail(err) {
    const box = $("error");
    box.textContent = `Viewer error: ${err.message || err}`;
    box.hidden = false;
    console.error(err);
  }

  async start() {
    const canvas = $("canvas");
    this.renderer = new Renderer(canvas, this.params.get("accum") || "auto");
    const status = (s) => { $("status").textContent = s; };
    const shaderSources = Promise.all(Object.values(SHADERS).map(fetchText));
    let bundleBase;
    this.live = await liveStatus();  // null: the viewer of one bundle
    if (this.live) {
      this.runPanel = new RunPanel();
      this.runPanel.show(this.live);
      while (!this.live.model) {  // a run that has written no checkpoint yet
        status("waiting for the run's first checkpoint");
        await sleep(POLL_MS);
        this.live = (await liveStatus()) || this.live;
        this.runPanel.show(this.live);
      }
      bundleBase = `live/${this.live.model.version}`;
      this.modelVersion = this.live.model.version;
    } else {
      bundleBase = sameOriginBase(this.params.get("bundle") || "bundle");
    }
    const [loaded, sources] = await Promise.all([loadBundle(bundleBase, status), shaderSources]);
    const shaders = Object.fromEntries(Object.keys(SHADERS).map((k, i) => [k, sources[i]]));
    const {bundle, arrays, pages} = loaded;
    this.bundle = bundle;
    this.renderer.init(bundle, arrays, pages, shaders);
    if (bundle.mesh) {
      status("mesh");
      const gl = this.renderer.gl;
      const [meshArrays, vs, fs] = await Promise.all([loadMesh(bundleBase, bundle.mesh), fetchText("mesh.vert"),
        fetchText("mesh.frag")]);
      this.mesh = new MeshLayer(gl, program(gl, vs, fs, ["mesh.vert", "mesh.frag"]), meshArrays, bundle.background);
    }
    this.cameras = bundle.cameras || [];
    this.center = bundle.center;
    this.up = sceneUp(this.cameras);
    this.radius = this.sceneRadius(arrays.means);
    this.worker = new Worker("sort_worker.js");
    this.worker.onmessage = (e) => this.onSorted(e.data);
    this.worker.onerror = (e) => this.fail(new Error(`sort worker: ${e.message}`));
    this.worker.postMessage({type: "init", means: arrays.means.slice()});
    this.controls = new Controls(canvas, this);
    this.buildUi();
    const want = this.params.get("camera");
    let idx = this.cameras.findIndex((c) => c.split === "test");
    if (want !== null) idx = /^\d+$/.test(want) ? Number(want) : this.cameras.findIndex((c) => c.name === want);
    if (this.cameras.length) this.setCamera(Math.max(0, Math.min(this.cameras.length - 1, idx)));
    else this.defaultPose();
    new ResizeObserver(() => this.cameraMoved()).observe($("view"));
    status("");
    await this.waitSorted(this.key(this.currentCam()));
    this.drawNow();
    this.renderer.finish();
    this.last = performance.now();
    this.asleep = true;
    this.wake();
    if (this.live) {
      this.pollTimer = setTimeout(() => this.poll(), POLL_MS);
      document.addEventListener("visibilitychange", () => {
        if (!document.hidden && this.pollTimer === null) this.poll();
      });
    }
  }

  // ---- a run folder: its status, and its newer models -----------------------------------------------
  async poll() {
    if (document.hidden) {  // a tab in the background asks for nothing; it catches up when shown (visibilitychange)
      this.pollTimer = null;
      return;
    }
    try {
      const st = await liveStatus();
      if (st) {
        this.live = st;
        this.runPanel.show(st);
        const newer = st.model && st.model.version > this.modelVersion;
        if (newer && !this.reloading && performance.now() >= this.reloadAfter) await this.reload(st.model.version);
        else if (newer) this.runPanel.waiting(st.model.iteration, (this.reloadAfter - performance.now()) / 1000);
      }
    } catch (err) {  // the server stopped (Ctrl-C) or a poll failed: said; the page and the model shown stay
      this.runPanel.note(`status: ${err.message}`);
    } finally {
      this.pollTimer = setTimeout(() => this.poll(), POLL_MS);
    }
  }

  // A newer model is drawn once RELOAD_SHARE of the time since the last one went to loading and drawing it: at once
  // with a GPU (tens of ms), and without one (software GL, seconds for a big model at a large canvas) seldom enough
  // that the page takes little CPU from the training beside it. (The first model's draw, which also compiles the
  // shaders, sets no pace: the first newer one is drawn as it lands.)
  pace(ms) {
    this.reloadAfter = performance.now() + ms * (1 / RELOAD_SHARE - 1);
  }

  // Show model `version` of the run in place of the one shown; the camera stays where it is.
  async reload(version) {
    this.reloading = true;
    const t0 = performance.now();
    try {
      const {bundle, arrays, pages} = await loadBundle(`live/${version}`, () => {});
      this.renderer.setData(bundle, arrays, pages);
      this.bundle = bundle;
      this.gen += 1;
      this.worker.postMessage({type: "init", means: arrays.means.slice()});
      this.sortedKey = null;
      this.modelVersion = version;
      this.renderStats();
      // (the loop draws nothing meanwhile: the new surfels have no order yet, the old picture stays up)
      await this.waitSorted(this.key(this.currentCam()));
      if (!this.holdLoop) {  // drawn here, to time it (a test's show() draws on its own)
        this.drawNow();
        this.renderer.finish();
        this.dirty = false;
      } else {
        this.dirty = true;
      }
      this.pace(performance.now() - t0);
    } catch (err) {  // a bundle replaced meanwhile by a newer one (the next poll loads that): said
      this.runPanel.note(`model ${version}: ${err.message}`);
    } finally {
      this.reloading = false;
    }
  }

  // Resolves once a model newer than `version` is drawn (tests: a run that goes on training).
  async waitModel(version) {
    while (this.modelVersion <= version || this.reloading) await sleep(100);
    await this.waitSorted(this.key(this.currentCam()));
    return this.modelVersion;
  }

  sceneRadius(means) {
    // Median distance of the surfels from the centre: robust to floaters far away.
    const n = means.length / 3, step = Math.max(1, Math.floor(n / 4096)), d = [];
    for (let i = 0; i < n; i += step) d.push(norm(sub([means[3 * i], means[3 * i + 1], means[3 * i + 2]], this.center)));
    d.sort((a, b) => a - b);
    return d.length ? Math.max(1e-6, d[d.length >> 1]) : 1;
  }

  defaultPose() {
    const eye = add(this.center, scale([0, 0, -1], 3 * this.radius));
    this.pose = lookAt(eye, this.center, this.up);
    this.target = this.center.slice();
    this.refCam = {fx: 500, fy: 500, cx: 400, cy: 300, width: 800, height: 600, near: 0.01 * this.radius};
    this.cameraMoved();
  }

  // ---- cameras -------------------------------------------------------------------------------------
  setCamera(i) {
    const c = this.cameras[i];
    this.camIndex = i;
    this.refCam = c;
    this.pose = poseFromViewmat(c.viewmat);
    // Orbit target: the point on the optical axis nearest the scene centre (at least 10% of the radius out).
    const fwd = column(this.pose.rot, 2), toCenter = sub(this.center, this.pose.pos);
    const along = Math.max(0.1 * this.radius, toCenter[0] * fwd[0] + toCenter[1] * fwd[1] + toCenter[2] * fwd[2]);
    this.target = add(this.pose.pos, scale(fwd, along));
    $("camera").value = String(i);
    this.cameraMoved();
  }

  cameraMoved() {
    if (this.controls && (this.controls.drag || this.controls.moving()) && this.camIndex >= 0) {
      this.camIndex = -1;  // left the recorded camera
      $("camera").value = "-1";
    }
    this.dirty = true;
  }

  // Fit: the reference camera's own intrinsics and image size (exactly what `ctgs render` uses).
  // Otherwise the canvas fills the view, with the reference camera's vertical field of view.
  intrinsics() {
    const c = this.refCam;
    if (this.fit) return {fx: c.fx, fy: c.fy, cx: c.cx, cy: c.cy, width: c.width, height: c.height};
    const view = $("view"), dpr = window.devicePixelRatio || 1;
    const width = Math.max(1, Math.round(view.clientWidth * dpr)), height = Math.max(1, Math.round(view.clientHeight * dpr));
    const fy = c.fy * height / c.height;
    return {fx: fy * c.fx / c.fy, fy, cx: width / 2, cy: height / 2, width, height};
  }

  currentCam() {
    const intr = this.intrinsics();
    return {...intr, viewmat: viewmatFromPose(this.pose), campos: this.pose.pos, near: this.refCam.near ?? 0.01};
  }

  key(cam) {
    return cam.viewmat.map((v) => v.toPrecision(9)).join(",") + "|" + cam.near;
  }

  // ---- sorting -------------------------------------------------------------------------------------
  requestSort(cam) {
    const key = this.key(cam);
    if (this.sortInFlight) { this.sortWanted = true; return; }
    this.sortInFlight = {id: ++this.sortId, key, gen: this.gen};
    this.worker.postMessage({type: "sort", id: this.sortId, view: new Float64Array(cam.viewmat), near: cam.near});
  }

  onSorted(msg) {
    const job = this.sortInFlight;
    this.sortInFlight = null;
    if (job.gen !== this.gen) {  // the order of the model before a reload: sort the new one
      this.requestSort(this.currentCam());
      return;
    }
    this.renderer.setOrder(msg.order, msg.count);
    this.sortedKey = job.key;
    this.readout.sort = msg.ms;
    this.lastSortMs = msg.ms;
    this.dirty = true;
    this.sortWaiters = this.sortWaiters.filter((w) => {
      if (w.key === job.key) { w.resolve(msg.ms); return false; }
      return true;
    });
    if (this.sortWanted || this.sortWaiters.length) {
      this.sortWanted = false;
      const cam = this.currentCam();
      if (this.key(cam) !== this.sortedKey) this.requestSort(cam);
    }
  }

  waitSorted(key) {
    if (this.sortedKey === key && !this.sortInFlight) return Promise.resolve(this.lastSortMs);
    const p = new Promise((resolve) => this.sortWaiters.push({key, resolve}));
    this.requestSort(this.currentCam());
    return p;
  }

  // ---- drawing -------------------------------------------------------------------------------------
  drawNow() {
    const cam = this.currentCam();
    const canvas = $("canvas");
    if (canvas.width !== cam.width || canvas.height !== cam.height) {
      canvas.width = cam.width;
      canvas.height = cam.height;
    }
    const dpr = window.devicePixelRatio || 1;
    canvas.style.width = `${cam.width / dpr}px`;
    canvas.style.height = `${cam.height / dpr}px`;
    if (this.showMesh && this.mesh) this.mesh.draw(cam, this.shadeMesh);
    else this.renderer.draw(cam, this.textures, this.map);
    return cam;
  }

  // The animation-frame loop runs while something changes (the camera, a draw or a sort pending, fly keys held, a
  // path playing) and sleeps otherwise: an idle page takes no CPU (in software GL the CPU draws it, beside a training).
  get dirty() { return this._dirty; }

  set dirty(v) {
    this._dirty = v;
    if (v) this.wake();
  }

  wake() {
    if (this.frameRequested || this.last === undefined) return;  // (before start() ends: it draws the first frame)
    this.frameRequested = true;
    requestAnimationFrame((t) => this.loop(t));
  }

  loop(now) {
    this.frameRequested = false;
    const dt = this.asleep ? 0 : Math.min(0.1, (now - this.last) / 1000);
    this.asleep = false;
    this.last = now;
    this.controls.update(dt);
    if (this.playing) this.playStep(now);
    this.pollFences(now);
    if (this.dirty && !this.holdLoop && !this.reloading) {
      const cam = this.currentCam();
      const key = this.key(cam);
      if (key !== this.sortedKey) this.requestSort(cam);
      const gl = this.renderer.gl;
      const t0 = performance.now();
      this.drawNow();
      this.pendingFences.push({sync: gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0), t0});
      gl.flush();
      this._dirty = key !== this.sortedKey;  // (the sort's answer wakes the loop again)
    }
    if (this._dirty || this.pendingFences.length || this.controls.moving() || this.playing) this.wake();
    else this.asleep = true;
  }

  // Frame time = from issuing the draw to the GPU signalling its fence (resolution: one animation frame).
  pollFences(now) {
    const gl = this.renderer.gl;
    while (this.pendingFences.length) {
      const f = this.pendingFences[0];
      if (gl.getSyncParameter(f.sync, gl.SYNC_STATUS) !== gl.SIGNALED) break;
      gl.deleteSync(f.sync);
      this.pendingFences.shift();
      const ms = now - f.t0;
      this.readout.frame = this.readout.frame === null ? ms : (1 - READOUT_EMA) * this.readout.frame + READOUT_EMA * ms;
    }
    const fmt = (v) => (v === null ? "-" : `${v.toFixed(1)} ms`);
    const text = `frame ${fmt(this.readout.frame)} · sort ${fmt(this.readout.sort)} (worker)`;
    // Only a change touches the page: a repaint every animation frame would keep a CPU busy while nothing moves
    // (half a core in software GL), taken from a training beside it.
    if (text !== this.readoutText) $("frametime").textContent = this.readoutText = text;
  }

  // ---- scripting interface (tests, benchmarks) ---------------------------------------------------------
  info() {
    const r = this.renderer;
    return {glRenderer: r.glRenderer, accumFormat: r.accumFormat.name, numSurfels: this.bundle.num_surfels,
      numTexels: this.bundle.num_texels, texelFormat: this.bundle.atlas.texel_format, cameras: this.cameras.length,
      meshTriangles: this.mesh ? this.mesh.count / 3 : 0, webgl2: true, live: !!this.live,
      modelVersion: this.modelVersion, modelIteration: this.bundle.live ? this.bundle.live.iteration : null};
  }

  // Render recorded camera i exactly (fit: its image size and intrinsics, or resized to size = [W, H]
  // with the intrinsics scaled; fit = false: the view's size), wait until the GPU is done, and return
  // the canvas rectangle in CSS pixels for a screenshot. mesh: the mesh instead of the surfels (shade: lit from the
  // camera). map: "image", or the map "texel_size" or "texture_res" (ctgs/render/texel_map.py).
  async show({camera, textures = true, size = null, fit = true, mesh = false, shade = true, map = "image"}) {
    await this.ready;
    if (mesh && !this.mesh) throw new Error("no mesh to show: start the viewer with ctgs view --mesh FILE");
    const held = this.holdLoop;
    this.holdLoop = true;  // no animation-frame draw meanwhile: it would queue ahead of ours
    try {
      this.showMesh = mesh;
      this.shadeMesh = shade;
      if (this.mesh) { $("mesh").checked = mesh; $("shade").checked = shade; }
      this.setMap(Math.max(0, MAPS.indexOf(map)));
      return await this.showHeld({camera, textures, size, fit});
    } finally {
      this.holdLoop = held;
    }
  }

  async showHeld({camera, textures, size, fit}) {
    this.textures = textures;
    $("textures").checked = textures;
    this.fit = fit;
    $("fit").checked = fit;
    this.setCamera(camera);
    if (size) {
      const c = this.refCam, sx = size[0] / c.width, sy = size[1] / c.height;
      this.refCam = {...c, fx: c.fx * sx, fy: c.fy * sy, cx: c.cx * sx, cy: c.cy * sy, width: size[0], height: size[1]};
    }
    await this.waitSorted(this.key(this.currentCam()));
    const t0 = performance.now();
    const cam = this.drawNow();
    this.renderer.finish();
    this.readout.frame = performance.now() - t0;
    this.dirty = false;
    const r = $("canvas").getBoundingClientRect();
    return {x: r.x, y: r.y, width: r.width, height: r.height, imageWidth: cam.width, imageHeight: cam.height,
      count: this.renderer.count};
  }

  // Orbit `frames` steps (a quarter turn in all) about the target from recorded camera i; per frame:
  // the worker's sort time and the draw time (issue to GPU completion, forced by a one-pixel read
  // back), both in ms.
  // tight = false draws bounds.h's pixel boxes instead of the tight quads (same image, more fragments).
  async benchmark({camera = 0, frames = 20, textures = true, size = null, tight = true}) {
    this.renderer.tightQuads = tight;
    await this.show({camera, textures, size});
    const drawMs = [], sortMs = [];
    const mode = this.controls.mode;
    this.controls.mode = "orbit";
    this.holdLoop = true;  // no animation-frame draws in between: they would be timed with ours
    try {
      for (let f = 0; f < frames; ++f) {
        this.controls.rotate(0.5 * Math.PI / frames / 0.005, 0);  // rotate() turns 0.005 rad per pixel
        sortMs.push(await this.waitSorted(this.key(this.currentCam())));
        const t0 = performance.now();
        this.drawNow();
        this.renderer.finish();
        drawMs.push(performance.now() - t0);
      }
    } finally {
      this.renderer.tightQuads = true;
      this.controls.mode = mode;
      this.holdLoop = false;
      this.dirty = true;
    }
    const cam = this.currentCam();
    return {drawMs, sortMs, width: cam.width, height: cam.height, count: this.renderer.count};
  }

  // ---- UI ----------------------------------------------------------------------------------------------
  buildUi() {
    const b = this.bundle, sel = $("camera");
    sel.replaceChildren();
    const free = document.createElement("option");
    free.value = "-1";
    free.textContent = "(free camera)";
    sel.appendChild(free);
    for (const split of ["train", "test"]) {
      const group = document.createElement("optgroup");
      group.label = split === "train" ? "Training cameras" : "Test cameras";
      this.cameras.forEach((c, i) => {
        if (c.split !== split) return;
        const o = document.createElement("option");
        o.value = String(i);
        o.textContent = `${c.name} (${c.width}x${c.height})`;
        group.appendChild(o);
      });
      if (group.children.length) sel.appendChild(group);
    }
    sel.onchange = () => { const i = Number(sel.value); if (i >= 0) this.setCamera(i); };
    const step = (d) => {
      if (!this.cameras.length) return;
      const i = this.camIndex < 0 ? 0 : (this.camIndex + d + this.cameras.length) % this.cameras.length;
      this.setCamera(i);
    };
    $("prev").onclick = () => step(-1);
    $("next").onclick = () => step(1);
    $("textures").checked = this.textures;
    $("textures").onchange = (e) => { this.textures = e.target.checked; this.dirty = true; };
    $("fit").checked = this.fit;
    $("fit").onchange = (e) => { this.fit = e.target.checked; this.dirty = true; };
    $("mesh-section").hidden = !this.mesh;
    $("mesh").checked = this.showMesh;
    $("mesh").onchange = (e) => { this.showMesh = e.target.checked; this.dirty = true; };
    $("shade").checked = this.shadeMesh;
    $("shade").onchange = (e) => { this.shadeMesh = e.target.checked; this.dirty = true; };
    for (const r of document.querySelectorAll("input[name=mode]")) {
      r.onchange = () => { this.controls.mode = r.value; };
      r.checked = r.value === (this.params.get("mode") || "orbit");
    }
    this.controls.mode = this.params.get("mode") === "fly" ? "fly" : "orbit";
    $("colour").onchange = (e) => this.setMap(Math.max(0, MAPS.indexOf(e.target.value)));
    this.setMap(this.map);
    $("key-add").onclick = () => this.addKeyframe();
    $("key-clear").onclick = () => { this.keyframes = []; this.stopPath(); this.showPathInfo(); };
    $("path-play").onclick = () => (this.playing ? this.stopPath() : this.playPath());
    $("path-save").onclick = () => this.saveCameraPath();
    this.showPathInfo();
    // Shortcuts work wherever the focus is (a clicked checkbox, the camera list), except in a text field; Shift
    // does not change them. Handled keys do nothing else (the camera list would jump to an option's first letter).
    window.addEventListener("keydown", (e) => {
      if (typesText(e.target) || e.ctrlKey || e.metaKey || e.altKey) return;
      const key = e.key.toLowerCase();
      if (key === "t") $("textures").click();
      else if (key === "m" && this.mesh) $("mesh").click();
      else if (key === "l" && this.mesh) $("shade").click();
      else if (key === "x") this.setMap((this.map + 1) % MAPS.length);
      else if (key === "k") this.addKeyframe();
      else if (key === "f") {
        const next = this.controls.mode === "orbit" ? "fly" : "orbit";
        document.querySelector(`input[name=mode][value=${next}]`).click();
      } else if (key === "]") step(1);
      else if (key === "[") step(-1);
      else if (!(this.controls.mode === "fly" && MOVE_CODES.has(e.code))) return;
      e.preventDefault();
    });
    this.renderStats();
  }

  // Every value from bundle.json goes in as text, never as HTML: a crafted bundle cannot run script here.
  renderStats() {
    const b = this.bundle;
    const mb = (x) => (Number(x) / 1e6).toFixed(1);
    const stats = $("stats"), dim = document.createElement("span");
    dim.className = "dim";
    const lines = (el, texts) => texts.forEach((t, i) => {
      if (i) el.appendChild(document.createElement("br"));
      el.appendChild(document.createTextNode(t));
    });
    stats.replaceChildren();
    const count = (x) => Number(x).toLocaleString();
    lines(stats, [`${count(b.num_surfels)} surfels · ${count(b.num_texels)} texels`,
      `SH degree ${b.sh_degree} · atlas ${b.atlas.pages.length} × ${b.atlas.page_size}² ${b.atlas.texel_format}`,
      `bundle ${mb(b.surfels.bytes + b.atlas.bytes)} MB`,
      ...(b.mesh ? [`mesh ${count(b.mesh.triangles)} triangles · ${mb(b.mesh.bytes)} MB`] : []), ""]);
    lines(dim, [String(this.renderer.glRenderer), `accumulation ${this.renderer.accumFormat.name}`]);
    stats.appendChild(dim);
  }

  // ---- the maps of texel size and texture resolution ------------------------------------------------------
  setMap(i) {
    this.map = i;
    $("colour").value = MAPS[i];
    drawLegend($("legend"), MAPS[i]);
    this.dirty = true;
  }

  // ---- the user's camera path (saved as nerfstudio's camera_path.json; `ctgs render --path FILE`) ---------
  addKeyframe() {
    this.keyframes.push({rot: this.pose.rot.slice(), pos: this.pose.pos.slice()});
    this.showPathInfo();
  }

  showPathInfo() {
    const n = this.keyframes.length;
    $("path-info").textContent = n ? `${n} keyframe${n > 1 ? "s" : ""}` : "no keyframes: add views (K)";
    $("path-play").disabled = $("path-save").disabled = n < 2;
    $("path-play").textContent = this.playing ? "Stop" : "Play";
  }

  // The camera path file of the keyframes: the reference camera's image size and the view's vertical field of view.
  cameraPath() {
    if (this.keyframes.length < 2) throw new Error("a camera path needs two keyframes or more (K adds the view)");
    const c = this.refCam, intr = this.intrinsics();
    const fovDeg = 2 * Math.atan(0.5 * intr.height / intr.fy) * 180 / Math.PI;
    const num = (id, lo, hi, dflt) => {
      const v = Number($(id).value);
      return Number.isFinite(v) && v >= lo && v <= hi ? v : dflt;
    };
    return cameraPathJson({keyframes: this.keyframes, fovDeg, width: c.width, height: c.height,
      fps: num("path-fps", 1, 120, 30), seconds: num("path-seconds", 0.1, 3600, 4)});
  }

  saveCameraPath() {
    const blob = new Blob([JSON.stringify(this.cameraPath(), null, 1)], {type: "application/json"});
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = "camera_path.json";
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 1000);
  }

  playPath() {
    const path = this.cameraPath();
    this.playing = {poses: splinePoses(this.keyframes, path.camera_path.length), fps: path.fps, t0: null};
    this.showPathInfo();
    this.wake();
  }

  playStep(now) {
    const p = this.playing;
    if (p.t0 === null) p.t0 = now;
    const i = Math.floor((now - p.t0) / 1000 * p.fps);
    if (i >= p.poses.length) { this.stopPath(); return; }
    this.pose = {rot: p.poses[i].rot.slice(), pos: p.poses[i].pos.slice()};
    if (this.camIndex >= 0) { this.camIndex = -1; $("camera").value = "-1"; }
    this.dirty = true;
  }

  stopPath() {
    this.playing = null;
    this.showPathInfo();
  }
}

window.viewer = new Viewer();
