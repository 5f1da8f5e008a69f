// Several trials on one plot: force against time and against indentation (as `rig replay LOG LOG ...`).
"use strict";
rigHeader("/history");
const PALETTE = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];
(async () => {
  const files = new URLSearchParams(location.search).getAll("file");
  const d = await RIG.get("/api/compare?" + files.map(f => "file=" + encodeURIComponent(f)).join("&"));
  if (!d.ok) { document.getElementById("title").textContent = d.error; window.rigCompareReady = true; return; }
  document.getElementById("title").textContent = `${d.trials.length} trials on one plot`;
  document.getElementById("list").innerHTML = d.trials.map((t, i) => `<div><span style="color: ${PALETTE[i % 10]}">&#9632;</span> ` +
    `<a href="/trial?file=${encodeURIComponent(t.file)}">${RIG.esc(t.label)}</a> <span class="muted">${RIG.esc(t.outcome)}, ` +
    `${t.samples} samples${t.every > 1 ? ` (every ${t.every}th drawn)` : ""}</span></div>`).join("");
  const faults = [];
  d.trials.forEach((t, i) => t.faults.forEach(ts => faults.push({type: "line", xref: "x", yref: "paper", x0: ts, x1: ts, y0: 0, y1: 1,
    line: {color: PALETTE[i % 10], dash: "dash", width: 1}})));
  const legend = {orientation: "h", y: -0.16};
  Plotly.newPlot("ft", d.trials.map((t, i) => ({x: t.t_s, y: t.force_N, mode: "lines", name: t.label, line: {color: PALETTE[i % 10], width: 1.2}})),
    {title: {text: "force against time", font: {size: 13}}, margin: {l: 60, r: 10, t: 30, b: 40}, legend, shapes: faults,
     xaxis: {title: {text: "time (s)"}}, yaxis: {title: {text: "force (N)"}}}, {displaylogo: false, responsive: true});
  Plotly.newPlot("fx", d.trials.map((t, i) => ({x: t.indentation_mm, y: t.force_N, mode: "lines", name: t.label, showlegend: false,
    line: {color: PALETTE[i % 10], width: 1.2}})),
    {title: {text: "force against indentation", font: {size: 13}}, margin: {l: 60, r: 10, t: 30, b: 40}, legend,
     xaxis: {title: {text: "indentation (mm): from the surface"}}, yaxis: {title: {text: "force (N)"}}}, {displaylogo: false, responsive: true});
  window.rigCompareReady = true;
})();
