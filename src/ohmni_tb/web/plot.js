// A small canvas plotter: time series (the wheel speeds) and an x-y trace (the odometry).
//
// Samples are pushed as they come; drawing happens at most once per animation frame and
// only when something changed, so a burst of samples costs one draw. Colours come from
// the page's CSS custom properties (light and dark themes alike).

/** A "nice" step for about `count` intervals over `span`: 1, 2 or 5 times a power of ten. */
function niceStep(span, count) {
  const raw = span / Math.max(1, count);
  const power = 10 ** Math.floor(Math.log10(raw));
  for (const factor of [1, 2, 5, 10]) {
    if (factor * power >= raw) return factor * power;
  }
  return 10 * power;
}

function decimals(step) {
  return Math.max(0, Math.min(3, -Math.floor(Math.log10(step) + 1e-9)));
}

class CanvasPlot {
  constructor(canvas) {
    this.canvas = canvas;
    this.context = canvas.getContext("2d");
    this.dirty = true;
    this.frame = 0;
    this.width = 0;
    this.height = 0;
    this.resize();
    new ResizeObserver(() => {
      this.resize();
      this.request();
    }).observe(canvas);
  }

  resize() {
    const ratio = window.devicePixelRatio || 1;
    const box = this.canvas.getBoundingClientRect();
    this.width = Math.max(1, box.width);
    this.height = Math.max(1, box.height);
    this.canvas.width = Math.round(this.width * ratio);
    this.canvas.height = Math.round(this.height * ratio);
    this.context.setTransform(ratio, 0, 0, ratio, 0, 0);
    this.dirty = true;
  }

  /** Draw at the next animation frame (once, however many samples came meanwhile). */
  request() {
    this.dirty = true;
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = 0;
      if (this.dirty) {
        this.dirty = false;
        this.draw();
      }
    });
  }

  colour(name, fallback) {
    const value = getComputedStyle(this.canvas).getPropertyValue(name).trim();
    return value || fallback;
  }

  clear() {
    const context = this.context;
    context.clearRect(0, 0, this.width, this.height);
    context.font = `${11}px system-ui, sans-serif`;
    context.lineJoin = "round";
    context.lineCap = "round";
  }
}

/**
 * Lines over the last `windowS` seconds. `series`: [{key, label, colour (a CSS custom
 * property), dash}]. Time is the samples' own stamp (the daemon's clock), so lines from
 * different streams line up.
 */
export class TimePlot extends CanvasPlot {
  constructor(canvas, { series, windowS = 10, minSpan = 0.2 }) {
    super(canvas);
    this.series = series;
    this.windowS = windowS;
    this.minSpan = minSpan;
    this.points = new Map(series.map((s) => [s.key, []]));
    this.latest = -Infinity;
  }

  push(key, t, value) {
    const line = this.points.get(key);
    if (!line || !Number.isFinite(value)) return;
    line.push([t, value]);
    this.latest = Math.max(this.latest, t);
    const oldest = this.latest - this.windowS - 1;
    let drop = 0;
    while (drop < line.length && line[drop][0] < oldest) drop += 1;
    if (drop) line.splice(0, drop);
    this.request();
  }

  clearData() {
    for (const line of this.points.values()) line.length = 0;
    this.latest = -Infinity;
    this.request();
  }

  draw() {
    this.clear();
    const c = this.context;
    const text = this.colour("--plot-text", "#555");
    const grid = this.colour("--plot-grid", "#ddd");
    const left = 40;
    const right = this.width - 8;
    const top = 8;
    const bottom = this.height - 20;
    const end = Number.isFinite(this.latest) ? this.latest : 0;
    const start = end - this.windowS;
    let low = 0;
    let high = 0;
    for (const line of this.points.values()) {
      for (const [t, v] of line) {
        if (t < start) continue;
        low = Math.min(low, v);
        high = Math.max(high, v);
      }
    }
    const pad = Math.max((high - low) * 0.1, (this.minSpan - (high - low)) / 2, 0);
    low -= pad;
    high += pad;
    const x = (t) => left + ((t - start) / this.windowS) * (right - left);
    const y = (v) => bottom - ((v - low) / (high - low)) * (bottom - top);

    const step = niceStep(high - low, Math.max(2, Math.floor((bottom - top) / 36)));
    c.strokeStyle = grid;
    c.fillStyle = text;
    c.lineWidth = 1;
    c.textAlign = "right";
    c.textBaseline = "middle";
    for (let v = Math.ceil(low / step) * step; v <= high + 1e-9; v += step) {
      const py = Math.round(y(v)) + 0.5;
      c.globalAlpha = Math.abs(v) < step / 2 ? 1 : 0.6;
      c.beginPath();
      c.moveTo(left, py);
      c.lineTo(right, py);
      c.stroke();
      c.globalAlpha = 1;
      c.fillText(v.toFixed(decimals(step)), left - 4, py);
    }
    c.textAlign = "center";
    c.textBaseline = "top";
    for (let s = 0; s <= this.windowS; s += 2) {
      const px = Math.round(x(end - s)) + 0.5;
      c.fillText(s === 0 ? "now" : `−${s} s`, Math.min(px, right - 12), bottom + 5);
    }

    c.save();
    c.beginPath();
    c.rect(left, top, right - left, bottom - top);
    c.clip();
    c.lineWidth = 2;
    for (const s of this.series) {
      const line = this.points.get(s.key);
      c.strokeStyle = this.colour(s.colour, "#06c");
      c.setLineDash(s.dash ? [6, 4] : []);
      c.beginPath();
      let first = true;
      for (const [t, v] of line) {
        if (t < start - 1) continue;
        if (first) c.moveTo(x(t), y(v));
        else c.lineTo(x(t), y(v));
        first = false;
      }
      c.stroke();
    }
    c.restore();
    c.setLineDash([]);
  }
}

/** The odometry's x-y path (the last `maxPoints` positions) with the robot's heading. */
export class TracePlot extends CanvasPlot {
  constructor(canvas, { maxPoints = 3000, minSpanM = 1, minMoveM = 0.005 } = {}) {
    super(canvas);
    this.maxPoints = maxPoints;
    this.minSpanM = minSpanM;
    this.minMoveM = minMoveM;
    this.path = [];
    this.pose = null;
  }

  push(x, y, yaw) {
    this.pose = [x, y, yaw];
    const last = this.path[this.path.length - 1];
    // A point per few millimetres moved: a robot standing still adds none.
    if (!last || Math.hypot(x - last[0], y - last[1]) >= this.minMoveM) {
      this.path.push([x, y]);
      if (this.path.length > this.maxPoints) this.path.splice(0, this.path.length - this.maxPoints);
    }
    this.request();
  }

  clearData() {
    this.path.length = 0;
    this.request();
  }

  draw() {
    this.clear();
    const c = this.context;
    const text = this.colour("--plot-text", "#555");
    const grid = this.colour("--plot-grid", "#ddd");
    const margin = 34;
    let minX = Infinity;
    let maxX = -Infinity;
    let minY = Infinity;
    let maxY = -Infinity;
    const points = this.pose ? [...this.path, this.pose] : this.path;
    for (const [px, py] of points) {
      minX = Math.min(minX, px);
      maxX = Math.max(maxX, px);
      minY = Math.min(minY, py);
      maxY = Math.max(maxY, py);
    }
    if (!Number.isFinite(minX)) {
      minX = maxX = minY = maxY = 0;
    }
    const width = this.width - 2 * margin;
    const height = this.height - 2 * margin;
    // One scale for both axes (a circle stays round), fitting the path with a margin.
    const span = Math.max(this.minSpanM, (maxX - minX) * 1.15, ((maxY - minY) * 1.15 * width) / height);
    const scale = width / span;
    const cx = (minX + maxX) / 2;
    const cy = (minY + maxY) / 2;
    const sx = (px) => margin + width / 2 + (px - cx) * scale;
    const sy = (py) => margin + height / 2 - (py - cy) * scale;

    const step = niceStep(span, 5);
    c.strokeStyle = grid;
    c.fillStyle = text;
    c.lineWidth = 1;
    c.textAlign = "center";
    c.textBaseline = "top";
    const x0 = cx - width / 2 / scale;
    const x1 = cx + width / 2 / scale;
    const y0 = cy - height / 2 / scale;
    const y1 = cy + height / 2 / scale;
    for (let gx = Math.ceil(x0 / step) * step; gx <= x1; gx += step) {
      const px = Math.round(sx(gx)) + 0.5;
      c.beginPath();
      c.moveTo(px, margin);
      c.lineTo(px, margin + height);
      c.stroke();
      c.fillText(`${gx.toFixed(decimals(step))}`, px, margin + height + 4);
    }
    c.textAlign = "right";
    c.textBaseline = "middle";
    for (let gy = Math.ceil(y0 / step) * step; gy <= y1; gy += step) {
      const py = Math.round(sy(gy)) + 0.5;
      c.beginPath();
      c.moveTo(margin, py);
      c.lineTo(margin + width, py);
      c.stroke();
      c.fillText(`${gy.toFixed(decimals(step))}`, margin - 3, py);
    }
    c.textAlign = "left";
    c.textBaseline = "top";
    c.fillText("x, y in metres", margin + 4, 4);

    c.strokeStyle = this.colour("--trace", "#06c");
    c.lineWidth = 2;
    c.beginPath();
    this.path.forEach(([px, py], i) => (i ? c.lineTo(sx(px), sy(py)) : c.moveTo(sx(px), sy(py))));
    if (this.pose) c.lineTo(sx(this.pose[0]), sy(this.pose[1]));
    c.stroke();

    if (this.pose) {
      const [px, py, yaw] = this.pose;
      const size = 9;
      c.save();
      c.translate(sx(px), sy(py));
      c.rotate(-yaw);
      c.fillStyle = this.colour("--robot", "#d33");
      c.beginPath();
      c.moveTo(size, 0);
      c.lineTo(-size * 0.7, size * 0.6);
      c.lineTo(-size * 0.4, 0);
      c.lineTo(-size * 0.7, -size * 0.6);
      c.closePath();
      c.fill();
      c.restore();
    }
  }
}

/** Samples a second over the last second, for the plots' captions. */
export class RateMeter {
  constructor() {
    this.stamps = [];
  }

  tick(now = performance.now()) {
    this.stamps.push(now);
    this.trim(now);
  }

  trim(now) {
    let drop = 0;
    while (drop < this.stamps.length && this.stamps[drop] < now - 1000) drop += 1;
    if (drop) this.stamps.splice(0, drop);
  }

  perSecond(now = performance.now()) {
    this.trim(now);
    return this.stamps.length;
  }
}
