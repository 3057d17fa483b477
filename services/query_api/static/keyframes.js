// Query by keyframe region: a strip of the map's keyframe thumbnails; click one to open it, drag a box over
// something (or click it) and the map's matching regions are listed and highlighted like a text search's.
// Uses viewer.js's state, api, apiBlob, showAnswer, showError and $.
"use strict";
const KF_LIMIT = Number(params.get("keyframes") || 60);  // the newest this many keyframes in the strip
const CLICK_PX = 4;  // a drag shorter than this is a click: the 1/8-grid cell under it is the query
const kf = { key: "", urls: new Map(), open: null, drag: null };  // urls: "stream/session/seq" → object URL

async function refreshKeyframes() {
  let data;
  try { data = await api(`/v1/streams/${state.stream}/keyframes?limit=${KF_LIMIT}`); }
  catch (e) { $("kf-status").textContent = "no keyframes: " + e.message; $("strip").innerHTML = ""; kf.key = ""; return; }
  const withCodes = data.keyframes.filter((k) => k.has_codes).length;
  $("kf-status").textContent = `${data.total} keyframes · ${withCodes} of the newest ${data.keyframes.length} queryable`;
  const session = (state.streams.find((s) => s.name === state.stream) || {}).session || "";
  const key = `${state.stream}/${session}/` + data.keyframes.map((k) => `${k.seq}:${k.has_codes ? 1 : 0}`).join(",");
  if (key === kf.key) return;  // nothing new: leave the strip (and its loaded images) alone
  kf.key = key;
  const strip = $("strip"), shown = data.keyframes.filter((k) => k.has_thumbnail).reverse();  // newest first
  const keep = new Set(shown.map((k) => `${state.stream}/${session}/${k.seq}`));
  for (const [id, url] of kf.urls) if (!keep.has(id)) { url.then(URL.revokeObjectURL, () => {}); kf.urls.delete(id); }
  strip.innerHTML = "";
  for (const k of shown) {
    const img = document.createElement("img");
    img.className = "thumb" + (k.has_codes ? "" : " no-codes") + (kf.open && kf.open.seq === k.seq ? " selected" : "");
    img.dataset.seq = k.seq; img.alt = `keyframe ${k.seq}`;
    img.title = `keyframe ${k.seq}` + (k.has_codes ? "" : " (its DINO codes are not in yet)");
    img.addEventListener("click", () => openKeyframe(k, session));
    strip.appendChild(img);
    thumbnailURL(session, k.seq).then((url) => { img.src = url; }).catch(() => { img.title += " (no image)"; });
  }
}

async function thumbnailURL(session, seq) {
  const id = `${state.stream}/${session}/${seq}`;
  if (!kf.urls.has(id)) kf.urls.set(id, apiBlob(`/v1/streams/${state.stream}/keyframes/${seq}/thumbnail`));
  return kf.urls.get(id);
}

function openKeyframe(k, session) {
  kf.open = k;
  for (const t of document.querySelectorAll("#strip img.thumb")) t.classList.toggle("selected", Number(t.dataset.seq) === k.seq);
  $("kf-title").textContent = `keyframe ${k.seq}` + (k.has_codes ? "" : " — codes not in yet");
  $("kf-box").style.display = "none";
  $("kf-panel").hidden = false;
  thumbnailURL(session, k.seq).then((url) => { $("kf-image").src = url; }).catch(showError);
}

function normalised(e) {  // the pointer in [0, 1]² of the shown image (0 = left/top edge)
  const r = $("kf-image").getBoundingClientRect();
  return [Math.min(1, Math.max(0, (e.clientX - r.left) / r.width)), Math.min(1, Math.max(0, (e.clientY - r.top) / r.height)),
    e.clientX, e.clientY];
}

function showBox(a, b) {
  const r = $("kf-image").getBoundingClientRect(), box = $("kf-box").style;
  box.left = `${Math.min(a[0], b[0]) * r.width}px`; box.top = `${Math.min(a[1], b[1]) * r.height}px`;
  box.width = `${Math.abs(b[0] - a[0]) * r.width}px`; box.height = `${Math.abs(b[1] - a[1]) * r.height}px`;
  box.display = "block";
}

async function queryRegion(a, b) {
  const click = Math.abs(b[2] - a[2]) < CLICK_PX && Math.abs(b[3] - a[3]) < CLICK_PX;
  const box = click ? [a[0], a[1], a[0], a[1]] : [Math.min(a[0], b[0]), Math.min(a[1], b[1]), Math.max(a[0], b[0]), Math.max(a[1], b[1])];
  const seq = kf.open.seq;
  $("error").textContent = "";
  try {
    const ans = await api(`/v1/streams/${state.stream}/query/keyframe`, { seq, box, top_k: 50, max_regions: 5 });
    showAnswer(ans, `by example: ${click ? "a spot" : "a box"} on keyframe ${seq}`);
  } catch (e) { showError(e); }
}

function closeKeyframe() { $("kf-panel").hidden = true; kf.open = null; kf.drag = null; }

function keyframeControls() {
  $("kf-close").addEventListener("click", closeKeyframe);
  $("stream").addEventListener("change", closeKeyframe);  // another stream: other keyframes
  $("kf-frame").addEventListener("mousedown", (e) => {
    if (!kf.open || e.button !== 0) return;
    e.preventDefault(); kf.drag = normalised(e); showBox(kf.drag, kf.drag);
  });
  addEventListener("mousemove", (e) => { if (kf.drag) showBox(kf.drag, normalised(e)); });
  addEventListener("mouseup", (e) => {
    if (!kf.drag) return;
    const a = kf.drag, b = normalised(e); kf.drag = null;
    queryRegion(a, b);
  });
}

keyframeControls();
