// The user's camera path: keyframes (poses the user adds), the spline through them, and the file `ctgs render --path
// FILE` renders (nerfstudio's camera_path.json layout). The spline is ctgs/scene/camera_path.py spline_poses:
// uniform Catmull-Rom through the keyframes' centres, viewing and up directions, frames evenly spaced by the length
// of the straight segments between keyframes, first and last frame on the first and last keyframe.

import {lookAt, add, sub, scale, norm, column} from "./camera.js";

function catmullRom(p0, p1, p2, p3, u) {
  const u2 = u * u, u3 = u2 * u;
  return p1.map((_, k) => 0.5 * (2 * p1[k] + (p2[k] - p0[k]) * u + (2 * p0[k] - 5 * p1[k] + 4 * p2[k] - p3[k]) * u2
    + (3 * p1[k] - p0[k] - 3 * p2[k] + p3[k]) * u3));
}

// Poses {rot, pos} (camera -> world rotation row-major, centre) of `frames` frames along the keyframes' spline.
export function splinePoses(keyframes, frames) {
  const k = keyframes.length;
  if (k === 1) return Array.from({length: frames}, () => ({rot: keyframes[0].rot.slice(), pos: keyframes[0].pos.slice()}));
  const centers = keyframes.map((p) => p.pos);
  const fwd = keyframes.map((p) => column(p.rot, 2));
  const up = keyframes.map((p) => scale(column(p.rot, 1), -1));
  let seg = [];
  for (let i = 0; i + 1 < k; ++i) seg.push(norm(sub(centers[i + 1], centers[i])));
  if (!(seg.reduce((a, b) => a + b, 0) > 1e-12)) seg = seg.map(() => 1);  // turning on the spot: by index
  const cum = [0];
  for (const s of seg) cum.push(cum[cum.length - 1] + s);
  const out = [];
  for (let f = 0; f < frames; ++f) {
    const s = cum[k - 1] * (frames > 1 ? f / (frames - 1) : 0);
    let i = 0;
    while (i < k - 2 && cum[i + 1] <= s) ++i;
    const u = seg[i] > 0 ? (s - cum[i]) / seg[i] : 0;
    const idx = [Math.max(i - 1, 0), i, i + 1, Math.min(i + 2, k - 1)];
    const pick = (arr) => idx.map((j) => arr[j]);
    const eye = catmullRom(...pick(centers), u);
    const dir = catmullRom(...pick(fwd), u);
    const upv = catmullRom(...pick(up), u);
    out.push(lookAt(eye, add(eye, dir), upv));
  }
  return out;
}

// camera -> world with OpenGL camera axes (x right, y up, z backward), row by row: nerfstudio's camera_to_world.
export function openglCameraToWorld({rot, pos}) {
  const r = rot;
  return [r[0], -r[1], -r[2], pos[0], r[3], -r[4], -r[5], pos[1], r[6], -r[7], -r[8], pos[2], 0, 0, 0, 1];
}

// The camera path file: keyframes, the frames of `seconds` at `fps` along their spline, the render size and the
// vertical field of view (degrees) the frames are rendered with.
export function cameraPathJson({keyframes, fovDeg, width, height, fps, seconds}) {
  const frames = Math.max(1, Math.round(fps * seconds));
  const aspect = width / height;
  return {
    camera_type: "perspective", render_width: width, render_height: height, fps, seconds: frames / fps,
    is_cycle: false, smoothness_value: 0.0, default_fov: fovDeg,
    keyframes: keyframes.map((p) => ({matrix: openglCameraToWorld(p), fov: fovDeg, aspect})),
    camera_path: splinePoses(keyframes, frames).map((p) => ({camera_to_world: openglCameraToWorld(p), fov: fovDeg,
      aspect})),
  };
}
