// The animated viewer of dqskin's compare report (see dqskin/report/viewer.py for the data).
// Reads #dqv-config (JSON) and #dqv-data (base64 zlib blob), plays every method in sync in one
// three.js scene with one orbit camera. Exposes window.dqskinViewer for tests.
(function () {
  "use strict";
  const api = { ready: false, error: null, renders: 0 };
  window.dqskinViewer = api;
  const $ = (id) => document.getElementById(id);
  const status = (text) => { $("dqv-status").textContent = text; };

  function fail(err) {
    api.error = String(err && err.message ? err.message : err);
    status("viewer unavailable: " + api.error);
  }

  function base64Bytes(text) {
    const bin = atob(text.trim());
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  async function inflate(bytes) {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("deflate"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  function section(raw, meta, name) {
    const [at, n] = meta.sections[name];
    return raw.subarray(at, at + n);
  }

  // uint16 values stored as a low-byte plane then a high-byte plane
  function unplane(bytes) {
    const n = bytes.length >> 1, out = new Uint16Array(n);
    for (let i = 0; i < n; i++) out[i] = bytes[i] | (bytes[n + i] << 8);
    return out;
  }

  function decode(raw, meta) {
    const V3 = meta.vertices * 3, F = meta.frames, M = meta.methods.length;
    const faceBytes = section(raw, meta, "faces");
    const faces = new Uint32Array(faceBytes.slice().buffer);
    const rest = unplane(section(raw, meta, "rest"));
    const q = unplane(section(raw, meta, "positions"));  // Uint16Array: sums wrap mod 2^16
    for (let f = 1; f < F; f++) {
      const a = f * V3, b = a - V3;
      for (let k = 0; k < V3; k++) q[a + k] += q[b + k];
    }
    for (let m = 1; m < M; m++) {
      for (let f = 0; f < F; f++) {
        const a = (m * F + f) * V3, b = f * V3;
        for (let k = 0; k < V3; k++) q[a + k] += q[b + k];
      }
    }
    const heat = meta.sections.heat ? section(raw, meta, "heat") : null;
    return { faces, rest, q, heat };
  }

  function setup(cfg, data) {
    const meta = cfg.meta, V = meta.vertices, V3 = V * 3, F = meta.frames;
    const M = meta.methods.length, step = meta.step, origin = meta.origin;
    const canvas = $("dqv-canvas"), stage = $("dqv-stage");
    const renderer = new THREE.WebGLRenderer({ canvas, antialias: true,
                                               preserveDrawingBuffer: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    renderer.setClearColor(0xfafafa, 1);
    const scene = new THREE.Scene();
    const up = cfg.up_axis === "Z" ? new THREE.Vector3(0, 0, 1) : new THREE.Vector3(0, 1, 0);
    const front = cfg.up_axis === "Z" ? new THREE.Vector3(0, -1, 0) : new THREE.Vector3(0, 0, 1);
    const right = new THREE.Vector3(1, 0, 0);

    // bounds of everything (grid units), for the layout and the camera
    const lo = [65535, 65535, 65535], hi = [0, 0, 0];
    for (const arr of [data.q, data.rest]) {
      for (let i = 0; i < arr.length; i += 3) {
        for (let c = 0; c < 3; c++) {
          const v = arr[i + c];
          if (v < lo[c]) lo[c] = v;
          if (v > hi[c]) hi[c] = v;
        }
      }
    }
    const world = (c, v) => origin[c] + v * step;
    const center = new THREE.Vector3(world(0, (lo[0] + hi[0]) / 2), world(1, (lo[1] + hi[1]) / 2),
                                     world(2, (lo[2] + hi[2]) / 2));
    const size = new THREE.Vector3((hi[0] - lo[0]) * step, (hi[1] - lo[1]) * step,
                                   (hi[2] - lo[2]) * step);
    const spacing = Math.max(size.x * 1.15, 1e-6);

    const index = new THREE.BufferAttribute(data.faces, 1);
    // 256 × [r, g, b] sRGB in 0..1 → linear (three.js converts its output back to sRGB)
    const toLinear = (c) => (c <= 0.04045 ? c / 12.92 : Math.pow((c + 0.055) / 1.055, 2.4));
    const lut = cfg.colormap.map((rgb) => rgb.map(toLinear));
    const groups = [], posed = [], ghosts = [];
    for (let m = 0; m < M; m++) {
      const group = new THREE.Group();
      const geo = new THREE.BufferGeometry();
      geo.setIndex(index);
      geo.setAttribute("position", new THREE.BufferAttribute(new Float32Array(V3), 3));
      geo.setAttribute("color", new THREE.BufferAttribute(new Float32Array(V3), 3));
      const mat = new THREE.MeshLambertMaterial({ color: cfg.colors[m], side: THREE.DoubleSide });
      const mesh = new THREE.Mesh(geo, mat);
      mesh.frustumCulled = false;
      group.add(mesh);
      const ghostGeo = new THREE.BufferGeometry();
      ghostGeo.setIndex(index);
      const restPos = new Float32Array(V3);
      for (let k = 0; k < V3; k++) restPos[k] = origin[k % 3] + data.rest[k] * step;
      ghostGeo.setAttribute("position", new THREE.BufferAttribute(restPos, 3));
      ghostGeo.computeVertexNormals();
      const ghost = new THREE.Mesh(ghostGeo, new THREE.MeshLambertMaterial({
        color: 0x888888, transparent: true, opacity: 0.25, depthWrite: false,
        side: THREE.DoubleSide, polygonOffset: true, polygonOffsetFactor: 2,
        polygonOffsetUnits: 2 }));
      ghost.frustumCulled = false;
      ghost.visible = false;
      group.add(ghost);
      scene.add(group);
      groups.push(group); posed.push(mesh); ghosts.push(ghost);
    }

    // orthographic: the methods side by side are seen from the same direction
    const camera = new THREE.OrthographicCamera(-1, 1, 1, -1, 1e-3, 1e6);
    camera.up.copy(up);
    const light = new THREE.DirectionalLight(0xffffff, 2.2);
    light.position.set(-0.4, 0.6, 1.0);
    camera.add(light);
    scene.add(camera);
    scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 1.1));
    const controls = new THREE.OrbitControls(camera, canvas);
    controls.enableDamping = false;
    controls.addEventListener("change", () => { dirty = true; });

    const state = { frame: 0, playing: true, heat: false, rest: false, overlay: false,
                    visible: new Array(M).fill(true), ab: false, pair: [0, Math.min(1, M - 1)],
                    side: 0 };
    let dirty = true;

    // the methods drawn: in A/B mode the pair's current side alone, else the visible ones
    function shown() {
      if (state.ab) return [state.pair[state.side]];
      const out = [];
      for (let m = 0; m < M; m++) if (state.visible[m]) out.push(m);
      return out;
    }

    function layout() {
      const on = shown(), n = on.length, together = state.overlay || state.ab;
      const width = together ? size.x : spacing * Math.max(n - 1, 0) + size.x;
      for (let m = 0; m < M; m++) {
        const k = on.indexOf(m);
        groups[m].visible = k >= 0;
        const dx = together || k < 0 ? 0 : spacing * (k - (n - 1) / 2);
        groups[m].position.copy(right).multiplyScalar(dx);
        const faded = state.overlay && !state.ab && k > 0;
        const mat = posed[m].material;
        mat.transparent = faded;
        mat.opacity = faded ? 0.55 : 1.0;
        mat.needsUpdate = true;
      }
      const tall = up.y ? size.y : size.z;
      const dist = 4 * Math.max(size.length(), width, 1e-6);
      const dir = front.clone().multiplyScalar(0.94).add(up.clone().multiplyScalar(0.34));
      camera.position.copy(center).add(dir.normalize().multiplyScalar(dist));
      camera.near = dist / 100; camera.far = dist * 4;
      camera.zoom = 1;
      frameHalfHeight = 0.55 * Math.max(tall, width / aspect());
      project();
      controls.target.copy(center);
      controls.update();
      dirty = true;
    }

    let frameHalfHeight = 1;
    const aspect = () => Math.max(stage.clientWidth, 1) / Math.max(stage.clientHeight, 1);
    function project() {
      const h = frameHalfHeight, a = aspect();
      camera.left = -h * a; camera.right = h * a; camera.top = h; camera.bottom = -h;
      camera.updateProjectionMatrix();
    }

    function resize() {
      renderer.setSize(Math.max(stage.clientWidth, 1), Math.max(stage.clientHeight, 1), false);
      project();
      dirty = true;
    }

    function showFrame(f) {
      for (let m = 0; m < M; m++) {
        const geo = posed[m].geometry, pos = geo.attributes.position.array;
        const base = (m * F + f) * V3;
        for (let k = 0; k < V3; k += 3) {
          pos[k] = origin[0] + data.q[base + k] * step;
          pos[k + 1] = origin[1] + data.q[base + k + 1] * step;
          pos[k + 2] = origin[2] + data.q[base + k + 2] * step;
        }
        geo.attributes.position.needsUpdate = true;
        geo.computeVertexNormals();
        if (state.heat && data.heat) {
          const col = geo.attributes.color.array, h = data.heat;
          for (let v = 0; v < V; v++) {
            const c = lut[h[f * V + v]];
            col[3 * v] = c[0]; col[3 * v + 1] = c[1]; col[3 * v + 2] = c[2];
          }
          geo.attributes.color.needsUpdate = true;
        }
      }
      state.frame = f;
      $("dqv-frame").value = String(f);
      $("dqv-time").textContent = `t = ${fmt(cfg.times[f])} (frame ${f + 1} of ${F})`;
      dirty = true;
    }

    function setHeat(on) {
      state.heat = Boolean(on) && Boolean(data.heat);
      for (const mesh of posed) {
        mesh.material.vertexColors = state.heat;
        mesh.material.color.set(state.heat ? 0xffffff : cfg.colors[posed.indexOf(mesh)]);
        mesh.material.needsUpdate = true;
      }
      $("dqv-heat").checked = state.heat;
      showFrame(state.frame);
      legend();
    }

    // one box per method (show/hide), built once
    const boxes = meta.methods.map((_, m) => {
      const label = document.createElement("label");
      const box = document.createElement("input");
      box.type = "checkbox"; box.checked = true; box.dataset.method = String(m);
      box.addEventListener("change", () => setVisible(m, box.checked));
      const swatch = document.createElement("span");
      swatch.className = "sw"; swatch.style.background = cfg.colors[m];
      label.append(box, swatch, cfg.labels[m]);
      $("dqv-methods").append(label);
      return box;
    });
    for (const id of ["dqv-a", "dqv-b"]) {
      cfg.labels.forEach((text, m) => {
        const opt = document.createElement("option");
        opt.value = String(m); opt.textContent = text;
        $(id).append(opt);
      });
    }
    $("dqv-a").value = String(state.pair[0]);
    $("dqv-b").value = String(state.pair[1]);

    function legend() {
      const note = document.createElement("span");
      note.className = "note";
      note.textContent = state.ab
        ? `A/B: ${cfg.labels[state.pair[state.side]]} (${state.side ? "B" : "A"}); flip: F`
        : state.overlay ? "overlaid (first opaque)" : "left to right";
      const parts = [note];
      if (state.heat) {
        const heat = document.createElement("span");
        heat.textContent = `heat: ${cfg.heat_label}, 0 – ` +
          (cfg.heat_max === null || cfg.heat_max === undefined ? fmt(meta.heat_max)
                                                                : `${fmt(cfg.heat_max)}${cfg.heat_unit}`);
        parts.push(heat);
      }
      $("dqv-legend").replaceChildren(...parts);
      $("dqv-flip").disabled = !state.ab;
    }

    function setVisible(m, on) {
      state.visible[m] = Boolean(on);
      boxes[m].checked = state.visible[m];
      layout(); legend();
    }

    function setAB(on, a, b) {
      if (a !== undefined) state.pair[0] = Math.max(0, Math.min(M - 1, a | 0));
      if (b !== undefined) state.pair[1] = Math.max(0, Math.min(M - 1, b | 0));
      state.ab = Boolean(on) && M > 1;
      state.side = 0;
      $("dqv-ab").checked = state.ab;
      $("dqv-a").value = String(state.pair[0]);
      $("dqv-b").value = String(state.pair[1]);
      layout(); legend();
    }

    function flip() {
      if (!state.ab) return;
      state.side = 1 - state.side;
      layout(); legend();
    }

    const fmt = (x) => (Math.abs(x) >= 1e4 || (Math.abs(x) < 1e-3 && x !== 0)
      ? x.toExponential(3) : String(Number(x.toPrecision(4))));

    // playback: clip time advances in real time at the asset's rate, looping
    const t0 = cfg.times[0], t1 = cfg.times[F - 1];
    let clip = t0, last = null;
    function tick(now) {
      if (state.playing && F > 1) {
        if (last !== null) {
          clip += ((now - last) / 1000) * cfg.fps;
          if (clip > t1) clip = t0 + ((clip - t0) % Math.max(t1 - t0, 1e-9));
        }
        let f = 0;
        while (f + 1 < F && cfg.times[f + 1] <= clip) f++;
        if (f !== state.frame) showFrame(f);
      }
      last = now;
      if (dirty) {
        renderer.render(scene, camera);
        api.renders++;
        dirty = false;
      }
      requestAnimationFrame(tick);
    }

    function setPlaying(on) {
      state.playing = Boolean(on);
      clip = cfg.times[state.frame];
      $("dqv-play").textContent = state.playing ? "Pause" : "Play";
    }

    const slider = $("dqv-frame");
    slider.max = String(F - 1);
    slider.addEventListener("input", () => { setPlaying(false); showFrame(Number(slider.value)); });
    $("dqv-play").addEventListener("click", () => setPlaying(!state.playing));
    $("dqv-heat").disabled = !data.heat;
    $("dqv-heat").addEventListener("change", (e) => setHeat(e.target.checked));
    $("dqv-rest").addEventListener("change", (e) => {
      state.rest = e.target.checked;
      for (const g of ghosts) g.visible = state.rest;
      dirty = true;
    });
    $("dqv-overlay").addEventListener("change", (e) => {
      state.overlay = e.target.checked; layout(); legend();
    });
    $("dqv-ab").disabled = M < 2;
    $("dqv-ab").addEventListener("change", (e) => setAB(e.target.checked));
    $("dqv-a").addEventListener("change", (e) => setAB(state.ab, Number(e.target.value)));
    $("dqv-b").addEventListener("change", (e) => setAB(state.ab, undefined,
                                                         Number(e.target.value)));
    $("dqv-flip").addEventListener("click", flip);
    document.addEventListener("keydown", (e) => {
      if ((e.key === "f" || e.key === "F") && !e.ctrlKey && !e.metaKey && !e.altKey) flip();
    });
    const worst = $("dqv-worst");
    if (cfg.worst.length) worst.append("worst frames: ");
    for (const w of cfg.worst) {
      const b = document.createElement("button");
      b.type = "button";
      b.textContent = `t = ${fmt(w.time)}`;
      b.title = w.why;
      b.addEventListener("click", () => { setPlaying(false); showFrame(nearest(w.time)); });
      worst.append(b, " ");
    }
    function nearest(t) {
      let best = 0;
      for (let f = 1; f < F; f++) {
        if (Math.abs(cfg.times[f] - t) < Math.abs(cfg.times[best] - t)) best = f;
      }
      return best;
    }
    window.addEventListener("resize", () => { resize(); layout(); });

    resize();
    layout();
    legend();
    showFrame(0);
    Object.assign(api, {
      frameCount: F,
      frame: () => state.frame,
      setFrame: (f) => { setPlaying(false); showFrame(Math.max(0, Math.min(F - 1, f | 0))); },
      setPlaying, playing: () => state.playing,
      setHeat, heat: () => state.heat,
      setRest: (on) => { $("dqv-rest").checked = on;
                         $("dqv-rest").dispatchEvent(new Event("change")); },
      setOverlay: (on) => { $("dqv-overlay").checked = on;
                            $("dqv-overlay").dispatchEvent(new Event("change")); },
      worstFrame: (i) => nearest(cfg.worst[i].time),
      positions: (m) => Array.from(posed[m].geometry.attributes.position.array),
      offset: (m) => groups[m].position.toArray(),
      setVisible, visible: () => state.visible.slice(),
      setAB, flip, shown: () => shown(),
      restPositions: () => Array.from(ghosts[0].geometry.attributes.position.array),
      canvas,
    });
    api.ready = true;
    status(`${M} methods × ${F} frames, ${V} vertices; drag to orbit, wheel to zoom`);
    requestAnimationFrame(tick);
  }

  async function main() {
    const cfg = JSON.parse($("dqv-config").textContent);
    const raw = await inflate(base64Bytes($("dqv-data").textContent));
    const data = decode(raw, cfg.meta);
    setup(cfg, data);
  }

  function start() {
    if (typeof THREE === "undefined") { fail("three.js did not load"); return; }
    if (typeof DecompressionStream === "undefined") {
      fail("this browser lacks DecompressionStream"); return;
    }
    main().catch(fail);
  }
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();
