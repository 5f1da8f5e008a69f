"use strict";
rigHeader("/history");
const COLS = [["start_time", "started"], ["specimen", "specimen"], ["protocol", "protocol"], ["outcome", "outcome"],
  ["peak_force_N", "peak force (N)"], ["stiffness_hold_end_N_per_m", "k at hold end (N/m)"],
  ["estimator_rms_error_N", "estimator error (N)"], ["duration_s", "duration (s)"], ["samples", "samples"],
  ["requested_by", "by"], ["campaign", "campaign"]];
let rows = [], sortKey = "start_time", sortDir = -1;
const chosen = new Set();  // the files selected for comparison
function compareButton() {
  const b = document.getElementById("btn-compare");
  b.disabled = chosen.size < 1;
  b.textContent = chosen.size ? `compare ${chosen.size} selected` : "compare selected";
}
const colFilters = {};
function render() {
  const q = document.getElementById("filter").value.toLowerCase();
  let shown = rows.filter(r => (!q || COLS.some(([k]) => String(r[k] ?? "").toLowerCase().includes(q))) &&
    Object.entries(colFilters).every(([k, v]) => !v || String(r[k] ?? "").toLowerCase().includes(v.toLowerCase())));
  shown.sort((a, b) => { const x = a[sortKey], y = b[sortKey];
    if (x === y) return 0; if (x === null || x === undefined) return 1; if (y === null || y === undefined) return -1;
    return (x < y ? -1 : 1) * sortDir; });
  document.querySelector("#trials tbody").innerHTML = shown.map(r => `<tr><td><input type="checkbox" class="pick" data-file="${RIG.esc(r.file)}" ${chosen.has(r.file) ? "checked" : ""} style="width: auto"></td>${COLS.map(([k]) => {
    const v = r[k]; const num = typeof v === "number";
    const text = k === "start_time" ? `<a href="/trial?file=${encodeURIComponent(r.file)}">${RIG.esc(String(v).replace("T", " ").slice(0, 19))}</a>` : RIG.esc(num ? RIG.fmt(v, 4) : (v ?? ""));
    return `<td class="${num ? "num" : ""}">${text}</td>`; }).join("")}</tr>`).join("");
  document.getElementById("count").textContent = `${shown.length} of ${rows.length} trials`;
  document.querySelectorAll("#trials input.pick").forEach(el => el.addEventListener("change", () => {
    if (el.checked) chosen.add(el.dataset.file); else chosen.delete(el.dataset.file); compareButton(); }));
}
function header() {
  const th = COLS.map(([k, t]) => `<th data-k="${k}">${t}${k === sortKey ? (sortDir > 0 ? " ▲" : " ▼") : ""}</th>`).join("");
  const tf = COLS.map(([k]) => `<th><input data-f="${k}" value="${RIG.esc(colFilters[k] || "")}" placeholder="filter"></th>`).join("");
  document.querySelector("#trials thead").innerHTML = `<tr><th title="select to compare">cmp</th>${th}</tr><tr><th></th>${tf}</tr>`;
  document.querySelectorAll("#trials th[data-k]").forEach(el => el.addEventListener("click", () => {
    const k = el.dataset.k; sortDir = k === sortKey ? -sortDir : 1; sortKey = k; header(); render(); }));
  document.querySelectorAll("#trials input[data-f]").forEach(el => el.addEventListener("input", () => { colFilters[el.dataset.f] = el.value; render(); }));
}
document.getElementById("filter").addEventListener("input", render);
document.getElementById("btn-compare").addEventListener("click", () => {
  location.href = "/compare?" + [...chosen].map(f => "file=" + encodeURIComponent(f)).join("&"); });
(async () => { const r = await RIG.get("/api/trials"); rows = r.trials; document.getElementById("folder").textContent = r.folder; header(); render(); window.rigHistoryReady = true; })();
