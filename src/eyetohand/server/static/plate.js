// eyetohand workbench: the plate flow (as `eyetohand calibrate-plate`), loaded after app.js and using its
// helpers ($, el, td, fmt, api, showError, clearError, fileBase64, showResult, refreshSaved, state).
// Grab or upload the plate's image(s) → POST /api/plate/detect (corners, A–D, border) drawn on a canvas →
// touches in a table (a click on the image snaps to a corner: POST /api/plate/snap, the fit's own rule and
// words) or a pasted CSV → POST /api/plate/calibrate → the result section, like any fit.
"use strict";

const plate = {
  images: [],   // {name, blob, det (detect's answer) | null, err ({error, seen_px}) | null, bitmap}
  view: 0,      // the image on the canvas
  rows: [],     // touches: {id, image, corner, u, v, x, y, z}
  active: 0,    // the row a click on the image sets
  check: null,  // check point records (from /api/pairs/parse)
  scale: 1,     // image px per canvas px
  gen: 0,       // the detection under way: a newer one (another spec, other images) overtakes it
};
state.plateFit = null;  // the last plate fit's answer, while it is the result shown

const PLATE_HELP = {
  chessboard: "chessboard:COLSxROWS:SQUARE_MM — counted in inner corners (9x6: a board of 10 × 7 squares); SQUARE_MM the squares' side",
  circles: "circles:COLSxROWS:PITCH_MM — a symmetric grid of dots, COLS per row; PITCH_MM between dot centres",
  acircles: "acircles:COLSxROWS:PITCH_MM — OpenCV's asymmetric dot grid: dot (c, r) at ((2c + r mod 2)·PITCH, r·PITCH)",
  charuco: "charuco:COLSxROWS:SQUARE_MM[:MARKER_MM] — inner corners as a chessboard; ArUco markers of DICT_5X5_1000, 0.75 of a square unless given",
};

function plateSpec() { return $("#plate-spec").value.trim(); }
function plateHelp() {
  const kind = (/^\s*([a-z]+)/.exec($("#plate-spec").value) || [])[1];
  if (PLATE_HELP[kind]) $("#plate-kind").value = kind;
  $("#plate-help").textContent = PLATE_HELP[$("#plate-kind").value];
}

// UTF-8 text as base64 (an upload's bytes)
function textBase64(text) {
  const b = new TextEncoder().encode(text);
  let s = "";
  for (let i = 0; i < b.length; i += 0x8000) s += String.fromCharCode(...b.subarray(i, i + 0x8000));
  return btoa(s);
}

// ------------------------------------------------------------------ images: upload, grab, detect

async function plateSetImages(items) {
  plate.images = items.map(({ name, blob }) => ({ name, blob, det: null, err: null, bitmap: null }));
  plate.view = 0;
  plate.rows = [];
  await plateDetect();
}

async function plateGrab() {
  clearError("#plate-err");
  $("#plate-state").textContent = "grabbing…";
  const headers = {};
  if ($("#token").value) headers.Authorization = "Bearer " + $("#token").value;
  let resp;
  try { resp = await fetch("/api/plate/grab.png", { headers }); }
  catch (e) { showError("#plate-err", { error: "cannot reach the server (" + e.message + ")" }); return; }
  if (!resp.ok) {
    let err = { error: `HTTP ${resp.status}` };
    try { err = await resp.json(); } catch { /* not JSON */ }
    $("#plate-state").textContent = "";
    showError("#plate-err", err);
    return;
  }
  const blob = await resp.blob();
  const name = `grab-${new Date().toISOString().slice(11, 19).replace(/:/g, "")}.png`;
  // a grab adds an image (one placement more), keeping the touches entered so far
  const rows = plate.rows;
  plate.images.push({ name, blob, det: null, err: null, bitmap: null });
  plate.view = plate.images.length - 1;
  await plateDetect();
  if (rows.length) plate.rows = rows;
  plateRenderRows();
}

async function plateDetect() {
  clearError("#plate-err", "#loader-plate");
  clearError("#plate-fit-err");
  if (!plate.images.length) { showError("#plate-err", { error: "choose the plate's image(s) or grab one first" }); return; }
  $("#plate-detect").disabled = true;
  const spec = plateSpec(), gen = ++plate.gen;
  let found = 0;
  for (const [k, im] of plate.images.entries()) {
    $("#plate-state").textContent = `detecting in ${im.name} (${k + 1} of ${plate.images.length})…`;
    im.det = null; im.err = null;
    if (!im.bitmap) im.bitmap = await createImageBitmap(im.blob).catch(() => null);
    const r = await api("POST", "/api/plate/detect", { plate: spec, image: { name: im.name, data_base64: await fileBase64(im.blob) } });
    if (gen !== plate.gen) return;  // overtaken
    if (r.ok) { im.det = r.data; found++; continue; }
    im.err = r.data;
    if (r.data.field === "plate") { showError("#plate-err", r.data, "#loader-plate"); break; }
  }
  $("#plate-detect").disabled = false;
  const n = plate.images.length;
  $("#plate-count").textContent = `${n} image${n === 1 ? "" : "s"}, plate found in ${found}`;
  $("#plate-count").classList.toggle("ok", found === n);
  $("#plate-state").textContent = "";
  if (!plate.rows.length) plateDefaultRows();
  plateShowView();
  plateRenderRows();
}

// A–D of the first image where the plate was found: the corners the labels name, x y z to enter
function plateDefaultRows() {
  const k = plate.images.findIndex((im) => im.det);
  if (k < 0) return;
  plate.rows = plate.images[k].det.labels.map((l) => ({ id: l.label, image: k, corner: l.id, u: l.u, v: l.v, x: "", y: "", z: "" }));
  plate.active = 0;
}

function plateShowView() {
  const sel = $("#plate-view");
  sel.innerHTML = "";
  plate.images.forEach((im, k) => sel.appendChild(el("option", { value: String(k) }, `${k + 1}: ${im.name}${im.det ? "" : " (not found)"}`)));
  sel.value = String(plate.view);
  $("#plate-view-box").hidden = plate.images.length < 2;
  const im = plate.images[plate.view];
  $("#plate-annotated").hidden = !im;
  if (im && im.err && im.err.field !== "plate") showError("#plate-err", im.err);
  else if (im && im.det) {
    clearError("#plate-err");
    const d = im.det;
    $("#plate-state").textContent = `${im.name}: ${d.seen < d.uv_px.length ? `${d.seen} of ` : ""}${d.uv_px.length} ${d.what} found (${d.plate}), spacing ${fmt(d.spacing_px, 1)} px; a click snaps within ${fmt(d.snap_radius_px, 1)} px`;
  }
  plateDraw();
}

function plateDraw() {
  const im = plate.images[plate.view];
  const fig = $("#plate-fig");
  if (!im || !im.bitmap) { fig.hidden = true; return; }
  fig.hidden = false;
  const c = $("#plate-canvas");
  const W = im.bitmap.width, H = im.bitmap.height;
  plate.scale = Math.max(1, W / 1600);
  c.width = Math.round(W / plate.scale); c.height = Math.round(H / plate.scale);
  const g = c.getContext("2d");
  g.drawImage(im.bitmap, 0, 0, c.width, c.height);
  const k = 1 / plate.scale, r = Math.max(3, c.width / 300), lw = Math.max(1.5, c.width / 600);
  const P = ([u, v]) => [(u + 0.5) * k, (v + 0.5) * k];  // pixel centres (OpenCV) to canvas
  c.dataset.found = im.det ? String(im.det.seen) : "0";
  c.dataset.seen = im.err && im.err.seen_px ? String(im.err.seen_px.length) : "0";
  c.dataset.labels = im.det ? im.det.labels.map((l) => `${l.label} ${l.id}`).join(",") : "";
  if (!im.det) {  // what was seen: red rings (as --annotate draws a plate not found)
    g.strokeStyle = "#d62728"; g.lineWidth = lw;
    for (const p of (im.err && im.err.seen_px) || []) { const [x, y] = P(p); g.beginPath(); g.arc(x, y, 2 * r, 0, 2 * Math.PI); g.stroke(); }
    return;
  }
  const d = im.det;
  g.setLineDash([8, 5]); g.strokeStyle = "#1f5fae"; g.lineWidth = lw;
  g.beginPath(); d.outline_px.forEach((p, i) => { const [x, y] = P(p); if (i) g.lineTo(x, y); else g.moveTo(x, y); }); g.closePath(); g.stroke();
  g.setLineDash([]);
  g.fillStyle = "#1f5fae";
  for (const p of d.uv_px) { if (!p) continue; const [x, y] = P(p); g.beginPath(); g.arc(x, y, r, 0, 2 * Math.PI); g.fill(); }
  g.font = `bold ${Math.round(c.width / 45)}px system-ui, sans-serif`;
  g.lineJoin = "round";
  const label = (text, x, y, colour) => {
    g.lineWidth = 4; g.strokeStyle = "#000"; g.strokeText(text, x, y);
    g.fillStyle = colour; g.fillText(text, x, y);
  };
  for (const l of d.labels) {
    const [x, y] = P([l.u, l.v]);
    g.strokeStyle = "#e6b800"; g.lineWidth = 2 * lw;
    g.beginPath(); g.arc(x, y, 3 * r, 0, 2 * Math.PI); g.stroke();
    label(`${l.label} ${l.id}`, x + 3.5 * r, y - 3.5 * r, "#ffd400");
  }
  // the touches on this image: a green cross and the touch's name
  plate.rows.forEach((t, i) => {
    if (t.image !== plate.view || t.u === null) return;
    const [x, y] = P([t.u, t.v]);
    g.strokeStyle = i === plate.active ? "#00c853" : "#2e7d32"; g.lineWidth = 2 * lw;
    g.beginPath(); g.moveTo(x - 4 * r, y); g.lineTo(x + 4 * r, y); g.moveTo(x, y - 4 * r); g.lineTo(x, y + 4 * r); g.stroke();
    if (!d.labels.some((l) => l.label === t.id && l.u === t.u && l.v === t.v)) label(t.id, x + 3.5 * r, y + 8 * r, "#7CFC00");
  });
}

// the image as `calibrate-plate --annotate` draws it (the server draws it: the same code), downloaded
async function plateAnnotated() {
  const im = plate.images[plate.view];
  if (!im) return;
  const r = await api("POST", "/api/plate/detect", { plate: plateSpec(), image: { name: im.name, data_base64: await fileBase64(im.blob) }, annotated: true });
  const b64 = r.data && r.data.annotated_png_base64;
  if (!b64) { showError("#plate-err", r.data || { error: "no annotated image" }); return; }
  const bytes = Uint8Array.from(atob(b64), (ch) => ch.charCodeAt(0));
  const a = el("a", { href: URL.createObjectURL(new Blob([bytes], { type: "image/png" })), download: im.name.replace(/\.[^.]*$/, "") + "-annotated.png" });
  document.body.appendChild(a); a.click(); a.remove();
}

// a click: the nearest detected corner, snapped by the server (the fit's rule), for the active row
async function plateClick(ev) {
  const im = plate.images[plate.view];
  if (!im || !im.det) return;
  const c = $("#plate-canvas"), box = c.getBoundingClientRect();
  const u = ((ev.clientX - box.left) * (c.width / box.width)) * plate.scale - 0.5;
  const v = ((ev.clientY - box.top) * (c.height / box.height)) * plate.scale - 0.5;
  if (!plate.rows.length) plateAddRow();
  const row = plate.rows[plate.active];
  // the other touches of this image come along: a corner touched twice is refused as the fit refuses it
  const others = plate.rows.map((t, i) => ({ t, i })).filter(({ t, i }) => i !== plate.active && t.image === plate.view && t.u !== null);
  const touches = [...others.map(({ t, i }) => ({ u: t.u, v: t.v, id: t.id, line: i + 2 })), { u, v, id: row.id, line: plate.active + 2 }];
  const r = await api("POST", "/api/plate/snap", { plate: im.det.plate, uv_px: im.det.uv_px, image_size: im.det.image_size, touches });
  if (!r.ok) { showError("#plate-err", r.data); $("#plate-err").dataset.click = `${fmt(u, 1)},${fmt(v, 1)}`; return; }
  clearError("#plate-err");
  const corner = r.data.corners[r.data.corners.length - 1];
  Object.assign(row, { image: plate.view, corner: corner.id, u: corner.u, v: corner.v });
  $("#plate-state").textContent = `touch ${row.id}: corner ${corner.id} (${fmt(corner.u, 1)}, ${fmt(corner.v, 1)}) px, ${fmt(corner.distance_px, 1)} px from the click`;
  // on to the next row still without a pixel, so A, B, C, D can be clicked in turn
  const next = plate.rows.findIndex((t, i) => i > plate.active && t.u === null);
  if (next >= 0) plate.active = next;
  plateRenderRows();
  plateDraw();
}

// ------------------------------------------------------------------ touches

function plateAddRow() {
  const used = new Set(plate.rows.map((t) => t.id));
  let id = "";
  for (let k = 0; !id; k++) { const c = k < 26 ? String.fromCharCode(65 + k) : `T${k + 1}`; if (!used.has(c)) id = c; }
  plate.rows.push({ id, image: plate.view, corner: "", u: null, v: null, x: "", y: "", z: "" });
  plate.active = plate.rows.length - 1;
  plateRenderRows();
}

function plateRenderRows() {
  const tb = $("#plate-touches tbody");
  tb.innerHTML = "";
  plate.rows.forEach((t, i) => {
    const tr = el("tr", { "data-row": String(i) });
    if (i === plate.active) tr.classList.add("active");
    const pick = el("input", { type: "radio", name: "plate-active", "aria-label": `a click on the image sets touch ${t.id}` });
    pick.checked = i === plate.active;
    pick.addEventListener("change", () => { plate.active = i; plateRenderRows(); plateDraw(); });
    const c0 = el("td", { class: "text" }); c0.appendChild(pick); tr.appendChild(c0);
    const idIn = el("input", { type: "text", class: "tid", value: t.id, "aria-label": "touch name" });
    idIn.addEventListener("change", () => { t.id = idIn.value.trim() || t.id; plateDraw(); });
    const c1 = el("td", { class: "text" }); c1.appendChild(idIn); tr.appendChild(c1);
    tr.appendChild(td(plate.images[t.image] ? `${t.image + 1}: ${plate.images[t.image].name}` : "–", "text"));
    tr.appendChild(td(t.corner || "click it", "text"));
    tr.appendChild(td(t.u === null ? "–" : fmt(t.u, 2)));
    tr.appendChild(td(t.v === null ? "–" : fmt(t.v, 2)));
    for (const k of ["x", "y", "z"]) {
      const inp = el("input", { type: "number", step: "any", value: t[k], class: `t${k}`, "aria-label": `touch ${t.id} ${k} mm` });
      inp.addEventListener("input", () => { t[k] = inp.value; plateButtons(); });
      const c = el("td"); c.appendChild(inp); tr.appendChild(c);
    }
    const rm = el("button", { type: "button", class: "link" }, "remove");
    rm.addEventListener("click", () => { plate.rows.splice(i, 1); plate.active = Math.min(plate.active, Math.max(0, plate.rows.length - 1)); plateRenderRows(); plateDraw(); });
    const c9 = el("td", { class: "text" }); c9.appendChild(rm); tr.appendChild(c9);
    tb.appendChild(tr);
  });
  plateButtons();
}

// the touches CSV the fit gets: the pasted one, else the table's (row i is line i + 2)
function plateTouchesCsv() {
  const pasted = $("#plate-csv").value;
  if (pasted.trim()) return { name: "pasted touches", text: pasted };
  const missing = plate.rows.find((t) => t.u === null);
  if (missing) return { error: `touch ${missing.id}: click its corner on the image first (or remove the row)` };
  const num = (x) => (x === "" || x === null ? "" : String(x));
  const lines = ["image,u,v,x,y,z,id", ...plate.rows.map((t) => [plate.images[t.image].name, t.u, t.v, num(t.x), num(t.y), num(t.z), t.id].join(","))];
  return { name: "touches", text: lines.join("\n") + "\n" };
}

function plateButtons() {
  const ready = plate.images.some((im) => im.det) && (plate.rows.length >= 3 || $("#plate-csv").value.trim());
  $("#plate-fit").disabled = !ready;
  $("#plate-detect").disabled = !plate.images.length;
  $("#plate-fit-state").textContent = ready ? ($("#plate-csv").value.trim() ? "the pasted CSV is used" : `${plate.rows.length} touches from the table`) : "detect the plate and enter at least 3 touches first";
}

async function plateLoadCheck(ev) {
  clearError("#plate-fit-err");
  const f = ev.target.files[0];
  plate.check = null;
  $("#plate-check-count").textContent = "";
  if (!f) return;
  const r = await api("POST", "/api/pairs/parse", { text: await f.text(), source: f.name });
  if (!r.ok) { showError("#plate-fit-err", r.data); return; }
  plate.check = r.data.pairs.map((p) => ({ id: p.id, u: p.u, v: p.v, x: p.x, y: p.y, z: p.z }));
  $("#plate-check-count").textContent = `${r.data.n} check points`;
}

// ------------------------------------------------------------------ fit and save

async function plateFit() {
  clearError("#plate-fit-err", "#loader-plate");
  const csv = plateTouchesCsv();
  if (csv.error) { showError("#plate-fit-err", { error: csv.error, field: "touches" }); return; }
  const body = { plate: plateSpec(), images: [], touches: { name: csv.name.replace(/ /g, "-") + ".csv", data_base64: textBase64(csv.text) } };
  for (const im of plate.images) body.images.push({ name: im.name, data_base64: await fileBase64(im.blob) });
  if (plate.check) body.check = plate.check;
  const tol = $("#plate-tolerance").value;
  if (tol !== "") body.touch_tolerance_mm = Number(tol);
  const name = $("#plate-name").value.trim();
  if (name) { body.name = name; body.note = `plate ${body.plate}`; }
  $("#plate-fit").disabled = true;
  $("#plate-fit-state").textContent = "fitting…";
  const r = await api("POST", "/api/plate/calibrate", body);
  plateButtons();
  delete body.name; delete body.note;
  state.plateRequest = body;  // Save below sends it again with a name (the server stores what it fits)
  if (!r.ok) { showError("#plate-fit-err", r.data, "#loader-plate"); $("#plate-fit-state").textContent = "refused"; return; }
  const d = r.data;
  state.job = null;  // the result shown is this plate fit, not a job
  state.plateFit = d;
  const stored = d.stored ? { id: d.stored.id, name: d.stored.name, version: d.stored.version } : null;
  showResult(d.summary, stored);
  const placed = d.plate.placements.map((p) => `image ${p.image}: touches fit RMS ${fmt(p.rms_mm)} mm`).join("; ");
  $("#plate-fit-state").textContent = `fitted: model ${d.model}; ${placed}` + (stored ? `; saved as “${stored.name}” v${stored.version}` : "; not saved (name it, or use Save below)");
  if (stored) await refreshSaved();
  $("#sec-result").scrollIntoView({ behavior: "smooth" });
}

// Save (section Save) of a plate fit: the same request again with a name, stored by the server as a new
// calibration or a new version (the fit is deterministic: the same file). Not the answered file sent back:
// JSON through JavaScript turns 0.0 into 0, and the file's content hash would no longer match.
async function savePlateFit(asVersion, note) {
  let name;
  if (asVersion) {
    const c = state.saved.find((s) => String(s.id) === $("#save-target").value);
    if (!c) { showError("#save-err", { error: "no saved calibration to add a version to", field: "calibration_id" }); return; }
    name = c.name;
  } else {
    name = $("#save-name").value.trim();
    if (!name) { showError("#save-err", { error: "name: give the calibration a name", field: "name" }, "#sec-save"); return; }
    if (state.saved.some((s) => s.name === name)) {
      showError("#save-err", { error: `name: a calibration called “${name}” exists; save as a new version of it, or choose another name`, field: "name" }, "#sec-save");
      return;
    }
  }
  const body = { ...state.plateRequest, name, note: note || `plate ${state.plateFit.plate.spec}` };
  const r = await api("POST", "/api/plate/calibrate", body);
  if (!r.ok) { showError("#save-err", r.data, "#sec-save"); return; }
  state.plateFit.stored = r.data.stored;
  await showSaved(r.data.stored);
}

// ------------------------------------------------------------------ wiring

$("#plate-kind").addEventListener("change", () => {
  const k = $("#plate-kind").value;
  const s = $("#plate-spec");
  s.value = /^\s*[a-z]*\s*:/.test(s.value) ? s.value.replace(/^\s*[a-z]*/, k) : `${k}:9x6:15`;
  plateHelp();
});
$("#plate-spec").addEventListener("input", plateHelp);
$("#plate-spec").addEventListener("change", () => { if (plate.images.length) { plate.rows = []; plateDetect(); } });
$("#plate-files").addEventListener("change", (ev) => {
  const files = [...ev.target.files];
  if (files.length) plateSetImages(files.map((f) => ({ name: f.name, blob: f })));
});
$("#plate-grab").addEventListener("click", plateGrab);
$("#plate-detect").addEventListener("click", () => { plate.rows = []; plateDetect(); });
$("#plate-view").addEventListener("change", () => { plate.view = Number($("#plate-view").value); plateShowView(); });
$("#plate-canvas").addEventListener("click", plateClick);
$("#plate-add").addEventListener("click", plateAddRow);
$("#plate-annotated").addEventListener("click", plateAnnotated);
$("#plate-csv").addEventListener("input", plateButtons);
$("#plate-check").addEventListener("change", plateLoadCheck);
$("#plate-fit").addEventListener("click", plateFit);
plateHelp();
plateButtons();
