// KM-ViPE live map viewer: plain 2D canvas with a software point renderer (no libraries, no build step).
"use strict";
const params = new URLSearchParams(location.search);
const apiKey = params.get("key") || localStorage.getItem("kmvipe-key") || "";
if (params.get("key")) localStorage.setItem("kmvipe-key", apiKey);
const POLL_MS = Number(params.get("poll") || 2000);
const HIGHLIGHT = [255, 40, 200];
const $ = (id) => document.getElementById(id);
const STREAMS_MS = 10000;  // how often the stream list (and what each stream's map can answer) is re-read
const state = { stream: params.get("stream") || "", xyz: new Float32Array(0), rgb: new Uint8Array(0), poses: [],
  regions: [], highlight: new Uint8Array(0), yaw: -0.5, pitch: 0.6, zoom: 1.0, centre: [0, 0, 0], radius: 1,
  streams: [], streamsAt: 0 };

async function api(path, body) {
  const opts = { headers: { "X-API-Key": apiKey } };
  if (body !== undefined) { opts.method = "POST"; opts.headers["Content-Type"] = "application/json"; opts.body = JSON.stringify(body); }
  const res = await fetch(path, opts);
  const data = await res.json().catch(() => ({}));
  if (!res.ok) throw new Error(data.detail || res.statusText);
  return data;
}

async function apiBlob(path) {  // an image behind the API key (an <img src> cannot send the header)
  const res = await fetch(path, { headers: { "X-API-Key": apiKey } });
  if (!res.ok) throw new Error((await res.json().catch(() => ({}))).detail || res.statusText);
  return URL.createObjectURL(await res.blob());
}

async function loadStreams() {
  const data = await api("/v1/streams");
  const sel = $("stream");
  const names = data.streams.map((s) => s.name);
  if (!state.stream && names.length) state.stream = names[0];
  sel.innerHTML = names.map((n) => `<option ${n === state.stream ? "selected" : ""}>${n}</option>`).join("");
  state.streams = data.streams; state.streamsAt = Date.now();
  showTextSupport(data.streams.find((s) => s.name === state.stream));
}

function textSupport(q) {  // a stream's `queries.text`, as {available, why, encoder, oracle}; null when not given
  if (!q || q.text === undefined || q.text === null) return null;
  if (typeof q.text === "object") return { available: !!q.text.available, why: q.text.why || "", encoder: q.text.encoder || "", oracle: !!q.text.oracle };
  return { available: !!q.text, why: q.text_why || "", encoder: q.encoder || "", oracle: !!q.oracle };  // flat form
}

function showTextSupport(entry) {
  const t = textSupport(entry && entry.queries), el = $("text-status");
  if (!t) { el.textContent = ""; el.title = ""; return; }
  el.textContent = !t.available ? `text: unavailable — ${t.why}` : t.oracle ? "text: oracle (synthetic ground truth)" : `text: ${t.encoder || "available"}`;
  el.className = t.available ? "muted" : "warn"; el.title = t.why;
}

async function refresh() {
  try {
    if (!state.stream || Date.now() - state.streamsAt > STREAMS_MS) await loadStreams();
    if (!state.stream) { $("status").textContent = "no stream yet"; return; }
    const map = await api(`/v1/streams/${state.stream}/map?format=json`);
    state.xyz = Float32Array.from(map.xyz); state.rgb = Uint8Array.from(map.rgb);
    $("point-count").textContent = map.returned; $("status").textContent = `${state.stream}: ${map.total_points} points`;
    try { state.poses = (await api(`/v1/streams/${state.stream}/trajectory`)).frames; } catch (e) { state.poses = []; }
    $("pose-count").textContent = state.poses.length;
    if (!state.framed) { frameScene(); state.framed = true; }
    markHighlights(); draw();
  } catch (e) { $("status").textContent = "error: " + e.message; }
  if (state.stream && typeof refreshKeyframes === "function") await refreshKeyframes();  // keyframes.js
}

function frameScene() {
  const n = state.xyz.length / 3; if (!n) return;
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  for (let i = 0; i < n; i++) for (let k = 0; k < 3; k++) { const v = state.xyz[3 * i + k]; if (v < lo[k]) lo[k] = v; if (v > hi[k]) hi[k] = v; }
  state.centre = lo.map((v, k) => (v + hi[k]) / 2);
  state.radius = Math.max(1e-6, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2);
}

function markHighlights() {
  const n = state.xyz.length / 3, h = new Uint8Array(n); let count = 0;
  for (let i = 0; i < n; i++) {
    const x = state.xyz[3 * i], y = state.xyz[3 * i + 1], z = state.xyz[3 * i + 2];
    for (const r of state.regions) {
      if (x >= r.box_min[0] && x <= r.box_max[0] && y >= r.box_min[1] && y <= r.box_max[1] && z >= r.box_min[2] && z <= r.box_max[2]) { h[i] = 1; count++; break; }
    }
  }
  state.highlight = h; $("highlight-count").textContent = count;
}

function camera() {
  const cy = Math.cos(state.yaw), sy = Math.sin(state.yaw), cp = Math.cos(state.pitch), sp = Math.sin(state.pitch);
  const dist = 1.7 * state.radius / state.zoom, c = state.centre;
  const canvas = $("canvas"), w = canvas.width, h = canvas.height, f = 0.9 * Math.min(w, h);
  return (p) => {  // world (z up) → screen; orbit camera looking at the centre
    const x = p[0] - c[0], y = p[1] - c[1], z = p[2] - c[2];
    const xr = cy * x - sy * y, yr = sy * x + cy * y;
    const depth = dist + cp * yr + sp * z, up = cp * z - sp * yr;
    if (depth <= 1e-3) return null;
    return [w / 2 + f * xr / depth, h / 2 - f * up / depth, depth];
  };
}

function draw() {
  const canvas = $("canvas"), ctx = canvas.getContext("2d");
  canvas.width = canvas.clientWidth; canvas.height = canvas.clientHeight;
  const w = canvas.width, h = canvas.height, project = camera();
  const img = ctx.createImageData(w, h), zbuf = new Float32Array(w * h).fill(Infinity);
  for (let i = 0; i < w * h; i++) { img.data[4 * i] = 17; img.data[4 * i + 1] = 17; img.data[4 * i + 2] = 17; img.data[4 * i + 3] = 255; }
  const n = state.xyz.length / 3;
  for (let i = 0; i < n; i++) {
    const s = project([state.xyz[3 * i], state.xyz[3 * i + 1], state.xyz[3 * i + 2]]); if (!s) continue;
    const hl = state.highlight[i] === 1, size = hl ? 3 : 2;
    const col = hl ? HIGHLIGHT : [state.rgb[3 * i], state.rgb[3 * i + 1], state.rgb[3 * i + 2]];
    for (let dy = 0; dy < size; dy++) for (let dx = 0; dx < size; dx++) {
      const u = Math.round(s[0]) + dx, v = Math.round(s[1]) + dy; if (u < 0 || v < 0 || u >= w || v >= h) continue;
      const j = v * w + u; if (s[2] >= zbuf[j] && !hl) continue; zbuf[j] = hl ? -1 : s[2];
      img.data[4 * j] = col[0]; img.data[4 * j + 1] = col[1]; img.data[4 * j + 2] = col[2];
    }
  }
  ctx.putImageData(img, 0, 0);
  drawTrajectory(ctx, project); drawBoxes(ctx, project);
}

function drawTrajectory(ctx, project) {
  ctx.strokeStyle = "#3cf"; ctx.lineWidth = 2; ctx.beginPath(); let started = false;
  for (const f of state.poses) {
    const m = f.world_from_cam, s = project([m[0][3], m[1][3], m[2][3]]); if (!s) continue;
    if (!started) { ctx.moveTo(s[0], s[1]); started = true; } else ctx.lineTo(s[0], s[1]);
  }
  ctx.stroke();
  if (state.poses.length) {  // the latest camera as a dot
    const m = state.poses[state.poses.length - 1].world_from_cam, s = project([m[0][3], m[1][3], m[2][3]]);
    if (s) { ctx.fillStyle = "#ff0"; ctx.beginPath(); ctx.arc(s[0], s[1], 5, 0, 2 * Math.PI); ctx.fill(); }
  }
}

function drawBoxes(ctx, project) {
  ctx.strokeStyle = "rgb(255,40,200)"; ctx.lineWidth = 1.5;
  for (const r of state.regions) {
    const a = r.box_min, b = r.box_max, c = [];
    for (let k = 0; k < 8; k++) c.push(project([k & 1 ? b[0] : a[0], k & 2 ? b[1] : a[1], k & 4 ? b[2] : a[2]]));
    for (const [i, j] of [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]]) {
      if (!c[i] || !c[j]) continue; ctx.beginPath(); ctx.moveTo(c[i][0], c[i][1]); ctx.lineTo(c[j][0], c[j][1]); ctx.stroke();
    }
  }
}

async function search() {
  const text = $("query").value.trim(); $("error").textContent = "";
  if (!text || !state.stream) return;
  try {
    showAnswer(await api(`/v1/streams/${state.stream}/query`, { texts: [text], top_k: 50, max_regions: 5 }), "");
  } catch (e) { showError(e); }
}

function escapeHtml(s) { return String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`); }

function showAnswer(ans, note) {  // a query's answer (text or keyframe region): results list, highlighted points
  const res = ans.results[0]; state.regions = res.regions;
  $("results").innerHTML = res.regions.map((r) =>
    `<li class="result" data-score="${r.score.toFixed(4)}" data-count="${r.count}">${escapeHtml(res.text)}: score ${r.score.toFixed(3)}, ` +
    `${r.count} points<br><span class="muted">centre (${r.centroid.map((v) => v.toFixed(2)).join(", ")})</span></li>`).join("")
    || "<li class='muted'>no region above the threshold</li>";
  $("answer-note").textContent = ans.oracle ? "oracle answer: the synthetic world's ground-truth label vectors, not a language model" : note;
  $("answer-note").className = ans.oracle ? "warn" : "muted";
  markHighlights(); draw();
}

function showError(e) {
  state.regions = []; $("results").innerHTML = ""; $("answer-note").textContent = ""; $("error").textContent = e.message;
  markHighlights(); draw();
}

function controls() {
  const canvas = $("canvas"); let drag = null;
  canvas.addEventListener("mousedown", (e) => { drag = [e.clientX, e.clientY]; });
  addEventListener("mouseup", () => { drag = null; });
  addEventListener("mousemove", (e) => {
    if (!drag) return; state.yaw += (e.clientX - drag[0]) * 0.01;
    state.pitch = Math.max(-1.5, Math.min(1.5, state.pitch + (e.clientY - drag[1]) * 0.01)); drag = [e.clientX, e.clientY]; draw();
  });
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); state.zoom *= e.deltaY < 0 ? 1.1 : 1 / 1.1; draw(); }, { passive: false });
  addEventListener("resize", draw);
  $("search").addEventListener("click", search);
  $("query").addEventListener("keydown", (e) => { if (e.key === "Enter") search(); });
  $("stream").addEventListener("change", (e) => {
    state.stream = e.target.value; state.framed = false; showTextSupport(state.streams.find((s) => s.name === state.stream)); refresh();
  });
}

controls();
refresh();
setInterval(() => { if ($("follow").checked) refresh(); }, POLL_MS);
