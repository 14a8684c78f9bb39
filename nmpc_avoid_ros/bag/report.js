// The report page's script (bag/report_page.py embeds it after the vendored uPlot): the glue from the runs'
// data to uPlot charts, the sample slider and the per-sample view. uPlot draws the axes, grids, lines, markers
// and legends; what it has no series for (the keep-in mask, the regions, the sample's cursor line) is drawn in
// its draw hooks, in its coordinates (valToPos).
"use strict";
const DATA = JSON.parse(document.getElementById("report-data").textContent);
const COLORS = ["#000000", "#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b"];
const PRED = "#d62728";
const WIDTH = 660;
let runIndex = 0, sample = 0, charts = [];
// what the plane's hook draws at the current sample (set by showSample; window.report for the browser test)
let view = {regions: [], predicted_regions: []};

const col = (rows, i) => rows.map(r => (r === null ? null : r[i]));
// a log axis shows v > 0 only: the others are gaps
const positive = ys => ys.map(v => (v !== null && v > 0 ? v : null));
const px = v => v * uPlot.pxRatio;  // CSS px -> canvas px (the hooks draw on uPlot's canvas)

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

// a circle, square or cross at each point of a series, as a points path builder: uPlot's own draws
// circles only, and in its xy mode (2) none (it passes no index range there)
function marker(shape) {
  return (u, si, i0, i1) => {
    const s = u.series[si], [xs, ys] = u.mode === 2 ? u.data[si] : [u.data[0], u.data[si]];
    const yKey = u.mode === 2 ? s.facets[1].scale : s.scale, r = px(s.points.size / 2), path = new Path2D();
    const [first, last] = u.mode === 2 ? [0, xs.length - 1] : [i0, i1];
    for (let n = first; n <= last; n++) {
      if (xs[n] === null || ys[n] === null) continue;
      const x = u.valToPos(xs[n], "x", true), y = u.valToPos(ys[n], yKey, true);
      if (shape === "square") path.rect(x - r, y - r, 2 * r, 2 * r);
      else if (shape === "circle") { path.moveTo(x + r, y); path.arc(x, y, r, 0, 2 * Math.PI); }
      else {
        path.moveTo(x - r, y - r); path.lineTo(x + r, y + r); path.moveTo(x - r, y + r); path.lineTo(x + r, y - r);
      }
    }
    const clip = new Path2D(), b = u.bbox;
    clip.rect(b.left, b.top, b.width, b.height);
    // flags: uPlot's BAND_CLIP_FILL | BAND_CLIP_STROKE, as its own points builder returns
    return {stroke: path, fill: shape === "x" ? null : path, clip: clip, flags: 3};
  };
}

// a series' points option: markers of `size` CSS px in `color`
const markers = (shape, size, color) => ({show: true, size: size, width: shape === "x" ? 2 : 0, fill: color,
  stroke: color, paths: marker(shape)});

function clipped(u, draw) {
  const c = u.ctx, b = u.bbox;
  c.save(); c.beginPath(); c.rect(b.left, b.top, b.width, b.height); c.clip(); draw(c); c.restore();
}

// the red line at the sample's abscissa (t or k) on a time chart, after uPlot drew it
function cursorLine(at) {
  return u => clipped(u, c => {
    const x = u.valToPos(at(), "x", true);
    c.strokeStyle = PRED; c.lineWidth = px(1); c.setLineDash([]); c.beginPath();  // uPlot leaves the last series' dash
    c.moveTo(x, u.bbox.top); c.lineTo(x, u.bbox.top + u.bbox.height); c.stroke();
  });
}

function polygon(u, c, points, fill, stroke, dash) {
  c.beginPath();
  points.forEach(([x, y], n) => c[n ? "lineTo" : "moveTo"](u.valToPos(x, "x", true), u.valToPos(y, "y", true)));
  c.closePath();
  if (fill) { c.fillStyle = fill; c.fill(); }
  if (stroke) {
    c.strokeStyle = stroke; c.lineWidth = px(1.2); c.setLineDash(dash.map(px)); c.stroke(); c.setLineDash([]);
  }
}

// under the series: the keep-in grid's violated cells, then the regions in force now and, dashed, where
// the plan predicted the moving ones over the horizon
function planeLayers(u) {
  const g = DATA.runs[runIndex].keep_in;
  clipped(u, c => {
    if (g) {
      const cw = (g.x[1] - g.x[0]) / (g.nx - 1), ch = (g.y[1] - g.y[0]) / (g.ny - 1);
      c.fillStyle = "rgba(244,182,182,0.8)";
      for (let r = 0; r < g.ny; r++) for (let q = 0; q < g.nx; q++) if (g.mask[r * g.nx + q] === "1") {
        const x0 = u.valToPos(g.x[0] + (q - 0.5) * cw, "x", true), y0 = u.valToPos(g.y[0] + (r + 0.5) * ch, "y", true);
        const x1 = u.valToPos(g.x[0] + (q + 0.5) * cw, "x", true), y1 = u.valToPos(g.y[0] + (r - 0.5) * ch, "y", true);
        c.fillRect(x0, y0, x1 - x0 + 0.5, y1 - y0 + 0.5);
      }
    }
    // output-frame regions are drawn in the same axes: the plane's states are the outputs there
    // (the robot's position); elsewhere they are a guide only
    view.regions.forEach(points => polygon(u, c, points, "rgba(214,39,40,0.35)", PRED, []));
    view.predicted_regions.forEach(points => polygon(u, c, points, null, "rgba(214,39,40,0.6)", [4, 3]));
  });
}

const point = (x, y) => (x === null || x === undefined || y === null || y === undefined ? [[], []] : [[x], [y]]);

// the plane's per-sample series: the plan, the measured state, x_a and the target's steady state
function planeSample(run, k) {
  const [i, j] = run.plane, pred = run.prediction[k], target = run.target[k];
  return [pred ? [col(pred, 0), col(pred, 1)] : [[], []], point(run.x[k][i], run.x[k][j]),
    run.x_a && run.x_a[k] ? point(run.x_a[k][0], run.x_a[k][1]) : [[], []],
    // the target's steady state is (target, 0) in the two-state models only
    run.state_names.length === 2 && target ? point(target[0], 0) : [[], []]];
}

function planeChart(run) {
  const [i, j] = run.plane, names = run.state_names;
  const trajectories = DATA.runs.map((other, n) => ({
    label: other.label, stroke: n === runIndex ? COLORS[n % 6] : "#ccc", width: n === runIndex ? 1.2 : 1,
    points: {show: false}}));
  const opts = {
    mode: 2, width: WIDTH, height: 400, title: "plane portrait",
    scales: {x: {time: false, range: run.box[0]}, y: {range: run.box[1]}},
    axes: [{label: names[i]}, {label: names[j]}],
    legend: {live: false},
    cursor: {drag: {x: false, y: false}},
    series: [{}, ...trajectories,
      {label: "plan", stroke: PRED, width: 2.5, points: markers("circle", 6, PRED)},
      {label: "state", stroke: "#111", paths: () => null, points: markers("square", 12, "#111")},
      {label: "x_a", stroke: "#2ca02c", paths: () => null, points: markers("x", 14, "#2ca02c")},
      {label: "target", stroke: "#000", paths: () => null, points: markers("x", 16, "#000")}],
    hooks: {drawAxes: [planeLayers]},
  };
  const fixed = DATA.runs.map(other => [col(other.x, i), col(other.x, j)]);
  const u = new uPlot(opts, [null, ...fixed, ...planeSample(run, 0)], document.getElementById("plane"));
  u.sample = k => { u.setData([null, ...fixed, ...planeSample(run, k)], false); u.redraw(); };  // scales fixed
  return u;
}

// a chart with the sample's cursor line at at(); a legend where it has more than one series (else its axis or
// title names it); opts.sync: the key of charts whose hover cursors move together
function timeChart(target, opts, data, at) {
  const cursor = {drag: {x: false, y: false}, ...(opts.sync ? {sync: {key: opts.sync}} : {})};
  const u = new uPlot({width: WIDTH, ...opts, cursor: cursor, legend: {show: opts.series.length > 2, live: false},
    hooks: {draw: [cursorLine(at)]}}, data, target);
  u.sample = () => u.redraw(false);
  return u;
}

// one chart per state and per input over t [s]: x(k) over K + 1 samples, u(k) held over the sample
function seriesCharts(run) {
  const t = run.t, tt = run.x.length > t.length ? t.concat([t[t.length - 1] + run.sample_time]) : t;
  const holder = document.getElementById("series"), color = COLORS[runIndex % 6];
  const scales = {x: {time: false, range: [0, tt[tt.length - 1] || 1]}};
  const at = () => t[Math.min(sample, t.length - 1)];
  const pad = ys => (ys.length < tt.length ? ys.concat([null]) : ys);
  const states = run.state_names.map((name, i) => {
    const series = [{label: "t [s]"}, {label: name, stroke: color, width: 1.5, points: {show: false}}];
    const data = [tt, col(run.x, i)];
    if (i === 0) {  // the output's artificial reference and target over the first state
      series.push({label: "y_a", stroke: "#2ca02c", width: 1.2, dash: [5, 3], points: {show: false}},
                  {label: "target", stroke: "#888", width: 1, dash: [2, 2], points: {show: false}});
      data.push(pad(col(run.y_a, 0)), pad(col(run.target, 0)));
    }
    return timeChart(holder, {height: 140, scales: scales, series: series, axes: ROW_AXES(name), sync: "series"},
      data, at);
  });
  return states.concat(run.input_names.map((name, i) => timeChart(holder, {height: 140, scales: scales,
    series: [{label: "t [s]"}, {label: name, stroke: color, width: 1.5, points: {show: false},
      paths: uPlot.paths.stepped({align: 1})}], axes: ROW_AXES(name), sync: "series"}, [t, col(run.u, i)], at)));
}

const LOG = {distr: 3, log: 10, range: (u, lo, hi) => (lo === null ? [1e-6, 1] : uPlot.rangeLog(lo, hi, 10, true))};
// at most 5 decade ticks: uPlot's log axis grids every 1..9 x 10^n, a grey wash over the cost's 10 decades
const DECADES = {
  splits: (u, ai, lo, hi) => {
    const a = Math.ceil(Math.log10(lo) - 1e-9), b = Math.floor(Math.log10(hi) + 1e-9), out = [];
    for (let e = a; e <= b; e += Math.max(1, Math.ceil((b - a + 1) / 5))) out.push(Math.pow(10, e));
    return out;
  },
  filter: (u, ticks) => ticks,  // uPlot's log filter would blank all but its own picks
  values: (u, ticks) => ticks.map(v => "1e" + Math.round(Math.log10(v))),
};
const X_AXIS = label => ({label: label, labelSize: 14, size: 34});  // uPlot's default leaves 50 px
// the per-state and per-input rows: y ticks 16 px apart
const ROW_AXES = name => [X_AXIS("t [s]"), {label: name, space: 16}];

// a chart over the sample index k: series [label, values [K], color, as crosses]
function sampleChart(id, title, series, log) {
  const run = DATA.runs[runIndex], ks = run.t.map((_, n) => n);
  return timeChart(document.getElementById(id), {
    height: 170, title: title,
    scales: {x: {time: false, range: [0, Math.max(ks.length - 1, 1)]}, ...(log ? {y: LOG} : {})},
    axes: [X_AXIS("sample k"), log ? DECADES : {}],
    series: [{label: "sample k"}, ...series.map(([label, , color, crosses]) => (crosses
      ? {label: label, stroke: color, paths: () => null, points: markers("x", 8, color)}
      : {label: label, stroke: color, width: 1.5, points: {show: false}}))],
  }, [ks, ...series.map(s => (log ? positive(s[1]) : s[1]))], () => Math.min(sample, ks.length - 1));
}

function buildCharts() {
  charts.forEach(u => u.destroy());
  for (const id of ["plane", "series", "solve", "costs", "certificate"]) document.getElementById(id).textContent = "";
  const run = DATA.runs[runIndex], c = run.certificate;
  charts = [planeChart(run), ...seriesCharts(run),
    sampleChart("solve", "solve time [ms]", [["solve ms", run.solve_ms, "#1f77b4"]], false),
    sampleChart("costs", "cost terms (log)", [["V_o", run.costs.offset, "#1f77b4"],
      ["V_a", run.costs.avoidance, PRED], ["tracking", run.costs.tracking, "#2ca02c"]], true)];
  if (c.value_function) charts.push(sampleChart("certificate", "certificate: V_N (log), violations x",
    [["V_N", c.value_function, "#000"],
      ["violation", c.value_function.map((v, n) => (run.violated[n] ? v : null)), PRED, true]], true));
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

function showSample() {
  const run = DATA.runs[runIndex], k = Math.min(sample, run.t.length - 1), t = run.times[k], [i, j] = run.plane;
  view = {regions: [], predicted_regions: []};
  for (const idx of run.active[k] || []) {
    const r = run.regions[idx];
    view.regions.push(regionPoints(r, t));
    if (r.velocity[0] || r.velocity[1]) for (let h = 1; h <= run.horizon; h++)
      view.predicted_regions.push(regionPoints(r, t + h * run.sample_time));
  }
  charts.forEach(u => u.sample(k));
  charts[0].root.querySelector(".u-title").textContent = "plane portrait at sample " + k;
  info(run, k);
  document.getElementById("klabel").textContent = `k = ${k}`;
  window.report = {run: runIndex, k: k, prediction: run.prediction[k], state: [run.x[k][i], run.x[k][j]], ...view};
}

function init() {
  const select = document.getElementById("run"), scrub = document.getElementById("scrub");
  DATA.runs.forEach((r, n) => { const o = document.createElement("option"); o.value = n; o.textContent = r.label; select.appendChild(o); });
  select.addEventListener("change", () => {
    runIndex = +select.value; scrub.max = DATA.runs[runIndex].t.length - 1; sample = Math.min(sample, +scrub.max);
    scrub.value = sample; buildCharts(); showSample();
  });
  scrub.max = DATA.runs[0].t.length - 1; scrub.value = 0;
  scrub.addEventListener("input", () => { sample = +scrub.value; showSample(); });
  const body = document.getElementById("metrics");
  for (const r of DATA.runs) {
    const m = r.metrics, tr = document.createElement("tr");
    const cells = [r.label, m.settling_step, m.final_error, m.max_penetration, m.solve_ms && m.solve_ms.median,
      m.solve_ms && m.solve_ms.max, m.fallbacks, m.certificate_violations, m.finished];
    cells.forEach(v => { const td = document.createElement("td"); td.textContent = typeof v === "number" ? +v.toPrecision(4) : String(v); tr.appendChild(td); });
    body.appendChild(tr);
  }
  buildCharts(); showSample();
  window.reportReady = true;
}
init();
