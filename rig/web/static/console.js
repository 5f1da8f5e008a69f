// The console: the live trial over the websocket, a start from the library, the devices' state.
"use strict";
rigHeader("/");
const live = window.rigLive = {draws: 0, messages: 0, delays: [], drawTimes: [], drawMs: []};
let limits = null, cfgLimits = null;
let buf = {t: [], f: [], x: [], k: []};
let pending = {t: [], f: [], x: [], k: []};
let steps = [];
let stepsDirty = false;
const STEP_COLOURS = {ramp: "rgba(37,99,235,0.07)", hold: "rgba(22,163,74,0.08)", return: "rgba(217,119,6,0.08)",
  tare: "rgba(107,114,128,0.08)"};

// the force and position axes follow the data (a limit far above would flatten it); a limit
// beyond the range is said in words at the top instead of drawn
let ranges = {y: null, y2: null};
function grow(axis, values, floor) {
  let lo = Infinity, hi = -Infinity;
  for (const v of values) if (v !== null) { if (v < lo) lo = v; if (v > hi) hi = v; }
  if (!isFinite(lo)) return false;
  const r = ranges[axis];
  if (r && lo >= r[0] && hi <= r[1]) return false;
  const span = Math.max(hi - lo, floor);
  ranges[axis] = [Math.min(lo, r ? r[0] : lo) - 0.15 * span, Math.max(hi, r ? r[1] : hi) + 0.3 * span];
  return true;
}
function limitNotes(lim) {
  const notes = [];
  const [fr, xr] = [ranges.y, ranges.y2];
  if (lim.max_force_N) notes.push({xref: "paper", x: 1, yref: "y domain", y: 1, showarrow: false, xanchor: "right", yanchor: "top",
    text: `force limit ${lim.max_force_N} N` + (fr && lim.max_force_N > fr[1] ? " (above)" : ""), font: {size: 10, color: "#dc2626"}});
  if (lim.travel_mm) notes.push({xref: "paper", x: 1, yref: "y2 domain", y: 1, showarrow: false, xanchor: "right", yanchor: "top",
    text: `travel [${lim.travel_mm[0]}, ${lim.travel_mm[1]}] mm` + (xr && (lim.travel_mm[1] > xr[1] || lim.travel_mm[0] < xr[0]) ? " (beyond)" : ""),
    font: {size: 10, color: "#dc2626"}});
  return notes;
}
function tsLayout() {
  const lim = limits || cfgLimits || {};
  const shapes = [];
  if (lim.max_force_N) shapes.push({type: "line", xref: "paper", x0: 0, x1: 1, yref: "y", y0: lim.max_force_N,
    y1: lim.max_force_N, line: {color: "#dc2626", dash: "dash", width: 1.5}});
  for (const v of (lim.travel_mm || [])) shapes.push({type: "line", xref: "paper", x0: 0, x1: 1, yref: "y2", y0: v, y1: v,
    line: {color: "#dc2626", dash: "dot", width: 1}});
  steps.forEach((s, i) => {
    const t1 = i + 1 < steps.length ? steps[i + 1][0] : (buf.t.length ? buf.t[buf.t.length - 1] : s[0]);
    shapes.push({type: "rect", xref: "x", yref: "paper", x0: s[0], x1: t1, y0: 0, y1: 1, line: {width: 0},
      fillcolor: STEP_COLOURS[s[2]] || "rgba(0,0,0,0.04)", layer: "below"});
  });
  return {margin: {l: 60, r: 10, t: 20, b: 36}, showlegend: false, shapes, annotations: limitNotes(lim),
    xaxis: {title: {text: "t (s)"}, anchor: "y3"},
    yaxis: {domain: [0.68, 1], title: {text: "force (N)"}, range: ranges.y, autorange: !ranges.y},
    yaxis2: {domain: [0.35, 0.65], title: {text: "position (mm)"}, range: ranges.y2, autorange: !ranges.y2},
    yaxis3: {domain: [0, 0.32], title: {text: "k (N/m)"}}};
}
function fxLayout() {
  const lim = limits || cfgLimits || {};
  return {margin: {l: 60, r: 10, t: 10, b: 36}, showlegend: false,
    xaxis: {title: {text: "position (mm)"}}, yaxis: {title: {text: "force (N)"}, range: ranges.y, autorange: !ranges.y},
    shapes: lim.max_force_N ? [{type: "line", xref: "paper", x0: 0, x1: 1, y0: lim.max_force_N, y1: lim.max_force_N,
      line: {color: "#dc2626", dash: "dash", width: 1.5}}] : []};
}
function resetPlots() {
  const cfg = {displaylogo: false, responsive: true};
  Plotly.newPlot("ts", [
    {x: buf.t.slice(), y: buf.f.slice(), mode: "lines", name: "force", line: {color: "#dc2626"}, yaxis: "y"},
    {x: buf.t.slice(), y: buf.x.slice(), mode: "lines", name: "position", line: {color: "#2563eb"}, yaxis: "y2"},
    {x: buf.t.slice(), y: buf.k.slice(), mode: "lines", name: "stiffness", line: {color: "#16a34a"}, yaxis: "y3"}],
    tsLayout(), cfg);
  Plotly.newPlot("fx", [{x: buf.x.slice(), y: buf.f.slice(), mode: "lines", line: {color: "#7c3aed"}}], fxLayout(), cfg);
}
function take(points) {
  for (const p of points) {
    for (const [key, i] of [["t", 0], ["f", 1], ["x", 2], ["k", 3]]) { buf[key].push(p[i]); pending[key].push(p[i]); }
  }
}
function draw() {
  if (!pending.t.length) return;
  const p = pending;
  pending = {t: [], f: [], x: [], k: []};
  const regrown = grow("y", p.f, 0.5) | grow("y2", p.x, 1);
  Plotly.extendTraces("ts", {x: [p.t, p.t, p.t], y: [p.f, p.x, p.k]}, [0, 1, 2]);
  Plotly.extendTraces("fx", {x: [p.x], y: [p.f]}, [0]);
  if (stepsDirty || regrown) {
    stepsDirty = false;
    const l = tsLayout();
    Plotly.relayout("ts", {shapes: l.shapes, annotations: l.annotations, "yaxis.range": ranges.y, "yaxis2.range": ranges.y2});
    if (regrown) Plotly.relayout("fx", {"yaxis.range": ranges.y});
  }
  live.draws += 1;
  live.drawTimes.push(performance.now());
  if (live.drawTimes.length > 400) live.drawTimes.splice(0, 200);
}
// 25 draws a second; a draw that takes long (a loaded machine: 25-200 ms measured at a load of 9 on
// two cores) spaces the next one out by a quarter of its time, so that a click is never queued
// behind draws back to back: it waits for one at most
(function drawLoop() {
  const t0 = performance.now();
  draw();
  const took = performance.now() - t0;
  if (took > 0.5) { live.drawMs.push(Math.round(took)); if (live.drawMs.length > 400) live.drawMs.splice(0, 200); }
  setTimeout(drawLoop, Math.max(40 - took, 0.25 * took));
})();

function banner(text, cls) { const b = document.getElementById("banner"); b.textContent = text; b.className = "banner " + (cls || ""); }
function kv(id, pairs) {
  document.getElementById(id).innerHTML = pairs.map(([k, v, cls]) => `<dt>${RIG.esc(k)}</dt><dd class="${cls || ""}">${RIG.esc(v)}</dd>`).join("");
}
let zero = null, trialMeta = null;
function showStatus(st) {
  if (!st || !st.ok) { banner("no daemon: " + (st ? st.error : "?"), "error"); kv("devices", [["daemon", st ? st.error : "-", "bad"]]); return; }
  const snap = st.snapshot || {};
  const pairs = [["daemon", st.state]];
  if (st.state === "idle") {
    if (snap.error) pairs.push(["devices", snap.error, "bad"]);
    else {
      pairs.push(["position", `${RIG.fmt(snap.position_mm)} mm`]);
      pairs.push(["drive alarm", snap.alarm_code ? `0x${snap.alarm_code.toString(16).toUpperCase()}` : "none", snap.alarm_code ? "bad" : "ok"]);
      pairs.push(["load cell", snap.force_N === null || snap.force_N === undefined ? "no reading" : `reading ${RIG.fmt(snap.force_N)} N (untared)`,
        snap.force_N === null || snap.force_N === undefined ? "bad" : "ok"]);
    }
  } else if (snap.fault) pairs.push(["fault", snap.fault, "bad"]);
  pairs.push(...zeroPair());
  if (st.campaign) pairs.push(["campaign", `${st.campaign.specimen}: ${st.campaign.phase}, ${st.campaign.trials} trials`]);
  followCampaign(st.campaign);
  liveDevices = "";
  kv("devices", pairs);
  if (st.state === "idle" && !document.getElementById("banner").dataset.ended) banner("idle: no trial running", "");
}
function ageText(s) { return s < 120 ? `${Math.round(s)} s` : s < 7200 ? `${Math.round(s / 60)} min` : s < 172800 ? `${Math.round(s / 3600)} h` : `${Math.round(s / 86400)} d`; }
function newTrial(trial) {
  trialMeta = trial;
  limits = trial && trial.limits ? trial.limits : null;
  buf = {t: [], f: [], x: [], k: []}; pending = {t: [], f: [], x: [], k: []}; steps = []; ranges = {y: null, y2: null};
  delete document.getElementById("banner").dataset.ended;
  resetPlots();
}
let liveDevices = "";
function zeroPair() {
  return zero ? [["zero", zero.zero_N === null ? zero.source : `${RIG.fmt(zero.zero_N)} N, ${zero.age_s === null ? "" : ageText(zero.age_s) + " old, "}${zero.source}`,
    zero.zero_N === null ? "bad" : ""]] : [];
}
function showLive(m) {
  const p = m.p;
  const key = `${m.state}|${m.fault}`;
  if (key !== liveDevices) {  // the devices as the trial's loop sees them
    liveDevices = key;
    kv("devices", [["daemon", `${m.state} (a trial owns the devices)`], ["fault", m.fault || "none", m.fault ? "bad" : "ok"], ...zeroPair()]);
  }
  const meta = trialMeta || {};
  banner(`running '${meta.protocol || "?"}' (specimen ${meta.specimen || "?"}): step ${m.step + 1}/${m.steps_total} ${m.step_kind}, ` +
    `${RIG.fmt(m.time_left_s, 2)} s left` + (m.fault ? ` FAULT: ${m.fault}` : ""), m.fault ? "fault" : "running");
  kv("trial", [["protocol", meta.protocol], ["specimen", meta.specimen], ["operator", meta.operator || meta.user],
    ["t", `${p[0].toFixed(2)} s`], ["force", `${RIG.fmt(p[1])} N`], ["position", `${RIG.fmt(p[2])} mm`],
    ["stiffness", `${RIG.fmt(p[3])} N/m`], ["log", meta.log]]);
}
function connect() {
  const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/ws`);
  ws.onmessage = ev => {
    const m = JSON.parse(ev.data);
    live.messages += 1;
    if (m.sent) { live.delays.push(Date.now() - m.sent * 1000); if (live.delays.length > 2000) live.delays.splice(0, 1000); }
    if (m.kind === "hello") {
      showStatus(m.status);
      newTrial(m.trial);
      if (m.trial) {
        steps = m.steps || []; take(m.points || []); pending = {t: [], f: [], x: [], k: []};
        grow("y", buf.f, 0.5); grow("y2", buf.x, 1); resetPlots();
      }
    } else if (m.kind === "status") { if (!trialMeta || m.status.state === "idle") showStatus(m.status); }
    else if (m.kind === "trial") newTrial(m.trial);
    else if (m.kind === "live") {
      if (!trialMeta) newTrial({});
      const ps = m.ps || [m.p];  // the points since the last message (25 messages a second)
      take(ps);
      ps.forEach((p, i) => {  // a new step is sent at once: its first point is the message's last
        const last = steps[steps.length - 1];
        if (!last || last[1] !== p[4]) { steps.push([p[0], p[4], i === ps.length - 1 ? m.step_kind : ""]); stepsDirty = true; }
      });
      showLive(m);
      if (m.campaign) followCampaign(m.campaign);
    } else if (m.kind === "end") {
      const last = m.last || {};
      const outcome = last.outcome || "ended";
      banner(`trial ended: ${outcome}` + (last.fault ? ` (${last.fault})` : "") + (last.log ? ` - log ${last.log}` : ""), outcome);
      document.getElementById("banner").dataset.ended = "1";
      live.lastOutcome = outcome;
      trialMeta = null;
      draw();
    } else if (m.kind === "campaign") followCampaign(m.campaign);
    else if (m.kind === "error") banner("daemon: " + m.error, "error");
  };
  ws.onclose = () => { banner("connection to rig web lost; reconnecting...", "error"); setTimeout(connect, 1000); };
}

async function loadProtocols() {
  const r = await RIG.get("/api/protocols");
  const sel = document.getElementById("proto");
  sel.innerHTML = r.protocols.map(p => `<option value="${RIG.esc(p.file)}" ${p.error ? "disabled" : ""}>${RIG.esc(p.name || p.file)}${p.error ? " (does not read)" : ""} - ${RIG.esc(p.file)}</option>`).join("");
  const demo = r.protocols.find(p => p.file === "demo.yaml");
  if (demo) sel.value = "demo.yaml";
}
let checked = null;
async function doCheck() {
  const file = document.getElementById("proto").value;
  const out = document.getElementById("check");
  out.innerHTML = "<span class='muted'>checking...</span>";
  const r = await RIG.post("/api/check", {file});
  checked = r.ok ? file : null;
  out.innerHTML = r.ok ? `<pre class="ok">${RIG.esc(r.lines.join("\n"))}</pre>` : `<pre class="bad">refused: ${RIG.esc(r.error)}</pre>`;
  document.getElementById("btn-start").disabled = !r.ok;
  return r;
}
async function doStart() {
  const file = document.getElementById("proto").value;
  const msg = document.getElementById("startmsg");
  if (checked !== file) { await doCheck(); if (checked !== file) return; }
  msg.innerHTML = "<span class='muted'>starting...</span>";
  const r = await RIG.post("/api/start", {file, specimen: document.getElementById("specimen").value,
    operator: document.getElementById("operator").value, notes: document.getElementById("notes").value});
  msg.innerHTML = r.ok ? `<pre class="ok">started '${RIG.esc(r.protocol)}'; log ${RIG.esc(r.log)}${(r.warnings || []).map(w => "\n" + RIG.esc(w)).join("")}</pre>`
    : `<pre class="bad">${RIG.esc(r.error)}</pre>`;
}
document.getElementById("btn-check").addEventListener("click", doCheck);
document.getElementById("btn-start").addEventListener("click", doStart);
document.getElementById("proto").addEventListener("change", () => { checked = null; document.getElementById("btn-start").disabled = true; document.getElementById("check").innerHTML = ""; });
// a campaign's journal (rig start --characterize): its events in words, followed while it runs
let campaign = null, journalAt = 0;
async function loadJournal() {
  journalAt = Date.now();
  const j = await RIG.get("/api/journal");
  const panel = document.getElementById("campaign-panel");
  if (!j.campaign) { panel.style.display = "none"; return; }
  panel.style.display = "";
  const c = j.campaign;
  document.getElementById("campaign-head").textContent = `specimen ${c.specimen}, started ${c.started} by ${c.user}: ${c.phase}` +
    (j.ok ? ` - ${j.journal}` : ` (${j.error})`);
  const ol = document.getElementById("journal");
  const atEnd = ol.scrollTop + ol.clientHeight >= ol.scrollHeight - 4;
  ol.innerHTML = (j.lines || []).map(l => `<li title="${RIG.esc(new Date(l.t * 1000).toLocaleTimeString())}">${RIG.esc(l.text)}</li>`).join("");
  if (atEnd) ol.scrollTop = ol.scrollHeight;
  window.rigJournal = j;
}
function followCampaign(c) {  // from the status or the live stream: again at most once a second while it runs
  const key = c ? `${c.specimen}|${c.phase}|${c.trials}|${c.status}` : "";
  const running = c && c.status === "running";
  if (key !== campaign || (running && Date.now() - journalAt > 1000)) { campaign = key; loadJournal().catch(() => {}); }
}
async function loadState() { try { const s = await RIG.get("/api/state"); zero = s.zero; cfgLimits = s.limits; } catch (e) { banner(String(e), "error"); } }
(async () => { await loadState(); resetPlots(); await loadProtocols(); doCheck(); connect(); setInterval(loadState, 5000); })();
