// sogm-service viewer: plain JavaScript and two canvases, no library, no network but this server.
// Map frame: x right, y up, metres.  The server sends display tiles as PNGs (already coloured:
// free white, occupied black, unknown muted blue; classes in the legend's colours), robot poses,
// tile events, ISM footprints and stats over one WebSocket; this page only places them.
"use strict";

(function () {
  const $ = (id) => document.getElementById(id);
  const mapCanvas = $("map");
  const overlay = $("overlay");
  const mapCtx = mapCanvas.getContext("2d", { willReadFrequently: true });
  const ovCtx = overlay.getContext("2d");
  const BACKGROUND = "#262a30";
  const FOOTPRINT_S = 1.5;
  const EVENT_FLASH_S = 3.0;
  const MAX_TILES = 600;
  const HISTORY = 120;

  const state = {
    socket: "connecting",        // connecting | open | closed
    connected: false,            // the viewer reaches the map server
    error: null,
    info: null,
    signature: null,             // picture the server's tiles currently belong to
    robots: {},                  // name -> pose message
    markers: {},                 // name -> {x, y, yaw, sx, sy} as last drawn (css px)
    events: [],                  // tile events, newest last
    footprints: new Map(),       // ISM key -> {corners, robot, t}: the latest of each key
    supercells: null,
    stats: [],
    probe: null,
    tilesReceived: 0,
    tilesDropped: 0,
    footprintsReceived: 0,
    refreshes: 0,
    lastRefresh: null,
    rounds: [],
    errors: [],
    userMoved: false,
  };
  const view = { cx: 0, cy: 0, z: 20, W: 1, H: 1, dpr: 1 };
  const tiles = new Map();       // key -> {bmp, x0, y0, span, level, signature, used}
  const decoding = new Map();    // key -> token of the newest tile being decoded
  let ws = null;
  let retries = 0;
  let seq = 0;
  let drawScheduled = false;
  let viewTimer = null;
  let scTimer = null;
  let probeInFlight = false;
  let probeWanted = null;
  let probeSent = null;
  let decodeToken = 0;

  // -- geometry -----------------------------------------------------------------------------
  function worldToScreen(x, y) {
    return [(x - view.cx) * view.z + view.W / 2, view.H / 2 - (y - view.cy) * view.z];
  }
  function screenToWorld(sx, sy) {
    return [(sx - view.W / 2) / view.z + view.cx, (view.H / 2 - sy) / view.z + view.cy];
  }
  function viewBox() {
    const [xmin, ymax] = screenToWorld(0, 0);
    const [xmax, ymin] = screenToWorld(view.W, view.H);
    return { xmin, ymin, xmax, ymax };
  }
  function palette() { return state.info ? state.info.palette : []; }

  // -- the socket ---------------------------------------------------------------------------
  function connect() {
    const url = new URL("ws", window.location.href);
    url.protocol = url.protocol === "https:" ? "wss:" : "ws:";
    state.socket = "connecting";
    ws = new WebSocket(url.href);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => {
      retries = 0;
      probeInFlight = false;          // a probe lost with the old socket is not waited for
      state.socket = "open";
      updateStatus();
      sendView(true);
    };
    ws.onclose = () => {
      state.socket = "closed";
      updateStatus();
      const delay = Math.min(5000, 250 * Math.pow(2, retries++));
      window.setTimeout(connect, delay);
    };
    ws.onmessage = (ev) => {
      if (typeof ev.data === "string") onMessage(JSON.parse(ev.data));
      else onTile(ev.data);
    };
  }
  function send(obj) {
    if (ws && ws.readyState === WebSocket.OPEN) { ws.send(JSON.stringify(obj)); return true; }
    return false;
  }

  function onMessage(m) {
    switch (m.type) {
      case "hello":
        onStatus(m.status);
        if (m.info) onInfo(m.info);
        m.robots.forEach(onPose);
        renderRobots();
        state.events = [];
        $("events").textContent = "";
        m.events.forEach((e) => onEvent(e, false));
        state.stats = m.stats.slice(-HISTORY);
        drawCharts();
        break;
      case "status": onStatus(m); break;
      case "info": onInfo(m); break;
      case "view_ack": state.signature = m.signature; scheduleDraw(); break;
      case "poses": m.poses.forEach(onPose); renderRobots(); scheduleDraw(); break;
      case "tile_events": m.events.forEach((e) => onEvent(e, true)); scheduleDraw(); break;
      case "footprints": onFootprints(m.footprints); break;
      case "stats":
        state.stats.push(m);
        if (state.stats.length > HISTORY) state.stats.shift();
        drawCharts();
        break;
      case "drop":
        m.keys.forEach((k) => {
          const t = tiles.get(k);
          if (t) { t.bmp.close(); tiles.delete(k); state.tilesDropped++; }
          decoding.delete(k);
        });
        scheduleDraw();
        break;
      case "refreshed":
        state.refreshes = m.n;
        state.lastRefresh = m;
        state.rounds.push(m);    // the last rounds, for scripts and tests
        if (state.rounds.length > 50) state.rounds.shift();
        break;
      case "probe": onProbe(m); break;
      case "supercells": state.supercells = m; scheduleDraw(); break;
      case "error": state.errors.push(m); console.warn("viewer:", m.code, m.message); break;
      default: break;
    }
  }

  function onTile(buf) {
    const n = new DataView(buf).getUint32(0, false);
    const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    const token = ++decodeToken;
    decoding.set(head.key, token);
    createImageBitmap(new Blob([new Uint8Array(buf, 4 + n)], { type: "image/png" }))
      .then((bmp) => {
        if (decoding.get(head.key) !== token) { bmp.close(); return; }  // dropped meanwhile
        decoding.delete(head.key);
        const old = tiles.get(head.key);
        if (old) old.bmp.close();
        tiles.set(head.key, { bmp, x0: head.x0, y0: head.y0, span: head.span,
                              level: head.level, signature: head.signature, used: Date.now() });
        state.tilesReceived++;
        trimTiles();
        scheduleDraw();
      })
      .catch((err) => console.warn("viewer: undecodable tile", head.key, err));
  }
  function trimTiles() {
    if (tiles.size <= MAX_TILES) return;
    const old = [...tiles.entries()].sort((a, b) => a[1].used - b[1].used);
    for (const [k, t] of old.slice(0, tiles.size - MAX_TILES)) { t.bmp.close(); tiles.delete(k); }
  }

  function onStatus(s) {
    state.connected = s.connected;
    state.error = s.error;
    $("mapname").textContent = `map “${s.map}” at ${s.endpoint}`;
    updateStatus();
  }
  function updateStatus() {
    const el = $("status");
    const banner = $("banner");
    if (state.socket !== "open") {
      el.dataset.state = "viewer-down";
      el.textContent = "viewer unreachable";
      banner.hidden = false;
      banner.textContent = "lost the viewer process; reconnecting…";
    } else if (!state.connected) {
      el.dataset.state = "map-down";
      el.textContent = "map server unreachable";
      banner.hidden = false;
      banner.textContent = "map server unreachable, showing the last picture; retrying…";
    } else {
      el.dataset.state = "connected";
      el.textContent = "live";
      banner.hidden = true;
    }
  }

  function onInfo(info) {
    const first = state.info === null;
    state.info = info;
    fillLayerControls(info.layers);
    renderLegend();
    if ((first || !state.userMoved) && info.bounds) fit(false);
    sendView(true);
    scheduleDraw();
  }

  function onPose(p) {
    state.robots[p.robot] = p;
  }
  function renderRobots() {
    const ul = $("robots");
    const names = Object.keys(state.robots).sort();
    ul.textContent = "";
    for (const name of names.slice(0, 50)) {
      const p = state.robots[name];
      const li = document.createElement("li");
      li.dataset.robot = name;
      li.textContent = `${name}: ${p.x.toFixed(2)}, ${p.y.toFixed(2)} m, ` +
        `${(p.yaw * 180 / Math.PI).toFixed(0)}°`;
      ul.appendChild(li);
    }
  }

  function onEvent(e, fresh) {
    e.seen = performance.now() / 1000;
    state.events.push(e);
    if (state.events.length > 200) state.events.shift();
    const ol = $("events");
    const li = document.createElement("li");
    li.dataset.robot = e.robot;
    li.dataset.i = e.i;
    li.dataset.j = e.j;
    const t = new Date((e.received || Date.now() / 1000) * 1000).toLocaleTimeString();
    li.textContent = `${t} ${e.robot} → tile (${e.i}, ${e.j})`;
    if (fresh) {
      li.className = "fresh";
      window.setTimeout(() => li.classList.remove("fresh"), 3000);
    }
    ol.insertBefore(li, ol.firstChild);
    while (ol.children.length > 50) ol.removeChild(ol.lastChild);
  }

  function onFootprints(list) {
    state.footprintsReceived += list.length;
    if (!$("show-footprints").checked) return;
    const now = performance.now() / 1000;
    for (const f of list) {
      state.footprints.delete(f.key);   // keep insertion order = age
      state.footprints.set(f.key, { corners: f.corners, robot: f.robot, t: now });
    }
    while (state.footprints.size > 200) {
      state.footprints.delete(state.footprints.keys().next().value);
    }
    scheduleDraw();
  }

  // -- controls -------------------------------------------------------------------------------
  function currentLayers() {
    return [...$("fused-layers").querySelectorAll("input")].filter((c) => c.checked)
      .map((c) => c.value);
  }
  function fillLayerControls(layers) {
    const sel = $("layer");
    const chosen = sel.value;
    const known = [...sel.options].map((o) => o.value).join("\n");
    if (known !== layers.join("\n")) {
      sel.textContent = "";
      for (const n of layers) {
        const o = document.createElement("option");
        o.value = n; o.textContent = n; sel.appendChild(o);
      }
      if (layers.includes(chosen)) sel.value = chosen;
      const box = $("fused-layers");
      const checked = new Set(currentLayers());
      const had = box.children.length > 0;
      box.textContent = "";
      for (const n of layers) {
        const label = document.createElement("label");
        const c = document.createElement("input");
        c.type = "checkbox"; c.value = n;
        const free = /(^|\/)(floor|free)$/.test(n);
        c.checked = had ? checked.has(n) || !known.split("\n").includes(n) : !free;
        c.addEventListener("change", () => sendView(true));
        label.appendChild(c);
        label.appendChild(document.createTextNode(" " + n));
        box.appendChild(label);
      }
    }
  }
  function renderLegend() {
    const el = $("legend");
    el.textContent = "";
    const row = (swatch, text) => {
      const d = document.createElement("div");
      d.appendChild(swatch);
      d.appendChild(document.createTextNode(text));
      el.appendChild(d);
    };
    const sw = (color) => {
      const s = document.createElement("span");
      s.className = "swatch"; s.style.background = color; return s;
    };
    const unknown = state.info ? state.info.unknown : "#466e96";
    if ($("mode").value === "class") {
      palette().forEach((c, k) => row(sw(c), state.info.layers[k]));
      row(sw(unknown), "unknown (no layer above 0.5)");
    } else if ($("mode").value === "keepout" || $("mode").value === "speed") {
      const keep = $("mode").value === "keepout";
      row(sw(keep ? "#e62828" : "#ffaa00"),
          keep ? "kept out (view --keepout)" : "speed limited, stronger when slower (view --speed)");
      row(sw("#808080"), "the map, pooled by max (P_M)");
      row(sw(unknown), "unknown (no evidence)");
    } else {
      const g = document.createElement("span");
      g.className = "gradient";
      row(g, " free 0 … 1 occupied");
      row(sw(unknown), "unknown (no evidence)");
    }
  }
  function onModeChange() {
    const mode = $("mode").value;
    $("layer-box").hidden = mode !== "layer";
    $("fused-box").hidden = mode !== "fused";
    renderLegend();
    sendView(true);
  }

  function sendView(now) {
    if (viewTimer !== null) window.clearTimeout(viewTimer);
    viewTimer = window.setTimeout(() => {
      viewTimer = null;
      const b = viewBox();
      const mode = $("mode").value;
      const msg = { type: "view", seq: ++seq, xmin: b.xmin, ymin: b.ymin, xmax: b.xmax,
                    ymax: b.ymax, px_per_m: view.z * view.dpr, mode, method: $("method").value,
                    layer: mode === "layer" ? $("layer").value : null,
                    layers: mode === "fused" ? currentLayers() : [] };
      if (mode === "layer" && !msg.layer) msg.mode = "class";
      send(msg);
      if ($("show-supercells").checked) askSupercells(false);
    }, now ? 0 : 60);
  }
  function askSupercells(now) {
    if (scTimer !== null) window.clearTimeout(scTimer);
    scTimer = window.setTimeout(() => {
      scTimer = null;
      if (!$("show-supercells").checked) return;
      const b = viewBox();
      send({ type: "supercells", xmin: b.xmin, ymin: b.ymin, xmax: b.xmax, ymax: b.ymax });
    }, now ? 0 : 400);
  }

  function fit(byUser) {
    if (!state.info || !state.info.bounds) return;
    const [x0, y0, x1, y1] = state.info.bounds;
    view.cx = (x0 + x1) / 2;
    view.cy = (y0 + y1) / 2;
    view.z = Math.max(1e-4, 0.95 * Math.min(view.W / (x1 - x0), view.H / (y1 - y0)));
    if (byUser) state.userMoved = false;
    sendView(true);
    scheduleDraw();
  }
  function setView(cx, cy, z) {
    view.cx = cx; view.cy = cy; view.z = z;
    state.userMoved = true;
    sendView(true);
    scheduleDraw();
  }

  // -- probing the cell under the cursor ----------------------------------------------------
  function probe(x, y) {
    probeWanted = [x, y];
    if (probeInFlight) return;
    if (send({ type: "probe", x, y })) { probeInFlight = true; probeSent = [x, y]; }
  }
  function onProbe(m) {
    probeInFlight = false;
    state.probe = m;
    const table = $("cursor-p");
    table.textContent = "";
    for (const v of m.values) {
      const tr = document.createElement("tr");
      const a = document.createElement("td");
      const b = document.createElement("td");
      a.textContent = v.layer;
      b.textContent = v.known ? v.p.toFixed(3) : "unknown";
      tr.appendChild(a); tr.appendChild(b); table.appendChild(tr);
    }
    if (probeWanted && (probeWanted[0] !== probeSent[0] || probeWanted[1] !== probeSent[1])) {
      probe(probeWanted[0], probeWanted[1]);
    }
  }
  function showCursor(x, y) {
    let text = `x ${x.toFixed(2)} m, y ${y.toFixed(2)} m (${state.info ? state.info.frame : "map"})`;
    const geo = state.info && state.info.geo;
    if (geo) {
      const lat = geo.latitude + y * geo.deg_lat_per_m;
      const lon = geo.longitude + x * geo.deg_lon_per_m;
      text += `, ${lat.toFixed(7)}°, ${lon.toFixed(7)}°`;
    }
    $("cursor-xy").textContent = text;
  }

  // -- input ----------------------------------------------------------------------------------
  let drag = null;
  overlay.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, cx: view.cx, cy: view.cy };
    overlay.setPointerCapture(e.pointerId);
    overlay.classList.add("dragging");
  });
  overlay.addEventListener("pointerup", (e) => {
    drag = null;
    overlay.releasePointerCapture(e.pointerId);
    overlay.classList.remove("dragging");
  });
  overlay.addEventListener("pointermove", (e) => {
    const r = overlay.getBoundingClientRect();
    const [x, y] = screenToWorld(e.clientX - r.left, e.clientY - r.top);
    if (drag) {
      view.cx = drag.cx - (e.clientX - drag.x) / view.z;
      view.cy = drag.cy + (e.clientY - drag.y) / view.z;
      state.userMoved = true;
      sendView(false);
      scheduleDraw();
    }
    showCursor(x, y);
    probe(x, y);
  });
  overlay.addEventListener("wheel", (e) => {
    e.preventDefault();
    const r = overlay.getBoundingClientRect();
    const sx = e.clientX - r.left;
    const sy = e.clientY - r.top;
    const [x, y] = screenToWorld(sx, sy);
    view.z = Math.min(2000, Math.max(1e-4, view.z * Math.exp(-e.deltaY * 0.0015)));
    view.cx = x - (sx - view.W / 2) / view.z;   // keep the point under the cursor still
    view.cy = y + (sy - view.H / 2) / view.z;
    state.userMoved = true;
    sendView(false);
    scheduleDraw();
  }, { passive: false });
  $("mode").addEventListener("change", onModeChange);
  $("layer").addEventListener("change", () => sendView(true));
  $("method").addEventListener("change", () => sendView(true));
  $("fit").addEventListener("click", () => fit(true));
  $("show-lattice").addEventListener("change", scheduleDraw);
  $("show-footprints").addEventListener("change", () => { state.footprints.clear(); scheduleDraw(); });
  $("show-supercells").addEventListener("change", () => {
    state.supercells = null;
    askSupercells(true);
    scheduleDraw();
  });
  window.setInterval(() => askSupercells(true), 5000);

  function resize() {
    const r = mapCanvas.parentElement.getBoundingClientRect();
    view.W = Math.max(1, r.width);
    view.H = Math.max(1, r.height);
    view.dpr = window.devicePixelRatio || 1;
    for (const c of [mapCanvas, overlay]) {
      c.width = Math.round(view.W * view.dpr);
      c.height = Math.round(view.H * view.dpr);
    }
    sendView(false);
    scheduleDraw();
  }
  window.addEventListener("resize", resize);

  // -- drawing --------------------------------------------------------------------------------
  function scheduleDraw() {
    if (drawScheduled) return;
    drawScheduled = true;
    window.requestAnimationFrame(draw);
  }
  function draw() {
    drawScheduled = false;
    drawMap();
    const animating = drawOverlay();
    drawScale();
    if (animating) scheduleDraw();
  }
  function drawMap() {
    const ctx = mapCtx;
    ctx.setTransform(view.dpr, 0, 0, view.dpr, 0, 0);
    ctx.imageSmoothingEnabled = false;
    ctx.fillStyle = BACKGROUND;
    ctx.fillRect(0, 0, view.W, view.H);
    const b = viewBox();
    const list = [...tiles.values()].filter((t) => t.signature === state.signature &&
      t.x0 < b.xmax && t.x0 + t.span > b.xmin && t.y0 < b.ymax && t.y0 + t.span > b.ymin);
    list.sort((p, q) => q.level - p.level);   // coarse first, finer on top
    const now = Date.now();
    for (const t of list) {
      const [sx, sy] = worldToScreen(t.x0, t.y0 + t.span);
      ctx.drawImage(t.bmp, sx, sy, t.span * view.z, t.span * view.z);
      t.used = now;
    }
  }
  function drawOverlay() {
    const ctx = ovCtx;
    ctx.setTransform(view.dpr, 0, 0, view.dpr, 0, 0);
    ctx.clearRect(0, 0, view.W, view.H);
    const now = performance.now() / 1000;
    let animating = false;
    const info = state.info;
    const span = info ? info.resolution * info.tile_size : 0;
    if (info && $("show-lattice").checked) drawLattice(ctx, span);
    // tile switches: the tile a robot entered flashes
    if (info) {
      for (const e of state.events) {
        const age = now - e.seen;
        if (age > EVENT_FLASH_S) continue;
        animating = true;
        const a = 1 - age / EVENT_FLASH_S;
        const [sx, sy] = worldToScreen(e.i * span, (e.j + 1) * span);
        ctx.fillStyle = `rgba(255, 213, 79, ${0.25 * a})`;
        ctx.strokeStyle = `rgba(255, 213, 79, ${a})`;
        ctx.lineWidth = 2;
        ctx.fillRect(sx, sy, span * view.z, span * view.z);
        ctx.strokeRect(sx, sy, span * view.z, span * view.z);
      }
    }
    // ISM footprints fading in and out
    if ($("show-footprints").checked) {
      for (const [k, f] of state.footprints) {
        if (now - f.t >= FOOTPRINT_S) state.footprints.delete(k);
      }
      for (const f of state.footprints.values()) {
        const age = (now - f.t) / FOOTPRINT_S;
        const a = age < 0.2 ? age / 0.2 : 1 - (age - 0.2) / 0.8;
        ctx.strokeStyle = `rgba(255, 255, 255, ${0.9 * a})`;
        ctx.fillStyle = `rgba(255, 255, 255, ${0.08 * a})`;
        ctx.lineWidth = 1.5;
        ctx.setLineDash([5, 3]);
        ctx.beginPath();
        f.corners.forEach(([x, y], k) => {
          const [sx, sy] = worldToScreen(x, y);
          if (k === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
        });
        ctx.closePath();
        ctx.fill();
        ctx.stroke();
      }
      ctx.setLineDash([]);
      if (state.footprints.size) animating = true;
    }
    if ($("show-supercells").checked && state.supercells) drawSupercells(ctx);
    drawRobots(ctx);
    return animating;
  }
  function drawLattice(ctx, span) {
    let step = span;
    while (step * view.z < 12) step *= 2;
    const b = viewBox();
    ctx.strokeStyle = "rgba(255, 255, 255, 0.10)";
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let x = Math.floor(b.xmin / step) * step; x <= b.xmax; x += step) {
      const sx = Math.round(worldToScreen(x, 0)[0]) + 0.5;
      ctx.moveTo(sx, 0); ctx.lineTo(sx, view.H);
    }
    for (let y = Math.floor(b.ymin / step) * step; y <= b.ymax; y += step) {
      const sy = Math.round(worldToScreen(0, y)[1]) + 0.5;
      ctx.moveTo(0, sy); ctx.lineTo(view.W, sy);
    }
    ctx.stroke();
    if (span * view.z < 6) return;
    ctx.strokeStyle = "rgba(100, 190, 255, 0.55)";
    for (const [i, j] of state.info.tiles) {
      if ((i + 1) * span < b.xmin || i * span > b.xmax || (j + 1) * span < b.ymin ||
          j * span > b.ymax) continue;
      const [sx, sy] = worldToScreen(i * span, (j + 1) * span);
      ctx.strokeRect(Math.round(sx) + 0.5, Math.round(sy) + 0.5, Math.round(span * view.z) - 1,
                     Math.round(span * view.z) - 1);
    }
  }
  function drawSupercells(ctx) {
    const sc = state.supercells;
    if (sc.error) return;
    const pos = new Map(sc.nodes.map((n) => [n.id, worldToScreen(n.x, n.y)]));
    ctx.strokeStyle = "rgba(102, 187, 106, 0.85)";
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (const [a, b] of sc.edges) {
      const p = pos.get(a); const q = pos.get(b);
      if (!p || !q) continue;
      ctx.moveTo(p[0], p[1]); ctx.lineTo(q[0], q[1]);
    }
    ctx.stroke();
    const pal = palette();
    for (const n of sc.nodes) {
      const [sx, sy] = pos.get(n.id);
      // A node's evidence: its occupied layer's colour, orange when observed free, else grey.
      ctx.fillStyle = n.cls >= 0 && n.cls < pal.length ? pal[n.cls]
        : (n.free ? "#ff8c00" : "#9e9e9e");
      ctx.strokeStyle = "#000";
      ctx.beginPath();
      ctx.arc(sx, sy, 3.5, 0, 2 * Math.PI);
      ctx.fill();
      ctx.stroke();
    }
  }
  function drawRobots(ctx) {
    const markers = {};
    ctx.font = "12px system-ui, sans-serif";
    for (const [name, p] of Object.entries(state.robots)) {
      const [sx, sy] = worldToScreen(p.x, p.y);
      markers[name] = { x: p.x, y: p.y, yaw: p.yaw, sx, sy };
      if (sx < -50 || sy < -50 || sx > view.W + 50 || sy > view.H + 50) continue;
      ctx.save();
      ctx.translate(sx, sy);
      ctx.rotate(-p.yaw);             // screen y points down
      ctx.beginPath();
      ctx.moveTo(12, 0); ctx.lineTo(-7, 7); ctx.lineTo(-3, 0); ctx.lineTo(-7, -7);
      ctx.closePath();
      ctx.fillStyle = "#ff5252";
      ctx.strokeStyle = "#fff";
      ctx.lineWidth = 1.5;
      ctx.fill();
      ctx.stroke();
      ctx.restore();
      ctx.fillStyle = "#fff";
      ctx.strokeStyle = "rgba(0,0,0,0.8)";
      ctx.lineWidth = 3;
      ctx.strokeText(name, sx + 10, sy - 10);
      ctx.fillText(name, sx + 10, sy - 10);
    }
    state.markers = markers;
    overlay.dataset.robots = JSON.stringify(markers);
  }
  function drawScale() {
    const target = 120 / view.z;  // metres in ~120 px
    const p = Math.pow(10, Math.floor(Math.log10(target)));
    const m = [5, 2, 1].map((k) => k * p).find((v) => v <= target) || p;
    $("scale-bar").style.width = `${m * view.z}px`;
    $("scale-label").textContent = m >= 1000 ? `${m / 1000} km` : m >= 1 ? `${m} m` :
      `${Math.round(m * 100 * 1000) / 1000} cm`;
  }

  // -- charts -----------------------------------------------------------------------------------
  const SERIES_COLORS = ["#4fc3f7", "#ffb74d", "#e57373", "#81c784", "#ba68c8", "#fff176"];
  function chart(canvas, series) {
    const ctx = canvas.getContext("2d");
    const w = canvas.width; const h = canvas.height;
    ctx.clearRect(0, 0, w, h);
    let max = 0;
    for (const s of series) for (const v of s.values) if (v > max) max = v;
    const top = max > 0 ? max * 1.15 : 1;
    series.forEach((s, k) => {
      ctx.strokeStyle = s.color || SERIES_COLORS[k % SERIES_COLORS.length];
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      s.values.forEach((v, i) => {
        const x = w - (s.values.length - 1 - i) * (w / (HISTORY - 1));
        const y = h - 2 - (v / top) * (h - 14);
        if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
      });
      ctx.stroke();
    });
    const last = series.length && series[0].values.length ?
      series[0].values[series[0].values.length - 1] : 0;
    ctx.fillStyle = "#cfd8dc";
    ctx.font = "10px system-ui, sans-serif";
    ctx.fillText(`max ${fmt(max)}  now ${fmt(last)}`, 4, 10);
  }
  function fmt(v) { return v >= 100 ? v.toFixed(0) : v >= 10 ? v.toFixed(1) : v.toFixed(2); }
  function drawCharts() {
    const s = state.stats;
    chart($("chart-isms"), [{ values: s.map((x) => x.isms_per_s) }]);
    chart($("chart-queue"), [{ values: s.map((x) => x.queue_depth), color: "#ffb74d" }]);
    const reasons = [...new Set(s.flatMap((x) => Object.keys(x.rejected)))].sort();
    chart($("chart-rejected"), reasons.map((r) => ({ values: s.map((x) => x.rejected[r] || 0) })));
    $("rejected-legend").textContent = reasons.length ?
      reasons.map((r, k) => `${r} (${["blue", "orange", "red", "green", "purple", "yellow"][k % 6]})`)
        .join(", ") : "no rejections";
    const names = [...new Set(s.flatMap((x) => Object.keys(x.latency_p50_ms)))].sort();
    chart($("chart-latency"), names.map((n) => ({ values: s.map((x) => x.latency_p50_ms[n] || 0) })));
    $("latency-legend").textContent = names.map((n, k) =>
      `${n} (${["blue", "orange", "red", "green"][k % 4]})`).join(", ");
  }

  // -- for scripts and tests ------------------------------------------------------------------
  window.sogmViewer = {
    state, view, tiles,
    worldToScreen,
    screenToWorld,
    /** Device pixel of the map canvas showing map point (x, y). */
    worldToCanvas(x, y) {
      const [sx, sy] = worldToScreen(x, y);
      return [Math.floor(sx * view.dpr), Math.floor(sy * view.dpr)];
    },
    /** RGBA of the map canvas (tiles only, no overlay) at map point (x, y). */
    pixelAt(x, y) {
      const [px, py] = this.worldToCanvas(x, y);
      return Array.from(mapCtx.getImageData(px, py, 1, 1).data);
    },
    setView,
    setMode(mode, opts) {
      opts = opts || {};
      $("mode").value = mode;
      if (opts.layer) $("layer").value = opts.layer;
      if (opts.method) $("method").value = opts.method;
      if (opts.layers) {
        for (const c of $("fused-layers").querySelectorAll("input")) {
          c.checked = opts.layers.includes(c.value);
        }
      }
      onModeChange();
    },
    probe,
    fit: () => fit(true),
  };

  resize();
  onModeChange();
  connect();
})();
