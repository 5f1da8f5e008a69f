// Shared by every page: the header (pages, STOP / HOLD / ESTOP), the keys, requests.
"use strict";
const RIG = {
  async get(url) {
    const r = await fetch(url, {credentials: "same-origin"});
    if (r.status === 401 || r.status === 403) throw new Error(await r.text());
    return r.json();
  },
  async post(url, body) {
    const r = await fetch(url, {method: "POST", credentials: "same-origin",
      headers: {"content-type": "application/json"}, body: JSON.stringify(body || {})});
    if (r.status === 401 || r.status === 403) return {ok: false, error: await r.text()};
    return r.json();
  },
  now() { return performance.timeOrigin + performance.now(); },
  esc(s) { return String(s ?? "").replace(/[&<>"']/g, c => ({"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}[c])); },
  fmt(v, d = 3) { return (v === null || v === undefined || v === "") ? "-" : (typeof v === "number" ? +v.toPrecision(d + 1) : v); },
};
window.rigClicks = [];

async function rigStop(kind) {
  const clicked = RIG.now();
  window.rigClicks.push({kind, clicked_ms: clicked});
  const msg = document.getElementById("stopmsg");
  msg.textContent = kind.toUpperCase() + " sent...";
  const reply = kind === "estop" ? await RIG.post("/api/estop", {clicked_ms: clicked})
    : await RIG.post("/api/stop", {mode: kind === "hold" ? "hold" : "abort", clicked_ms: clicked});
  window.rigClicks[window.rigClicks.length - 1].answered_ms = RIG.now();
  msg.textContent = reply.ok ? (reply.message || "done") : ("refused: " + reply.error);
  msg.className = reply.ok ? "" : "bad";
  document.dispatchEvent(new CustomEvent("rig-stopped", {detail: reply}));
  return reply;
}

function rigHeader(here) {
  const h = document.createElement("header");
  const pages = [["/", "Console"], ["/history", "History"], ["/maps", "Maps"]];
  h.innerHTML = `<span class="brand">rig web</span><nav>${pages.map(([u, t]) =>
      `<a href="${u}" class="${u === here ? "here" : ""}">${t}</a>`).join("")}</nav>
    <div class="stops"><span id="stopmsg"></span>
      <button class="hold" id="btn-hold" title="stop and stay (key H)">HOLD <kbd>H</kbd></button>
      <button class="stop" id="btn-stop" title="stop, then return to the start (key S)">STOP <kbd>S</kbd></button>
      <button class="estop" id="btn-estop" title="emergency stop: the motor, now (key Esc)">ESTOP <kbd>Esc</kbd></button></div>`;
  document.body.prepend(h);
  document.getElementById("btn-estop").addEventListener("click", () => rigStop("estop"));
  document.getElementById("btn-stop").addEventListener("click", () => rigStop("stop"));
  document.getElementById("btn-hold").addEventListener("click", () => rigStop("hold"));
  document.addEventListener("keydown", ev => {
    if (ev.key === "Escape") { ev.preventDefault(); rigStop("estop"); return; }
    const typing = /^(INPUT|TEXTAREA|SELECT)$/.test(document.activeElement?.tagName || "");
    if (typing && !ev.altKey) return;
    if (ev.key === "s" || ev.key === "S") { ev.preventDefault(); rigStop("stop"); }
    if (ev.key === "h" || ev.key === "H") { ev.preventDefault(); rigStop("hold"); }
  });
  // the token came in the address: the cookie now carries it; take it out of the address bar
  const url = new URL(location.href);
  if (url.searchParams.has("token")) {
    url.searchParams.delete("token");
    history.replaceState(null, "", url.pathname + (url.search || "") + url.hash);
  }
}
