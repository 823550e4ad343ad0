// PackPilot live dashboard: one WebSocket, plain <canvas> charts, no external resources.
// Protocol (see docs/dashboard.md): a "hello" message (scenario, battery names), then "update"
// messages with new chart points, new events, the latest sample and, at the end, the metrics.
"use strict";

// Battery colours: none of them is the alarm red (ALARM), so "battery B" never reads as an alarm.
const COLORS = ["#1f6fd1", "#e07b00", "#1f9d55", "#8e44ad", "#0f9fa8", "#6d4c41", "#5c6bc0",
  "#7a8a00"];
const ALARM = "#d33a2c";
const CHARTS = [
  { key: "voltage_v", title: "Voltage", unit: "V", scale: 1 },
  { key: "current_a", title: "Current (+ discharge)", unit: "A", scale: 1 },
  { key: "soc", title: "SOC", unit: "%", scale: 100 },
  { key: "temp_c", title: "Temperature", unit: "°C", scale: 1 },
];
// Each event carries its severity from the one table (contract/severity.py); routine events
// that change a mode or stage are still marked, in blue.
const isBad = (e) => e.severity === "alarm" || e.severity === "fault";
const INFO_KINDS = /Mode|Stage|Joined|Reset|Resupplied/i;
const MAX_EVENT_ROWS = 1000;

const S = {
  names: [], points: [], events: [], latest: null, maxPoints: 2000, duration: 0, speed: 0,
  received: 0, updates: 0, state: "connecting", metrics: null, cards: [], dirty: false,
};

const $ = (id) => document.getElementById(id);
const el = (tag, cls, text) => {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined) e.textContent = text;
  return e;
};
const isNum = (x) => typeof x === "number" && Number.isFinite(x);
const fmt = (x, d = 2, unit = "") => (isNum(x) ? x.toFixed(d) + (unit ? " " + unit : "") : "—");
function fmtTime(t) {
  if (!isNum(t)) return "—";
  const h = Math.floor(t / 3600), m = Math.floor((t % 3600) / 60), s = t % 60;
  const ss = s.toFixed(1).padStart(4, "0");
  return (h ? h + ":" + String(m).padStart(2, "0") : String(m)) + ":" + ss;
}
function fmtAny(v) {
  if (v === null || v === undefined) return "—";
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toPrecision(4);
  if (typeof v === "boolean") return v ? "yes" : "no";
  if (Array.isArray(v)) return v.map(fmtAny).join(", ");
  if (typeof v === "object") return Object.entries(v).map(([k, x]) => k + ": " + fmtAny(x)).join(", ");
  return String(v);
}

// ------------------------------------------------------------------ connection
function connect() {
  const proto = location.protocol === "https:" ? "wss://" : "ws://";
  const ws = new WebSocket(proto + location.host + "/ws");
  ws.onopen = () => setConn(true);
  ws.onmessage = (ev) => {
    const msg = JSON.parse(ev.data);
    if (msg.type === "hello") onHello(msg);
    else if (msg.type === "update") onUpdate(msg);
  };
  ws.onclose = () => {
    setConn(false);
    setTimeout(connect, 2000); // the server may come back (e.g. restarted)
  };
  ws.onerror = () => ws.close();
}

function setConn(on) {
  const c = $("conn");
  c.className = "conn " + (on ? "on" : "off");
  c.textContent = on ? "live" : "offline";
}

function onHello(msg) {
  // A (re)connection replays the whole history: start from scratch.
  S.names = msg.battery_names || [];
  S.points = [];
  S.events = [];
  S.latest = null;
  S.received = 0;
  S.updates = 0;
  S.maxPoints = msg.max_points || 2000;
  S.duration = msg.duration_s || 0;
  S.speed = msg.speed || 0;
  $("scenario").textContent = msg.scenario;
  document.title = "PackPilot live — " + msg.scenario;
  $("speed").textContent = S.speed > 0 ? S.speed + "× real time" : "as fast as possible";
  document.querySelector("#events tbody").textContent = "";
  buildCards();
}

function onUpdate(msg) {
  S.updates += 1;
  if (msg.points && msg.points.length) {
    S.received += msg.points.length;
    for (const p of msg.points) S.points.push(p);
    while (S.points.length > S.maxPoints) S.points = S.points.filter((_, i) => i % 2 === 0);
  }
  if (msg.events && msg.events.length) addEvents(msg.events);
  if (msg.latest) S.latest = msg.latest;
  S.state = msg.state;
  S.metrics = msg.metrics;
  renderStatus(msg);
  if (msg.verdict) renderVerdict(msg.verdict);
  renderCards();
  if (msg.metrics) renderMetrics(msg.metrics);
  const b = document.body.dataset;
  b.samples = String(S.received);
  b.updates = String(S.updates);
  b.events = String(S.events.length);
  b.state = S.state;
  requestDraw();
}

// ------------------------------------------------------------------ pack status
function renderStatus(msg) {
  const badge = $("run-state");
  badge.textContent = msg.state;
  badge.className = "badge state-" + msg.state;
  const L = S.latest;
  $("t-s").textContent = fmtTime(msg.t_s) + (S.duration ? " / " + fmtTime(S.duration) : "");
  const done = msg.state === "finished";
  $("progress-bar").style.width = (done ? 100 : 100 * (msg.progress || 0)).toFixed(1) + "%";
  if (L) {
    $("bus-v").textContent = fmt(L.bus_v, 2, "V");
    $("load-a").textContent = fmt(L.load_a, 1, "A") + " (" + fmt(L.load_demand_a, 1) + ")";
    $("charger").textContent = fmt(L.charger_v, 1, "V") + " · " + fmt(L.charger_a, 2, "A");
    $("mode").textContent = L.mode || "—";
  }
  $("n-events").textContent = String(S.events.length);
  const err = $("error");
  if (msg.error) {
    err.hidden = false;
    err.textContent = (msg.state === "stopped" ? "stopped: " : "error: ") + msg.error;
  } else err.hidden = true;
}

// ------------------------------------------------------------------ verdict + alarms
function renderVerdict(v) {
  const badge = $("verdict");
  badge.textContent = v.verdict;
  badge.className = "badge verdict-" + v.verdict.toLowerCase();
  document.body.dataset.verdict = v.verdict;
  const rows = v.alarms || [];
  $("alarms-none").hidden = rows.length > 0;
  $("alarms").hidden = rows.length === 0;
  const tbody = document.querySelector("#alarms tbody");
  tbody.textContent = "";
  for (const a of rows) {
    const tr = el("tr", "sev-" + a.severity);
    const what = a.kind + (a.count > 1 ? " ×" + a.count : "");
    const cleared = a.cleared ? "yes, at " + fmtTime(a.cleared_t_s) : "no";
    tr.append(el("td", null, fmtTime(a.t_s)), el("td", null, a.battery || "pack"),
      el("td", "sev", a.severity), el("td", null, what), el("td", null, a.cause),
      el("td", null, cleared));
    tbody.append(tr);
  }
}

// ------------------------------------------------------------------ battery cards
function buildCards() {
  const root = $("batteries");
  root.textContent = "";
  S.cards = S.names.map((name, i) => {
    const card = el("div", "panel bat");
    const h = el("h3");
    const sw = el("span", "swatch");
    sw.style.background = COLORS[i % COLORS.length];
    h.append(sw, el("span", null, name));
    const nums = el("div", "nums");
    const cells = {};
    for (const [k, label] of [["voltage_v", "V"], ["current_a", "A"], ["soc", "SOC"],
      ["temp_c", "°C"]]) {
      const n = el("div", "num");
      cells[k] = el("div", "v", "—");
      n.append(cells[k], el("div", "k", label));
      nums.append(n);
    }
    const socbar = el("div", "socbar");
    const socfill = el("div");
    socbar.append(socfill);
    const cellsLine = el("div", "line");
    const switches = el("div", "line");
    const prot = el("div", "line");
    const extra = el("div", "line");
    const details = el("details");
    details.append(el("summary", null, "all controller status"));
    const table = el("table");
    details.append(table);
    card.append(h, nums, socbar, cellsLine, switches, prot, extra, details);
    root.append(card);
    return { cells, socfill, cellsLine, switches, prot, extra, table, details };
  });
}

function pill(label, on, diode) {
  const p = el("span", "sw " + (on ? "on" : diode ? "diode" : "off"));
  p.textContent = label + " " + (on ? "on" : diode ? "diode" : "off");
  return p;
}

function renderCards() {
  const L = S.latest;
  if (!L) return;
  L.batteries.forEach((b, i) => {
    const c = S.cards[i];
    if (!c) return;
    c.cells.voltage_v.textContent = fmt(b.voltage_v, 2);
    c.cells.current_a.textContent = fmt(b.current_a, 2);
    c.cells.soc.textContent = isNum(b.soc) ? (100 * b.soc).toFixed(1) + "%" : "—";
    c.cells.temp_c.textContent = fmt(b.temp_c, 1);
    c.socfill.style.width = isNum(b.soc) ? Math.max(0, Math.min(100, 100 * b.soc)) + "%" : "0";
    c.cellsLine.innerHTML = "";
    c.cellsLine.append(el("span", "k", "cells"),
      el("span", null, fmt(b.min_cell_v, 3) + " … " + fmt(b.max_cell_v, 3) + " V"),
      el("span", "k", " · remaining"), el("span", null, fmt(b.remaining_ah, 2, "Ah")));
    c.switches.textContent = "";
    c.switches.append(el("span", "k", "switches"),
      pill("CHG", b.chg_on > 0.5, Math.abs(b.chg_diode_a || 0) > 0.01),
      pill("DSG", b.dsg_on > 0.5, Math.abs(b.dsg_diode_a || 0) > 0.01));
    const st = b.status || {};
    c.prot.textContent = "";
    if ("protection_param" in st) {
      c.prot.append(el("span", "k", "protection"));
      const p = st.protection_param;
      const txt = p ? p + " (cut-off " + fmt(st.protection_cutoff_v, 2, "V") + ", t_max " +
        fmt(st.protection_tmax_s, 0, "s") + ")" : "none active";
      c.prot.append(el("span", null, txt));
      if (isNum(st.protection_fraction))
        c.prot.append(el("span", "k", " · used " + (100 * st.protection_fraction).toFixed(0) + "%"));
      if (st.protection_tripped) c.prot.append(el("span", "tripped", " TRIPPED"));
    }
    const bits = [];
    if ("seq_state" in st) bits.push(["sequencing", st.seq_state]);
    if ("chg_stage" in st) bits.push(["charging", st.chg_stage]);
    if ("eq_fault" in st && st.eq_fault) bits.push(["equalizer", "fault"]);
    c.extra.textContent = "";
    for (const [k, v] of bits) c.extra.append(el("span", "k", k), el("span", null, fmtAny(v) + "  "));
    if (c.details.open || !c.table.rows.length) {
      c.table.textContent = "";
      for (const [k, v] of Object.entries(st)) {
        const tr = el("tr");
        tr.append(el("td", null, k), el("td", null, fmtAny(v)));
        c.table.append(tr);
      }
    }
  });
}

// ------------------------------------------------------------------ events + metrics
function addEvents(evs) {
  const tbody = document.querySelector("#events tbody");
  for (const e of evs) {
    S.events.push(e);
    const tr = el("tr");
    const cls = isBad(e) ? "kind-bad" : e.severity === "warning" ? "kind-warn"
      : INFO_KINDS.test(e.kind) ? "kind-info" : "kind-other";
    tr.append(el("td", null, fmtTime(e.t_s)), el("td", cls, e.kind),
      el("td", null, e.battery_name || ""), el("td", null, e.message || ""));
    tbody.insertBefore(tr, tbody.firstChild); // newest on top
  }
  while (tbody.rows.length > MAX_EVENT_ROWS) tbody.deleteRow(tbody.rows.length - 1);
  $("events-count").textContent = "(" + S.events.length + ", newest first)";
}

function renderMetrics(m) {
  const tbody = document.querySelector("#metrics tbody");
  tbody.textContent = "";
  for (const [k, v] of Object.entries(m)) {
    const tr = el("tr");
    tr.append(el("td", null, k), el("td", null, fmtAny(v)));
    tbody.append(tr);
  }
  $("metrics-note").textContent = "(final)";
}

// ------------------------------------------------------------------ charts
function niceTicks(lo, hi, n) {
  const span = hi - lo;
  const raw = span / Math.max(1, n);
  const mag = Math.pow(10, Math.floor(Math.log10(raw)));
  const step = [1, 2, 2.5, 5, 10].map((f) => f * mag).find((s) => span / s <= n) || 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9 * span; v += step) out.push(v);
  return { ticks: out, step };
}

function tickLabel(v, step) {
  const d = Math.max(0, -Math.floor(Math.log10(step) + 1e-9));
  return v.toFixed(Math.min(d, 4));
}

function drawChart(spec) {
  const canvas = $("chart-" + spec.key);
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth, h = canvas.clientHeight;
  if (!w || !h) return;
  if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
    canvas.width = Math.round(w * dpr);
    canvas.height = Math.round(h * dpr);
  }
  const g = canvas.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, w, h);
  const pad = { l: 52, r: 10, t: 22, b: 26 };
  const pw = w - pad.l - pad.r, ph = h - pad.t - pad.b;
  g.font = "12px system-ui, sans-serif";
  g.fillStyle = "#1d2430";
  g.fillText(spec.title + " [" + spec.unit + "]", pad.l, 14);

  const pts = S.points;
  const n = S.names.length;
  let ylo = Infinity, yhi = -Infinity;
  for (const p of pts) {
    const row = p[spec.key] || [];
    for (let i = 0; i < n; i++) {
      const v = row[i];
      if (isNum(v)) { ylo = Math.min(ylo, v * spec.scale); yhi = Math.max(yhi, v * spec.scale); }
    }
  }
  if (!pts.length || !Number.isFinite(ylo)) {
    g.fillStyle = "#6b7686";
    g.fillText("waiting for data…", pad.l + 10, pad.t + ph / 2);
    return;
  }
  if (yhi - ylo < 1e-9) { ylo -= 0.5; yhi += 0.5; }
  const ym = 0.06 * (yhi - ylo);
  ylo -= ym; yhi += ym;
  const t0 = pts[0].t_s, t1 = Math.max(pts[pts.length - 1].t_s, t0 + 1e-6);
  const X = (t) => pad.l + ((t - t0) / (t1 - t0)) * pw;
  const Y = (v) => pad.t + (1 - (v - ylo) / (yhi - ylo)) * ph;

  // grid + labels
  g.strokeStyle = "#e6eaef";
  g.lineWidth = 1;
  g.fillStyle = "#6b7686";
  g.textAlign = "right";
  const yt = niceTicks(ylo, yhi, 5);
  for (const v of yt.ticks) {
    const y = Math.round(Y(v)) + 0.5;
    g.beginPath(); g.moveTo(pad.l, y); g.lineTo(pad.l + pw, y); g.stroke();
    g.fillText(tickLabel(v, yt.step), pad.l - 6, y + 4);
  }
  g.textAlign = "center";
  const xt = niceTicks(t0, t1, 6);
  for (const t of xt.ticks) {
    const x = Math.round(X(t)) + 0.5;
    g.beginPath(); g.moveTo(x, pad.t); g.lineTo(x, pad.t + ph); g.stroke();
    g.fillText(tickLabel(t, xt.step) + " s", x, pad.t + ph + 16);
  }
  g.strokeStyle = "#b9c1cc";
  g.strokeRect(pad.l + 0.5, pad.t + 0.5, pw, ph);

  // event marks: faint verticals for trips/faults (red) and mode/stage changes (blue);
  // routine kinds (balancing updates, SOC corrections) would only clutter the chart
  let marks = 0;
  for (let k = S.events.length - 1; k >= 0 && marks < 200; k--) {
    const e = S.events[k];
    if (!isNum(e.t_s) || e.t_s < t0 || e.t_s > t1) continue;
    const bad = isBad(e);
    if (!bad && !INFO_KINDS.test(e.kind)) continue;
    marks++;
    g.strokeStyle = bad ? ALARM + "59" : "rgba(47, 111, 222, 0.25)"; // 0x59: 35 % alpha
    const x = Math.round(X(e.t_s)) + 0.5;
    g.beginPath(); g.moveTo(x, pad.t); g.lineTo(x, pad.t + ph); g.stroke();
  }

  // one line per battery; a null value breaks the line
  g.save();
  g.beginPath(); g.rect(pad.l, pad.t, pw, ph); g.clip();
  g.lineWidth = 1.6;
  g.lineJoin = "round";
  for (let i = 0; i < n; i++) {
    g.strokeStyle = COLORS[i % COLORS.length];
    g.beginPath();
    let pen = false;
    for (const p of pts) {
      const v = (p[spec.key] || [])[i];
      if (!isNum(v)) { pen = false; continue; }
      const x = X(p.t_s), y = Y(v * spec.scale);
      if (pen) g.lineTo(x, y); else { g.moveTo(x, y); pen = true; }
    }
    g.stroke();
  }
  g.restore();

  // legend
  g.textAlign = "left";
  let lx = pad.l + pw;
  for (let i = n - 1; i >= 0; i--) {
    const label = S.names[i];
    const tw = g.measureText(label).width;
    lx -= tw + 22;
    g.fillStyle = COLORS[i % COLORS.length];
    g.fillRect(lx, 6, 12, 8);
    g.fillStyle = "#1d2430";
    g.fillText(label, lx + 16, 14);
  }
}

function drawAll() {
  S.dirty = false;
  for (const spec of CHARTS) drawChart(spec);
}

function requestDraw() {
  if (S.dirty) return;
  S.dirty = true;
  // rAF pauses in background tabs; the timeout keeps a hidden tab's charts current too.
  if (document.hidden) setTimeout(drawAll, 250);
  else requestAnimationFrame(drawAll);
}

window.addEventListener("resize", requestDraw);
document.addEventListener("visibilitychange", requestDraw);
drawAll();
connect();
