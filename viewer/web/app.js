// fullview viewer: 3-D scene (three.js), virtual tour (Photo Sphere Viewer), correlated views and hand-point picker.
// Geometry follows fullview's conventions: pixels (0,0) = top-left corner, lon = 2π(x/W − 0.5), lat = π(0.5 − y/H),
// bearing = (cos lat sin lon, −sin lat, cos lat cos lon); x_cam = R_cam_from_world (x_world − centre).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { Viewer } from '@photo-sphere-viewer/core';
import { MarkersPlugin } from '@photo-sphere-viewer/markers-plugin';

const TOUR_WIDTH = 4096;      // display width of tour panoramas (served downscaled, cached by the server)
const CORR_WIDTH = 2048;      // display width of the correlated views
const RAY_TOLERANCE = 0.01;   // rad: a point this close to a clicked ray counts as lying on it
const TARGET_FPS = 30;        // the point budget is lowered until the 3-D scene renders this fast
const MIN_BUDGET = 20000;     // ... but never below this many points (nor the model's readable budget)
const hooks = window.fullview = { ready: false, lastClick: null, tour: null, errors: [] };

// ------------------------------------------------------------------------------------------------ server access
// The server answers data requests only with the token of its start, which `fullview view` prints in the page's URL;
// fetches send it as a header, image URLs (which cannot) as a query parameter. Names (images, tracks) reach the page
// as text only: textContent, DOM elements, or escaped where a library option takes HTML.
const TOKEN = new URLSearchParams(location.search).get('token') || '';
const api = (url, options = {}) => fetch(url, { ...options, headers: { ...options.headers, 'X-Fullview-Token': TOKEN } });
const post = (url, body) => api(url, { method: 'POST', headers: { 'Content-Type': 'application/json' },
  body: JSON.stringify(body) });
const withToken = (url) => `${url}${url.includes('?') ? '&' : '?'}token=${encodeURIComponent(TOKEN)}`;
const escapeHtml = (text) => String(text).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);

// ------------------------------------------------------------------------------------------------ small math
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => Math.hypot(a[0], a[1], a[2]);
const unit = (a) => { const n = norm(a) || 1; return [a[0] / n, a[1] / n, a[2] / n]; };
const mul = (R, v) => [dot(R[0], v), dot(R[1], v), dot(R[2], v)];
const mulT = (R, v) => [R[0][0] * v[0] + R[1][0] * v[1] + R[2][0] * v[2], R[0][1] * v[0] + R[1][1] * v[1] +
  R[2][1] * v[2], R[0][2] * v[0] + R[1][2] * v[1] + R[2][2] * v[2]];

export function pixelToBearing(x, y, W, H) {
  const lon = 2 * Math.PI * (x / W - 0.5), lat = Math.PI * (0.5 - y / H);
  return [Math.cos(lat) * Math.sin(lon), -Math.sin(lat), Math.cos(lat) * Math.cos(lon)];
}
export function bearingToPixel(b, W, H) {
  const lon = Math.atan2(b[0], b[2]), lat = Math.atan2(-b[1], Math.hypot(b[0], b[2]));
  return [((lon / (2 * Math.PI) + 0.5) * W + W) % W, (0.5 - lat / Math.PI) * H];
}
const yawPitch = (b) => ({ yaw: Math.atan2(b[0], b[2]), pitch: Math.atan2(-b[1], Math.hypot(b[0], b[2])) });
const fromYawPitch = (p) => [Math.cos(p.pitch) * Math.sin(p.yaw), -Math.sin(p.pitch), Math.cos(p.pitch) * Math.cos(p.yaw)];

// Great circle of bearings orthogonal to `n` (camera frame), as full-size pixel polylines split where they wrap.
function greatCircle(n, W, H, samples = 720) {
  n = unit(n);
  const a = Math.abs(n[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
  const u = unit(cross(n, a)), v = cross(n, u);
  const lines = [[]];
  let prev = null;
  for (let k = 0; k <= samples; k++) {
    const t = (2 * Math.PI * k) / samples;
    const p = bearingToPixel([u[0] * Math.cos(t) + v[0] * Math.sin(t), u[1] * Math.cos(t) + v[1] * Math.sin(t),
      u[2] * Math.cos(t) + v[2] * Math.sin(t)], W, H);
    if (prev && Math.abs(p[0] - prev[0]) > W / 2) lines.push([]);
    lines[lines.length - 1].push(p);
    prev = p;
  }
  return lines;
}

// ------------------------------------------------------------------------------------------------ data
let state = null;
const cams = new Map();   // name -> camera entry of the model
const imageSize = new Map();
let clouds = {};          // kind -> {positions Float32Array (world), colors Uint8Array, count}

async function getJSON(url) {
  const r = await api(url);
  const body = await r.json();
  if (!r.ok) throw new Error(body.error || r.statusText);
  return body;
}
async function getCloud(kind) {
  if (clouds[kind]) return clouds[kind];
  const buf = await (await api(`/api/points/${kind}`)).arrayBuffer();
  const count = new Uint32Array(buf, 0, 1)[0];
  const positions = new Float32Array(buf.slice(4, 4 + 12 * count));
  const colors = new Uint8Array(buf.slice(4 + 12 * count, 4 + 15 * count));
  return (clouds[kind] = { positions, colors, count });
}

// The dense mesh: uint32 vertex and triangle counts, float32 xyz, uint8 rgb (padded to 4 bytes), uint32 indices.
let meshData = null;
async function getMesh() {
  if (meshData) return meshData;
  const buf = await (await api('/api/mesh')).arrayBuffer();
  const [nv, nt] = new Uint32Array(buf, 0, 2);
  const positions = new Float32Array(buf.slice(8, 8 + 12 * nv));
  const colors = new Uint8Array(buf.slice(8 + 12 * nv, 8 + 15 * nv));
  const start = 8 + 15 * nv + ((4 - ((15 * nv) % 4)) % 4);
  const index = new Uint32Array(buf.slice(start, start + 12 * nt));
  return (meshData = { positions, colors, index, vertices: nv, triangles: nt });
}

function showMessage(text, id = 'message') {
  const el = document.getElementById(id);
  el.hidden = !text;
  if (text && id === 'message') el.textContent = text;
}

// ------------------------------------------------------------------------------------------------ 3-D scene
const scene3d = { renderer: null, camera: null, controls: null, group: null, points: null, cameraMeshes: [],
  highlight: null };

function initScene() {
  const canvas = document.getElementById('scene3d');
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x15171a);
  const camera = new THREE.PerspectiveCamera(60, 1, 0.001, 1000);
  scene.add(new THREE.AmbientLight(0xffffff, 1.6), camera);  // lights for the mesh (points ignore them)
  camera.add(new THREE.DirectionalLight(0xffffff, 1.4));
  const controls = new OrbitControls(camera, canvas);
  const group = new THREE.Group();
  scene.add(group);
  Object.assign(scene3d, { renderer, scene, camera, controls, group });
  const resize = () => {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (!w || !h) return;
    renderer.setSize(w, h, false);
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
  };
  new ResizeObserver(resize).observe(canvas);
  canvas.addEventListener('click', onSceneClick);
  renderer.setAnimationLoop(() => { controls.update(); renderer.render(scene, camera); });
}

// The scene opens framed on the model's bounds (the 2nd-98th percentiles of its points per axis, from the server),
// seen from outside and above like a dollhouse; the cameras are spheres to click into the tour.
function buildScene(model) {
  const { group } = scene3d;
  group.clear();
  const R = model.R_display_from_world;
  const m = new THREE.Matrix4().set(R[0][0], R[0][1], R[0][2], 0, R[1][0], R[1][1], R[1][2], 0,
    R[2][0], R[2][1], R[2][2], 0, 0, 0, 0, 1);
  group.matrixAutoUpdate = false;
  group.matrix.copy(m);
  const registered = model.cameras.filter((c) => c.registered);
  const centres = registered.map((c) => c.center);
  const display = centres.map((c) => new THREE.Vector3(...c).applyMatrix4(m));
  const box = model.tour.bounds ? new THREE.Box3(new THREE.Vector3(...model.tour.bounds[0]),
    new THREE.Vector3(...model.tour.bounds[1])) : new THREE.Box3().setFromPoints(display);
  if (box.isEmpty()) box.expandByScalar(1);
  scene3d.bounds = box;
  const size = box.getSize(new THREE.Vector3());
  const extent = Math.max(1e-6, size.length());
  const spacing = display.map((p, i) => Math.min(...display.filter((_, j) => j !== i).map((q) => p.distanceTo(q))))
    .sort((a, b) => a - b)[Math.floor(display.length / 2)];  // median distance to the nearest other camera
  const radius = Math.min(0.012 * extent, 0.25 * (spacing || extent));
  scene3d.cameraMeshes = [];
  for (const cam of registered) {
    const sphere = new THREE.Mesh(new THREE.SphereGeometry(radius, 16, 12),
      new THREE.MeshBasicMaterial({ color: cam.walked ? 0xffcc33 : 0x888888 }));
    sphere.position.set(...cam.center);
    sphere.userData.name = cam.name;
    group.add(sphere);
    scene3d.cameraMeshes.push(sphere);
    const forward = mulT(cam.R_cam_from_world, [0, 0, 1]);  // heading: the panorama's centre direction
    const tip = cam.center.map((v, i) => v + 3 * radius * forward[i]);
    group.add(line([cam.center, tip], 0xff6633));
  }
  group.add(line(centres, 0x66aaff));  // the capture's track, in image order
  scene3d.extent = extent;
  setupCut(model.tour, box);
  frameModel();
}

// Place the 3-D camera outside the bounds, above them, so that the whole box is in view.
function frameModel() {
  const { camera, controls, bounds } = scene3d;
  const centre = bounds.getCenter(new THREE.Vector3());
  const corners = boxCorners(bounds);
  const dir = new THREE.Vector3(0.55, 0.75, 0.9).normalize();  // from the side and above (45° or so)
  camera.up.set(0, 1, 0);
  const rect = scene3d.renderer.domElement.getBoundingClientRect();
  camera.aspect = rect.width && rect.height ? rect.width / rect.height : camera.aspect;
  // The nearest distance along `dir` at which every corner projects inside the view (with a 10% margin).
  let lo = 0, hi = 1e3 * scene3d.extent;
  for (let it = 0; it < 60; it++) {
    const d = (lo + hi) / 2;
    camera.position.copy(centre).addScaledVector(dir, d);
    camera.lookAt(centre);
    camera.near = d * 1e-3; camera.far = d * 1e2;
    camera.updateProjectionMatrix(); camera.updateMatrixWorld();
    const inside = corners.every((c) => { const p = c.clone().project(camera);
      return p.z < 1 && Math.abs(p.x) <= 0.9 && Math.abs(p.y) <= 0.9; });
    if (inside) hi = d; else lo = d;
  }
  camera.position.copy(centre).addScaledVector(dir, hi);
  camera.near = hi * 1e-3; camera.far = hi * 1e2;
  camera.updateProjectionMatrix();
  controls.target.copy(centre);
  controls.update();
}

function boxCorners(box) {
  const out = [];
  for (const x of [box.min.x, box.max.x]) {
    for (const y of [box.min.y, box.max.y]) {
      for (const z of [box.min.z, box.max.z]) out.push(new THREE.Vector3(x, y, z));
    }
  }
  return out;
}
// Where the bounds' corners project in the 3-D view (NDC; tests check they are all in view).
hooks.sceneCamera = () => scene3d.camera.position.toArray();
hooks.state = () => state;
hooks.sceneFraming = () => boxCorners(scene3d.bounds).map((c) => c.clone().project(scene3d.camera))
  .map((p) => [p.x, p.y, p.z]);

// The dollhouse's cut: everything above a height (display y) is clipped away, the mesh's ceiling first; the
// default is just below the ceiling the server estimated from the depth above the cameras.
const CUT_BELOW_CEILING = 0.1;  // default cut: this share of the floor-to-ceiling height below the ceiling
function setupCut(t, box) {
  const slider = document.getElementById('cut');
  const low = t.floor ?? box.min.y, high = Math.max(t.ceiling ?? box.max.y, box.max.y);
  slider.min = low; slider.max = high + 0.02 * (high - low); slider.step = (high - low) / 500 || 0.001;
  const ceiling = t.ceiling ?? box.max.y;
  slider.value = ceiling - CUT_BELOW_CEILING * (ceiling - (t.floor ?? box.min.y));
  slider.disabled = false;
  scene3d.cut = new THREE.Plane(new THREE.Vector3(0, -1, 0), Number(slider.value));
  scene3d.renderer.localClippingEnabled = true;
  const update = () => {
    scene3d.cut.constant = Number(slider.value);
    const above = Number(slider.value) - (t.floor ?? box.min.y);
    document.getElementById('cut-label').textContent = Number(slider.value) >= Number(slider.max) - 1e-9 ? 'none'
      : `${above.toFixed(2)} above the floor`;
    hooks.cut = Number(slider.value);
  };
  slider.addEventListener('input', update);
  update();
  document.getElementById('frame').onclick = frameModel;
}

function line(points, color) {
  const geometry = new THREE.BufferGeometry().setFromPoints(points.map((p) => new THREE.Vector3(...p)));
  return new THREE.Line(geometry, new THREE.LineBasicMaterial({ color }));
}

async function showCloud(kind) {
  if (kind === 'mesh' && !state.model.has_mesh) kind = 'dense';
  if (kind === 'dense' && !state.model.has_dense) kind = 'sparse';
  if (kind === 'sparse' && !state.model.has_sparse) return;
  if (kind === 'mesh') return showMesh();
  const cloud = await getCloud(kind);
  if (scene3d.points) scene3d.group.remove(scene3d.points);
  document.getElementById('budget').disabled = false;
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(cloud.positions, 3));
  geometry.setAttribute('color', new THREE.BufferAttribute(cloud.colors, 3, true));
  const material = new THREE.PointsMaterial({ size: kind === 'sparse' ? 3 : 2, sizeAttenuation: false,
    vertexColors: true, clippingPlanes: [scene3d.cut] });
  scene3d.points = new THREE.Points(geometry, material);
  scene3d.group.add(scene3d.points);
  const slider = document.getElementById('budget');
  slider.max = Math.max(1000, cloud.count);
  applyBudget();
  hooks.shown = { kind, points: cloud.count };
  fitBudgetToFrameRate();
}

// The trimmed Poisson mesh, vertex-coloured and lit from the viewer's side (both faces: one looks at walls from
// inside and outside); the point budget does not apply.
async function showMesh() {
  const mesh = await getMesh();
  if (scene3d.points) scene3d.group.remove(scene3d.points);
  const geometry = new THREE.BufferGeometry();
  geometry.setAttribute('position', new THREE.BufferAttribute(mesh.positions, 3));
  geometry.setAttribute('color', new THREE.BufferAttribute(mesh.colors, 3, true));
  geometry.setIndex(new THREE.BufferAttribute(mesh.index, 1));
  geometry.computeVertexNormals();
  const material = new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide,
    clippingPlanes: [scene3d.cut] });
  scene3d.points = new THREE.Mesh(geometry, material);
  scene3d.group.add(scene3d.points);
  document.getElementById('budget').disabled = true;
  document.getElementById('budget-label').textContent = `${mesh.triangles.toLocaleString()} triangles`;
  hooks.shown = { kind: 'mesh', triangles: mesh.triangles, vertices: mesh.vertices };
}

// Halve the point budget until the scene renders at 30 fps or more (the slider can raise it again), never below
// the readable budget: the server orders the cloud coarse to fine (viewer/tour.py spatial_order), and that many
// points give every occupied cell of 1/128 of the model's extent a point.
async function fitBudgetToFrameRate() {
  const slider = document.getElementById('budget');
  const floor = Math.max(MIN_BUDGET, state.model.tour.readable_points || 0);
  for (let round = 0; round < 6 && Number(slider.value) > floor; round++) {
    const fps = await measureFps();
    hooks.fps = fps;
    if (fps >= TARGET_FPS) break;
    slider.value = Math.max(floor, Math.floor(Math.min(Number(slider.value), Number(slider.max)) / 2));
    applyBudget();
  }
}

function measureFps(ms = 700) {
  return new Promise((resolve) => {
    let frames = 0;
    const start = performance.now();
    const tick = (now) => {
      frames++;
      if (now - start < ms) requestAnimationFrame(tick); else resolve((1000 * frames) / (now - start));
    };
    requestAnimationFrame(tick);
  });
}

function applyBudget() {
  const slider = document.getElementById('budget');
  const n = Math.min(Number(slider.value), Number(slider.max));
  if (!scene3d.points || scene3d.points.isMesh) return;
  scene3d.points.geometry.setDrawRange(0, n);  // clouds come coarse to fine: a prefix is spread over the model
  document.getElementById('budget-label').textContent = `${n.toLocaleString()} points`;
}

function onSceneClick(event) {
  const rect = event.target.getBoundingClientRect();
  const ndc = new THREE.Vector2(((event.clientX - rect.left) / rect.width) * 2 - 1,
    -((event.clientY - rect.top) / rect.height) * 2 + 1);
  const ray = new THREE.Raycaster();
  ray.setFromCamera(ndc, scene3d.camera);
  const hit = ray.intersectObjects(scene3d.cameraMeshes)[0];
  if (hit) openTour(hit.object.userData.name);
}

function highlightPoint(p) {
  if (scene3d.highlight) scene3d.group.remove(scene3d.highlight);
  scene3d.highlight = null;
  if (!p) return;
  const mesh = new THREE.Mesh(new THREE.SphereGeometry(0.006 * scene3d.extent, 12, 8),
    new THREE.MeshBasicMaterial({ color: 0xff2222 }));
  mesh.position.set(...p);
  scene3d.group.add(mesh);
  scene3d.highlight = mesh;
}

// Screen position of a camera sphere (tests click it).
hooks.cameraScreenPosition = (name) => {
  const mesh = scene3d.cameraMeshes.find((m) => m.userData.name === name);
  if (!mesh) return null;
  const v = new THREE.Vector3();
  mesh.getWorldPosition(v).project(scene3d.camera);
  const rect = scene3d.renderer.domElement.getBoundingClientRect();
  return [rect.left + (v.x + 1) / 2 * rect.width, rect.top + (1 - v.y) / 2 * rect.height];
};

// ------------------------------------------------------------------------------------------------ tour
// Hotspots come from the server (viewer/tour.py): one per visible walked neighbour, on the floor below it, as a disc
// of angular radius `radius` that clears every other one. A hotspot is drawn as a square inscribed in the disc's
// image (half-side f·radius/√2, f the view's focal length in pixels), so no two overlap at any heading or zoom.
const HOTSPOT_BASE = 100;     // CSS px of a hotspot's box before scaling (its text is sized for this box)
const TRANSITION_MS = 600;    // crossfade between panoramas (PSV's fade), under a second
const FACE_BELOW_DEG = 25;    // opening a panorama looks this far above its nearest hotspot (on the floor)
let tour = null, markers = null;

function initTour() {
  tour = new Viewer({ container: 'tour', navbar: ['zoom', 'move', 'caption', 'fullscreen'], loadingTxt: 'loading',
    plugins: [[MarkersPlugin, { defaultHoverScale: null }]], defaultZoomLvl: 0 });
  markers = tour.getPlugin(MarkersPlugin);
  markers.addEventListener('select-marker', ({ marker }) => moveTo(marker.data.target));
  tour.addEventListener('panorama-loaded', () => { hooks.loadedAt = performance.now(); });
  tour.addEventListener('click', ({ data }) => { if (measuring.on && !data.marker) measureClick(data); });
  document.getElementById('measure').addEventListener('click', () => {
    measuring.on = !measuring.on;
    measuring.points = [];
    document.getElementById('measure').classList.toggle('active', measuring.on);
    clearMeasureMarks();
    document.getElementById('measure-result').textContent = measuring.on ? 'click two points in the panorama' : '';
  });
}

// ------------------------------------------------------------------------------------------------ measuring
// Two clicks in a panorama: the server reads both ranges from its depth map and gives the distance with its
// standard error (metres when a scale is stated, else model units), or says why it cannot.
const measuring = { on: false, points: [] };
function clearMeasureMarks() {
  for (const id of ['measure-A', 'measure-B']) {
    if (markers.getMarkers().some((m) => m.id === id)) markers.removeMarker(id);
  }
}
async function measureClick(data) {
  const name = hooks.tour && hooks.tour.name;
  const size = imageSize.get(name);
  if (!size) return;
  if (measuring.points.length === 2) { measuring.points = []; clearMeasureMarks(); }
  const px = [(data.yaw / (2 * Math.PI) + 0.5) * size[0], (0.5 - data.pitch / Math.PI) * size[1]];
  const id = measuring.points.length ? 'measure-B' : 'measure-A';
  const dotEl = document.createElement('div');
  dotEl.className = 'measure-dot';
  markers.addMarker({ id, position: { yaw: data.yaw, pitch: data.pitch }, anchor: 'center center', element: dotEl });
  measuring.points.push(px);
  const out = document.getElementById('measure-result');
  if (measuring.points.length < 2) { out.textContent = 'click the second point'; return; }
  const [a, b] = measuring.points;
  const r = await api(`/api/measure?image=${encodeURIComponent(name)}&a=${a[0]},${a[1]}&b=${b[0]},${b[1]}`);
  const body = await r.json();
  hooks.measured = body;
  out.textContent = r.ok ? `${body.distance.toFixed(3)} ± ${body.sigma.toFixed(3)} ${body.units} ` +
    `(ranges ${body.ranges.map((v, i) => `${v.toFixed(2)} ± ${body.range_sigmas[i].toFixed(2)}`).join(', ')})`
    : `not measured: ${body.error}`;
}
hooks.measurePixels = async (a, b) => {  // tests: the same request as two clicks
  const name = hooks.tour.name;
  const r = await api(`/api/measure?image=${encodeURIComponent(name)}&a=${a[0]},${a[1]}&b=${b[0]},${b[1]}`);
  return { ok: r.ok, ...(await r.json()) };
};

function tourHint(text) {
  const el = document.getElementById('tour-hint');
  el.hidden = !text;
  el.textContent = text || '';
}

// Scale of a hotspot's box for the current zoom: its half-side is f·radius/√2 pixels.
function hotspotScale(radius, el) {
  return (zoomLevel) => {
    const vfov = THREE.MathUtils.degToRad(tour.dataHelper.zoomLevelToFov(zoomLevel));
    const f = tour.state.size.height / 2 / Math.tan(vfov / 2);
    return (2 * f * radius / Math.SQRT2) / (el.offsetWidth || HOTSPOT_BASE);  // its laid-out size, border included
  };
}

const walkedCameras = () => [...cams.values()].filter((c) => c.walked);

let opening = 0;  // the latest openTour: an older one still loading gives way to it
async function openTour(name, position = null, transition = false, zoom = null) {
  const ticket = ++opening;
  hooks.tour = { name, ready: false };
  selectTab('tour');
  const cam = cams.get(name);
  markers.clearMarkers();
  const spots = cam && cam.walked ? cam.hotspots : [];
  // Opened from the scene or a list: face the nearest hotspot, looking a little above it, so it is in view.
  const facing = spots.length
    ? { yaw: spots[0].yaw, pitch: Math.min(0, spots[0].pitch + FACE_BELOW_DEG * Math.PI / 180) } : { yaw: 0, pitch: 0 };
  const label = cam ? cam.label || name : name;
  const caption = label === name ? name : `${label} · ${name}`;
  await tour.setPanorama(withToken(`/pano/${encodeURIComponent(name)}?width=${TOUR_WIDTH}`),
    { position: position || facing, caption: escapeHtml(caption), showLoader: false, ...(zoom === null ? {} : { zoom }),
      transition: transition ? { speed: TRANSITION_MS, rotation: false, effect: 'fade' } : false });
  if (ticket !== opening) return;
  tourHint(null);
  const info = document.getElementById('tour-info');
  if (!cam || !cam.registered) {
    info.textContent = `${name} is not registered: no neighbours to walk to`;
  } else if (!cam.walked) {
    info.textContent = `${name}: placed ${cam.verdict}, so not in the walk (its position is not confirmed)`;
  } else {
    info.textContent = `${caption}: ${spots.length} hotspot(s) on the floor below the panoramas seen from here; ` +
      `click one to walk there` + (cam.left_out.length ? ` · not linked: ${cam.left_out.map((l) =>
        `${l.label} (${l.reason})`).join('; ')}` : '');
    for (const h of spots) {
      const el = document.createElement('div');
      el.className = 'hotspot';
      el.dataset.target = h.name;
      const text = document.createElement('span');
      text.textContent = h.label;
      const file = document.createElement('span');  // the file name, for screen readers and searches; not drawn
      file.className = 'file';
      file.textContent = h.name;
      el.append(text, file);
      markers.addMarker({ id: `to-${h.name}`, position: { yaw: h.yaw, pitch: h.pitch }, anchor: 'center center',
        element: el, data: { target: h.name }, scale: hotspotScale(h.radius, el), hoverScale: null,
        tooltip: escapeHtml(h.label === h.name ? h.name : `${h.label} · ${h.name}`) });  // PSV tooltips are HTML
    }
  }
  hooks.tour = { name, ready: true, hotspots: spots, neighbours: cam ? cam.neighbours : [] };
  prefetch(spots.map((h) => h.name));
}

// The panoramas one click away, fetched ahead (the server lets the browser cache them): a walk then waits for the
// fade only, not for the server to encode and send the next panorama.
const prefetched = new Set();
function prefetch(names) {
  for (const name of names) {
    if (prefetched.has(name)) continue;
    prefetched.add(name);
    fetch(withToken(`/pano/${encodeURIComponent(name)}?width=${TOUR_WIDTH}`)).catch(() => prefetched.delete(name));
  }
}
hooks.openTour = (name) => openTour(name);

// Walk to a neighbour keeping the world direction of the view: first the current panorama is magnified as a
// step forward would magnify what lies ahead (a surface at range r, seen along the view, grows by r / (r − s) when
// the camera moves s towards it: s the step's component along the view, r the depth found beyond the neighbour),
// then the next panorama is crossfaded in while the zoom returns. Timed: hooks.transitions.
const STEP_MS = 250;          // the magnification's duration (before the 600 ms fade)
const MAX_STEP_ZOOM = 2.5;    // never magnified more than this
async function moveTo(target) {
  const from = cams.get(hooks.tour.name), to = cams.get(target);
  const view = fromYawPitch(tour.getPosition());
  const world = mulT(from.R_cam_from_world, view);
  const zoom = tour.getZoomLevel();
  const start = performance.now();
  const spot = (hooks.tour.hotspots || []).find((h) => h.name === target);
  if (spot && spot.beyond) {
    const s = spot.walk_distance * Math.max(0, dot(view, spot.walk_bearing));
    const m = Math.min(MAX_STEP_ZOOM, spot.beyond / Math.max(spot.beyond - s, spot.beyond / MAX_STEP_ZOOM));
    if (m > 1.05) {
      const fov = tour.dataHelper.zoomLevelToFov(zoom) * Math.PI / 180;
      const narrower = 2 * Math.atan(Math.tan(fov / 2) / m) * 180 / Math.PI;
      await tour.animate({ zoom: tour.dataHelper.fovToZoomLevel(narrower), speed: STEP_MS });
    }
  }
  await openTour(target, yawPitch(mul(to.R_cam_from_world, world)), true, zoom);
  const end = performance.now();  // ms: click to done (step, loading the next panorama, fade); fade_ms: the fade
  (hooks.transitions = hooks.transitions || []).push({ from: from.name, to: target, ms: end - start,
    fade_ms: end - Math.max(start, hooks.loadedAt || start) });
}
hooks.moveTo = moveTo;
// Boxes of the hotspots on screen (tests check that none overlap).
hooks.hotspotBoxes = () => [...document.querySelectorAll('.psv-marker--visible .hotspot')].map((el) => {
  const r = el.getBoundingClientRect();
  return { target: el.dataset.target, left: r.left, top: r.top, right: r.right, bottom: r.bottom };
});
hooks.registeredNames = () => [...cams.values()].filter((c) => c.registered).map((c) => c.name);
hooks.tourPosition = () => tour.getPosition();
hooks.tourLookAt = (position) => tour.rotate(position);

// ------------------------------------------------------------------------------------------------ correlated views
const corr = { views: [], tracks: [], current: -1 };

function initCorr() {
  const list = document.getElementById('corr-pick-list');
  const names = state.images.map((i) => i.name);
  const chosen = names.slice(0, Math.min(4, names.length));
  list.replaceChildren();
  for (const name of names) {
    const label = document.createElement('label');
    const box = document.createElement('input');
    box.type = 'checkbox';
    box.value = name;
    box.checked = chosen.includes(name);
    label.append(box, ` ${name}`);
    box.addEventListener('change', () => {
      const on = [...list.querySelectorAll('input:checked')].map((i) => i.value);
      if (on.length > 4) { box.checked = false; return; }
      buildCorrViews(on);
    });
    list.appendChild(label);
  }
  buildCorrViews(chosen);
  document.getElementById('show-matches').addEventListener('change', redrawAll);
  document.getElementById('show-depth').addEventListener('change', redrawAll);
  document.getElementById('pick-mode').addEventListener('change', (e) => {
    document.getElementById('picker').hidden = !e.target.checked;
    redrawAll();
  });
  document.getElementById('new-track').addEventListener('click', newTrack);
  document.getElementById('save-tracks').addEventListener('click', saveTracks);
  document.getElementById('rerun').addEventListener('click', rerun);
}

function buildCorrViews(names) {
  const box = document.getElementById('corr-views');
  box.replaceChildren();
  corr.views = names.map((name) => {
    const div = document.createElement('div');
    div.className = 'corr';
    const canvas = document.createElement('canvas');
    div.appendChild(canvas);
    const label = document.createElement('span');
    label.className = 'label';
    label.textContent = name + (cams.get(name)?.registered ? '' : ' (not registered)');
    div.appendChild(label);
    box.appendChild(div);
    const view = { name, canvas, image: new Image(), depth: null, overlay: null };
    [view.W, view.H] = imageSize.get(name);
    view.image.onload = () => { canvas.width = view.image.width; canvas.height = view.image.height; redraw(view); };
    view.image.src = withToken(`/pano/${encodeURIComponent(name)}?width=${CORR_WIDTH}`);
    canvas.addEventListener('click', (e) => onCorrClick(view, e));
    return view;
  });
  corr.matches = null;
}

// Full-size pixel of a click on a view's canvas.
function clickPixel(view, event) {
  const rect = view.canvas.getBoundingClientRect();
  return [(event.clientX - rect.left) / rect.width * view.W, (event.clientY - rect.top) / rect.height * view.H];
}
// Page position of a full-size pixel of a view (tests click there).
hooks.viewPagePosition = (name, x, y) => {
  const view = corr.views.find((v) => v.name === name);
  view.canvas.scrollIntoView({ block: 'nearest' });
  const rect = view.canvas.getBoundingClientRect();
  return [rect.left + x / view.W * rect.width, rect.top + y / view.H * rect.height];
};

async function onCorrClick(view, event) {
  const px = clickPixel(view, event);
  if (document.getElementById('pick-mode').checked) return pick(view, px);
  const cam = cams.get(view.name);
  if (!cam || !cam.registered) return;
  const w = mulT(cam.R_cam_from_world, pixelToBearing(px[0], px[1], view.W, view.H));  // world direction of the ray
  const point = await pointOnRay(cam.center, w);
  const result = { view: view.name, pixel: px, circles: {}, markers: {}, point };
  for (const other of corr.views) {
    const oc = cams.get(other.name);
    other.overlay = null;
    if (other === view || !oc || !oc.registered) continue;
    const normal = mul(oc.R_cam_from_world, cross(w, sub(oc.center, cam.center)));
    const circle = greatCircle(normal, other.W, other.H);
    const marker = point ? bearingToPixel(mul(oc.R_cam_from_world, sub(point, oc.center)), other.W, other.H) : null;
    other.overlay = { circle, marker };
    result.circles[other.name] = circle;
    if (marker) result.markers[other.name] = marker;
  }
  view.overlay = { clicked: px };
  highlightPoint(point);
  hooks.lastClick = result;
  redrawAll();
}

// The sparse (or dense) point closest in angle to a ray, when within RAY_TOLERANCE.
async function pointOnRay(origin, w) {
  if (!state.model.has_sparse) return null;
  let best = null, bestAngle = RAY_TOLERANCE;
  for (const kind of state.model.has_dense ? ['sparse', 'dense'] : ['sparse']) {
    const { positions, count } = await getCloud(kind);
    for (let k = 0; k < count; k++) {
      const d = [positions[3 * k] - origin[0], positions[3 * k + 1] - origin[1], positions[3 * k + 2] - origin[2]];
      const t = dot(d, w);
      if (t <= 0) continue;
      const angle = Math.atan2(norm(cross(d, w)), t);
      if (angle < bestAngle) { bestAngle = angle; best = [positions[3 * k], positions[3 * k + 1], positions[3 * k + 2]]; }
    }
    if (best) break;  // a sparse point is the better-supported answer
  }
  return best;
}

function redrawAll() { corr.views.forEach(redraw); maybeLoadMatches(); }

function redraw(view) {
  const ctx = view.canvas.getContext('2d');
  if (!view.image.complete || !view.canvas.width) return;
  const sx = view.canvas.width / view.W, sy = view.canvas.height / view.H;
  ctx.drawImage(view.image, 0, 0);
  if (document.getElementById('show-depth').checked) drawDepth(view, ctx);
  if (document.getElementById('show-matches').checked && corr.matches) drawMatches(view, ctx, sx, sy);
  ctx.lineWidth = Math.max(2, view.canvas.width / 800);
  if (view.overlay?.circle) {
    ctx.strokeStyle = '#00ff66';
    for (const seg of view.overlay.circle) {
      ctx.beginPath();
      seg.forEach(([x, y], k) => (k ? ctx.lineTo(x * sx, y * sy) : ctx.moveTo(x * sx, y * sy)));
      ctx.stroke();
    }
  }
  if (view.overlay?.marker) dot2d(ctx, view.overlay.marker[0] * sx, view.overlay.marker[1] * sy, '#ff2222', 8);
  if (view.overlay?.clicked) dot2d(ctx, view.overlay.clicked[0] * sx, view.overlay.clicked[1] * sy, '#ffff00', 6);
  if (document.getElementById('pick-mode').checked) drawTracks(view, ctx, sx, sy);
}

function dot2d(ctx, x, y, color, r) {
  ctx.fillStyle = color;
  ctx.beginPath();
  ctx.arc(x, y, r, 0, 2 * Math.PI);
  ctx.fill();
}

function drawDepth(view, ctx) {
  if (!view.depth) {
    view.depth = new Image();
    view.depth.onload = () => redraw(view);
    view.depth.onerror = () => { view.depth.failed = true; };
    view.depth.src = withToken(`/depth/${encodeURIComponent(view.name)}`);
    return;
  }
  if (view.depth.complete && !view.depth.failed) {
    ctx.globalAlpha = 0.6;
    ctx.drawImage(view.depth, 0, 0, view.canvas.width, view.canvas.height);
    ctx.globalAlpha = 1;
  }
}

async function maybeLoadMatches() {
  if (!document.getElementById('show-matches').checked || corr.views.length < 2) return;
  const [a, b] = corr.views;
  const key = `${a.name}|${b.name}`;
  if (corr.matchesKey === key) return;
  corr.matchesKey = key;
  corr.matches = await getJSON(`/api/matches?a=${encodeURIComponent(a.name)}&b=${encodeURIComponent(b.name)}`);
  redraw(a); redraw(b);
}

function drawMatches(view, ctx, sx, sy) {
  const index = corr.views.indexOf(view);
  if (index > 1) return;
  corr.matches.forEach((m, k) => {
    const hue = (k * 47) % 360;
    dot2d(ctx, m[2 * index] * sx, m[2 * index + 1] * sy, `hsl(${hue} 90% 55%)`, 3);
  });
}

// ------------------------------------------------------------------------------------------------ hand points
async function loadTracks() {
  corr.tracks = (await getJSON('/api/hand_points')).map((t) => ({ name: t.name, observations: t.observations }));
  corr.current = corr.tracks.length - 1;
  renderTracks();
  await checkTracks();
}

function newTrack() {
  const used = new Set(corr.tracks.map((t) => t.name));
  let k = corr.tracks.length;
  while (used.has(`point_${k}`)) k++;
  corr.tracks.push({ name: `point_${k}`, observations: {} });
  corr.current = corr.tracks.length - 1;
  renderTracks();
}

function pick(view, px) {
  if (corr.current < 0) newTrack();
  corr.tracks[corr.current].observations[view.name] = [Math.round(px[0] * 100) / 100, Math.round(px[1] * 100) / 100];
  renderTracks();
  redrawAll();
  checkTracks();
}

// Pairs with >= 8 shared tracks: the F they give (server-side geometry), its epipolar circles for the current
// track, and the tracks far from their circles.
async function checkTracks() {
  const r = await post('/api/hand_check', { points: corr.tracks });
  const body = await r.json();
  corr.check = r.ok ? body : null;
  hooks.handCheck = corr.check;
  renderTracks();
  redrawAll();
}

function handCircles(view) {
  const t = corr.tracks[corr.current];
  if (!corr.check || !t) return [];
  const circles = [];
  for (const pair of corr.check.pairs) {
    const other = pair.a === view.name ? pair.b : pair.b === view.name ? pair.a : null;
    const xy = other && t.observations[other];
    if (!xy) continue;
    const [W, H] = imageSize.get(other);
    const b = pixelToBearing(xy[0], xy[1], W, H);
    const F = pair.F;  // b_aᵀ F b_b = 0
    const normal = pair.a === other ? mulT(F, b) : mul(F, b);
    circles.push(greatCircle(normal, view.W, view.H));
  }
  return circles;
}

function renderTracks() {
  const list = document.getElementById('tracks');
  list.replaceChildren();
  corr.tracks.forEach((t, k) => {
    const li = document.createElement('li');
    const flagged = corr.check ? corr.check.pairs.filter((p) => p.flagged.includes(t.name)) : [];
    li.className = (k === corr.current ? 'current ' : '') + (flagged.length ? 'flagged' : '');
    li.title = flagged.map((p) => `${p.a}–${p.b}: ${p.errors_deg[t.name].toFixed(2)}° from its epipolar circle`)
      .join('\n');
    const input = document.createElement('input');
    input.value = t.name;
    input.addEventListener('change', () => { t.name = input.value; });
    const count = document.createElement('span');
    count.textContent = ` ${Object.keys(t.observations).length} observation(s) `;
    const select = document.createElement('button');
    select.textContent = 'edit';
    select.addEventListener('click', () => { corr.current = k; renderTracks(); });
    const del = document.createElement('button');
    del.textContent = 'delete';
    del.addEventListener('click', () => { corr.tracks.splice(k, 1); corr.current = corr.tracks.length - 1;
      renderTracks(); redrawAll(); checkTracks(); });
    li.append(input, count, select, del);
    list.appendChild(li);
  });
}

function drawTracks(view, ctx, sx, sy) {
  ctx.strokeStyle = '#ff9933';
  ctx.setLineDash([8, 6]);
  for (const circle of handCircles(view)) {
    for (const seg of circle) {
      ctx.beginPath();
      seg.forEach(([x, y], k) => (k ? ctx.lineTo(x * sx, y * sy) : ctx.moveTo(x * sx, y * sy)));
      ctx.stroke();
    }
  }
  ctx.setLineDash([]);
  corr.tracks.forEach((t, k) => {
    const xy = t.observations[view.name];
    if (!xy) return;
    dot2d(ctx, xy[0] * sx, xy[1] * sy, k === corr.current ? '#ffd58a' : '#ff66ff', 6);
    ctx.fillStyle = '#fff';
    ctx.font = `${Math.max(12, view.canvas.width / 120)}px sans-serif`;
    ctx.fillText(t.name, xy[0] * sx + 8, xy[1] * sy - 8);
  });
}

async function saveTracks() {
  const status = document.getElementById('picker-status');
  const points = corr.tracks.filter((t) => Object.keys(t.observations).length >= 2);
  const r = await post('/api/hand_points', { points });
  const body = await r.json();
  status.textContent = r.ok ? `saved ${points.length} track(s) to ${body.saved}` +
    (body.backup ? ` (previous file kept as ${body.backup})` : '') + `; rerun: ${body.command}` : `not saved: ${body.error}`;
  hooks.saved = r.ok;
}

async function rerun() {
  const body = await (await post('/api/rerun', {})).json();
  document.getElementById('picker-status').textContent = `pipeline run ${body.rerun}; the page notices when it is done`;
}

// ------------------------------------------------------------------------------------------------ page
/** "a, b, c: reason; d: other reason": images sharing a reason (a whole separate model) are listed once. */
function groupByReason(names, why) {
  const groups = new Map();
  names.forEach((n) => {
    const reason = why[n] || 'no reason recorded';
    if (!groups.has(reason)) groups.set(reason, []);
    groups.get(reason).push(n);
  });
  return [...groups].map(([reason, members]) => `${members.join(', ')}: ${reason}`).join('; ');
}

const TABS = ['scene', 'tour', 'corr'];

// A tab shown (by a click or the address' #hash, kept in the address): the tour shows a panorama as soon as the
// reconstruction is known (the first walked camera unless one is open), and a hint until then — never a blank page.
function selectTab(name) {
  if (!TABS.includes(name)) name = 'scene';
  document.querySelectorAll('.tab').forEach((b) => b.classList.toggle('active', b.dataset.tab === name));
  document.querySelectorAll('.tabpage').forEach((p) => p.classList.toggle('active', p.id === `tab-${name}`));
  if (location.hash !== `#${name}`) history.replaceState(null, '', `${location.pathname}${location.search}#${name}`);
  if (name === 'tour' && tour) {
    tour.autoSize();
    if (!hooks.tour) openFirstPanorama();
  }
}

function openFirstPanorama() {
  if (!state) return tourHint('loading the reconstruction…');
  const first = walkedCameras()[0] || [...cams.values()].find((c) => c.registered);
  if (first) return openTour(first.name);
  if (state.images.length) {
    tourHint(state.model ? 'no panorama is placed in the model: showing the first one, without hotspots'
      : 'this dataset has not been reconstructed yet: showing the first panorama, without hotspots');
    return openTour(state.images[0].name);
  }
  tourHint('this dataset has no panoramas');
}

async function poll() {
  try {
    const now = await getJSON('/api/generation');
    showMessage(now.generation !== state.generation, 'changed');
    if (now.rerun) document.getElementById('picker-status').textContent = now.rerun;
  } catch (e) {
    showMessage(`lost the viewer server: ${e.message}`);
  }
}

async function main() {
  document.querySelectorAll('.tab').forEach((b) => b.addEventListener('click', () => selectTab(b.dataset.tab)));
  initTour();
  selectTab(location.hash.slice(1) || 'scene');
  if (!TOKEN) throw new Error('this address has no token: open the URL `fullview view` printed');
  state = await getJSON('/api/state');
  document.getElementById('title').textContent = `fullview · ${state.dataset}`;
  document.getElementById('stages').textContent = Object.entries(state.stages)
    .map(([s, st]) => `${s}: ${st.state}`).join(' · ');
  state.images.forEach((i) => imageSize.set(i.name, i.size));
  const messages = [state.message];
  document.getElementById('reload').addEventListener('click', () => location.reload());
  if (state.model) {
    state.model.cameras.forEach((c) => cams.set(c.name, c));
    if (state.model.unregistered.length) {
      messages.push('not in this model: ' + groupByReason(state.model.unregistered,
                                                          state.model.unregistered_reasons || {}));
    }
    const t = state.model.tour;
    if (t.names_problem) messages.push(`room names: ${t.names_problem} (numbers used)`);
    if (t.left_apart.length) messages.push(`not in the walk (placement not confirmed): ${t.left_apart.join(', ')}`);
  }
  showMessage(messages.filter(Boolean).join(' — '));
  if (document.getElementById('tab-tour').classList.contains('active') && !hooks.tour) openFirstPanorama();
  if (state.model) {
    initScene();
    buildScene(state.model);
    document.querySelector('#cloud option[value=mesh]').disabled = !state.model.has_mesh;
    document.getElementById('cloud').value = state.model.has_mesh ? 'mesh' : state.model.has_dense ? 'dense'
      : 'sparse';
    await showCloud(document.getElementById('cloud').value);
    document.getElementById('cloud').addEventListener('change', (e) => showCloud(e.target.value));
    document.getElementById('budget').addEventListener('input', applyBudget);
  }
  initCorr();
  await loadTracks();
  setInterval(poll, 3000);
  hooks.ready = true;
}

main().catch((e) => { showMessage(`the viewer failed to start: ${e.message}`); hooks.errors.push(String(e)); });
