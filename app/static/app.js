// fuzzyrisk operator page: maps, their risk, the last scan, and plans on them.
// Plain browser JavaScript, no build step; everything it loads comes from this service.
"use strict";

(() => {
  // The service root is the folder above /ui/, so the page also works behind a path prefix.
  const API_ROOT = new URL("..", document.baseURI);
  const KEY_STORE = "fuzzyrisk.apiKey";
  const POLL_MS = 1000;

  const $ = (id) => document.getElementById(id);
  const enc = encodeURIComponent;

  const state = {
    current: null,       // MapInfo of the shown map
    gen: 0,              // bumped on every map switch: answers for an older map are dropped
    loading: null,       // promise of the image load in flight, so polls do not stack loads
    image: null,         // ImageBitmap of the risk PNG, one pixel per cell
    shownVersion: null,  // map version the image shows
    scan: null,          // GET /maps/{name}/scans/last, or null before the first scan
    start: null,         // [x, y(, z)] world metres
    goal: null,
    path: null,          // [[x, y(, z)], ...] of the last plan
    zoom: 1,             // canvas pixels per cell
  };

  // ---------------------------------------------------------------- API

  class ApiError extends Error {
    constructor(status, detail) {
      super(describeDetail(status, detail));
      this.status = status;
      this.detail = detail;
      this.code = detail && typeof detail === "object" && !Array.isArray(detail) ? detail.code : undefined;
    }

    static async from(response) {
      let detail = response.statusText;
      try {
        const body = await response.json();
        detail = body.detail ?? body;
      } catch (_) { /* not JSON: keep the status text */ }
      return new ApiError(response.status, detail);
    }
  }

  function describeDetail(status, detail) {
    if (typeof detail === "string" && detail) return detail;
    if (Array.isArray(detail)) {
      // FastAPI's validation errors: name the field the server complained about
      return detail.map((e) => {
        const where = (e.loc || []).filter((p) => p !== "body").join(".");
        return where ? `${where}: ${e.msg}` : e.msg;
      }).join("; ");
    }
    if (detail && typeof detail === "object" && detail.message) return detail.message;
    return `HTTP ${status}`;
  }

  let keyRequest = null;  // one form for every request that met a 401

  function askForKey(message) {
    if (!keyRequest) {
      keyRequest = new Promise((resolve) => {
        const form = $("auth-form");
        const input = $("api-key");
        $("auth-msg").textContent = message;
        $("auth").hidden = false;
        input.value = "";
        input.focus();
        form.onsubmit = (event) => {
          event.preventDefault();
          const key = input.value.trim();
          if (!key) return;
          sessionStorage.setItem(KEY_STORE, key);
          $("auth").hidden = true;
          form.onsubmit = null;
          keyRequest = null;
          updateKeyButton();
          resolve();
        };
      });
    }
    return keyRequest;
  }

  async function api(path, { method = "GET", body = null, as = "json" } = {}) {
    for (;;) {
      const key = sessionStorage.getItem(KEY_STORE);
      const headers = {};
      if (key) headers.Authorization = `Bearer ${key}`;
      if (body !== null) headers["Content-Type"] = "application/json";
      const response = await fetch(new URL(path, API_ROOT), {
        method, headers, body: body === null ? null : JSON.stringify(body), cache: "no-store",
      });
      if (response.status === 401) {
        // a request sent before the operator typed a new key: just send it again
        if (key !== sessionStorage.getItem(KEY_STORE)) continue;
        if (key) {
          sessionStorage.removeItem(KEY_STORE);
          updateKeyButton();
        }
        await askForKey(key
          ? "The service rejected that key. Check it and try again."
          : "This service needs an API key. It is kept for this browser tab only.");
        continue;
      }
      if (!response.ok) throw await ApiError.from(response);
      if (response.status === 204) return null;
      return as === "blob" ? response.blob() : response.json();
    }
  }

  function updateKeyButton() {
    $("forget-key").hidden = !sessionStorage.getItem(KEY_STORE);
  }

  function setConn(text) {
    if ($("conn").textContent !== text) $("conn").textContent = text;
  }

  // ---------------------------------------------------------------- formatting

  const fmt = (v, digits = 2) => (typeof v === "number" && Number.isFinite(v) ? v.toFixed(digits) : "?");

  // a map size as typed at creation: 4 not 4.000, 0.35 not 0.4
  const fmtLength = (v) => String(Number(v.toFixed(3)));

  function coordDigits() {
    // enough decimals to name a cell centre exactly (0.05 m cells: 3 decimals)
    const res = state.current ? state.current.resolution : 0.01;
    return Math.min(6, Math.max(2, Math.ceil(-Math.log10(res)) + 1));
  }

  function fmtPoint(p) {
    const d = coordDigits();
    return `(${p.map((v) => fmt(v, d)).join(", ")})`;
  }

  function cellsOf(info) {
    return info.shape || info.size.map((s) => Math.round(s / info.resolution));
  }

  // ---------------------------------------------------------------- map list

  let shownList = "";  // the list as last drawn: redraw only on a change, not on every poll

  function renderMaps(maps) {
    const signature = JSON.stringify([maps, state.current && state.current.name]);
    if (signature === shownList) return;
    shownList = signature;
    const body = $("maps-body");
    $("maps-empty").hidden = maps.length > 0;
    const rows = maps.map((m) => {
      const tr = document.createElement("tr");
      tr.dataset.name = m.name;
      if (state.current && state.current.name === m.name) tr.setAttribute("aria-current", "true");
      const nameCell = document.createElement("th");
      nameCell.scope = "row";
      const button = document.createElement("button");
      button.type = "button";
      button.className = "linkish";
      button.textContent = m.name;
      button.setAttribute("aria-label", `Show map ${m.name}`);
      button.addEventListener("click", () => selectMap(m));
      nameCell.append(button);
      const cells = [
        `${m.size.map(fmtLength).join(" × ")} m (${m.dimensions}-D)`,
        `${cellsOf(m).join(" × ")} @ ${m.resolution} m`,
        m.model,
        String(m.scans_fused),
        String(m.version),
      ].map((text) => {
        const td = document.createElement("td");
        td.textContent = text;
        return td;
      });
      tr.append(nameCell, ...cells);
      return tr;
    });
    // keep focus on the row the operator is on when the list changes under it
    const focusedName = document.activeElement && document.activeElement.closest("#maps-body tr")
      ? document.activeElement.closest("tr").dataset.name : null;
    body.replaceChildren(...rows);
    if (focusedName) {
      const again = body.querySelector(`tr[data-name="${CSS.escape(focusedName)}"] button`);
      if (again) again.focus();
    }
  }

  // ---------------------------------------------------------------- polling

  async function poll() {
    try {
      if (!document.hidden) {
        const maps = await api("maps");
        setConn("");
        renderMaps(maps);
        // after the first answer, so that a key, if needed, has been asked for once already
        if (!plannersAsked) { plannersAsked = true; loadPlanners(); }
        if (state.current) {
          const info = maps.find((m) => m.name === state.current.name);
          if (!info) {
            mapGone();
          } else {
            state.current = info;
            if (info.version !== state.shownVersion) await loadMap();
          }
        } else if (location.hash.length > 1) {
          const wanted = maps.find((m) => m.name === decodeURIComponent(location.hash.slice(1)));
          if (wanted) selectMap(wanted);
        }
      }
    } catch (error) {
      setConn(error instanceof ApiError ? error.message : "The service does not answer; retrying every second.");
    } finally {
      setTimeout(poll, POLL_MS);
    }
  }

  function mapGone() {
    const name = state.current.name;
    state.gen += 1;
    Object.assign(state, { current: null, image: null, shownVersion: null, scan: null, path: null });
    $("view-title").textContent = "No map selected";
    $("map-summary").textContent = `Map ${name} was deleted.`;
    draw();
  }

  function selectMap(info) {
    state.gen += 1;
    Object.assign(state, {
      current: info, image: null, shownVersion: null, scan: null, path: null, start: null, goal: null,
      loading: null,
    });
    history.replaceState(null, "", `#${enc(info.name)}`);
    for (const tr of $("maps-body").children) {
      if (tr.dataset.name === info.name) tr.setAttribute("aria-current", "true");
      else tr.removeAttribute("aria-current");
    }
    const is3d = info.dimensions === 3;
    for (const el of document.querySelectorAll(".z-only")) el.hidden = !is3d;
    for (const id of ["start-x", "start-y", "goal-x", "goal-y"]) $(id).value = "";
    if (is3d) {
      const midZ = info.origin[2] + info.size[2] / 2;
      $("start-z").value = $("goal-z").value = fmt(midZ, coordDigits());
    }
    $("view-title").textContent = `Map ${info.name}`;
    setResult("idle", "Set a start and a goal, then press Plan.", 0);
    showPathList(null);
    loadMap().catch((error) => setConn(`Could not load map ${info.name}: ${error.message}`));
  }

  function loadMap() {
    if (state.loading) return state.loading;
    const gen = state.gen;
    const info = state.current;
    const base = `maps/${enc(info.name)}`;
    const job = (async () => {
      const blob = await api(`${base}/risk?format=png`, { as: "blob" });
      const image = await createImageBitmap(blob);
      let scan = null;
      try {
        scan = await api(`${base}/scans/last`);
      } catch (error) {
        if (!(error instanceof ApiError && error.status === 404)) throw error;  // 404: no scan yet
      }
      if (gen !== state.gen) {  // the operator switched maps meanwhile
        image.close();
        return;
      }
      if (state.image) state.image.close();  // free the previous version's pixels now, not at GC
      Object.assign(state, { image, scan, shownVersion: info.version });
      layout();
      draw();
      describeMap();
    })();
    state.loading = job;
    const clear = () => { if (state.loading === job) state.loading = null; };
    job.then(clear, clear);
    return job;
  }

  // ---------------------------------------------------------------- drawing

  const canvas = $("map-canvas");
  const ctx = canvas.getContext("2d");
  const PATH_COLOUR = "#ff00ff";   // magenta: on no risk colour scale, so a path always stands out
  const BEAM_COLOUR = "rgba(0, 120, 255, 0.3)";
  const HIT_COLOUR = "#0032a0";   // dark blue: reads on the white-to-crimson ramp and on unknown grey-blue

  function gridSize() {
    return state.image ? [state.image.width, state.image.height] : [0, 0];
  }

  function layout() {
    const [w, h] = gridSize();
    if (!w) return;
    const avail = Math.max(200, $("canvas-wrap").clientWidth);
    const availH = Math.max(240, window.innerHeight * 0.7);
    const fit = Math.min(avail / w, availH / h);
    // whole canvas pixels per cell when the map is small, so cells stay square and crisp
    state.zoom = fit >= 1 ? Math.min(32, Math.floor(fit)) : fit;
    const cw = Math.max(1, Math.round(w * state.zoom));
    const ch = Math.max(1, Math.round(h * state.zoom));
    if (canvas.width !== cw || canvas.height !== ch) {
      canvas.width = cw;
      canvas.height = ch;
    }
  }

  // world metres -> canvas pixels (x right, y up in the world; the PNG's top row is the highest y)
  function toCanvas(p) {
    const { origin, resolution } = state.current;
    const [, h] = gridSize();
    return [(p[0] - origin[0]) / resolution * state.zoom, (h - (p[1] - origin[1]) / resolution) * state.zoom];
  }

  // pointer position -> centre of the cell under it, in world metres (null outside the map)
  function cellCentreAt(clientX, clientY) {
    const [w, h] = gridSize();
    if (!w) return null;
    const rect = canvas.getBoundingClientRect();
    const px = Math.floor((clientX - rect.left) / rect.width * w);
    const py = Math.floor((clientY - rect.top) / rect.height * h);
    if (px < 0 || py < 0 || px >= w || py >= h) return null;
    const { origin, resolution } = state.current;
    return [origin[0] + (px + 0.5) * resolution, origin[1] + (h - py - 0.5) * resolution];
  }

  function draw() {
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    if (!state.image) {
      canvas.dataset.version = "";
      return;
    }
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(state.image, 0, 0, canvas.width, canvas.height);
    if (state.scan && $("show-scan").checked) drawScan(state.scan);
    if (state.path && state.path.length > 1) drawPath(state.path);
    if (state.start) drawMarker(state.start, "S");
    if (state.goal) drawMarker(state.goal, "G");
    canvas.dataset.version = String(state.shownVersion);
    canvas.setAttribute("aria-label", canvasLabel());
  }

  function drawScan(scan) {
    const o = toCanvas(scan.origin);
    ctx.lineWidth = 1;
    ctx.strokeStyle = BEAM_COLOUR;
    ctx.beginPath();
    for (const end of scan.endpoints) {
      const e = toCanvas(end);
      ctx.moveTo(o[0], o[1]);
      ctx.lineTo(e[0], e[1]);
    }
    ctx.stroke();
    const r = Math.max(1, Math.min(2, state.zoom / 4));
    ctx.fillStyle = HIT_COLOUR;
    ctx.beginPath();
    scan.endpoints.forEach((end, i) => {
      if (!scan.hit[i]) return;
      const e = toCanvas(end);
      ctx.rect(e[0] - r, e[1] - r, 2 * r, 2 * r);
    });
    ctx.fill();
    // the sensor: a black diamond edged in white
    ctx.beginPath();
    ctx.moveTo(o[0], o[1] - 7); ctx.lineTo(o[0] + 7, o[1]); ctx.lineTo(o[0], o[1] + 7); ctx.lineTo(o[0] - 7, o[1]);
    ctx.closePath();
    ctx.fillStyle = "#000";
    ctx.fill();
    ctx.lineWidth = 1.5;
    ctx.strokeStyle = "#fff";
    ctx.stroke();
  }

  function tracePath(points) {
    ctx.beginPath();
    points.forEach((p, i) => {
      const [cx, cy] = toCanvas(p);
      if (i === 0) ctx.moveTo(cx, cy); else ctx.lineTo(cx, cy);
    });
  }

  function drawPath(points) {
    ctx.lineJoin = "round";
    ctx.lineCap = "round";
    // a dark casing first, so the path reads on light and dark cells alike
    tracePath(points);
    ctx.strokeStyle = "#000";
    ctx.lineWidth = 6;
    ctx.stroke();
    tracePath(points);
    ctx.strokeStyle = PATH_COLOUR;
    ctx.lineWidth = 3;
    ctx.stroke();
  }

  function drawMarker(p, letter) {
    const [cx, cy] = toCanvas(p);
    const radius = Number($("robot-radius").value);
    if (Number.isFinite(radius) && radius > 0) {
      // the robot's footprint at this point
      ctx.setLineDash([4, 3]);
      ctx.lineWidth = 1.5;
      ctx.strokeStyle = "#000";
      ctx.beginPath();
      ctx.arc(cx, cy, radius / state.current.resolution * state.zoom, 0, 2 * Math.PI);
      ctx.stroke();
      ctx.setLineDash([]);
    }
    ctx.beginPath();
    ctx.arc(cx, cy, 9, 0, 2 * Math.PI);
    ctx.fillStyle = "#fff";
    ctx.fill();
    ctx.lineWidth = 2;
    ctx.strokeStyle = "#000";
    ctx.stroke();
    ctx.fillStyle = "#000";
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    ctx.fillText(letter, cx, cy + 0.5);
  }

  function canvasLabel() {
    const info = state.current;
    let text = `Risk map of ${info.name}, version ${state.shownVersion}`;
    if (info.dimensions === 3) text += " (maximum over z)";
    if (state.start) text += `; start ${fmtPoint(state.start)}`;
    if (state.goal) text += `; goal ${fmtPoint(state.goal)}`;
    if (state.path && state.path.length > 1) text += `; a path of ${state.path.length} points is drawn`;
    return text;
  }

  function describeMap() {
    const info = state.current;
    const [w, h] = gridSize();
    const dims = info.dimensions === 3 ? "3-D map, shown as its maximum risk over z" : "2-D map";
    $("map-summary").textContent =
      `${dims}, ${info.model} model: ${info.size.map(fmtLength).join(" × ")} m at ${info.resolution} m ` +
      `(${w} × ${h} cells shown), origin ${fmtPoint(info.origin)}. ` +
      `Version ${info.version}, ${info.scans_fused} scans fused.`;
    const scan = state.scan;
    if (!scan) {
      $("scan-text").textContent = "No scan yet.";
    } else {
      const hits = scan.hit.filter(Boolean).length;
      $("scan-text").textContent =
        `Last scan: ${scan.endpoints.length} beams, ${hits} returns, ${scan.endpoints.length - hits} without ` +
        `return, sensor at ${fmtPoint(scan.origin)}.`;
    }
  }

  // ---------------------------------------------------------------- legend

  // The service's risk colour ramp (app/exports.py, _RAMP_AT / _RAMP_RGB, linear in between);
  // the browser test holds the two together.
  const SCALE = [
    [0.0, [255, 255, 255]], [0.25, [254, 230, 150]], [0.5, [253, 141, 60]], [0.75, [222, 35, 32]],
    [1.0, [110, 0, 30]],
  ];

  function scaleColour(risk) {
    for (let i = 1; i < SCALE.length; i += 1) {
      const [r1, c1] = SCALE[i];
      const [r0, c0] = SCALE[i - 1];
      if (risk <= r1) {
        const t = (risk - r0) / (r1 - r0);
        return c0.map((v, k) => Math.round(v + t * (c1[k] - v)));
      }
    }
    return SCALE[SCALE.length - 1][1];
  }

  function drawLegend() {
    const bar = $("legend-bar");
    const g = bar.getContext("2d");
    for (let x = 0; x < bar.width; x += 1) {
      const [r, gg, b] = scaleColour(x / (bar.width - 1));
      g.fillStyle = `rgb(${r}, ${gg}, ${b})`;
      g.fillRect(x, 0, 1, bar.height);
    }
  }

  // ---------------------------------------------------------------- start, goal, plan

  function readPoint(which) {
    const info = state.current;
    const axes = info.dimensions === 3 ? ["x", "y", "z"] : ["x", "y"];
    const values = axes.map((a) => $(`${which}-${a}`).value.trim());
    if (values.some((v) => v === "")) return null;
    return values.map(Number);
  }

  function setPoint(which, p) {
    $(`${which}-x`).value = fmt(p[0], coordDigits());
    $(`${which}-y`).value = fmt(p[1], coordDigits());
    syncPoints();
  }

  function syncPoints() {
    if (!state.current) return;
    state.start = validPoint(readPoint("start"));
    state.goal = validPoint(readPoint("goal"));
    draw();
  }

  const validPoint = (p) => (p && p.every(Number.isFinite) ? p : null);

  function setResult(kind, text, points) {
    const box = $("plan-result");
    box.dataset.state = kind;
    box.dataset.pathPoints = String(points);
    box.textContent = text;
  }

  function showPathList(path) {
    const details = $("path-details");
    details.hidden = !path || path.length === 0;
    $("path-list").replaceChildren(...(path || []).map((p) => {
      const li = document.createElement("li");
      li.textContent = fmtPoint(p);
      return li;
    }));
  }

  const CODE_TEXT = {
    START_OUTSIDE_MAP: "The start is outside the map.",
    GOAL_OUTSIDE_MAP: "The goal is outside the map.",
    START_OCCUPIED: "The start is in an obstacle or too close to one: the risk within the robot radius is above the max risk.",
    GOAL_OCCUPIED: "The goal is in an obstacle or too close to one: the risk within the robot radius is above the max risk.",
  };

  function numberField(id, label, { min = -Infinity, max = Infinity } = {}) {
    const value = Number($(id).value);
    if ($(id).value.trim() === "" || !Number.isFinite(value) || value < min || value > max) {
      const range = max === Infinity ? `at least ${min}` : `between ${min} and ${max}`;
      throw new Error(`${label} must be a number ${range}.`);
    }
    return value;
  }

  async function plan(event) {
    event.preventDefault();
    const info = state.current;
    if (!info) {
      setResult("error", "Choose a map in the list first.", 0);
      return;
    }
    const start = validPoint(readPoint("start"));
    const goal = validPoint(readPoint("goal"));
    let body;
    try {
      if (!start) throw new Error("Set the start: click the map or type its coordinates.");
      if (!goal) throw new Error("Set the goal: click the map or type its coordinates.");
      body = {
        start,
        goal,
        state_space: info.dimensions === 3 ? "R3" : "R2",
        planner: $("planner").value,
        time_limit: numberField("time-limit", "Time limit", { min: 0.01 }),
        robot_radius: numberField("robot-radius", "Robot radius", { min: 0 }),
        max_risk: numberField("max-risk", "Max risk", { min: 0, max: 1 }),
        risk_weight: numberField("risk-weight", "Risk weight", { min: 0 }),
        allow_unknown: $("allow-unknown").checked,
      };
    } catch (error) {
      setResult("error", error.message, 0);
      return;
    }
    const gen = state.gen;
    const button = $("plan-button");
    button.disabled = true;
    setResult("busy", `Planning with ${body.planner}…`, 0);
    try {
      const result = await api(`maps/${enc(info.name)}/plan`, { method: "POST", body });
      if (gen !== state.gen) return;
      state.path = result.path;
      showPlan(result);
    } catch (error) {
      if (gen !== state.gen) return;
      state.path = null;
      showPathList(null);
      if (error instanceof ApiError && error.code) {
        const words = CODE_TEXT[error.code] || "";
        setResult("error", `Cannot plan: ${error.code}. ${words} The service says: ${error.message}`, 0);
        $("plan-result").dataset.code = error.code;
      } else if (error instanceof ApiError) {
        setResult("error", `Cannot plan (HTTP ${error.status}): ${error.message}`, 0);
      } else {
        setResult("error", "Cannot plan: the service does not answer.", 0);
      }
    } finally {
      button.disabled = false;
      draw();
    }
  }

  function showPlan(r) {
    const n = r.path ? r.path.length : 0;
    delete $("plan-result").dataset.code;
    showPathList(r.path);
    const figures = `length ${fmt(r.length)} m, max risk ${fmt(r.max_risk)}, mean risk ${fmt(r.mean_risk)}, ` +
      `cost ${fmt(r.cost)}; planned by ${r.planner} in ${fmt(r.planning_time, 3)} s; ${n} points.`;
    if (r.status === "exact") {
      setResult("path", `Path found: ${figures}`, n);
    } else if (r.status === "approximate") {
      setResult("approximate", `Approximate path only, it does not reach the goal: ${figures}`, n);
    } else {
      setResult("none", `No path found by ${r.planner} within ${fmt(r.planning_time, 3)} s. ` +
        "Try a higher max risk, a smaller robot radius, allowing unknown cells, or a longer time limit.", 0);
    }
  }

  // ---------------------------------------------------------------- wiring

  canvas.addEventListener("click", (event) => {
    if (!state.current) return;
    const p = cellCentreAt(event.clientX, event.clientY);
    if (!p) return;
    const which = document.querySelector("input[name=click]:checked").value;
    setPoint(which, p);
    // start then goal: the next click sets the other one
    $(which === "start" ? "click-goal" : "click-start").checked = true;
  });
  canvas.addEventListener("mousemove", (event) => {
    const p = state.current && cellCentreAt(event.clientX, event.clientY);
    canvas.title = p ? `cell centre x ${fmt(p[0], coordDigits())} m, y ${fmt(p[1], coordDigits())} m` : "";
  });
  for (const id of ["start-x", "start-y", "start-z", "goal-x", "goal-y", "goal-z", "robot-radius"]) {
    $(id).addEventListener("input", syncPoints);
  }
  $("plan-form").addEventListener("submit", plan);
  $("show-scan").addEventListener("change", draw);
  $("forget-key").addEventListener("click", () => {
    sessionStorage.removeItem(KEY_STORE);
    updateKeyButton();
  });
  window.addEventListener("resize", () => { layout(); draw(); });

  // the planners this build runs come from the service, so the page never offers one it refuses
  let plannersAsked = false;

  async function loadPlanners() {
    try {
      const { planners } = await api("planners");
      const select = $("planner");
      const chosen = select.value || "RRTstar";
      select.replaceChildren(...planners.map(({ name }) => {
        const option = document.createElement("option");
        option.value = name;
        option.textContent = name === "grid" ? "grid (A*)" : name;
        option.selected = name === chosen;
        return option;
      }));
    } catch (error) {
      setTimeout(loadPlanners, POLL_MS);
    }
  }

  updateKeyButton();
  drawLegend();
  poll();
})();
