// A run folder followed while it trains (`ctgs view RUN_DIR`, ctgs/viewer/live.py): its status, the run panel (state,
// iteration, loss, time left, the test PSNR curve over the loss), and the legends of the texel maps. Every value from
// the server goes in as text (textContent, canvas text), never as HTML.

// How often the page asks for the run's status (ms): a stat of a few files and the log's new lines on the server.
export const POLL_MS = 2000;

const $ = (id) => document.getElementById(id);

// The run's status, or null when this server shows a bundle, not a run folder (404).
export async function liveStatus() {
  const r = await fetch("live/status.json");
  if (r.status === 404) return null;
  if (!r.ok) throw new Error(`live/status.json: HTTP ${r.status}`);
  return r.json();
}

const STATES = {training: "training", finished: "finished", stopped: "stopped (not running; ctgs train --resume goes on)",
  diverged: "stopped: diverged (see its log)"};

function clock(seconds) {
  const s = Math.max(0, Math.round(seconds));
  return `${Math.floor(s / 3600)}:${String(Math.floor(s % 3600 / 60)).padStart(2, "0")}:${String(s % 60).padStart(2, "0")}`;
}

const fixed = (v, d) => (typeof v === "number" && Number.isFinite(v) ? v.toFixed(d) : "-");

export class RunPanel {
  constructor() {
    $("run-section").hidden = false;
    this.notes = [];
  }

  note(text) {
    this.extra = text;
    this.render();
  }

  show(st) {
    this.st = st;
    this.extra = null;
    this.render();
  }

  // A newer model (of iteration `it`) is there, drawn in `seconds` (the page paces its drawing: viewer.js pace()).
  waiting(it, seconds) {
    this.extra = `newer: iteration ${it.toLocaleString()}, drawn in ${Math.max(0, Math.ceil(seconds))} s`;
    this.render();
  }

  render() {
    const st = this.st;
    if (!st) return;
    const state = `${st.run}: ${STATES[st.state] || st.state}`;
    if ($("run-state").textContent !== state) $("run-state").textContent = state;
    const count = (x) => (typeof x === "number" ? x.toLocaleString() : "-");
    const last = st.test.length ? st.test[st.test.length - 1] : null;
    const lines = [
      `iteration ${count(st.iteration)}${st.planned ? ` / ${count(st.planned)}` : ""}`,
      `loss ${fixed(st.loss, 4)} · train PSNR ${fixed(st.train_psnr, 2)}`,
      `test PSNR ${last ? `${fixed(last[1], 2)} dB (it ${count(last[0])})` : "-"}`,
      `${count(st.primitives)} surfels · ${count(st.texels)} texels`,
      `time left ${typeof st.seconds_left === "number" ? clock(st.seconds_left) : "-"}`,
      st.model ? `shown: iteration ${count(st.model.iteration)} (${st.model.source})` : "shown: nothing yet",
      ...st.notes, ...(this.extra ? [this.extra] : []),
    ];
    // Only what changed is written: every change repaints the page (in software GL a cost taken from the training).
    const text = lines.join("\n");
    if (text !== this.text) {
      this.text = text;
      const el = $("run-stats");
      el.replaceChildren();
      lines.forEach((t, i) => {
        if (i) el.appendChild(document.createElement("br"));
        el.appendChild(document.createTextNode(String(t)));
      });
    }
    const curve = JSON.stringify([st.planned, st.test, st.loss_curve.length, st.loss_curve[st.loss_curve.length - 1]]);
    if (curve !== this.curve) {
      this.curve = curve;
      this.chart(st);
    }
  }

  // Test PSNR (dots, its scale on the left) over the loss (grey, log scale), against the iteration.
  chart(st) {
    const c = $("run-chart"), g = c.getContext("2d"), W = c.width, H = c.height, pad = 4, left = 30;
    g.clearRect(0, 0, W, H);
    g.fillStyle = "#15171a";
    g.fillRect(0, 0, W, H);
    const xmax = Math.max(1, st.planned || 0, st.iteration || 0);
    const x = (it) => left + (W - left - pad) * it / xmax;
    const loss = st.loss_curve.filter((p) => p[1] > 0);
    if (loss.length > 1) {
      const ls = loss.map((p) => Math.log(p[1])), lo = Math.min(...ls), hi = Math.max(...ls) + 1e-9;
      g.strokeStyle = "#666";
      g.beginPath();
      loss.forEach((p, i) => {
        const y = pad + (H - 2 * pad) * (1 - (Math.log(p[1]) - lo) / (hi - lo));
        if (i) g.lineTo(x(p[0]), y); else g.moveTo(x(p[0]), y);
      });
      g.stroke();
    }
    g.fillStyle = "#ddd";
    g.font = "10px sans-serif";
    if (st.test.length) {
      const ps = st.test.map((p) => p[1]);
      const lo = Math.floor(Math.min(...ps)) - 0.5, hi = Math.ceil(Math.max(...ps)) + 0.5;
      const y = (v) => pad + (H - 2 * pad) * (1 - (v - lo) / (hi - lo));
      g.strokeStyle = "#4aa3ff";
      g.fillStyle = "#4aa3ff";
      g.beginPath();
      st.test.forEach((p, i) => { if (i) g.lineTo(x(p[0]), y(p[1])); else g.moveTo(x(p[0]), y(p[1])); });
      g.stroke();
      for (const p of st.test) g.fillRect(x(p[0]) - 1.5, y(p[1]) - 1.5, 3, 3);
      g.fillStyle = "#ddd";
      g.fillText(`${hi.toFixed(1)}`, 2, 12);
      g.fillText(`${lo.toFixed(1)}`, 2, H - 4);
      g.fillText("test PSNR (dB) · loss", left + 4, 12);
    } else {
      g.fillText("no test evaluation yet", left + 4, 12);
    }
  }
}

// ctgs/render/texel_map.py TURBO and scales (the legend only; composite.frag colours the image)
const TURBO = [[0.188, 0.071, 0.231], [0.251, 0.251, 0.635], [0.275, 0.420, 0.890], [0.259, 0.580, 1.000],
  [0.157, 0.737, 0.922], [0.094, 0.867, 0.761], [0.196, 0.949, 0.596], [0.427, 0.996, 0.384],
  [0.643, 0.988, 0.235], [0.796, 0.929, 0.204], [0.925, 0.820, 0.227], [0.992, 0.682, 0.208],
  [0.984, 0.506, 0.133], [0.925, 0.325, 0.059], [0.824, 0.192, 0.020], [0.675, 0.090, 0.004],
  [0.478, 0.016, 0.012]];
const LEGENDS = {texel_size: ["½ px", "8 px", "128 px per texel"], texture_res: ["1", "256", "65,536 texels"]};

export function drawLegend(canvas, map) {
  canvas.hidden = !LEGENDS[map];
  if (canvas.hidden) return;
  const g = canvas.getContext("2d"), W = canvas.width, H = canvas.height;
  const grad = g.createLinearGradient(0, 0, W, 0);
  TURBO.forEach((c, i) => grad.addColorStop(i / (TURBO.length - 1), `rgb(${c.map((v) => Math.round(255 * v))})`));
  g.clearRect(0, 0, W, H);
  g.fillStyle = grad;
  g.fillRect(0, 0, W, 10);
  g.fillStyle = "#ddd";
  g.font = "10px sans-serif";
  const [a, b, c] = LEGENDS[map];
  g.textAlign = "left";
  g.fillText(a, 0, H - 3);
  g.textAlign = "center";
  g.fillText(b, W / 2, H - 3);
  g.textAlign = "right";
  g.fillText(c, W, H - 3);
}
