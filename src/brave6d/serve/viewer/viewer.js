// BRAVE-6D browser viewer: drives one episode of the render server through its REST API, or,
// in free view (the "free view" toggle; always for a bundle without objects, and when no episode
// can start), moves a camera of its own and asks POST /render for each pose: no episode, no
// object poses, the same pose checks (a pose outside the workspace or in a box shows the red banner).
// Drag orbits around the target, the wheel and WASD/QE move the camera (camera-frame twists),
// the arrow keys turn it. Object axes (x red, y green, z blue) and ids are drawn from the
// ground-truth poses (cam_T_obj) and the intrinsics K of each observation, which only a server in
// training mode sends (a scored server sends no object poses: the view shows the images alone, and
// the orbit centres on the bundle's start target, or the target's placement in training mode). Refused moves show
// a red banner with the server's reason; moves stopped part-way at a collision an orange one.
// State for tests: document.body.dataset.{frames, refusals, state, lastRefusal}; window.braveViewer.
// A server started with a token is opened as /viewer/?token=TOKEN: the page sends it with every
// request (Authorization: Bearer, or ?token= where no header can be set).
"use strict";

(function () {
  const params = new URLSearchParams(window.location.search);
  const token = params.get("token");
  const canvas = document.getElementById("view");
  const ctx = canvas.getContext("2d");
  const banner = document.getElementById("banner");
  const body = document.body;
  const STEP_S = 0.4, LIN = 0.05, ANG = 0.3; // one key press: 2 cm or ~7 degrees

  const state = {
    bundle: null, episodeId: null, last: null, frames: 0, refusals: 0,
    queue: [], busy: false, bannerTimer: null, drag: null, labels: [],
    free: false, pose: null, size: null, // free view: its camera pose (world_T_cam) and image size
  };
  const freeBox = document.getElementById("free");

  function showBanner(kind, text) {
    banner.className = "banner " + kind;
    banner.textContent = text;
    clearTimeout(state.bannerTimer);
    state.bannerTimer = setTimeout(() => banner.classList.add("hidden"), 5000);
  }

  async function api(method, path, payload) {
    const init = { method, headers: {} };
    if (token) init.headers["Authorization"] = "Bearer " + token;
    if (payload !== undefined) {
      init.headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(payload);
    }
    const response = await fetch(path, init);
    const data = await response.json().catch(() => ({ error: response.statusText }));
    if (!response.ok) {
      const err = new Error(data.error || ("HTTP " + response.status));
      err.status = response.status;
      throw err;
    }
    return data;
  }

  // ------------------------------------------------------------------ drawing
  function project(K, T, p) {
    const x = T[0][0] * p[0] + T[0][1] * p[1] + T[0][2] * p[2] + T[0][3];
    const y = T[1][0] * p[0] + T[1][1] * p[1] + T[1][2] * p[2] + T[1][3];
    const z = T[2][0] * p[0] + T[2][1] * p[1] + T[2][2] * p[2] + T[2][3];
    if (z <= 1e-4) return null;
    return [K[0][0] * x / z + K[0][2], K[1][1] * y / z + K[1][2]];
  }

  function drawOverlay(obs) {
    const K = obs.K;
    state.labels = [];
    for (const o of obs.objects) {
      const info = state.bundle.objects.find((b) => b.gt_id === o.gt_id);
      const len = info ? 0.5 * info.diameter_mm / 1000 : 0.02;
      const origin = project(K, o.cam_T_obj, [0, 0, 0]);
      if (!origin) continue;
      const axes = [[[len, 0, 0], "#ff3b30"], [[0, len, 0], "#34c759"], [[0, 0, len], "#0a84ff"]];
      ctx.lineWidth = o.is_target ? 3 : 2;
      for (const [p, colour] of axes) {
        const q = project(K, o.cam_T_obj, p);
        if (!q) continue;
        ctx.strokeStyle = colour;
        ctx.beginPath();
        ctx.moveTo(origin[0], origin[1]);
        ctx.lineTo(q[0], q[1]);
        ctx.stroke();
      }
      const vis = o.visib_fract === null ? "" : " " + Math.round(100 * o.visib_fract) + "%";
      const label = "id " + o.obj_id + " " + o.name + vis;
      ctx.font = "12px sans-serif";
      ctx.fillStyle = "rgba(0,0,0,0.6)";
      ctx.fillRect(origin[0] + 4, origin[1] - 16, ctx.measureText(label).width + 6, 15);
      ctx.fillStyle = o.is_target ? "#ffd34d" : "#ffffff";
      ctx.fillText(label, origin[0] + 7, origin[1] - 4);
      state.labels.push(label);
    }
  }

  function updatePanel(step) {
    const obs = step.observation;
    document.getElementById("episode").textContent = step.episode_id;
    document.getElementById("adjustments").textContent = String(step.adjustments);
    document.getElementById("render-ms").textContent =
      step.accepted ? step.timings_ms.render.toFixed(1) + " ms" : "- (refused: nothing rendered)";
    document.getElementById("total-ms").textContent = step.timings_ms.total.toFixed(1) + " ms";
    const t = obs.world_T_cam;
    document.getElementById("pose").textContent =
      "[" + [t[0][3], t[1][3], t[2][3]].map((v) => v.toFixed(3)).join(", ") + "]";
    const tbody = document.querySelector("#objects tbody");
    tbody.innerHTML = "";
    for (const o of obs.objects) {
      const tr = document.createElement("tr");
      if (o.is_target) tr.className = "target";
      const vis = o.visib_fract === null ? "-" : (100 * o.visib_fract).toFixed(0) + "%";
      for (const cell of [o.obj_id, o.name, vis, o.cam_T_obj[2][3].toFixed(3)]) {
        const td = document.createElement("td");
        td.textContent = String(cell);
        tr.appendChild(td);
      }
      tbody.appendChild(tr);
    }
  }

  function show(step) {
    return new Promise((resolve) => {
      const obs = step.observation;
      const img = new Image();
      img.onload = () => {
        if (canvas.width !== obs.width || canvas.height !== obs.height) {
          canvas.width = obs.width;
          canvas.height = obs.height;
        }
        ctx.drawImage(img, 0, 0);
        drawOverlay(obs);
        state.frames += 1;
        body.dataset.frames = String(state.frames);
        resolve();
      };
      img.onerror = () => resolve();
      img.src = "data:image/" + (obs.rgb.encoding === "png" ? "png" : "jpeg") + ";base64," + obs.rgb.data;
    });
  }

  function refused(message) {
    state.refusals += 1;
    body.dataset.refusals = String(state.refusals);
    body.dataset.lastRefusal = message;
    showBanner("refused", "Refused: " + message);
  }

  function handle(step) {
    state.last = step;
    updatePanel(step);
    if (!step.accepted) {
      refused(step.refusal.message);
    } else if (step.collided && step.refusal) {
      showBanner("stopped", "Stopped at a collision: " + step.refusal.message);
    } else {
      banner.classList.add("hidden");
    }
    return show(step);
  }

  // ------------------------------------------------------------------ requests (one at a time)
  function enqueue(kind, payload) {
    if (!state.episodeId && !state.free) return;
    if (kind === "set_pose") state.queue = state.queue.filter((q) => q.kind !== "set_pose");
    if (state.queue.length > 8) state.queue.shift();
    state.queue.push({ kind, payload });
    pump();
  }

  async function pump() {
    if (state.busy || state.queue.length === 0) return;
    const item = state.queue.shift();
    state.busy = true;
    try {
      if (state.free) {
        const pose = item.kind === "set_pose" ? item.payload.pose : { world_T_cam: twisted(state.pose, item.payload) };
        await renderFree(pose);
      } else {
        const step = await api("POST", "/episodes/" + state.episodeId + "/" + item.kind,
          Object.assign({ rgb: "jpeg", depth: "none" }, item.payload));
        await handle(step);
      }
    } catch (err) {
      if (state.free && err.status === 422) refused(err.message);
      else showBanner("error", "Error: " + err.message);
    } finally {
      state.busy = false;
      pump();
    }
  }

  function move(linear, angular) {
    enqueue("move", { linear, angular, duration: STEP_S, frame: "camera" });
  }

  function setPose(pose) {
    enqueue("set_pose", { pose });
  }

  // ------------------------------------------------------------------ orbit
  function targetCentre() {
    if (state.free || state.bundle.objects.length === 0) {
      const c = (state.bundle.start && state.bundle.start.target) || [0, 0, 0];
      return [c[0], c[1], c[2]];
    }
    const gt = Number(document.getElementById("target").value || 0);
    const o = state.bundle.objects.find((b) => b.gt_id === gt) || state.bundle.objects[0];
    const T = o.world_T_obj; // training mode only: a scored server lists no placements
    if (!T) {
      const c = (state.bundle.start && state.bundle.start.target) || [0, 0, 0];
      return [c[0], c[1], c[2]];
    }
    return [T[0][3], T[1][3], T[2][3] + 0.01];
  }

  function currentPose() {
    if (state.free) return state.pose;
    return state.last ? state.last.observation.world_T_cam : null;
  }

  function orbitStart(x, y) {
    const T = currentPose();
    if (!T) return;
    const c = targetCentre();
    const d = [T[0][3] - c[0], T[1][3] - c[1], T[2][3] - c[2]];
    const r = Math.hypot(d[0], d[1], d[2]);
    state.drag = { x, y, c, r, az: Math.atan2(d[1], d[0]), el: Math.asin(Math.max(-1, Math.min(1, d[2] / r))) };
  }

  function orbitTo(x, y) {
    const g = state.drag;
    if (!g) return;
    const az = g.az - (x - g.x) * 0.01;
    const el = Math.max(-1.2, Math.min(1.5, g.el + (y - g.y) * 0.01));
    const eye = [g.c[0] + g.r * Math.cos(el) * Math.cos(az), g.c[1] + g.r * Math.cos(el) * Math.sin(az),
      g.c[2] + g.r * Math.sin(el)];
    setPose({ look_at: { eye, target: g.c, up: [0, 0, 1] } });
  }

  canvas.addEventListener("mousedown", (e) => { canvas.focus(); orbitStart(e.offsetX, e.offsetY); });
  canvas.addEventListener("mousemove", (e) => { if (state.drag && e.buttons) orbitTo(e.offsetX, e.offsetY); });
  window.addEventListener("mouseup", (e) => {
    if (state.drag) { orbitTo(e.offsetX, e.offsetY); state.drag = null; }
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    move([0, 0, e.deltaY < 0 ? LIN : -LIN], [0, 0, 0]);
  }, { passive: false });

  const KEYS = {
    w: [[0, 0, LIN], [0, 0, 0]], s: [[0, 0, -LIN], [0, 0, 0]],
    a: [[-LIN, 0, 0], [0, 0, 0]], d: [[LIN, 0, 0], [0, 0, 0]],
    q: [[0, -LIN, 0], [0, 0, 0]], e: [[0, LIN, 0], [0, 0, 0]],
    arrowleft: [[0, 0, 0], [0, -ANG, 0]], arrowright: [[0, 0, 0], [0, ANG, 0]],
    arrowup: [[0, 0, 0], [ANG, 0, 0]], arrowdown: [[0, 0, 0], [-ANG, 0, 0]],
  };
  window.addEventListener("keydown", (e) => {
    if (e.target && e.target.tagName === "SELECT") return;
    const key = e.key.toLowerCase();
    if (key === "r") { if (state.free) startFree(); else reset(); return; }
    const twist = KEYS[key];
    if (!twist) return;
    e.preventDefault();
    move(twist[0], twist[1]);
  });

  // ------------------------------------------------------------------ free view (POST /render)
  function rotation(w) { // Rodrigues: the rotation of the axis-angle vector w
    const a = Math.hypot(w[0], w[1], w[2]);
    if (a < 1e-12) return [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
    const k = [w[0] / a, w[1] / a, w[2] / a], c = Math.cos(a), s = Math.sin(a), v = 1 - c;
    return [[c + k[0] * k[0] * v, k[0] * k[1] * v - k[2] * s, k[0] * k[2] * v + k[1] * s],
      [k[1] * k[0] * v + k[2] * s, c + k[1] * k[1] * v, k[1] * k[2] * v - k[0] * s],
      [k[2] * k[0] * v - k[1] * s, k[2] * k[1] * v + k[0] * s, c + k[2] * k[2] * v]];
  }

  function twisted(T, move) { // T moved by a camera-frame twist for move.duration (as the server's move)
    const d = move.duration, R = rotation(move.angular.map((w) => w * d));
    const out = [];
    for (let i = 0; i < 3; i++) {
      const row = [0, 0, 0, T[i][3]];
      for (let j = 0; j < 3; j++) {
        for (let k = 0; k < 3; k++) row[j] += T[i][k] * R[k][j];
        row[3] += T[i][j] * move.linear[j] * d;
      }
      out.push(row);
    }
    out.push([0, 0, 0, 1]);
    return out;
  }

  function startPose() { // a held-out capture view (a pose a real camera had), else a look at the start target
    const held = state.bundle.holdout || [];
    if (held.length) return { world_T_cam: held[0].world_T_cam };
    const s = state.bundle.start || {}, c = targetCentre();
    const r = (s.distances_m && s.distances_m.length) ? Math.min(...s.distances_m) : 0.5;
    const el = Math.PI / 180 * (((s.min_elevation_deg ?? 30) + (s.max_elevation_deg ?? 60)) / 2);
    const eye = [c[0], c[1] - r * Math.cos(el), c[2] + r * Math.sin(el)];
    return { look_at: { eye, target: c, up: [0, 0, 1] } };
  }

  async function renderFree(pose) {
    const view = await api("POST", "/render", Object.assign({ pose, rgb: "jpeg", depth: "none" }, state.size));
    state.pose = view.observation.world_T_cam;
    banner.classList.add("hidden");
    document.getElementById("episode").textContent = "- (free view of " + view.scene + ")";
    document.getElementById("adjustments").textContent = "-";
    document.getElementById("render-ms").textContent = view.timings_ms.render.toFixed(1) + " ms";
    document.getElementById("total-ms").textContent = view.timings_ms.total.toFixed(1) + " ms";
    const t = state.pose;
    document.getElementById("pose").textContent =
      "[" + [t[0][3], t[1][3], t[2][3]].map((v) => v.toFixed(3)).join(", ") + "]";
    document.querySelector("#objects tbody").innerHTML = "";
    await show(view);
  }

  async function startFree(why) { // leave any episode; look from the current pose, else the start pose
    const pose = currentPose();
    const old = state.episodeId;
    state.episodeId = null;
    state.queue = [];
    if (old) api("POST", "/episodes/" + old + "/close").catch(() => {});
    state.free = true;
    freeBox.checked = true;
    body.dataset.mode = "free";
    body.dataset.state = "resetting";
    try {
      await renderFree(pose ? { world_T_cam: pose } : startPose());
      body.dataset.state = "ready";
      if (why) showBanner("stopped", why);
    } catch (err) {
      body.dataset.state = "error";
      showBanner("error", "Error: " + err.message);
    }
  }

  function imageSize() {
    const r = state.bundle.render;
    const width = Number(params.get("width")) || Math.min(640, r.width);
    const height = Number(params.get("height")) || Math.round(width * r.height / r.width);
    return { width, height };
  }

  // ------------------------------------------------------------------ episodes
  async function reset() {
    if (state.bundle.objects.length === 0) { await startFree(); return; }
    body.dataset.state = "resetting";
    const old = state.episodeId;
    state.episodeId = null;
    state.queue = [];
    state.free = false;
    freeBox.checked = false;
    body.dataset.mode = "episode";
    if (old) api("POST", "/episodes/" + old + "/close").catch(() => {});
    const seed = params.has("seed") ? Number(params.get("seed")) : Math.floor(Math.random() * 1e9);
    const request = Object.assign({ seed, rgb: "jpeg", depth: "none",
      target: Number(document.getElementById("target").value || 0) }, state.size);
    try {
      const step = await api("POST", "/episodes", request);
      state.episodeId = step.episode_id;
      await handle(step);
      body.dataset.state = "ready";
    } catch (err) { // no episode can start (too many open, a scene that refuses): look around freely
      await startFree("No episode (" + err.message + "): free view");
    }
  }

  async function init() {
    try {
      state.bundle = await api("GET", "/bundle");
    } catch (err) {
      body.dataset.state = "error";
      showBanner("error", "Cannot load the bundle: " + err.message);
      return;
    }
    document.getElementById("scene").textContent =
      state.bundle.name + " (" + state.bundle.gaussians + " Gaussians, " + state.bundle.device + ", " +
      (state.bundle.mode || "training") + " mode)";
    body.dataset.serverMode = state.bundle.mode || "training";
    const select = document.getElementById("target");
    for (const o of state.bundle.objects) {
      const opt = document.createElement("option");
      opt.value = String(o.gt_id);
      opt.textContent = o.obj_id + ": " + o.name;
      select.appendChild(opt);
    }
    if (params.has("target")) select.value = params.get("target");
    state.size = imageSize();
    const noObjects = state.bundle.objects.length === 0;
    freeBox.disabled = noObjects; // a bundle without objects has free views only
    select.disabled = noObjects;
    document.getElementById("reset").disabled = noObjects;
    freeBox.addEventListener("change", () => (freeBox.checked ? startFree() : reset()));
    select.addEventListener("change", reset);
    document.getElementById("reset").addEventListener("click", reset);
    window.addEventListener("beforeunload", () => {
      if (state.episodeId) {
        const query = token ? "?token=" + encodeURIComponent(token) : "";
        navigator.sendBeacon("/episodes/" + state.episodeId + "/close" + query);
      }
    });
    if (noObjects || params.get("free") === "1") await startFree();
    else await reset();
  }

  window.braveViewer = {
    get frames() { return state.frames; },
    get episodeId() { return state.episodeId; },
    get last() { return state.last; },
    get labels() { return state.labels.slice(); },
    get idle() { return !state.busy && state.queue.length === 0; },
    get free() { return state.free; },
    get pose() { return currentPose(); },
    setPose, move, reset, startFree,
  };
  init();
})();
