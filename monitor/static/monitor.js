// MineTwin stockpile monitor: polls the stockpile's REST interface through the
// monitor (/api/...) and draws everything on canvases by hand (no libraries,
// no network besides the monitor). Units from the API are SI; the page shows
// t, %, mm and t/h.
"use strict";

const params = new URLSearchParams(window.location.search);
const POLL_MS = Math.max(200, Number(params.get("poll") || 1000));
const FEED_HORIZON_S = 30;
const PARTICLE_LIMIT = 6000;  // larger piles are thinned to about this many dots
const HISTORY_KEEP = 20000;

// Shared with tests and the curious: what the page shows right now.
const state = window.monitorState = {
  updates: 0, reachable: null, colourBy: "grade", lastTime: null,
  history: [], particles: null, fields: null, feed: null,
};

const $ = (id) => document.getElementById(id);

// --------------------------------------------------------------- data access
async function getJSON(path) {
  const controller = new AbortController();
  const timer = setTimeout(() => controller.abort(), 4000);
  try {
    const response = await fetch("/api/" + path, {signal: controller.signal, cache: "no-store"});
    const body = await response.json();
    if (!response.ok) throw new Error(body.error || ("HTTP " + response.status));
    return body;
  } finally {
    clearTimeout(timer);
  }
}

async function fetchAll() {
  const totals = await getJSON("totals");
  if (state.lastTime !== null && totals.time_s < state.lastTime) {
    state.history = [];  // the stockpile restarted: a new run, new clock
  }
  const since = state.history.length ? state.history[state.history.length - 1].time_s : -1e12;
  const [history, particles, fields, feed] = await Promise.all([
    getJSON("history?limit=" + HISTORY_KEEP + "&since=" + since),
    getJSON("particles?limit=" + PARTICLE_LIMIT + "&stride=" +
            Math.max(1, Math.ceil(totals.particle_count / PARTICLE_LIMIT))),
    getJSON("fields?nx=36&ny=18&field=mass,velocity"),
    getJSON("feed?horizon=" + FEED_HORIZON_S),
  ]);
  return {totals, history, particles, fields, feed};
}

async function poll() {
  let data = null;
  try {
    data = await fetchAll();
  } catch (error) {
    showReachable(false, error);
  }
  if (data) {
    state.history = state.history.concat(data.history.rows).slice(-HISTORY_KEEP);
    Object.assign(state, {particles: data.particles, fields: data.fields, feed: data.feed,
                          lastTime: data.totals.time_s});
    state.updates += 1;
    showReachable(true);
    // a drawing fault is a page bug, not an unreachable stockpile: report it
    try {
      showTotals(data.totals);
      showFeed(data.feed);
      drawPile();
      drawCharts();
    } catch (error) {
      console.error("monitor drawing failed:", error);
    }
  }
  setTimeout(poll, POLL_MS);
}

// ------------------------------------------------------------------ numbers
function fmt(value, digits, scale = 1) {
  return (value === null || value === undefined) ? "–" : (value * scale).toFixed(digits);
}

function setNumber(id, raw, digits, scale = 1) {
  const el = $(id);
  el.textContent = fmt(raw, digits, scale);
  el.dataset.value = raw === null || raw === undefined ? "" : String(raw);
}

function showTotals(t) {
  setNumber("sim-time", t.time_s, 1);
  setNumber("held-mass", t.held_mass_kg, 3, 1e-3);
  setNumber("grade", t.grade, 2, 100);
  setNumber("hardness", t.hardness, 3);
  setNumber("d80", t.d80_m, 1, 1e3);
  setNumber("discharge-rate", t.discharge_rate_kg_s, 0, 3.6);
  setNumber("particle-count", t.particle_count, 0);
}

function showFeed(f) {
  $("feed-horizon").textContent = fmt(f.horizon_s, 0);
  setNumber("feed-mass", f.mass_kg, 2, 1e-3);
  setNumber("feed-grade", f.grade, 2, 100);
  setNumber("feed-hardness", f.hardness, 3);
  setNumber("feed-d80", f.d80_m, 1, 1e3);
  drawFeedChart(f);
}

function showReachable(ok, error) {
  state.reachable = ok;
  const status = $("status");
  status.className = "status " + (ok ? "live" : "unreachable");
  status.textContent = ok ? "LIVE" : "STOCKPILE UNREACHABLE";
  status.title = ok ? "" : String(error && error.message || error);
  $("unreachable-banner").hidden = ok;
  $("main").classList.toggle("stale", !ok);
  $("last-time").textContent = fmt(state.lastTime, 1);
}

// ------------------------------------------------------------------ colours
// Viridis-like ramp (9 stops), perceptually ordered; categorical for origin.
const RAMP = [[68, 1, 84], [72, 40, 120], [62, 74, 137], [49, 104, 142], [38, 130, 142],
              [31, 158, 137], [53, 183, 121], [109, 205, 89], [180, 222, 44], [253, 231, 37]];
const CATEGORIES = ["#4e79a7", "#f28e2b", "#e15759", "#76b7b2", "#59a14f", "#edc948",
                    "#b07aa1", "#ff9da7"];

function rampColour(u) {
  if (!Number.isFinite(u)) return "rgb(120,120,120)";
  const x = Math.min(Math.max(u, 0), 1) * (RAMP.length - 1);
  const k = Math.min(Math.floor(x), RAMP.length - 2), w = x - k;
  const c = RAMP[k].map((v, i) => Math.round(v + w * (RAMP[k + 1][i] - v)));
  return `rgb(${c[0]},${c[1]},${c[2]})`;
}

function colouring(values, attribute) {
  const finite = values.filter((v) => v !== null && Number.isFinite(v));
  const distinct = [...new Set(finite)].sort((a, b) => a - b);
  if (attribute === "origin" && distinct.length <= CATEGORIES.length) {
    const index = new Map(distinct.map((v, i) => [v, i]));
    return {categorical: distinct, colour: (v) => CATEGORIES[index.get(v) ?? 0]};
  }
  let lo = finite.length ? Math.min(...finite) : 0, hi = finite.length ? Math.max(...finite) : 1;
  if (attribute === "grade") { lo = 0; hi = 1; }
  if (attribute === "residence_time") lo = 0;
  if (!(hi > lo)) hi = lo + 1;
  return {lo, hi, colour: (v) => rampColour((v - lo) / (hi - lo))};
}

const LABELS = {grade: "grade [-]", hardness: "hardness [-]",
                residence_time: "residence time [s]", origin: "origin"};

function drawLegend(scheme, attribute) {
  const bar = $("colour-bar"), ctx = bar.getContext("2d");
  ctx.clearRect(0, 0, bar.width, bar.height);
  if (scheme.categorical) {
    const w = bar.width / scheme.categorical.length;
    scheme.categorical.forEach((v, i) => {
      ctx.fillStyle = scheme.colour(v);
      ctx.fillRect(i * w, 0, w - 2, bar.height);
    });
    $("legend-min").textContent = "source " + scheme.categorical.join(", ");
    $("legend-max").textContent = "";
  } else {
    for (let x = 0; x < bar.width; x++) {
      ctx.fillStyle = rampColour(x / (bar.width - 1));
      ctx.fillRect(x, 0, 1, bar.height);
    }
    $("legend-min").textContent = scheme.lo.toPrecision(3);
    $("legend-max").textContent = scheme.hi.toPrecision(3);
  }
  $("legend-label").textContent = LABELS[attribute];
}

// --------------------------------------------------------------------- pile
function drawPile() {
  const canvas = $("pile"), ctx = canvas.getContext("2d");
  const p = state.particles, fields = state.fields;
  const attribute = state.colourBy;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  canvas.dataset.colourBy = attribute;
  if (!p || !fields) return;
  // World box: the field grid (it spans the pile) plus every particle drawn.
  let x0 = fields.x_edges[0], x1 = fields.x_edges[fields.x_edges.length - 1];
  let y0 = fields.y_edges[0], y1 = fields.y_edges[fields.y_edges.length - 1];
  for (let i = 0; i < p.x.length; i++) {
    x0 = Math.min(x0, p.x[i]); x1 = Math.max(x1, p.x[i]);
    y0 = Math.min(y0, p.y[i]); y1 = Math.max(y1, p.y[i]);
  }
  const pad = 28;
  const scale = Math.min((canvas.width - 2 * pad) / Math.max(x1 - x0, 1e-6),
                         (canvas.height - 2 * pad) / Math.max(y1 - y0, 1e-6));
  const ox = (canvas.width - scale * (x1 - x0)) / 2, oy = canvas.height - pad;
  const sx = (x) => ox + (x - x0) * scale, sy = (y) => oy - (y - y0) * scale;

  // floor and outlet line
  ctx.strokeStyle = "#56626e"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(pad / 2, sy(y0) + 4); ctx.lineTo(canvas.width - pad / 2, sy(y0) + 4); ctx.stroke();

  const values = p[attribute] || [];
  const scheme = colouring(values, attribute);
  const radius = Math.max(1.5, Math.min(6, 0.45 * Math.sqrt((scale * scale * (x1 - x0) * (y1 - y0)) / Math.max(p.x.length, 1))));
  for (let i = 0; i < p.x.length; i++) {
    ctx.fillStyle = scheme.colour(values[i]);
    ctx.beginPath();
    ctx.arc(sx(p.x[i]), sy(p.y[i]), radius, 0, 2 * Math.PI);
    ctx.fill();
  }
  canvas.dataset.drawn = String(p.x.length);
  drawLegend(scheme, attribute);
  $("particle-note").textContent = p.total > p.x.length
    ? `showing ${p.x.length} of ${p.total} particles` : `${p.total} particles`;

  if ($("show-velocity").checked) drawVelocity(ctx, fields, sx, sy, scale);
}

function drawVelocity(ctx, fields, sx, sy, scale) {
  const nx = fields.nx, ny = fields.ny, vx = fields.vx, vy = fields.vy;
  if (!vx || !vy) return;
  const speeds = [];
  for (let j = 0; j < ny; j++) for (let i = 0; i < nx; i++) {
    const u = vx[j][i], v = vy[j][i];
    if (u !== null && v !== null) speeds.push(Math.hypot(u, v));
  }
  speeds.sort((a, b) => a - b);
  // Scale by the 90th percentile so that a few fast cells near the outlet do
  // not shrink every other arrow to nothing; longer arrows are capped.
  const vref = speeds.length ? speeds[Math.floor(0.9 * (speeds.length - 1))] : 0;
  const vmax = speeds.length ? speeds[speeds.length - 1] : 0;
  if (!(vref > 0)) return;
  const cell = Math.min(fields.x_edges[1] - fields.x_edges[0], fields.y_edges[1] - fields.y_edges[0]);
  const k = 0.8 * cell * scale / vref;
  const cap = 1.3 * cell * scale;
  ctx.strokeStyle = "rgba(255,255,255,0.9)"; ctx.fillStyle = ctx.strokeStyle; ctx.lineWidth = 1.3;
  for (let j = 0; j < ny; j++) for (let i = 0; i < nx; i++) {
    const u = vx[j][i], v = vy[j][i];
    if (u === null || v === null || Math.hypot(u, v) < 0.02 * vref) continue;
    const cx = sx((fields.x_edges[i] + fields.x_edges[i + 1]) / 2);
    const cy = sy((fields.y_edges[j] + fields.y_edges[j + 1]) / 2);
    const shrink = Math.min(1, cap / (Math.hypot(u, v) * k));
    const dx = u * k * shrink, dy = -v * k * shrink, len = Math.hypot(dx, dy);
    const hx = dx / len, hy = dy / len, head = Math.min(5, 0.4 * len);
    ctx.beginPath(); ctx.moveTo(cx - dx / 2, cy - dy / 2); ctx.lineTo(cx + dx / 2, cy + dy / 2); ctx.stroke();
    ctx.beginPath();
    ctx.moveTo(cx + dx / 2, cy + dy / 2);
    ctx.lineTo(cx + dx / 2 - head * (hx - 0.5 * hy), cy + dy / 2 - head * (hy + 0.5 * hx));
    ctx.lineTo(cx + dx / 2 - head * (hx + 0.5 * hy), cy + dy / 2 - head * (hy - 0.5 * hx));
    ctx.fill();
  }
  ctx.fillStyle = "#c9d1d9"; ctx.font = "12px sans-serif";
  ctx.fillText(`arrows: velocity (0.8 cell = ${(vref * 1000).toPrecision(3)} mm/s; ` +
               `fastest ${(vmax * 1000).toPrecision(3)} mm/s, capped)`, 10, 16);
}

// ------------------------------------------------------------------- charts
function lineChart(canvas, times, values, colour, digits) {
  const ctx = canvas.getContext("2d"), w = canvas.width, h = canvas.height;
  ctx.clearRect(0, 0, w, h);
  const left = 48, right = 8, top = 8, bottom = 20;
  const pts = [];
  for (let i = 0; i < times.length; i++) if (values[i] !== null && Number.isFinite(values[i])) pts.push([times[i], values[i]]);
  ctx.strokeStyle = "#2a3540"; ctx.strokeRect(left, top, w - left - right, h - top - bottom);
  if (pts.length === 0) return;
  let t0 = pts[0][0], t1 = pts[pts.length - 1][0];
  let lo = Math.min(...pts.map((q) => q[1])), hi = Math.max(...pts.map((q) => q[1]));
  if (!(t1 > t0)) t1 = t0 + 1;
  // a flat series (up to rounding noise) gets a band of +-5 % around it
  if (!(hi - lo > 1e-9 * Math.max(Math.abs(hi), 1))) {
    const mid = (hi + lo) / 2, m = Math.abs(mid) * 0.05 || 1; lo = mid - m; hi = mid + m;
  }
  const X = (t) => left + (t - t0) / (t1 - t0) * (w - left - right);
  const Y = (v) => h - bottom - (v - lo) / (hi - lo) * (h - top - bottom);
  ctx.fillStyle = "#8b98a5"; ctx.font = "11px sans-serif";
  ctx.fillText(hi.toFixed(digits), 2, top + 9);
  ctx.fillText(lo.toFixed(digits), 2, h - bottom);
  ctx.fillText(t0.toFixed(0) + " s", left, h - 5);
  ctx.fillText(t1.toFixed(0) + " s", w - right - 40, h - 5);
  ctx.strokeStyle = colour; ctx.lineWidth = 2; ctx.beginPath();
  pts.forEach(([t, v], i) => (i ? ctx.lineTo(X(t), Y(v)) : ctx.moveTo(X(t), Y(v))));
  ctx.stroke();
}

function drawCharts() {
  const rows = state.history, t = rows.map((r) => r.time_s);
  lineChart($("chart-mass"), t, rows.map((r) => r.held_mass_kg / 1000), "#f0b429", 1);
  lineChart($("chart-grade"), t, rows.map((r) => r.grade === null ? null : r.grade * 100), "#3fb950", 1);
  lineChart($("chart-hardness"), t, rows.map((r) => r.hardness), "#58a6ff", 2);
}

function drawFeedChart(feed) {
  const canvas = $("feed-chart"), ctx = canvas.getContext("2d"), w = canvas.width, h = canvas.height;
  ctx.clearRect(0, 0, w, h);
  const profile = feed.profile;
  ctx.fillStyle = "#8b98a5"; ctx.font = "11px sans-serif";
  if (!profile || !profile.t_s.length) {
    ctx.fillText("no per-interval prediction from this stockpile", 4, h / 2);
    return;
  }
  const n = profile.t_s.length, bottom = 16, barW = w / n;
  const mmax = Math.max(...profile.mass_kg.map((m) => m || 0), 0);
  if (!(mmax > 0)) {
    ctx.fillText("nothing predicted to leave (feeder stopped or pile empty)", 4, h / 2);
    return;
  }
  for (let i = 0; i < n; i++) {
    const m = profile.mass_kg[i] || 0, g = profile.grade[i];
    const bh = (h - bottom - 4) * m / mmax;
    ctx.fillStyle = g === null ? "#444" : rampColour(g);
    ctx.fillRect(i * barW + 1, h - bottom - bh, barW - 2, bh);
  }
  ctx.fillStyle = "#8b98a5";
  ctx.fillText("now", 2, h - 3);
  ctx.fillText(`+${profile.t_s[n - 1].toFixed(0)} s  (bar: mass, colour: grade)`, w - 190, h - 3);
}

// -------------------------------------------------------------------- start
$("colour-by").addEventListener("change", (event) => {
  state.colourBy = event.target.value;
  drawPile();
});
$("show-velocity").addEventListener("change", drawPile);
poll();
