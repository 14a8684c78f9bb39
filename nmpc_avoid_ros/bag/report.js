// The report page's script (bag/report_page.py embeds it): plain JavaScript drawing on canvases.
"use strict";
const DATA = JSON.parse(document.getElementById("report-data").textContent);
const COLORS = ["#000000", "#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b"];
const PRED = "#d62728";
let runIndex = 0, sample = 0;

function niceTicks(lo, hi, count) {
  const span = hi - lo || 1, step0 = span / count, mag = Math.pow(10, Math.floor(Math.log10(step0)));
  const step = [1, 2, 5, 10].map(f => f * mag).find(s => span / s <= count) || 10 * mag;
  const ticks = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * span; v += step) ticks.push(+v.toPrecision(6));
  return ticks;
}

class Plot {
  constructor(canvas, xr, yr, opts = {}) {
    this.canvas = typeof canvas === "string" ? document.getElementById(canvas) : canvas;
    this.ctx = this.canvas.getContext("2d");
    this.log = !!opts.log;
    this.m = {l: 58, r: 10, t: 22, b: 30};
    this.title = opts.title || "";
    this.xr = xr; this.yr = this.log ? yr.map(v => Math.log10(Math.max(v, 1e-300))) : yr;
    if (this.yr[0] === this.yr[1]) this.yr = [this.yr[0] - 1, this.yr[1] + 1];
  }
  X(v) { const w = this.canvas.width - this.m.l - this.m.r; return this.m.l + (v - this.xr[0]) / (this.xr[1] - this.xr[0]) * w; }
  Y(v) {
    const h = this.canvas.height - this.m.t - this.m.b;
    const y = this.log ? Math.log10(Math.max(v, 1e-300)) : v;
    return this.m.t + (1 - (y - this.yr[0]) / (this.yr[1] - this.yr[0])) * h;
  }
  frame(xlabel, ylabel) {
    const c = this.ctx, W = this.canvas.width, H = this.canvas.height;
    c.fillStyle = "#fff"; c.fillRect(0, 0, W, H);
    c.strokeStyle = "#eee"; c.fillStyle = "#555"; c.font = "11px sans-serif"; c.lineWidth = 1;
    for (const v of niceTicks(this.xr[0], this.xr[1], 8)) {
      c.beginPath(); c.moveTo(this.X(v), this.m.t); c.lineTo(this.X(v), H - this.m.b); c.stroke();
      c.fillText(String(v), this.X(v) - 8, H - this.m.b + 13);
    }
    for (const v of niceTicks(this.yr[0], this.yr[1], Math.max(2, Math.min(5, Math.floor((H - this.m.t - this.m.b) / 18))))) {
      const y = this.log ? Math.pow(10, v) : v;
      c.beginPath(); c.moveTo(this.m.l, this.Y(y)); c.lineTo(W - this.m.r, this.Y(y)); c.stroke();
      c.fillText(this.log ? "1e" + v : String(v), 4, this.Y(y) + 4);
    }
    c.strokeStyle = "#999"; c.strokeRect(this.m.l, this.m.t, W - this.m.l - this.m.r, H - this.m.t - this.m.b);
    c.fillStyle = "#222"; c.font = "12px sans-serif";
    c.fillText(this.title, this.m.l, 14);
    c.fillText(xlabel, W - this.m.r - 60, H - 4);
    if (ylabel) c.fillText(ylabel, W - this.m.r - 160, 14);
  }
  clip(draw) {
    const c = this.ctx; c.save(); c.beginPath();
    c.rect(this.m.l, this.m.t, this.canvas.width - this.m.l - this.m.r, this.canvas.height - this.m.t - this.m.b);
    c.clip(); draw(c); c.restore();
  }
  line(xs, ys, color, width = 1.5, dash = [], step = false) {
    this.clip(c => {
      c.strokeStyle = color; c.lineWidth = width; c.setLineDash(dash); c.beginPath();
      let started = false, prev = null;
      for (let i = 0; i < xs.length; i++) {
        if (ys[i] === null || ys[i] === undefined || (this.log && ys[i] <= 0)) { started = false; continue; }
        const px = this.X(xs[i]), py = this.Y(ys[i]);
        if (!started) { c.moveTo(px, py); started = true; }
        else { if (step) c.lineTo(px, prev); c.lineTo(px, py); }
        prev = py;
      }
      c.stroke(); c.setLineDash([]);
    });
  }
  dots(xs, ys, color, r = 2.5, shape = "circle") {
    this.clip(c => {
      c.fillStyle = color; c.strokeStyle = color; c.lineWidth = 2;
      for (let i = 0; i < xs.length; i++) {
        if (ys[i] === null || ys[i] === undefined) continue;
        const px = this.X(xs[i]), py = this.Y(ys[i]);
        c.beginPath();
        if (shape === "x") { c.moveTo(px - r, py - r); c.lineTo(px + r, py + r); c.moveTo(px - r, py + r); c.lineTo(px + r, py - r); c.stroke(); }
        else if (shape === "square") { c.fillRect(px - r, py - r, 2 * r, 2 * r); }
        else { c.arc(px, py, r, 0, 2 * Math.PI); c.fill(); }
      }
    });
  }
  polygon(points, fill, stroke, dash = []) {
    this.clip(c => {
      c.beginPath();
      points.forEach((p, i) => i ? c.lineTo(this.X(p[0]), this.Y(p[1])) : c.moveTo(this.X(p[0]), this.Y(p[1])));
      c.closePath();
      if (fill) { c.fillStyle = fill; c.fill(); }
      if (stroke) { c.strokeStyle = stroke; c.setLineDash(dash); c.lineWidth = 1.2; c.stroke(); c.setLineDash([]); }
    });
  }
  cursor(x) {
    this.clip(c => { c.strokeStyle = "#d62728"; c.lineWidth = 1; c.beginPath();
      c.moveTo(this.X(x), this.m.t); c.lineTo(this.X(x), this.canvas.height - this.m.b); c.stroke(); });
  }
}

function range(arrays, log) {
  let lo = Infinity, hi = -Infinity;
  for (const a of arrays) for (const v of a) if (v !== null && v !== undefined && (!log || v > 0)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  if (!isFinite(lo)) return log ? [1e-6, 1] : [0, 1];
  const pad = log ? 0 : 0.05 * (hi - lo || 1);
  return [lo - pad, hi + pad];
}
const col = (rows, i) => rows.map(r => (r === null ? null : r[i]));

function regionPoints(r, t) {
  const dt = t - r.stamp, vx = r.velocity[0], vy = r.velocity[1];
  if (r.kind === "ellipse") {
    const pts = [], cx = r.center[0] + vx * dt, cy = r.center[1] + vy * dt, c = Math.cos(r.yaw), s = Math.sin(r.yaw);
    for (let i = 0; i < 48; i++) {
      const a = 2 * Math.PI * i / 48, ex = r.semi_axes[0] * Math.cos(a), ey = r.semi_axes[1] * Math.sin(a);
      pts.push([cx + c * ex - s * ey, cy + s * ex + c * ey]);
    }
    return pts;
  }
  return r.vertices.map(v => [v[0] + vx * dt, v[1] + vy * dt]);
}

function drawPlane(run, k) {
  const [xr, yr] = run.box, p = new Plot("plane", xr, yr, {title: "plane portrait at sample " + k});
  const names = run.state_names, [i, j] = run.plane;
  p.frame(names[i], names[j]);
  const g = run.keep_in;
  if (g) {
    const cw = (g.x[1] - g.x[0]) / (g.nx - 1), ch = (g.y[1] - g.y[0]) / (g.ny - 1);
    p.clip(c => { c.fillStyle = "rgba(244,182,182,0.8)";
      for (let r = 0; r < g.ny; r++) for (let q = 0; q < g.nx; q++) if (g.mask[r * g.nx + q] === "1") {
        const x0 = g.x[0] + (q - 0.5) * cw, y0 = g.y[0] + (r + 0.5) * ch;
        c.fillRect(p.X(x0), p.Y(y0), p.X(x0 + cw) - p.X(x0) + 0.5, p.Y(y0 - ch) - p.Y(y0) + 0.5);
      } });
  }
  const t = run.times[k], drawn = {regions: [], predicted_regions: []};
  for (const idx of run.active[k] || []) {
    const r = run.regions[idx];
    // output-frame regions are drawn in the same axes: the plane's states are the outputs there
    // (the robot's position); elsewhere they are a guide only
    const now = regionPoints(r, t);
    p.polygon(now, "rgba(214,39,40,0.35)", "#d62728");
    drawn.regions.push(now);
    if (r.velocity[0] || r.velocity[1]) for (let h = 1; h <= run.horizon; h++) {
      const later = regionPoints(r, t + h * run.sample_time);
      p.polygon(later, null, "rgba(214,39,40,0.6)", [4, 3]);
      drawn.predicted_regions.push(later);
    }
  }
  DATA.runs.forEach((other, n) => p.line(col(other.x, i), col(other.x, j), n === runIndex ? COLORS[n % 6] : "#ccc", n === runIndex ? 1.2 : 1));
  const pred = run.prediction[k];
  if (pred) { p.line(col(pred, 0), col(pred, 1), PRED, 2.5); p.dots(col(pred, 0), col(pred, 1), PRED, 3); }
  p.dots([run.x[k][i]], [run.x[k][j]], "#111", 6, "square");
  if (run.x_a && run.x_a[k]) p.dots([run.x_a[k][0]], [run.x_a[k][1]], "#2ca02c", 7, "x");
  const target = run.target[k];
  if (names.length === 2 && target && target[0] !== null) p.dots([target[0]], [0], "#000", 8, "x");
  window.report = {run: runIndex, k: k, prediction: pred, state: [run.x[k][i], run.x[k][j]], ...drawn};
}

function drawSeries(run, k) {
  const t = run.t, tt = run.x.length > t.length ? t.concat([t[t.length - 1] + run.sample_time]) : t;
  const tr = [0, tt[tt.length - 1] || 1];
  const rows = [...run.state_names.map((n, i) => [n, col(run.x, i), tt]), ...run.input_names.map((n, i) => [n, col(run.u, i), t])];
  const c = document.getElementById("series"), h = Math.floor(c.height / rows.length);
  const ctx = c.getContext("2d"); ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, c.width, c.height);
  rows.forEach(([name, ys, xs], r) => {
    const sub = document.createElement("canvas"); sub.width = c.width; sub.height = h;
    const p = new Plot(sub, tr, range([ys, r === 0 ? col(run.y_a, 0) : []]), {title: name});
    p.frame("t [s]", "");
    p.line(xs, ys, COLORS[runIndex % 6], 1.5, [], r >= run.state_names.length);
    if (r === 0) { p.line(t, col(run.y_a, 0), "#2ca02c", 1.2, [5, 3]); p.line(t, col(run.target, 0), "#888", 1, [2, 2]); }
    p.cursor(t[k]); ctx.drawImage(sub, 0, r * h);
  });
}

function drawSimple(id, title, series, k, log) {
  const run = DATA.runs[runIndex], ys = series.map(s => s[1]);
  const p = new Plot(id, [0, Math.max(run.t.length - 1, 1)], range(ys, log), {title: title, log: log});
  p.frame("sample k", "");
  const ks = run.t.map((_, n) => n);
  series.forEach(([name, y, color, dash, dots]) => dots ? p.dots(ks, y, color, 4, "x") : p.line(ks, y, color, 1.5, dash || []));
  p.cursor(k);
  p.ctx.font = "11px sans-serif";
  series.forEach(([name, , color], n) => { p.ctx.fillStyle = color; p.ctx.fillText(name, p.canvas.width - 150, 36 + 13 * n); });
}

function info(run, k) {
  const f = v => (v === null || v === undefined ? "-" : typeof v === "number" ? v.toPrecision(6) : JSON.stringify(v));
  const c = run.certificate, lines = [
    `run        ${run.label}`, `sample k   ${k} of ${run.t.length - 1}   t = ${f(run.t[k])} s`,
    `status     ${run.status[k]}`, `state      ${f(run.x[k])}`, `command    ${f(run.u[k])}`,
    `y_a        ${f(run.y_a[k])}`, `target     ${f(run.target[k])}`, `solve      ${f(run.solve_ms[k])} ms`,
    `V_o V_a l  ${f(run.costs.offset[k])} ${f(run.costs.avoidance[k])} ${f(run.costs.tracking[k])}`];
  if (c.value_function) lines.push(`V_N        ${f(c.value_function[k])}`, `decrease   ${f(c.decrease[k])}`,
    `bound      ${f(c.decrease_bound[k])}`, `certificate ${run.violated[k] ? "VIOLATED" : "ok"}`);
  lines.push(`regions    ${(run.active[k] || []).length} in force`, `plan       ${run.prediction[k] ? run.prediction[k].length + " points" : "none published"}`);
  document.getElementById("info").textContent = lines.join("\n");
}

function draw() {
  const run = DATA.runs[runIndex], k = Math.min(sample, run.t.length - 1);
  drawPlane(run, k); drawSeries(run, k);
  drawSimple("solve", "solve time [ms]", [["solve ms", run.solve_ms, "#1f77b4"]], k, false);
  drawSimple("costs", "cost terms (log)", [["V_o", run.costs.offset, "#1f77b4"], ["V_a", run.costs.avoidance, "#d62728"],
    ["tracking", run.costs.tracking, "#2ca02c"]], k, true);
  const c = run.certificate;
  if (c.value_function) drawSimple("certificate", "certificate: V_N (log), violations x", [["V_N", c.value_function, "#000"],
    ["violation", c.value_function.map((v, n) => (run.violated[n] ? v : null)), "#d62728", [], true]], k, true);
  info(run, k);
  document.getElementById("klabel").textContent = `k = ${k}`;
}

function init() {
  const select = document.getElementById("run"), scrub = document.getElementById("scrub");
  DATA.runs.forEach((r, n) => { const o = document.createElement("option"); o.value = n; o.textContent = r.label; select.appendChild(o); });
  select.addEventListener("change", () => { runIndex = +select.value; scrub.max = DATA.runs[runIndex].t.length - 1; sample = Math.min(sample, +scrub.max); scrub.value = sample; draw(); });
  scrub.max = DATA.runs[0].t.length - 1; scrub.value = 0;
  scrub.addEventListener("input", () => { sample = +scrub.value; draw(); });
  const body = document.getElementById("metrics");
  for (const r of DATA.runs) {
    const m = r.metrics, tr = document.createElement("tr");
    const cells = [r.label, m.settling_step, m.final_error, m.max_penetration, m.solve_ms && m.solve_ms.median,
      m.solve_ms && m.solve_ms.max, m.fallbacks, m.certificate_violations, m.finished];
    cells.forEach(v => { const td = document.createElement("td"); td.textContent = typeof v === "number" ? +v.toPrecision(4) : String(v); tr.appendChild(td); });
    body.appendChild(tr);
  }
  draw();
  window.reportReady = true;
}
init();
