// dpmhw operator page: polls /status and /frame.png, builds the setting controls from the
// API's own schema, and sends changes with the bearer token kept in sessionStorage only.
"use strict";

const STATUS_EVERY_MS = 500;
const FRAME_EVERY_MS = 250;          // a few Hz: enough to watch, cheap for the API process
const HISTORY = 240;                 // samples kept for the rolling plots (2 min at 2 Hz)
const TOKEN_KEY = "dpmhw-token";

const $ = (id) => document.getElementById(id);
const history = { fps: [], p50: [], p99: [], reg: [] };
let settingsSchema = null;           // SettingsModel from /openapi.json
let lastSettings = null;
let frameUrl = null;

// ---- token: entered once per browser session, sent only in the Authorization header ----------
function token() { return sessionStorage.getItem(TOKEN_KEY) || ""; }
function showTokenState() {
  $("token-state").textContent = token() ? "token set for this browser session" : "no token: controls will be refused";
  $("token").value = "";
}
$("token-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  const value = $("token").value.trim();
  if (value) sessionStorage.setItem(TOKEN_KEY, value); else sessionStorage.removeItem(TOKEN_KEY);
  showTokenState();
});

function say(text, ok) {
  const m = $("message");
  m.textContent = text;
  m.className = ok ? "ok" : "error";
}

// The API's reason, whatever shape the error body has (a string, or pydantic's list of errors).
function reasonOf(body, response) {
  const d = body && body.detail !== undefined ? body.detail : body && body.message;
  if (Array.isArray(d)) return d.map((e) => `${(e.loc || []).filter((p) => p !== "body").join(".")}: ${e.msg}`).join("; ");
  if (d) return String(d);
  return `${response.status} ${response.statusText}`;
}

async function send(method, path, body) {
  const headers = { "Accept": "application/json" };
  if (token()) headers["Authorization"] = "Bearer " + token();
  if (body !== undefined) headers["Content-Type"] = "application/json";
  let response, data = null;
  try {
    response = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    data = await response.json().catch(() => null);
  } catch (err) {
    say(`rejected: the service did not answer (${err.message})`, false);
    return null;
  }
  if (!response.ok) {
    say(`rejected (${response.status}): ${reasonOf(data, response)}`, false);
    if (response.status === 401) { sessionStorage.removeItem(TOKEN_KEY); showTokenState(); }
    return null;
  }
  return data;
}

// ---- actions -------------------------------------------------------------------------------
// The blank goes first to the operator port (served by the session process itself, so it answers
// while this page's service is flooded or stopped), then, if that did not answer, to the service.
let operatorPort = null;             // from /status, kept once known
async function blankAtOperatorPort() {
  if (!operatorPort || !token()) return null;
  const stop = new AbortController();
  const timer = setTimeout(() => stop.abort(), 2000);
  try {
    const response = await fetch(`${location.protocol}//${location.hostname}:${operatorPort}/session/blank`,
      { method: "POST", headers: { "Authorization": "Bearer " + token() }, signal: stop.signal });
    const data = await response.json().catch(() => null);
    return response.ok ? data : null;
  } catch (err) {
    return null;
  } finally {
    clearTimeout(timer);
  }
}

for (const [id, path] of [["blank", "/session/blank"], ["resume", "/session/resume"], ["reset-history", "/session/reset-history"]]) {
  $(id).addEventListener("click", async () => {
    const r = (id === "blank" && await blankAtOperatorPort()) || await send("POST", path);
    if (r) say(`${r.message} (state: ${r.state})`, r.ok);
    pollStatus();
  });
}

// ---- settings controls, built from the SettingsModel schema --------------------------------
function resolve(schema) {
  // `x: T | None` appears as anyOf [T, null]; take the non-null branch.
  if (schema.anyOf) return Object.assign({}, schema, schema.anyOf.find((s) => s.type !== "null"));
  return schema;
}

// A slider over a number field's bounds in round steps (a power of ten, about 100 positions): its
// ends are the first and last multiples of the step within the bounds (exclusive ones excluded).
function sliderRange(s) {
  const lo = s.minimum ?? s.exclusiveMinimum ?? 0, hi = s.maximum ?? s.exclusiveMaximum;
  const step = 10 ** Math.round(Math.log10((hi - lo) / 100));
  let first = Math.ceil(lo / step) * step, last = Math.floor(hi / step) * step;
  if (s.minimum === undefined && first <= lo) first += step;
  if (s.maximum === undefined && last >= hi) last -= step;
  return [first, last, step];
}

function labelText(name) { return name.replace(/_/g, " "); }

async function applySetting(name, value) {
  const r = await send("PATCH", "/settings", { [name]: value });
  if (r) { say(`${labelText(name)} = ${JSON.stringify(r[name])} accepted (applied on the next frame)`, true); lastSettings = r; }
  renderSettingValues(lastSettings);
}

function buildControls(schema, values) {
  const box = $("settings");
  box.textContent = "";
  for (const [name, raw] of Object.entries(schema.properties || {})) {
    const s = resolve(raw);
    const row = document.createElement("div");
    row.className = "setting";
    const label = document.createElement("label");
    label.htmlFor = "set-" + name;
    label.textContent = labelText(name);
    if (s.description) label.title = s.description;
    row.appendChild(label);
    let input;
    if (s.enum) {
      input = document.createElement("select");
      for (const v of s.enum) { const o = document.createElement("option"); o.value = v; o.textContent = v; input.appendChild(o); }
      input.addEventListener("change", () => applySetting(name, input.value));
    } else if (s.type === "boolean") {
      input = document.createElement("input");
      input.type = "checkbox";
      input.addEventListener("change", () => applySetting(name, input.checked));
    } else if (s.type === "number" && (s.maximum !== undefined || s.exclusiveMaximum !== undefined)) {
      input = document.createElement("input");
      input.type = "range";
      const [min, max, step] = sliderRange(s);
      input.min = min; input.max = max; input.step = step;
      const out = document.createElement("output");
      out.id = "val-" + name;
      input.addEventListener("input", () => { out.textContent = Number(input.value).toFixed(2); });
      input.addEventListener("change", () => applySetting(name, Number(input.value)));
      row.appendChild(input); row.appendChild(out);
    } else if (s.type === "integer" || s.type === "number") {
      input = document.createElement("input");
      input.type = "number";
      if (s.type === "integer") input.step = 1; else input.step = "any";
      if (s.minimum !== undefined) input.min = s.minimum;
      if (s.maximum !== undefined) input.max = s.maximum;
      input.addEventListener("change", () => { if (input.value !== "") applySetting(name, Number(input.value)); });
    } else {
      input = document.createElement("input");
      input.type = "text";
      input.addEventListener("change", () => applySetting(name, input.value));
    }
    input.id = "set-" + name;
    input.dataset.setting = name;
    if (!row.contains(input)) row.appendChild(input);
    if (s.description) { const d = document.createElement("small"); d.textContent = s.description; row.appendChild(d); }
    box.appendChild(row);
  }
  renderSettingValues(values);
}

function renderSettingValues(values) {
  if (!values) return;
  for (const input of document.querySelectorAll("[data-setting]")) {
    if (document.activeElement === input) continue;   // don't fight the operator's hand
    const v = values[input.dataset.setting];
    if (v === undefined) continue;
    if (input.type === "checkbox") input.checked = !!v; else input.value = v;
    const out = $("val-" + input.dataset.setting);
    if (out) out.textContent = Number(v).toFixed(2);
  }
}

async function loadSettings() {
  try {
    const [api, values] = await Promise.all([fetch("/openapi.json").then((r) => r.json()), fetch("/settings").then((r) => r.json())]);
    settingsSchema = api.components.schemas.SettingsModel;
    lastSettings = values;
    buildControls(settingsSchema, values);
  } catch (err) {
    say(`could not read the settings: ${err.message}`, false);
    setTimeout(loadSettings, 2000);
  }
}

// ---- status --------------------------------------------------------------------------------
const STATE_WORDS = {
  running: "Projecting",
  fault: "Dark: fault",
  starting: "Starting (dark)",
  stopped: "Stopped (dark)",
};

// "blanked" is every deliberate dark spell; its words say whose: the operator's blank, a cause
// such as lost tracking, the wait for an explicit resume, or the hold-off after a cause cleared
// (the session resumes by itself when it ends).
function stateWords(st) {
  const state = st.state || "unknown";
  if (state !== "blanked") return STATE_WORDS[state] || state;
  const names = (st.causes || []).map((c) => c.name);
  if (names.includes("operator")) return "Dark: operator blank";
  if (names.includes("tracking")) return "Dark: tracking lost";
  if (names.length) return "Dark: " + names.join(", ");
  if ((st.reason || "").includes("explicit resume")) return "Dark: waiting for resume";
  const cleared = /^(\S+) cleared/.exec(st.reason || "");  // safety.py: "<cause> cleared … ago; holding off …"
  if (cleared && cleared[1] !== "operator") return `Dark: ${cleared[1]} hold-off (resumes by itself)`;
  return "Dark: hold-off (resumes by itself)";
}

function push(series, v) { series.push(v === undefined || v === null ? NaN : Number(v)); if (series.length > HISTORY) series.shift(); }
function fmt(v, digits = 1) { return v === undefined || v === null || Number.isNaN(Number(v)) ? "–" : Number(v).toFixed(digits); }

function renderStatus(st) {
  const state = st.state || "unknown";
  $("state-box").className = "state " + state;
  $("state").textContent = stateWords(st);
  $("reason").textContent = st.reason ? "— " + st.reason : (st.output_on ? "— output on" : "");
  const operator = st.api && st.api.operator;
  if (operator && operator.url) {  // kept when the page later gets no answer: that is when it is needed
    operatorPort = new URL(operator.url).port;
    $("operator-port").textContent = `Blank goes to the operator port first (${operator.url}), which answers ` +
      `while this page's service is flooded; GET ${operator.url}/status reports there too.`;
  }
  const causes = $("causes");
  causes.textContent = "";
  for (const c of st.causes || []) {
    const li = document.createElement("li");
    li.className = c.kind;
    li.textContent = `${c.name} (${c.kind}, for ${fmt(c.since_s, 1)} s): ${c.reason}`;
    causes.appendChild(li);
  }
  const lat = st.latency_ms || {};
  const reg = st.registration_px && typeof st.registration_px === "object" ? st.registration_px.p50 : st.registration_px;
  push(history.fps, st.fps); push(history.p50, lat.p50); push(history.p99, lat.p99); push(history.reg, reg);
  $("v-fps").textContent = `${fmt(st.fps)} presented, ${fmt(st.render_fps)} rendered`;
  $("v-lat").textContent = `${fmt(lat.p50, 2)} / ${fmt(lat.p99, 2)}`;
  $("v-reg").textContent = reg === undefined ? "(not measured by this session)" : fmt(reg, 2);
  plot($("plot-fps"), [[history.fps, "#2b7bb9"]], "fps");
  plot($("plot-latency"), [[history.p50, "#2b7bb9"], [history.p99, "#d9534f"]], "ms");
  plot($("plot-registration"), [[history.reg, "#5a9a3a"]], "px");

  const tbody = document.querySelector("#stages tbody");
  tbody.textContent = "";
  for (const [name, s] of Object.entries(st.stages_ms || {})) {
    const tr = document.createElement("tr");
    for (const v of [name, fmt(s.mean_ms, 3), fmt(s.p50_ms, 3), fmt(s.p95_ms, 3), fmt(s.p99_ms, 3)]) {
      const td = document.createElement("td"); td.textContent = v; tr.appendChild(td);
    }
    tbody.appendChild(tr);
  }
  renderGovernor(st.governor);
  renderDevices(st.devices || {});
  $("counters").textContent = Object.entries(st.counters || {}).map(([k, v]) => `${k.replace(/_/g, " ")}: ${v}`).join(" · ");
  const output = st.output_size ? `, ${st.output_size.join("×")} output` : "";
  const shaded = st.render_size && st.output_size && st.render_size.join() !== st.output_size.join()
    ? ` (shaded at ${st.render_size.join("×")})` : "";
  $("frame-info").textContent = `frame ${st.frame_number ?? "–"}${output}${shaded}`;
  if (st.settings && !document.activeElement?.dataset?.setting) { lastSettings = st.settings; renderSettingValues(st.settings); }
}

// what the quality governor chose (its rung and the settings it set) and why
function renderGovernor(g) {
  const box = $("governor");
  box.textContent = "";
  if (!g) return;
  const shown = {
    state: g.enabled ? g.rung : "off (settings as configured and set)",
    target_fps: `${fmt(g.target_fps, 1)} (${g.target_from})`,
    measured_fps: fmt(g.measured_fps, 1),
    frame_p90_ms: `${fmt(g.frame_p90_ms, 1)} (budget ${fmt(g.latency_budget_ms, 0)})`,
    why: g.reason,
    chose: Object.entries(g.choices || {}).map(([k, v]) => `${k.replace(/_/g, " ")} ${v}`).join(", "),
    pinned_by_operator: g.pinned,
    changes: g.changes,
  };
  box.appendChild(kv(shown));
}

function kv(obj) {
  const dl = document.createElement("dl");
  for (const [k, v] of Object.entries(obj)) {
    if (v === null || v === "" || typeof v === "object" && !Array.isArray(v)) continue;
    const dt = document.createElement("dt"); dt.textContent = k.replace(/_/g, " ");
    const dd = document.createElement("dd");
    dd.textContent = Array.isArray(v) ? (v.length ? v.join(", ") : "none") : typeof v === "number" ? String(Math.round(v * 1000) / 1000) : String(v);
    if ((k === "stale" || k === "malformed" && v > 0 || k === "parked" || k === "standby" || k === "hardware_faults" || k === "error") && v && (!Array.isArray(v) || v.length)) dd.className = "bad";
    dl.appendChild(dt); dl.appendChild(dd);
  }
  return dl;
}

let trackerSeen = null;  // {frames, t}: the tracker's rate is the change of its frame count between polls

function renderDevices(devices) {
  const box = $("devices");
  box.textContent = "";
  const tr = devices.tracker;
  if (tr && typeof tr.frames === "number") {
    const now = performance.now();
    if (trackerSeen && now > trackerSeen.t && tr.frames >= trackerSeen.frames) {
      tr.rate_hz = (tr.frames - trackerSeen.frames) / ((now - trackerSeen.t) / 1000);
    }
    trackerSeen = { frames: tr.frames, t: now };
  }
  for (const [name, d] of Object.entries(devices)) {
    const div = document.createElement("div");
    div.className = "device";
    const h = document.createElement("h3"); h.textContent = name.replace(/_/g, " ");
    div.appendChild(h);
    div.appendChild(d && typeof d === "object" ? kv(d) : Object.assign(document.createElement("p"), { textContent: String(d) }));
    box.appendChild(div);
  }
}

function plot(canvas, series, unit) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width, h = canvas.height, left = 34, bottom = 12;
  ctx.clearRect(0, 0, w, h);
  const all = series.flatMap(([s]) => s).filter((v) => Number.isFinite(v));
  let hi = all.length ? Math.max(...all) : 1;
  hi = hi > 0 ? hi * 1.1 : 1;
  ctx.strokeStyle = "#bbb"; ctx.fillStyle = "#555"; ctx.font = "10px sans-serif"; ctx.lineWidth = 1;
  ctx.beginPath(); ctx.moveTo(left, 2); ctx.lineTo(left, h - bottom); ctx.lineTo(w, h - bottom); ctx.stroke();
  ctx.fillText(hi >= 100 ? hi.toFixed(0) : hi.toPrecision(2), 2, 10);
  ctx.fillText("0", 2, h - bottom);
  ctx.fillText(unit, 2, (h - bottom) / 2 + 4);
  ctx.fillText(`−${Math.round(HISTORY * STATUS_EVERY_MS / 1000)} s`, left, h - 1);
  ctx.fillText("now", w - 20, h - 1);
  for (const [s, color] of series) {
    ctx.strokeStyle = color; ctx.lineWidth = 1.5; ctx.beginPath();
    let pen = false;
    s.forEach((v, i) => {
      if (!Number.isFinite(v)) { pen = false; return; }
      const x = left + (w - left) * (i + HISTORY - s.length) / (HISTORY - 1);
      const y = (h - bottom) - (h - bottom - 2) * v / hi;
      if (pen) ctx.lineTo(x, y); else ctx.moveTo(x, y);
      pen = true;
    });
    ctx.stroke();
  }
}

let statusBusy = false;
async function pollStatus() {
  if (statusBusy) return;
  statusBusy = true;
  try {
    const r = await fetch("/status", { cache: "no-store" });
    const st = await r.json();
    if (!r.ok) throw new Error(st.detail || r.statusText);
    renderStatus(st);
  } catch (err) {
    $("state-box").className = "state unknown";
    $("state").textContent = "No answer from the session";
    $("reason").textContent = "— " + err.message;
  } finally {
    statusBusy = false;
  }
}

let frameBusy = false;
async function pollFrame() {
  if (frameBusy) return;
  frameBusy = true;
  try {
    const r = await fetch("/frame.png", { cache: "no-store" });
    if (r.ok) {
      const blob = await r.blob();
      const url = URL.createObjectURL(blob);
      const img = $("frame");
      img.onload = () => { if (frameUrl) URL.revokeObjectURL(frameUrl); frameUrl = url; };
      img.src = url;
      img.dataset.frameNumber = r.headers.get("X-Frame-Number") || "";
      img.dataset.blank = r.headers.get("X-Frame-Blank") || "";
      img.className = img.dataset.blank === "true" ? "dark" : "";
    }
  } catch (err) { /* the status line already says the session is unreachable */ }
  finally { frameBusy = false; }
}

showTokenState();
loadSettings();
pollStatus();
pollFrame();
setInterval(pollStatus, STATUS_EVERY_MS);
setInterval(pollFrame, FRAME_EVERY_MS);
