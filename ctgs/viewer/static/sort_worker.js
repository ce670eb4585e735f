// Blending-order sort off the main thread. docs/renderer.md ("Blending order") blends in increasing
// sort_depth, ties by index: the centre depth mu_c.z when the centre projects inside the image, else the
// depth at which the surfel's plane crosses the ray through the image point nearest its projected centre
// (when that hit is well defined and in front of the near plane). The viewer draws back to front, so it
// gets that order reversed. Surfels whose centre lies before the near plane are dropped.
//
// Messages in:  {type: "init", means: Float32Array [N*3], normals: Float32Array [N*3] (world, unit)}
//               {type: "sort", id, view: Float64Array(16) row-major world->camera, near,
//                intr: {fx, fy, cx, cy, width, height}}
// Messages out: {type: "sorted", id, order: Uint32Array (back to front), count, ms}

"use strict";

let means = null;  // Float32Array [N*3]
let normals = null;  // Float32Array [N*3]
let depth = null;  // Float32Array [N]
let keys = null, keys2 = null, idx = null, idx2 = null;  // Uint32Array [N] scratch

const PARALLEL_EPS = 1e-6;  // docs/renderer.md: the ray/plane hit is valid iff |n.d| > PARALLEL_EPS |d|

function init(m, nrm) {
  means = m;
  normals = nrm;
  const n = m.length / 3;
  depth = new Float32Array(n);
  keys = new Uint32Array(n);
  keys2 = new Uint32Array(n);
  idx = new Uint32Array(n);
  idx2 = new Uint32Array(n);
}

// LSD radix sort of (keys, idx)[0..count), 4 passes of 8 bits. Stable, so equal depths keep index order.
function radixSort(count) {
  const hist = new Uint32Array(256);
  let k = keys, k2 = keys2, v = idx, v2 = idx2;
  for (let shift = 0; shift < 32; shift += 8) {
    hist.fill(0);
    for (let i = 0; i < count; ++i) hist[(k[i] >>> shift) & 255]++;
    let sum = 0;
    for (let b = 0; b < 256; ++b) { const h = hist[b]; hist[b] = sum; sum += h; }
    for (let i = 0; i < count; ++i) {
      const pos = hist[(k[i] >>> shift) & 255]++;
      k2[pos] = k[i];
      v2[pos] = v[i];
    }
    [k, k2] = [k2, k];
    [v, v2] = [v2, v];
  }
  return v;  // after an even number of passes: the original idx array
}

function sort(view, near, intr) {
  const t0 = performance.now();
  const n = depth.length;
  const {fx, fy, cx, cy, width, height} = intr;
  const f32 = new Float32Array(1), u32 = new Uint32Array(f32.buffer);
  let count = 0;
  for (let i = 0; i < n; ++i) {
    const wx = means[3 * i], wy = means[3 * i + 1], wz = means[3 * i + 2];
    const z = view[8] * wx + view[9] * wy + view[10] * wz + view[11];
    if (!(z >= near)) continue;  // mu_c.z < near (or NaN): culled
    let key = z;
    const x = view[0] * wx + view[1] * wy + view[2] * wz + view[3];
    const y = view[4] * wx + view[5] * wy + view[6] * wz + view[7];
    const mx = fx * x / z + cx, my = fy * y / z + cy;
    const px = Math.min(Math.max(mx, 0), width), py = Math.min(Math.max(my, 0), height);
    if (px !== mx || py !== my) {  // centre outside the image: the plane's depth at the image point nearest it
      const ax = normals[3 * i], ay = normals[3 * i + 1], az = normals[3 * i + 2];
      const nx = view[0] * ax + view[1] * ay + view[2] * az;
      const ny = view[4] * ax + view[5] * ay + view[6] * az;
      const nz = view[8] * ax + view[9] * ay + view[10] * az;
      const dx = (px - cx) / fx, dy = (py - cy) / fy;
      const denom = nx * dx + ny * dy + nz;
      if (Math.abs(denom) > PARALLEL_EPS * Math.sqrt(dx * dx + dy * dy + 1)) {
        const t = (nx * x + ny * y + nz * z) / denom;
        if (t >= near) key = t;
      }
    }
    f32[0] = key;
    const b = u32[0];
    keys[count] = (b & 0x80000000) ? ~b >>> 0 : (b | 0x80000000) >>> 0;  // float order as unsigned order
    idx[count] = i;
    ++count;
  }
  const asc = radixSort(count);
  const order = new Uint32Array(count);
  for (let i = 0; i < count; ++i) order[i] = asc[count - 1 - i];
  return {order, count, ms: performance.now() - t0};
}

self.onmessage = (e) => {
  const msg = e.data;
  if (msg.type === "init") {
    init(msg.means, msg.normals);
  } else if (msg.type === "sort") {
    const {order, count, ms} = sort(msg.view, msg.near, msg.intr);
    self.postMessage({type: "sorted", id: msg.id, order, count, ms}, [order.buffer]);
  }
};
