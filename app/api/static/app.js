// fuzzyrisk operator page: maps, their risk, the last scan, the trajectory and its rebuild, and plans on them.
// Plain browser JavaScript, no build step; everything it loads comes from this service.
"use strict";

(() => {
  // The service root is the folder above /ui/, so the page also works behind a path prefix.
  const API_ROOT = new URL("..", document.baseURI);
  const KEY_STORE = "fuzzyrisk.apiKey";
  const POLL_MS = 1000;
  // a big map's trajectory is megabytes of JSON: read again for a new version at most this often
  const TRAJECTORY_EVERY_MS = 10000;
  // poses drawn at most (every k-th beyond): a 100,000-pose trajectory stays light to draw
  const TRAJECTORY_MAX_DRAWN = 5000;
  // a rebuild is read every poll while it runs; otherwise this often, to see a new correction come in
  const REBUILD_IDLE_MS = 5000;

  const $ = (id) => document.getElementById(id);
  const enc = encodeURIComponent;

  const state = {
    current: null,       // MapInfo of the shown map
    gen: 0,              // bumped on every map switch: answers for an older map are dropped
    loading: null,       // promise of the image load in flight, so polls do not stack loads
    image: null,         // ImageBitmap of the risk PNG, one pixel per cell
    imageOrigin: null,   // map-frame corner of the image's first cell (a growing map's moves as it grows)
    shownVersion: null,  // map version the image shows
    scan: null,          // GET /maps/{name}/scans/last, or null before the first scan
    trajectory: null,    // {points: [[x, y], ...] drawn, total, step, problem} of GET /maps/{name}/trajectory
    trajectoryVersion: null,  // map version the trajectory was last read at (null: read it at the next poll)
    trajectoryAt: 0,     // Date.now() of that read
    trajectoryLoading: false,
    rebuild: null,       // GET /maps/{name}/rebuild (RebuildStatus), or null when the service has none
    rebuildAt: 0,        // Date.now() of its last read
    start: null,         // [x, y(, z)] world metres
    goal: null,
    startHeading: null,  // radians (REP 103: 0 = +x, counter-clockwise), or null when none applies
    goalHeading: null,
    path: null,          // [[x, y(, z or theta)], ...] of the last plan
    pathHeadings: false, // the path's third value is a heading (SE2, Dubins, ReedsShepp)
    zoom: 1,             // canvas pixels per cell
  };

  // ---------------------------------------------------------------- API

  class ApiError extends Error {
    // every error answer of the service is {code, message, details}
    constructor(status, code, message, details) {
      super(describeError(status, message, details));
      this.status = status;
      this.code = code;
      this.details = details;
    }

    static async from(response) {
      let body = {};
      try {
        body = await response.json();
      } catch (_) { /* not JSON: keep the status text */ }
      return new ApiError(response.status, body.code, body.message || response.statusText, body.details);
    }
  }

  function describeError(status, message, details) {
    if (Array.isArray(details) && details.length) {
      // a request that does not match the schema: name the fields the server complained about
      return details.map((e) => {
        const where = (e.loc || []).filter((p) => p !== "body").join(".");
        return where ? `${where}: ${e.msg}` : e.msg;
      }).join("; ");
    }
    return message || `HTTP ${status}`;
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
      if (as === "image") return { blob: await response.blob(), headers: response.headers };
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

  // a map size without trailing zeros: 4 not 4.000, 0.35 not 0.4
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

  const fmtHeading = (theta) => `heading ${fmt(theta, 3)} rad`;

  // a 2-D pose [x, y, theta]: the position in metres, then the heading in words
  const fmtPose = (p) => `${fmtPoint(p.slice(0, 2))}, ${fmtHeading(p[2])}`;

  function cellsOf(info) {
    if (info.shape) return info.shape;
    return info.size ? info.size.map((s) => Math.round(s / info.resolution)) : [0, 0];
  }

  // a map's extent in words: a growing map's is its bounds, none until a scan reaches a cell
  function fmtExtent(m) {
    if (!m.size) return `growing, nothing observed yet (${m.dimensions}-D)`;
    const growing = m.extent === "growing" ? ", growing" : "";
    return `${m.size.map(fmtLength).join(" × ")} m (${m.dimensions}-D${growing})`;
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
        fmtExtent(m),
        `${m.size ? cellsOf(m).join(" × ") : "no cells yet"} @ ${m.resolution} m`,
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
            if (trajectoryDue()) loadTrajectory();  // not awaited: a big one takes seconds, the list must not wait
            if (rebuildDue()) await loadRebuild();
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

  // what selectMap and mapGone reset: the shown map's trajectory and rebuild, read again at the next poll
  const OVERLAYS_UNREAD = {
    trajectory: null, trajectoryVersion: null, trajectoryAt: 0, trajectoryLoading: false, rebuild: null, rebuildAt: 0,
  };

  function mapGone() {
    const name = state.current.name;
    state.gen += 1;
    Object.assign(state, { current: null, image: null, imageOrigin: null, shownVersion: null, scan: null, path: null });
    Object.assign(state, OVERLAYS_UNREAD);
    showTrajectoryText();
    showRebuild(null);
    $("view-title").textContent = "No map selected";
    $("map-summary").textContent = `Map ${name} was deleted.`;
    draw();
  }

  function selectMap(info) {
    state.gen += 1;
    Object.assign(state, {
      current: info, image: null, imageOrigin: null, shownVersion: null, scan: null, path: null, start: null, goal: null,
      loading: null, ...OVERLAYS_UNREAD,
    });
    showTrajectoryText();
    showRebuild(null);
    history.replaceState(null, "", `#${enc(info.name)}`);
    for (const tr of $("maps-body").children) {
      if (tr.dataset.name === info.name) tr.setAttribute("aria-current", "true");
      else tr.removeAttribute("aria-current");
    }
    const is3d = info.dimensions === 3;
    for (const el of document.querySelectorAll(".z-only")) el.hidden = !is3d;
    for (const id of ["start-x", "start-y", "goal-x", "goal-y"]) $(id).value = "";
    if (is3d) {
      const midZ = info.origin ? info.origin[2] + info.size[2] / 2 : 0;
      $("start-z").value = $("goal-z").value = fmt(midZ, coordDigits());
    }
    renderMotionModels();
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
      let answer;
      try {
        answer = await api(`${base}/risk?format=png`, { as: "image" });
      } catch (error) {
        // 409: a growing map that has observed nothing yet has no cell to show
        if (!(error instanceof ApiError && error.status === 409) || gen !== state.gen) throw error;
        if (state.image) state.image.close();
        Object.assign(state, { image: null, imageOrigin: null, scan: null, shownVersion: info.version });
        layout();
        draw();
        $("map-summary").textContent = `Growing map ${info.name}: nothing observed yet; it appears with the first scan.`;
        return;
      }
      const image = await createImageBitmap(answer.blob);
      // the image's own corner: a growing map's bounds move as it grows (the map list may be a version behind)
      const corner = (answer.headers.get("X-Map-Origin") || "").split(",").map(Number);
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
      const imageOrigin = corner.length >= 2 && corner.every(Number.isFinite) ? corner : info.origin;
      Object.assign(state, { image, imageOrigin, scan, shownVersion: info.version });
      layout();
      draw();
      describeMap();
    })();
    state.loading = job;
    const clear = () => { if (state.loading === job) state.loading = null; };
    job.then(clear, clear);
    return job;
  }

  // ---------------------------------------------------------------- trajectory and rebuild

  function trajectoryDue() {
    if (state.trajectoryLoading || state.trajectoryVersion === state.current.version) return false;
    return state.trajectoryVersion === null || Date.now() - state.trajectoryAt >= TRAJECTORY_EVERY_MS;
  }

  // every k-th pose, and the last one always: at most about TRAJECTORY_MAX_DRAWN points
  function thinTrajectory(poses) {
    const step = Math.max(1, Math.ceil(poses.length / TRAJECTORY_MAX_DRAWN));
    const at = (i) => [poses[i].pose.position.x, poses[i].pose.position.y];
    const points = [];
    for (let i = 0; i < poses.length; i += step) points.push(at(i));
    if (poses.length > 1 && (poses.length - 1) % step !== 0) points.push(at(poses.length - 1));
    return { points, total: poses.length, step, problem: null };
  }

  async function loadTrajectory() {
    const gen = state.gen;
    const info = state.current;
    Object.assign(state, { trajectoryLoading: true, trajectoryAt: Date.now(), trajectoryVersion: info.version });
    try {
      const answer = await api(`maps/${enc(info.name)}/trajectory`);
      if (gen !== state.gen) return;
      state.trajectory = thinTrajectory(answer.poses);
    } catch (error) {
      if (gen !== state.gen) return;
      if (error instanceof ApiError) {
        // e.g. 413: more poses than the service reads out (FUZZYRISK_MAX_TRAJECTORY_POSES)
        state.trajectory = { points: [], total: null, step: 1, problem: error.message };
      } else {
        state.trajectoryVersion = null;  // the service does not answer (the poll says so): read it again later
      }
    } finally {
      if (gen === state.gen) state.trajectoryLoading = false;
    }
    showTrajectoryText();
    draw();
  }

  function showTrajectoryText() {
    const t = state.trajectory;
    let text = "No trajectory yet.";
    if (t && t.problem) text = `The trajectory cannot be shown: ${t.problem}`;
    else if (t && t.total === 0) text = "No trajectory: the map holds no stored scan.";
    else if (t) {
      const thinned = t.step > 1 ? `, every ${ordinal(t.step)} drawn` : "";
      text = `Trajectory: ${t.total.toLocaleString("en")} poses${thinned}, one per stored scan.`;
    }
    $("trajectory-text").textContent = text;
  }

  const ordinal = (k) => `${k}${k % 10 === 1 && k % 100 !== 11 ? "st" : k % 10 === 2 && k % 100 !== 12 ? "nd"
    : k % 10 === 3 && k % 100 !== 13 ? "rd" : "th"}`;

  function rebuildDue() {
    const running = state.rebuild && state.rebuild.state === "running";
    return running || Date.now() - state.rebuildAt >= REBUILD_IDLE_MS;
  }

  async function loadRebuild() {
    const gen = state.gen;
    state.rebuildAt = Date.now();
    let status;
    try {
      status = await api(`maps/${enc(state.current.name)}/rebuild`);
    } catch (error) {
      // 404: a service without re-fusion (or the map just deleted: the next poll says so)
      if (!(error instanceof ApiError && error.status === 404)) throw error;
      status = null;
    }
    if (gen !== state.gen) return;
    const before = state.rebuild;
    state.rebuild = status;
    // a new correction, or its rebuild done: the poses changed, so the trajectory is read again now
    if (before && status && (before.id !== status.id || before.state !== status.state)) state.trajectoryVersion = null;
    showRebuild(status);
  }

  // seconds in words: 4.2 s, 3 min 05 s
  function fmtSeconds(s) {
    if (typeof s !== "number" || !Number.isFinite(s)) return "?";
    if (s < 60) return `${s.toFixed(1)} s`;
    const whole = Math.round(s);
    return `${Math.floor(whole / 60)} min ${String(whole % 60).padStart(2, "0")} s`;
  }

  const fmtClock = (iso) => (iso ? new Date(iso).toLocaleTimeString("en-GB") : "?");

  function showRebuild(r) {
    const box = $("rebuild");
    box.hidden = !r;
    if (!r) return;
    box.dataset.state = r.state;
    const bar = $("rebuild-bar");
    const count = (n) => Number(n).toLocaleString("en");
    const reposed = `${count(r.scans_reposed)} scans re-posed`;
    const refused = `${count(r.scans_done)} of ${count(r.scans_total)} scans re-fused`;
    let said = "";
    let figures = "";
    if (r.state === "none") {
      said = "No corrected trajectory yet.";
      figures = `A SLAM node's PUT /maps/${state.current.name}/trajectory re-poses the stored scans and rebuilds `
        + "the map here, in the background.";
    } else if (r.state === "running") {
      said = `Rebuilding on the corrected trajectory of ${fmtClock(r.requested)}…`;
      const left = r.eta_s === null || r.eta_s === undefined ? "time left unknown" : `${fmtSeconds(r.eta_s)} left`;
      figures = `${refused}, ${fmtSeconds(r.elapsed_s)} elapsed, ${left}; ${reposed} (of version `
        + `${r.from_version}). The map shown is the current one until the rebuild replaces it.`;
    } else if (r.state === "done") {
      said = `Rebuilt on the corrected trajectory of ${fmtClock(r.requested)}: map version ${r.version}.`;
      figures = `${reposed}; ${count(r.scans_total)} scans re-fused in ${fmtSeconds(r.elapsed_s)}.`;
    } else {
      said = `The rebuild on the corrected trajectory of ${fmtClock(r.requested)} failed; the map is as it was.`;
      figures = `${refused}, ${fmtSeconds(r.elapsed_s)} elapsed; ${reposed}.`;
    }
    if ($("rebuild-state").textContent !== said) $("rebuild-state").textContent = said;
    $("rebuild-figures").textContent = figures;
    bar.hidden = r.state !== "running";
    bar.max = Math.max(1, r.scans_total);
    bar.value = r.scans_done;
    bar.setAttribute("aria-valuetext", refused);
    $("rebuild-error").hidden = r.state !== "failed";
    $("rebuild-error").textContent = r.state === "failed" ? `Why: ${r.error}` : "";
  }

  // ---------------------------------------------------------------- drawing

  const canvas = $("map-canvas");
  const ctx = canvas.getContext("2d");
  const PATH_COLOUR = "#ff00ff";   // magenta: on no risk colour scale, so a path always stands out
  const BEAM_COLOUR = "rgba(0, 120, 255, 0.3)";
  const HIT_COLOUR = "#0032a0";   // dark blue: reads on the white-to-crimson ramp and on unknown grey-blue
  const TRAJECTORY_COLOUR = "#00a050";  // green: on no risk colour scale, apart from the path's magenta

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
    const { resolution } = state.current;
    const origin = state.imageOrigin || state.current.origin;
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
    if (state.trajectory && state.trajectory.points.length && $("show-trajectory").checked) {
      drawTrajectory(state.trajectory.points);
    }
    if (state.scan && $("show-scan").checked) drawScan(state.scan);
    if (state.path && state.path.length > 1) drawPath(state.path);
    if (state.start) drawMarker(state.start, "S", state.startHeading);
    if (state.goal) drawMarker(state.goal, "G", state.goalHeading);
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

  // the sensor's way through the map: a thin green line on a white casing, the newest pose a dot
  function drawTrajectory(points) {
    strokeCased(points, "#fff", 4, TRAJECTORY_COLOUR, 2);
    const [cx, cy] = toCanvas(points[points.length - 1]);
    ctx.beginPath();
    ctx.arc(cx, cy, 4, 0, 2 * Math.PI);
    ctx.fillStyle = TRAJECTORY_COLOUR;
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

  // a line on a wider casing, so that it reads on light and dark cells alike
  function strokeCased(points, casing, casingWidth, colour, width) {
    ctx.lineJoin = "round";
    ctx.lineCap = "round";
    tracePath(points);
    ctx.strokeStyle = casing;
    ctx.lineWidth = casingWidth;
    ctx.stroke();
    tracePath(points);
    ctx.strokeStyle = colour;
    ctx.lineWidth = width;
    ctx.stroke();
  }

  function drawPath(points) {
    strokeCased(points, "#000", 6, PATH_COLOUR, 3);
  }

  // the heading as an arrow from the marker's centre: black, edged in white so that it reads
  // on free (white), risky (crimson) and unknown (grey-blue) cells alike
  function drawHeading(cx, cy, theta) {
    const length = 30;  // canvas pixels, centre to tip
    const head = 9;
    const dx = Math.cos(theta);
    const dy = -Math.sin(theta);  // world y up, canvas y down (see toCanvas)
    const tip = [cx + dx * length, cy + dy * length];
    const base = [tip[0] - dx * head, tip[1] - dy * head];
    const side = [-dy * head * 0.6, dx * head * 0.6];
    const shaft = () => {
      ctx.beginPath();
      ctx.moveTo(cx, cy);
      ctx.lineTo(base[0], base[1]);
    };
    const arrowHead = () => {
      ctx.beginPath();
      ctx.moveTo(tip[0], tip[1]);
      ctx.lineTo(base[0] + side[0], base[1] + side[1]);
      ctx.lineTo(base[0] - side[0], base[1] - side[1]);
      ctx.closePath();
    };
    ctx.lineCap = "butt";
    ctx.lineJoin = "miter";
    ctx.strokeStyle = "#fff";
    ctx.lineWidth = 6;
    shaft();
    ctx.stroke();
    ctx.lineWidth = 3;
    arrowHead();
    ctx.stroke();
    ctx.strokeStyle = "#000";
    ctx.fillStyle = "#000";
    ctx.lineWidth = 3;
    shaft();
    ctx.stroke();
    arrowHead();
    ctx.fill();
  }

  function drawMarker(p, letter, heading = null) {
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
    // under the letter's disc, so that the arrow starts at its edge
    if (heading !== null) drawHeading(cx, cy, heading);
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
    const heading = (theta) => (theta === null ? "" : `, ${fmtHeading(theta)}`);
    if (state.start) text += `; start ${fmtPoint(state.start)}${heading(state.startHeading)}`;
    if (state.goal) text += `; goal ${fmtPoint(state.goal)}${heading(state.goalHeading)}`;
    if (state.path && state.path.length > 1) text += `; a path of ${state.path.length} points is drawn`;
    if (state.trajectory && state.trajectory.total && $("show-trajectory").checked) {
      text += `; the trajectory of ${state.trajectory.total} poses is drawn`;
    }
    return text;
  }

  function describeMap() {
    const info = state.current;
    const [w, h] = gridSize();
    const dims = info.dimensions === 3 ? "3-D map, shown as its maximum risk over z" : "2-D map";
    $("map-summary").textContent =
      `${dims}, ${info.model} model: ${fmtExtent(info)} at ${info.resolution} m ` +
      `(${w} × ${h} cells shown), origin ${fmtPoint(state.imageOrigin || info.origin)}. ` +
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
    [0.0, [255, 255, 255]], [0.4, [254, 230, 150]], [0.6, [253, 141, 60]], [0.8, [222, 35, 32]],
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

  // the heading typed for the start or goal, or null when the motion model has none or it is not a number
  function readHeading(which) {
    if (!motion().heading) return null;
    const text = $(`${which}-theta`).value.trim();
    const theta = Number(text);
    return text !== "" && Number.isFinite(theta) ? theta : null;
  }

  function syncPoints() {
    if (!state.current) return;
    state.start = validPoint(readPoint("start"));
    state.goal = validPoint(readPoint("goal"));
    state.startHeading = readHeading("start");
    state.goalHeading = readHeading("goal");
    draw();
  }

  const validPoint = (p) => (p && p.every(Number.isFinite) ? p : null);

  // ---------------------------------------------------------------- motion models

  // The state spaces this page can ask for: the map dimensions each fits, whether start and goal
  // carry a heading, and whether the motion is a car's with a turning radius. GET /planners says
  // which ones the service runs; the page offers those that fit the shown map.
  const MOTION = {
    R2: { dims: 2, label: "R2 (x, y)", heading: false, curved: false,
      hint: "Position only: the robot can move in any direction." },
    SE2: { dims: 2, label: "SE2 (x, y, heading)", heading: true, curved: false,
      hint: "Position and heading: the robot can turn on the spot and move in any direction." },
    Dubins: { dims: 2, label: "Dubins car (forward only)", heading: true, curved: true,
      hint: "A car that drives forward only and turns no tighter than its turning radius." },
    ReedsShepp: { dims: 2, label: "Reeds-Shepp car (forward, reverse)", heading: true, curved: true,
      hint: "A car that drives forward and in reverse and turns no tighter than its turning radius." },
    R3: { dims: 3, label: "R3 (x, y, z)", heading: false, curved: false,
      hint: "Position in 3-D: the robot can move in any direction." },
  };
  let servedSpaces = null;  // GET /planners' state_spaces, null until it answers

  const motion = () => MOTION[$("motion-model").value] || MOTION.R2;

  function renderMotionModels() {
    const dims = state.current ? state.current.dimensions : 2;
    const fallback = dims === 3 ? "R3" : "R2";
    let names = Object.keys(MOTION).filter((name) => MOTION[name].dims === dims
      && (!servedSpaces || servedSpaces.includes(name)));
    if (names.length === 0) names = [fallback];
    const select = $("motion-model");
    // keep the operator's choice from map to map when the new map offers it too
    const previous = select.value;
    const chosen = names.includes(previous) ? previous : (names.includes(fallback) ? fallback : names[0]);
    if ([...select.options].map((o) => o.value).join() !== names.join()) {
      select.replaceChildren(...names.map((name) => {
        const option = document.createElement("option");
        option.value = name;
        option.textContent = MOTION[name].label;
        return option;
      }));
    }
    select.value = chosen;
    applyMotionModel(chosen !== previous);
  }

  function applyMotionModel(changed = true) {
    const m = motion();
    for (const el of document.querySelectorAll(".heading-only")) el.hidden = !m.heading;
    for (const el of document.querySelectorAll(".curved-only")) el.hidden = !m.curved;
    $("motion-hint").textContent = m.hint;
    if (changed) $("planner-note").hidden = true;
    fitPlannerToMotion();
    syncPoints();
  }

  // the grid planner (A*) searches positions only: it is offered in R2 and R3, not with a heading
  function fitPlannerToMotion() {
    const select = $("planner");
    const grid = select.querySelector('option[value="grid"]');
    if (!grid) return;
    const positionsOnly = !motion().heading;
    grid.disabled = !positionsOnly;
    grid.textContent = positionsOnly ? "grid (A*)" : "grid (A*, R2 and R3 only)";
    if (!positionsOnly && select.value === "grid") {
      const other = [...select.options].find((o) => o.value === "RRTstar" && !o.disabled)
        || [...select.options].find((o) => !o.disabled);
      if (!other) return;
      select.value = other.value;
      const note = $("planner-note");
      note.textContent = `The grid planner plans positions only, so the planner is now ${other.value}.`;
      note.hidden = false;
    }
  }

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
      li.textContent = state.pathHeadings ? fmtPose(p) : fmtPoint(p);
      return li;
    }));
  }

  const CODE_TEXT = {
    START_OUTSIDE_MAP: "The start is outside the map.",
    GOAL_OUTSIDE_MAP: "The goal is outside the map.",
    START_OCCUPIED: "The start is in an obstacle or too close to one: the risk within the robot radius is above the max risk.",
    GOAL_OCCUPIED: "The goal is in an obstacle or too close to one: the risk within the robot radius is above the max risk.",
  };

  // an Error naming the form field it is about, so that the field can be marked and focused
  function fieldError(id, message) {
    const error = new Error(message);
    error.field = id;
    return error;
  }

  // min and max are inclusive, above is an exclusive lower bound; unit goes into the message
  function numberField(id, label, { min = -Infinity, max = Infinity, above = -Infinity, unit = "" } = {}) {
    const input = $(id);
    const value = Number(input.value);
    if (input.value.trim() === "" || input.validity.badInput || !Number.isFinite(value) || value < min
        || value > max || value <= above) {
      let range = "";
      if (above > -Infinity) range = ` greater than ${above}`;
      else if (min > -Infinity) range = max === Infinity ? ` at least ${min}` : ` between ${min} and ${max}`;
      throw fieldError(id, `${label} must be a number${range}${unit ? ` (${unit})` : ""}.`);
    }
    return value;
  }

  const SEED_MAX = 2 ** 32 - 1;

  // the optional seed: null when empty (a random plan), else a whole number 0 .. 2^32 - 1
  function readSeed() {
    const text = $("seed").value.trim();
    if (text === "") return null;
    if (!/^[0-9]+$/.test(text) || Number(text) > SEED_MAX) {
      throw fieldError("seed", `Seed must be a whole number from 0 to ${SEED_MAX}, or empty for a random plan.`);
    }
    return Number(text);
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
    const space = $("motion-model").value;
    const m = motion();
    let body;
    try {
      if (!start) throw new Error("Set the start: click the map or type its coordinates.");
      if (!goal) throw new Error("Set the goal: click the map or type its coordinates.");
      const heading = (which, label) => numberField(`${which}-theta`, label, { unit: "radians" });
      body = {
        start: m.heading ? [...start, heading("start", "Start heading")] : start,
        goal: m.heading ? [...goal, heading("goal", "Goal heading")] : goal,
        state_space: m.dims === info.dimensions ? space : (info.dimensions === 3 ? "R3" : "R2"),
        planner: $("planner").value,
        time_limit: numberField("time-limit", "Time limit", { min: 0.01 }),
        robot_radius: numberField("robot-radius", "Robot radius", { min: 0 }),
        max_risk: numberField("max-risk", "Max risk", { min: 0, max: 1 }),
        risk_weight: numberField("risk-weight", "Risk weight", { min: 0 }),
        allow_unknown: $("allow-unknown").checked,
      };
      if (m.curved) body.turning_radius = numberField("turning-radius", "Turning radius", { above: 0, unit: "metres" });
      const seed = readSeed();
      if (seed !== null) body.seed = seed;
      if (m.heading && body.planner === "grid") {
        throw fieldError("planner", `The grid planner plans positions only: choose another planner for ${m.label}.`);
      }
    } catch (error) {
      setResult("error", error.message, 0);
      if (error.field) {
        $(error.field).setAttribute("aria-invalid", "true");
        $(error.field).focus();
      }
      return;
    }
    const gen = state.gen;
    const button = $("plan-button");
    button.disabled = true;
    setResult("busy", `Planning with ${body.planner}${m.heading ? ` for ${m.label}` : ""}…`, 0);
    try {
      const result = await api(`maps/${enc(info.name)}/plan`, { method: "POST", body });
      if (gen !== state.gen) return;
      state.path = result.path;
      state.pathHeadings = info.dimensions === 2 && result.state_space !== "R2";
      showPlan(result);
    } catch (error) {
      if (gen !== state.gen) return;
      state.path = null;
      showPathList(null);
      if (error instanceof ApiError && error.code in CODE_TEXT) {
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
    const space = ["R2", "R3"].includes(r.state_space) ? "" : ` in ${r.state_space}`;
    const note = r.message ? ` Note: ${r.message}.` : "";
    const figures = `length ${fmt(r.length)} m, max risk ${fmt(r.max_risk)}, mean risk ${fmt(r.mean_risk)}, ` +
      `cost ${fmt(r.cost)}; planned by ${r.planner}${space} in ${fmt(r.planning_time, 3)} s; ${n} points.${note}`;
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
  for (const id of ["start-x", "start-y", "start-z", "start-theta", "goal-x", "goal-y", "goal-z", "goal-theta",
    "robot-radius"]) {
    $(id).addEventListener("input", syncPoints);
  }
  $("motion-model").addEventListener("change", () => applyMotionModel());
  // a field marked invalid by the last Plan is unmarked as soon as it is edited
  $("plan-form").addEventListener("input", (event) => event.target.removeAttribute("aria-invalid"));
  $("plan-form").addEventListener("change", (event) => event.target.removeAttribute("aria-invalid"));
  $("plan-form").addEventListener("submit", plan);
  $("show-scan").addEventListener("change", draw);
  $("show-trajectory").addEventListener("change", draw);
  $("forget-key").addEventListener("click", () => {
    sessionStorage.removeItem(KEY_STORE);
    updateKeyButton();
  });
  window.addEventListener("resize", () => { layout(); draw(); });

  // the planners this build runs come from the service, so the page never offers one it refuses
  let plannersAsked = false;

  async function loadPlanners() {
    try {
      const { planners, state_spaces: spaces } = await api("planners");
      const select = $("planner");
      const chosen = select.value || "RRTstar";
      select.replaceChildren(...planners.map(({ name }) => {
        const option = document.createElement("option");
        option.value = name;
        option.textContent = name === "grid" ? "grid (A*)" : name;
        option.selected = name === chosen;
        return option;
      }));
      servedSpaces = spaces;
      renderMotionModels();
    } catch (error) {
      setTimeout(loadPlanners, POLL_MS);
    }
  }

  updateKeyButton();
  drawLegend();
  poll();
})();
