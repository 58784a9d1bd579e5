// The `ssg view` page's renderer (ssgc/view/page.py writes the data it reads).
// A canvas 2-D painter: every triangle of every object is turned into the camera's frame,
// projected, sorted far to near and filled, shaded by the angle of its normal to the view.
// No WebGL, so the page draws the same in any browser, with or without a GPU.
(function () {
  "use strict";

  const data = JSON.parse(document.getElementById("ssg-data").textContent);
  const canvas = document.getElementById("canvas");
  const ctx = canvas.getContext("2d");
  const $ = (id) => document.getElementById(id);
  const FOV = 40 * Math.PI / 180;
  const MIN_PX = 8; // an object is never drawn smaller than this (CSS pixels across)

  const state = {
    scene: 0, yaw: -2.2, pitch: 0.6, zoom: 1, pan: [0, 0, 0],
    selected: -1, // an index into the scene's `objects`
    world: [],    // per object: its triangles in the world frame
    centre: [0, 0, 0], radius: 1, floor: 0,
    drawn: [],    // the triangles as last drawn, far to near: {pts, object}
  };

  // ---------------------------------------------------------------- vectors ---
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [
    a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0],
  ];
  const norm = (a) => { const n = Math.hypot(a[0], a[1], a[2]) || 1; return scale(a, 1 / n); };
  const place = (r, t, v) => [
    r[0] * v[0] + r[1] * v[1] + r[2] * v[2] + t[0],
    r[3] * v[0] + r[4] * v[1] + r[5] * v[2] + t[1],
    r[6] * v[0] + r[7] * v[1] + r[8] * v[2] + t[2],
  ];

  function hexRgb(hex) {
    return [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16));
  }

  // ---------------------------------------------------------------- a scene ---
  function scene() { return data.scenes[state.scene]; }

  function prepare() {
    // World triangles of every object, and the box that holds the scene.
    const s = scene();
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    const grow = (p) => { for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[k]); hi[k] = Math.max(hi[k], p[k]); } };
    s.nodes.forEach((n) => grow(n.xyz));
    state.world = s.objects.map((nodeIndex, k) => {
      const node = s.nodes[nodeIndex];
      const type = data.types[node.type];
      const verts = type.shape.vertices.map((v) => place(node.rot, node.xyz, v));
      verts.forEach(grow);
      const tris = type.shape.faces.map((f) => {
        const p = [verts[f[0]], verts[f[1]], verts[f[2]]];
        return { p: p, normal: norm(cross(sub(p[1], p[0]), sub(p[2], p[0]))) };
      });
      const faint = s.faint[k];
      return { tris: tris, rgb: hexRgb(type.colour), alpha: faint ? 0.3 : 1.0, cull: type.shape.closed && !faint };
    });
    if (!isFinite(lo[0])) { lo.splice(0, 3, 0, 0, 0); hi.splice(0, 3, 0, 0, 0); }
    state.centre = scale(add(lo, hi), 0.5);
    state.radius = Math.max(0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]), 0.05);
    state.floor = lo[2];
  }

  // ---------------------------------------------------------------- camera ---
  function camera() {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    const target = add(state.centre, state.pan);
    const dist = state.radius / Math.sin(FOV / 2) / state.zoom * 1.05;
    const dir = [Math.cos(state.pitch) * Math.cos(state.yaw), Math.cos(state.pitch) * Math.sin(state.yaw), Math.sin(state.pitch)];
    const eye = add(target, scale(dir, dist));
    const forward = norm(sub(target, eye));
    const right = norm(cross(forward, [0, 0, 1]));
    const up = cross(right, forward);
    const focal = 0.5 * Math.min(w, h) / Math.tan(FOV / 2);
    return { eye, forward, right, up, focal, w, h, near: dist * 0.01 };
  }

  function project(cam, p) {
    const d = sub(p, cam.eye);
    const z = dot(d, cam.forward);
    return [cam.w / 2 + cam.focal * dot(d, cam.right) / z, cam.h / 2 - cam.focal * dot(d, cam.up) / z, z];
  }

  // ---------------------------------------------------------------- drawing ---
  function resize() {
    const dpr = window.devicePixelRatio || 1;
    canvas.width = Math.max(1, Math.round(canvas.clientWidth * dpr));
    canvas.height = Math.max(1, Math.round(canvas.clientHeight * dpr));
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  }

  function draw() {
    const cam = camera();
    ctx.clearRect(0, 0, cam.w, cam.h);
    drawFloor(cam);
    const light = norm(add(scale(cam.forward, -1), scale(cam.up, 0.6)));
    const tris = [];
    state.world.forEach((obj, k) => {
      const mine = [];
      obj.tris.forEach((t) => {
        if (obj.cull && dot(t.normal, sub(t.p[0], cam.eye)) > 0) return; // its back
        const q = t.p.map((p) => project(cam, p));
        if (q[0][2] < cam.near || q[1][2] < cam.near || q[2][2] < cam.near) return;
        const shade = 0.45 + 0.55 * Math.abs(dot(t.normal, light));
        mine.push({ pts: q, depth: (q[0][2] + q[1][2] + q[2][2]) / 3, object: k, shade: shade });
      });
      atLeast(mine, MIN_PX);
      mine.forEach((t) => tris.push(t));
    });
    // Far to near; a see-through container (a bin, a table) first, so what it holds is drawn
    // whole over it whatever the depths of its large faces say.
    const faint = (t) => (state.world[t.object].alpha < 1 ? 0 : 1);
    tris.sort((a, b) => faint(a) - faint(b) || b.depth - a.depth);
    tris.forEach((t) => {
      const obj = state.world[t.object];
      const c = obj.rgb.map((x) => Math.round(x * t.shade));
      const fill = "rgba(" + c[0] + "," + c[1] + "," + c[2] + "," + obj.alpha + ")";
      path(t.pts);
      ctx.fillStyle = fill;
      ctx.fill();
      if (obj.alpha === 1) { // closes the hairline gaps between neighbouring triangles
        ctx.strokeStyle = fill;
        ctx.lineWidth = 0.5;
        ctx.stroke();
      }
    });
    state.drawn = tris;
    drawTree(cam);
    drawSelection();
  }

  function atLeast(tris, px) {
    // An object's projected triangles, grown about their centre to `px` across when they are
    // smaller: a 3 cm marker in a scene a kilometre wide is still seen, and clicked.
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    tris.forEach((t) => t.pts.forEach((p) => {
      x0 = Math.min(x0, p[0]); y0 = Math.min(y0, p[1]); x1 = Math.max(x1, p[0]); y1 = Math.max(y1, p[1]);
    }));
    const size = Math.max(x1 - x0, y1 - y0);
    if (!tris.length || size >= px) return;
    const f = px / Math.max(size, 1e-6), cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
    tris.forEach((t) => {
      t.pts = t.pts.map((p) => [cx + (p[0] - cx) * f, cy + (p[1] - cy) * f, p[2]]);
    });
  }

  function path(pts) {
    ctx.beginPath();
    ctx.moveTo(pts[0][0], pts[0][1]);
    for (let i = 1; i < pts.length; i++) ctx.lineTo(pts[i][0], pts[i][1]);
    ctx.closePath();
  }

  function drawFloor(cam) {
    // A grid on the lowest height of the scene, its step chosen for the scene's extent
    // (page.py: 10 cm for a scene of a metre, 10 to 25 lines across whatever its size).
    const step = scene().grid.step;
    const half = Math.ceil(state.radius * 1.3 / step) * step;
    const c = state.centre;
    ctx.strokeStyle = "#d5d8dd";
    ctx.lineWidth = 1;
    for (let x = -half; x <= half + 1e-9; x += step) {
      line(cam, [c[0] + x, c[1] - half, state.floor], [c[0] + x, c[1] + half, state.floor]);
      line(cam, [c[0] - half, c[1] + x, state.floor], [c[0] + half, c[1] + x, state.floor]);
    }
    const o = farCorner(cam, c, half);
    [[1, 0, 0, "#c0392b"], [0, 1, 0, "#27ae60"], [0, 0, 1, "#2e5fb3"]].forEach((a) => {
      ctx.strokeStyle = a[3];
      ctx.lineWidth = 2;
      line(cam, o, add(o, scale([a[0], a[1], a[2]], step * 3)));
    });
  }

  function farCorner(cam, c, half) {
    // The grid corner farthest from the camera, where the x/y/z marker goes: the camera
    // looks down across the grid at it, whereas the nearest corner is below the canvas or
    // behind the camera (the default view's, at yaw -2.2).
    let best = null, far = -1;
    [[-1, -1], [1, -1], [-1, 1], [1, 1]].forEach(([sx, sy]) => {
      const p = [c[0] + sx * half, c[1] + sy * half, state.floor];
      const d = sub(p, cam.eye);
      if (dot(d, d) > far) { far = dot(d, d); best = p; }
    });
    return best;
  }

  function line(cam, a, b) {
    const p = project(cam, a), q = project(cam, b);
    if (p[2] < cam.near || q[2] < cam.near) return;
    ctx.beginPath();
    ctx.moveTo(p[0], p[1]);
    ctx.lineTo(q[0], q[1]);
    ctx.stroke();
  }

  function drawTree(cam) {
    // Edges between node poses (coloured by rule log-probability for a parse); latent nodes
    // as small grey squares.
    const s = scene();
    s.nodes.forEach((n) => {
      if (n.parent < 0) return;
      ctx.strokeStyle = n.edge || "#333";
      ctx.lineWidth = n.edge ? 2.5 : 1;
      line(cam, s.nodes[n.parent].xyz, n.xyz);
    });
    ctx.fillStyle = "#555";
    s.nodes.forEach((n) => {
      if (n.observed) return;
      const p = project(cam, n.xyz);
      if (p[2] > cam.near) ctx.fillRect(p[0] - 3, p[1] - 3, 6, 6);
    });
  }

  function drawSelection() {
    // A dashed frame around the selected object as drawn (its colour stays its type's).
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    state.drawn.forEach((t) => {
      if (t.object !== state.selected) return;
      t.pts.forEach((p) => { x0 = Math.min(x0, p[0]); y0 = Math.min(y0, p[1]); x1 = Math.max(x1, p[0]); y1 = Math.max(y1, p[1]); });
    });
    if (!isFinite(x0)) return;
    ctx.save();
    ctx.setLineDash([5, 3]);
    ctx.strokeStyle = "#111";
    ctx.lineWidth = 1.5;
    ctx.strokeRect(x0 - 4, y0 - 4, x1 - x0 + 8, y1 - y0 + 8);
    ctx.restore();
  }

  // ---------------------------------------------------------------- picking ---
  function inside(pts, x, y) {
    let hit = false;
    for (let i = 0, j = pts.length - 1; i < pts.length; j = i++) {
      const [xi, yi] = pts[i], [xj, yj] = pts[j];
      if ((yi > y) !== (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi) hit = !hit;
    }
    return hit;
  }

  function pick(x, y) {
    // The nearest object under the point: the last triangle drawn there.
    for (let i = state.drawn.length - 1; i >= 0; i--) {
      if (inside(state.drawn[i].pts, x, y)) return state.drawn[i].object;
    }
    return -1;
  }

  function screenPoint(k) {
    // A point of the canvas (CSS pixels) where a click picks object k, or null if none shows.
    for (let i = state.drawn.length - 1; i >= 0; i--) {
      const t = state.drawn[i];
      if (t.object !== k) continue;
      const x = (t.pts[0][0] + t.pts[1][0] + t.pts[2][0]) / 3;
      const y = (t.pts[0][1] + t.pts[1][1] + t.pts[2][1]) / 3;
      if (pick(x, y) === k) return [x, y];
    }
    return null;
  }

  // ---------------------------------------------------------------- the panel ---
  function formatLogp(v) {
    if (v === null || v === undefined) return null;
    const x = Number(v);
    return x === -Infinity ? "−∞" : x.toFixed(2);
  }

  function nodeLabel(s, i) {
    return data.types[s.nodes[i].type].name + " #" + i;
  }

  function treePath(s, i) {
    const chain = [];
    for (let j = i; j >= 0; j = s.nodes[j].parent) chain.unshift(j);
    return chain;
  }

  function showSelection() {
    const s = scene();
    const list = $("path");
    list.replaceChildren();
    if (state.selected < 0) {
      $("selected-title").textContent = "Click an object";
      return;
    }
    const nodeIndex = s.objects[state.selected];
    $("selected-title").textContent =
      data.types[s.nodes[nodeIndex].type].name + ": object " + (state.selected + 1) + " of " + s.objects.length +
      (s.tree ? ", its path in the tree" : " (no tree known)");
    // A rule is marked low at or below the page's mark (page.py: the lowest quarter of its
    // range), or when it is −∞; with no mark (every finite rule alike) only −∞ is.
    const mark = data.scores ? data.scores.mark : null;
    const isLow = (v) => Number(v) === -Infinity || (mark !== null && Number(v) <= mark);
    treePath(s, nodeIndex).forEach((j) => {
      const n = s.nodes[j];
      const li = document.createElement("li");
      li.dataset.node = String(j);
      li.dataset.type = data.types[n.type].name;
      const name = document.createElement("span");
      name.className = "node" + (j === nodeIndex ? " here" : "");
      name.textContent = nodeLabel(s, j) + (n.observed ? "" : " (latent)");
      li.appendChild(name);
      const lp = formatLogp(n.log_prob);
      if (n.parent >= 0 || lp !== null) {
        const rule = document.createElement("span");
        rule.className = "rule";
        const parts = [];
        if (n.rule) parts.push("rule " + n.rule);
        if (lp !== null) parts.push("log p = " + lp);
        rule.textContent = parts.join(", ");
        if (lp !== null && data.scores && isLow(n.log_prob)) rule.classList.add("low");
        if (parts.length) li.appendChild(rule);
      }
      list.appendChild(li);
    });
  }

  function showScene() {
    const s = scene();
    $("scene-title").textContent = s.title;
    $("count").textContent = String(s.objects.length);
    $("count-word").textContent = s.objects.length === 1 ? "object" : "objects";
    const latent = s.nodes.length - s.objects.length;
    $("tree-note").textContent = s.tree
      ? ", " + latent + " latent node" + (latent === 1 ? "" : "s") + " in its tree"
      : ", no tree known";
    $("position").textContent = "scene " + (state.scene + 1) + " of " + data.scenes.length;
    $("grid-step").textContent = s.grid.label;
    $("pick-scene").value = String(state.scene);
    $("prev").disabled = state.scene === 0;
    $("next").disabled = state.scene === data.scenes.length - 1;
  }

  function setup() {
    const choose = $("pick-scene");
    data.scenes.forEach((s, i) => {
      const o = document.createElement("option");
      o.value = String(i);
      o.textContent = (i + 1) + ". " + s.name;
      choose.appendChild(o);
    });
    const legend = $("legend");
    data.types.forEach((t) => {
      if (!t.observed) return;
      const li = document.createElement("li");
      const sw = document.createElement("span");
      sw.className = "swatch";
      sw.style.background = t.colour;
      li.appendChild(sw);
      li.appendChild(document.createTextNode(t.name + (t.geometry ? "" : " (no geometry)")));
      legend.appendChild(li);
    });
    if (data.scores) {
      $("score-legend").hidden = false;
      $("score-low").textContent = data.scores.low.toFixed(2);
      $("score-high").textContent = data.scores.high.toFixed(2);
    }
  }

  function go(i) {
    state.scene = Math.max(0, Math.min(data.scenes.length - 1, i));
    state.selected = -1;
    state.pan = [0, 0, 0];
    prepare();
    showScene();
    showSelection();
    draw();
  }

  function select(k) {
    state.selected = k;
    showSelection();
    draw();
  }

  // ---------------------------------------------------------------- input ---
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, moved: 0, shift: e.shiftKey };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.moved += Math.abs(dx) + Math.abs(dy);
    drag.x = e.clientX;
    drag.y = e.clientY;
    if (drag.shift) {
      const cam = camera();
      const k = state.radius * 2 / Math.min(cam.w, cam.h) / state.zoom;
      state.pan = add(state.pan, add(scale(cam.right, -dx * k), scale(cam.up, dy * k)));
    } else {
      state.yaw -= dx * 0.01;
      state.pitch = Math.max(-1.5, Math.min(1.5, state.pitch + dy * 0.01));
    }
    draw();
  });
  canvas.addEventListener("pointerup", (e) => {
    if (drag && drag.moved < 4) {
      const r = canvas.getBoundingClientRect();
      select(pick(e.clientX - r.left, e.clientY - r.top));
    }
    drag = null;
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    state.zoom = Math.max(0.2, Math.min(20, state.zoom * Math.exp(-e.deltaY * 0.001)));
    draw();
  }, { passive: false });
  $("prev").addEventListener("click", () => go(state.scene - 1));
  $("next").addEventListener("click", () => go(state.scene + 1));
  $("pick-scene").addEventListener("change", (e) => go(Number(e.target.value)));
  document.addEventListener("keydown", (e) => {
    if (e.target.tagName === "SELECT") return;
    if (e.key === "ArrowLeft") go(state.scene - 1);
    if (e.key === "ArrowRight") go(state.scene + 1);
  });
  window.addEventListener("resize", () => { resize(); draw(); });

  // What a test (or a curious user, from the console) can ask the page.
  window.ssgView = {
    state: state,
    go: go,
    select: select,
    pick: pick,
    screenPoint: screenPoint,
    objectCount: () => scene().objects.length,
    ready: false,
  };

  setup();
  resize();
  go(0);
  window.ssgView.ready = true;
})();
