// The page script of `softgrasp view` (softgrasp.viz.view inlines it after three.js, the global THREE).
// Data format (softgrasp.view/2), SI units: `nodes` boundary nodes, `tris` flat node triples (outward
// when `closed`), `frames[k]` with `pos` (node coordinates in whole micrometres, frame 0 absolute and
// every later frame the difference to the previous one), `centres` [m], `forces` [N] (of each
// fingertip on the object), `normals` (their normal components [N]), `hand` (the hand's link polylines,
// flat [m]; polyline j is points hand_lines[j] to hand_lines[j + 1] - 1), `deformation` (each node's
// displacement from the start less the best-fit rigid motion, in thousandths of `deformation_max_m`),
// `travel_mm` and `held`; `radius` of the fingertips [m], `fingers` names, `setpoints` (each finger's
// set-point [N], the normal force the force controller closes to; null when unknown), `colours`,
// default `view`.
"use strict";
(function () {
  const $ = id => document.getElementById(id);
  const D = JSON.parse($("softgrasp-data").textContent);
  const T = window.THREE;

  const BACKGROUND = 0xf3f4f6, HAND = "#4b5563", PALM = "#7b8494", TABLE = 0xc4c9d1;
  const OBJECT = [236, 230, 219];  // sRGB of the object where it has not moved
  // Displacement colour map (sRGB stops): the object's colour through amber and red to plum.
  const RAMP = [[0, OBJECT], [0.3, [246, 196, 106]], [0.65, [222, 90, 50]], [1, [116, 26, 86]]];
  const FOV = 35;  // vertical field of view [deg]
  const nNodes = D.nodes, nF = D.fingers.length, tipR = D.radius, lines = D.hand_lines;
  const nFrames = D.frames.length, heldIndex = D.frames.findIndex(f => f.held);

  function ramp(x) {
    for (let i = 1; i < RAMP.length; i++) {
      const [x0, c0] = RAMP[i - 1], [x1, c1] = RAMP[i];
      if (x <= x1) return c0.map((v, j) => v + (c1[j] - v) * (x - x0) / (x1 - x0));
    }
    return RAMP[RAMP.length - 1][1];
  }
  // 256 colours of the map in three.js's linear working space, for the vertex colours.
  const LUT = new Float32Array(3 * 256);
  for (let i = 0; i < 256; i++) {
    const c = ramp(i / 255), col = new T.Color().setRGB(c[0] / 255, c[1] / 255, c[2] / 255, T.SRGBColorSpace);
    LUT.set([col.r, col.g, col.b], 3 * i);
  }

  // Frames: node positions [m] decoded from the micrometre differences, the colour-map index of each
  // node's deformation and the forces' magnitudes.
  const frames = [], dMax = D.deformation_max_m;
  let fMax = 0;
  {
    const acc = new Float64Array(3 * nNodes);
    for (const f of D.frames) {
      const p = new Float32Array(3 * nNodes);
      for (let i = 0; i < p.length; i++) { acc[i] += f.pos[i]; p[i] = acc[i] * 1e-6; }
      const def = Uint8Array.from(f.deformation, x => Math.round(x * 255 / 1000));
      const mag = f.forces.map(v => Math.hypot(v[0], v[1], v[2]));
      for (const m of mag) fMax = Math.max(fMax, m);
      frames.push({ p: p, def: def, centres: f.centres, forces: f.forces, normals: f.normals, mag: mag,
                    hand: Float32Array.from(f.hand), held: f.held, travel: f.travel_mm });
    }
  }

  // Sizes: the object's radius at the start sets the arrows' and the table's; arrows are scaled by
  // the largest force of all frames, so that their lengths compare across the closing.
  const box0 = new T.Box3().setFromArray(frames[0].p);
  const objR = Math.max(0.5 * box0.getSize(new T.Vector3()).length(), 1e-4);
  const arrowMax = 0.7 * objR, shaftR = 0.17 * tipR, headR = 0.4 * tipR, headL = 1.1 * tipR;
  const linkR = 0.42 * tipR, palmR = 0.3 * tipR;

  // A force arrow's ends: pushing the fingertip from behind along the force, its point on the
  // fingertip's surface opposite the contact, its length proportional to the force; null for no force.
  function arrowEnds(f, i) {
    const m = f.mag[i];
    if (!(fMax > 0) || !(m > 1e-6 * fMax)) return null;
    const dir = new T.Vector3(...f.forces[i]).divideScalar(m);
    const tip = new T.Vector3(...f.centres[i]).addScaledVector(dir, -tipR);
    return { tip: tip, tail: tip.clone().addScaledVector(dir, -arrowMax * m / fMax), dir: dir };
  }

  // The sphere around everything drawn in any frame (object nodes, hand joints, fingertips, arrow
  // tails, each with its radius): the camera frames it whichever way it turns. Its centre starts at
  // the middle of the bounding box and moves towards the farthest point with shrinking steps, which
  // approaches the smallest enclosing sphere (Badoiu and Clarkson's iteration).
  const bounds = (() => {
    const pts = [], stride = Math.max(1, Math.floor(nNodes * nFrames / 20000));
    for (const f of frames) {
      for (let i = 0; i < 3 * nNodes; i += 3 * stride) pts.push([f.p[i], f.p[i + 1], f.p[i + 2], 0]);
      for (let i = 0; i < f.hand.length; i += 3) pts.push([f.hand[i], f.hand[i + 1], f.hand[i + 2], linkR]);
      f.centres.forEach((c, i) => {
        pts.push([c[0], c[1], c[2], tipR]);
        const a = arrowEnds(f, i);
        if (a) pts.push([a.tail.x, a.tail.y, a.tail.z, headR]);
      });
    }
    const box = new T.Box3(), v = new T.Vector3();
    for (const q of pts) box.expandByPoint(v.set(q[0], q[1], q[2]));
    const c = box.getCenter(new T.Vector3());
    const farthest = () => {
      let best = 0, R = 0;
      pts.forEach((q, k) => { const r = c.distanceTo(v.set(q[0], q[1], q[2])) + q[3]; if (r > R) { R = r; best = k; } });
      return [R, pts[best]];
    };
    let [R, far] = farthest(), centre = c.clone();
    for (let it = 1; it <= 100; it++) {
      c.lerp(v.set(far[0], far[1], far[2]), 1 / (it + 1));
      const [r, q] = farthest();
      far = q;
      if (r < R) { R = r; centre = c.clone(); }
    }
    return { centre: centre, R: 1.02 * R };
  })();

  // Renderer, scene, camera, lights.
  const canvas = $("view"), main = canvas.parentElement;
  let renderer;
  try {
    renderer = new T.WebGLRenderer({ canvas: canvas, antialias: true, preserveDrawingBuffer: true });
  } catch (e) {
    $("error").textContent = "This browser cannot draw WebGL, which this page needs (" + e.message + ").";
    $("error").style.display = "flex";
    document.body.dataset.ready = "error";
    return;
  }
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  const scene = new T.Scene();
  scene.background = new T.Color(BACKGROUND);
  const camera = new T.PerspectiveCamera(FOV, 1, 0.01 * bounds.R, 100 * bounds.R);
  camera.up.set(0, 0, 1);
  scene.add(camera);
  scene.add(new T.HemisphereLight(0xffffff, 0x8a8276, 1.0));
  const top = new T.DirectionalLight(0xffffff, 0.9);  // from above, fixed: tops lighter than sides
  top.position.set(0.3, -0.2, 1);
  scene.add(top);
  const headlight = new T.DirectionalLight(0xffffff, 1.4);  // turns with the camera: upper left, in front
  headlight.position.set(-0.7, 0.6, 1);
  headlight.target.position.set(0, 0, -1);
  camera.add(headlight, headlight.target);

  // The object's surface, flat-shaded (its facets as meshed): positions and colours change with the frame.
  const geometry = new T.BufferGeometry();
  const positions = new T.BufferAttribute(new Float32Array(3 * nNodes), 3).setUsage(T.DynamicDrawUsage);
  const colours = new T.BufferAttribute(new Float32Array(3 * nNodes), 3).setUsage(T.DynamicDrawUsage);
  geometry.setAttribute("position", positions);
  geometry.setAttribute("color", colours);
  geometry.setIndex(new T.BufferAttribute(Uint32Array.from(D.tris), 1));
  const object = new T.Mesh(geometry, new T.MeshStandardMaterial({
    vertexColors: true, flatShading: true, roughness: 0.85, metalness: 0, side: D.closed ? T.FrontSide : T.DoubleSide }));
  scene.add(object);

  // The table the object rests on during the closing (removed in the held state): a grid under it.
  const table = (() => {
    const raw = objR / 4, pow = Math.pow(10, Math.floor(Math.log10(raw)));
    const step = [1, 2, 5, 10].map(m => m * pow).find(g => g >= raw), n = 2 * Math.ceil(1.6 * objR / step);
    const g = new T.GridHelper(n * step, n, TABLE, TABLE);
    g.rotation.x = Math.PI / 2;
    g.position.set(box0.getCenter(new T.Vector3()).x, box0.getCenter(new T.Vector3()).y, box0.min.z);
    scene.add(g);
    return g;
  })();

  // Fingertips and force arrows.
  const unitCylinder = new T.CylinderGeometry(1, 1, 1, 20).translate(0, 0.5, 0);  // base at 0, along y
  const unitCone = new T.ConeGeometry(1, 1, 24).translate(0, 0.5, 0);
  const unitSphere = new T.SphereGeometry(1, 24, 16);
  const Y = new T.Vector3(0, 1, 0);
  const tips = [], arrows = [], labels = [];
  D.fingers.forEach((name, i) => {
    const colour = new T.Color(D.colours[i]);
    const tip = new T.Mesh(new T.SphereGeometry(tipR, 40, 24),
                           new T.MeshStandardMaterial({ color: colour, roughness: 0.35 }));
    const dark = new T.MeshStandardMaterial({ color: colour.clone().multiplyScalar(0.8), roughness: 0.5 });
    const arrow = new T.Group(), shaft = new T.Mesh(unitCylinder, dark), head = new T.Mesh(unitCone, dark);
    arrow.add(shaft, head);
    arrow.userData = { shaft: shaft, head: head };
    scene.add(tip, arrow);
    tips.push(tip);
    arrows.push(arrow);
    const label = document.createElement("div");
    label.className = "force";
    label.style.background = D.colours[i];
    $("labels").append(label);
    labels.push(label);
  });

  function placeArrow(arrow, a) {
    arrow.visible = a !== null;
    if (!a) return;
    const L = a.tip.distanceTo(a.tail), hl = Math.min(headL, 0.6 * L), k = hl / headL;
    arrow.position.copy(a.tail);
    arrow.quaternion.setFromUnitVectors(Y, a.dir);
    arrow.userData.shaft.scale.set(shaftR * k, L - hl, shaftR * k);
    arrow.userData.head.position.set(0, L - hl, 0);
    arrow.userData.head.scale.set(headR * k, hl, headR * k);
  }

  // The hand: each link a capsule (a cylinder between joint spheres), the palm outline thinner.
  const hand = new T.Group(), links = [], joints = [];
  {
    const linkMat = new T.MeshStandardMaterial({ color: HAND, roughness: 0.45, metalness: 0.25 });
    const palmMat = new T.MeshStandardMaterial({ color: PALM, roughness: 0.5, metalness: 0.2 });
    for (let j = 0; j + 1 < lines.length; j++) {
      const r = j === 0 ? palmR : linkR, mat = j === 0 ? palmMat : linkMat;
      for (let p = lines[j]; p < lines[j + 1]; p++) {
        if (p + 1 < lines[j + 1]) {
          const m = new T.Mesh(unitCylinder, mat);
          m.userData = { a: p, b: p + 1, r: r };
          links.push(m);
        }
        const s = new T.Mesh(unitSphere, mat);
        s.scale.setScalar(r);
        s.userData = { a: p };
        joints.push(s);
      }
    }
    if (joints.length) hand.add(...links, ...joints);
    scene.add(hand);
  }
  function placeHand(points) {
    const a = new T.Vector3(), b = new T.Vector3();
    for (const m of links) {
      a.fromArray(points, 3 * m.userData.a);
      b.fromArray(points, 3 * m.userData.b);
      const L = a.distanceTo(b);
      m.visible = L > 0;
      if (!m.visible) continue;
      m.position.copy(a);
      m.quaternion.setFromUnitVectors(Y, b.sub(a).divideScalar(L));
      m.scale.set(m.userData.r, L, m.userData.r);
    }
    for (const s of joints) s.position.fromArray(points, 3 * s.userData.a);
  }

  // Camera fit: the bounding sphere fills the smaller of the two fields of view.
  const controls = new T.OrbitControls(camera, canvas);
  let touched = false, current = heldIndex, colourOn = true;
  function fit() {
    const aspect = camera.aspect, half = Math.PI * FOV / 360;
    const halfMin = Math.min(half, Math.atan(Math.tan(half) * aspect));
    const dist = bounds.R / Math.sin(halfMin);
    const az = D.view.azimuth_deg * Math.PI / 180, el = D.view.elevation_deg * Math.PI / 180;
    controls.target.copy(bounds.centre);
    camera.position.set(Math.cos(el) * Math.cos(az), Math.cos(el) * Math.sin(az), Math.sin(el))
      .multiplyScalar(dist).add(bounds.centre);
    controls.minDistance = 0.15 * bounds.R;
    controls.maxDistance = 8 * dist;
    camera.far = controls.maxDistance + 2 * bounds.R;
    camera.updateProjectionMatrix();
    controls.update();
    touched = false;
  }
  function resize() {
    const w = Math.max(1, main.clientWidth), h = Math.max(1, main.clientHeight);
    renderer.setSize(w, h, false);
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
    if (!touched) fit();
    render();
  }

  function render() {
    renderer.render(scene, camera);
    // Force labels beside the arrows' tails (hidden behind the camera or without a force).
    const f = frames[current], w = main.clientWidth, h = main.clientHeight, v = new T.Vector3();
    labels.forEach((label, i) => {
      const a = arrowEnds(f, i);
      if (a) v.copy(a.tail).addScaledVector(a.dir, -0.9 * headR - 0.06 * objR).project(camera);
      const show = a !== null && v.z < 1;
      label.style.display = show ? "" : "none";
      if (!show) return;
      label.style.left = ((v.x + 1) / 2 * w).toFixed(1) + "px";
      label.style.top = ((1 - v.y) / 2 * h).toFixed(1) + "px";
    });
  }

  function newton(x) { return x.toFixed(3) + " N"; }
  function setFrame(k) {
    k = Math.max(0, Math.min(nFrames - 1, Math.round(Number(k)) || 0));
    current = k;
    slider.value = String(k);
    const f = frames[k];
    positions.array.set(f.p);
    positions.needsUpdate = true;
    for (let i = 0; i < nNodes; i++) {
      const c = colourOn ? f.def[i] : 0;
      colours.array.set(LUT.subarray(3 * c, 3 * c + 3), 3 * i);
    }
    colours.needsUpdate = true;
    geometry.computeBoundingSphere();
    f.centres.forEach((c, i) => tips[i].position.set(...c));
    arrows.forEach((arrow, i) => placeArrow(arrow, arrowEnds(f, i)));
    labels.forEach((label, i) => {
      label.textContent = D.fingers[i] + " " + newton(f.normals[i])
        + (D.setpoints ? " (set-point " + newton(D.setpoints[i]) + ")" : "");
    });
    placeHand(f.hand);
    table.visible = !f.held;
    $("frame-label").textContent = f.held ? "held" : k === 0 ? "start" : "increment " + k + " / " + (heldIndex - 1);
    const readout = $("readout"), travel = f.travel === null ? "" : "travel " + f.travel.toFixed(3) + " mm";
    readout.textContent = (f.held ? "held by the fingers alone (table removed)" + (travel ? ", " : "") : "")
      + travel + "; normal force (|force|):  ";
    f.normals.forEach((n, i) => {
      const span = document.createElement("span"), dot = document.createElement("span");
      span.className = "finger";
      dot.className = "dot";
      dot.style.background = D.colours[i];
      span.append(dot, D.fingers[i] + " " + newton(n) + " (" + newton(f.mag[i]) + ")");
      readout.append(span, i + 1 < nF ? ",  " : "");
    });
    render();
  }

  // Legend: the colour bar of the displacement, the fingertips, the hand and the arrows.
  function legend() {
    const mm = dMax * 1e3, um = mm < 0.1, unit = um ? " \u00b5m" : " mm", s = um ? 1e3 : 1;
    const fmt = x => (x * s).toPrecision(2).replace(/\.?0+$/, "");
    const stops = RAMP.map(([x, c]) => "rgb(" + c.map(Math.round).join(",") + ") " + (100 * x) + "%");
    const box = $("legend");
    box.replaceChildren();
    const row = html => { const d = document.createElement("div"); d.className = "row"; d.innerHTML = html; box.append(d); return d; };
    if (colourOn) {
      row("deformation: displacement from the start").title =
        "each node's displacement from the start of the closing less the rigid motion that fits best";
      row("less the best-fitting rigid motion");
      const bar = row("");
      bar.className = "bar";
      bar.style.background = "linear-gradient(to right, " + stops.join(", ") + ")";
      const ticks = row("");
      ticks.className = "ticks";
      for (const x of [0, 0.5, 1]) { const t = document.createElement("span"); t.textContent = fmt(x * mm) + (x === 1 ? unit : ""); ticks.append(t); }
    }
    D.fingers.forEach((name, i) => {
      const r = row("<span class=\"swatch\"></span>");
      r.firstChild.style.background = D.colours[i];
      r.append("fingertip " + name);
    });
    if (links.length) row("<span class=\"swatch\" style=\"background:" + HAND + "\"></span>hand links");
    row("arrows: force on the object (length \u221d force),");
    row(D.setpoints ? "labelled with its normal component and the set-point" : "labelled with its normal component");
  }

  // Controls.
  const slider = $("frame");
  slider.max = String(nFrames - 1);
  slider.addEventListener("input", () => setFrame(slider.value));
  let timer = null;
  const stop = () => { if (timer !== null) { clearInterval(timer); timer = null; $("play").innerHTML = "&#9654;"; } };
  $("play").addEventListener("click", () => {
    if (timer !== null) { stop(); return; }
    if (current >= heldIndex) setFrame(0);
    $("play").innerHTML = "&#10074;&#10074;";
    timer = setInterval(() => { if (current >= heldIndex) stop(); else setFrame(current + 1); }, 350);
  });
  $("colour").addEventListener("change", e => { colourOn = e.target.checked; legend(); setFrame(current); });
  $("hand").addEventListener("change", e => { hand.visible = e.target.checked; render(); });
  $("hand").parentElement.style.display = links.length ? "" : "none";
  controls.addEventListener("change", render);
  controls.addEventListener("start", () => { touched = true; stop(); });
  canvas.addEventListener("dblclick", () => { fit(); render(); });
  new ResizeObserver(resize).observe(main);
  $("title").textContent = D.title;

  window.softgraspView = {
    frames: nFrames,
    held: heldIndex,
    get frame() { return current; },
    setFrame: setFrame,
    handLinks: links.length,
    showHand: on => { $("hand").checked = !!on; hand.visible = !!on; render(); },
    resetView: () => { fit(); render(); },
  };
  legend();
  camera.aspect = Math.max(1, main.clientWidth) / Math.max(1, main.clientHeight);
  renderer.setSize(Math.max(1, main.clientWidth), Math.max(1, main.clientHeight), false);
  fit();
  setFrame(heldIndex);
  document.body.dataset.ready = "1";
})();
