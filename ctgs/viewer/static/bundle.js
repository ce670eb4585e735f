// Fetch a web bundle (docs/reference/model_format.md, "Web bundle") from `base`: bundle.json, surfels.bin and
// the atlas pages, as typed arrays aliasing the downloaded buffers.

const TYPED = {float32: Float32Array, float16: Uint16Array, uint16: Uint16Array, uint32: Uint32Array,
  int8: Int8Array, uint8: Uint8Array};

async function get(url, kind) {
  const r = await fetch(url);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  return kind === "json" ? r.json() : r.arrayBuffer();
}

export async function loadBundle(base, progress) {
  const bundle = await get(`${base}/bundle.json`, "json");
  if (bundle.format !== "ctgs-web" || bundle.version !== 1) {
    throw new Error(`${base}/bundle.json: not a version 1 ctgs web bundle (re-export with ctgs export --format web)`);
  }
  progress(`surfels: ${bundle.num_surfels.toLocaleString()}`);
  const raw = await get(`${base}/${bundle.surfels.file}`, "bin");
  const arrays = {};
  for (const [name, spec] of Object.entries(bundle.surfels.arrays)) {
    const T = TYPED[spec.dtype];
    if (!T) throw new Error(`surfels.bin: array ${name} has unsupported dtype ${spec.dtype}`);
    const count = spec.shape.reduce((a, b) => a * b, 1);
    arrays[name] = new T(raw, spec.offset, count);
  }
  const snorm = bundle.atlas.texel_format === "snorm8";
  const pages = [];
  for (const [p, page] of bundle.atlas.pages.entries()) {
    progress(`atlas page ${p + 1}/${bundle.atlas.pages.length}`);
    const buf = await get(`${base}/${page.file}`, "bin");
    pages.push(snorm ? new Int8Array(buf) : new Uint16Array(buf));
  }
  return {bundle, arrays, pages};
}
