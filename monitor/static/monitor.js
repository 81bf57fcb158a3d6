// MineTwin stockpile monitor: polls the stockpile's REST interface through the
// monitor (/api/...), the capacity and alarm limits from /monitor/config, and
// draws the pile and feed on canvases and the trends with uPlot (served by the
// monitor, /static/vendor/). Nothing loads from the network. The API is SI;
// the page shows one unit per quantity: mass t, grade %, hardness [-]
// (relative), D80 mm, rates t/h, time s.
"use strict";

const params = new URLSearchParams(window.location.search);
const POLL_MS = Math.max(200, Number(params.get("poll") || 1000));
const FEED_HORIZON_S = 30;
const PARTICLE_LIMIT = 6000;  // larger piles are thinned to about this many dots
const HISTORY_KEEP = 20000;
const EVENTS_KEEP = 5000;
const EVENTS_SHOWN = 200;
const ALARMS_SHOWN = 50;
const STALE_MS = 5000;        // a value older than this is marked
// The feed prediction is the stockpile's slowest answer (a forecast of the flow;
// 40 ms for a ROM pile of 1,500 t and a 30 s horizon with both cores busy, about
// 15x that for 600 s), and the stockpile answers one request at a time between its
// exchange cycles: it is read after the other values, with its own time-out,
// at most FEED_SHARE of the time (a feed that took 1 s is read again 5 s later;
// a fast one every poll), and a slow or failed one only ages the feed shown.
const FEED_SHARE = 0.2;
const REQUEST_TIMEOUT_MS = 4000, FEED_TIMEOUT_MS = 16000;  // the monitor's proxy: 3 s, feed 15 s

// Shared with tests and the curious: what the page shows right now.
const state = window.monitorState = {
  updates: 0, reachable: null, colourBy: "grade", lastTime: null, config: null,
  history: [], particles: null, fields: null, feed: null, totals: null,
  events: [], lastSeq: 0, alarms: [], alarmsShown: null, restarts: [], zoom: null,
  received: {}, charts: {}, scheme: null, originNames: new Map(), originColours: new Map(),
  feedCostMs: 0, restarted: false,
};

const $ = (id) => document.getElementById(id);

// --------------------------------------------------------------- data access
async function getJSON(path, timeoutMs = REQUEST_TIMEOUT_MS) {
  const controller = new AbortController();
  const timer = setTimeout(() => controller.abort(), timeoutMs);
  try {
    const response = await fetch(path, {signal: controller.signal, cache: "no-store"});
    const body = await response.json();
    if (!response.ok) throw new Error(body.error || ("HTTP " + response.status));
    return body;
  } finally {
    clearTimeout(timer);
  }
}

const api = (path, timeoutMs) => getJSON("/api/" + path, timeoutMs);

async function fetchAll() {
  const totals = await api("totals");
  if (state.lastTime !== null && totals.time_s < state.lastTime) restarted(state.lastTime, totals.time_s);
  const since = state.history.length ? state.history[state.history.length - 1].time_s : -1e12;
  const [history, particles, fields, events] = await Promise.all([
    api("history?limit=" + HISTORY_KEEP + "&since=" + since),
    api("particles?limit=" + PARTICLE_LIMIT + "&stride=" +
        Math.max(1, Math.ceil(totals.particle_count / PARTICLE_LIMIT))),
    api("fields?nx=36&ny=18&field=mass,velocity"),
    api("events?since=" + state.lastSeq),
  ]);
  const alarms = await getJSON("/monitor/alarms");
  return {totals, history, particles, fields, events, alarms};
}

// The predicted feed, when due (see FEED_EVERY_MS); drawn as it arrives.
async function pollFeed() {
  const last = state.received.feed, wait = state.feedCostMs / FEED_SHARE;
  if (last !== undefined && Date.now() - last < wait && !state.restarted) return;
  state.restarted = false;
  const start = Date.now();
  try {
    state.feed = await api("feed?horizon=" + FEED_HORIZON_S, FEED_TIMEOUT_MS);
    state.received.feed = Date.now();
    showFeed(state.feed);
  } catch (error) {
    console.warn("monitor: no feed prediction this time:", error);
    if (!state.feed) $("feed-caption").textContent = "no feed prediction received yet (" +
      (error.name === "AbortError" ? "the stockpile took longer than " +
       `${FEED_TIMEOUT_MS / 1000} s` : error.message) + "); retrying";
  }
  state.feedCostMs = Date.now() - start;
}

// The stockpile's clock went back: a new run. Say so, and start the trends
// and events afresh (what was shown belongs to the old run).
function restarted(fromS, toS) {
  const at = new Date();
  state.restarts.push({from_s: fromS, to_s: toS, at: at.toISOString()});
  state.history = [];
  state.events = [];
  state.lastSeq = 0;
  state.zoom = null;
  state.originNames = new Map();
  state.originColours = new Map();
  state.restarted = true;  // the old run's feed prediction: read the new one at once
  $("restart-detail").textContent =
    `its clock went back from t = ${fromS.toFixed(1)} s to ${toS.toFixed(1)} s at ${clock(at)}; ` +
    "trends and events start again with the new run; the old run's active alarms are cleared.";
  $("restart-banner").hidden = false;
}

async function poll() {
  let data = null;
  try {
    if (!state.config) showConfig(await getJSON("/monitor/config"));
    data = await fetchAll();
  } catch (error) {
    showReachable(false, error);
  }
  if (data) {
    const now = Date.now();
    if (data.events.last_seq < state.lastSeq) {  // a new run whose clock had not gone back
      state.events = [];
    }
    state.history = state.history.concat(data.history.rows).slice(-HISTORY_KEEP);
    state.events = state.events.concat(data.events.events).slice(-EVENTS_KEEP);
    state.lastSeq = data.events.events.length
      ? data.events.events[data.events.events.length - 1].seq : data.events.last_seq;
    Object.assign(state, {particles: data.particles, fields: data.fields,
                          totals: data.totals, lastTime: data.totals.time_s});
    for (const source of ["totals", "particles", "events"]) state.received[source] = now;
    // names are kept once seen: the events name sources whose particles have all left
    for (const o of data.particles.origin_names || []) state.originNames.set(o.origin, o.name);
    state.updates += 1;
    showReachable(true);
    // a drawing fault is a page bug, not an unreachable stockpile: report it
    try {
      showTotals(data.totals);
      showAlarms(data.alarms);
      drawPile();
      if (state.feed) drawFeedChart(state.feed);  // in the pile's colouring of now
      drawTrends();
      showEvents();
      showAges();
    } catch (error) {
      console.error("monitor drawing failed:", error);
    }
    await pollFeed();
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

const pad2 = (n) => String(n).padStart(2, "0");
function clock(date) {
  return `${pad2(date.getHours())}:${pad2(date.getMinutes())}:${pad2(date.getSeconds())}`;
}

function fillPercent(totals) {
  return 100 * totals.held_mass_kg / (1000 * state.config.stockpile.capacity_t);
}

function showConfig(config) {
  state.config = config;
  const a = config.alarms;
  $("capacity").textContent = String(config.stockpile.capacity_t);
  // a grade limit of 0 or 100 % can never be passed: that alarm is off (the default)
  const gradeOff = a.grade_low_pct <= 0 && a.grade_high_pct >= 100;
  $("grade-band").textContent = gradeOff ? "grade alarms off"
    : `alarm band ${a.grade_low_pct}–${a.grade_high_pct} %`;
  $("alarm-limits").textContent = `(from the monitor's config: level ${a.level_low_pct}–` +
    `${a.level_high_pct} % of ${config.stockpile.capacity_t} t, dead band ` +
    `${a.level_deadband_pct} %; ` + (gradeOff ? "grade alarms off: set a band for your ore" :
    `grade ${a.grade_low_pct}–${a.grade_high_pct} %, dead band ` +
    `${a.grade_deadband_pct} percentage points`) + ")";
  $("trend-range").value = String(config.trends.window_s);
  if ($("trend-range").value === "") {  // a window not in the list: add it
    const option = new Option(`last ${config.trends.window_s} s`, String(config.trends.window_s));
    $("trend-range").add(option);
    $("trend-range").value = option.value;
  }
}

function showTotals(t) {
  setNumber("sim-time", t.time_s, 1);
  setNumber("held-mass", t.held_mass_kg, 1, 1e-3);  // 0.1 t: one 100 kg particle
  const fill = fillPercent(t);
  setNumber("fill-pct", fill, 1);
  $("fill-level").style.width = Math.min(Math.max(fill, 0), 100) + "%";
  setNumber("grade", t.grade, 2, 100);
  setNumber("hardness", t.hardness, 3);
  setNumber("d80", t.d80_m, 1, 1e3);
  setNumber("discharge-rate", t.discharge_rate_kg_s, 0, 3.6);
  setNumber("discharge-actual", t.discharge_actual_kg_s, 0, 3.6);
  setNumber("discharge-ratio", t.discharge_rate_kg_s > 0
    ? 100 * t.discharge_actual_kg_s / t.discharge_rate_kg_s : null, 0);
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
  showAges();
}

// The wall-clock time each value was received, and its age now.
function showAges() {
  const now = Date.now();
  const last = state.received.totals;
  $("update-clock").textContent = last ? `${clock(new Date(last))} (${((now - last) / 1000).toFixed(1)} s ago)` : "–";
  for (const el of document.querySelectorAll(".kpi-age")) {
    const at = state.received[el.dataset.source];
    if (!at) continue;
    el.textContent = `received ${clock(new Date(at))}, ${((now - at) / 1000).toFixed(1)} s ago`;
    el.classList.toggle("old", now - at > STALE_MS);
  }
}

// ------------------------------------------------------------------- alarms
// The monitor server keeps the alarms (monitor/alarms.py: limits with a dead
// band, checked on every history row; acknowledgements with who and when), so
// they are the same after a reload and in every browser. The page shows them
// and sends the operator's acknowledgements.
const STATE_TEXT = {ACTIVE_UNACK: "ACTIVE, UNACK", ACTIVE_ACK: "ACTIVE, ACK",
                    CLEARED_UNACK: "CLEARED, UNACK", CLEARED: "CLEARED"};

function limitText(a) {
  return `${a.direction === "high" ? ">" : "<"} ${a.limit} ${a.unit}; clears ` +
         `${a.direction === "high" ? "≤" : "≥"} ${a.clears_at} ${a.unit}`;
}

function wallClock(iso) {
  return iso ? clock(new Date(iso)) : "–";
}

function showAlarms(book) {
  state.alarms = book.alarms;
  state.alarmsChecked = book.checked_s;
  const badge = $("alarm-count");
  badge.className = "status " + (book.active ? "alarm" : (book.unacknowledged ? "notice" : "waiting"));
  badge.textContent = (book.active ? `${book.active} ALARM${book.active > 1 ? "S" : ""}` : "NO ALARM") +
    (book.unacknowledged ? ` (${book.unacknowledged} UNACK)` : "");
  Object.assign(badge.dataset, {value: String(book.active), unacknowledged: String(book.unacknowledged)});
  $("ack-all").disabled = book.unacknowledged === 0;
  // redrawn only on a change, so that a button is not replaced under the operator's click
  const key = JSON.stringify(book.alarms);
  if (key === state.alarmsShown) return;
  state.alarmsShown = key;
  const rows = book.alarms.slice(-ALARMS_SHOWN).reverse().map((a) => {
    const tr = document.createElement("tr");
    Object.assign(tr.dataset, {alarm: a.id, seq: String(a.seq), state: a.state});
    const cleared = a.cleared_s === null ? "–"
      : `${a.cleared_s.toFixed(1)}, ${wallClock(a.cleared_at)}${a.cleared_by === "restart" ? " (restart)" : ""}`;
    const acked = a.acked_by === null ? "–" : `${a.acked_by}, ${wallClock(a.acked_at)}`;
    const cells = [STATE_TEXT[a.state], a.name, limitText(a), `${a.value.toFixed(1)} ${a.unit}`,
                   `${a.raised_s.toFixed(1)}, ${wallClock(a.raised_at)}`, cleared, acked];
    for (const text of cells) tr.appendChild(document.createElement("td")).textContent = text;
    // beside the state, so that it is on screen when a narrow screen scrolls the table
    if (a.acked_by === null) {
      const button = tr.firstChild.appendChild(document.createElement("button"));
      button.type = "button";
      button.className = "ack";
      button.textContent = "acknowledge";
      button.addEventListener("click", () => acknowledge(a.seq));
    }
    return tr;
  });
  $("alarm-list").replaceChildren(...rows);
}

// The operator's name goes with each acknowledgement; the browser remembers it.
async function acknowledge(seq) {
  const operator = $("operator").value.trim();
  const note = $("ack-note");
  if (!operator) {
    note.textContent = "type your name in 'operator' to acknowledge";
    $("operator").focus();
    return;
  }
  window.localStorage.setItem("minetwin.operator", operator);
  const response = await fetch("/monitor/alarms/ack", {
    method: "POST", headers: {"Content-Type": "application/json"},
    body: JSON.stringify({seq, operator})});
  const body = await response.json();
  note.textContent = response.ok
    ? `acknowledged ${body.acknowledged.length} by ${operator}` : body.error;
  showAlarms(await getJSON("/monitor/alarms"));
}

// ------------------------------------------------------------------- events
function sourceName(source) {
  if (source === null || source === undefined) return "–";
  return state.originNames.get(source) || `source ${source}`;
}

function showEvents() {
  const lots = {in: [0, 0], out: [0, 0]};
  for (const e of state.events) { lots[e.kind][0] += 1; lots[e.kind][1] += e.mass_kg; }
  $("event-summary").textContent = `lots in: ${lots.in[0]} (${(lots.in[1] / 1000).toFixed(1)} t); ` +
    `out: ${lots.out[0]} events (${(lots.out[1] / 1000).toFixed(1)} t); newest first`;
  const rows = state.events.slice(-EVENTS_SHOWN).reverse().map((e) => {
    const tr = document.createElement("tr");
    Object.assign(tr.dataset, {seq: e.seq, kind: e.kind, trackingId: e.tracking_id ?? "",
                               mass: e.mass_kg});
    const cells = [e.seq, e.time_s.toFixed(1), e.kind === "in" ? "IN" : "OUT",
                   e.tracking_id ?? "–", (e.mass_kg / 1000).toFixed(3), fmt(e.grade, 2, 100),
                   sourceName(e.source), e.particle_count];
    for (const text of cells) tr.appendChild(document.createElement("td")).textContent = String(text);
    return tr;
  });
  $("event-list").replaceChildren(...rows);
}

// ------------------------------------------------------------------ colours
// Viridis-like ramp (10 stops), perceptually ordered; categorical for origin.
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

// Shown value and unit of each colouring (grade in %, like everywhere else).
const SHOWN = {grade: {scale: 100, label: "grade [%]", digits: 2},
               hardness: {scale: 1, label: "hardness (relative) [-]", digits: 3},
               residence_time: {scale: 1, label: "residence time [s]", digits: 0},
               origin: {scale: 1, label: "origin", digits: 0}};
// origin is the index of the source a particle was mined at (named by the
// stockpile's origin_names); more sources than colours go on a ramp of the index.
const ORIGIN_RAMP_LABEL = "origin: source index";

// A source's colour is fixed by the order in which the page first saw it, so that
// it keeps its colour while other sources come and go, in the pile and the feed bars.
function originColour(origin) {
  if (!state.originColours.has(origin)) state.originColours.set(origin, state.originColours.size);
  const k = state.originColours.get(origin);
  return k < CATEGORIES.length ? CATEGORIES[k] : rampColour((k % 10) / 9);
}

function colouring(values, attribute) {
  const finite = values.filter((v) => v !== null && Number.isFinite(v));
  const distinct = [...new Set(finite)].sort((a, b) => a - b);
  if (attribute === "origin" && distinct.length <= CATEGORIES.length) {
    distinct.forEach(originColour);
    return {attribute, categorical: distinct, colour: originColour};
  }
  let lo = finite.length ? Math.min(...finite) : 0, hi = finite.length ? Math.max(...finite) : 1;
  if (attribute === "residence_time") lo = 0;
  if (!(hi > lo)) hi = lo + 1;
  return {attribute, lo, hi, colour: (v) => rampColour((v - lo) / (hi - lo))};
}

function drawLegend(scheme, attribute) {
  const bar = $("colour-bar"), ctx = bar.getContext("2d");
  ctx.clearRect(0, 0, bar.width, bar.height);
  const shown = SHOWN[attribute];
  if (scheme.categorical) {
    bar.hidden = true;
    $("legend-min").replaceChildren(...scheme.categorical.map((v) => {
      const item = document.createElement("span");
      const swatch = item.appendChild(document.createElement("span"));
      swatch.className = "swatch";
      swatch.style.background = scheme.colour(v);
      item.appendChild(document.createTextNode(sourceName(v)));
      return item;
    }));
    $("legend-max").textContent = "";
  } else {
    bar.hidden = false;
    for (let x = 0; x < bar.width; x++) {
      ctx.fillStyle = rampColour(x / (bar.width - 1));
      ctx.fillRect(x, 0, 1, bar.height);
    }
    $("legend-min").textContent = (scheme.lo * shown.scale).toFixed(shown.digits);
    $("legend-max").textContent = (scheme.hi * shown.scale).toFixed(shown.digits);
  }
  $("legend-label").textContent = attribute === "origin" && !scheme.categorical
    ? ORIGIN_RAMP_LABEL : shown.label;
}

// 1, 2 or 5 times a power of ten, the largest not above x.
function niceBelow(x) {
  const p = Math.pow(10, Math.floor(Math.log10(x)));
  return [5, 2, 1].map((m) => m * p).find((v) => v <= x) || p;
}

// --------------------------------------------------------------------- pile
function drawPile() {
  const canvas = $("pile"), ctx = canvas.getContext("2d");
  const p = state.particles, fields = state.fields;
  const attribute = state.colourBy;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  canvas.dataset.colourBy = attribute;
  if (!p || !fields) return;
  const schematic = (p.layout || fields.layout) === "schematic";
  canvas.dataset.layout = schematic ? "schematic" : "particles";
  $("pile-title").textContent = schematic
    ? "Pile cross-section — SCHEMATIC (not a flow simulation)"
    : "Pile cross-section — particle positions";
  $("pile-note").textContent = schematic
    ? "This storage model has no geometry: each dot is a pseudo-particle placed by its rank " +
      "in the order of leaving (nearer the outlet leaves sooner), in a half disc of the " +
      "display radius. Arrows: the speed at which that order drains."
    : "Each dot is a pseudo-particle at its position in the storage model (x horizontal, y up).";
  // World box: the field grid (it spans the pile) plus every particle drawn.
  let x0 = fields.x_edges[0], x1 = fields.x_edges[fields.x_edges.length - 1];
  let y0 = fields.y_edges[0], y1 = fields.y_edges[fields.y_edges.length - 1];
  for (let i = 0; i < p.x.length; i++) {
    x0 = Math.min(x0, p.x[i]); x1 = Math.max(x1, p.x[i]);
    y0 = Math.min(y0, p.y[i]); y1 = Math.max(y1, p.y[i]);
  }
  const pad = 34;
  const scale = Math.min((canvas.width - 2 * pad) / Math.max(x1 - x0, 1e-6),
                         (canvas.height - 2 * pad) / Math.max(y1 - y0, 1e-6));
  const ox = (canvas.width - scale * (x1 - x0)) / 2, oy = canvas.height - pad;
  const sx = (x) => ox + (x - x0) * scale, sy = (y) => oy - (y - y0) * scale;

  // floor and outlet line
  ctx.strokeStyle = "#56626e"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(pad / 2, sy(y0) + 4); ctx.lineTo(canvas.width - pad / 2, sy(y0) + 4); ctx.stroke();
  if (schematic) {
    ctx.fillStyle = "#c9d1d9"; ctx.font = "12px sans-serif";
    ctx.fillText("▼ outlet", sx(0) - 24, sy(y0) + 18);
  }

  const values = p[attribute] || [];
  const scheme = colouring(values, attribute);
  state.scheme = scheme;
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
  drawMetreScale(ctx, canvas, scale);
  if ($("show-velocity").checked) drawVelocity(ctx, fields, sx, sy, scale);
}

// A scale bar of a round number of metres, about a fifth of the picture wide.
function drawMetreScale(ctx, canvas, scale) {
  const metres = niceBelow(0.2 * canvas.width / scale);
  const length = metres * scale, x = canvas.width - 20 - length, y = canvas.height - 10;
  ctx.strokeStyle = "#e6edf3"; ctx.fillStyle = "#e6edf3"; ctx.lineWidth = 2;
  ctx.beginPath();
  ctx.moveTo(x, y - 5); ctx.lineTo(x, y); ctx.lineTo(x + length, y); ctx.lineTo(x + length, y - 5);
  ctx.stroke();
  ctx.font = "12px sans-serif";
  ctx.fillText(`${metres} m`, x + length / 2 - 12, y - 6);
  canvas.dataset.scaleMetres = String(metres);
}

function speedText(v) {
  return v >= 1 ? `${v.toPrecision(3)} m/s` : `${(v * 1000).toPrecision(3)} mm/s`;
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
  const k = 0.8 * cell * scale / vref;  // pixels per (m/s)
  const cap = 1.3 * cell * scale;
  ctx.strokeStyle = "rgba(255,255,255,0.9)"; ctx.fillStyle = ctx.strokeStyle; ctx.lineWidth = 1.3;
  const arrow = (cx, cy, dx, dy) => {
    const len = Math.hypot(dx, dy), hx = dx / len, hy = dy / len, head = Math.min(5, 0.4 * len);
    ctx.beginPath(); ctx.moveTo(cx - dx / 2, cy - dy / 2); ctx.lineTo(cx + dx / 2, cy + dy / 2); ctx.stroke();
    ctx.beginPath();
    ctx.moveTo(cx + dx / 2, cy + dy / 2);
    ctx.lineTo(cx + dx / 2 - head * (hx - 0.5 * hy), cy + dy / 2 - head * (hy + 0.5 * hx));
    ctx.lineTo(cx + dx / 2 - head * (hx + 0.5 * hy), cy + dy / 2 - head * (hy - 0.5 * hx));
    ctx.fill();
  };
  for (let j = 0; j < ny; j++) for (let i = 0; i < nx; i++) {
    const u = vx[j][i], v = vy[j][i];
    if (u === null || v === null || Math.hypot(u, v) < 0.02 * vref) continue;
    const cx = sx((fields.x_edges[i] + fields.x_edges[i + 1]) / 2);
    const cy = sy((fields.y_edges[j] + fields.y_edges[j + 1]) / 2);
    const shrink = Math.min(1, cap / (Math.hypot(u, v) * k));
    arrow(cx, cy, u * k * shrink, -v * k * shrink);
  }
  // key: a sample arrow of a round speed
  const vkey = niceBelow(vref);
  arrow(10 + vkey * k / 2, 14, vkey * k, 0);
  ctx.fillStyle = "#c9d1d9"; ctx.font = "12px sans-serif";
  ctx.fillText(`= ${speedText(vkey)}   velocity (fastest ${speedText(vmax)}; ` +
               "arrows longer than 1.3 cells are drawn at 1.3 cells)", 18 + vkey * k, 18);
  $("pile").dataset.velocityKey = String(vkey);
}

// ------------------------------------------------------------------- trends
const MUTED = "#8b98a5", GRID = "#2a3540", LIMIT = "#ff7b72";
const rowsOf = (key, scale = 1) => (r) => (r[key] === null ? null : r[key] * scale);

// One trend per tile. zero: the y axis starts at 0; minSpan: a flat signal
// is drawn in a band at least this fraction of its value wide, not stretched.
const TRENDS = [
  {id: "mass", title: "Held mass", unit: "t", digits: 2, zero: true,
   series: [{label: "held mass", value: rowsOf("held_mass_kg", 1e-3), colour: "#f0b429"}],
   limits: (c) => [["high level", c.alarms.level_high_pct / 100 * c.stockpile.capacity_t],
                   ["low level", c.alarms.level_low_pct / 100 * c.stockpile.capacity_t]]},
  {id: "grade", title: "Grade", unit: "%", digits: 2, zero: true,
   series: [{label: "grade", value: rowsOf("grade", 100), colour: "#3fb950"}],
   limits: (c) => [["grade high", c.alarms.grade_high_pct], ["grade low", c.alarms.grade_low_pct]]
     .filter(([, v]) => v > 0 && v < 100)},  // 0 and 100 % are no limits: that alarm is off
  {id: "hardness", title: "Hardness (relative)", unit: "-", digits: 3, minSpan: 0.1,
   series: [{label: "hardness", value: rowsOf("hardness"), colour: "#58a6ff"}]},
  {id: "d80", title: "D80", unit: "mm", digits: 1, zero: true,
   series: [{label: "D80", value: rowsOf("d80_m", 1e3), colour: "#d2a8ff"}]},
  {id: "discharge", title: "Discharge rate", unit: "t/h", digits: 0, zero: true,
   series: [{label: "actual", value: rowsOf("discharge_actual_kg_s", 3.6), colour: "#ffa657"},
            {label: "setpoint", value: rowsOf("discharge_rate_kg_s", 3.6), colour: "#e6edf3", dash: [6, 4]}]},
  {id: "particles", title: "Particles held", unit: "count", digits: 0, zero: true,
   series: [{label: "particles", value: rowsOf("particle_count"), colour: "#79c0ff"}]},
];

// The y range of a trend over the x range shown, from its own series (not its
// limit lines). Set by the page with the x range (the y scale has auto off):
// uPlot's own auto-ranging would include the limit lines.
function yRange(trend, data, range) {
  if (trend.range) return {min: trend.range[0], max: trend.range[1]};
  const x = data[0];
  let lo = Infinity, hi = -Infinity;
  for (let s = 1; s <= trend.series.length; s++) {
    const ys = data[s] || [];
    for (let i = 0; i < x.length; i++) {
      if (ys[i] === null || x[i] < range.min || x[i] > range.max) continue;
      lo = Math.min(lo, ys[i]); hi = Math.max(hi, ys[i]);
    }
  }
  if (!Number.isFinite(lo)) return {min: 0, max: 1};
  if (trend.zero) return {min: 0, max: hi > 0 ? hi * 1.1 : 1};
  const mid = (lo + hi) / 2, span = Math.max(hi - lo, trend.minSpan * Math.abs(mid), 1e-9);
  return {min: mid - 0.6 * span, max: mid + 0.6 * span};
}

function makeTrend(trend) {
  const box = document.createElement("div");
  box.className = "trend";
  box.id = "trend-" + trend.id;
  $("trend-grid").appendChild(box);
  const limits = trend.limits ? trend.limits(state.config) : [];
  const value = (u, v) => (v === null || v === undefined ? "–" : v.toFixed(trend.digits));
  const axis = {stroke: MUTED, grid: {stroke: GRID, width: 1}, ticks: {stroke: GRID, width: 1}};
  const series = [{label: "t [s]", value: (u, v) => (v === null ? "–" : v.toFixed(1))},
    ...trend.series.map((s) => ({label: `${s.label} [${trend.unit}]`, stroke: s.colour, width: 2,
                                 dash: s.dash, value})),
    ...limits.map(([label]) => ({label: `${label} [${trend.unit}]`, stroke: LIMIT, width: 1,
                                 dash: [3, 3], value}))];
  const chart = new uPlot({
    title: `${trend.title} [${trend.unit}]`,
    width: Math.max(box.clientWidth, 200), height: 200,
    scales: {x: {time: false}, y: {auto: false}},
    axes: [{...axis, label: "simulation time [s]", labelSize: 16, size: 36},
           {...axis, label: `${trend.title} [${trend.unit}]`, labelSize: 16, size: 58}],
    series,
    cursor: {drag: {x: true, y: false, setScale: false}},
    hooks: {setSelect: [(u) => {
      if (u.select.width > 3) {
        zoomTo(u.posToVal(u.select.left, "x"), u.posToVal(u.select.left + u.select.width, "x"));
      }
      u.setSelect({left: 0, top: 0, width: 0, height: 0}, false);
    }]},
  }, [[], ...series.slice(1).map(() => [])], box);
  chart.over.addEventListener("dblclick", () => zoomTo(null));
  chart.trend = trend;
  chart.limitValues = limits.map(([, v]) => v);
  state.charts[trend.id] = chart;
}

function zoomTo(min, max) {
  state.zoom = min === null || !(max > min) ? null : {min, max};
  $("zoom-reset").disabled = state.zoom === null;
  $("zoom-note").textContent = state.zoom
    ? `zoomed to t = ${min.toFixed(1)}–${max.toFixed(1)} s (double-click a trend or reset)`
    : "drag across a trend to zoom";
  applyXRange();
}

// Zoom (by dragging) wins over the time-range selection, which follows the newest value.
function xRange() {
  const rows = state.history;
  if (state.zoom) return state.zoom;
  if (!rows.length) return null;
  const t0 = rows[0].time_s, t1 = rows[rows.length - 1].time_s;
  const windowS = Number($("trend-range").value);
  const min = windowS > 0 ? Math.max(t0, t1 - windowS) : t0;
  return {min, max: t1 > min ? t1 : min + 1};
}

function applyXRange() {
  const range = xRange();
  if (!range) return;
  for (const chart of Object.values(state.charts)) {
    chart.batch(() => {
      chart.setScale("x", range);
      chart.setScale("y", yRange(chart.trend, chart.data, range));
    });
  }
  const note = $("range-shown");
  note.textContent = `t = ${range.min.toFixed(1)}–${range.max.toFixed(1)} s`;
  Object.assign(note.dataset, {min: String(range.min), max: String(range.max)});
}

function drawTrends() {
  if (!Object.keys(state.charts).length) TRENDS.forEach(makeTrend);
  const rows = state.history, t = rows.map((r) => r.time_s);
  for (const chart of Object.values(state.charts)) {
    const data = [t, ...chart.trend.series.map((s) => rows.map(s.value)),
                  ...chart.limitValues.map((v) => t.map(() => v))];
    chart.setData(data, false);
  }
  applyXRange();
}

// The trends' data as CSV: the /history rows in the time range the trends show
// (the zoom, else the time-range selection), every column in SI.
function historyCSV() {
  const range = xRange();
  const rows = range ? state.history.filter((r) => r.time_s >= range.min && r.time_s <= range.max) : [];
  if (!rows.length) return "";
  const keys = Object.keys(rows[0]);
  const lines = [keys.join(",")];
  for (const row of rows) lines.push(keys.map((k) => (row[k] === null ? "" : String(row[k]))).join(","));
  return lines.join("\n") + "\n";
}

function exportCSV() {
  const blob = new Blob([historyCSV()], {type: "text/csv"});
  const range = xRange();
  const link = document.createElement("a");
  link.href = URL.createObjectURL(blob);
  link.download = range ? `stockpile_history_t${range.min.toFixed(0)}-${range.max.toFixed(0)}s.csv`
    : "stockpile_history.csv";
  document.body.appendChild(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(link.href), 1000);
}

// --------------------------------------------------------------- feed chart
// Bars: mass [t] predicted to leave per interval; colour: the pile's colouring
// when the prediction has that attribute (grade, hardness), else neutral.
function drawFeedChart(feed) {
  const canvas = $("feed-chart"), ctx = canvas.getContext("2d"), w = canvas.width, h = canvas.height;
  ctx.clearRect(0, 0, w, h);
  const profile = feed.profile;
  ctx.fillStyle = MUTED; ctx.font = "11px sans-serif";
  if (!profile || !profile.t_s.length) {
    ctx.fillText("no per-interval prediction from this stockpile", 4, h / 2);
    return;
  }
  const n = profile.t_s.length, left = 46, right = 8, top = 8, bottom = 30;
  const interval = profile.t_s[0];
  const masses = profile.mass_kg.map((m) => (m || 0) / 1000);
  const mmax = Math.max(...masses, 0);
  if (!(mmax > 0)) {
    ctx.fillText("nothing predicted to leave (feeder stopped or pile empty)", 4, h / 2);
    $("feed-caption").textContent = "";
    return;
  }
  const step = niceBelow(mmax / 2), ytop = Math.ceil(mmax / step) * step;
  const Y = (m) => h - bottom - (h - top - bottom) * m / ytop;
  const barW = (w - left - right) / n;
  const attribute = state.colourBy;
  const coloured = profile[attribute] !== undefined && state.scheme && !state.scheme.categorical;
  // coloured by origin: each bar stacked by the mass from each source, in the pile's colours
  const stacked = attribute === "origin" && Array.isArray(profile.origins) && state.scheme &&
    state.scheme.attribute === "origin" && Boolean(state.scheme.categorical);
  ctx.strokeStyle = GRID; ctx.lineWidth = 1;
  for (let m = 0; m <= ytop + 1e-9; m += step) {
    ctx.beginPath(); ctx.moveTo(left, Y(m)); ctx.lineTo(w - right, Y(m)); ctx.stroke();
    ctx.fillText(`${m.toPrecision(2)} t`, 2, Y(m) + 4);
  }
  for (let i = 0; i < n; i++) {
    if (stacked) {
      let below = 0;
      profile.origins.forEach((origin, k) => {
        const m = Math.max(profile.origin_mass_kg[k][i] || 0, 0) / 1000;
        ctx.fillStyle = originColour(origin);
        ctx.fillRect(left + i * barW + 1, Y(below + m), barW - 2, Y(below) - Y(below + m));
        below += m;
      });
      continue;
    }
    const value = coloured ? profile[attribute][i] : null;
    ctx.fillStyle = coloured ? (value === null ? "#444" : state.scheme.colour(value)) : "#6e7681";
    ctx.fillRect(left + i * barW + 1, Y(masses[i]), barW - 2, Y(0) - Y(masses[i]));
  }
  canvas.dataset.colouredBy = stacked ? "origin" : (coloured ? attribute : "none");
  canvas.dataset.origins = stacked ? profile.origins.join(",") : "";
  ctx.fillStyle = MUTED;
  for (let s = 0; s <= profile.t_s[n - 1] + 1e-9; s += 10) {
    const x = left + (w - left - right) * s / profile.t_s[n - 1];
    ctx.fillText(String(s), x - 4, h - bottom + 12);
  }
  ctx.fillText("time from now [s]", left + (w - left - right) / 2 - 40, h - 4);
  const per = `bar height: mass leaving per ${interval.toPrecision(2)} s`;
  $("feed-caption").textContent = stacked
    ? `${per}; colours: the mass from each source, as in the origin key under the pile`
    : coloured
      ? `${per}; colour: ${SHOWN[attribute].label} on the pile's colour bar`
      : `${per}; grey: the prediction has no ${SHOWN[attribute].label} per interval ` +
        "(colour by grade, hardness or origin to colour the bars)";
}

// -------------------------------------------------------------------- start
$("colour-by").addEventListener("change", (event) => {
  state.colourBy = event.target.value;
  drawPile();
  if (state.feed) drawFeedChart(state.feed);
});
$("show-velocity").addEventListener("change", drawPile);
// A new time range replaces a zoom (the zoom would hide it).
$("trend-range").addEventListener("change", () => zoomTo(null));
$("zoom-reset").addEventListener("click", () => zoomTo(null));
$("export-csv").addEventListener("click", exportCSV);
$("restart-dismiss").addEventListener("click", () => { $("restart-banner").hidden = true; });
$("operator").value = window.localStorage.getItem("minetwin.operator") || "";
$("ack-all").addEventListener("click", () => acknowledge("all"));
window.addEventListener("resize", () => {
  for (const chart of Object.values(state.charts)) {
    chart.setSize({width: Math.max(chart.root.parentElement.clientWidth, 200), height: 200});
  }
});
setInterval(showAges, 500);
poll();
