// voxfusion page: sessions, upload, viewer embed, render and AR panels, accuracy and speed plots.
// Plain JS, no build step (plots.js draws the plots).
"use strict";

const $ = (id) => document.getElementById(id);
const PRESETS = ["", "test", "cpu", "paper", "gpu"];

// ------------------------------------------------------------------ token and API calls
const token = (() => {
  const fromUrl = new URLSearchParams(location.search).get("token");
  if (fromUrl) sessionStorage.setItem("voxfusion_token", fromUrl);
  return fromUrl || sessionStorage.getItem("voxfusion_token") || "";
})();

function withToken(url) {
  if (!token) return url;
  return url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);
}

function authHeaders(extra = {}) {
  return token ? { ...extra, Authorization: "Bearer " + token } : extra;
}

async function errorText(response) {
  try {
    const body = await response.json();
    if (typeof body.detail === "string") return body.detail;
    if (Array.isArray(body.detail)) return body.detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("; ");
    return JSON.stringify(body);
  } catch (_) {
    return `${response.status} ${response.statusText}`;
  }
}

async function api(path, { method = "GET", json, expect = "json" } = {}) {
  const options = { method, headers: authHeaders() };
  if (json !== undefined) {
    options.headers["Content-Type"] = "application/json";
    options.body = JSON.stringify(json);
  }
  const response = await fetch(path, options);
  if (!response.ok) throw new Error(await errorText(response));
  if (expect === "json") return response.status === 204 ? null : response.json();
  if (expect === "text") return response.text();
  return response.blob();
}

function say(id, text, kind = "") {
  const el = $(id);
  el.textContent = text;
  el.className = "message " + kind;
}

// ------------------------------------------------------------------ small 3D maths (row-major 4x4 arrays)
const deg = (d) => (d * Math.PI) / 180;
const norm = (v) => { const n = Math.hypot(...v) || 1; return v.map((x) => x / n); };
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];

// A run's world is its first camera's frame (OpenCV axes), so up is -y and yaw 0, pitch 0 looks
// along +z, as the first camera did.
const UP = [0, -1, 0];

function poseLooking(position, yawDeg, pitchDeg) {
  // Camera at `position` looking along yaw (about the up axis, from +z towards +x) and pitch (up).
  const yaw = deg(yawDeg), pitch = deg(pitchDeg);
  const forward = [Math.cos(pitch) * Math.sin(yaw), -Math.sin(pitch), Math.cos(pitch) * Math.cos(yaw)];
  const right = norm(cross(forward, UP));
  const down = cross(forward, right);
  return [
    [right[0], down[0], forward[0], position[0]],
    [right[1], down[1], forward[1], position[1]],
    [right[2], down[2], forward[2], position[2]],
    [0, 0, 0, 1],
  ];
}

// An AR object at `position` standing upright (its +z along the world's up, -y; ar.UPRIGHT),
// turned by yaw about that axis.
function yawPose(position, yawDeg) {
  const c = Math.cos(deg(yawDeg)), s = Math.sin(deg(yawDeg));
  return [[c, s, 0, position[0]], [0, 0, -1, position[1]], [-s, c, 0, position[2]], [0, 0, 0, 1]];
}

// An AR object at `position` whose +z (the shapes' axis) is a picked surface's `normal`, turned
// by yaw about it: its x is yawPose's x laid onto the surface (yawPose's y where that is the normal).
function surfacePose(position, normal, yawDeg) {
  const c = Math.cos(deg(yawDeg)), s = Math.sin(deg(yawDeg));
  const length = Math.hypot(...normal);
  const z = normal.map((v) => v / length);
  const along = (a) => a.map((v, i) => v - (a[0] * z[0] + a[1] * z[1] + a[2] * z[2]) * z[i]);
  let x = along([c, 0, -s]);
  if (Math.hypot(...x) < 1e-6) x = along([s, 0, c]);
  const xLength = Math.hypot(...x);
  x = x.map((v) => v / xLength);
  const y = [z[1] * x[2] - z[2] * x[1], z[2] * x[0] - z[0] * x[2], z[0] * x[1] - z[1] * x[0]];
  return [0, 1, 2].map((i) => [x[i], y[i], z[i], position[i]]).concat([[0, 0, 0, 1]]);
}

// The inverse of poseLooking for the render panel's fields: position, and the yaw and pitch of
// the optical axis (its roll is not shown; Set rebuilds the pose without roll).
function lookFromPose(T) {
  const forward = [T[0][2], T[1][2], T[2][2]];
  const yaw = Math.atan2(forward[0], forward[2]), pitch = Math.asin(Math.max(-1, Math.min(1, -forward[1])));
  return { position: [T[0][3], T[1][3], T[2][3]], yaw: (yaw * 180) / Math.PI, pitch: (pitch * 180) / Math.PI };
}

function formatMatrix(T) {
  return "[" + T.map((row) => "[" + row.map((v) => Number(v).toFixed(5)).join(", ") + "]").join(",\n ") + "]";
}

function readMatrix() {
  const text = $("cam-matrix").value.trim();
  let values;
  try {
    values = JSON.parse(text).flat();
  } catch (_) {
    values = text.split(/[\s,\[\]]+/).filter((s) => s.length).map(Number);
  }
  if (values.length !== 16 || values.some((v) => !Number.isFinite(v))) {
    throw new Error("T_world_cam: enter 16 numbers (a 4x4 matrix)");
  }
  return [0, 1, 2, 3].map((r) => values.slice(4 * r, 4 * r + 4));
}

// ------------------------------------------------------------------ sessions
let sessions = [];
let selectedId = null;

const ENDED = StatusText.ENDED;
const { plural, centimetres } = StatusText;
const ateText = StatusText.ate;
const describe = StatusText.describe;
const phaseText = StatusText.phase;

// Each phase has its own progress (StatusText.progress): tracking counts frames, an end-of-run
// step its time against its estimate; without either (a stream, no estimate, past it) the bar
// runs (indeterminate) next to the time spent so far.
function showPhaseProgress(bar, s) {
  const progress = StatusText.progress(s);
  bar.hidden = progress === null;
  if (progress && progress.max) {
    bar.max = progress.max;
    bar.value = progress.value;
  } else {
    bar.removeAttribute("value");
  }
}

function sourceText(s) {
  const files = (s.files || []).length ? ` · ${s.files.join(", ")}` : "";
  return `${s.source}${files} · preset ${s.preset}`;
}

function showSelectedStatus() {
  const s = sessions.find((x) => x.id === selectedId);
  $("session-status").textContent = s ? `· ${s.id}: ${s.status}, ${phaseText(s)}${ateText(s)}` : "";
}

// Items are created once per session and updated in place, so that polling never swaps an
// element out from under a click.
const sessionItems = new Map();

function createSessionItem(id) {
  const li = document.createElement("li");
  li.dataset.id = id;
  li.innerHTML = `<div class="top"><span class="id"></span><span class="badge"></span></div>
    <div class="source"></div><div class="phase"></div><progress hidden></progress><div class="stats"></div>
    <div class="error" hidden></div><div class="actions"></div>`;
  li.querySelector(".id").textContent = id;
  li.addEventListener("click", (event) => {
    if (event.target.closest("a,button")) return;
    selectSession(id);
  });
  return li;
}

function updateSessionItem(li, s) {
  li.classList.toggle("selected", s.id === selectedId);
  const badge = li.querySelector(".badge");
  badge.className = "badge " + s.status;
  badge.textContent = s.status;
  li.querySelector(".source").textContent = sourceText(s);
  const phase = li.querySelector(".phase");
  phase.dataset.phase = s.phase;
  phase.textContent = phaseText(s);
  showPhaseProgress(li.querySelector("progress"), s);
  li.querySelector(".stats").textContent = describe(s);
  const error = li.querySelector(".error");
  error.hidden = !s.error;
  error.textContent = s.error || "";
  const actionsKey = `${s.status}|${s.outputs.mesh}|${s.outputs.trajectory}|${s.agents}`;
  if (li.dataset.actions !== actionsKey) {
    li.dataset.actions = actionsKey;
    li.querySelector(".actions").replaceChildren(...sessionActions(s));
  }
}

function sessionActions(s) {
  const actions = [];
  const base = `/api/sessions/${s.id}`;
  if (s.outputs.mesh) {
    for (const fmt of ["ply", "glb", "obj"]) actions.push(link(withToken(`${base}/mesh?format=${fmt}`), fmt.toUpperCase()));
  }
  if (s.outputs.trajectory) {
    const agents = s.agents || 1;
    if (agents === 1) actions.push(link(withToken(`${base}/trajectory`), "trajectory"));
    else for (let k = 0; k < agents; k++) actions.push(link(withToken(`${base}/trajectory?agent=${k}`), `trajectory ${k}`));
  }
  if (s.status === "running" || s.status === "queued") actions.push(button("cancel", () => cancelSession(s.id)));
  actions.push(button("delete", () => deleteSession(s.id), "danger"));
  return actions;
}

function link(href, text) {
  const a = document.createElement("a");
  a.href = href;
  a.textContent = text;
  a.setAttribute("download", "");
  return a;
}

function button(text, onClick, extraClass = "") {
  const b = document.createElement("button");
  b.type = "button";
  b.className = "small " + extraClass;
  b.textContent = text;
  b.addEventListener("click", onClick);
  return b;
}

function renderSessionList() {
  const list = $("session-list");
  if (!sessions.length) {
    sessionItems.clear();
    list.replaceChildren(emptyItem());
  } else {
    const wanted = sessions.map((s) => {
      const li = sessionItems.get(s.id) || createSessionItem(s.id);
      sessionItems.set(s.id, li);
      updateSessionItem(li, s);
      return li;
    });
    for (const id of [...sessionItems.keys()]) {
      if (!sessions.some((s) => s.id === id)) sessionItems.delete(id);
    }
    const current = [...list.children];
    if (current.length !== wanted.length || current.some((li, i) => li !== wanted[i])) list.replaceChildren(...wanted);
  }
  $("render-session").textContent = selectedId ? `session ${selectedId}` : "(select a session)";
  showSelectedStatus();
}

function emptyItem() {
  const li = document.createElement("li");
  li.className = "empty";
  li.textContent = "No sessions yet: upload a dataset or start the synthetic demo.";
  return li;
}

let listedIds = new Set();  // the sessions of the previous poll
// A link to one session (`/?session=ID`, as `voxfusion stream` prints) opens that session
// instead of the newest, if the server has it.
let linkedId = new URLSearchParams(location.search).get("session");

async function refreshSessions() {
  try {
    sessions = await api("/api/sessions");
    if (linkedId) {
      if (sessions.some((s) => s.id === linkedId)) setSelected(linkedId);
      linkedId = null;
    }
    // The newest session on a fresh load, or when the selected one is gone. A session created
    // a moment ago may be missing from a poll that was already under way: it stays selected.
    const gone = listedIds.has(selectedId) && !sessions.some((s) => s.id === selectedId);
    if (!selectedId || gone) setSelected(sessions.length ? sessions[0].id : null);
    listedIds = new Set(sessions.map((s) => s.id));
    renderSessionList();
    followSession();
    $("server-note").textContent = "";
  } catch (error) {
    $("server-note").textContent = "server unreachable: " + error.message;
  }
  refreshPlots();
}

// The page and the 3D viewer show the same session: every change of selection tells the viewer.
function setSelected(id) {
  selectedId = id;
  if (id) api(`/api/viewer/select/${id}`, { method: "POST" }).catch(() => {});
}

function selectSession(id) {
  if (id !== selectedId) cameraChosen = false;  // another session, another world: follow its camera
  setSelected(id);
  renderSessionList();
  refreshPlots();
}

async function cancelSession(id) {
  try { await api(`/api/sessions/${id}/cancel`, { method: "POST" }); } catch (error) { alert(error.message); }
  refreshSessions();
}

async function deleteSession(id) {
  if (!confirm(`Delete session ${id} and all its results?`)) return;
  try { await api(`/api/sessions/${id}`, { method: "DELETE" }); } catch (error) { alert(error.message); }
  if (selectedId === id) selectedId = null;
  refreshSessions();
}

// ------------------------------------------------------------------ new sessions
function fillPresets() {
  for (const select of document.querySelectorAll("select.preset")) {
    for (const p of PRESETS) {
      const option = document.createElement("option");
      option.value = p;
      option.textContent = p || "server default";
      select.appendChild(option);
    }
  }
}

function uploadDataset(event) {
  event.preventDefault();
  const files = [...$("upload-file").files];
  if (!files.length) return say("upload-message", "Choose a zip first.", "error");
  const form = new FormData();
  for (const file of files) form.append("file", file);  // several parts: one agent each, in this order
  form.append("format", $("upload-format").value);
  if ($("upload-preset").value) form.append("preset", $("upload-preset").value);
  if ($("upload-intrinsics").value.trim()) form.append("intrinsics", $("upload-intrinsics").value.trim());
  if ($("upload-depth-scale").value.trim()) form.append("depth_scale", $("upload-depth-scale").value.trim());
  const xhr = new XMLHttpRequest();
  const bar = $("upload-progress");
  bar.hidden = false;
  bar.value = 0;
  $("upload-button").disabled = true;
  say("upload-message", "Uploading…");
  xhr.upload.addEventListener("progress", (e) => {
    if (e.lengthComputable) bar.value = e.loaded / e.total;
    if (e.loaded === e.total) say("upload-message", "Checking the dataset…");
  });
  xhr.addEventListener("loadend", () => {
    $("upload-button").disabled = false;
    bar.hidden = true;
    let body = {};
    try { body = JSON.parse(xhr.responseText); } catch (_) { /* not JSON */ }
    if (xhr.status === 201) {
      const agents = files.length > 1 ? `, ${files.length} agents` : "";
      say("upload-message", `Session ${body.id} created (${body.status}${agents}).`, "ok");
      selectSession(body.id);
      refreshSessions();
    } else {
      say("upload-message", `Upload refused: ${body.detail || xhr.statusText || "connection failed"}`, "error");
    }
  });
  xhr.open("POST", "/api/sessions");
  if (token) xhr.setRequestHeader("Authorization", "Bearer " + token);
  xhr.send(form);
}

async function startDemo(event) {
  event.preventDefault();
  const kind = $("demo-kind").value;
  const frames = `frames=${$("demo-frames").value}&width=320&height=240`;
  let spec = `${kind}?${frames}`;
  if (kind === "agents") {
    // A collaborative session: one spec per agent of the same scene.
    const n = Math.max(1, Math.min(8, Number($("demo-agents").value) || 2));
    spec = Array.from({ length: n }, (_, k) => `agents?agent=${k}&agents=${n}&${frames}`);
  }
  const json = { source: "synthetic", spec };
  if ($("demo-preset").value) json.preset = $("demo-preset").value;
  try {
    const created = await api("/api/sessions", { method: "POST", json });
    say("demo-message", `Session ${created.id} created (${created.status}).`, "ok");
    selectSession(created.id);
    await refreshSessions();
  } catch (error) {
    say("demo-message", error.message, "error");
  }
}

// ------------------------------------------------------------------ viewer
async function setUpViewer() {
  try {
    const info = await api("/api/viewer");
    if (!info.enabled) throw new Error("viewer off");
    $("viewer-frame").src = withToken("/viewer");
    $("viewer-open").href = withToken("/viewer");
    $("viewer-open").hidden = false;
  } catch (_) {
    $("viewer-frame").hidden = true;
    $("viewer-off").hidden = false;
  }
}

// The viewer's height is this browser's choice, kept across visits.
function toggleViewerSize(save = true) {
  const tall = $("viewer-box").classList.toggle("tall");
  $("viewer-size").textContent = tall ? "shorter" : "taller";
  if (save) localStorage.setItem("voxfusion_viewer_tall", tall ? "1" : "");
}

// ------------------------------------------------------------------ render panel
let lastCamera = null;

const CROP_FIELDS = ["crop-x0", "crop-y0", "crop-z0", "crop-x1", "crop-y1", "crop-z1"];

// The crop box of the render panel: null when its fields are empty.
function cropBox() {
  const values = CROP_FIELDS.map((id) => $(id).value.trim());
  if (values.every((v) => v === "")) return null;
  if (values.some((v) => v === "" || !Number.isFinite(Number(v)))) throw new Error("crop box: give all six numbers, or none");
  const v = values.map(Number);
  if (!(v[0] < v[3] && v[1] < v[4] && v[2] < v[5])) throw new Error("crop box: every min must be below its max");
  return { min: v.slice(0, 3), max: v.slice(3) };
}

function currentCamera() {
  const width = Number($("cam-width").value), height = Number($("cam-height").value);
  const fov = deg(Number($("cam-fov").value));
  const f = (0.5 * height) / Math.tan(fov / 2);
  const camera = { T_world_cam: readMatrix(), intrinsics: { fx: f, fy: f, cx: width / 2, cy: height / 2, width, height } };
  const crop = cropBox();
  if (crop) camera.crop = crop;
  return camera;
}

// The crop box of the 3D viewer (the browser that changed it last) into the fields.
async function cropFromViewer() {
  try {
    const box = await api("/api/viewer/crop");
    [...box.min, ...box.max].forEach((v, i) => { $(CROP_FIELDS[i]).value = Number(v.toFixed(3)); });
    say("render-message", "Crop box taken from the viewer.", "ok");
  } catch (error) {
    say("render-message", error.message, "error");
  }
}

async function downloadCroppedMesh(event) {
  event.preventDefault();
  if (!selectedId) return say("render-message", "Select a session first.", "error");
  try {
    const crop = cropBox();
    if (!crop) throw new Error("crop box: fill in its six numbers first");
    const query = [...crop.min, ...crop.max].join(",");
    const blob = await api(`/api/sessions/${selectedId}/mesh?format=ply&crop=${encodeURIComponent(query)}`, { expect: "blob" });
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = `${selectedId}_mesh_crop.ply`;
    a.click();
    say("render-message", "Cropped mesh downloaded.", "ok");
  } catch (error) {
    say("render-message", error.message, "error");
  }
}

// The viewer's pose and vertical field of view; the render size stays what the user set (the
// viewer's window has an aspect of its own, which used to replace it for good).
async function useViewerCamera() {
  try {
    const width = Number($("cam-width").value) || 320, height = Number($("cam-height").value) || 240;
    const camera = await api(`/api/viewer/camera?width=${width}`);
    setCameraPose(camera.T_world_cam);
    const i = camera.intrinsics;
    $("cam-fov").value = verticalFov(i).toFixed(1);
    cameraChosen = true;
    say("render-message", `Camera taken from the viewer (pose and vertical field of view; size kept at ${width}x${height}).`, "ok");
  } catch (error) {
    say("render-message", error.message, "error");
  }
}

const verticalFov = (i) => (2 * Math.atan(i.height / 2 / i.fy) * 180) / Math.PI;

// The matrix is what renders; the fields show its position, yaw and pitch.
function setCameraPose(T) {
  $("cam-matrix").value = formatMatrix(T);
  const look = lookFromPose(T);
  ["cam-x", "cam-y", "cam-z"].forEach((id, k) => { $(id).value = look.position[k].toFixed(2); });
  $("cam-yaw").value = look.yaw.toFixed(1);
  $("cam-pitch").value = look.pitch.toFixed(1);
}

// Until the user picks a camera, the render panel follows the selected session's last tracked
// frame with that camera's own field of view and aspect (the synthetic room's default camera
// shows little of a real upload).
let cameraChosen = false;
let cameraOf = null;  // the session whose last tracked camera the panel holds

// The selected session's last tracked frame: its pose, and the input camera's field of view and
// aspect at the panel's width. `quiet`: no message (the automatic follow).
async function useLastPose(quiet = false) {
  if (!selectedId) return quiet || say("render-message", "Select a session first.", "error");
  const id = selectedId;
  try {
    const camera = await api(`/api/sessions/${id}/camera?agent=${plotAgent(id)}`);
    if (id !== selectedId) return;
    setCameraPose(camera.T_world_cam);
    const i = camera.intrinsics;
    const width = Number($("cam-width").value) || 320;
    $("cam-height").value = Math.max(16, Math.round((width * i.height) / i.width));
    $("cam-fov").value = verticalFov(i).toFixed(1);
    cameraOf = id;
    if (!quiet) {
      cameraChosen = true;
      say("render-message", `Pose and camera of the last tracked frame (frame ${camera.index}, t = ${camera.timestamp}).`, "ok");
    }
  } catch (error) {
    if (!quiet) say("render-message", error.message, "error");
  }
}

function followSession() {
  if (!cameraChosen && selectedId && cameraOf !== selectedId) useLastPose(true);
}

function poseFromNumbers() {
  const p = ["cam-x", "cam-y", "cam-z"].map((id) => Number($(id).value));
  $("cam-matrix").value = formatMatrix(poseLooking(p, Number($("cam-yaw").value), Number($("cam-pitch").value)));
}

async function renderView() {
  if (!selectedId) return say("render-message", "Select a session first.", "error");
  let camera;
  try { camera = currentCamera(); } catch (error) { return say("render-message", error.message, "error"); }
  say("render-message", "Rendering…");
  $("render-button").disabled = true;
  try {
    const path = `/api/sessions/${selectedId}/render`;
    const [color, preview] = await Promise.all([
      api(path, { method: "POST", json: camera, expect: "blob" }),
      api(path + secondImageQuery(), { method: "POST", json: camera, expect: "blob" }),
    ]);
    $("render-color").src = URL.createObjectURL(color);
    $("render-depth").src = URL.createObjectURL(preview);
    lastCamera = { ...camera, session: selectedId };
    say("render-message", `Rendered ${camera.intrinsics.width}x${camera.intrinsics.height}.`, "ok");
  } catch (error) {
    say("render-message", error.message, "error");
  } finally {
    $("render-button").disabled = false;
  }
}

// The second image: depth (colour-mapped, over min-max metres when given) or normals.
function secondImageQuery() {
  if ($("render-second").value === "normals") return "?output=normals";
  let query = "?output=depth_preview";
  for (const [id, name] of [["depth-min", "depth_min"], ["depth-max", "depth_max"]]) {
    if ($(id).value.trim() !== "") query += `&${name}=${Number($(id).value)}`;
  }
  return query;
}

async function downloadDepth(event) {
  event.preventDefault();
  if (!lastCamera) return say("render-message", "Render a view first.", "error");
  try {
    const { session, ...camera } = lastCamera;
    const blob = await api(`/api/sessions/${session}/render?output=depth`, { method: "POST", json: camera, expect: "blob" });
    const a = document.createElement("a");
    a.href = URL.createObjectURL(blob);
    a.download = `${session}_depth_mm.png`;
    a.click();
  } catch (error) {
    say("render-message", error.message, "error");
  }
}

// ------------------------------------------------------------------ AR panel
let assetId = null;

async function uploadAsset() {
  const file = $("ar-asset-file").files[0];
  if (!file) { assetId = null; $("ar-asset-note").textContent = ""; return; }
  const form = new FormData();
  form.append("file", file);
  $("ar-asset-note").textContent = "Uploading…";
  const response = await fetch("/api/assets", { method: "POST", headers: authHeaders(), body: form });
  if (!response.ok) {
    assetId = null;
    $("ar-asset-note").textContent = "Asset refused: " + (await errorText(response));
    return;
  }
  const body = await response.json();
  assetId = body.id;
  $("ar-asset-note").textContent = `Using ${file.name} (${body.faces} faces) instead of the shape.`;
}

const AR_POSITION = ["ar-x", "ar-y", "ar-z"];
let arNormal = null;  // the surface normal under the last placing click; typing x, y, z drops it

// The object to composite. Without x, y, z the server puts it in front of the camera.
function arObject() {
  const hex = $("ar-color").value;
  const color = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
  const fields = AR_POSITION.map((id) => $(id).value.trim());
  const object = { scale: Number($("ar-scale").value) };
  if (fields.some((v) => v !== "")) {
    if (fields.some((v) => v === "")) throw new Error("x, y, z: give all three, or none to put the object in front of the camera");
    const yaw = Number($("ar-yaw").value);
    object.T_world_obj = arNormal && $("ar-normal-up").checked
      ? surfacePose(fields.map(Number), arNormal, yaw) : yawPose(fields.map(Number), yaw);
  }
  if (assetId) object.asset = assetId;
  else { object.shape = $("ar-shape").value; object.color = color; }
  return object;
}

function arObjectName() {
  return assetId ? $("ar-asset-file").files[0]?.name || "object" : $("ar-shape").value;
}

// What the server says of the object (the X-AR-Objects header): shown, hidden, or out of view.
function visibilityMessage(report, name) {
  const entry = report[0];
  if (!entry) return ["Done.", "ok"];
  const at = `at (${entry.position.map((v) => v.toFixed(2)).join(", ")})`;
  const fix = "Move it, or empty x, y, z to put it in front of the camera.";
  if (entry.state === "outside") return [`The ${name} ${at} is outside the camera's view: nothing of it shows. ${fix}`, "warn"];
  if (entry.state === "hidden") return [`The ${name} ${at} is fully hidden behind the scene in this view. ${fix}`, "warn"];
  return [`Done: the ${name} shows ${at} (${plural(entry.visible_pixels, "pixel")}).`, "ok"];
}

async function composite() {
  if (!selectedId) return say("ar-message", "Select a session first.", "error");
  let request;
  try { request = { objects: [arObject()] }; } catch (error) { return say("ar-message", error.message, "error"); }
  if ($("ar-background").value === "frame") {
    request.background = `frame:${Number($("ar-frame").value)}`;
  } else {
    try {
      const { crop, ...camera } = currentCamera();  // the composite shows the whole map
      Object.assign(request, camera);
    } catch (error) { return say("ar-message", error.message, "error"); }
    request.background = "render";
  }
  say("ar-message", "Compositing…");
  try {
    const response = await fetch(`/api/sessions/${selectedId}/ar`, {
      method: "POST", headers: authHeaders({ "Content-Type": "application/json" }), body: JSON.stringify(request),
    });
    if (!response.ok) throw new Error(await errorText(response));
    $("ar-image").src = URL.createObjectURL(await response.blob());
    const report = JSON.parse(response.headers.get("X-AR-Objects") || "[]");
    say("ar-message", ...visibilityMessage(report, arObjectName()));
  } catch (error) {
    say("ar-message", error.message, "error");
  }
}

async function pickSurface(event) {
  if (!lastCamera || !$("ar-place").checked) return;
  const img = $("render-color");
  const rect = img.getBoundingClientRect();
  const u = ((event.clientX - rect.left) / rect.width) * lastCamera.intrinsics.width;
  const v = ((event.clientY - rect.top) / rect.height) * lastCamera.intrinsics.height;
  const { session, ...camera } = lastCamera;
  try {
    const hit = await api(`/api/sessions/${session}/pick`, { method: "POST", json: { ...camera, u, v } });
    if (!hit.hit) return say("ar-message", "Nothing of the map under that pixel.", "error");
    const half = Number($("ar-scale").value) / 2;
    const centre = hit.point.map((p, i) => p + hit.normal[i] * half);
    AR_POSITION.forEach((id, i) => { $(id).value = centre[i].toFixed(3); });
    arNormal = hit.normal;
    $("ar-background").value = "render";
    say("ar-message", `Placed on the surface at ${hit.point.map((p) => p.toFixed(2)).join(", ")}.`, "ok");
    composite();
  } catch (error) {
    say("ar-message", error.message, "error");
  }
}

// ------------------------------------------------------------------ camera path video
let pathKeys = [];  // T_world_cam of the path's keyframes, in order
let pathSession = null;
const PATH_POLL_MS = 700;

function showPathKeys() {
  $("path-count").textContent = pathKeys.length ? plural(pathKeys.length, "keyframe") : "no keyframes";
}

function addPathKey(T) {
  if (pathSession !== selectedId) { pathKeys = []; pathSession = selectedId; }  // keyframes belong to one map
  pathKeys.push(T);
  showPathKeys();
  say("path-message", pathKeys.length < 2 ? "Add at least one more keyframe." : "", "ok");
  previewPath();
}

// The path as the video will fly it, drawn in the 3D viewer (orange); cleared with the keyframes.
async function previewPath() {
  if (!pathSession) return;
  const url = `/api/sessions/${pathSession}/render/path/preview`;
  try {
    if (pathKeys.length < 2) await api(url, { method: "DELETE" });
    else await api(url, { method: "PUT", json: { keyframes: pathKeys, loop: $("path-loop").checked } });
  } catch (error) {
    say("path-message", "preview: " + error.message, "error");
  }
}

async function addViewerKey() {
  try {
    addPathKey((await api("/api/viewer/camera?width=64")).T_world_cam);
  } catch (error) {
    say("path-message", error.message, "error");
  }
}

function addRenderKey() {
  try { addPathKey(readMatrix()); } catch (error) { say("path-message", error.message, "error"); }
}

async function renderPath() {
  if (!selectedId) return say("path-message", "Select a session first.", "error");
  if (pathKeys.length < 2 || pathSession !== selectedId) return say("path-message", "Add two keyframes or more of this session first.", "error");
  const outputs = ["color", "depth", "normals"].filter((o) => $(`path-${o}`).checked);
  let camera;
  try { camera = currentCamera(); } catch (error) { return say("path-message", error.message, "error"); }
  const body = { keyframes: pathKeys, intrinsics: camera.intrinsics, crop: camera.crop, duration_s: Number($("path-duration").value),
                 fps: Number($("path-fps").value), loop: $("path-loop").checked, outputs };
  $("path-button").disabled = true;
  try {
    let job = await api(`/api/sessions/${selectedId}/render/path`, { method: "POST", json: body });
    const bar = $("path-progress");
    bar.hidden = false;
    while (job.state === "queued" || job.state === "rendering") {
      bar.max = job.frames_total;
      bar.value = job.frames_done;
      say("path-message", `Rendering frame ${job.frames_done} of ${job.frames_total}…`);
      await new Promise((resolve) => setTimeout(resolve, PATH_POLL_MS));
      job = await api(job.video.replace(/\/video$/, ""));
    }
    bar.hidden = true;
    if (job.state !== "finished") throw new Error(job.error || job.state);
    const blob = await api(job.video, { expect: "blob" });
    const url = URL.createObjectURL(blob);
    $("path-video").src = url;
    $("path-video").hidden = false;
    $("path-download").href = url;
    $("path-download").download = `${selectedId}_path.mp4`;
    $("path-download").hidden = false;
    say("path-message", `Rendered ${job.frames_total} frames (${outputs.join(" | ")}).`, "ok");
  } catch (error) {
    $("path-progress").hidden = true;
    say("path-message", error.message, "error");
  } finally {
    $("path-button").disabled = false;
  }
}

// ------------------------------------------------------------------ accuracy and speed plots
const PLOT_EVERY_MS = 3000;
const MIN_FPS_SPAN_S = 0.25;  // as the server's: the first poses can arrive with the phase's start
const AXES = ["x", "y", "z"];
let plotsShown = null;  // {id, at, ended} of the plots drawn last
let plotsBusy = false;

// Fetch and draw the selected session's series: when the selection changes, every few seconds
// while it runs, and once more when it has ended.
async function refreshPlots() {
  const s = sessions.find((x) => x.id === selectedId);
  $("plots-session").textContent = s ? `session ${s.id}` : "";
  if (!s && plotsShown) {  // the session shown was deleted and none is left
    for (const id of ["plot-trajectory", "plot-error", "plot-fps"]) Plots.message($(id), "no session");
    $("plots-note").textContent = "";
    plotsShown = null;
  }
  if (!s || plotsBusy) return;
  showAgentChoice(s);
  const agent = plotAgent(s.id);
  const ended = ENDED.includes(s.status);
  const shown = plotsShown && plotsShown.id === s.id && plotsShown.agent === agent;
  if (shown && (ended ? plotsShown.ended : Date.now() - plotsShown.at < PLOT_EVERY_MS)) return;
  plotsBusy = true;
  try {
    drawPlots(await api(`/api/sessions/${s.id}/series?agent=${agent}`), s);
    plotsShown = { id: s.id, agent, at: Date.now(), ended };
  } catch (error) {
    $("plots-note").textContent = "plots: " + error.message;
  } finally {
    plotsBusy = false;
  }
}

// A collaborative session's plots show one agent at a time, chosen beside the card's title.
let agentChoice = { id: null, agent: 0 };

function plotAgent(id) {
  return agentChoice.id === id ? agentChoice.agent : 0;
}

function showAgentChoice(s) {
  const agents = s.agents || 1, select = $("plots-agent");
  $("plots-agent-label").hidden = agents < 2;
  if (agentChoice.id !== s.id) agentChoice = { id: s.id, agent: 0 };
  if (select.options.length !== agents) {
    select.replaceChildren(...Array.from({ length: agents }, (_, k) => new Option(`agent ${k}`, String(k))));
  }
  select.value = String(agentChoice.agent);
}

function chooseAgent() {
  agentChoice = { id: selectedId, agent: Number($("plots-agent").value) };
  refreshPlots();
}

// The two axes along which the path spreads most: the ground plane of a walk (a top view).
function topAxes(points) {
  const spread = [0, 1, 2].map((k) => Math.max(...points.map((p) => p[k])) - Math.min(...points.map((p) => p[k])));
  return [0, 1, 2].sort((a, b) => spread[b] - spread[a]).slice(0, 2).sort();
}

function drawPlots(series, s) {
  const truth = series.ground_truth;
  const reference = truth && truth.length ? truth : series.estimated;
  const running = ENDED.includes(s.status) ? "" : " so far";
  // Agent 0's is the status's, as in the list: one number on the page; another agent's is its own.
  const ate = series.agent === 0 ? s.ate_rmse_m ?? series.ate_rmse_m : series.ate_rmse_m;
  const who = (s.agents || 1) > 1 ? `agent ${series.agent}: ` : "";
  $("plots-note").textContent = ate != null
    ? `${who}ATE ${centimetres(ate)} over ${plural(series.estimated.length, "frame")}${running} (RMSE after a rigid alignment onto the ground truth)`
    : truth ? "Too few frames to align onto the ground truth yet." : "This input has no ground truth: the trajectory is shown in the session's own frame.";
  drawTrajectory(series, reference);
  drawError(series);
  drawFps(series);
}

function drawTrajectory(series, reference) {
  if (!reference.length) return Plots.message($("plot-trajectory"), "no poses yet");
  const [a, b] = topAxes(reference);
  const project = (points) => points.map((p) => [p[a], p[b]]);
  const lines = [{ points: project(series.estimated), color: "#2a6fc9", width: 2 }];
  if (series.ground_truth) lines.unshift({ points: project(series.ground_truth), color: "#9aa5b1", width: 3 });
  Plots.lines($("plot-trajectory"), lines, { xLabel: `${AXES[a]} (m)`, yLabel: `${AXES[b]} (m)`, equal: true });
  $("plot-trajectory-caption").textContent = `trajectory, top view (${AXES[a]}, ${AXES[b]}): estimated (blue)` +
    (series.ground_truth ? (series.aligned ? ", aligned onto the ground truth (grey)" : " and ground truth (grey), not aligned yet") : "");
}

function drawError(series) {
  if (!series.error_m) return Plots.message($("plot-error"), series.ground_truth ? "too few frames to align yet" : "no ground truth for this input");
  const t0 = series.timestamps[0];
  const points = series.error_m.map((e, i) => (e == null ? null : [series.timestamps[i] - t0, e * 100]));
  const t1 = series.timestamps[series.timestamps.length - 1] - t0;
  const rmse = series.ate_rmse_m * 100;
  Plots.lines($("plot-error"), [
    { points, color: "#c93c3c" },
    { points: [[0, rmse], [t1, rmse]], color: "#6b7785", dash: [5, 4], width: 1 },
  ], { xLabel: "input time (s)", yLabel: "error (cm)", yFromZero: true });
}

// frames/s between consecutive samples (from the phase's start, 0 frames at 0 s, so the
// start-up before the first pose shows), and the average (the status's frames/s) dashed.
function drawFps(series) {
  if (!series.fps_time_s.length) return Plots.message($("plot-fps"), "tracking has not started yet");
  if (series.fps_frames[series.fps_frames.length - 1] < 2) return Plots.message($("plot-fps"), "measuring…");
  const t = [0, ...series.fps_time_s], n = [0, ...series.fps_frames];
  const rates = t.slice(1).map((ti, i) => [ti, (n[i + 1] - n[i]) / Math.max(ti - t[i], MIN_FPS_SPAN_S)]);
  const average = n[n.length - 1] / Math.max(t[t.length - 1], MIN_FPS_SPAN_S);
  Plots.lines($("plot-fps"), [
    { points: rates, color: "#2e9d5b" },
    { points: [[t[0], average], [t[t.length - 1], average]], color: "#6b7785", dash: [5, 4], width: 1 },
  ], { xLabel: "time since tracking began (s)", yLabel: "frames/s", yFromZero: true });
}

// ------------------------------------------------------------------ start
function start() {
  fillPresets();
  poseFromNumbers();
  $("upload-form").addEventListener("submit", uploadDataset);
  $("demo-form").addEventListener("submit", startDemo);
  $("demo-kind").addEventListener("change", () => { $("demo-agents-label").hidden = $("demo-kind").value !== "agents"; });
  $("use-viewer-camera").addEventListener("click", useViewerCamera);
  $("use-last-pose").addEventListener("click", () => useLastPose());
  $("pose-from-numbers").addEventListener("click", () => { cameraChosen = true; poseFromNumbers(); });
  $("cam-matrix").addEventListener("input", () => { cameraChosen = true; });
  $("plots-agent").addEventListener("change", chooseAgent);
  $("render-button").addEventListener("click", renderView);
  $("depth-download").addEventListener("click", downloadDepth);
  $("render-color").addEventListener("click", pickSurface);
  $("ar-asset-file").addEventListener("change", uploadAsset);
  $("ar-button").addEventListener("click", composite);
  $("ar-auto").addEventListener("click", () => { AR_POSITION.forEach((id) => { $(id).value = ""; }); composite(); });
  AR_POSITION.forEach((id) => $(id).addEventListener("input", () => { arNormal = null; }));  // typed: world-upright
  window.addEventListener("resize", () => { plotsShown = null; refreshPlots(); });
  $("viewer-size").addEventListener("click", () => toggleViewerSize());
  $("path-add-viewer").addEventListener("click", addViewerKey);
  $("path-add-render").addEventListener("click", addRenderKey);
  $("path-clear").addEventListener("click", () => { pathKeys = []; showPathKeys(); say("path-message", ""); previewPath(); });
  $("path-loop").addEventListener("change", previewPath);
  $("path-button").addEventListener("click", renderPath);
  $("crop-mesh").addEventListener("click", downloadCroppedMesh);
  $("crop-from-viewer").addEventListener("click", cropFromViewer);
  $("render-second").addEventListener("change", () => {
    $("depth-range").hidden = $("render-second").value !== "depth";
    if (lastCamera) renderView();
  });
  $("crop-clear").addEventListener("click", () => { CROP_FIELDS.forEach((id) => { $(id).value = ""; }); });
  if (localStorage.getItem("voxfusion_viewer_tall")) toggleViewerSize(false);
  setUpViewer();
  refreshSessions();
  setInterval(refreshSessions, 1000);
}

start();
