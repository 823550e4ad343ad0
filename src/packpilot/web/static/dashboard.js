// PackPilot dashboard: one WebSocket, plain <canvas> charts, an inline-SVG pack schematic, no
// external resources. Protocol (see docs/dashboard.md): a "hello" message (scenario, battery
// names, pack layout), then "update" messages with new chart points, new events, the latest
// sample and, at the end, the metrics. A new "hello" means the server switched to another run.
// Controls POST to /api/* with the page's token in the X-PackPilot-Token header.
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
const SEVERITY = { info: 0, warning: 1, alarm: 2, fault: 3 };
const isBad = (e) => e.severity === "alarm" || e.severity === "fault";
const INFO_KINDS = /Mode|Stage|Joined|Reset|Resupplied/i;
const MAX_EVENT_ROWS = 1000;
const BALANCING_A = 1e-4; // an equalizer current above this marks its group as balancing
const TOKEN = (document.querySelector('meta[name="packpilot-token"]') || {}).content || "";
const SVG = "http://www.w3.org/2000/svg";

const S = {
  names: [], points: [], events: [], latest: null, maxPoints: 2000, duration: 0, speed: 0,
  received: 0, updates: 0, state: "connecting", metrics: null, cards: [], dirty: false,
  kind: "live", layout: null, paused: false, cursorT: null, playing: null, sch: null,
  finalLatest: null, headline: null, power: null, powerNote: null,
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
  t = Math.round(t * 10) / 10; // 3599.96 s is 1:00:00.0, not 59:60.0
  const h = Math.floor(t / 3600), m = Math.floor((t % 3600) / 60), s = t % 60;
  const ss = (Math.round(s * 10) / 10).toFixed(1).padStart(4, "0");
  return (h ? h + ":" + String(m).padStart(2, "0") : String(m)) + ":" + ss;
}
function fmtDur(t) {
  if (!isNum(t)) return "—";
  if (t >= 3600) return Math.floor(t / 3600) + " h " + String(Math.floor((t % 3600) / 60)).padStart(2, "0") + " min";
  if (t >= 60) return Math.floor(t / 60) + " min " + String(Math.floor(t % 60)).padStart(2, "0") + " s";
  return t.toFixed(0) + " s";
}
function fmtAny(v) {
  if (v === null || v === undefined) return "—";
  if (typeof v === "number") return Number.isInteger(v) ? String(v) : v.toPrecision(4);
  if (typeof v === "boolean") return v ? "yes" : "no";
  if (Array.isArray(v)) return v.map(fmtAny).join(", ");
  if (typeof v === "object") return Object.entries(v).map(([k, x]) => k + ": " + fmtAny(x)).join(", ");
  return String(v);
}
function svg(tag, attrs, text) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined) e.textContent = text;
  return e;
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
  c.textContent = on ? "connected" : "offline"; // not "live": a recording is connected too
}

function onHello(msg) {
  // A (re)connection or a switch to another run replays the whole history: start from scratch.
  stopPlay();
  S.names = msg.battery_names || [];
  S.points = [];
  S.events = [];
  S.latest = null;
  S.finalLatest = null;
  S.received = 0;
  S.updates = 0;
  S.cursorT = null;
  S.maxPoints = msg.max_points || 2000;
  S.duration = msg.duration_s || 0;
  S.speed = msg.speed || 0;
  S.kind = msg.kind || "live";
  S.layout = msg.layout || null;
  $("scenario").textContent = msg.scenario;
  // "attached": a run another process is writing, followed read-only from its telemetry file
  const kindLabel = { recorded: "recording", attached: "attached (read-only)" }[S.kind] || "live";
  $("kind").textContent = kindLabel;
  $("source").textContent = msg.source ? "(" + msg.source + ")" : "";
  $("schematic-note").textContent = "(bus, switches, charger, load; " + ({
    recorded: "at the time on the scrubber", attached: "as its writer records it" }[S.kind]
    || "live") + ")";
  hideConfirm();
  document.title = "PackPilot " + kindLabel + " — " + msg.scenario;
  $("pace-controls").hidden = S.kind === "attached"; // nothing here paces a run it only reads
  $("btn-pause").hidden = S.kind !== "live";
  $("scrub-controls").hidden = S.kind !== "recorded";
  $("scrub").max = String(Math.max(S.duration, 1e-3));
  $("scrub").value = $("scrub").max;
  $("scrub-t").textContent = S.kind === "recorded" ? "end / " + fmtTime(S.duration) : "—";
  $("report-link").hidden = true;
  showSpeed(S.kind === "recorded" ? 10 : S.speed); // a recording plays at 10x by default
  document.querySelector("#events tbody").textContent = "";
  countEvents(); // "0" is a count too: data-events-shown is always there
  const fb = $("filter-battery");
  const keep = fb.value;
  fb.length = 2;
  for (const n of S.names) fb.append(new Option(n, n));
  fb.value = [...fb.options].some((o) => o.value === keep) ? keep : "*";
  document.body.dataset.kind = S.kind;
  document.body.dataset.scrub = "";
  buildCards();
  buildSchematic();
  loadCatalog();
}

function onUpdate(msg) {
  S.updates += 1;
  if (msg.points && msg.points.length) {
    S.received += msg.points.length;
    for (const p of msg.points) S.points.push(p);
    while (S.points.length > S.maxPoints) S.points = S.points.filter((_, i) => i % 2 === 0);
  }
  if (msg.events && msg.events.length) addEvents(msg.events);
  if (msg.latest) S.finalLatest = msg.latest;
  if (S.cursorT === null) { // a scrubbed recording shows the moment chosen, not the end
    S.latest = S.finalLatest;
    S.headline = msg.headline;
    S.power = msg.power || null;
  }
  S.powerNote = msg.power_note || null;
  S.state = msg.state;
  S.metrics = msg.metrics;
  S.paused = !!msg.paused;
  if (isNum(msg.speed) && S.kind === "live") S.speed = msg.speed;
  renderStatus(msg);
  renderControls(msg);
  if (msg.verdict) renderVerdict(msg.verdict);
  renderLatest();
  if (msg.metrics) renderMetrics(msg.metrics);
  const b = document.body.dataset;
  b.samples = String(S.received);
  b.updates = String(S.updates);
  b.events = String(S.events.length);
  b.state = S.state;
  b.paused = String(S.paused);
  b.speed = String(S.speed);
  requestDraw();
}

function renderLatest() {
  const L = S.latest;
  if (L) {
    $("bus-v").textContent = fmt(L.bus_v, 2, "V");
    $("load-a").textContent = fmt(L.load_a, 1, "A") + " (" + fmt(L.load_demand_a, 1) + ")";
    $("charger").textContent = fmt(L.charger_v, 1, "V") + " · " + fmt(L.charger_a, 2, "A");
    $("mode").textContent = L.mode || "—";
  }
  renderHeadline(S.headline);
  renderPower(S.power);
  renderCards();
  renderSchematic();
}

// ------------------------------------------------------------------ state of power (#28)
// The server's prediction (sim/power_view.py, the one the runtime publishes as CCL/DCL and
// 0x231) from the core's state at one step; each figure carries data-sop="dsg:10" etc. and
// its value in data-v, so a test reads exactly what is shown.
const fmtA = (x) => (isNum(x) ? x.toFixed(1) + " A" : "—");
const fmtW = (x) => (isNum(x) ? (Math.abs(x) >= 1000 ? (x / 1000).toFixed(2) + " kW" : x.toFixed(0) + " W") : "—");
function sopCell(key, a, w) {
  const td = el("td", "num", fmtA(a) + (w === undefined ? "" : " · " + fmtW(w)));
  td.dataset.sop = key;
  td.dataset.v = isNum(a) ? String(a) : "";
  if (w !== undefined) td.dataset.w = isNum(w) ? String(w) : "";
  return td;
}
function renderPower(P) {
  const none = $("power-none"), tab = $("power"), bt = $("power-bat");
  const ok = P && P.horizons && !P.error;
  none.hidden = !!ok;
  tab.hidden = bt.hidden = !ok;
  if (!ok) {
    none.textContent = P && P.error ? "no prediction: " + P.error
      : S.powerNote || (S.latest ? "computing…" : "—");
    return;
  }
  const why = (w, who) => w === "none" ? "—" : w + (who ? ", battery " + who : "");
  const body = tab.tBodies[0];
  body.textContent = "";
  for (const h of P.horizons) {
    const tr = el("tr");
    const s = String(h.horizon_s);
    tr.append(el("td", null, s + " s"), sopCell("dsg:" + s, h.dsg_a, h.dsg_w),
      el("td", null, why(h.why_dsg, h.who_dsg)), sopCell("chg:" + s, h.chg_a, h.chg_w),
      el("td", null, why(h.why_chg, h.who_chg)));
    body.append(tr);
  }
  const k10 = P.horizons.findIndex((h) => h.horizon_s === 10);
  const bb = bt.tBodies[0];
  bb.textContent = "";
  for (const b of P.batteries) {
    const tr = el("tr");
    tr.dataset.battery = b.name;
    const src = el("td", "src-" + b.soc_source, SOC_SOURCE_SHORT[b.soc_source] || b.soc_source);
    tr.append(el("td", null, b.name + (b.present ? "" : " (absent)")), src,
      sopCell("share_dsg:" + b.name, b.share_dsg_a[k10], b.share_dsg_w[k10]),
      sopCell("alone_dsg:" + b.name, b.alone_dsg_a[k10], b.alone_dsg_w[k10]),
      sopCell("share_chg:" + b.name, b.share_chg_a[k10], b.share_chg_w[k10]),
      sopCell("alone_chg:" + b.name, b.alone_chg_a[k10], b.alone_chg_w[k10]));
    bb.append(tr);
  }
  $("power-note").textContent = "(the largest constant current held for 2 / 10 / 30 s without any battery " +
    "crossing its cut-off, current or temperature limit; predicted from the core's state at " +
    fmtTime(P.t_s) + ")";
}

// ------------------------------------------------------------------ controls
async function post(path, body) {
  const r = await fetch(path, {
    method: "POST",
    headers: { "Content-Type": "application/json", "X-PackPilot-Token": TOKEN },
    body: JSON.stringify(body || {}),
  });
  let j = {};
  try { j = await r.json(); } catch (_) { /* an empty or non-JSON answer */ }
  if (!r.ok) throw new Error(j.error || (j.detail && JSON.stringify(j.detail)) || "HTTP " + r.status);
  return j;
}

function say(text, bad) {
  const m = $("control-msg");
  m.textContent = text || "";
  m.className = "ctl-msg" + (bad ? " bad" : "");
}

async function act(path, body, what) {
  try {
    say(what + "…");
    const r = await post(path, body);
    say("");
    return r;
  } catch (err) {
    say(what + " refused: " + err.message, true);
    return null;
  }
}

function showSpeed(speed) {
  const sel = $("speed-select");
  const v = String(speed);
  if (![...sel.options].some((o) => o.value === v)) sel.append(new Option(speed + "×", v));
  sel.value = v;
  $("speed").textContent = S.kind === "recorded" ? "recorded"
    : S.kind === "attached" ? "following its telemetry file"
    : speed > 0 ? speed + "× real time" : "as fast as possible";
}

function renderControls(msg) {
  const btn = $("btn-pause");
  const running = msg.state === "running" || msg.state === "starting";
  btn.textContent = S.paused ? "resume" : "pause";
  btn.disabled = S.kind !== "live" || !running;
  btn.classList.toggle("paused", S.paused);
  if (S.kind === "live" && document.activeElement !== $("speed-select")) showSpeed(S.speed);
  const link = $("report-link");
  link.hidden = !msg.report;
  if (msg.report) link.href = msg.report;
  const note = $("notice");
  note.hidden = !msg.notice;
  note.textContent = msg.notice || "";
}

async function loadCatalog() {
  let cat;
  try {
    const r = await fetch("/api/catalog");
    if (!r.ok) return;
    cat = await r.json();
  } catch (_) { return; }
  fillExamples($("example-select"), cat.examples || [], cat.current || null);
  $("example-pick").hidden = $("btn-start").hidden = !(cat.examples || []).length;
  fillSelect($("recording-select"), cat.recordings || []);
  $("recording-pick").hidden = $("btn-open").hidden = !(cat.recordings || []).length;
  // the fleet view (#27: battery health across flights) when the server was given --fleet
  $("fleet-link").hidden = $("fleet-api").hidden = !cat.fleet;
  if (cat.fleet) $("fleet-link").href = cat.fleet;
}

// The example picker shows the example on show (not the first name in the list); when what is
// on show is not an example, a placeholder, so *start* cannot start something by accident.
function fillExamples(sel, names, current) {
  sel.textContent = "";
  if (!current || !names.includes(current))
    sel.append(new Option(S.kind === "live" ? "(choose an example)" : "(choose one)", ""));
  for (const n of names) sel.append(new Option(n, n));
  sel.value = current && names.includes(current) ? current : "";
  S.currentExample = current;
  syncStart();
}

function syncStart() {
  const v = $("example-select").value;
  $("btn-start").disabled = !v;
  $("btn-start").textContent = v && v === S.currentExample ? "restart" : "start";
}

function fillSelect(sel, names) {
  const keep = sel.value;
  sel.textContent = "";
  for (const n of names) sel.append(new Option(n, n));
  if (names.includes(keep)) sel.value = keep;
}

$("btn-pause").addEventListener("click", () => {
  act(S.paused ? "/api/resume" : "/api/pause", {}, S.paused ? "resume" : "pause");
});
$("speed-select").addEventListener("change", () => {
  const v = Number($("speed-select").value);
  if (S.kind === "live") act("/api/speed", { speed: v }, "speed");
});
// Starting an example replaces the run on show: a running (or paused) live run is only
// replaced after the user confirms it, next to the button.
function startChosen() {
  const ex = $("example-select").value;
  hideConfirm();
  if (ex) act("/api/start", { example: ex, speed: Number($("speed-select").value) || 0 }, "start " + ex);
}
function hideConfirm() { $("confirm-start").hidden = true; }
$("example-select").addEventListener("change", () => { hideConfirm(); syncStart(); });
$("btn-start").addEventListener("click", () => {
  const ex = $("example-select").value;
  if (!ex) return;
  const busy = S.kind === "live" && (S.state === "running" || S.state === "starting");
  if (!busy) { startChosen(); return; }
  $("confirm-text").textContent = $("scenario").textContent + " is " +
    (S.paused ? "paused" : "running") + " (" + fmtTime(S.latest ? S.latest.t_s : NaN) +
    "): stop it and start " + ex + "?";
  $("confirm-start").hidden = false;
  $("btn-cancel-start").focus();
});
$("btn-confirm-start").addEventListener("click", startChosen);
$("btn-cancel-start").addEventListener("click", hideConfirm);
$("btn-open").addEventListener("click", () => {
  const rec = $("recording-select").value;
  if (rec) act("/api/open", { recording: rec }, "open " + rec);
});

// ------------------------------------------------------------------ scrubbing a recording
let atSeq = 0;
async function scrubTo(t) {
  S.cursorT = t;
  document.body.dataset.scrub = String(t);
  $("scrub-t").textContent = fmtTime(t) + " / " + fmtTime(S.duration);
  const seq = ++atSeq;
  let r;
  try {
    const resp = await fetch("/api/at?t_s=" + encodeURIComponent(t));
    if (!resp.ok) return;
    r = await resp.json();
  } catch (_) { return; }
  if (seq !== atSeq) return; // a later position was asked for meanwhile
  S.latest = r.latest;
  S.headline = r.headline;
  S.power = r.power || null;
  $("t-s").textContent = fmtTime(r.t_s) + (S.duration ? " / " + fmtTime(S.duration) : "");
  renderLatest();
  renderEvents();
  requestDraw();
  document.body.dataset.scrubbed = String(r.index);
}

function stopPlay() {
  if (S.playing) clearInterval(S.playing);
  S.playing = null;
  $("btn-play").textContent = "play";
}

$("scrub").addEventListener("input", () => { stopPlay(); scrubTo(Number($("scrub").value)); });
$("btn-play").addEventListener("click", () => {
  if (S.playing) { stopPlay(); return; }
  const rate = Number($("speed-select").value) || 100;
  let t = S.cursorT === null || S.cursorT >= S.duration ? 0 : S.cursorT;
  $("btn-play").textContent = "stop";
  S.playing = setInterval(() => {
    t = Math.min(S.duration, t + rate * 0.2);
    $("scrub").value = String(t);
    scrubTo(t);
    if (t >= S.duration) stopPlay();
  }, 200);
});

// ------------------------------------------------------------------ pack status
function renderStatus(msg) {
  const badge = $("run-state");
  const shown = S.paused && msg.state === "running" ? "paused" : msg.state;
  badge.textContent = shown;
  badge.className = "badge state-" + shown;
  if (S.cursorT === null)
    $("t-s").textContent = fmtTime(msg.t_s) + (S.duration ? " / " + fmtTime(S.duration) : "");
  const done = msg.state === "finished";
  $("progress-bar").style.width = (done ? 100 : 100 * (msg.progress || 0)).toFixed(1) + "%";
  $("n-events").textContent = String(S.events.length);
  const err = $("error");
  if (msg.error) {
    err.hidden = false;
    err.textContent = (msg.state === "stopped" ? "stopped: " : "error: ") + msg.error;
  } else err.hidden = true;
}

function renderHeadline(h) {
  h = h || {};
  $("hl-go").textContent = fmtDur(h.time_to_go_s);
  $("hl-cutoff").textContent = h.time_to_cutoff_s === 0 ? "tripped" : fmtDur(h.time_to_cutoff_s);
  $("hl-cutoff").classList.toggle("bad", isNum(h.time_to_cutoff_s) && h.time_to_cutoff_s < 60);
  $("hl-full").textContent = fmtDur(h.time_to_full_s);
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

// ------------------------------------------------------------------ pack schematic
function switchState(on, diodeA) {
  return on ? "on" : Math.abs(diodeA || 0) > 0.01 ? "diode" : "off";
}

// Two geometries: wide (charger left and load right of the batteries, on the bus) and compact
// for a phone (charger and load above the bus, narrower battery columns), so the drawing is
// scaled down little and its text stays readable at 390 px.
const COMPACT_PX = 560;
function buildSchematic() {
  const root = $("schematic");
  root.textContent = "";
  S.sch = null;
  const L = S.layout;
  if (!L || !L.batteries || !L.batteries.length) return;
  const n = L.batteries.length;
  const compact = (root.clientWidth || 1000) < COMPACT_PX;
  const top = compact && (L.charger || L.load);
  const colW = compact ? 104 : 150;
  const left = compact ? 12 : L.charger ? 150 : 40, right = compact ? 12 : L.load ? 150 : 40;
  const W = Math.max(left + n * colW + right, top ? 300 : 0);
  const busY = top ? 84 : 34, dy = busY - 34, H = 284 + dy;
  const bx = compact ? (W - n * colW) / 2 : left; // batteries centred under the bus
  const g = svg("svg", { viewBox: "0 0 " + W + " " + H, width: W, height: H, role: "img",
    "aria-label": "pack schematic", id: "pack-svg", "data-layout": compact ? "compact" : "wide" });
  g.append(svg("line", { x1: 12, y1: busY, x2: W - 12, y2: busY, class: "bus" }));
  // the bus's voltage: left above the bus, or (compact, with boxes above) between the boxes
  const busV = svg("text", top ? { x: W / 2, y: busY - 10, class: "lbl mid" }
    : { x: 16, y: busY - 10, class: "lbl" }, "bus");
  g.append(busV);
  const parts = { busV, bats: [], compact };
  const box = (what, cx, y0) => {
    g.append(svg("line", { x1: cx, y1: top ? y0 + 46 : busY, x2: cx, y2: top ? busY : y0, class: "wire" }));
    const r = svg("rect", { x: cx - 66, y: y0, width: 132, height: 46, rx: 6, class: "part",
      "data-part": what, "data-state": "off" });
    const txt = svg("text", { x: cx, y: y0 + 36, class: "val mid" }, "—");
    g.append(r, svg("text", { x: cx, y: y0 + 18, class: "lbl mid" }, what), txt);
    return { box: r, txt };
  };
  if (L.charger) parts.charger = box("charger", top ? 78 : 75, top ? 8 : 90);
  if (L.load) parts.load = box("load", top ? W - 78 : W - 75, top ? 8 : 90);
  L.batteries.forEach((b, i) => {
    const cx = bx + i * colW + colW / 2;
    const aux = b.role === "aux";
    g.append(svg("line", { x1: cx, y1: busY, x2: cx, y2: 150 + dy, class: "wire" }));
    const p = { name: b.name, fets: {} };
    if (aux) g.append(svg("text", { x: cx + 8, y: busY + 16, class: "lbl" }, "DC/DC ↓"));
    if (b.switch === "relay") {
      const r = svg("rect", { x: cx - 34, y: 70 + dy, width: 68, height: 50, rx: 4, class: "fet",
        "data-relay": b.name, "data-state": "open" });
      const blade = svg("line", { x1: cx - 14, y1: 104 + dy, x2: cx + 14, y2: 86 + dy, class: "blade" });
      g.append(r, blade, svg("text", { x: cx, y: 116 + dy, class: "lbl mid small" }, "relay"));
      p.relay = { box: r, blade, cx, dy };
    } else {
      for (const [k, y] of [["DSG", 62 + dy], ["CHG", 100 + dy]]) {
        const r = svg("rect", { x: cx - 30, y, width: 60, height: 30, rx: 4, class: "fet",
          "data-fet": b.name + ":" + k, "data-state": "off" });
        g.append(r, svg("text", { x: cx, y: y + 20, class: "lbl mid small" }, k));
        p.fets[k] = r;
      }
    }
    const half = compact ? 48 : 45;
    const cell = svg("rect", { x: cx - half, y: 150 + dy, width: 2 * half, height: 78, rx: 6,
      class: "bat", "data-battery": b.name });
    cell.style.stroke = COLORS[i % COLORS.length];
    const fill = svg("rect", { x: cx - half + 4, y: 224 + dy, width: 2 * half - 8, height: 0, class: "socfill" });
    g.append(cell, fill,
      svg("rect", { x: cx - 12, y: 144 + dy, width: 24, height: 6, class: "terminal" }),
      svg("text", { x: cx, y: 170 + dy, class: "lbl mid strong" }, b.name + (aux ? " (aux)" : "")));
    const v = svg("text", { x: cx, y: 190 + dy, class: "val mid" }, "—");
    const a = svg("text", { x: cx, y: 208 + dy, class: "val mid" }, "—");
    const jg = svg("g", { class: "join", "data-join": b.name, "data-state": "none" });
    g.append(v, a, jg);
    Object.assign(p, { fill, v, a, cx, dy, join: { group: jg, peak: null, dv: null } });
    parts.bats.push(p);
  });
  root.append(g);
  S.sch = parts;
  renderSchematic();
}

window.addEventListener("resize", () => {
  const compact = ($("schematic").clientWidth || 1000) < COMPACT_PX;
  if (S.sch && S.sch.compact !== compact) buildSchematic();
});

function setState(node, state) {
  node.setAttribute("data-state", state);
  node.setAttribute("class", node.getAttribute("class").replace(/ st-\w+/g, "") + " st-" + state);
}

function renderSchematic() {
  const P = S.sch, L = S.latest;
  if (!P || !L) return;
  P.busV.textContent = "bus " + fmt(L.bus_v, 2, "V");
  if (P.charger) {
    setState(P.charger.box, Math.abs(L.charger_a || 0) > 0.01 ? "on" : "off");
    P.charger.txt.textContent = fmt(L.charger_v, 1, "V") + " · " + fmt(L.charger_a, 1, "A");
  }
  if (P.load) {
    setState(P.load.box, (L.load_a || 0) > 0.01 ? "on" : "off");
    P.load.txt.textContent = fmt(L.load_a, 1, "A");
  }
  P.bats.forEach((p, i) => {
    const b = L.batteries[i];
    if (!b) return;
    if (p.relay) {
      const closed = b.chg_on > 0.5 && b.dsg_on > 0.5;
      setState(p.relay.box, closed ? "closed" : "open");
      p.relay.blade.setAttribute("y2", String((closed ? 104 : 86) + p.relay.dy));
    } else {
      setState(p.fets.DSG, switchState(b.dsg_on > 0.5, b.dsg_diode_a));
      setState(p.fets.CHG, switchState(b.chg_on > 0.5, b.chg_diode_a));
    }
    const soc = isNum(b.soc_core) ? Math.max(0, Math.min(1, b.soc_core)) : 0;
    p.fill.setAttribute("height", String(70 * soc));
    p.fill.setAttribute("y", String(224 + p.dy - 70 * soc));
    p.v.textContent = fmt(b.voltage_v, 2, "V");
    const cur = b.current_a;
    p.a.textContent = isNum(cur) ? (cur > 0.05 ? "↑ " : cur < -0.05 ? "↓ " : "") +
      Math.abs(cur).toFixed(1) + " A" : "—";
    renderJoin(p, joinOf(b.name));
  });
}

// The join planner (#28 §4) under a battery about to join (its path not fully closed while
// others hold the bus): the predicted peak through its switch once it closes, against the
// battery's limit in that direction, and the admissible voltage difference derived for it.
function joinOf(name) {
  const P = S.power;
  return P && P.joins ? P.joins.find((j) => j.name === name) || null : null;
}
function renderJoin(p, j) {
  const g = p.join;
  g.group.setAttribute("data-state", j ? (j.within ? "ok" : "over") : "none");
  // the texts exist only while there is a plan (an empty <text> would be a 0 px label)
  if (!j) { g.group.textContent = ""; g.peak = g.dv = null; return; }
  if (!g.peak) {
    g.peak = svg("text", { x: p.cx, y: 248 + p.dy, class: "lbl mid small" }, "");
    g.dv = svg("text", { x: p.cx, y: 264 + p.dy, class: "lbl mid small" }, "");
    g.group.append(g.peak, g.dv);
  }
  g.peak.dataset.peak = isNum(j.peak_a) ? String(j.peak_a) : "";
  g.peak.dataset.limit = isNum(j.limit_a) ? String(j.limit_a) : "";
  g.peak.textContent = "join " + (isNum(j.peak_a) ? Math.abs(j.peak_a).toFixed(1) : "?") +
    " A / " + (isNum(j.limit_a) ? j.limit_a.toFixed(0) : "∞") + " A";
  g.dv.dataset.dv = isNum(j.dv_v) ? String(j.dv_v) : "";
  g.dv.textContent = "ΔV " + fmt(j.dv_v, 2) + " (ok −" + fmt(j.dv_down_v, 1) + "…+" + fmt(j.dv_up_v, 1) + ")";
}

// ------------------------------------------------------------------ battery cards
function buildCards() {
  const root = $("batteries");
  root.textContent = "";
  S.cards = S.names.map((name, i) => {
    const card = el("div", "panel bat");
    card.dataset.battery = name;
    const h = el("h3");
    const sw = el("span", "swatch");
    sw.style.background = COLORS[i % COLORS.length];
    h.append(sw, el("span", null, name));
    const nums = el("div", "nums");
    const cells = {};
    let socSource = null;
    for (const [k, label] of [["voltage_v", "V"], ["current_a", "A"], ["soc", "SOC"],
      ["temp_c", "°C"]]) {
      const n = el("div", "num");
      cells[k] = el("div", "v", "—");
      const lab = el("div", "k", label);
      if (k === "soc") { socSource = lab; lab.classList.add("socsrc"); }
      n.append(cells[k], lab);
      nums.append(n);
    }
    const socbar = el("div", "socbar");
    const socfill = el("div");
    socbar.append(socfill);
    const plot = el("div", "cellplot");
    const axis = el("div", "cellaxis");
    const bars = el("div", "cellbars");
    plot.append(axis, bars);
    const cellsLine = el("div", "line");
    const switches = el("div", "line");
    const prot = el("div", "line");
    const extra = el("div", "line");
    const details = el("details");
    details.append(el("summary", null, "all controller status"));
    const table = el("table");
    details.append(table);
    card.append(h, nums, socbar, plot, cellsLine, switches, prot, extra, details);
    root.append(card);
    return { cells, socfill, bars, axis, cellsLine, switches, prot, extra, table, details, socSource };
  });
}

function pill(label, on, diode) {
  const p = el("span", "sw " + (on ? "on" : diode ? "diode" : "off"));
  p.textContent = label + " " + (on ? "on" : diode ? "diode" : "off");
  return p;
}

// Per-cell (series group) voltage bars, diyBMS style: the lowest and highest group marked,
// a group the equalizer is moving charge in/out of marked as balancing. The bars stand on an
// absolute axis, the cell set's voltage window times the group's cells in series (layout
// group_v_min..group_v_max, widened to any group outside it), with its voltages ticked on the left: a 49 mV spread looks like 49 mV of a
// 1.2 V window. Each bar's voltage is written above it, horizontally, on the card's white (never
// on a coloured fill); where the bars are too narrow for that, in the tooltip only.
const BAR_LABEL_MIN_PX = 30;
function cellAxis(i, vals) {
  const own = S.layout && S.layout.batteries[i] ? S.layout.batteries[i] : {};
  let lo = own.group_v_min, hi = own.group_v_max;
  const vlo = Math.min(...vals), vhi = Math.max(...vals);
  if (!isNum(lo) || !isNum(hi) || hi <= lo) { // unknown cell set: a round window around the cells
    lo = Math.floor(vlo * 10 - 1) / 10;
    hi = Math.ceil(vhi * 10 + 1) / 10;
  }
  return { lo: Math.min(lo, Math.floor(vlo * 20) / 20), hi: Math.max(hi, Math.ceil(vhi * 20) / 20) };
}

function renderAxis(c, ax) {
  const key = ax.lo + ":" + ax.hi;
  if (c.axis.dataset.key === key) return;
  c.axis.dataset.key = key;
  c.axis.textContent = "";
  for (const f of [0, 0.5, 1]) {
    const v = ax.lo + f * (ax.hi - ax.lo);
    const t = el("span", "tick", v.toFixed(f === 0.5 ? 2 : 1));
    t.style.bottom = (100 * f).toFixed(1) + "%";
    c.axis.append(t);
  }
  c.axis.title = "group voltage (V): the cell set's window " + ax.lo.toFixed(2) + "–" + ax.hi.toFixed(2) + " V";
  c.bars.dataset.axisLo = String(ax.lo);
  c.bars.dataset.axisHi = String(ax.hi);
}

function renderCellBars(c, b, i) {
  // group_v is padded with NaN up to the pack's largest battery: show this one's groups only
  const own = S.layout && S.layout.batteries[i] ? S.layout.batteries[i].series_groups : null;
  let gv = (b.group_v || []).map((v) => (isNum(v) ? v : null));
  if (isNum(own)) gv = gv.slice(0, own);
  else while (gv.length && gv[gv.length - 1] === null) gv.pop();
  const vals = gv.filter((v) => v !== null);
  const st = b.status || {};
  if (c.bars.childElementCount !== gv.length) {
    c.bars.textContent = "";
    gv.forEach((_, k) => {
      const bar = el("div", "cellbar");
      bar.dataset.cell = String(k);
      const fill = el("div", "fill");
      const lab = el("span", "lab");
      bar.append(fill, lab, el("span", "no", String(k + 1)));
      c.bars.append(bar);
    });
  }
  const barW = gv.length ? (c.bars.clientWidth - 2 * (gv.length - 1)) / gv.length : 0;
  c.bars.classList.toggle("dense", barW > 0 && barW < BAR_LABEL_MIN_PX);
  c.bars.classList.toggle("sparse-no", gv.length > 16);
  if (!vals.length) return;
  const ax = cellAxis(i, vals);
  renderAxis(c, ax);
  const lo = Math.min(...vals), hi = Math.max(...vals);
  // a spread under 0.1 mV has no lowest or highest group worth pointing at
  const marked = vals.length > 1 && hi - lo >= 1e-4;
  const iLo = marked ? gv.indexOf(lo) : -1, iHi = marked ? gv.indexOf(hi) : -1;
  [...c.bars.children].forEach((bar, k) => {
    const v = gv[k];
    const eq = st["eq_i_a_g" + k];
    const bal = isNum(eq) && Math.abs(eq) > BALANCING_A;
    bar.classList.toggle("min", k === iLo);
    bar.classList.toggle("max", k === iHi);
    bar.classList.toggle("balancing", bal);
    bar.dataset.v = v === null ? "" : v.toFixed(4);
    bar.title = "group " + (k + 1) + ": " + fmt(v, 3, "V") + (bal ? " · balancing " +
      (eq * 1000).toFixed(0) + " mA" : "");
    const f = v === null ? 0 : Math.max(0, Math.min(1, (v - ax.lo) / (ax.hi - ax.lo)));
    bar.children[0].style.height = (100 * f).toFixed(2) + "%";
    bar.children[1].textContent = v === null ? "—" : v.toFixed(3);
  });
}

// What the BMS measured (status bms_*) is the card's number; the plant's truth is shown
// beside it only when the two disagree (a failed, frozen or stale sensor), so a card never
// shows a healthy 20 °C while the BMS reads NaN (#17 §1).
const MEASURED = { voltage_v: ["bms_v", 0.05], current_a: ["bms_a", 0.2],
  temp_c: ["bms_degc", 1.0] };
// The SOC a card shows is the one the core uses (contract/soc_source.py): the observer's
// estimate while it is trusted, its fallback (the coulomb counter) otherwise, the battery's own
// report without an estimator; the card says which, and a fallback is marked.
const SOC_SOURCE_SHORT = { observer: "observer", fallback: "fallback: coulomb counter",
  counter: "coulomb counter", battery: "battery's own" };
function showSoc(c, b) {
  const cell = c.cells.soc;
  const v = b.soc_core;
  cell.classList.remove("sensorbad");
  cell.textContent = isNum(v) ? (100 * v).toFixed(1) + "%" : "no reading";
  cell.dataset.v = isNum(v) ? String(v) : "";
  cell.title = "the SOC the BMS uses: " + (b.soc_source_label || "—");
  if (isNum(v) && isNum(b.soc) && Math.abs(v - b.soc) > 0.02)
    cell.append(el("small", "plant", " plant " + (100 * b.soc).toFixed(1) + "%"));
  const tag = c.socSource;
  tag.textContent = "SOC · " + (SOC_SOURCE_SHORT[b.soc_source] || "—");
  tag.title = b.soc_source_label || "";
  tag.dataset.source = b.soc_source || "";
  tag.classList.toggle("fallback", b.soc_source === "fallback");
}
function showMeasured(cell, st, b, key, text) {
  const [mk, tol] = MEASURED[key];
  cell.classList.remove("sensorbad");
  cell.title = "";
  if (!(mk in st)) { cell.textContent = text(b[key]); return; }
  const m = st[mk];
  if (!isNum(m)) {
    cell.textContent = "no reading";
    cell.classList.add("sensorbad");
    cell.title = "the BMS reads no valid value; the plant has " + text(b[key]);
    return;
  }
  cell.textContent = text(m);
  if (isNum(b[key]) && Math.abs(m - b[key]) > tol) {
    cell.classList.add("sensorbad");
    cell.append(el("small", "plant", " plant " + text(b[key])));
    cell.title = "what the BMS measured; the plant's true value differs";
  }
}

function renderCards() {
  const L = S.latest;
  if (!L) return;
  L.batteries.forEach((b, i) => {
    const c = S.cards[i];
    if (!c) return;
    const stm = b.status || {};
    showMeasured(c.cells.voltage_v, stm, b, "voltage_v", (x) => fmt(x, 2));
    showMeasured(c.cells.current_a, stm, b, "current_a", (x) => fmt(x, 2));
    showSoc(c, b);
    showMeasured(c.cells.temp_c, stm, b, "temp_c", (x) => fmt(x, 1));
    c.socfill.style.width = isNum(b.soc_core) ? Math.max(0, Math.min(100, 100 * b.soc_core)) + "%" : "0";
    renderCellBars(c, b, i);
    c.cellsLine.textContent = "";
    const spread = isNum(b.max_cell_v) && isNum(b.min_cell_v) ?
      " (spread " + (1000 * (b.max_cell_v - b.min_cell_v)).toFixed(0) + " mV)" : "";
    c.cellsLine.append(el("span", "k", "cells"),
      el("span", null, fmt(b.min_cell_v, 3) + " … " + fmt(b.max_cell_v, 3) + " V" + spread),
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
    if ("chg_stage" in st) bits.push(["charging", stageText(st.chg_stage)]);
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

// The staged-charging stages (docs/staged_charging.md) in words: "S40" alone means nothing to
// someone who has not read the spec.
const STAGE_MEANING = {
  idle: "not docked", rest: "docked, resting before measuring",
  hold: "docked, no battery can be charged now",
  S20: "S20: charging the lowest battery up to the next",
  S30: "S30: charging two voltage levels together",
  S40: "S40: all level, charging in bounded steps",
  top_off: "top-off at constant voltage", complete: "charge complete", fault: "charging fault",
};
function stageText(v) {
  return v === null || v === undefined ? "—" : STAGE_MEANING[v] || String(v);
}

// ------------------------------------------------------------------ events + metrics
// "important" (the default): warnings and worse, plus the routine events that change what the
// pack is doing (mode, stage, joins); the routine balancing updates, which are most of a
// run's events, only under "all".
function passes(e) {
  const f = $("filter-severity").value;
  if (f === "important") {
    if ((SEVERITY[e.severity] || 0) < 1 && !INFO_KINDS.test(e.kind)) return false;
  } else if ((SEVERITY[e.severity] || 0) < (SEVERITY[f] || 0)) return false;
  const fb = $("filter-battery").value;
  if (fb === "-" && e.battery_name) return false;
  if (fb !== "*" && fb !== "-" && e.battery_name !== fb) return false;
  if (S.cursorT !== null && isNum(e.t_s) && e.t_s > S.cursorT) return false;
  return true;
}

function eventRow(e) {
  const tr = el("tr");
  const cls = isBad(e) ? "kind-bad" : e.severity === "warning" ? "kind-warn"
    : INFO_KINDS.test(e.kind) ? "kind-info" : "kind-other";
  tr.dataset.severity = e.severity;
  tr.append(el("td", null, fmtTime(e.t_s)), el("td", cls, e.kind),
    el("td", null, e.battery_name || ""), el("td", null, e.message || ""));
  return tr;
}

function addEvents(evs) {
  const tbody = document.querySelector("#events tbody");
  for (const e of evs) {
    S.events.push(e);
    if (passes(e)) tbody.insertBefore(eventRow(e), tbody.firstChild); // newest on top
  }
  while (tbody.rows.length > MAX_EVENT_ROWS) tbody.deleteRow(tbody.rows.length - 1);
  countEvents();
}

function renderEvents() {
  const tbody = document.querySelector("#events tbody");
  tbody.textContent = "";
  const shown = [];
  for (let k = S.events.length - 1; k >= 0 && shown.length < MAX_EVENT_ROWS; k--)
    if (passes(S.events[k])) shown.push(eventRow(S.events[k]));
  tbody.append(...shown);
  countEvents();
}

function countEvents() {
  const n = document.querySelector("#events tbody").rows.length;
  document.body.dataset.eventsShown = String(n);
  $("events-count").textContent = "(" + (n === S.events.length ? n : n + " of " + S.events.length) +
    ", newest first)";
}

$("filter-severity").addEventListener("change", renderEvents);
$("filter-battery").addEventListener("change", renderEvents);

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

  // the scrubbed moment of a recording
  if (S.cursorT !== null && S.cursorT >= t0 && S.cursorT <= t1) {
    g.strokeStyle = "#1d2430";
    g.setLineDash([4, 3]);
    const x = Math.round(X(S.cursorT)) + 0.5;
    g.beginPath(); g.moveTo(x, pad.t); g.lineTo(x, pad.t + ph); g.stroke();
    g.setLineDash([]);
  }

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
