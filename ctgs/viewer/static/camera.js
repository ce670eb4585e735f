// Camera pose, intrinsics and the orbit / fly controls. Conventions of ctgs.render.camera (OpenCV):
// camera looks down +z, x right, y down; viewmat maps world -> camera. A pose is (rot, pos): rot is the
// camera -> world rotation (row-major 3x3, its columns are the camera axes in world coordinates), pos
// the camera centre.

export function mat3Mul(a, b) {
  const o = new Array(9);
  for (let i = 0; i < 3; ++i)
    for (let j = 0; j < 3; ++j) o[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
  return o;
}

export function mat3Vec(a, v) {
  return [a[0] * v[0] + a[1] * v[1] + a[2] * v[2], a[3] * v[0] + a[4] * v[1] + a[5] * v[2],
          a[6] * v[0] + a[7] * v[1] + a[8] * v[2]];
}

const transpose3 = (a) => [a[0], a[3], a[6], a[1], a[4], a[7], a[2], a[5], a[8]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const norm = (a) => Math.sqrt(dot(a, a));
const normalize = (a) => { const n = norm(a); return n > 0 ? scale(a, 1 / n) : a; };
const column = (r, j) => [r[j], r[3 + j], r[6 + j]];

// Rotation of `angle` radians about the unit `axis` (Rodrigues), row-major 3x3.
export function axisAngle(axis, angle) {
  const [x, y, z] = normalize(axis), c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
  return [t * x * x + c, t * x * y - s * z, t * x * z + s * y,
          t * x * y + s * z, t * y * y + c, t * y * z - s * x,
          t * x * z - s * y, t * y * z + s * x, t * z * z + c];
}

export function poseFromViewmat(vm) {  // vm: 16 numbers, row-major world -> camera
  const rw2c = [vm[0], vm[1], vm[2], vm[4], vm[5], vm[6], vm[8], vm[9], vm[10]];
  const rot = transpose3(rw2c);
  return {rot, pos: scale(mat3Vec(rot, [vm[3], vm[7], vm[11]]), -1)};
}

export function viewmatFromPose({rot, pos}) {  // -> 16 numbers, row-major world -> camera
  const r = transpose3(rot), t = scale(mat3Vec(r, pos), -1);
  return [r[0], r[1], r[2], t[0], r[3], r[4], r[5], t[1], r[6], r[7], r[8], t[2], 0, 0, 0, 1];
}

// Re-orthonormalise a rotation (accumulated control steps drift).
function orthonormal(rot) {
  const z = normalize(column(rot, 2));
  let x = column(rot, 0);
  x = normalize(sub(x, scale(z, dot(x, z))));
  const y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]];
  return [x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]];
}

// World "up": the mean of the cameras' up directions (-y in OpenCV), else -y.
export function sceneUp(cameras) {
  let up = [0, 0, 0];
  for (const c of cameras) up = add(up, scale(column(poseFromViewmat(c.viewmat).rot, 1), -1));
  return norm(up) > 1e-6 ? normalize(up) : [0, -1, 0];
}

// A camera looking at `target` from `eye` (used when the bundle holds no cameras).
export function lookAt(eye, target, up) {
  const z = normalize(sub(target, eye));
  const x = normalize([z[1] * up[2] - z[2] * up[1], z[2] * up[0] - z[0] * up[2], z[0] * up[1] - z[1] * up[0]]);  // z x up
  const y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]];
  return {rot: [x[0], y[0], z[0], x[1], y[1], z[1], x[2], y[2], z[2]], pos: eye.slice()};
}

// Whether keys typed into element `el` go to it (a text field), not to the viewer's keys.
export function typesText(el) {
  if (el instanceof HTMLTextAreaElement || (el instanceof HTMLElement && el.isContentEditable)) return true;
  const keyless = ["checkbox", "radio", "button", "range", "submit", "reset"];
  return el instanceof HTMLInputElement && !keyless.includes(el.type);
}

// Fly keys by physical key (KeyboardEvent.code) -> the letter update() reads.
export const MOVE_CODES = new Map([["KeyW", "w"], ["KeyA", "a"], ["KeyS", "s"], ["KeyD", "d"], ["KeyQ", "q"],
  ["KeyE", "e"]]);

// Orbit: drag rotates about `target` (yaw about world up, pitch about the camera's x axis), wheel
// dollies, right/shift drag pans. Fly: W A S D move, Q E down/up, drag looks around, wheel sets speed.
export class Controls {
  constructor(element, viewer) {
    this.viewer = viewer;
    this.mode = "orbit";
    this.keys = new Set();
    this.drag = null;
    this.speed = 1.0;  // fly speed, scene radii per second
    element.addEventListener("contextmenu", (e) => e.preventDefault());
    element.addEventListener("pointerdown", (e) => {
      element.setPointerCapture(e.pointerId);
      this.drag = {x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey};
    });
    element.addEventListener("pointermove", (e) => {
      if (!this.drag) return;
      const dx = e.clientX - this.drag.x, dy = e.clientY - this.drag.y;
      this.drag.x = e.clientX;
      this.drag.y = e.clientY;
      if (this.drag.pan) this.pan(dx, dy); else this.rotate(dx, dy);
    });
    element.addEventListener("pointerup", () => { this.drag = null; });
    element.addEventListener("wheel", (e) => {
      e.preventDefault();
      if (this.mode === "orbit") this.dolly(Math.exp(e.deltaY * 0.001));
      else this.speed *= Math.exp(-e.deltaY * 0.001);
    }, {passive: false});
    // Only the movement keys are held (by physical key: Shift or a layout change between press and release must
    // not leave one stuck); any other key, `[` `]` included, is a shortcut and not a camera motion.
    window.addEventListener("keydown", (e) => {
      if (typesText(e.target) || e.ctrlKey || e.metaKey || e.altKey || !MOVE_CODES.has(e.code)) return;
      this.keys.add(MOVE_CODES.get(e.code));
      this.viewer.wake();  // (the render loop sleeps while nothing moves)
    });
    window.addEventListener("keyup", (e) => { if (MOVE_CODES.has(e.code)) this.keys.delete(MOVE_CODES.get(e.code)); });
    window.addEventListener("blur", () => this.keys.clear());
  }

  // Whether a held key is moving the camera now (fly mode; orbit mode ignores them).
  moving() {
    return this.mode === "fly" && this.keys.size > 0;
  }

  rotate(dx, dy) {
    const v = this.viewer, pose = v.pose, k = 0.005;
    const yaw = axisAngle(v.up, -dx * k), pitch = axisAngle(column(pose.rot, 0), -dy * k);
    const r = mat3Mul(yaw, pitch);
    if (this.mode === "orbit") pose.pos = add(v.target, mat3Vec(r, sub(pose.pos, v.target)));
    pose.rot = orthonormal(mat3Mul(r, pose.rot));
    if (this.mode === "fly") v.target = add(pose.pos, scale(column(pose.rot, 2), norm(sub(v.target, pose.pos))));
    v.cameraMoved();
  }

  pan(dx, dy) {
    const v = this.viewer, pose = v.pose;
    const dist = norm(sub(v.target, pose.pos));
    const k = dist / v.intrinsics().fy;  // one pixel at the target's distance
    const move = add(scale(column(pose.rot, 0), -dx * k), scale(column(pose.rot, 1), -dy * k));
    pose.pos = add(pose.pos, move);
    v.target = add(v.target, move);
    v.cameraMoved();
  }

  dolly(factor) {
    const v = this.viewer, pose = v.pose;
    pose.pos = add(v.target, scale(sub(pose.pos, v.target), factor));
    v.cameraMoved();
  }

  // Fly keys, called once per animation frame with the elapsed seconds.
  update(dt) {
    if (this.mode !== "fly" || this.keys.size === 0) return;
    const v = this.viewer, rot = v.pose.rot;
    const dir = [0, 0, 0];
    if (this.keys.has("w")) dir[2] += 1;
    if (this.keys.has("s")) dir[2] -= 1;
    if (this.keys.has("d")) dir[0] += 1;
    if (this.keys.has("a")) dir[0] -= 1;
    if (this.keys.has("q")) dir[1] += 1;  // camera y points down
    if (this.keys.has("e")) dir[1] -= 1;
    if (norm(dir) === 0) return;
    const step = mat3Vec(rot, scale(normalize(dir), this.speed * v.radius * dt));
    v.pose.pos = add(v.pose.pos, step);
    v.target = add(v.target, step);
    v.cameraMoved();
  }
}

export {add, sub, scale, norm, column};
