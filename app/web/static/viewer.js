// The 3D view: mesh.glb (the reconstructed surface) and skeleton.glb (the medial curves as glTF LINES
// plus a thin tube mesh) loaded with three.js's GLTFLoader, turned with OrbitControls. skeleton.glb
// holds all ribs in one lines and one tube primitive; skeleton.json says which node belongs to which
// rib, so every vertex goes to the rib of its nearest skeleton node and each rib becomes its own
// object: shown or hidden on its own, and picked with the mouse. Coordinates are mm (the input's
// frame, RAS+ for NIfTI: +z up, the camera starts in front of the patient, +y).

import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const GRID_MM = 2.0; // cell of the node lookup grid: tube vertices lie 0.6 mm from their curve
const PICK_COLOR = new THREE.Color(0xff1a00); // the rib palette below keeps clear of red
const UNLABELLED = 'other'; // skeleton edges no rib curve covers (junctions, spurs)

function parseGlb(loader, bytes) {
  return new Promise((resolve, reject) => loader.parse(bytes, '', resolve, reject));
}

/** Nearest-node lookup on a uniform grid (nodes: flat [x, y, z, ...] in mm). */
class NodeGrid {
  constructor(nodes) {
    this.nodes = nodes;
    this.cells = new Map();
    for (let i = 0; i < nodes.length / 3; i += 1) {
      const key = this.key(nodes[3 * i], nodes[3 * i + 1], nodes[3 * i + 2]);
      if (!this.cells.has(key)) this.cells.set(key, []);
      this.cells.get(key).push(i);
    }
  }

  key(x, y, z) { return `${Math.floor(x / GRID_MM)},${Math.floor(y / GRID_MM)},${Math.floor(z / GRID_MM)}`; }

  nearest(x, y, z) {
    let best = -1;
    let bestD = Infinity;
    const scan = (ids) => {
      for (const i of ids) {
        const dx = this.nodes[3 * i] - x;
        const dy = this.nodes[3 * i + 1] - y;
        const dz = this.nodes[3 * i + 2] - z;
        const d = dx * dx + dy * dy + dz * dz;
        if (d < bestD) { bestD = d; best = i; }
      }
    };
    const cx = Math.floor(x / GRID_MM);
    const cy = Math.floor(y / GRID_MM);
    const cz = Math.floor(z / GRID_MM);
    for (let a = -1; a <= 1; a += 1) {
      for (let b = -1; b <= 1; b += 1) {
        for (let c = -1; c <= 1; c += 1) {
          const ids = this.cells.get(`${cx + a},${cy + b},${cz + c}`);
          if (ids) scan(ids);
        }
      }
    }
    if (best < 0) scan(this.nodes.length ? Array.from({ length: this.nodes.length / 3 }, (_, i) => i) : []);
    return best;
  }
}

/** Rib index of every skeleton node (-1: on no rib curve), from skeleton.json's components. */
function nodeRibs(skeleton) {
  const ribOf = new Int32Array(skeleton.nodes.length).fill(-1);
  skeleton.components.forEach((c, r) => { for (const id of c.node_ids) ribOf[id] = r; });
  return ribOf;
}

/** World-space positions of a glTF primitive (the loader keeps node transforms on the object). */
function worldPositions(object) {
  object.updateWorldMatrix(true, false);
  const pos = object.geometry.getAttribute('position');
  const out = new Float32Array(pos.count * 3);
  const v = new THREE.Vector3();
  for (let i = 0; i < pos.count; i += 1) {
    v.fromBufferAttribute(pos, i).applyMatrix4(object.matrixWorld);
    out[3 * i] = v.x; out[3 * i + 1] = v.y; out[3 * i + 2] = v.z;
  }
  return out;
}

/** Split the LINES and tube primitives of skeleton.glb into per-rib geometries. */
function splitSkeleton(gltfScene, skeleton) {
  const nodes = new Float32Array(skeleton.nodes.flat());
  const grid = new NodeGrid(nodes);
  const ribOf = nodeRibs(skeleton);
  const nRibs = skeleton.components.length;
  const ribOfVertex = (xyz, i) => {
    const r = ribOf[grid.nearest(xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2])];
    return r < 0 ? nRibs : r; // nRibs: the "other" group
  };
  const lines = Array.from({ length: nRibs + 1 }, () => []);
  const tubes = []; // per triangle primitive: its position + normal attributes and each rib's triangles
  gltfScene.traverse((obj) => {
    if (obj.isLineSegments) { // LINES: non-indexed vertex pairs
      const xyz = worldPositions(obj);
      for (let i = 0; i + 1 < xyz.length / 3; i += 2) {
        lines[ribOfVertex(xyz, i)].push(...xyz.subarray(3 * i, 3 * i + 6));
      }
    } else if (obj.isMesh) {
      const xyz = worldPositions(obj);
      const count = xyz.length / 3;
      const index = obj.geometry.index ? obj.geometry.index.array : Array.from({ length: count }, (_, i) => i);
      const whole = new THREE.BufferGeometry(); // normals once, shared by the per-rib pieces
      whole.setAttribute('position', new THREE.BufferAttribute(xyz, 3));
      whole.setIndex(Array.from(index));
      whole.computeVertexNormals();
      const vertexRib = new Int32Array(count);
      for (let i = 0; i < count; i += 1) vertexRib[i] = ribOfVertex(xyz, i);
      const byRib = Array.from({ length: nRibs + 1 }, () => []);
      for (let t = 0; t + 2 < index.length; t += 3) byRib[vertexRib[index[t]]].push(index[t], index[t + 1], index[t + 2]);
      tubes.push({ position: whole.getAttribute('position'), normal: whole.getAttribute('normal'), byRib });
    }
  });
  return { lines, tubes };
}

function ribColor(r, n) {
  return new THREE.Color().setHSL(0.12 + (r / Math.max(n, 1)) * 0.72, 0.7, 0.45);
}

/**
 * Build the view in `container`. meshGlb / skeletonGlb: ArrayBuffers (skeletonGlb may be null);
 * skeleton: skeleton.json; metrics: metrics.json; infoBox / ribList: elements for the picked rib's
 * measurements and the per-rib checkboxes. Resolves to a small control object.
 */
export async function createViewer(container, { meshGlb, skeletonGlb, skeleton, metrics, infoBox, ribList }) {
  const canvas = document.createElement('canvas');
  canvas.id = 'viewer-canvas';
  container.append(canvas);
  let renderer;
  try {
    // preserveDrawingBuffer: the picture stays readable (screenshots, the page's tests)
    renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  } catch (err) {
    canvas.remove();
    throw new Error(`3D view unavailable: this browser gives no WebGL context (${err.message})`);
  }
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setClearColor(0xf4f4f0);
  const scene = new THREE.Scene();
  const camera = new THREE.PerspectiveCamera(35, 1, 1, 10000);
  camera.up.set(0, 0, 1);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x555566, 1.6));
  const headLight = new THREE.DirectionalLight(0xffffff, 1.8);
  camera.add(headLight);
  scene.add(camera);

  const loader = new GLTFLoader();
  const meshGltf = await parseGlb(loader, meshGlb);
  const surface = new THREE.Group();
  surface.name = 'surface';
  meshGltf.scene.traverse((obj) => {
    if (obj.isMesh) {
      obj.material = new THREE.MeshStandardMaterial({
        color: 0xe1d7be, roughness: 0.8, transparent: true, opacity: 0.3, depthWrite: false, side: THREE.DoubleSide,
      });
    }
  });
  surface.add(meshGltf.scene);
  scene.add(surface);

  const curveMetrics = new Map(((metrics.skeleton || {}).curves || []).map((c) => [c.label, c]));
  const ribs = [];
  if (skeletonGlb && skeleton) {
    const skelGltf = await parseGlb(loader, skeletonGlb);
    const { lines, tubes } = splitSkeleton(skelGltf.scene, skeleton);
    const n = skeleton.components.length;
    for (let r = 0; r <= n; r += 1) {
      const comp = skeleton.components[r];
      const label = comp ? comp.label : UNLABELLED;
      if (!comp && !lines[r].length && !tubes.some((t) => t.byRib[r].length)) continue;
      const color = comp ? ribColor(r, n) : new THREE.Color(0x888888);
      const group = new THREE.Group();
      group.name = label;
      for (const part of tubes.filter((t) => t.byRib[r].length)) {
        const g = new THREE.BufferGeometry();
        g.setAttribute('position', part.position);
        g.setAttribute('normal', part.normal);
        g.setIndex(part.byRib[r]);
        const tube = new THREE.Mesh(g, new THREE.MeshStandardMaterial({ color, roughness: 0.5 }));
        tube.userData.rib = label;
        group.add(tube);
      }
      if (lines[r].length) {
        const g = new THREE.BufferGeometry();
        g.setAttribute('position', new THREE.Float32BufferAttribute(lines[r], 3));
        const line = new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color }));
        line.userData.rib = label;
        group.add(line);
      }
      scene.add(group);
      ribs.push({ label, group, color, component: comp, metrics: curveMetrics.get(label) });
    }
  }

  const controls = new OrbitControls(camera, canvas);
  const box = new THREE.Box3().setFromObject(surface);
  /** Look at the surface from the front (+y): its x extent and z extent fill the view. */
  function frame(aspect) {
    const size = box.getSize(new THREE.Vector3());
    const centre = box.getCenter(new THREE.Vector3());
    const tan = Math.tan(THREE.MathUtils.degToRad(camera.fov / 2));
    const dist = Math.max(size.z / 2 / tan, size.x / 2 / (tan * aspect)) * 1.12 + size.y / 2;
    controls.target.copy(centre);
    camera.position.copy(centre).add(new THREE.Vector3(0, dist, 0));
    camera.near = Math.max(dist / 100, 0.1);
    camera.far = dist * 10;
    camera.updateProjectionMatrix();
    controls.update();
  }

  const render = () => renderer.render(scene, camera);
  let framed = false;
  const resize = () => {
    const w = container.clientWidth || 640;
    const h = Math.max(360, Math.round(w * 0.62));
    renderer.setSize(w, h, true);
    camera.aspect = w / h;
    if (!framed) { frame(camera.aspect); framed = true; }
    camera.updateProjectionMatrix();
    render();
  };
  controls.addEventListener('change', render); // render on demand: no busy loop on a CPU renderer
  new ResizeObserver(resize).observe(container);

  let picked = null;
  const setColor = (rib, color) => rib.group.traverse((o) => { if (o.material) o.material.color.copy(color); });
  function pick(label) {
    if (picked) setColor(picked, picked.color);
    picked = ribs.find((r) => r.label === label) || null;
    ribList.querySelectorAll('li').forEach((li) => li.classList.toggle('picked', li.dataset.rib === label));
    if (!picked) { infoBox.textContent = 'Click a rib (in the view or the list) to see its measurements.'; render(); return; }
    setColor(picked, PICK_COLOR);
    const m = picked.metrics || picked.component || {};
    const rows = [['rib', picked.label]];
    if (m.length_mm != null) rows.push(['length', `${m.length_mm.toFixed(1)} mm`]);
    if (m.mean_radius_mm != null) rows.push(['mean radius', `${m.mean_radius_mm.toFixed(2)} mm`]);
    if (m.min_radius_mm != null) rows.push(['min radius', `${m.min_radius_mm.toFixed(2)} mm`]);
    if (picked.component) rows.push(['nodes', String(picked.component.node_ids.length)]);
    const dl = document.createElement('dl');
    for (const [k, v] of rows) {
      const dt = document.createElement('dt'); dt.textContent = k;
      const dd = document.createElement('dd'); dd.textContent = v;
      dd.dataset.field = k;
      dl.append(dt, dd);
    }
    infoBox.replaceChildren(dl);
    infoBox.dataset.rib = picked.label;
    render();
  }

  // the rib list: a checkbox (visibility) and the name (pick) per rib
  ribList.replaceChildren(...ribs.map((rib) => {
    const li = document.createElement('li');
    li.dataset.rib = rib.label;
    const box = document.createElement('input');
    box.type = 'checkbox';
    box.checked = true;
    box.setAttribute('aria-label', `show ${rib.label}`);
    box.addEventListener('change', () => { rib.group.visible = box.checked; render(); });
    const swatch = document.createElement('span');
    swatch.className = 'swatch';
    swatch.style.background = `#${rib.color.getHexString()}`;
    const name = document.createElement('button');
    name.type = 'button';
    name.className = 'rib-name';
    name.textContent = rib.label;
    name.addEventListener('click', () => pick(rib.label));
    li.append(box, swatch, name);
    return li;
  }));

  // picking: a click that did not drag the view picks the rib under the pointer (tubes, then lines)
  const raycaster = new THREE.Raycaster();
  raycaster.params.Line.threshold = 1.5; // mm
  let down = null;
  canvas.addEventListener('pointerdown', (ev) => { down = [ev.clientX, ev.clientY]; });
  canvas.addEventListener('pointerup', (ev) => {
    if (!down || Math.hypot(ev.clientX - down[0], ev.clientY - down[1]) > 4) return;
    const rect = canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(((ev.clientX - rect.left) / rect.width) * 2 - 1,
      -((ev.clientY - rect.top) / rect.height) * 2 + 1);
    raycaster.setFromCamera(ndc, camera);
    const targets = ribs.filter((r) => r.group.visible).flatMap((r) => r.group.children);
    const hits = raycaster.intersectObjects(targets, false);
    const tubeHit = hits.find((h) => h.object.isMesh);
    const hit = tubeHit || hits[0];
    pick(hit ? hit.object.userData.rib : null);
  });

  resize();
  const api = {
    renderer,
    ribs: ribs.map((r) => r.label),
    pick,
    setSurfaceVisible(v) { surface.visible = v; render(); },
    resetView() { frame(camera.aspect); render(); },
    setAllRibsVisible(v) {
      ribs.forEach((r) => { r.group.visible = v; });
      ribList.querySelectorAll('input[type=checkbox]').forEach((b) => { b.checked = v; });
      render();
    },
    /** Which ribs are shown, and what the last frame drew (for the page's tests and the console). */
    state() {
      const gl = renderer.getContext();
      const dbg = gl.getExtension('WEBGL_debug_renderer_info');
      return {
        webgl2: typeof WebGL2RenderingContext !== 'undefined' && gl instanceof WebGL2RenderingContext,
        glRenderer: dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER),
        triangles: renderer.info.render.triangles,
        visible: Object.fromEntries(ribs.map((r) => [r.label, r.group.visible])),
      };
    },
    /** Page coordinates of the middle node of a rib's curve (where a click picks that rib). */
    screenPoint(label) {
      const rib = ribs.find((r) => r.label === label);
      if (!rib || !rib.component) return null;
      const ids = rib.component.node_ids;
      const p = new THREE.Vector3(...skeleton.nodes[ids[Math.floor(ids.length / 2)]]).project(camera);
      const rect = canvas.getBoundingClientRect();
      return { x: rect.left + ((p.x + 1) / 2) * rect.width, y: rect.top + ((1 - p.y) / 2) * rect.height };
    },
  };
  window.ribpullViewer = api;
  return api;
}
