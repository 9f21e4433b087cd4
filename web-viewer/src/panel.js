// One session on screen: its WebSocket, its surface, the three.js view and the heads-up
// panel. The viewer only watches: it never sends anything that moves a tool.

import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { decodeFrame, encodeRequest } from './protocol.js';
import { Surface } from './surface.js';
import { TimelineCurves } from './curves.js';

// Colours per material id (0 = skin); back faces show the underside of the tissue.
const MATERIAL_COLOURS = [0xe7b49c, 0xf2d16b, 0xb4473c, 0xc98a5a, 0x8e3b5f, 0x6d2f2a, 0xa5605a, 0xd89f8f];
const BACK_COLOUR = 0x8a2c2c;
const LIP_COLOUR = 0xd01010;
const WALL_COLOUR = 0xa01818;
// The wound's walls are drawn this deep below the lips (a skin's thickness), m.
const WALL_DEPTH_M = 0.002;
// Force arrow: 1 N is drawn this long, m.
const ARROW_M_PER_N = 0.02;
const PLOT_SECONDS = 5;
// The planned incision (dashed, over the tissue).
const PLAN_COLOUR = 0x30e070;
// Warnings listed under the metrics.
const WARNINGS_SHOWN = 4;

/**
 * Puts forceps' two jaw meshes either side of the axis: `gap` (m) between their inner
 * flats where the server says (stopped on a grasped fold, or open where a gripper does
 * not squeeze), else open or closed by the button.
 */
function placeJaws(jaws, closed, gap) {
  const offset = typeof gap === 'number' ? gap / 2 + jaws.halfThickness : closed ? jaws.closed : jaws.open;
  jaws.meshes.forEach((mesh, k) => {
    const sign = k === 0 ? -1 : 1;
    mesh.position.set(jaws.alongX ? 0 : -sign * offset, jaws.alongX ? sign * offset : 0, 0);
  });
}

export class SessionPanel {
  /**
   * @param {HTMLElement} container where the panel goes
   * @param {{id: string, token: string, onClose: Function, onGone: Function}} options
   */
  constructor(container, { id, token, controlToken, onClose, onGone }) {
    this.id = id;
    this.token = token;
    // Only replays get one: it drives their playback (never a tool).
    this.controlToken = controlToken;
    this.playback = null;
    this.onGone = onGone;
    this.surface = new Surface();
    this.state = 'connecting';
    this.stats = null;
    this.tools = [];
    this.toolInfo = [];
    this.forceHistory = []; // [ms, |F|]
    this.resyncs = 0;
    this.attempt = 0;
    this.latencyMs = null;
    this.errors = [];
    this.closed = false;
    this.wireframe = false;
    this.buildDom(container, onClose);
    this.buildScene();
    this.connect();
  }

  buildDom(container, onClose) {
    const el = document.createElement('section');
    el.className = 'panel';
    el.dataset.session = this.id;
    // A fixed template: every text from the server or the address bar is set below as
    // text, never as markup.
    el.innerHTML = `
      <header>
        <span class="title">session <code class="id"></code> <span class="scene"></span></span>
        <span class="state" data-role="state">connecting…</span>
        <button data-role="reset" title="Reset the view">Reset view</button>
        <button data-role="report" title="Download the session's assessment as a printable page">Report</button>
        <label><input type="checkbox" data-role="wire"> wireframe</label>
        <button data-role="close" title="Close this panel">✕</button>
      </header>
      <div class="view"><canvas></canvas><div class="legend"></div>
        <div class="hud">
          <dl>
            <dt>status</dt><dd data-role="status">–</dd>
            <dt>physics</dt><dd data-role="rate">–</dd>
            <dt>p99 step</dt><dd data-role="p99">–</dd>
            <dt>missed</dt><dd data-role="missed">–</dd>
            <dt>force</dt><dd data-role="force">–</dd>
            <dt>cuts</dt><dd data-role="cuts">–</dd>
            <dt>incision</dt><dd data-role="incision">–</dd>
            <dt>triangles</dt><dd data-role="triangles">–</dd>
            <dt>latency</dt><dd data-role="latency">–</dd>
          </dl>
          <canvas class="plot" width="260" height="70" title="|force| over the last ${PLOT_SECONDS} s"></canvas>
          <div class="task" data-role="task" hidden>
            <p class="task-text" data-role="task-text"></p>
            <dl>
              <dt>score</dt><dd data-role="score">–</dd>
              <dt>verdict</dt><dd data-role="verdict">–</dd>
              <dt>coverage</dt><dd data-role="coverage">–</dd>
              <dt>deviation</dt><dd data-role="deviation">–</dd>
              <dt>depth error</dt><dd data-role="depth">–</dd>
              <dt>time</dt><dd data-role="time">–</dd>
              <dt>strokes</dt><dd data-role="strokes">–</dd>
              <dt>path</dt><dd data-role="path">–</dd>
              <dt>peak force</dt><dd data-role="peak">–</dd>
              <dt data-role="grip-label" hidden>peak grip</dt><dd data-role="grip" hidden>–</dd>
              <dt>no-go</dt><dd data-role="nogo">–</dd>
            </dl>
            <ul class="warnings" data-role="warnings"></ul>
          </div>
        </div>
      </div>
      <div class="timeline" hidden>
        <button data-role="play" title="Play / pause">▶</button>
        <input type="range" data-role="scrub" min="0" max="0" value="0" step="1">
        <span data-role="position">–</span>
        <select data-role="speed" title="Replay speed">
          <option value="0.25">¼×</option><option value="0.5">½×</option><option value="1" selected>1×</option><option value="2">2×</option><option value="4">4×</option>
        </select>
        <canvas class="curves" data-role="curves" width="900" height="64" title="The recording's largest force, score, coverage and deviation over time; click to go there"></canvas>
      </div>
`;
    el.querySelector('code.id').textContent = this.id;
    container.appendChild(el);
    this.el = el;
    this.canvas = el.querySelector('.view > canvas');
    this.plot = el.querySelector('canvas.plot');
    this.field = (role) => el.querySelector(`[data-role="${role}"]`);
    this.field('close').onclick = () => {
      this.dispose();
      onClose(this);
    };
    this.field('reset').onclick = () => this.resetView();
    this.field('report').onclick = () => this.downloadReport();
    this.field('wire').onchange = (e) => {
      this.wireframe = e.target.checked;
      this.front.material.wireframe = this.wireframe;
      this.back.visible = !this.wireframe;
    };
    el.querySelector('.legend').textContent = `force arrow: ${ARROW_M_PER_N * 100} cm = 1 N (force on the tool)`;
    const scrub = this.field('scrub');
    scrub.oninput = () => {
      this.scrubbing = true;
      this.field('position').textContent = this.positionText(Number(scrub.value));
    };
    scrub.onchange = async () => {
      await this.playbackRequest({ action: 'seek', step: Number(scrub.value) });
      this.scrubbing = false;
    };
    this.curves = new TimelineCurves(this.field('curves'), {
      load: () => this.loadTimeline(),
      seek: (step) => this.playbackRequest({ action: 'seek', step }),
    });
    this.field('play').onclick = () => this.playbackRequest({ action: this.playback?.playing ? 'pause' : 'play' });
    this.field('speed').onchange = (e) => this.playbackRequest({ action: 'speed', speed: Number(e.target.value) });
  }

  /** The printable report (docs/assessment.md), saved as a file of its own. */
  async downloadReport() {
    const response = await fetch(`/api/sessions/${encodeURIComponent(this.id)}/report`, { headers: { 'cutsim-token': this.token } });
    if (!response.ok) {
      this.errors.push(`report: HTTP ${response.status}`);
      this.setState(`report failed (HTTP ${response.status})`, this.state);
      return;
    }
    const url = URL.createObjectURL(await response.blob());
    const link = document.createElement('a');
    link.href = url;
    link.download = `cutsim-report-${this.id}.html`;
    document.body.appendChild(link);
    link.click();
    link.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10_000);
  }

  /** The replay's curves (null while it starts or after an error, which is kept). */
  async loadTimeline() {
    try {
      const response = await fetch(`/api/sessions/${encodeURIComponent(this.id)}/timeline`, { cache: 'no-store', headers: { 'cutsim-token': this.token } });
      if (response.ok) return await response.json();
      if (response.status !== 503) {
        this.errors.push(`timeline: HTTP ${response.status}`);
        this.curves.stop();
      }
    } catch (e) {
      this.errors.push(`timeline: ${e}`);
    }
    return null;
  }

  async playbackRequest(body) {
    const response = await fetch(`/api/sessions/${encodeURIComponent(this.id)}/playback`, {
      method: 'POST',
      headers: { 'content-type': 'application/json', 'cutsim-token': this.controlToken || '' },
      body: JSON.stringify(body),
    });
    if (!response.ok) this.errors.push(`playback ${body.action}: HTTP ${response.status} ${await response.text()}`);
  }

  positionText(step) {
    const total = this.playback?.total_steps ?? 0;
    const rate = this.rateHz || 1000;
    return `${(step / rate).toFixed(2)} / ${(total / rate).toFixed(2)} s`;
  }

  updateTimeline() {
    const p = this.playback;
    const bar = this.el.querySelector('.timeline');
    bar.hidden = !p;
    if (!p) return;
    this.curves.start();
    this.curves.setCursor(p.step);
    const scrub = this.field('scrub');
    scrub.max = String(p.total_steps);
    if (!this.scrubbing) {
      scrub.value = String(p.step);
      this.field('position').textContent = this.positionText(p.step);
    }
    this.field('play').textContent = p.playing ? '❚❚' : '▶';
  }

  buildScene() {
    this.renderer = new THREE.WebGLRenderer({ canvas: this.canvas, antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio);
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x20242a);
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.001, 10);
    this.camera.up.set(0, 0, 1);
    this.controls = new OrbitControls(this.camera, this.canvas);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x402020, 1.2));
    const sun = new THREE.DirectionalLight(0xffffff, 1.6);
    sun.position.set(0.3, -0.4, 1);
    this.scene.add(sun);

    this.geometry = new THREE.BufferGeometry();
    this.front = new THREE.Mesh(this.geometry, new THREE.MeshStandardMaterial({ vertexColors: true, roughness: 0.75, side: THREE.FrontSide }));
    this.back = new THREE.Mesh(this.geometry, new THREE.MeshStandardMaterial({ color: BACK_COLOUR, roughness: 0.9, side: THREE.BackSide }));
    this.lips = new THREE.LineSegments(new THREE.BufferGeometry(), new THREE.LineBasicMaterial({ color: LIP_COLOUR }));
    this.walls = new THREE.Mesh(new THREE.BufferGeometry(), new THREE.MeshStandardMaterial({ color: WALL_COLOUR, roughness: 0.8, side: THREE.DoubleSide }));
    this.scene.add(this.front, this.back, this.lips, this.walls);
    this.toolGroup = new THREE.Group();
    this.scene.add(this.toolGroup);

    this.resizeObserver = new ResizeObserver(() => this.resize());
    this.resizeObserver.observe(this.canvas.parentElement);
    this.resize();
    const loop = () => {
      if (this.closed) return;
      this.render();
      this.raf = requestAnimationFrame(loop);
    };
    loop();
  }

  resize() {
    const parent = this.canvas.parentElement;
    const w = Math.max(1, parent.clientWidth);
    const h = Math.max(1, parent.clientHeight);
    this.renderer.setSize(w, h, false);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
  }

  // ───────────── connection ─────────────

  connect() {
    if (this.closed) return;
    const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
    const ws = new WebSocket(`${scheme}://${location.host}/ws/sessions/${encodeURIComponent(this.id)}?token=${encodeURIComponent(this.token)}`);
    ws.binaryType = 'arraybuffer';
    this.ws = ws;
    this.setState(this.attempt ? `reconnecting (attempt ${this.attempt})…` : 'connecting…', 'connecting');
    ws.onopen = () => {
      this.attempt = 0;
    };
    ws.onmessage = (event) => {
      try {
        this.handle(decodeFrame(event.data));
      } catch (e) {
        this.errors.push(String(e));
        console.error('cutsim viewer:', e);
      }
    };
    ws.onclose = (event) => {
      if (this.closed) return;
      if (event.code === 1001 && event.reason === 'session closed') {
        this.setState('session closed', 'closed');
        return;
      }
      if (event.code === 1011) {
        this.setState(event.reason || 'the session failed', 'failed');
        return;
      }
      this.scheduleReconnect();
    };
  }

  /** Retries with exponential backoff; stops when the server no longer has the session. */
  async scheduleReconnect() {
    this.attempt += 1;
    const delay = Math.min(8000, 250 * 2 ** Math.min(this.attempt, 6));
    this.setState(`reconnecting in ${(delay / 1000).toFixed(1)} s (attempt ${this.attempt})…`, 'reconnecting');
    await new Promise((r) => setTimeout(r, delay));
    if (this.closed) return;
    try {
      const response = await fetch(`/api/sessions/${encodeURIComponent(this.id)}`, { cache: 'no-store', headers: { 'cutsim-token': this.token } });
      if (response.status === 404) {
        this.setState('this session no longer exists on the server (it restarted or the session was closed)', 'gone');
        this.onGone?.(this);
        return;
      }
    } catch {
      // The server is down: keep trying.
      this.scheduleReconnect();
      return;
    }
    this.connect();
  }

  setState(text, state) {
    this.state = state;
    const el = this.field('state');
    el.textContent = text;
    el.dataset.state = state;
  }

  handle(frame) {
    switch (frame.frame) {
      case 'hello':
        this.hello(frame.hello);
        break;
      case 'snapshot':
        if (this.surface.version >= 0) this.resyncs += 1;
        this.surface.loadSnapshot(frame.snapshot);
        if (!this.framed) {
          this.resetView();
          this.framed = true;
        }
        this.setState(this.resyncs ? `live (resynchronised ${this.resyncs}×)` : 'live', 'live');
        break;
      case 'delta':
        if (!this.surface.applyDelta(frame.delta)) {
          // A gap: ask for a fresh snapshot rather than show a wrong surface.
          this.ws.send(encodeRequest({ resync: {} }));
        }
        break;
      case 'positions':
        this.surface.applyPositions(frame.positions);
        break;
      case 'tools':
        this.tools = frame.tools.tools;
        this.recordForce();
        break;
      case 'stats':
        this.stats = frame.stats;
        this.playback = frame.stats.playback;
        // Sent only when the metrics changed: keep the last ones.
        if (frame.stats.assessment) this.setAssessment(frame.stats.assessment);
        this.latencyMs = Date.now() - frame.stats.server_unix_ms;
        break;
      default:
        break;
    }
  }

  hello(h) {
    const s = h.session;
    this.rateHz = s.rate_hz;
    this.playback = s.playback;
    const deformation = s.deformation_rate_hz ? `, deformation ${Math.round(s.deformation_rate_hz)} Hz` : '';
    this.el.querySelector('.scene').textContent = `— ${s.scene} (${s.model}, ${Math.round(s.rate_hz)} Hz${deformation})${s.playback ? ` — replay of ${s.playback.recorded_session}` : ''}`;
    this.toolInfo = s.tools;
    this.toolGroup.clear();
    this.toolMeshes = s.tools.map((t) => {
      let geometry;
      let jaws = null;
      if (t.jaw_opening_m > 0) {
        // Forceps: two jaws, each a plate, either side of the axis across their flats
        // (the tool frame's y for an edge along x); placed open or closed in updateTools.
        const alongX = Math.abs(t.edge?.x ?? 1) > 0.5;
        geometry = new THREE.BoxGeometry(alongX ? t.width_m : t.thickness_m, alongX ? t.thickness_m : t.width_m, t.length_m);
        jaws = { alongX, open: t.jaw_opening_m / 2 + t.thickness_m / 2, closed: t.thickness_m / 2, halfThickness: t.thickness_m / 2 };
      } else if (t.width_m > 0) {
        // A blade's plate: its width along its edge's direction (the tool frame's x or y).
        const alongX = Math.abs(t.edge?.x ?? 1) > 0.5;
        geometry = new THREE.BoxGeometry(alongX ? t.width_m : t.thickness_m, alongX ? t.thickness_m : t.width_m, t.length_m);
      } else if (t.round_tip) {
        // A ball end: a capsule whose lower cap's apex is the tip (three.js capsules
        // stand on y, their length between the caps' centres).
        geometry = new THREE.CapsuleGeometry(t.radius_m, Math.max(t.length_m - 2 * t.radius_m, 0), 8, 24);
        geometry.rotateX(Math.PI / 2);
      } else {
        geometry = new THREE.CylinderGeometry(t.radius_m, t.radius_m, t.length_m, 24);
        geometry.rotateX(Math.PI / 2); // three.js cylinders stand on y; our tools point along +z
      }
      geometry.translate(0, 0, t.length_m / 2); // from the tip upwards
      const material = new THREE.MeshStandardMaterial({ color: t.can_cut ? 0xc0c8d0 : 0x4a7bd0, metalness: 0.6, roughness: 0.3 });
      let mesh;
      if (jaws) {
        mesh = new THREE.Group();
        mesh.material = material;
        jaws.meshes = [new THREE.Mesh(geometry, material), new THREE.Mesh(geometry, material)];
        mesh.add(...jaws.meshes);
        placeJaws(jaws, false);
      } else {
        mesh = new THREE.Mesh(geometry, material);
      }
      mesh.visible = false;
      const arrow = new THREE.ArrowHelper(new THREE.Vector3(0, 0, 1), new THREE.Vector3(), 0.01, 0xffd030);
      arrow.visible = false;
      this.toolGroup.add(mesh, arrow);
      return { mesh, arrow, info: t, jaws };
    });
  }

  recordForce() {
    const now = performance.now();
    let magnitude = 0;
    for (const t of this.tools) {
      if (!t.active || !t.force_n) continue;
      magnitude = Math.max(magnitude, Math.hypot(t.force_n.x, t.force_n.y, t.force_n.z));
    }
    this.forceHistory.push([now, magnitude]);
    while (this.forceHistory.length && this.forceHistory[0][0] < now - PLOT_SECONDS * 1000) this.forceHistory.shift();
  }

  // ───────────── drawing ─────────────

  resetView() {
    const { lo, hi } = this.surface.bounds();
    if (!Number.isFinite(lo[0])) return;
    const centre = new THREE.Vector3((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
    const size = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 0.01);
    this.camera.position.set(centre.x - 0.2 * size, centre.y - 1.1 * size, centre.z + 1.0 * size);
    this.camera.near = size / 1000;
    this.camera.far = size * 100;
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(centre);
    this.controls.update();
  }

  updateGeometry() {
    const s = this.surface;
    if (s.topologyChanged || !this.positionArray || this.positionArray.length < s.slotCount * 3) {
      const capacity = Math.max(s.slotCount, 16) * 3;
      this.positionArray = new Float32Array(capacity);
      this.colourArray = new Float32Array(capacity);
      this.geometry.setAttribute('position', new THREE.BufferAttribute(this.positionArray, 3).setUsage(THREE.DynamicDrawUsage));
      this.geometry.setAttribute('color', new THREE.BufferAttribute(this.colourArray, 3));
      const colour = new THREE.Color();
      for (const v of s.vertices.values()) {
        colour.setHex(MATERIAL_COLOURS[v.material % MATERIAL_COLOURS.length]);
        this.colourArray.set([colour.r, colour.g, colour.b], v.slot * 3);
      }
      const index = new Uint32Array(s.triangles.size * 3);
      let k = 0;
      for (const t of s.triangles.values()) {
        index[k++] = s.vertices.get(t[0]).slot;
        index[k++] = s.vertices.get(t[1]).slot;
        index[k++] = s.vertices.get(t[2]).slot;
      }
      this.geometry.setIndex(new THREE.BufferAttribute(index, 1));
      this.lipKeys = s.lipEdges().map((key) => key.split(',').map(Number));
      s.topologyChanged = false;
      s.positionsChanged = true;
    }
    if (s.positionsChanged) {
      for (const v of s.vertices.values()) {
        this.positionArray[v.slot * 3] = v.x;
        this.positionArray[v.slot * 3 + 1] = v.y;
        this.positionArray[v.slot * 3 + 2] = v.z;
      }
      this.geometry.attributes.position.needsUpdate = true;
      this.geometry.computeVertexNormals();
      this.geometry.computeBoundingSphere();
      // Lips as lines, and the wound's walls: each lip edge extruded down the surface
      // normal by a skin's thickness.
      const normals = this.geometry.attributes.normal.array;
      const lip = new Float32Array(this.lipKeys.length * 6);
      const wall = new Float32Array(this.lipKeys.length * 18);
      this.lipKeys.forEach(([a, b], i) => {
        const va = s.vertices.get(a);
        const vb = s.vertices.get(b);
        if (!va || !vb) return;
        lip.set([va.x, va.y, va.z, vb.x, vb.y, vb.z], i * 6);
        const down = (v) => [v.x - WALL_DEPTH_M * normals[v.slot * 3], v.y - WALL_DEPTH_M * normals[v.slot * 3 + 1], v.z - WALL_DEPTH_M * normals[v.slot * 3 + 2]];
        const [ax, ay, az] = down(va);
        const [bx, by, bz] = down(vb);
        wall.set([va.x, va.y, va.z, vb.x, vb.y, vb.z, bx, by, bz, va.x, va.y, va.z, bx, by, bz, ax, ay, az], i * 18);
      });
      this.lips.geometry.setAttribute('position', new THREE.BufferAttribute(lip, 3));
      this.walls.geometry.setAttribute('position', new THREE.BufferAttribute(wall, 3));
      this.walls.geometry.computeVertexNormals();
      s.positionsChanged = false;
    }
  }

  updateTools() {
    if (!this.toolMeshes) return;
    for (const state of this.tools) {
      const tool = this.toolMeshes[state.tool];
      if (!tool) continue;
      const visible = state.active && state.pose;
      tool.mesh.visible = !!visible;
      tool.arrow.visible = false;
      if (!visible) continue;
      const p = state.pose.position_m;
      const q = state.pose.orientation;
      tool.mesh.position.set(p.x, p.y, p.z);
      tool.mesh.quaternion.set(q.x, q.y, q.z, q.w);
      if (tool.jaws) {
        // The button closes forceps' jaws (it cuts nothing), as far as what they grasp lets them.
        placeJaws(tool.jaws, !!state.cut, state.jaws_gap_m);
      } else {
        tool.mesh.material.emissive.setHex(state.cutting || state.cut ? 0x600000 : 0x000000);
      }
      const f = state.force_n;
      const magnitude = f ? Math.hypot(f.x, f.y, f.z) : 0;
      if (magnitude > 1e-6) {
        tool.arrow.position.set(p.x, p.y, p.z);
        tool.arrow.setDirection(new THREE.Vector3(f.x / magnitude, f.y / magnitude, f.z / magnitude));
        const length = magnitude * ARROW_M_PER_N;
        tool.arrow.setLength(length, Math.min(0.3 * length, 0.006), Math.min(0.15 * length, 0.003));
        tool.arrow.visible = true;
      }
    }
  }

  /** The trainee's metrics (docs/assessment.md), and the planned incision drawn once. */
  setAssessment(a) {
    this.assessment = a;
    if (!this.planLine && a.plan_points_m && a.plan_points_m.length >= 6) {
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute('position', new THREE.Float32BufferAttribute(a.plan_points_m, 3));
      // Drawn over the tissue (no depth test) so that the cut's lips never hide the plan.
      this.planLine = new THREE.Line(geometry, new THREE.LineDashedMaterial({ color: PLAN_COLOUR, dashSize: 0.002, gapSize: 0.001, depthTest: false }));
      this.planLine.computeLineDistances();
      this.planLine.renderOrder = 2;
      this.scene.add(this.planLine);
    }
    this.updateTask();
  }

  updateTask() {
    const a = this.assessment;
    const box = this.field('task');
    if (!a) return;
    box.hidden = false;
    const set = (role, text) => {
      this.field(role).textContent = text;
    };
    const mm = (v) => (v == null ? '–' : `${v.toFixed(1)} mm`);
    set('task-text', a.task || 'no task: motion and force only');
    set('score', a.score == null ? '–' : a.score.toFixed(0));
    const verdict = this.field('verdict');
    // Not passed yet is only "in progress" while the trainee can still finish.
    verdict.textContent = a.passed == null ? '–' : a.passed ? 'passed' : a.completed || !this.stepping ? 'failed' : 'in progress';
    verdict.dataset.verdict = a.passed == null ? '' : a.passed ? 'passed' : 'failed';
    verdict.title = (a.failures || []).join('; ');
    set('coverage', a.coverage == null ? '–' : `${(a.coverage * 100).toFixed(0)} %`);
    set('deviation', a.deviation_rms_mm == null ? '–' : `${mm(a.deviation_rms_mm)} RMS, ${mm(a.deviation_max_mm)} max (±${a.band_mm.toFixed(1)})`);
    set('depth', mm(a.depth_error_rms_mm));
    set('time', a.time_to_complete_s == null ? (a.started_s == null ? '–' : 'not complete') : `${a.time_to_complete_s.toFixed(2)} s`);
    set('strokes', `${a.strokes}`);
    set('path', `${a.path_length_mm.toFixed(0)} mm${a.economy_of_motion == null ? '' : `, economy ${a.economy_of_motion.toFixed(2)}`}`);
    set('peak', `${a.peak_force_n.toFixed(2)} N${a.time_above_force_limit_s ? `, ${a.time_above_force_limit_s.toFixed(2)} s over the limit` : ''}`);
    // The forceps' hardest pinch, once there was one (or the task limits it).
    const grip = a.peak_grip_force_n > 0 || a.time_above_grip_limit_s != null;
    this.field('grip-label').hidden = !grip;
    this.field('grip').hidden = !grip;
    set('grip', `${a.peak_grip_force_n.toFixed(2)} N${a.time_above_grip_limit_s ? `, ${a.time_above_grip_limit_s.toFixed(2)} s over the limit` : ''}`);
    set('nogo', a.no_go_entries ? `${a.no_go_entries} entr${a.no_go_entries === 1 ? 'y' : 'ies'}` : 'none');
    // Warnings as they happened, newest first (text, never markup).
    const list = this.field('warnings');
    const warnings = (a.events || []).filter((e) => e.kind !== 'completed').slice(-WARNINGS_SHOWN).reverse();
    list.replaceChildren(
      ...warnings.map((e) => {
        const li = document.createElement('li');
        li.dataset.kind = e.kind;
        li.textContent = `${e.time_s.toFixed(2)} s — ${e.message}`;
        return li;
      }),
    );
  }

  updateHud() {
    const st = this.stats;
    const set = (role, text) => {
      this.field(role).textContent = text;
    };
    if (st) {
      set('status', String(st.status).replace('SESSION_STATUS_', '').toLowerCase().replace('_', ' '));
      const stepping = ['SESSION_STATUS_RUNNING', 'SESSION_STATUS_RUNNING_SCRIPT', 'SESSION_STATUS_DEGRADED'].includes(st.status);
      if (stepping !== this.stepping) {
        this.stepping = stepping;
        this.updateTask(); // the verdict of an unfinished task depends on it
      }
      set('rate', `${st.stats.achieved_rate_hz.toFixed(0)} Hz`);
      set('p99', `${st.stats.p99_us.toFixed(0)} µs`);
      set('missed', `${st.stats.missed_deadlines}`);
      // Cut updates whose wound could not be stitched, left as open holes, and strokes
      // whose last piece was left uncut (the incision ends a millimetre or two short of
      // where the blade left): counted beside the cuts, with each hole's step and why on
      // hover.
      const open = st.fallbacks || [];
      const uncut = st.counters.uncut_last_pieces || 0;
      const notes = [];
      if (open.length) notes.push(`${open.length} left open`);
      if (uncut) notes.push(`${uncut} end${uncut === 1 ? '' : 's'} left uncut`);
      set('cuts', notes.length ? `${st.counters.cuts} (${notes.join(', ')})` : `${st.counters.cuts}`);
      const hover = open.map((f) => `step ${f.step}: ${f.reason}`);
      if (uncut) hover.push(`${uncut} stroke${uncut === 1 ? '' : 's'} ended short of where the blade left: the last piece could not be stitched`);
      this.field('cuts').title = hover.join('\n');
      set('incision', `${(st.counters.incision_length_m * 1000).toFixed(1)} mm`);
    }
    const last = this.forceHistory.length ? this.forceHistory[this.forceHistory.length - 1][1] : 0;
    set('force', `${last.toFixed(3)} N`);
    set('triangles', `${this.surface.triangles.size}`);
    // Server step → frame shown; only meaningful while the session steps (and assumes the
    // two clocks agree, as they do on one machine or with NTP).
    set('latency', this.latencyMs == null || !this.stepping ? '–' : `≈ ${Math.max(0, this.latencyMs).toFixed(0)} ms`);
    this.drawPlot();
  }

  drawPlot() {
    const g = this.plot.getContext('2d');
    const { width: w, height: h } = this.plot;
    g.clearRect(0, 0, w, h);
    g.fillStyle = '#14171b';
    g.fillRect(0, 0, w, h);
    if (this.forceHistory.length < 2) return;
    const max = Math.max(0.1, ...this.forceHistory.map((p) => p[1]));
    const now = performance.now();
    g.strokeStyle = '#ffd030';
    g.beginPath();
    this.forceHistory.forEach(([t, f], i) => {
      const x = w * (1 - (now - t) / (PLOT_SECONDS * 1000));
      const y = h - 4 - (h - 8) * (f / max);
      if (i === 0) g.moveTo(x, y);
      else g.lineTo(x, y);
    });
    g.stroke();
    g.fillStyle = '#aab';
    g.font = '10px sans-serif';
    g.fillText(`${max.toFixed(2)} N`, 4, 11);
    g.fillText(`${PLOT_SECONDS} s`, w - 22, h - 4);
  }

  render() {
    this.updateGeometry();
    this.updateTools();
    this.updateHud();
    this.updateTimeline();
    this.controls.update();
    this.renderer.render(this.scene, this.camera);
  }

  dispose() {
    this.closed = true;
    cancelAnimationFrame(this.raf);
    this.resizeObserver.disconnect();
    this.ws?.close();
    this.curves.stop();
    this.renderer.dispose();
    this.el.remove();
  }
}
