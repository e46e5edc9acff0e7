// The collection view: polls /api/collect/status and reloads the camera's image every second, as a JPEG
// sized to the view (/api/camera/frame.jpg?width=W); the full-resolution PNG only when asked for.
"use strict";
const $ = (s) => document.querySelector(s);
const f4 = (x) => (x === null || x === undefined ? "" : Number(x).toFixed(4));
let frameUrl = null;

function headers() {
  const h = {};
  const tok = $("#token").value;
  if (tok) h["Authorization"] = "Bearer " + tok;
  return h;
}

async function api(path, opts = {}) {
  const h = headers();
  if (opts.method && opts.method !== "GET") h["X-Requested-With"] = "eyetohand";  // no cross-site POSTs
  const resp = await fetch(path, { ...opts, headers: h });
  if (resp.status === 401) $("#token-box").hidden = false;
  return resp;
}

function showError(msg) {
  const e = $("#global-err");
  e.textContent = msg || "";
  e.hidden = !msg;
}

// the view's width in device pixels, in steps of 64 (a window resized by a few px asks for the same size)
function viewWidth() {
  const img = $("#frame");
  const css = img.clientWidth || img.parentElement.clientWidth || 640;
  return Math.max(64, Math.min(8192, Math.ceil((css * (window.devicePixelRatio || 1)) / 64) * 64));
}

async function refreshFrame() {
  try {
    const resp = await api(`/api/camera/frame.jpg?width=${viewWidth()}`);
    if (!resp.ok) { showError((await resp.json()).error); return; }
    const blob = await resp.blob();
    const url = URL.createObjectURL(blob);
    const img = $("#frame");
    img.onload = () => { if (frameUrl) URL.revokeObjectURL(frameUrl); frameUrl = url; };
    img.src = url;
    img.dataset.frame = resp.headers.get("X-Frame") || "";
    img.dataset.bytes = String(blob.size);
    const size = resp.headers.get("X-Frame-Size");
    $("#frame-count").textContent = "frame " + img.dataset.frame + (size ? ` · camera ${size} px` : "");
    const src = resp.headers.get("X-Frame-Source") || "";
    $("#frame-source").textContent = src === "live" ? "" : src;
  } catch (err) { $("#server-status").textContent = "server unreachable"; }
}

function renderStatus(st) {
  $("#server-status").textContent = "connected";
  $("#c-name").textContent = st.name || "–";
  $("#c-state").textContent = st.state;
  $("#camera").textContent = st.camera || "";
  const done = st.poses.filter((p) => p.done).length;
  $("#plan-count").textContent = st.poses.length ? `${done} of ${st.poses.length} poses done` : "no plan";
  const poses = $("#poses");
  poses.replaceChildren(...st.poses.map((p) => {
    const s = document.createElement("span");
    s.className = "pose" + (p.done ? " done" : p.failed ? " failed" : "");
    s.title = `pose ${p.index + 1}: ${p.xyz_mm.map(f4).join(", ")} mm` + (p.done ? " (done)" : p.failed ? " (failed)" : "");
    return s;
  }));
  const active = st.points.filter((p) => !p.dropped).length;
  $("#points-count").textContent = `${active} in the fit` + (active < st.points.length ? `, ${st.points.length - active} dropped` : "");
  const body = $("#points tbody");
  body.replaceChildren(...st.points.map((p) => {
    const tr = document.createElement("tr");
    tr.className = p.dropped ? "dropped" : "";
    tr.dataset.n = p.n;
    const d = p.detection || {};
    for (const v of [p.n, f4(p.xyz_mm[0]), f4(p.xyz_mm[1]), f4(p.xyz_mm[2]), f4(p.u), f4(p.v),
      d.diameter_px === undefined ? "" : Number(d.diameter_px).toFixed(2),
      d.score === undefined ? "" : Number(d.score).toFixed(2),
      d.rms_px === undefined || d.rms_px === null ? "" : Number(d.rms_px).toFixed(3),
      p.still_shift_px === undefined ? "" : Number(p.still_shift_px).toFixed(3)]) {
      const td = document.createElement("td");
      td.textContent = v;
      tr.appendChild(td);
    }
    const td = document.createElement("td");
    td.className = "act";
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = p.dropped ? "Keep" : "Drop";
    b.className = p.dropped ? "keep" : "drop";
    b.disabled = st.state !== "collecting";
    b.addEventListener("click", () => setDropped(p.n, !p.dropped));
    td.appendChild(b);
    tr.appendChild(td);
    return tr;
  }));
  const r = st.result;
  const fitText = !r ? "no fit yet (CAL END)"
    : st.kind === "plate" ? `${r.model}: ${r.n} touches, touch rms ${f4(r.touch_rms_mm)} mm, max ${f4(r.touch_max_mm)} mm`
      : `${r.model}: ${r.n} points, leave-one-out rms ${f4(r.loo_rms_mm)} mm, max ${f4(r.loo_max_mm)} mm (${r.utc})`;
  $("#fit").textContent = fitText;
  renderPlate(st);
  $("#fit").className = r ? "" : "muted";
  $("#check-count").textContent = st.checks.length ? String(st.checks.length) : "";
  $("#checks").textContent = st.checks.length
    ? st.checks.slice(-5).map((c) => `${c.utc}: error ${f4(c.error_mm)} mm (dx ${f4(c.dx_mm)}, dy ${f4(c.dy_mm)})`).join(" · ")
    : "none";
}

// A robot's plate session (CAL PLATE … CAL TOUCH … CAL END): the image the collection kept, drawn in an
// SVG in its own pixels (the status's corners are in them), each corner A-D marked and whether the robot
// touched it on this placement; the image is fetched again only when the session's image changes.
const SVG = "http://www.w3.org/2000/svg";
let plateShown = null;  // the image file the SVG shows
function svgEl(tag, attrs) {
  const e = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  return e;
}
async function renderPlate(st) {
  const block = $("#plate-block");
  if (st.kind !== "plate") { block.hidden = true; plateShown = null; return; }
  block.hidden = false;
  $("#plate-spec").textContent = st.plate;
  const touches = new Map();
  for (const p of st.points) if (!p.dropped && p.placement === st.placements) touches.set(String(p.corner_id), p);
  const done = st.corners.filter((c) => touches.has(String(c.id))).length;
  $("#plate-count").textContent = `placement ${st.placements} · ${done} of ${st.corners.length} corners touched`;
  const [w, h] = st.image_size;
  const svg = $("#plate-svg");
  svg.setAttribute("viewBox", `0 0 ${w} ${h}`);
  const r = Math.max(8, Math.min(w, h) / 40), font = Math.max(14, Math.min(w, h) / 22);
  const marks = st.corners.map((c) => {
    const t = touches.get(String(c.id));
    const g = svgEl("g", { class: "corner " + (t ? "touched" : "todo"), "data-label": c.label });
    g.appendChild(svgEl("circle", { cx: c.u, cy: c.v, r }));
    const label = svgEl("text", { x: c.u + r * 1.2, y: c.v - r * 1.2, "font-size": font });
    label.textContent = c.label + (t ? " ✓" : "");
    g.appendChild(label);
    return g;
  });
  let img = svg.querySelector("image");
  if (!img) { img = svgEl("image", { x: 0, y: 0 }); }
  img.setAttribute("width", w); img.setAttribute("height", h);
  svg.replaceChildren(img, ...marks);
  $("#plate-corners tbody").replaceChildren(...st.corners.map((c) => {
    const t = touches.get(String(c.id));
    const tr = document.createElement("tr");
    tr.className = t ? "touched" : "";
    tr.dataset.label = c.label;
    const text = t ? `#${t.n} at ${t.xyz_mm.map(f4).join(", ")} mm` : "not yet";
    for (const v of [c.label, c.id, Number(c.u).toFixed(2), Number(c.v).toFixed(2), text]) {
      const td = document.createElement("td");
      td.textContent = v;
      tr.appendChild(td);
    }
    return tr;
  }));
  if (plateShown === st.image_file) return;
  plateShown = st.image_file;
  const resp = await api(`/api/collect/plate.jpg?width=${Math.min(1600, viewWidth())}`);
  if (!resp.ok) { showError((await resp.json()).error); plateShown = null; return; }
  const url = URL.createObjectURL(await resp.blob());
  const old = img.getAttribute("href");
  img.setAttribute("href", url);
  img.dataset.file = st.image_file;
  if (old) URL.revokeObjectURL(old);
}

async function refreshStatus() {
  try {
    const resp = await api("/api/collect/status");
    const data = await resp.json();
    if (!resp.ok) { showError(data.error); return; }
    showError("");
    renderStatus(data);
  } catch (err) { $("#server-status").textContent = "server unreachable"; }
}

async function setDropped(n, drop) {
  const resp = await api(`/api/collect/points/${n}/${drop ? "drop" : "keep"}`, { method: "POST" });
  if (!resp.ok) showError((await resp.json()).error);
  refreshStatus();
}

// the full-resolution image (lossless, several MB) in a new tab; with a token, fetched with it
async function openFull(ev) {
  if (!$("#token").value) return;  // the link itself works
  ev.preventDefault();
  const resp = await api("/api/camera/frame.png");
  if (!resp.ok) { showError((await resp.json()).error); return; }
  window.open(URL.createObjectURL(await resp.blob()), "_blank");
}
$("#frame-full").addEventListener("click", openFull);

// The token (when the server asks for one) is kept in this page only, never stored.
$("#token").addEventListener("change", () => { refreshStatus(); refreshFrame(); });
let busy = false;
async function tick() {
  if (busy) return;
  busy = true;
  try { await Promise.all([refreshFrame(), refreshStatus()]); } finally { busy = false; }
}
tick();
setInterval(tick, 1000);
