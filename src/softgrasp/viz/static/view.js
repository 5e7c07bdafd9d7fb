// The page script of `softgrasp view` (softgrasp.viz.view inlines it into the page).
// Data format (softgrasp.view/1): `nodes` boundary nodes, `tris` flat node triples (outward when
// `cull`), `frames[k]` with `pos` (node coordinates in whole micrometres, frame 0 absolute and every
// later frame the difference to the previous one), `centres` [m], `forces` [N], `travel_mm` and
// `held`; `radius` of the fingertips [m], `fingers` names, `colours`, default `view`.
"use strict";
(function () {
  const D = JSON.parse(document.getElementById("softgrasp-data").textContent);
  const $ = id => document.getElementById(id);
  const canvas = $("view"), ctx = canvas.getContext("2d"), slider = $("frame");

  const BACKGROUND = "#f3f4f6";
  const OBJECT_RGB = [222, 186, 138];
  // Colour by deformation: from the object's colour (none) through orange to plum (the largest).
  const RAMP = [[0, OBJECT_RGB], [0.5, [240, 128, 48]], [1, [128, 34, 104]]];
  const LIGHT = normalise([-0.45, 0.6, 0.66]);  // fixed in camera space: upper left, in front
  const SHADES = 96, TINTS = 24;  // quantised brightness and deformation colour
  const KEY_SPAN = 4194304;  // sort key = quantised depth * KEY_SPAN + item index (< 2^22)

  const nNodes = D.nodes, tris = Int32Array.from(D.tris), nTri = tris.length / 3;
  const nF = D.fingers.length, tipR = D.radius, nFrames = D.frames.length;
  const heldIndex = D.frames.findIndex(f => f.held);

  function normalise(v) {
    const l = Math.hypot(v[0], v[1], v[2]) || 1;
    return [v[0] / l, v[1] / l, v[2] / l];
  }
  function rgb(c) { return "rgb(" + c.map(v => Math.max(0, Math.min(255, Math.round(v)))).join(",") + ")"; }
  function mix(a, b, t) { return a.map((v, i) => v + (b[i] - v) * t); }
  function ramp(x) {
    for (let i = 1; i < RAMP.length; i++) {
      const [x0, c0] = RAMP[i - 1], [x1, c1] = RAMP[i];
      if (x <= x1) return mix(c0, c1, (x - x0) / (x1 - x0));
    }
    return RAMP[RAMP.length - 1][1];
  }
  function shadeHex(hex, k) {  // k > 0 towards white, k < 0 towards black
    const n = parseInt(hex.slice(1), 16), c = [(n >> 16) & 255, (n >> 8) & 255, n & 255];
    return rgb(k >= 0 ? mix(c, [255, 255, 255], k) : c.map(v => v * (1 + k)));
  }

  // Frames: node positions [m] decoded from the micrometre differences, and the deformation of
  // each node, |u - mean u| with u its displacement from the start (the mean is the rigid shift).
  const frames = [];
  let dMax = 0;
  {
    const acc = new Float64Array(3 * nNodes);
    for (const f of D.frames) {
      const p = new Float32Array(3 * nNodes);
      for (let i = 0; i < p.length; i++) { acc[i] += f.pos[i]; p[i] = acc[i] * 1e-6; }
      delete f.pos;
      const p0 = frames.length ? frames[0].p : p, mean = [0, 0, 0], def = new Float32Array(nNodes);
      for (let i = 0; i < 3 * nNodes; i++) mean[i % 3] += (p[i] - p0[i]) / nNodes;
      for (let i = 0; i < nNodes; i++) {
        def[i] = Math.hypot(p[3 * i] - p0[3 * i] - mean[0], p[3 * i + 1] - p0[3 * i + 1] - mean[1],
                            p[3 * i + 2] - p0[3 * i + 2] - mean[2]);
        dMax = Math.max(dMax, def[i]);
      }
      frames.push({
        p: p, def: def, centres: f.centres, forces: f.forces, held: f.held, label: f.label,
        travel: f.travel_mm, mag: f.forces.map(v => Math.hypot(v[0], v[1], v[2])),
      });
    }
  }

  // The scene: centre and size of the object at the start, largest force, table grid.
  const scene = (() => {
    const p = frames[0].p, lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < 3 * nNodes; i++) {
      lo[i % 3] = Math.min(lo[i % 3], p[i]); hi[i % 3] = Math.max(hi[i % 3], p[i]);
    }
    const c = [0, 1, 2].map(a => 0.5 * (lo[a] + hi[a]));
    let R = 0;
    for (let i = 0; i < nNodes; i++) {
      R = Math.max(R, Math.hypot(p[3 * i] - c[0], p[3 * i + 1] - c[1], p[3 * i + 2] - c[2]));
    }
    R = R || 1e-3;
    let fMax = 0;
    for (const f of frames) for (const m of f.mag) fMax = Math.max(fMax, m);
    const raw = R / 3, pow = Math.pow(10, Math.floor(Math.log10(raw)));
    const grid = [1, 2, 5, 10].map(m => m * pow).find(g => g >= raw);
    return { c: c, R: R, fMax: fMax, arrowMax: 0.55 * R, grid: grid, half: Math.ceil(1.3 * R / grid) * grid };
  })();

  // Camera: orbit around the scene centre, z up; `dist` gives a mild perspective.
  const cam = { az: 0, el: 0, zoom: 1, dist: 7 * scene.R };
  const fit = { x0: -1, x1: 1, y0: -1, y1: 1 };  // the default view's extent in view units
  let W = 300, H = 150, scale = 1, panX = 0, panY = 0, exaggerate = 1, colourOn = true;
  let current = 0, drawCount = 0, lastDrawMs = 0;

  function basis() {
    const ca = Math.cos(cam.az), sa = Math.sin(cam.az), ce = Math.cos(cam.el), se = Math.sin(cam.el);
    return { r: [-sa, ca, 0], u: [-se * ca, -se * sa, ce], e: [ce * ca, ce * sa, se] };
  }

  // View coordinates of a world point (x right, y up, z towards the camera) and its screen point.
  function project(B, P) {
    const dx = P[0] - scene.c[0], dy = P[1] - scene.c[1], dz = P[2] - scene.c[2];
    const vx = dx * B.r[0] + dy * B.r[1];
    const vy = dx * B.u[0] + dy * B.u[1] + dz * B.u[2];
    const vz = dx * B.e[0] + dy * B.e[1] + dz * B.e[2];
    const s = cam.dist / (cam.dist - vz), k = cam.zoom * scale * s;
    return { vx: vx, vy: vy, vz: vz, s: s,
             X: W / 2 + cam.zoom * panX + k * vx, Y: H / 2 - cam.zoom * panY - k * vy };
  }

  // Fingertip centre as drawn: with exaggerated displacements it moves with the surface nearest
  // to it, so that it still touches the object as it does.
  function tipCentre(f, i, g) {
    const c = f.centres[i];
    if (g === 1) return c;
    if (!f.near) {
      f.near = f.centres.map(q => {
        let best = 0, dBest = Infinity;
        for (let j = 0; j < nNodes; j++) {
          const d = (f.p[3 * j] - q[0]) ** 2 + (f.p[3 * j + 1] - q[1]) ** 2 + (f.p[3 * j + 2] - q[2]) ** 2;
          if (d < dBest) { dBest = d; best = j; }
        }
        return best;
      });
    }
    const j = 3 * f.near[i], p0 = frames[0].p;
    return [0, 1, 2].map(a => c[a] + (g - 1) * (f.p[j + a] - p0[j + a]));
  }

  // Force arrow: its tip where the fingertip touches, its length proportional to the force.
  function arrowEnds(f, i, g) {
    const m = f.mag[i];
    if (!(scene.fMax > 0) || !(m > 1e-6 * scene.fMax)) return null;
    const c = tipCentre(f, i, g), F = f.forces[i], L = scene.arrowMax * m / scene.fMax;
    const tip = [0, 1, 2].map(a => c[a] + tipR * F[a] / m);
    return { tip: tip, tail: [0, 1, 2].map(a => tip[a] - L * F[a] / m) };
  }

  // Extent of everything (all frames, fingertips, arrows) seen from the default camera.
  function fitDefault() {
    cam.az = D.view.azimuth_deg * Math.PI / 180;
    cam.el = D.view.elevation_deg * Math.PI / 180;
    cam.zoom = 1;
    const B = basis();
    let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
    const add = (P, pad) => {
      const q = project(B, P);
      x0 = Math.min(x0, q.vx * q.s - pad); x1 = Math.max(x1, q.vx * q.s + pad);
      y0 = Math.min(y0, q.vy * q.s - pad); y1 = Math.max(y1, q.vy * q.s + pad);
    };
    const stride = Math.max(1, Math.floor(nNodes * nFrames / 60000));
    for (const f of frames) {
      for (let i = 0; i < nNodes; i += stride) add([f.p[3 * i], f.p[3 * i + 1], f.p[3 * i + 2]], 0);
      for (let i = 0; i < nF; i++) {
        add(tipCentre(f, i, 1), tipR);
        const a = arrowEnds(f, i, 1);
        if (a) add(a.tail, 0);
      }
    }
    Object.assign(fit, { x0: x0, x1: x1, y0: y0, y1: y1 });
  }

  function layout() {
    const rect = canvas.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    W = Math.max(1, rect.width); H = Math.max(1, rect.height);
    canvas.width = Math.round(W * dpr); canvas.height = Math.round(H * dpr);
    ctx.setTransform(canvas.width / W, 0, 0, canvas.height / H, 0, 0);
    const mx = Math.min(110, 0.15 * W), my = Math.min(30, 0.08 * H);  // room for the arrow labels
    scale = Math.min((W - 2 * mx) / (fit.x1 - fit.x0), (H - 2 * my) / (fit.y1 - fit.y0));
    panX = -scale * 0.5 * (fit.x0 + fit.x1);
    panY = -scale * 0.5 * (fit.y0 + fit.y1);
  }

  // Fill styles by deformation tint and brightness (above 1: a highlight towards white); the
  // outline of a triangle is a little darker than its fill.
  const fillStyles = [], edgeStyles = [];
  for (let t = 0; t < TINTS; t++) {
    const base = ramp(t / (TINTS - 1));
    for (let l = 0; l < SHADES; l++) {
      const b = 1.2 * l / (SHADES - 1);
      const c = b <= 1 ? base.map(v => v * b) : mix(base, [255, 255, 255], (b - 1) / 0.5);
      fillStyles.push(rgb(c));
      edgeStyles.push(rgb(c.map(v => 0.8 * v)));
    }
  }

  // Work arrays, sized once.
  const VX = new Float32Array(nNodes), VY = new Float32Array(nNodes), VZ = new Float32Array(nNodes);
  const SX = new Float32Array(nNodes), SY = new Float32Array(nNodes);
  const keys = new Float64Array(nTri + nF), style = new Uint16Array(nTri);

  function drawTable(B, alpha) {
    const c = scene.c, h = scene.half, g = scene.grid;
    const x0 = Math.round(c[0] / g) * g - h, y0 = Math.round(c[1] / g) * g - h, n = Math.round(2 * h / g);
    const P = (x, y) => project(B, [x, y, 0]);
    ctx.save();
    ctx.globalAlpha = alpha;
    ctx.beginPath();
    [P(x0, y0), P(x0 + 2 * h, y0), P(x0 + 2 * h, y0 + 2 * h), P(x0, y0 + 2 * h)].forEach(
      (q, i) => (i ? ctx.lineTo(q.X, q.Y) : ctx.moveTo(q.X, q.Y)));
    ctx.closePath();
    ctx.fillStyle = "rgba(120, 132, 148, 0.14)";
    ctx.fill();
    ctx.beginPath();
    for (let i = 0; i <= n; i++) {
      const u = x0 + i * g, v = y0 + i * g;
      for (const [a, b] of [[P(u, y0), P(u, y0 + 2 * h)], [P(x0, v), P(x0 + 2 * h, v)]]) {
        ctx.moveTo(a.X, a.Y); ctx.lineTo(b.X, b.Y);
      }
    }
    ctx.strokeStyle = "rgba(96, 108, 124, 0.3)";
    ctx.lineWidth = 1;
    ctx.stroke();
    ctx.restore();
  }

  function drawTip(q, i) {
    const rp = Math.max(1.5, cam.zoom * scale * tipR * q.s), col = D.colours[i];
    const g = ctx.createRadialGradient(q.X - 0.4 * rp, q.Y - 0.45 * rp, 0.05 * rp, q.X, q.Y, rp);
    g.addColorStop(0, shadeHex(col, 0.75));
    g.addColorStop(0.45, col);
    g.addColorStop(1, shadeHex(col, -0.45));
    ctx.beginPath();
    ctx.arc(q.X, q.Y, rp, 0, 2 * Math.PI);
    ctx.fillStyle = g;
    ctx.fill();
    ctx.lineWidth = 1;
    ctx.strokeStyle = shadeHex(col, -0.55);
    ctx.stroke();
  }

  function label(text, x, y, align, colour) {
    ctx.font = "600 13px system-ui, -apple-system, 'Segoe UI', Roboto, Arial, sans-serif";
    ctx.textAlign = align;
    ctx.textBaseline = "middle";
    ctx.lineJoin = "round";
    ctx.lineWidth = 4;
    ctx.strokeStyle = "rgba(255, 255, 255, 0.92)";
    ctx.strokeText(text, x, y);
    ctx.fillStyle = colour;
    ctx.fillText(text, x, y);
  }

  // Force arrows and their labels, over everything; dashed when the fingertip is behind the object.
  function drawArrows(f, B, tips) {
    const o = project(B, scene.c);
    for (let i = 0; i < nF; i++) {
      const q = tips[i], col = D.colours[i], dark = shadeHex(col, -0.25);
      const behind = q.vz < -0.3 * scene.R;
      const a = arrowEnds(f, i, exaggerate);
      let ux = q.X - o.X, uy = q.Y - o.Y, at = null;
      if (a) {
        const t = project(B, a.tip), s = project(B, a.tail), len = Math.hypot(t.X - s.X, t.Y - s.Y);
        if (len > 1) {
          const dx = (t.X - s.X) / len, dy = (t.Y - s.Y) / len, head = Math.min(16, 0.45 * len + 4);
          const bx = t.X - head * dx, by = t.Y - head * dy;
          ctx.save();
          ctx.globalAlpha = behind ? 0.65 : 1;
          ctx.lineCap = "round";
          ctx.setLineDash(behind ? [7, 5] : []);
          for (const [w, st] of [[7, "rgba(255, 255, 255, 0.9)"], [3.2, dark]]) {
            ctx.beginPath(); ctx.moveTo(s.X, s.Y); ctx.lineTo(bx, by);
            ctx.lineWidth = w; ctx.strokeStyle = st; ctx.stroke();
          }
          ctx.setLineDash([]);
          ctx.beginPath();
          ctx.moveTo(t.X, t.Y);
          ctx.lineTo(bx - 0.5 * head * dy, by + 0.5 * head * dx);
          ctx.lineTo(bx + 0.5 * head * dy, by - 0.5 * head * dx);
          ctx.closePath();
          ctx.lineWidth = 2; ctx.strokeStyle = "rgba(255, 255, 255, 0.9)"; ctx.stroke();
          ctx.fillStyle = dark; ctx.fill();
          ctx.restore();
          ux = -dx; uy = -dy; at = s;
        }
      }
      const l = Math.hypot(ux, uy) || 1;
      ux /= l; uy /= l;
      if (!at) {  // no arrow: the label beside the fingertip, away from the object
        const rp = cam.zoom * scale * tipR * q.s;
        at = { X: q.X + rp * ux, Y: q.Y + rp * uy };
      }
      const align = ux > 0.35 ? "left" : ux < -0.35 ? "right" : "center";
      label(D.fingers[i] + ": " + f.mag[i].toFixed(2) + " N", at.X + 8 * ux, at.Y + 10 * uy, align, dark);
    }
  }

  // A small axis cross in the lower right corner (x, y on the table, z up).
  function drawAxes(B) {
    const ox = W - 40, oy = H - 64, L = 22;
    ctx.save();
    ctx.lineWidth = 1.5; ctx.strokeStyle = "#57606a"; ctx.fillStyle = "#57606a";
    ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "center"; ctx.textBaseline = "middle";
    [["x", [1, 0, 0]], ["y", [0, 1, 0]], ["z", [0, 0, 1]]].forEach(([name, v]) => {
      const x = v[0] * B.r[0] + v[1] * B.r[1], y = v[0] * B.u[0] + v[1] * B.u[1] + v[2] * B.u[2];
      ctx.beginPath(); ctx.moveTo(ox, oy); ctx.lineTo(ox + L * x, oy - L * y); ctx.stroke();
      ctx.fillText(name, ox + (L + 8) * x, oy - (L + 8) * y);
    });
    ctx.restore();
  }

  function draw() {
    const t0 = performance.now();
    const f = frames[current], p = f.p, p0 = frames[0].p, g = exaggerate, B = basis();
    ctx.fillStyle = BACKGROUND;
    ctx.fillRect(0, 0, W, H);
    const table = !f.held;
    if (table && cam.el >= 0) drawTable(B, 1);

    // Project the nodes (displacements from the start exaggerated by g).
    let zMin = Infinity, zMax = -Infinity;
    const k = cam.zoom * scale, cx = W / 2 + cam.zoom * panX, cy = H / 2 - cam.zoom * panY;
    for (let i = 0; i < nNodes; i++) {
      const j = 3 * i;
      const dx = p0[j] + g * (p[j] - p0[j]) - scene.c[0];
      const dy = p0[j + 1] + g * (p[j + 1] - p0[j + 1]) - scene.c[1];
      const dz = p0[j + 2] + g * (p[j + 2] - p0[j + 2]) - scene.c[2];
      const vx = dx * B.r[0] + dy * B.r[1];
      const vy = dx * B.u[0] + dy * B.u[1] + dz * B.u[2];
      const vz = dx * B.e[0] + dy * B.e[1] + dz * B.e[2];
      const s = k * cam.dist / (cam.dist - vz);
      VX[i] = vx; VY[i] = vy; VZ[i] = vz;
      SX[i] = cx + s * vx;
      SY[i] = cy - s * vy;
      if (vz < zMin) zMin = vz;
      if (vz > zMax) zMax = vz;
    }
    const tips = [];
    for (let i = 0; i < nF; i++) {
      const q = project(B, tipCentre(f, i, g));
      tips.push(q);
      zMin = Math.min(zMin, q.vz); zMax = Math.max(zMax, q.vz);
    }
    const zScale = (1 << 30) / Math.max(zMax - zMin, 1e-12);
    const tint = colourOn && dMax > 0 ? (TINTS - 1) / dMax : 0;

    // Visible triangles: their style and depth key (sorted: far ones first).
    let n = 0, edgeSum = 0, edgeCount = 0;
    for (let t = 0; t < nTri; t++) {
      const a = tris[3 * t], b = tris[3 * t + 1], c = tris[3 * t + 2];
      const cross = (SX[b] - SX[a]) * (SY[c] - SY[a]) - (SY[b] - SY[a]) * (SX[c] - SX[a]);
      if (D.cull && cross >= 0) continue;  // a back face (screen y points down)
      const ux = VX[b] - VX[a], uy = VY[b] - VY[a], uz = VZ[b] - VZ[a];
      const wx = VX[c] - VX[a], wy = VY[c] - VY[a], wz = VZ[c] - VZ[a];
      let nx = uy * wz - uz * wy, ny = uz * wx - ux * wz, nz = ux * wy - uy * wx;
      let l = Math.hypot(nx, ny, nz);
      if (!(l > 0)) continue;
      if (!D.cull && nz < 0) l = -l;  // two-sided lighting
      const lambert = Math.max(0, (nx * LIGHT[0] + ny * LIGHT[1] + nz * LIGHT[2]) / l);
      const bright = 0.45 + 0.55 * lambert + 0.12 * Math.pow(lambert, 12);
      const shade = Math.min(SHADES - 1, Math.round(bright / 1.2 * (SHADES - 1)));
      const d = Math.round(tint * (f.def[a] + f.def[b] + f.def[c]) / 3);
      style[t] = Math.min(TINTS - 1, d) * SHADES + shade;
      keys[n++] = Math.floor(((VZ[a] + VZ[b] + VZ[c]) / 3 - zMin) * zScale) * KEY_SPAN + t;
      if ((t & 15) === 0) { edgeSum += Math.abs(SX[b] - SX[a]) + Math.abs(SY[b] - SY[a]); edgeCount++; }
    }
    for (let i = 0; i < nF; i++) keys[n++] = Math.floor((tips[i].vz - zMin) * zScale) * KEY_SPAN + nTri + i;
    const order = keys.subarray(0, n).sort();

    // A light outline on coarse meshes; on fine ones the edges only close the seams.
    const coarse = edgeSum / Math.max(1, edgeCount) > 7, width = coarse ? 0.7 : 0.6;
    const edges = coarse ? edgeStyles : fillStyles;
    ctx.lineJoin = "round";
    ctx.lineWidth = width;
    for (let j = 0; j < n; j++) {
      const t = order[j] % KEY_SPAN;
      if (t >= nTri) { drawTip(tips[t - nTri], t - nTri); ctx.lineWidth = width; continue; }
      const a = tris[3 * t], b = tris[3 * t + 1], c = tris[3 * t + 2], st = style[t];
      ctx.beginPath();
      ctx.moveTo(SX[a], SY[a]); ctx.lineTo(SX[b], SY[b]); ctx.lineTo(SX[c], SY[c]);
      ctx.closePath();
      ctx.fillStyle = fillStyles[st];
      ctx.fill();
      ctx.strokeStyle = edges[st];
      ctx.stroke();
    }
    if (table && cam.el < 0) drawTable(B, 0.6);
    drawArrows(f, B, tips);
    drawAxes(B);
    drawCount++;
    lastDrawMs = performance.now() - t0;
  }

  let pending = false;
  function requestDraw() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; draw(); });
  }

  function describe(f, k) {
    $("frame-label").textContent = f.held ? "held" : "step " + k + " / " + (heldIndex - 1);
    const readout = $("readout"), travel = f.travel === null ? "" : "travel " + f.travel.toFixed(3) + " mm";
    readout.textContent = (f.held ? "held by the fingers alone (table removed)" + (travel ? ", " : "") : "") +
      travel + ": ";
    for (let i = 0; i < nF; i++) {
      const span = document.createElement("span"), dot = document.createElement("span");
      span.className = "finger";
      dot.className = "dot";
      dot.style.background = D.colours[i];
      span.append(dot, D.fingers[i] + " " + f.mag[i].toFixed(3) + " N");
      readout.append(span, i + 1 < nF ? ",  " : "");
    }
  }

  function setFrame(i) {
    current = Math.max(0, Math.min(nFrames - 1, Math.round(Number(i)) || 0));
    slider.value = String(current);
    describe(frames[current], current);
    draw();
  }

  // Controls.
  $("title").textContent = D.title;
  slider.max = String(nFrames - 1);
  slider.addEventListener("input", () => setFrame(slider.value));
  $("scale").addEventListener("change", e => { exaggerate = Number(e.target.value) || 1; draw(); });
  $("colour").addEventListener("change", e => { colourOn = e.target.checked; legendRamp(); draw(); });
  let timer = null;
  const play = $("play");
  function stop() { clearInterval(timer); timer = null; play.innerHTML = "&#9654;"; }
  play.addEventListener("click", () => {
    if (timer) { stop(); return; }
    if (current >= nFrames - 1) setFrame(0);
    play.innerHTML = "&#10074;&#10074;";
    timer = setInterval(() => { if (current >= nFrames - 1) stop(); else setFrame(current + 1); }, 700);
  });
  let drag = null;
  canvas.addEventListener("pointerdown", e => {
    drag = { x: e.clientX, y: e.clientY };
    canvas.setPointerCapture(e.pointerId);
    canvas.classList.add("dragging");
  });
  canvas.addEventListener("pointermove", e => {
    if (!drag) return;
    cam.az -= 0.01 * (e.clientX - drag.x);
    cam.el = Math.max(-1.5, Math.min(1.5, cam.el + 0.01 * (e.clientY - drag.y)));
    drag = { x: e.clientX, y: e.clientY };
    requestDraw();
  });
  const release = () => { drag = null; canvas.classList.remove("dragging"); };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("wheel", e => {
    e.preventDefault();
    cam.zoom = Math.max(0.2, Math.min(20, cam.zoom * Math.exp(-0.0015 * e.deltaY)));
    requestDraw();
  }, { passive: false });
  canvas.addEventListener("dblclick", () => { fitDefault(); layout(); requestDraw(); });
  new ResizeObserver(() => { layout(); requestDraw(); }).observe(canvas);

  // Legend.
  const legend = $("legend");
  const row = html => {
    const d = document.createElement("div");
    d.innerHTML = html;
    legend.append(d);
    return d;
  };
  row('<span class="swatch" style="background:' + rgb(OBJECT_RGB) + '"></span>object');
  const tipsRow = row("");
  D.colours.forEach(c => {
    const dot = document.createElement("span");
    dot.className = "dot"; dot.style.background = c;
    tipsRow.append(dot);
  });
  tipsRow.append(" fingertips");
  row("&#10230; force on the object, &prop; |F| (up to " + scene.fMax.toFixed(2) + " N)");
  const rampRow = row('deformation 0<span class="ramp" style="background:linear-gradient(to right,' +
    RAMP.map(s => rgb(s[1]) + " " + 100 * s[0] + "%").join(",") + ')"></span>' +
    (1e3 * dMax).toFixed(2) + " mm");
  rampRow.title = "displacement from the start, less the mean (rigid) shift";
  function legendRamp() { rampRow.style.display = colourOn && dMax > 0 ? "" : "none"; }
  legendRamp();
  row('<span class="swatch" style="background:rgba(120,132,148,0.3)"></span>table, z = 0');

  window.softgraspView = {
    frames: nFrames,
    held: heldIndex,
    get frame() { return current; },
    setFrame: setFrame,
    redraw: draw,
    get drawCount() { return drawCount; },
    get lastDrawMs() { return lastDrawMs; },
  };

  fitDefault();
  layout();
  setFrame(0);
  document.body.dataset.ready = "1";
})();
