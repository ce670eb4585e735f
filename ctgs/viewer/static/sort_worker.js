// Depth sort off the main thread. docs/reference/renderer.md blends in increasing centre depth mu_c.z, ties by
// index; the viewer draws back to front, so it gets that order reversed. Surfels whose centre lies
// before the near plane are dropped (they contribute nowhere).
//
// Messages in:  {type: "init", means: Float32Array [N*3]}
//               {type: "sort", id, view: Float64Array(16) row-major world->camera, near}
// Messages out: {type: "sorted", id, order: Uint32Array (back to front), count, ms}

"use strict";

let means = null;  // Float32Array [N*3]
let depth = null;  // Float32Array [N]
let keys = null, keys2 = null, idx = null, idx2 = null;  // Uint32Array [N] scratch

function init(m) {
  means = m;
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

function sort(view, near) {
  const t0 = performance.now();
  const n = depth.length;
  const r0 = view[8], r1 = view[9], r2 = view[10], t = view[11];  // third row: camera-space z
  const f32 = new Float32Array(1), u32 = new Uint32Array(f32.buffer);
  let count = 0;
  for (let i = 0; i < n; ++i) {
    const z = Math.fround(r0 * means[3 * i] + r1 * means[3 * i + 1] + r2 * means[3 * i + 2] + t);
    if (!(z >= near)) continue;  // mu_c.z < near (or NaN): culled
    f32[0] = z;
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
    init(msg.means);
  } else if (msg.type === "sort") {
    const {order, count, ms} = sort(msg.view, msg.near);
    self.postMessage({type: "sorted", id: msg.id, order, count, ms}, [order.buffer]);
  }
};
