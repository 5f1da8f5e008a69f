"use strict";
rigHeader("/history");
const COLOURS = {ramp: "rgba(37,99,235,0.07)", hold: "rgba(22,163,74,0.08)", return: "rgba(217,119,6,0.08)", tare: "rgba(107,114,128,0.08)"};
(async () => {
  const file = new URLSearchParams(location.search).get("file") || "";
  const d = await RIG.get("/api/trial?file=" + encodeURIComponent(file));
  if (!d.ok) { document.getElementById("title").textContent = d.error; return; }
  const tr = d.trial || {};
  document.getElementById("title").textContent = `${tr.protocol_name || "?"}: specimen ${tr.specimen || "?"}, ${d.outcome}`;
  const f = d.figures || {};
  document.getElementById("meta").innerHTML = [["started", tr.start_time], ["operator", tr.operator], ["outcome", d.outcome],
    ["samples", d.samples + (d.every > 1 ? ` (every ${d.every}th drawn)` : "")], ["peak force", `${RIG.fmt(f.peak_force_N)} N`],
    ["k at hold end", `${RIG.fmt(f.stiffness_hold_end_N_per_m)} N/m`], ["estimator error", `${RIG.fmt(f.estimator_rms_error_N)} N rms`],
    ["notes", tr.notes], ["file", d.file]].map(([k, v]) => `<dt>${k}</dt><dd>${RIG.esc(v ?? "-")}</dd>`).join("");
  document.getElementById("download").href = "/files/log?file=" + encodeURIComponent(d.file);
  document.getElementById("download-csv").href = "/files/csv?file=" + encodeURIComponent(d.file);
  const shapes = d.spans.map(s => ({type: "rect", xref: "x", yref: "paper", x0: s[0], x1: s[1], y0: 0, y1: 1, line: {width: 0},
    fillcolor: COLOURS[s[2]] || "rgba(0,0,0,0.04)", layer: "below"}));
  const lim = d.limits;
  if (lim && lim.max_force_N) shapes.push({type: "line", xref: "paper", x0: 0, x1: 1, yref: "y", y0: lim.max_force_N, y1: lim.max_force_N, line: {color: "#dc2626", dash: "dash"}});
  Plotly.newPlot("ts", [
    {x: d.t_s, y: d.force_N, name: "force", line: {color: "#dc2626"}},
    {x: d.t_s, y: d.force_pred_N, name: "estimator's force", line: {color: "#9ca3af", dash: "dot"}},
    {x: d.t_s, y: d.position_mm, name: "position", yaxis: "y2", line: {color: "#2563eb"}},
    {x: d.t_s, y: d.stiffness_N_per_m, name: "stiffness", yaxis: "y3", line: {color: "#16a34a"}}],
    {margin: {l: 60, r: 10, t: 28, b: 40}, shapes, legend: {orientation: "h", x: 0, y: 1.0, yanchor: "bottom"},
     xaxis: {title: {text: "t (s)"}, anchor: "y3"}, yaxis: {domain: [0.68, 1], title: {text: "force (N)"}},
     yaxis2: {domain: [0.35, 0.65], title: {text: "position (mm)"}}, yaxis3: {domain: [0, 0.32], title: {text: "k (N/m)"}}},
    {displaylogo: false, responsive: true});
  Plotly.newPlot("fx", [{x: d.position_mm, y: d.force_N, mode: "lines", line: {color: "#7c3aed"}}],
    {margin: {l: 60, r: 10, t: 10, b: 40}, xaxis: {title: {text: "position (mm)"}}, yaxis: {title: {text: "force (N)"}}},
    {displaylogo: false, responsive: true});
  const keys = ["t_s", "event", "step", "kind", "message", "reason", "outcome"];
  document.getElementById("events").innerHTML = `<tr><th>t (s)</th><th>event</th><th>details</th></tr>` + d.events.map(e =>
    `<tr><td class="num">${RIG.fmt(e.t_s)}</td><td>${RIG.esc(e.event || e.kind || "")}</td><td style="white-space: normal">${RIG.esc(
      Object.entries(e).filter(([k]) => !["t_s", "event"].includes(k)).map(([k, v]) => `${k}=${typeof v === "object" ? JSON.stringify(v) : v}`).join("  "))}</td></tr>`).join("");
  window.rigTrialReady = true;
})();
