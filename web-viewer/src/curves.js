// A replay's force and metric curves over its whole recording, drawn under the
// timeline with a cursor at the step shown; a click seeks there. The server builds the
// curves by playing the recording through once when the replay opens
// (GET /api/sessions/{id}/timeline, docs/server.md); until that is done the curves grow
// and the canvas says how far it got.

const SERIES = [
  // key, colour, label, scale: 'force' (0 to the largest force) or a fixed maximum
  { key: 'force_peak_n', colour: '#ffd030', label: 'force', scale: 'force' },
  { key: 'score', colour: '#5fd38d', label: 'score', scale: 100 },
  { key: 'coverage_pct', colour: '#5fa8ff', label: 'coverage %', scale: 100 },
  { key: 'deviation_rms_mm', colour: '#ff7f50', label: 'deviation mm', scale: 'deviation' },
];
const POLL_MS = 400;

export class TimelineCurves {
  /** `load()` fetches the timeline (or null); `seek(step)` asks the replay to go there. */
  constructor(canvas, { load, seek }) {
    this.canvas = canvas;
    this.load = load;
    this.timeline = null;
    this.cursor = 0;
    // Fetching starts once, and ends when the curves are complete or on stop().
    this.started = false;
    this.stopped = false;
    canvas.onclick = (e) => {
      const t = this.timeline;
      if (!t || !t.total_steps) return;
      const rect = canvas.getBoundingClientRect();
      const fraction = Math.min(1, Math.max(0, (e.clientX - rect.left) / rect.width));
      seek(Math.round(fraction * t.total_steps));
    };
  }

  /** Fetches the curves, again until they cover the recording; later calls do nothing. */
  async start() {
    if (this.started) return;
    this.started = true;
    while (!this.stopped) {
      const timeline = await this.load();
      if (timeline) {
        this.timeline = timeline;
        this.canvas.dataset.bins = String(timeline.force_peak_n.length);
        this.canvas.dataset.complete = String(timeline.indexed_steps >= timeline.total_steps);
        this.draw();
        if (timeline.indexed_steps >= timeline.total_steps) break;
      }
      await new Promise((resolve) => setTimeout(resolve, POLL_MS));
    }
  }

  stop() {
    this.stopped = true;
  }

  /** The step shown moved. */
  setCursor(step) {
    if (step === this.cursor) return;
    this.cursor = step;
    this.draw();
  }

  draw() {
    const t = this.timeline;
    const g = this.canvas.getContext('2d');
    const { width: w, height: h } = this.canvas;
    g.clearRect(0, 0, w, h);
    g.fillStyle = '#14171b';
    g.fillRect(0, 0, w, h);
    g.font = '10px sans-serif';
    if (!t || !t.total_steps) {
      g.fillStyle = '#aab';
      g.fillText('timeline: waiting for the replay…', 6, 14);
      return;
    }
    const bins = Math.ceil(t.total_steps / t.bin_steps);
    const x = (i) => (w * (i + 0.5)) / bins;
    const maxForce = Math.max(0.1, ...t.force_peak_n);
    const maxDeviation = Math.max(1, ...t.deviation_rms_mm.filter((d) => d != null));
    const top = 14;
    const y = (v, max) => h - 3 - (h - top - 3) * Math.min(1, v / max);
    const legend = [];
    for (const s of SERIES) {
      const values = t[s.key];
      if (!values || values.every((v) => v == null)) continue;
      const max = s.scale === 'force' ? maxForce : s.scale === 'deviation' ? maxDeviation : s.scale;
      g.strokeStyle = s.colour;
      g.beginPath();
      let drawing = false;
      values.forEach((v, i) => {
        if (v == null) {
          drawing = false;
          return;
        }
        if (drawing) g.lineTo(x(i), y(v, max));
        else g.moveTo(x(i), y(v, max));
        drawing = true;
      });
      g.stroke();
      legend.push([s.colour, s.scale === 'force' ? `force ≤ ${maxForce.toFixed(2)} N` : s.scale === 'deviation' ? `deviation ≤ ${maxDeviation.toFixed(1)} mm` : s.label]);
    }
    // Where the index has not reached yet.
    if (t.indexed_steps < t.total_steps) {
      const from = (w * t.indexed_steps) / t.total_steps;
      g.fillStyle = 'rgba(255,255,255,0.06)';
      g.fillRect(from, 0, w - from, h);
      g.fillStyle = '#aab';
      g.fillText(`indexing ${Math.floor((100 * t.indexed_steps) / t.total_steps)} %`, Math.min(from + 4, w - 80), h - 6);
    }
    let lx = 6;
    for (const [colour, text] of legend) {
      g.fillStyle = colour;
      g.fillText(text, lx, 11);
      lx += g.measureText(text).width + 12;
    }
    const cx = (w * this.cursor) / t.total_steps;
    g.strokeStyle = '#ffffff';
    g.beginPath();
    g.moveTo(cx, 0);
    g.lineTo(cx, h);
    g.stroke();
  }
}
