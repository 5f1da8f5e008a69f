"use strict";
rigHeader("/maps");
const timing = window.rigMaps = {};
let current = null;
const CFG = {displaylogo: false, displayModeBar: false, responsive: false};
function span(v) {  // an axis over the pixels' centres, half a pixel beyond each end
  const half = v.length > 1 ? Math.abs(v[1] - v[0]) / 2 : 0.5;
  return [Math.min(...v) - half, Math.max(...v) + half];
}
function heat(div, m, z, title, unit, opts = {}) {
  const trace = {type: "heatmap", x: m.x_um, y: m.y_um, z, colorscale: opts.colorscale || "Viridis",
    colorbar: {title: {text: unit, side: "right"}, thickness: 10, ...(opts.colorbar || {})}, hoverongaps: false,
    zmin: opts.zmin, zmax: opts.zmax, hovertemplate: `x %{x} ${m.axes_unit}<br>y %{y} ${m.axes_unit}<br>${title} %{z}<extra></extra>`};
  const drawn = Plotly.newPlot(div, [trace], {title: {text: title, font: {size: 13}}, margin: {l: 46, r: 8, t: 28, b: 36},
    xaxis: {title: {text: `x (${m.axes_unit})`}, range: span(m.x_um), constrain: "domain"},
    yaxis: {title: {text: `y (${m.axes_unit})`}, range: span(m.y_um), scaleanchor: "x", constrain: "domain"}}, CFG);
  document.getElementById(div).on("plotly_click", ev => {
    const p = ev.points[0];
    const ix = m.x_um.indexOf(p.x), iy = m.y_um.indexOf(p.y);
    const row = (m.row[iy] || [])[ix];
    if (row !== null && row !== undefined) openCurve(row);
  });
  return drawn;
}
// a press on a map: the click's time, from before plotly's own handling of it
document.addEventListener("pointerdown", () => { timing.pressed = performance.now(); }, true);
const painted = () => new Promise(r => requestAnimationFrame(() => setTimeout(r, 0)));  // after the frame is drawn
async function openMap(table) {
  const t0 = performance.now();
  timing.mapMs = null;
  const m = await RIG.get("/api/map?table=" + encodeURIComponent(table));
  if (!m.ok) { document.getElementById("summary").textContent = m.error; return; }
  current = m;
  const drawn = [heat("m-E", m, m.maps.E_kPa, "E", "kPa")];
  drawn.push(heat("m-h", m, m.maps.contact_height_um, "contact height", "um", {colorscale: "Cividis"}));
  drawn.push(heat("m-r", m, m.maps.rmse_over_noise, "RMSE / noise", "", {colorscale: "Magma"}));
  drawn.push(heat("m-v", m, m.maps.adequate, "verdict", "", {colorscale: [[0, "#dc2626"], [0.5, "#dc2626"], [0.5, "#16a34a"], [1, "#16a34a"]],
    zmin: 0, zmax: 1, colorbar: {tickvals: [0.25, 0.75], ticktext: ["not adequate", "adequate"]}}));
  const req = m.request || {};
  document.getElementById("summary").textContent = `${m.rows} curves on ${m.nx} x ${m.ny}; model ${req.model || "?"}` +
    `${req.indenter ? ", " + req.indenter : ""}; adequate ${m.adequate} of ${m.rows}${m.failed ? `, ${m.failed} could not be analysed` : ""}`;
  await Promise.all(drawn);
  await painted();
  timing.mapMs = performance.now() - t0;
  (timing.maps = timing.maps || []).push(timing.mapMs);
}
function focus(depth) {  // the contact, and as much of the approach before it as the indentation is deep
  const deepest = Math.max(...depth.filter(v => v !== null));
  const first = Math.min(...depth.filter(v => v !== null));
  return deepest > 0 ? [Math.max(first, -1.5 * deepest), 1.05 * deepest] : undefined;
}
let lastCurve = null;
function axisMode() { return document.querySelector("input[name=xaxis]:checked")?.value || "indentation"; }
function drawCurve(c) {  // against indentation, or against the tip-sample separation (minus it)
  const u = c.force_unit;
  const sep = axisMode() === "separation" && c.separation;
  const sign = sep ? -1 : 1;
  const flip = a => (a || []).map(v => v === null ? null : sign * v);
  const x = flip(c.indentation_um), rx = flip(c.retract_indentation_um);
  const approach = x.map((v, i) => c.branch[i] === "retract" ? null : v);
  const traces = [
    {x: approach, y: c.force, mode: "markers", name: "approach", marker: {size: 3, color: "#2563eb"}},
    {x: rx, y: c.retract_force || [], mode: "markers", name: "retract", marker: {size: 3, color: "#d97706"}},
    {x, y: c.fit, mode: "lines", name: `fit (${c.model}, ${c.segment})`, line: {color: "#dc2626", width: 2}},
    {x, y: c.residual, mode: "markers", name: "residual", xaxis: "x", yaxis: "y2", marker: {size: 3, color: "#6b7280"}, showlegend: false}];
  const r = focus(c.indentation_um);
  const title = sep ? "tip-sample separation (um): the fitted contact at 0, negative in contact"
    : "indentation (um): travel past the fitted contact point";
  const drawn = Plotly.react("curve", traces,
    {margin: {l: 60, r: 10, t: 10, b: 40}, legend: {orientation: "h", y: 1.08},
     xaxis: {title: {text: title}, anchor: "y2", range: r ? (sep ? [-r[1], -r[0]] : r) : undefined},
     yaxis: {domain: [0.32, 1], title: {text: `force (${u})`}}, yaxis2: {domain: [0, 0.25], title: {text: `residual (${u})`}},
     shapes: [{type: "line", x0: 0, x1: 0, xref: "x", yref: "paper", y0: 0, y1: 1, line: {color: "#111", dash: "dot"}}],
     annotations: [{x: 0, xref: "x", y: 1, yref: "paper", text: "contact point" + (c.contact_point_um !== null && c.contact_point_um !== undefined
       ? ` (${RIG.fmt(c.contact_point_um)} um of travel)` : ""), showarrow: false, xanchor: sep ? "right" : "left", font: {size: 11}}]},
    {displaylogo: false, responsive: true});
  document.getElementById("xaxis-note").textContent = axisMode() === "separation" && !c.separation
    ? "no tip-sample separation: the record's travel is the piezo's (no spring constant to take the deflection off)"
    : (c.retract_note || "");
  return drawn;
}
document.querySelectorAll("input[name=xaxis]").forEach(el => el.addEventListener("change", () => { if (lastCurve) drawCurve(lastCurve); }));
async function openCurve(row) {
  const now = performance.now();
  const t0 = timing.pressed && now - timing.pressed < 1000 ? timing.pressed : now;
  timing.pressed = null;
  timing.curveMs = null;
  document.getElementById("curve-title").textContent = "fitting the curve again...";
  const c = await RIG.get(`/api/curve?table=${encodeURIComponent(current.table)}&row=${row}`);
  const where = c.x_um !== null && c.x_um !== undefined ? ` at (${RIG.fmt(c.x_um)}, ${RIG.fmt(c.y_um)}) um` : "";
  document.getElementById("curve-title").textContent = `curve ${c.curve ?? row}${where}: ${(c.file || "").split("/").pop()}`;
  if (!c.ok || c.error) { document.getElementById("verdict").innerHTML = `<p class="bad">${RIG.esc(c.error)}</p>`; Plotly.purge("curve"); timing.curveMs = performance.now() - t0; return; }
  const adequate = c.adequate === true || c.adequate === "True";
  document.getElementById("verdict").innerHTML = `<p><b class="${adequate ? "ok" : "bad"}">${adequate ? "adequate" : "NOT adequate"}</b>` +
    ` (RMSE / noise ${RIG.fmt(c.rmse_over_noise)}), model ${RIG.esc(c.model)}, E ${RIG.fmt(c.E_kPa)} kPa` +
    (c.effect ? `; missing: <b>${RIG.esc(c.effect)}</b> (try rig analyze ... --add ${RIG.esc(c.effect)})` : "") + "</p>";
  lastCurve = c;
  await drawCurve(c);
  await painted();
  timing.curveMs = performance.now() - t0;
  (timing.curves = timing.curves || []).push(timing.curveMs);
  (timing.server = timing.server || []).push(Math.round(1000 * (c.seconds || 0)));  // of which the server's
}
(async () => {
  const r = await RIG.get("/api/tables");
  const sel = document.getElementById("table");
  sel.innerHTML = r.tables.map(t => `<option>${RIG.esc(t.table)}</option>`).join("") || "<option disabled>no batch tables in " + RIG.esc(r.folder) + "</option>";
  sel.addEventListener("change", () => openMap(sel.value));
  const want = new URLSearchParams(location.search).get("table");
  if (want) sel.value = want;
  if (sel.value && r.tables.length) {
    await openMap(sel.value);
    timing.loadMs = performance.now();  // from the page's navigation to the maps drawn
  }
  window.rigMapsReady = true;
})();
