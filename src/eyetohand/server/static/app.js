// eyetohand workbench: plain JS, no build step, no external resources.
"use strict";

const $ = (sel) => document.querySelector(sel);
const state = {
  meta: null,
  pairs: null,        // records from /api/pairs/parse
  check: null,
  job: null,          // current fit job id
  history: [],
  iterations: 0,
  result: null,       // Summary of the last finished fit
  resultRequest: null,
  excluded: new Set(),
  saved: [],
  poll: null,
  imagesJob: false,   // the current job is a calibration from uploaded images
  imageFiles: new Map(),  // file name -> File, for the thumbnails
  thumbs: 0,
  etags: {},          // calibration id -> ETag of the state this page last saw (sent as If-Match)
  savedListed: null,  // the stored list (JSON) the saved table shows
};
const MAX_THUMBS = 48;

// ------------------------------------------------------------------ helpers

function fmt(x, digits = 4) {
  if (x === null || x === undefined || Number.isNaN(x)) return "–";
  return Number(x).toFixed(digits);
}
function esc(s) {
  return String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
}
function el(tag, attrs = {}, text = null) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text !== null) e.textContent = text;
  return e;
}
// a height as typed: up to 4 decimals, no trailing zeros (167.4166, 150)
function fmtZ(z) { return z === null || z === undefined ? "–" : String(Number(Number(z).toFixed(4))); }
// the offset of the first byte that is not valid UTF-8 (as Python's decoder reports it)
function firstBadUtf8(b) {
  let i = b.length >= 3 && b[0] === 0xef && b[1] === 0xbb && b[2] === 0xbf ? 3 : 0;
  while (i < b.length) {
    const c = b[i];
    const n = c < 0x80 ? 0 : c >= 0xc2 && c < 0xe0 ? 1 : c >= 0xe0 && c < 0xf0 ? 2 : c >= 0xf0 && c < 0xf5 ? 3 : -1;
    if (n < 0) return i;
    for (let k = 1; k <= n; k++) if (i + k >= b.length || (b[i + k] & 0xc0) !== 0x80) return i;
    i += n + 1;
  }
  return i;
}
// number the visible sections 1, 2, 3, … (a hidden one takes no number)
function renumber() {
  let k = 0;
  document.querySelectorAll("main > section").forEach((sec) => {
    const n = sec.querySelector("h2 .num");
    if (n && !sec.hidden) n.textContent = String(++k);
  });
}
function td(text, cls) { const c = el("td", cls ? { class: cls } : {}, text); return c; }

// A JSON body sent as written: a calibration file's text goes to the server byte for byte. JSON.parse then
// JSON.stringify would turn 0.0 into 0 and 1.0 into 1, and the file's content hash would no longer match.
class RawJson { constructor(text) { this.text = text; } }

// `ifMatchId`: a calibration this request changes: sends the ETag this page last saw of it as If-Match,
// so a change made meanwhile (another tab, another user) answers 412 instead of being overwritten
async function api(method, path, body, ifMatchId) {
  const headers = {};
  const tok = $("#token").value;
  if (tok) headers["Authorization"] = "Bearer " + tok;
  if (method !== "GET") headers["X-Requested-With"] = "eyetohand";  // the server refuses cross-site POSTs
  if (ifMatchId !== undefined && state.etags[ifMatchId]) headers["If-Match"] = state.etags[ifMatchId];
  const opts = { method, headers };
  if (body !== undefined) { headers["Content-Type"] = "application/json"; opts.body = body instanceof RawJson ? body.text : JSON.stringify(body); }
  let resp;
  try { resp = await fetch(path, opts); }
  catch (e) { return { ok: false, status: 0, data: { error: "cannot reach the server (" + e.message + ")", field: null } }; }
  let data = null;
  if (resp.status !== 204) {
    const text = await resp.text();
    try { data = text ? JSON.parse(text) : null; }
    catch { data = { error: `HTTP ${resp.status}: ${text.slice(0, 200)}`, field: null }; }
  }
  if (resp.status === 401) { $("#token-box").hidden = false; }
  if (resp.status === 412 && data && data.error) {
    data.error += ` (now version ${data.current_version}: the list is reloaded)`;
    setTimeout(refreshSaved, 0);
  }
  if (data && data.id !== undefined && data.etag) state.etags[data.id] = data.etag;
  return { ok: resp.ok, status: resp.status, data };
}

// Load a PNG of the API into the <img> `imgSel` through fetch (an <img src> cannot send the token).
// Answers {ok, status, headers, error}; a load overtaken by a newer one for the same image changes
// nothing (stale: true), so the picture always belongs to the calibration last asked for.
const imageLoads = {};
async function loadPlot(imgSel, path) {
  const n = (imageLoads[imgSel] = (imageLoads[imgSel] || 0) + 1);
  const headers = {};
  const tok = $("#token").value;
  if (tok) headers["Authorization"] = "Bearer " + tok;
  let resp;
  try { resp = await fetch(path, { headers }); }
  catch (e) { return { ok: false, status: 0, error: "cannot reach the server (" + e.message + ")" }; }
  if (n !== imageLoads[imgSel]) return { ok: false, stale: true };
  if (!resp.ok) {
    let error = `HTTP ${resp.status}`;
    try { error = (await resp.json()).error || error; } catch { /* not JSON */ }
    if (resp.status === 401) $("#token-box").hidden = false;
    return { ok: false, status: resp.status, error };
  }
  const blob = await resp.blob();
  if (n !== imageLoads[imgSel]) return { ok: false, stale: true };
  const img = $(imgSel);
  if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
  await new Promise((resolve) => { img.onload = img.onerror = resolve; img.src = URL.createObjectURL(blob); });
  return { ok: true, status: resp.status, headers: resp.headers };
}
// a header the server percent-encodes (X-Caption, X-Trust-Background)
function headerText(h, name) { try { return decodeURIComponent(h.get(name) || ""); } catch { return h.get(name) || ""; } }
// the PNG width for an image shown at most 800 CSS px wide: sharp on a high-density screen
function plotWidth() { return Math.min(1600, Math.max(320, Math.round(800 * Math.min(2, window.devicePixelRatio || 1)))); }

// Show an API error next to where it happened: the box `boxId`, plus the field's own marker.
function showError(boxId, err, scope) {
  const box = $(boxId);
  // the server's messages name their line already ("x.csv line 1: ..."): add it only when they do not
  const where = err.line && !new RegExp(`\\bline ${err.line}\\b`).test(err.error || "") ? ` (line ${err.line})` : "";
  box.textContent = (err.error || "error") + where;
  box.hidden = false;
  const field = err.field || "";
  const root = scope ? $(scope) : document;
  root.querySelectorAll(".field-err").forEach((s) => {
    if (s.dataset.field === field || field.startsWith(s.dataset.field + "[")) {
      s.textContent = err.error;
      const input = s.parentElement.querySelector("input, select");
      if (input) input.classList.add("bad");
    }
  });
  return field;
}
function clearError(boxId, scope) {
  $(boxId).hidden = true;
  $(boxId).textContent = "";
  const root = scope ? $(scope) : document;
  root.querySelectorAll(".field-err").forEach((s) => { s.textContent = ""; });
  root.querySelectorAll(".bad").forEach((e) => e.classList.remove("bad"));
}

// ------------------------------------------------------------------ 1. point pairs

async function loadPairs(set, text, source) {
  clearError(`#${set}-err`, `#loader-${set}`);
  $(`#${set}-notes`).innerHTML = "";
  const r = await api("POST", "/api/pairs/parse", { text, source });
  if (!r.ok) {
    showError(`#${set}-err`, r.data);
    $(`#${set}-text`).classList.add("bad");
    state[set] = null;
    $(`#${set}-count`).textContent = "not loaded";
    $(`#${set}-count`).classList.remove("ok");
    updateButtons();
    return;
  }
  const d = r.data;
  state[set] = d.pairs.map((p) => ({ id: p.id, u: p.u, v: p.v, x: p.x, y: p.y, z: p.z }));
  if (set === "pairs") state.excluded = new Set();
  const zs = [...new Set(state[set].map((p) => p.z))];
  const z = zs.length === 1 ? `z = ${fmtZ(zs[0])} mm`  // the height as the file gives it, not a rounded level
    : `${d.z_levels_mm.length} heights (z = ${d.z_levels_mm.map((h) => fmtZ(h)).join(", ")} mm)`;
  $(`#${set}-count`).textContent = `${d.n} pairs from ${d.source}, ${z}`;
  $(`#${set}-count`).classList.add("ok");
  for (const n of d.notes) $(`#${set}-notes`).appendChild(el("li", {}, n));
  updateButtons();
}

function wireLoader(set) {
  $(`#${set}-file`).addEventListener("change", async (ev) => {
    const f = ev.target.files[0];
    if (!f) return;
    const limit = state.meta ? state.meta.limits.max_text_chars : 16 * 2 ** 20;
    if (f.size > limit) {
      showError(`#${set}-err`, { error: `${f.name}: ${f.size} bytes, more than the ${limit} byte limit`, field: "text" });
      return;
    }
    // decode as the CLI does (strict UTF-8, a BOM allowed): a Latin-1 file is refused with its words,
    // not read with replacement characters
    const bytes = new Uint8Array(await f.arrayBuffer());
    let text;
    try { text = new TextDecoder("utf-8", { fatal: true }).decode(bytes); }
    catch {
      const bad = firstBadUtf8(bytes);
      const line = bytes.subarray(0, bad).reduce((n, b) => n + (b === 10), 1);
      clearError(`#${set}-err`, `#loader-${set}`);
      showError(`#${set}-err`, { error: `${f.name} line ${line}: not UTF-8 text (byte ${bad}); save the file as UTF-8 (in Excel: 'CSV UTF-8')`, field: "text", line });
      $(`#${set}-text`).value = "";
      state[set] = null;
      $(`#${set}-count`).textContent = "not loaded";
      $(`#${set}-count`).classList.remove("ok");
      updateButtons();
      return;
    }
    $(`#${set}-text`).value = text;
    await loadPairs(set, text, f.name);
  });
  $(`#${set}-load`).addEventListener("click", () => loadPairs(set, $(`#${set}-text`).value, "pasted text"));
}

// ------------------------------------------------------------------ 1b. from images (calibrate-images)

function imagesChosen() {
  const poses = $("#images-poses").files[0];
  const files = [...$("#images-files").files];
  const total = files.reduce((n, f) => n + f.size, 0) + (poses ? poses.size : 0);
  $("#images-count").textContent = poses || files.length
    ? `${poses ? poses.name : "no poses CSV yet"}, ${files.length} image${files.length === 1 ? "" : "s"} (${(total / 2 ** 20).toFixed(1)} MiB)`
    : "none chosen";
  $("#images-count").classList.remove("ok");
  imagesButton();
}
function imagesButton() {
  $("#images-go").disabled = !($("#images-poses").files.length && $("#images-files").files.length) || !$("#cancel").disabled;
}

function fileBase64(file) {
  return new Promise((resolve, reject) => {
    const r = new FileReader();
    r.onload = () => resolve(String(r.result).split(",", 2)[1] || "");
    r.onerror = () => reject(r.error);
    r.readAsDataURL(file);
  });
}

async function runImages() {
  clearError("#images-err", "#loader-images");
  clearError("#fit-err", "#sec-fit");
  $("#images-notes").innerHTML = "";
  const poses = $("#images-poses").files[0];
  const files = [...$("#images-files").files];
  if (!poses || !files.length) { showError("#images-err", { error: "choose the poses CSV and the images it names" }); return; }
  const limit = state.meta.limits.max_body_bytes;
  const total = files.reduce((n, f) => n + f.size, 0) + poses.size;
  if ((total * 4) / 3 + 65536 > limit) {  // sent as base64: 4 bytes per 3
    showError("#images-err", { error: `${files.length} images, ${(total / 2 ** 20).toFixed(1)} MiB: more than one upload to this server takes (about ${Math.floor((limit * 0.75) / 2 ** 20)} MiB of files); choose fewer or smaller images, or run eyetohand calibrate-images on this computer` });
    return;
  }
  $("#images-go").disabled = true;
  $("#images-hint").textContent = "reading the files…";
  const req = { poses: { name: poses.name, data_base64: await fileBase64(poses) }, images: [], polarity: $("#images-polarity").value };
  for (const f of files) req.images.push({ name: f.name, data_base64: await fileBase64(f) });
  const d = $("#images-diameter").value;
  if (d !== "") req.diameter_px = Number(d);
  const fit = fitRequest();
  for (const k of ["model", "optimizer", "objective", "particles", "iterations", "seed", "check", "target_diameter_mm"]) if (fit[k] !== undefined) req[k] = fit[k];
  state.imageFiles = new Map(files.map((f) => [f.name, f]));
  $("#images-hint").textContent = `uploading ${(total / 2 ** 20).toFixed(1)} MiB…`;
  const r = await api("POST", "/api/images/calibrate", req);
  $("#images-hint").textContent = "";
  if (!r.ok) { showError("#images-err", r.data, "#loader-images"); imagesButton(); return; }
  $("#images-table tbody").innerHTML = "";
  $("#images-table").hidden = false;
  $("#images-thumbs").innerHTML = "";
  state.thumbs = 0;
  startJob(r.data.id, req, true);
}

// the detections so far: a table row and a thumbnail (target circled) per image
function renderDetections(j) {
  const tb = $("#images-table tbody");
  for (const det of j.detections.slice(tb.children.length)) {
    const tr = el("tr", det.ok ? {} : { class: "bad" });
    tr.appendChild(td(det.image, "text"));
    tr.appendChild(td(det.ok ? "found" : "not found", det.ok ? "ok" : "no"));
    tr.appendChild(td(fmt(det.u, 3)));
    tr.appendChild(td(fmt(det.v, 3)));
    tr.appendChild(td(fmt(det.diameter_px, 2)));
    tr.appendChild(td(fmt(det.score, 3)));
    tr.appendChild(td(det.reason || "", "errcell"));
    tb.appendChild(tr);
    if (state.thumbs++ < MAX_THUMBS) thumbnail(det);
  }
  const found = j.detections.filter((d) => d.ok).length;
  $("#images-count").textContent = `${j.detections.length} of ${j.poses || "?"} images detected, target found in ${found}`;
  $("#images-count").classList.toggle("ok", j.status === "done");
}

function thumbnail(det) {
  const base = det.image.split(/[\\/]/).pop();
  const file = state.imageFiles.get(base);
  const fig = el("figure", det.ok ? {} : { class: "bad" });
  const c = el("canvas", { width: 168, height: 126 });
  fig.appendChild(c);
  const cap = el("figcaption", { title: det.ok ? det.image : det.reason }, base);
  cap.appendChild(el("br"));
  cap.appendChild(document.createTextNode(det.ok ? `(${fmt(det.u, 1)}, ${fmt(det.v, 1)}) px · score ${fmt(det.score, 2)}` : "not found"));
  fig.appendChild(cap);
  $("#images-thumbs").appendChild(fig);
  if (!file) return;
  const img = new Image();
  img.onload = () => {
    const k = c.width / img.naturalWidth;
    c.height = Math.max(1, Math.round(img.naturalHeight * k));
    const g = c.getContext("2d");
    g.drawImage(img, 0, 0, c.width, c.height);
    URL.revokeObjectURL(img.src);
    if (!det.ok) return;
    const x = det.u * k, y = det.v * k, r = Math.max(5, (det.diameter_px * k) / 2 + 3);
    g.strokeStyle = "#D55E00"; g.lineWidth = 2;
    g.beginPath(); g.arc(x, y, r, 0, 2 * Math.PI); g.stroke();
    g.beginPath(); g.moveTo(x - r - 4, y); g.lineTo(x + r + 4, y); g.moveTo(x, y - r - 4); g.lineTo(x, y + r + 4); g.stroke();
  };
  img.src = URL.createObjectURL(file);
}

function imagesFinished(j) {
  const notes = $("#images-notes");
  if (j.left_out.length) notes.appendChild(el("li", {}, `left out ${j.left_out.length} image(s) where the target was not found: ${j.left_out.join(", ")}`));
  if (j.unused_images.length) notes.appendChild(el("li", {}, `not named in the poses CSV, not used: ${j.unused_images.join(", ")}`));
  if (j.detections.length > MAX_THUMBS) notes.appendChild(el("li", {}, `the first ${MAX_THUMBS} images are shown; the table lists all`));
  if (j.status !== "done" || !j.pairs) return;
  // the detected pairs become the loaded calibration pairs: refit, compare and save work on them
  state.pairs = j.pairs.map((p) => ({ id: p.id, u: p.u, v: p.v, x: p.x, y: p.y, z: p.z }));
  state.excluded = new Set();
  $("#pairs-text").value = "";
  $("#pairs-file").value = "";
  clearError("#pairs-err", "#loader-pairs");
  $("#pairs-notes").innerHTML = "";
  $("#pairs-count").textContent = `${state.pairs.length} pairs detected in the images of ${$("#images-poses").files[0] ? $("#images-poses").files[0].name : "the poses CSV"}`;
  $("#pairs-count").classList.add("ok");
}

// ------------------------------------------------------------------ 2. model and solver

function fillSelect(sel, values, value) {
  const s = $(sel);
  s.innerHTML = "";
  for (const v of values) s.appendChild(el("option", { value: v }, v));
  if (value) s.value = value;
}

function applyPreset() {
  if ($("#preset").value !== "paper") return;
  const p = state.meta.presets.paper;
  $("#model").value = p.model;
  $("#optimizer").value = p.optimizer;
  $("#objective").value = p.objective;
  $("#particles").value = p.particles;
  $("#iterations").value = p.iterations;
  $("#seed").value = p.seed;
  updateButtons();
}

function fitRequest() {
  const req = {
    pairs: state.pairs,
    model: $("#model").value,
    optimizer: $("#optimizer").value,
    objective: $("#objective").value,
    exclude: [...state.excluded],
  };
  if (state.check) req.check = state.check;
  const num = (id) => ($(id).value === "" ? null : Number($(id).value));
  if ($("#optimizer").value.includes("pso")) {
    req.particles = num("#particles");
    req.iterations = num("#iterations");
    req.seed = num("#seed");
  }
  for (const k of ["particles", "iterations", "seed"]) if (req[k] === null) delete req[k];
  const diameter = num("#target_diameter_mm");  // the server checks it, in the words of the CLI and library
  if (diameter !== null) req.target_diameter_mm = diameter;
  return req;
}

async function runFit() {
  clearError("#fit-err", "#sec-fit");
  clearError("#fit-err");
  if (!state.pairs) { showError("#fit-err", { error: "load calibration pairs first (section 1)", field: "pairs" }); return; }
  const req = fitRequest();
  const r = await api("POST", "/api/jobs/fit", req);
  if (!r.ok) { reportFitError(r.data); return; }
  startJob(r.data.id, req);
}

function reportFitError(err) {
  const field = showError("#fit-err", err, "#sec-fit");
  const m = /^(pairs|check)\[(\d+)\]/.exec(field || "");
  if (m) {  // point at the row of the table the pair came from
    const box = m[1] === "pairs" ? "#pairs-err" : "#check-err";
    showError(box, { error: `row ${Number(m[2]) + 1} of the loaded ${m[1] === "pairs" ? "pairs" : "check points"}: ${err.error}` });
  } else if (field === "pairs" || field === "exclude" || (field || "").startsWith("exclude")) {
    $("#fit-err").textContent = err.error;
  }
}

function startJob(id, req, images = false) {
  state.job = id;
  state.plateFit = null;
  state.imagesJob = images;
  state.history = [];
  state.iterations = req.optimizer.includes("pso") ? (req.iterations || 150) : 0;
  state.resultRequest = req;
  $("#run").disabled = true;
  $("#cancel").disabled = false;
  setJobState({ status: "queued", phase: "submitted", elapsed_s: 0 });
  drawCurve();
  if (state.poll) clearTimeout(state.poll);
  pollJob();
}

async function pollJob() {
  const id = state.job;
  const images = state.imagesJob;
  const r = await api("GET", `/api/${images ? "images/jobs" : "jobs"}/${id}?since=${state.history.length}`);
  if (id !== state.job) return;
  if (!r.ok) { showError(images ? "#images-err" : "#fit-err", r.data); finishJob(); return; }
  const j = r.data;
  if (images) renderDetections(j);
  if (j.history_from === state.history.length) state.history.push(...j.history);
  if (j.iterations) state.iterations = j.iterations;
  setJobState(j);
  drawCurve();
  if (j.status === "queued" || j.status === "running") { state.poll = setTimeout(pollJob, 150); return; }
  finishJob();
  if (images) imagesFinished(j);
  if (j.status === "done") showResult(j.result, null);
  else if (j.status === "failed" && images && j.error.field !== "pairs") showError("#images-err", j.error, "#loader-images");
  else if (j.status === "failed") reportFitError(j.error);
  else showError("#fit-err", { error: "the fit was cancelled; nothing changed" });
}

function finishJob() {
  $("#run").disabled = !state.pairs;
  $("#cancel").disabled = true;
  imagesButton();
}

function setJobState(j) {
  const s = $("#job-status");
  s.textContent = j.status;
  s.className = "status-" + j.status;
  $("#job-phase").textContent = j.phase || "–";
  const n = state.history.length;
  $("#job-iter").textContent = state.iterations ? `${n} of ${state.iterations}` : (n ? "closed form / LM" : "–");
  const best = n ? state.history[n - 1] : null;
  $("#job-best").textContent = best === null ? "–" : `${fmt(best, 5)} mm`;
  $("#job-elapsed").textContent = `${fmt(j.elapsed_s, 1)} s`;
  showProgress("#job-progress", "#job-eta", j);
}

// a step counted in units (images, iterations, fits): a bar and the time it has left at its rate so far
function timeLeft(p) {
  if (p && p.done >= p.total) return `${p.total} ${p.unit} done; finishing`;
  if (!p || p.eta_s === null || p.eta_s === undefined) return p && p.done < p.total ? "estimating…" : "–";
  const s = Math.round(p.eta_s);
  return (s >= 60 ? `about ${Math.floor(s / 60)} min ${s % 60} s` : `about ${s} s`) + ` (${p.unit}: ${p.done} of ${p.total})`;
}
function showProgress(barId, textId, j) {
  const p = j.progress, bar = $(barId), running = j.status === "running" || j.status === "queued";
  bar.hidden = !p || !running;
  if (p) { bar.max = p.total; bar.value = p.done; }
  if (textId) $(textId).textContent = running ? timeLeft(p) : "–";
}

// Tick values at 1-2-5 steps covering [lo, hi] (at least 2, about `n`).
function niceTicks(lo, hi, n) {
  const raw = (hi - lo) / Math.max(n, 1);
  const p = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((m) => m * p).find((st) => st >= raw) || 10 * p;
  const out = [];
  for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + step * 1e-9; v += step) out.push(Number(v.toPrecision(12)));
  return { ticks: out, step };
}
function tickLabel(v, step) {
  const d = Math.max(0, -Math.floor(Math.log10(step) + 1e-9));
  return v.toFixed(Math.min(d, 8));
}

// The convergence curve: best fitness (mm) against iteration, log scale when it spans a decade.
// A solver that reports one value (linear, LM) is drawn as that value: a marked point and a level.
function drawCurve() {
  const c = $("#curve");
  const ctx = c.getContext("2d");
  const W = c.width, H = c.height, L = 76, R = 22, T = 12, B = 36;
  const pw = W - L - R, ph = H - T - B;
  ctx.clearRect(0, 0, W, H);
  ctx.font = "12px system-ui, sans-serif";
  ctx.fillStyle = "#5f6b7a";
  ctx.strokeStyle = "#d5dae1";
  ctx.strokeRect(L, T, pw, ph);
  ctx.textAlign = "center";
  ctx.fillText("iteration", L + pw / 2, H - 4);
  ctx.save(); ctx.translate(14, T + ph / 2); ctx.rotate(-Math.PI / 2);
  ctx.fillText("best fitness (mm)", 0, 0); ctx.restore();
  ctx.textAlign = "left";
  const pts = state.history.map((v, i) => [i, v]).filter(([, v]) => v !== null && v > 0);
  c.dataset.points = String(state.history.length);
  c.dataset.drawn = "0";
  if (!pts.length) { ctx.fillText("no iterations yet", L + 10, T + 20); return; }
  const ys = pts.map(([, v]) => v);
  const nmax = Math.max(state.iterations || 0, state.history.length);
  let lo = Math.min(...ys), hi = Math.max(...ys);
  const log = hi / lo > 10;
  if (hi - lo < 1e-9 * hi) { const pad = Math.max(Math.abs(hi) * 0.05, 1e-6); lo -= pad; hi += pad; }
  else if (!log) { const pad = (hi - lo) * 0.06; lo = Math.max(0, lo - pad); hi += pad; }
  const fy = log ? (v) => Math.log10(v) : (v) => v;
  const y0 = fy(lo), y1 = fy(hi);
  const X = (i) => L + pw * (nmax > 1 ? i / (nmax - 1) : 0.5);
  const Y = (v) => T + ph * (1 - (fy(v) - y0) / (y1 - y0 || 1));
  // y ticks: 1-2-5 steps (decades on a log scale)
  const yt = log ? { ticks: [], step: 1 } : niceTicks(lo, hi, 4);
  if (log) for (let e = Math.ceil(y0); e <= Math.floor(y1); e++) for (const m of [1, 2, 5]) { const v = m * 10 ** e; if (v >= lo && v <= hi) yt.ticks.push(v); }
  for (const v of yt.ticks) {
    const y = Y(v);
    ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(W - R, y); ctx.strokeStyle = "#eef0f3"; ctx.stroke();
    ctx.textAlign = "right";
    ctx.fillText(log ? String(Number(v.toPrecision(3))) : tickLabel(v, yt.step), L - 4, y + 4);
  }
  // x ticks: whole iterations 1..nmax, the last label kept inside the canvas
  if (nmax > 1) {
    const xt = niceTicks(1, nmax, 5);
    const ticks = [1, ...xt.ticks.filter((i) => i > 1 && Number.isInteger(i))];
    for (const i of ticks) {
      const x = X(i - 1);
      ctx.textAlign = x > W - R - 12 ? "right" : x < L + 12 ? "left" : "center";
      ctx.fillText(String(i), Math.min(x, W - 2), H - B + 16);
    }
  }
  ctx.textAlign = "left";
  ctx.strokeStyle = "#1f5fae"; ctx.fillStyle = "#1f5fae"; ctx.lineWidth = 2;
  if (pts.length === 1) {  // one value: the level across the plot and the point on it
    const y = Y(pts[0][1]);
    ctx.setLineDash([6, 4]); ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(W - R, y); ctx.stroke(); ctx.setLineDash([]);
    ctx.beginPath(); ctx.arc(X(pts[0][0]), y, 5, 0, 2 * Math.PI); ctx.fill();
    ctx.fillStyle = "#5f6b7a";
    ctx.fillText(`${fmt(pts[0][1], 5)} mm: the solver's final value (it reports no iterations)`, L + 8, y - 10);
  } else {
    ctx.beginPath();
    pts.forEach(([i, v], k) => { const x = X(i), y = Y(v); if (k === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y); });
    ctx.stroke();
    ctx.fillStyle = "#5f6b7a";
  }
  ctx.lineWidth = 1;
  c.dataset.drawn = String(pts.length);
  if (log) ctx.fillText("log scale", W - R - 60, T + 14);
}

// ------------------------------------------------------------------ 4. result

function statsRow(tbody, label, s) {
  if (!s) return;
  const tr = el("tr");
  tr.appendChild(td(label, "text"));
  tr.appendChild(td(String(s.n)));
  for (const k of ["rms_mm", "mean_mm", "p95_mm", "max_mm"]) tr.appendChild(td(fmt(s[k])));
  tr.appendChild(td(s.outliers.length ? "id " + s.outliers.join(", ") : "none", "text"));
  tbody.appendChild(tr);
}

// `saved`: {id, name, version} when the result is a stored calibration, else null (an unsaved fit).
function showResult(sum, saved) {
  state.result = sum;
  state.resultSaved = saved;
  state.excluded = new Set(sum.excluded_ids);
  $("#sec-result").hidden = false;
  setResultTitle();
  const tb = $("#stats-table tbody");
  tb.innerHTML = "";
  statsRow(tb, "calibration pairs (fit)", sum.train);
  statsRow(tb, "leave-one-out", sum.loo);
  statsRow(tb, "check points", sum.check);
  statsRow(tb, "excluded pairs", sum.excluded);
  // the expected accuracy (the error budget) as `eyetohand calibrate` prints it, for every fit
  const acc = sum.expected_accuracy;
  $("#result-accuracy").textContent = acc ? acc.line : "expected accuracy: not known (the calibration records no uncertainty)";
  const notes = $("#result-notes");
  notes.innerHTML = "";
  for (const n of sum.notes) notes.appendChild(el("li", {}, n));
  if (sum.selection) notes.appendChild(el("li", {}, `auto: chose ${sum.selection.chosen} — ${sum.selection.reason}`));
  renderTrainTable(sum);
  renderCheckTable(sum);
  drawVectors(sum);
  showTrustMap(saved);
  state.history = sum.history.slice();
  state.iterations = sum.optimizer.includes("pso") ? sum.history.length : 0;
  drawCurve();
  $("#map-z").placeholder = sum.plane_z_mm !== null && sum.plane_z_mm !== undefined ? `plane ${fmtZ(sum.plane_z_mm)}` : sum.uses_z ? "height" : "plane";
  clearMapResult();  // the answer on screen was another calibration's
  renumber();
  $("#save-state").textContent = saved ? `this is “${saved.name}” v${saved.version}` : "not saved yet";
  updateButtons();
  refreshMapSources(saved ? `cal:${saved.id}` : "job");
}

// the trust map of a saved version (the server draws it, ~2 s the first time): σ over the image
async function showTrustMap(saved) {
  const fig = $("#trust-fig"), st = $("#trust-state");
  if (!saved) {
    imageLoads["#trust-map"] = (imageLoads["#trust-map"] || 0) + 1;  // a load under way is for another
    fig.hidden = true;
    st.textContent = "save the fit to see its trust map";
    return;
  }
  st.textContent = "drawing…";
  const r = await loadPlot("#trust-map", `/api/calibrations/${saved.id}/trust-map.png?version=${saved.version}&width=${plotWidth()}`);
  if (r.stale) return;
  if (!r.ok) { fig.hidden = true; st.textContent = `no trust map: ${r.error}`; return; }
  const caption = headerText(r.headers, "X-Caption");
  const under = headerText(r.headers, "X-Trust-Background");
  $("#trust-map").alt = caption || "the trust map of this calibration";
  $("#trust-map").title = caption;
  st.textContent = `“${saved.name}” v${saved.version}` + (under.startsWith("the camera") ? `, over ${under}` : "");
  fig.hidden = false;
}

function setResultTitle() {
  const sum = state.result, saved = state.resultSaved;
  const what = saved ? `saved “${saved.name}” version ${saved.version}` : "unsaved fit";
  $("#result-title").textContent =
    `${what}: model ${sum.model}, ${sum.optimizer}, objective ${sum.objective}, fitness ${fmt(sum.fitness_mm, 5)} mm, ` +
    `${sum.n_pairs} pairs, ${fmt(sum.seconds, 2)} s`;
}

function renderTrainTable(sum) {
  const tb = $("#train-table tbody");
  tb.innerHTML = "";
  const loo = new Map((sum.loo ? sum.loo.points : []).map((p) => [p.id, p.error_mm]));
  const pts = new Map(sum.train.points.map((p) => [p.id, p]));
  const ex = new Map((sum.excluded ? sum.excluded.points : []).map((p) => [p.id, p]));
  const uv = new Map([...sum.vectors.train, ...sum.vectors.excluded].map((v) => [v.id, v]));
  const ids = [...sum.vectors.train, ...sum.vectors.excluded].map((v) => v.id);
  for (const id of ids) {
    const p = pts.get(id) || ex.get(id);
    const excluded = ex.has(id);
    const tr = el("tr", { "data-id": id });
    if (excluded) tr.classList.add("excluded");
    if (p.outlier) tr.classList.add("outlier");
    const cb = el("input", { type: "checkbox", "aria-label": `use pair ${id}` });
    cb.checked = !state.excluded.has(id);
    cb.addEventListener("change", () => {
      if (cb.checked) state.excluded.delete(id); else state.excluded.add(id);
      $("#refit-hint").textContent = state.excluded.size ? `${state.excluded.size} pair(s) to leave out: ${[...state.excluded].join(", ")}` : "";
    });
    const c0 = el("td"); c0.appendChild(cb); tr.appendChild(c0);
    tr.appendChild(td(id, "text"));
    tr.appendChild(td(fmt(uv.get(id).u, 2)));
    tr.appendChild(td(fmt(uv.get(id).v, 2)));
    for (const k of ["dx_mm", "dy_mm", "dz_mm", "error_mm"]) tr.appendChild(td(fmt(p[k])));
    tr.appendChild(td(excluded ? "(excluded)" : fmt(loo.get(id))));
    tb.appendChild(tr);
  }
  $("#refit-hint").textContent = "";
}

function renderCheckTable(sum) {
  const tb = $("#check-table tbody");
  tb.innerHTML = "";
  $("#check-block").hidden = !sum.check;
  if (!sum.check) return;
  const src = new Map((state.check || []).map((p) => [p.id, p]));
  const uv = new Map(sum.vectors.check.map((v) => [v.id, v]));
  for (const p of sum.check.points) {
    const tr = el("tr", { "data-id": p.id });
    if (p.outlier) tr.classList.add("outlier");
    const s = src.get(p.id) || {};
    tr.appendChild(td(p.id, "text"));
    tr.appendChild(td(fmt(uv.get(p.id).u, 2)));
    tr.appendChild(td(fmt(uv.get(p.id).v, 2)));
    tr.appendChild(td(fmt(s.x)));
    tr.appendChild(td(fmt(s.y)));
    for (const k of ["dx_mm", "dy_mm", "dz_mm", "error_mm"]) tr.appendChild(td(fmt(p[k])));
    tb.appendChild(tr);
  }
}

// Residual vectors over the image: each pair at its (u, v); the arrow is the image displacement
// that its robot-space error corresponds to, magnified so that the largest is ~8 % of the frame.
function drawVectors(sum) {
  const svg = $("#vectors");
  const NS = "http://www.w3.org/2000/svg";
  svg.innerHTML = "";
  const groups = [["train", sum.vectors.train, sum.train, "var(--train)"],
                  ["check", sum.vectors.check, sum.check, "var(--check)"],
                  ["excluded", sum.vectors.excluded, sum.excluded, "var(--excl)"]];
  const all = groups.flatMap((g) => g[1]);
  if (!all.length) return;
  const us = all.map((p) => p.u), vs = all.map((p) => p.v);
  let u0 = Math.min(...us), u1 = Math.max(...us), v0 = Math.min(...vs), v1 = Math.max(...vs);
  const span = Math.max(u1 - u0, v1 - v0, 1);
  const pad = span * 0.12;
  u0 -= pad; u1 += pad; v0 -= pad; v1 += pad;
  const Wv = 800, Hv = Math.max(300, Math.min(640, 800 * (v1 - v0) / (u1 - u0)));
  svg.setAttribute("viewBox", `0 0 ${Wv} ${Hv + 30}`);
  const sx = Wv / (u1 - u0), sy = Hv / (v1 - v0), s = Math.min(sx, sy);
  const X = (u) => (u - u0) * s, Y = (v) => (v - v0) * s;
  const lens = all.map((p) => Math.hypot(p.du_px || 0, p.dv_px || 0)).filter((x) => x > 0);
  const maxLen = lens.length ? Math.max(...lens) : 1;
  const gain = (0.08 * Math.hypot(Wv, Hv)) / (maxLen * s);
  const mk = (tag, attrs) => { const e = document.createElementNS(NS, tag); for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v); return e; };
  const defs = mk("defs", {});
  for (const [name, , , color] of groups) {
    const m = mk("marker", { id: `arrow-${name}`, viewBox: "0 0 10 10", refX: "9", refY: "5", markerWidth: "7", markerHeight: "7", orient: "auto-start-reverse" });
    m.appendChild(mk("path", { d: "M0,0 L10,5 L0,10 z", fill: color }));
    defs.appendChild(m);
  }
  svg.appendChild(defs);
  svg.appendChild(mk("rect", { x: 0, y: 0, width: Wv, height: Hv, fill: "none", stroke: "#d5dae1" }));
  // heights told apart by the marker's shape (data at one height: circles only)
  const zOf = new Map([...(state.pairs || []), ...(state.check || [])].map((p) => [p.id, p.z]));
  const levels = [...new Set(all.map((p) => zOf.get(p.id)).filter((z) => z !== undefined))].sort((a, b) => a - b);
  const SHAPES = ["circle", "square", "triangle", "diamond"];
  const shapeOf = (id) => (levels.length > 1 ? SHAPES[Math.max(0, levels.indexOf(zOf.get(id))) % SHAPES.length] : "circle");
  const marker = (shape, x, y, color) => {
    if (shape === "circle") return mk("circle", { cx: x, cy: y, r: 4, fill: color });
    if (shape === "square") return mk("rect", { x: x - 4, y: y - 4, width: 8, height: 8, fill: color });
    const d = shape === "triangle" ? `M${x},${y - 5} L${x + 5},${y + 4} L${x - 5},${y + 4} z`
      : `M${x},${y - 5} L${x + 5},${y} L${x},${y + 5} L${x - 5},${y} z`;
    return mk("path", { d, fill: color });
  };
  const placed = [];  // label boxes already drawn: a label that would overlap one is left to the tooltip
  const free = (x, y, w) => placed.every((b) => x + w < b.x || b.x + b.w < x || y < b.y - 12 || b.y < y - 12);
  for (const [name, vecs, stats, color] of groups) {
    if (!stats) continue;
    const err = new Map(stats.points.map((p) => [p.id, p]));
    for (const p of vecs) {
      const g = mk("g", { class: `pt pt-${name}`, "data-id": p.id });
      const e = err.get(p.id);
      const title = mk("title", {});
      const zs = zOf.has(p.id) ? `, z ${fmtZ(zOf.get(p.id))} mm` : "";
      title.textContent = `${name} ${p.id}: u ${fmt(p.u, 1)} px, v ${fmt(p.v, 1)} px${zs}; error ${fmt(e.error_mm)} mm ` +
        `(dx ${fmt(e.dx_mm)}, dy ${fmt(e.dy_mm)} mm)`;
      g.appendChild(title);
      const shape = shapeOf(p.id);
      const m = marker(shape, X(p.u), Y(p.v), color);
      m.setAttribute("class", "mark");
      m.dataset.shape = shape;
      g.appendChild(m);
      if (p.du_px !== null && p.dv_px !== null) {
        g.appendChild(mk("line", { x1: X(p.u), y1: Y(p.v), x2: X(p.u) + p.du_px * gain * s, y2: Y(p.v) + p.dv_px * gain * s,
          stroke: color, "stroke-width": 1.6, "marker-end": `url(#arrow-${name})` }));
      }
      const w = 6.5 * String(p.id).length, tx = X(p.u) + 6, ty = Y(p.v) - 6;
      if (free(tx, ty, w)) {
        const t = mk("text", { x: tx, y: ty, "font-size": 11, fill: "#5f6b7a" });
        t.textContent = p.id;
        g.appendChild(t);
        placed.push({ x: tx, y: ty, w });
      }
      svg.appendChild(g);
    }
  }
  // frame labels in image pixels
  const lab = (x, y, txt, anchor) => { const t = mk("text", { x, y, "font-size": 11, fill: "#5f6b7a", "text-anchor": anchor }); t.textContent = txt; svg.appendChild(t); };
  lab(4, Hv + 14, `u ${fmt(u0, 0)} px`, "start");
  lab(Wv - 4, Hv + 14, `u ${fmt(u1, 0)} px`, "end");
  lab(4, 14, `v ${fmt(v0, 0)} px`, "start");
  lab(4, Hv - 4, `v ${fmt(v1, 0)} px`, "start");
  svg.dataset.gain = String(gain);
  svg.dataset.levels = String(levels.length);
  const GLYPH = { circle: "●", square: "■", triangle: "▲", diamond: "◆" };
  const heights = levels.length > 1
    ? " Heights: " + levels.map((z, k) => `${GLYPH[SHAPES[k % SHAPES.length]]} z = ${fmtZ(z)} mm`).join(", ") + "."
    : "";
  $("#vectors-caption").innerHTML =
    `Residual vectors over the image (u right, v down). <b style="color:var(--train)">●</b> calibration pairs, ` +
    `<b style="color:var(--check)">●</b> check points, <b style="color:var(--excl)">●</b> excluded. ` +
    `Each arrow is the image displacement equivalent to the pair's robot-space error, magnified ×${gain.toPrecision(3)}; ` +
    `the tables give the errors in mm.${esc(heights)} Labels that would overlap are left out: hover a point for its values.`;
}

// ------------------------------------------------------------------ 5. save

async function saveResult(asVersion) {
  clearError("#save-err", "#sec-save");
  const body = { note: $("#save-note").value };
  if (asVersion) {
    body.calibration_id = Number($("#save-target").value);
    if (!body.calibration_id) { showError("#save-err", { error: "no saved calibration to add a version to", field: "calibration_id" }); return; }
  } else {
    body.name = $("#save-name").value.trim();
    if (!body.name) { showError("#save-err", { error: "name: give the calibration a name", field: "name" }, "#sec-save"); return; }
  }
  if (state.plateFit && !state.job) { await savePlateFit(asVersion, body.note); return; }  // plate.js
  const r = await api("POST", `/api/jobs/${state.job}/save`, body, asVersion ? body.calibration_id : undefined);
  if (!r.ok) { showError("#save-err", r.data, "#sec-save"); return; }
  await showSaved(r.data);
}

// the result section after a save (a job's fit here, a plate fit in plate.js): its name, trust map, lists
async function showSaved(d) {
  $("#save-state").textContent = `saved as “${d.name}” (id ${d.id}) version ${d.version}`;
  state.resultSaved = { id: d.id, name: d.name, version: d.version };
  setResultTitle();
  showTrustMap(state.resultSaved);
  await refreshSaved();
  refreshMapSources(`cal:${d.id}`);
}

// ------------------------------------------------------------------ 6. map a point

function refreshMapSources(select) {
  const s = $("#map-source");
  const prev = select || s.value;
  s.innerHTML = "";
  if (state.job && state.result) s.appendChild(el("option", { value: "job" }, "last fit (unsaved result)"));
  for (const c of state.saved) s.appendChild(el("option", { value: `cal:${c.id}` }, `${c.name} (id ${c.id}, v${c.current_version})`));
  if ([...s.options].some((o) => o.value === prev)) s.value = prev;
  showDiameterField();
}

// The circle diameter whose centres the chosen calibration maps (fitted with a target diameter), or
// null: image points as detected. Such a calibration maps a detection with its part's diameter.
function mapCircleDiameter() {
  const src = $("#map-source").value;
  if (src === "job") return state.result ? state.result.circle_diameter_mm ?? null : null;
  const c = state.saved.find((x) => `cal:${x.id}` === src);
  return c ? c.circle_diameter_mm ?? null : null;
}
function showDiameterField() {
  const d = mapCircleDiameter();
  $("#map-diameter-box").hidden = d === null;
  $("#map-diameter-hint").textContent = d === null ? "" : `it maps the centres of ${d} mm circles`;
}

const MAP_EMPTY = "x – mm, y – mm, z – mm";

// The map box shows one answer at a time: a new error replaces the previous result, never sits beside it.
function clearMapResult() {
  $("#map-out").textContent = MAP_EMPTY;
  $("#map-out").classList.add("empty");
  $("#map-extra").textContent = "";
  $("#map-extra").className = "hint";
}

function mapError(err) {
  clearMapResult();
  showError("#map-err", err);
  const f = err.field || "";  // points[0] (outside), points[0].z / z (height), angles, points[0][k]
  const mark = (id) => $(id).classList.add("bad");
  if (/^points\[0\]$/.test(f)) { mark("#map-u"); mark("#map-v"); }
  else if (/(^|\.)z$/.test(f)) mark("#map-z");
  else if (f.startsWith("angles")) mark("#map-angle");
  else if (f.startsWith("symmetry")) mark("#map-symmetry");
  else if (f.startsWith("tool_rz")) mark("#map-tool");
  else if (f.endsWith("part_diameter_mm")) mark("#map-diameter");
  else if (f === "points[0][0]") mark("#map-u");
  else if (f === "points[0][1]") mark("#map-v");
}

async function mapPoint() {
  clearError("#map-err", "#sec-map");
  const src = $("#map-source").value;
  if (!src) { mapError({ error: "no calibration: run a fit or save one first" }); return; }
  const u = $("#map-u").value, v = $("#map-v").value, z = $("#map-z").value, a = $("#map-angle").value;
  const missing = [["points[0][0]", u, "u"], ["points[0][1]", v, "v"]].filter((x) => x[1] === "");
  if (missing.length) { mapError({ error: `${missing[0][2]}: type a number of pixels`, field: missing[0][0] }); return; }
  const body = { points: [[Number(u), Number(v)]], allow_outside: $("#map-allow").checked };
  if (z !== "") body.z = Number(z);  // the server refuses a z off a single-height calibration's plane
  if (a !== "") body.angles = [Number(a)];
  const sym = $("#map-symmetry").value, tool = $("#map-tool").value;
  // the part's diameter, where the calibration maps circle centres; left empty the server refuses a
  // detection whose bias exceeds its predicted error, in its own words (shown as they come)
  const dia = $("#map-diameter").value;
  if (!$("#map-diameter-box").hidden && dia !== "") body.part_diameter_mm = Number(dia);
  if (sym !== "" && sym !== "1") body.symmetry = Number(sym);
  if (tool !== "") body.tool_rz_offset_deg = Number(tool);
  const path = src === "job" ? `/api/jobs/${state.job}/image-to-robot` : `/api/calibrations/${src.slice(4)}/image-to-robot`;
  const r = await api("POST", path, body);
  if (!r.ok) { mapError(r.data); return; }
  const d = r.data, p = d.points[0];
  const rz = d.rz_deg ? `, rz ${fmt(d.rz_deg[0], 3)} deg` : "";
  $("#map-out").textContent = `x ${fmt(p[0])} mm, y ${fmt(p[1])} mm, z ${fmt(p[2])} mm${rz}`;
  $("#map-out").classList.remove("empty");
  const sigma = d.sigma_mm ? `predicted error σ ${fmt(d.sigma_mm[0])} mm` : "no σ";
  const inside = d.inside[0];
  $("#map-extra").textContent = `${sigma} · ` + (inside ? "inside the calibrated region"
    : "OUTSIDE the calibrated region (mapped because “allow outside” is ticked): do not trust it");
  $("#map-extra").className = inside ? "hint inside" : "warn outside";
}

// ------------------------------------------------------------------ 7. compare methods

async function compareMethods() {
  clearError("#compare-err");
  if (!state.pairs || !state.check) { showError("#compare-err", { error: "load calibration pairs and check points first (section 1)" }); return; }
  const used = state.pairs.filter((p) => !state.excluded.has(p.id));  // the pairs a fit would use
  if (used.length < state.pairs.length) $("#compare-note").textContent = `on ${used.length} pairs: the ${state.pairs.length - used.length} unticked in section “Result” are left out, as in the fit`;
  else $("#compare-note").textContent = "";
  $("#compare-go").disabled = true;
  const r = await api("POST", "/api/jobs/compare", { pairs: used, check: state.check, seed: 0 });
  if (!r.ok) { showError("#compare-err", r.data); $("#compare-go").disabled = false; return; }
  const id = r.data.id;
  const tick = async () => {
    const q = await api("GET", `/api/jobs/${id}`);
    if (!q.ok) { showError("#compare-err", q.data); $("#compare-go").disabled = false; return; }
    const j = q.data;
    const phase = j.phase && j.phase !== j.status ? `: ${j.phase}` : "";
    const running = j.status === "queued" || j.status === "running";
    const left = running && j.progress ? `; time left ${timeLeft(j.progress)}` : "";
    $("#compare-state").textContent = `${j.status}${phase} (${fmt(j.elapsed_s, 1)} s${left})`;
    showProgress("#compare-progress", null, j);
    if (j.status === "queued" || j.status === "running") { setTimeout(tick, 300); return; }
    $("#compare-go").disabled = false;
    if (j.status !== "done") { showError("#compare-err", j.error || { error: j.status }); return; }
    renderCompare(j.compare);
  };
  tick();
}

function renderCompare(rows) {
  const tb = $("#compare-table tbody");
  tb.innerHTML = "";
  const ok = rows.filter((r) => !r.error && r.check_rms_mm !== null);
  const best = ok.length ? Math.min(...ok.map((r) => r.check_rms_mm)) : null;
  const top = ok.find((r) => r.check_rms_mm === best);
  $("#compare-caption").textContent = top
    ? `Highlighted: ${top.model} + ${top.optimizer}, the lowest check RMS — ranked on the check points alone. ` +
      "Model “auto” chooses by cross-validation on the calibration pairs and never sees the check points, " +
      "so it may choose another model; compare the check max too."
    : "";
  for (const r of rows) {
    const tr = el("tr");
    tr.appendChild(td(r.model, "text"));
    tr.appendChild(td(r.optimizer, "text"));
    if (r.error) {
      const c = td(r.error, "errcell"); c.colSpan = 4; tr.appendChild(c); tr.classList.add("bad");
    } else {
      if (r.check_rms_mm === best) tr.classList.add("best");
      tr.appendChild(td(fmt(r.fitness_mm, 5)));
      tr.appendChild(td(fmt(r.check_rms_mm)));
      tr.appendChild(td(fmt(r.check_max_mm)));
      tr.appendChild(td(fmt(r.seconds, 2)));
    }
    tb.appendChild(tr);
  }
  $("#compare-table").hidden = false;
}

// ------------------------------------------------------------------ 8. saved calibrations

async function refreshSaved() {
  const r = await api("GET", "/api/calibrations");
  if (!r.ok) { showError("#saved-err", r.data); return; }
  state.saved = r.data;
  for (const c of r.data) state.etags[c.id] = c.etag;
  // the same list as the one shown keeps its rows: a rebuild between a click's press and release lost
  // the click (two refreshes in flight after a token change) and unticked the boxes
  const listed = JSON.stringify(r.data);
  const rebuild = listed !== state.savedListed;
  state.savedListed = listed;
  const tb = $("#saved-table tbody");
  if (rebuild) tb.innerHTML = "";
  const target = $("#save-target");
  const prevTarget = target.value;
  target.innerHTML = "";
  for (const c of r.data) {
    target.appendChild(el("option", { value: c.id }, `${c.name} (id ${c.id})`));
    if (!rebuild) continue;
    const tr = el("tr", { "data-id": c.id });
    const cb = el("input", { type: "checkbox", class: "pick", value: c.id, "aria-label": `pick ${c.name}` });
    const c0 = el("td"); c0.appendChild(cb); tr.appendChild(c0);
    tr.appendChild(td(c.name, "text name"));
    // the actions next to the name, where a 1024 px touch panel shows them without scrolling sideways
    const acts = el("td", { class: "text acts" });
    const btn = (label, fn, cls) => { const b = el("button", { type: "button", class: "link " + (cls || "") }, label); b.addEventListener("click", fn); acts.appendChild(b); };
    btn("open", () => openSaved(c.id));
    btn("history", () => { showVersions(c.id); showChecks(c); });
    btn("checks", () => showChecks(c));
    const a = el("a", { href: `/api/calibrations/${c.id}/export`, download: "", class: "link" }, "export JSON");
    a.addEventListener("click", (ev) => { if ($("#token").value) { ev.preventDefault(); exportWithToken(c.id); } });
    acts.appendChild(a);
    btn("delete", () => deleteSaved(c), "danger");
    tr.appendChild(acts);
    tr.appendChild(td(String(c.id)));
    tr.appendChild(td(String(c.current_version)));
    tr.appendChild(td(c.model, "text"));
    tr.appendChild(td(c.optimizer, "text"));
    tr.appendChild(td(fmt(c.fitness_mm, 5)));
    tr.appendChild(td(fmt(c.train_rms_mm)));
    tr.appendChild(td(fmt(c.check_rms_mm)));
    tr.appendChild(td(c.updated_utc.replace("T", " ").slice(0, 19), "text"));
    tb.appendChild(tr);
  }
  if ([...target.options].some((o) => o.value === prevTarget)) target.value = prevTarget;
  $("#db-info").textContent = `${r.data.length} stored`;
  refreshMapSources();
  updateButtons();
}

// import a calibration file (eyetohand calibrate -o): a new calibration, or a new version of that name
async function importFile() {
  clearError("#saved-err");
  const f = $("#import-file").files[0];
  if (!f) { showError("#saved-err", { error: "choose a calibration file (.json) to import", field: "file" }); return; }
  const text = await f.text();
  try { JSON.parse(text); } catch (e) { showError("#saved-err", { error: `${f.name}: not JSON (${e.message})` }); return; }
  const name = $("#import-name").value.trim() || f.name.replace(/\.json$/i, "");
  const note = `imported ${f.name}`.slice(0, 200);
  const body = `{"name": ${JSON.stringify(name)}, "note": ${JSON.stringify(note)}, "calibration": ${text}}`;
  const r = await api("POST", "/api/calibrations/import", new RawJson(body));
  if (!r.ok) { showError("#saved-err", r.data); return; }
  await refreshSaved();
}

// the verification history of one calibration: a table, with a bar per check scaled to the worst max
async function showChecks(c) {
  clearError("#saved-err");
  const r = await api("GET", `/api/calibrations/${c.id}/history`);
  if (!r.ok) { showError("#saved-err", r.data); return; }
  $("#checks-name").textContent = `“${r.data.name}”` + (r.data.entries.length ? "" : " — none yet");
  $("#checks-table").hidden = !r.data.entries.length;
  showDrift(c.id, r.data.entries.length + (r.data.collection_checks || 0));
  const tb = $("#checks-table tbody");
  tb.innerHTML = "";
  const worst = Math.max(1e-9, ...r.data.entries.map((e) => e.max_mm));
  for (const e of r.data.entries) {
    const tr = el("tr");
    tr.appendChild(td(e.utc.replace("T", " ").slice(0, 19), "text"));
    for (const v of [String(e.version), String(e.n), fmt(e.rms_mm), fmt(e.max_mm)]) tr.appendChild(td(v));
    tr.appendChild(td("█".repeat(Math.max(1, Math.round(12 * e.max_mm / worst))), "text"));
    tr.appendChild(td(`${fmt(e.shift_px[0], 2)}, ${fmt(e.shift_px[1], 2)}`));
    tr.appendChild(td(fmt(e.rotation_deg, 4)));
    tr.appendChild(td(fmt(100 * e.scale_change, 3)));
    tr.appendChild(td((e.passed ? "pass" : "FAIL") + (e.drift_significant ? ` — moved: ${e.named.join(", ")}` : ""), "text"));
    tb.appendChild(tr);
  }
  $("#checks-block").hidden = false;
}

// the checks over time as the server draws them (the verifications and the collection's CAL CHECKs)
async function showDrift(id, checks) {
  const fig = $("#drift-fig");
  if (!checks) {  // nothing to draw (the server would answer 404)
    imageLoads["#drift-img"] = (imageLoads["#drift-img"] || 0) + 1;
    fig.hidden = true;
    return;
  }
  const r = await loadPlot("#drift-img", `/api/calibrations/${id}/drift.png?width=${plotWidth()}`);
  if (r.stale) return;
  fig.hidden = !r.ok;  // 404: no checks yet (the heading says so)
  if (r.ok) $("#drift-img").dataset.checks = r.headers.get("X-Checks") || "";
}

async function exportWithToken(id) {
  const resp = await fetch(`/api/calibrations/${id}/export`, { headers: { Authorization: "Bearer " + $("#token").value } });
  if (!resp.ok) { showError("#saved-err", { error: `export failed: HTTP ${resp.status}` }); return; }
  const blob = await resp.blob();
  const a = el("a", { href: URL.createObjectURL(blob), download: `calibration-${id}.json` });
  document.body.appendChild(a); a.click(); a.remove();
}

async function openSaved(id, version) {
  clearError("#saved-err");
  const r = await api("GET", `/api/calibrations/${id}` + (version ? `?version=${version}` : ""));
  if (!r.ok) { showError("#saved-err", r.data); return; }
  const d = r.data;
  state.pairs = d.pairs; state.check = d.check;
  $("#pairs-count").textContent = `${d.pairs.length} pairs from “${d.name}” v${d.version}`;
  $("#check-count").textContent = d.check ? `${d.check.length} pairs from “${d.name}” v${d.version}` : "none loaded";
  const req = d.request;
  for (const k of ["model", "optimizer", "objective"]) $("#" + k).value = req[k];
  for (const k of ["particles", "iterations", "seed"]) $("#" + k).value = req[k] ?? "";
  $("#preset").value = "custom";
  state.job = null;
  state.plateFit = null;
  showResult(d.summary, { id: d.id, name: d.name, version: d.version });
  $("#save-target").value = String(d.id);
  $("#sec-result").scrollIntoView({ behavior: "smooth" });
}

// who signed a version and when; the version in force that waits for a signature (serve
// --require-signed) says so in the server's words, an older unsigned one just "unsigned"
function signatureCell(v, current) {
  const s = v.signature;
  if (s) return td(`signed by ${s.signed_by}, ${s.signed_utc.replace("T", " ").slice(0, 19)}` + (s.origin === "sign" ? "" : ` (${s.origin})`), "text sig signed");
  if (v.waiting && current) return td(v.waiting, "text sig warn waiting");
  return td(v.waiting ? "unsigned: not mapped with" : "unsigned", "text sig unsigned");
}

// POST …/versions/{v}/sign with the page's token: the server refuses a token that is not a signer's
// (403), a version signed already (409); its words are shown under the history
async function signVersion(id, version) {
  clearError("#versions-err");
  const r = await api("POST", `/api/calibrations/${id}/versions/${version}/sign`);
  if (!r.ok) { showError("#versions-err", r.data); return; }
  await showVersions(id);
}

async function showVersions(id) {
  clearError("#versions-err");
  const r = await api("GET", `/api/calibrations/${id}/versions`);
  if (!r.ok) { showError("#saved-err", r.data); return; }
  const d = r.data;
  $("#versions-block").hidden = false;
  $("#versions-name").textContent = `“${d.name}” (current: version ${d.current_version})`;
  fillDiffControl(id, d);
  showAudit(id);
  const tb = $("#versions-table tbody");
  tb.innerHTML = "";
  for (const v of d.versions.slice().reverse()) {
    const tr = el("tr");
    if (v.version === d.current_version) tr.classList.add("best");
    tr.appendChild(td(String(v.version)));
    tr.appendChild(td(v.created_utc.replace("T", " ").slice(0, 19), "text"));
    tr.appendChild(td(v.note, "text"));
    tr.appendChild(td(v.model, "text"));
    tr.appendChild(td(v.optimizer, "text"));
    tr.appendChild(td(fmt(v.fitness_mm, 5)));
    tr.appendChild(td(fmt(v.train_rms_mm)));
    tr.appendChild(td(fmt(v.check_rms_mm)));
    tr.appendChild(signatureCell(v, v.version === d.current_version));
    const acts = el("td", { class: "text" });
    const open = el("button", { type: "button", class: "link" }, "open");
    open.addEventListener("click", () => openSaved(id, v.version));
    acts.appendChild(open);
    // a signer signs with the server's key (the server says whether it has one); its token decides
    if (!v.signature && state.meta.signing.key_id) {
      const sb = el("button", { type: "button", class: "link sign" }, "sign");
      sb.addEventListener("click", () => signVersion(id, v.version));
      acts.appendChild(sb);
    }
    if (v.version !== d.current_version) {
      const rb = el("button", { type: "button", class: "link" }, "roll back to this");
      rb.addEventListener("click", async () => {
        const q = await api("POST", `/api/calibrations/${id}/rollback`, { version: v.version }, id);
        if (!q.ok) { showError("#saved-err", q.data); return; }
        await refreshSaved(); await showVersions(id);
      });
      acts.appendChild(rb);
    }
    tr.appendChild(acts);
    tb.appendChild(tr);
  }
}

async function deleteSaved(c) {
  if (!window.confirm(`Delete “${c.name}” and its ${c.current_version} version(s)? This cannot be undone.`)) return;
  const r = await api("DELETE", `/api/calibrations/${c.id}`, undefined, c.id);
  if (!r.ok) { showError("#saved-err", r.data); return; }
  $("#versions-block").hidden = true;
  $("#checks-block").hidden = true;
  await refreshSaved();
}

async function compareSaved() {
  clearError("#saved-err");
  const ids = [...document.querySelectorAll("#saved-table input.pick:checked")].map((x) => Number(x.value));
  if (!ids.length) { showError("#saved-err", { error: "tick one or more calibrations to compare" }); return; }
  const tb = $("#saved-compare-table tbody");
  tb.innerHTML = "";
  for (const id of ids) {
    const r = await api("GET", `/api/calibrations/${id}`);
    if (!r.ok) { showError("#saved-err", r.data); continue; }
    const d = r.data, s = d.summary;
    let ev = null;
    if (state.check) {
      const q = await api("POST", `/api/calibrations/${id}/evaluate`, { pairs: state.check, allow_outside: true });
      ev = q.ok ? q.data : null;
      if (!q.ok) showError("#saved-err", q.data);
    }
    const tr = el("tr");
    tr.appendChild(td(`${d.name} v${d.version}`, "text"));
    tr.appendChild(td(s.model, "text"));
    tr.appendChild(td(s.optimizer, "text"));
    tr.appendChild(td(fmt(s.train.rms_mm)));
    tr.appendChild(td(s.loo ? fmt(s.loo.rms_mm) : "–"));
    tr.appendChild(td(s.check ? fmt(s.check.rms_mm) : "–"));
    tr.appendChild(td(ev ? fmt(ev.rms_mm) : "–"));
    tr.appendChild(td(ev ? fmt(ev.max_mm) : "–"));
    tb.appendChild(tr);
  }
  $("#saved-compare-table").hidden = false;
}

// ------------------------------------------------------------------ wiring

function updateButtons() {
  const running = !$("#cancel").disabled;
  $("#run").disabled = !state.pairs || running;
  $("#run-hint").textContent = state.pairs ? "" : "load calibration pairs first, or detect them from images (section 1)";
  const pso = $("#optimizer").value.includes("pso");
  document.querySelectorAll("label.pso").forEach((l) => { l.style.opacity = pso ? 1 : 0.45; l.querySelector("input").disabled = !pso; });
  const fitted = (state.job && state.result) || state.plateFit;  // a fit job's result, or a plate fit's
  const unsaved = fitted && !state.resultSaved;
  $("#save-new").disabled = !fitted;
  $("#save-version").disabled = !fitted || !state.saved.length;
  $("#refit").disabled = Boolean(state.plateFit);  // a plate's pairs are its corners: refit from the plate
  if (unsaved) $("#save-state").textContent = "not saved yet";
  $("#compare-state").textContent = state.pairs && state.check ? "ready: takes a few seconds (16 fits)" : "needs calibration pairs and check points";
}

let wired = false;

async function init() {
  const m = await api("GET", "/api/meta");
  if (!m.ok) {
    $("#server-status").textContent = "server error";
    const g = $("#global-err"); g.textContent = m.data ? m.data.error : "cannot reach the server"; g.hidden = false;
    if (m.status === 401) $("#token-box").hidden = false;
    return;
  }
  $("#global-err").hidden = true;
  state.meta = m.data;
  if (wired) { await refreshSaved(); return; }
  wired = true;
  $("#server-status").textContent = `server v${m.data.version} · body ≤ ${m.data.limits.max_body_bytes / 2 ** 20} MiB · ≤ ${m.data.limits.max_pairs} pairs`;
  if (m.data.auth) $("#token-box").hidden = false;
  fillSelect("#model", m.data.models, "auto");
  fillSelect("#optimizer", m.data.optimizers, "lm");
  fillSelect("#objective", m.data.objectives, "l2");
  $("#preset").addEventListener("change", applyPreset);
  for (const id of ["#model", "#optimizer", "#objective", "#particles", "#iterations", "#seed"]) {
    $(id).addEventListener("change", () => { $("#preset").value = "custom"; updateButtons(); });
  }
  wireLoader("pairs");
  wireLoader("check");
  $("#check-clear").addEventListener("click", () => {
    state.check = null; $("#check-text").value = ""; $("#check-file").value = "";
    $("#check-count").textContent = "none loaded"; $("#check-count").classList.remove("ok");
    clearError("#check-err"); updateButtons();
  });
  $("#run").addEventListener("click", runFit);
  $("#images-poses").addEventListener("change", imagesChosen);
  $("#images-files").addEventListener("change", imagesChosen);
  $("#images-go").addEventListener("click", runImages);
  $("#cancel").addEventListener("click", async () => { if (state.job) await api("DELETE", `/api/jobs/${state.job}`); });
  $("#refit").addEventListener("click", async () => {
    if (!state.pairs) { showError("#fit-err", { error: "no pairs loaded" }); return; }
    await runFit();
    $("#sec-progress").scrollIntoView({ behavior: "smooth" });
  });
  $("#save-new").addEventListener("click", () => saveResult(false));
  $("#save-version").addEventListener("click", () => saveResult(true));
  $("#map-go").addEventListener("click", mapPoint);
  $("#map-source").addEventListener("change", showDiameterField);
  $("#compare-go").addEventListener("click", compareMethods);
  $("#saved-compare").addEventListener("click", compareSaved);
  renumber();
  $("#import-btn").addEventListener("click", importFile);
  drawCurve();
  updateButtons();
  await refreshSaved();
}

// The token (when the server asks for one) is kept in this page only, never stored.
$("#token").addEventListener("change", () => { $("#global-err").hidden = true; init(); });
init();

// compare two versions of one calibration (GET /api/diff): default the one in force against the previous
let diffId = null;
function fillDiffControl(id, d) {
  diffId = id;
  const nums = d.versions.map((v) => v.version);
  const prev = nums.filter((n) => n < d.current_version).pop() ?? nums[0];
  for (const [sel, pick] of [["#diff-a", prev], ["#diff-b", d.current_version]]) {
    const s = $(sel);
    s.innerHTML = "";
    for (const n of nums) s.appendChild(el("option", { value: String(n) }, `v${n}`));
    s.value = String(pick);
  }
  $("#diff-verdict").hidden = true; $("#diff-fig").hidden = true; clearError("#diff-err");
}
async function showDiff() {
  clearError("#diff-err");
  $("#diff-verdict").hidden = true;
  const q = `a=${diffId}&b=${diffId}&a_version=${$("#diff-a").value}&b_version=${$("#diff-b").value}`;
  const r = await api("GET", `/api/diff?${q}`);
  if (!r.ok) { showError("#diff-err", r.data); $("#diff-verdict").hidden = true; $("#diff-fig").hidden = true; return; }
  const d = r.data, m = d.moved;
  $("#diff-verdict").textContent = `${d.verdict}: ${d.reason} — rms ${fmt(d.rms_mm)} mm, p95 ${fmt(d.p95_mm)} mm, max ${fmt(d.max_mm)} mm, median ratio ${fmt(d.ratio_median, 2)}`
    + (m ? `; fitted motion dx ${fmt(m.dx_mm)} dy ${fmt(m.dy_mm)} dz ${fmt(m.dz_mm)} mm, ${fmt(m.rotation_deg, 4)}°` : "");
  $("#diff-verdict").hidden = false;
  const p = await loadPlot("#diff-img", `/api/diff.png?${q}&width=${plotWidth()}`);
  if (p.stale) return;
  if (!p.ok) { showError("#diff-err", { error: p.error, field: null }); }
  $("#diff-fig").hidden = !p.ok;
}
$("#diff-go").addEventListener("click", showDiff);

// who changed this calibration, when and why (GET /api/audit, newest first)
async function showAudit(id) {
  clearError("#audit-err");
  const tb = $("#audit-table tbody");
  tb.innerHTML = "";
  const r = await api("GET", `/api/audit?calibration=id:${id}&limit=20`);
  if (!r.ok) { showError("#audit-err", r.data); return; }
  for (const e of r.data.entries) {
    const tr = el("tr");
    tr.appendChild(td(e.utc.replace("T", " ").slice(0, 19), "text"));
    tr.appendChild(td(e.user, "text"));
    tr.appendChild(td(e.action.replace("_", " "), "text"));
    tr.appendChild(td(e.version_before === null ? "" : String(e.version_before)));
    tr.appendChild(td(e.version_after === null ? "" : String(e.version_after)));
    tr.appendChild(td(e.note, "text"));
    tb.appendChild(tr);
  }
  $("#audit-more").hidden = r.data.next_before === null;
}
