"use strict";
// The plant view: GET /api/plant every 5 s; a rollback sends the ETag this page last saw (If-Match).
const $ = (s) => document.querySelector(s);
// ?calibration=ID opens the page on that calibration's trail (the workbench links here)
let auditOf = Number(new URLSearchParams(location.search).get("calibration")) || null;

function el(tag, attrs, text) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  if (text !== undefined && text !== null) e.textContent = String(text);
  return e;
}

async function api(method, path, body, etag) {
  const headers = {};
  const tok = $("#token").value;
  if (tok) headers["Authorization"] = "Bearer " + tok;
  if (method !== "GET") headers["X-Requested-With"] = "eyetohand";
  if (etag) headers["If-Match"] = etag;
  const opts = { method, headers };
  if (body !== undefined) { headers["Content-Type"] = "application/json"; opts.body = JSON.stringify(body); }
  let resp;
  try { resp = await fetch(path, opts); }
  catch (e) { return { ok: false, status: 0, data: { error: "cannot reach the server (" + e.message + ")" } }; }
  let data = null;
  try { data = await resp.json(); } catch { data = { error: `HTTP ${resp.status}` }; }
  if (resp.status === 401) $("#token-box").hidden = false;
  return { ok: resp.ok, status: resp.status, data };
}

function showError(text) {
  const box = $("#global-err");
  box.textContent = text || "";
  box.hidden = !text;
}

function checkText(c) {
  if (!c) return el("span", { class: "muted" }, "no check yet");
  const span = el("span", { class: c.passed ? "pass" : "fail" },
    `${c.passed ? "passed" : "failed"} (v${c.version}) rms ${Number(c.rms_mm).toFixed(3)} mm`);
  if (c.drift_significant) span.append(el("div", {}, "drift: " + (c.named || []).join(", ")));
  span.append(el("div", { class: "muted" }, c.utc));
  return span;
}

function cellsText(cells, inForce) {
  const td = el("td");
  if (!cells.length) { td.append(el("span", { class: "muted" }, "none")); return td; }
  for (const c of cells) {
    const behind = c.version !== null && c.version !== inForce ? ` (answers with v${c.version})` : "";
    td.append(el("div", { class: c.alive ? "" : "silent", title: `pid ${c.pid}, last seen ${c.seen_utc}` },
      c.cell + behind + (c.alive ? "" : " — silent")));
  }
  return td;
}

function rollbackForm(row) {
  const td = el("td");
  const input = el("input", { type: "number", min: "1", max: String(row.current_version), size: "4",
    "aria-label": `version of ${row.name} to make current` });
  const button = el("button", { type: "button" }, "make current");
  button.addEventListener("click", async () => {
    const v = Number(input.value);
    if (!Number.isInteger(v) || v < 1) { showError(`${row.name}: give a version 1..${row.current_version}`); return; }
    const r = await api("POST", `/api/calibrations/${row.id}/rollback`, { version: v }, row.etag);
    if (!r.ok) showError(`${row.name}: ${r.data.error}`);
    else showError("");
    refresh();
  });
  td.append(input, " ", button);
  return td;
}

async function refresh() {
  const r = await api("GET", "/api/plant");
  $("#server-status").textContent = r.ok ? "connected" : "not answering";
  if (!r.ok) { if (r.status !== 401) showError(r.data.error); return; }
  $("#alive-s").textContent = r.data.alive_s;
  const body = $("#plant");
  body.replaceChildren();
  for (const row of r.data.calibrations) {
    const tr = el("tr");
    const name = el("a", { href: "#" }, row.name);
    name.addEventListener("click", (ev) => { ev.preventDefault(); auditOf = row.id; loadAudit(); });
    const first = el("td"); first.append(name, el("div", { class: "muted" }, `id ${row.id}`));
    tr.append(first, el("td", { class: "ver" }, `version ${row.current_version}`));
    const chk = el("td"); chk.append(checkText(row.last_check)); tr.append(chk);
    tr.append(cellsText(row.cells, row.current_version), rollbackForm(row));
    body.append(tr);
  }
  const others = $("#other-cells");
  others.replaceChildren(...r.data.other_cells.map((c) =>
    el("li", { class: c.alive ? "" : "silent" }, `${c.cell}: ${c.calibration || "no calibration yet"}`)));
  loadAudit();
}

async function loadAudit() {
  const q = auditOf === null ? "" : `&calibration=id:${auditOf}`;
  const r = await api("GET", `/api/audit?limit=50${q}`);
  if (!r.ok) return;
  $("#audit-of").textContent = auditOf === null ? "(all calibrations)" : `(calibration ${auditOf})`;
  $("#audit").replaceChildren(...r.data.entries.map((e) => {
    const tr = el("tr");
    const v = `${e.version_before ?? "–"} → ${e.version_after ?? "–"}`;
    for (const t of [e.utc, e.user, e.action, e.calibration, v, e.note]) tr.append(el("td", {}, t));
    return tr;
  }));
}

$("#token").addEventListener("change", refresh);
refresh();
setInterval(refresh, 5000);
