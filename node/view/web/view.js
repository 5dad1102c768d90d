// vlff's own page: a foxglove.websocket.v1 client of vlff-view that draws the
// labelled voxels with three.js, the camera and label images, the legend and the
// node's status, and posts prompt sets when the server offers clientPublish.
// Relative imports, no import map: the page's Content-Security-Policy allows no
// inline script (node/view/CMakeLists.txt points OrbitControls at three.module.js).
import * as THREE from './three/three.module.js';
import { OrbitControls } from './three/addons/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const FREE = 65534;
const ws = new WebSocket(`ws://${location.host}/`, 'foxglove.websocket.v1');
ws.binaryType = 'arraybuffer';
const topics = {};            // subscription id (= channel id) -> topic
const map = { vox: new Map(), prompts: [], colors: [], version: 0 };
let mesh = null, order = [], promptChannel = 0;

// --- the 3D view
const host = $('scene');
const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
host.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0x111111);
scene.add(new THREE.HemisphereLight(0xffffff, 0x444444, 2.5));
const camera = new THREE.PerspectiveCamera(50, 1, 0.05, 200);
camera.up.set(0, 0, 1);       // the map's z is up
camera.position.set(-4, -6, 7);
const controls = new OrbitControls(camera, renderer.domElement);
const cameraMark = new THREE.AxesHelper(0.4);
cameraMark.visible = false;
scene.add(cameraMark);
function resize() {
  renderer.setSize(host.clientWidth, host.clientHeight);
  camera.aspect = host.clientWidth / Math.max(1, host.clientHeight);
  camera.updateProjectionMatrix();
  redraw();
}
window.addEventListener('resize', resize);
// draw only when something changed: a software-rendered browser stays responsive
let dirty = true;
const redraw = () => { dirty = true; };
controls.addEventListener('change', redraw);
renderer.setAnimationLoop(() => { if (dirty) { dirty = false; renderer.render(scene, camera); } });
resize();

function rebuild(centre) {
  if (mesh) { scene.remove(mesh); mesh.geometry.dispose(); mesh.material.dispose(); }
  const s = map.voxel_size, [nx, ny] = map.dims;
  mesh = new THREE.InstancedMesh(new THREE.BoxGeometry(s * 0.96, s * 0.96, s * 0.96),
    new THREE.MeshLambertMaterial(), Math.max(1, map.vox.size));
  order = [...map.vox.keys()];
  const m = new THREE.Matrix4(), c = new THREE.Color();
  order.forEach((idx, n) => {
    const i = idx % nx, j = Math.floor(idx / nx) % ny, k = Math.floor(idx / (nx * ny));
    m.makeTranslation(...voxelCentre(i, j, k));
    mesh.setMatrixAt(n, m);
    mesh.setColorAt(n, c.set(map.colors[map.vox.get(idx)[0]] || '#808080'));
  });
  mesh.count = order.length;
  scene.add(mesh);
  if (centre) {
    controls.target.set(...voxelCentre(map.dims[0] / 2, map.dims[1] / 2, 0));
    camera.position.copy(controls.target).add(new THREE.Vector3(-0.3, -0.7, 1.25).multiplyScalar(nx * s));
    controls.update();
  }
  redraw();
}
const voxelCentre = (i, j, k) => [0, 1, 2].map((a) => map.origin[a] + ([i, j, k][a] + 0.5) * map.voxel_size);

// --- picking: the voxel under a point of the window
const ray = new THREE.Raycaster(), ndc = new THREE.Vector2();
function pickAt(x, y) {
  const r = renderer.domElement.getBoundingClientRect();
  ndc.set(((x - r.left) / r.width) * 2 - 1, -((y - r.top) / r.height) * 2 + 1);
  ray.setFromCamera(ndc, camera);
  const hit = mesh && ray.intersectObject(mesh)[0];
  if (!hit) return null;
  const idx = order[hit.instanceId], [label, conf] = map.vox.get(idx);
  return { idx, label, conf, prompt: map.prompts[label] ?? '(none)', point: hit.point };
}
// the pointer's last place over the view: the text is picked again there when the
// map changes under a still pointer
let pointer = null;
function showPick() {
  const h = pointer && pickAt(pointer.x, pointer.y), p = h && h.point;
  $('pick').textContent = h ? `label ${h.label} prompt ${h.prompt} confidence ${h.conf} ` +
    `at (${p.x.toFixed(2)}, ${p.y.toFixed(2)}, ${p.z.toFixed(2)}) map version ${map.version}` : 'point at a voxel';
}
renderer.domElement.addEventListener('pointermove', (e) => { pointer = { x: e.clientX, y: e.clientY }; showPick(); });
renderer.domElement.addEventListener('pointerleave', () => { pointer = null; showPick(); });
// where a voxel's centre is on the screen (for scripts and the browser console)
function screenOf(idx) {
  const [nx, ny] = map.dims, v = new THREE.Vector3(...voxelCentre(idx % nx, Math.floor(idx / nx) % ny,
    Math.floor(idx / (nx * ny)))).project(camera), r = renderer.domElement.getBoundingClientRect();
  return { x: r.left + (v.x + 1) / 2 * r.width, y: r.top + (1 - v.y) / 2 * r.height };
}
window.vlff = { map, pickAt, screenOf, render: () => renderer.render(scene, camera) };

// --- messages
let fresh = false; // a new map's voxels are coming: centre the view once they are drawn
function onVoxels(d) {
  fresh ||= d.full || !map.dims || d.dims.join() !== map.dims.join();
  if (d.full) map.vox.clear();
  Object.assign(map, { version: d.version, origin: d.origin, voxel_size: d.voxel_size, dims: d.dims,
    prompts: d.prompts, colors: d.colors });
  const v = d.voxels;
  for (let n = 0; n < v.length; n += 3) {
    if (v[n + 1] >= FREE) map.vox.delete(v[n]); else map.vox.set(v[n], [v[n + 1], v[n + 2]]);
  }
  // a version in pieces is drawn once, at its last piece (no piece numbers: one piece)
  if ((d.piece ?? 0) + 1 < (d.pieces ?? 1)) return;
  rebuild(fresh && !mesh);
  fresh = false;
  if (pointer) showPick();
  document.body.dataset.version = d.version;
  $('legend').replaceChildren(...d.prompts.map((p, i) => {
    // the swatch's colour set through the DOM: the CSP refuses style attributes in markup
    const li = document.createElement('li'), sw = document.createElement('span');
    sw.style.background = d.colors[i];
    li.append(sw, p);
    return li;
  }));
}
// Images are drawn at the display's pace, the latest one per canvas: a page
// on a busy machine skips the frames it could not draw instead of falling
// behind on every message, prompt replies included.
const latestImage = new Map();
function onImage(canvas, d) {
  if (!latestImage.size) requestAnimationFrame(drawImages);
  latestImage.set(canvas, d);
}
function drawImages() {
  latestImage.forEach((d, canvas) => drawImage(canvas, d));
  latestImage.clear();
}
// foxglove.CompressedImage (JPEG camera, PNG labels), decoded by the browser off
// the main thread; a canvas takes its image's size.
function drawImage(canvas, d) {
  const bytes = Uint8Array.from(atob(d.data), (ch) => ch.charCodeAt(0));
  createImageBitmap(new Blob([bytes], { type: `image/${d.format}` })).then((bmp) => {
    if (canvas.width !== bmp.width || canvas.height !== bmp.height) { canvas.width = bmp.width; canvas.height = bmp.height; }
    canvas.getContext('2d').drawImage(bmp, 0, 0);
    bmp.close();
  }, (e) => { $('msg').textContent = `an image on ${canvas.id} could not be decoded: ${e.message}`; });
}
function onStatus(d) {
  const set = (id, v) => { $(id).textContent = v; };
  set('s-version', d.map.version);
  set('s-age', d.map.age_s === null ? '-' : d.map.age_s.toFixed(1));
  set('s-alive', d.map.writer_alive ? 'yes' : 'no');
  set('s-generation', d.map.generation);
  set('s-dims', d.map.dims.join(' x '));
  set('s-occupied', d.map.occupied);
  set('s-frames', d.frames.attached ? d.frames.head : '-');
  set('s-fps', d.frames.fps.toFixed(1));
  set('s-clients', d.viewer.clients);
  onLearner(d.learner);
}
// The learner's own numbers, as the map segment carries them (null before the
// learner set any); shown as received, so they read as vlff-shm stat prints them.
function onLearner(l) {
  const set = (id, v) => { $(id).textContent = v === null || v === undefined ? '-' : String(v); };
  document.body.dataset.learnerUpdates = l ? l.updates : '';
  for (const k of ['frames_in', 'frames_lost', 'frames_refused', 'keyframes', 'iterations', 'iterations_per_s',
    'loss', 'psnr']) set(`l-${k}`, l && l[k]);
  set('l-state', l && l.state);
  set('l-terms', l && [l.loss_rgb, l.loss_depth, l.loss_feat].map((v) => (v === null ? '-' : v)).join(' | '));
  const ul = $('refusals');
  ul.replaceChildren();
  for (const r of l ? l.refused : []) {
    if (!r.count) continue;
    const li = document.createElement('li');
    li.textContent = `${r.reason}: ${r.count}`;
    ul.append(li);
  }
}
function onPose(d) {
  cameraMark.visible = true;
  cameraMark.position.set(d.translation.x, d.translation.y, d.translation.z);
  cameraMark.quaternion.set(d.rotation.x, d.rotation.y, d.rotation.z, d.rotation.w);
  redraw();
}
const handlers = { '/map/voxels': onVoxels, '/camera/image': (d) => onImage($('image'), d),
  '/camera/labels': (d) => onImage($('labels'), d), '/tf': onPose, '/vlff/status': onStatus };

// Reconnecting reloads the page; the wait doubles from 3 s up to 60 s while the
// viewer keeps refusing or is away (kept across reloads in sessionStorage) and
// starts over once a connection opens.
const RETRY_KEY = 'vlff-view-retry-s';
ws.onopen = () => { $('conn').textContent = 'live'; sessionStorage.removeItem(RETRY_KEY); };
ws.onclose = (e) => {
  const last = Number(sessionStorage.getItem(RETRY_KEY)) || 0, wait = last ? Math.min(60, last * 2) : 3;
  sessionStorage.setItem(RETRY_KEY, String(wait));
  $('conn').textContent = `closed ${e.code} ${e.reason}; reconnecting in ${wait} s`;
  $('conn').style.color = '#c66';
  setTimeout(() => location.reload(), wait * 1000);
};
ws.onmessage = (ev) => {
  if (typeof ev.data === 'string') {
    const m = JSON.parse(ev.data);
    if (m.op === 'serverInfo') {
      // the editor only where the server takes prompt sets (vlff-view --token-file)
      const publish = m.capabilities.includes('clientPublish');
      $('editor').hidden = !publish;
      $('editor-fields').disabled = !publish;
    }
    if (m.op === 'status') $('msg').textContent = m.message;
    if (m.op === 'advertise') {
      const subs = m.channels.filter((c) => handlers[c.topic]).map((c) => ({ id: c.id, channelId: c.id }));
      m.channels.forEach((c) => { topics[c.id] = c.topic; });
      ws.send(JSON.stringify({ op: 'subscribe', subscriptions: subs }));
    }
    return;
  }
  const dv = new DataView(ev.data);
  if (dv.getUint8(0) !== 1) return;
  const topic = topics[dv.getUint32(1, true)];
  handlers[topic](JSON.parse(new TextDecoder().decode(new Uint8Array(ev.data, 13))));
};

$('editor').addEventListener('submit', (e) => {
  e.preventDefault();
  const prompts = $('prompts').value.split('\n').map((s) => s.trim()).filter(Boolean);
  if (!promptChannel) {
    promptChannel = 1;
    ws.send(JSON.stringify({ op: 'advertise', channels: [{ id: promptChannel, topic: '/vlff/prompts',
      encoding: 'json', schemaName: 'vlff.PromptSet' }] }));
  }
  const body = new TextEncoder().encode(JSON.stringify({ token: $('token').value, prompts }));
  const msg = new Uint8Array(5 + body.length);
  msg[0] = 1;
  new DataView(msg.buffer).setUint32(1, promptChannel, true);
  msg.set(body, 5);
  ws.send(msg);
});
