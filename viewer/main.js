// ms3d viewer: three.js + 3d-tiles-renderer, no online service. Loads ?tileset=URL (default
// /output/tileset.json), colours faces by the EXT_structural_metadata provenance (grade, source, region)
// or by each face's signed scan-to-model distance (mode "deviation": the face_quality table of the leaves),
// or shows the textures, and prints the provenance of a clicked face. ?label=1: the labelling mode (label.js).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { DRACOLoader } from 'three/addons/loaders/DRACOLoader.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import { KTX2Loader } from 'three/addons/loaders/KTX2Loader.js';
import { TilesRenderer } from '3d-tiles-renderer';
import { GLTFExtensionsPlugin, ImplicitTilingPlugin, ReorientationPlugin } from '3d-tiles-renderer/plugins';
import { NO_DEVIATION, deviationColour } from './deviation.js';
import { setupLabelling } from './label.js';
import { describeMeasure, measureBetween } from './measure.js';

const params = new URLSearchParams(location.search);
const tilesetUrl = params.get('tileset') || '/output/tileset.json';
let mode = params.get('mode') || 'grade';
document.getElementById('mode').value = mode;

const COLOURS = { good: [0x3f, 0xa3, 0x4d], bad: [0xd9, 0x41, 0x2e], rebuilt: [0x2f, 0x6f, 0xde], unknown: [0x9a, 0x9a, 0x9a] };
const state = { ready: false, models: 0, faces: { good: 0, bad: 0, rebuilt: 0, unknown: 0 }, errors: [], pick: null };
window.ms3d = state;
state.debug = () => ({ root: !!tiles.root, rootTileset: !!tiles.rootTileset, stats: { ...tiles.stats }, framed, cam: camera.position.toArray(), group: tiles.group.position.toArray(), children: tiles.group.children.length });

const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
renderer.setPixelRatio(1);
renderer.setSize(innerWidth, innerHeight);
renderer.setClearColor(0xdde4ea);
document.body.appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x667788, 2.0));
const sun = new THREE.DirectionalLight(0xffffff, 1.5);
sun.position.set(0.4, 1.0, 0.3);
scene.add(sun);
const camera = new THREE.PerspectiveCamera(45, innerWidth / innerHeight, 0.5, 20000);
const controls = new OrbitControls(camera, renderer.domElement);

const draco = new DRACOLoader().setDecoderPath('/node_modules/three/examples/jsm/libs/draco/gltf/');
const tiles = new TilesRenderer(tilesetUrl);
// KTX2 / Basis textures are transcoded for this GPU (detectSupport after the renderer exists)
const ktx2 = new KTX2Loader().setTranscoderPath('/node_modules/three/examples/jsm/libs/basis/').detectSupport(renderer);
tiles.registerPlugin(new GLTFExtensionsPlugin({ metadata: true, dracoLoader: draco, meshoptDecoder: MeshoptDecoder, ktxLoader: ktx2 }));
tiles.registerPlugin(new ImplicitTilingPlugin());  // export.tiling: implicit (subtrees; not a default plugin)
tiles.registerPlugin(new ReorientationPlugin({ recenter: true }));
tiles.errorTarget = Number(params.get('errorTarget') || 8);  // pixels of screen-space error
// GPU bytes of loaded tiles kept (3d-tiles-renderer's default is 0.4 GB): textured LOD parents and photo
// leaves outgrow it on a street (0.5 GB of leaf textures for one production), ?cacheMB= to change it
tiles.lruCache.maxBytesSize = Number(params.get('cacheMB') || 1024) * 2 ** 20;
tiles.lruCache.minBytesSize = Math.min(tiles.lruCache.minBytesSize, tiles.lruCache.maxBytesSize * 0.75);
tiles.setCamera(camera);
tiles.setResolutionFromRenderer(camera, renderer);
scene.add(tiles.group);

// Deviation mode: the face_quality table's deviation_m through the diverging ramp of deviation.js.
state.deviation = { faces: 0, absent: 0 };
state.deviationColour = deviationColour;

// the per-vertex colours of the deviation mode (leaves: a vertex per face corner, _FEATURE_ID_1 = the face's
// row of the face_quality table); null where the mesh has no such table (LOD parents: all grey)
function deviationColours(geometry, meshFeatures, structuralMetadata) {
  const count = geometry.getAttribute('position').count;
  const out = new Float32Array(count * 3);
  const info = meshFeatures.getFeatureInfo().find((f) => f.label === 'face_quality');
  const ids = info ? geometry.getAttribute(`_feature_id_${info.attribute}`) : null;
  const c = new THREE.Color();
  const rows = new Map();
  for (let i = 0; i < count; i++) {
    let rgb = NO_DEVIATION;
    if (ids) {
      const id = ids.getX(i);
      if (!rows.has(id)) {
        const row = structuralMetadata.getPropertyTableData(info.propertyTable, id);
        rows.set(id, row ? row.deviation_m : null);
      }
      rgb = deviationColour(rows.get(id));
    }
    c.setRGB(rgb[0] / 255, rgb[1] / 255, rgb[2] / 255, THREE.SRGBColorSpace);
    out.set([c.r, c.g, c.b], i * 3);
  }
  for (const d of rows.values()) { state.deviation.faces += 1; if (d === null || !Number.isFinite(d)) state.deviation.absent += 1; }
  return out;
}

function category(row) {
  if (!row) return 'unknown';
  if (row.source === 'rebuilt') return 'rebuilt';
  return row.grade === 'good' || row.grade === 'bad' ? row.grade : 'unknown';
}

// per mesh: the provenance category of each vertex (faces never share vertices across features)
function prepareMesh(mesh) {
  const { meshFeatures, structuralMetadata } = mesh.userData;
  const geometry = mesh.geometry;
  const ids = geometry.getAttribute('_feature_id_0');
  if (!meshFeatures || !structuralMetadata || !ids) return;
  const info = meshFeatures.getFeatureInfo()[0];
  const rows = new Map();
  const colours = new Float32Array(ids.count * 3);
  const c = new THREE.Color();
  for (let i = 0; i < ids.count; i++) {
    const id = ids.getX(i);
    if (!rows.has(id)) rows.set(id, category(structuralMetadata.getPropertyTableData(info.propertyTable, id)));
    const rgb = COLOURS[rows.get(id)];
    c.setRGB(rgb[0] / 255, rgb[1] / 255, rgb[2] / 255, THREE.SRGBColorSpace);
    colours.set([c.r, c.g, c.b], i * 3);
  }
  const index = geometry.getIndex();
  const n = index ? index.count / 3 : ids.count / 3;
  for (let f = 0; f < n; f++) state.faces[rows.get(ids.getX(index ? index.getX(3 * f) : 3 * f))] += 1;
  if (!geometry.getAttribute('normal')) geometry.computeVertexNormals();  // unlit textured primitives carry none
  mesh.userData.ms3d = {
    original: { material: mesh.material, color: geometry.getAttribute('color') || null },
    grade: { material: new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide }),
             color: new THREE.BufferAttribute(colours, 3) },
    deviation: { material: new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide }),
                 color: new THREE.BufferAttribute(deviationColours(geometry, meshFeatures, structuralMetadata), 3) },
  };
  applyMode(mesh);
}

function applyMode(mesh) {
  const m = mesh.userData.ms3d;
  if (!m) return;
  const which = mode === 'grade' ? m.grade : mode === 'deviation' ? m.deviation : m.original;
  mesh.material = which.material;
  if (which.color) mesh.geometry.setAttribute('color', which.color);
  else mesh.geometry.deleteAttribute('color');
}

tiles.addEventListener('load-model', ({ scene: model }) => {
  state.models += 1;
  model.traverse((o) => { if (o.isMesh) { prepareMesh(o); clipMesh(o, afterPlane); } });
});
tiles.addEventListener('load-error', (e) => state.errors.push(String(e.error || e)));

// The MLS points overlay (output/points/tileset.json, written by the export when the tiles have stores):
// a second tileset in the same ECEF frame, kept aligned by copying the mesh tiles' group matrix (the
// ReorientationPlugin recentres that group) every frame. Loaded only while its checkbox is on.
const pointsUrl = params.get('points') || new URL('points/tileset.json', new URL(tilesetUrl, location.href)).pathname;
const pointsBox = document.getElementById('points');
const pointSize = Number(params.get('pointSize') || 2);
state.points = { probed: false, available: false, models: 0, count: 0, shown: false };
let points = null;
pointsBox.checked = params.get('showPoints') === '1';
fetch(pointsUrl, { method: 'HEAD' }).then((r) => {
  state.points.probed = true;
  if (!r.ok) { pointsBox.disabled = true; pointsBox.parentElement.title = 'no points overlay: re-run the export'; return; }
  state.points.available = true;
  points = new TilesRenderer(pointsUrl);
  points.errorTarget = tiles.errorTarget;
  points.setCamera(camera);
  points.setResolutionFromRenderer(camera, renderer);
  points.group.matrixAutoUpdate = false;
  points.addEventListener('load-model', ({ scene: model }) => {
    state.points.models += 1;
    model.traverse((o) => {
      if (!o.isPoints) return;
      o.material.size = pointSize; o.material.sizeAttenuation = false; o.material.vertexColors = true;
      state.points.count += o.geometry.getAttribute('position').count;
    });
  });
  points.addEventListener('load-error', (e) => state.errors.push(String(e.error || e)));
  scene.add(points.group);
}).catch((e) => { state.points.probed = true; state.errors.push(`points overlay: ${e}`); });
pointsBox.addEventListener('change', () => { settled = 0; state.ready = false; });

// Before / after: output/before/tileset.json (the input mesh, written by the export with export.before) in
// the same frame, shown left of a vertical split through the view's centre, the merged model right of it.
// The split is a clipping plane whose normal is the camera's right vector; the slider moves it sideways.
const beforeUrl = params.get('before') || new URL('before/tileset.json', new URL(tilesetUrl, location.href)).pathname;
const compareBox = document.getElementById('compare');
const splitSlider = document.getElementById('split');
const afterPlane = new THREE.Plane(new THREE.Vector3(1, 0, 0), 0);   // keeps the right side: the merged model
const beforePlane = new THREE.Plane(new THREE.Vector3(-1, 0, 0), 0); // keeps the left side: the input
state.before = { probed: false, available: false, models: 0, shown: false, faces: 0 };
let before = null;
compareBox.checked = params.get('compare') === '1';
splitSlider.value = params.get('split') || '0';
function clipMesh(mesh, plane) {
  const mats = [mesh.material, ...Object.values(mesh.userData.ms3d || {}).map((m) => m.material)];
  for (const m of mats) if (m) { m.clippingPlanes = [plane]; m.clipShadows = true; }
}
fetch(beforeUrl, { method: 'HEAD' }).then((r) => {
  state.before.probed = true;
  if (!r.ok) { compareBox.disabled = true; compareBox.parentElement.title = 'no input tileset: export with export.before: true'; return; }
  state.before.available = true;
  before = new TilesRenderer(beforeUrl);
  before.registerPlugin(new GLTFExtensionsPlugin({ metadata: true, dracoLoader: draco, meshoptDecoder: MeshoptDecoder, ktxLoader: ktx2 }));
  before.registerPlugin(new ImplicitTilingPlugin());
  before.errorTarget = tiles.errorTarget;
  before.setCamera(camera);
  before.setResolutionFromRenderer(camera, renderer);
  before.group.matrixAutoUpdate = false;
  before.addEventListener('load-model', ({ scene: model }) => {
    state.before.models += 1;
    model.traverse((o) => {
      if (!o.isMesh) return;
      const counts = { ...state.faces };
      prepareMesh(o);
      state.before.faces += Object.keys(counts).reduce((n, k) => n + state.faces[k] - counts[k], 0);
      Object.assign(state.faces, counts);  // the merged model's counts stay the merged model's
      clipMesh(o, beforePlane);
    });
  });
  before.addEventListener('load-error', (e) => state.errors.push(String(e.error || e)));
  scene.add(before.group);
}).catch((e) => { state.before.probed = true; state.errors.push(`before tileset: ${e}`); });
compareBox.addEventListener('change', () => { settled = 0; state.ready = false; });

function updateBefore() {
  state.before.shown = !!before && compareBox.checked;
  renderer.localClippingEnabled = state.before.shown;
  splitSlider.disabled = !state.before.shown;
  if (!before) return compareBox.checked && !state.before.probed ? 1 : 0;
  before.group.visible = state.before.shown;
  if (!state.before.shown) return 0;
  const right = new THREE.Vector3(1, 0, 0).applyQuaternion(camera.quaternion);
  const at = controls.target.clone().addScaledVector(right, Number(splitSlider.value) * camera.position.distanceTo(controls.target) * 0.5);
  afterPlane.setFromNormalAndCoplanarPoint(right, at);
  beforePlane.setFromNormalAndCoplanarPoint(right.clone().negate(), at);
  tiles.group.updateMatrix();
  before.group.matrix.copy(tiles.group.matrix);
  before.group.matrixWorldNeedsUpdate = true;
  before.update();
  const s = before.stats;
  return s.downloading + s.parsing + (s.queued || 0) + (state.before.models ? 0 : 1);
}

function updatePoints() {
  state.points.shown = !!points && pointsBox.checked;
  if (!points) return pointsBox.checked && !state.points.probed ? 1 : 0;
  points.group.visible = state.points.shown;
  if (!state.points.shown) return 0;
  tiles.group.updateMatrix();
  points.group.matrix.copy(tiles.group.matrix);
  points.group.matrixWorldNeedsUpdate = true;
  points.update();
  const s = points.stats;
  return s.downloading + s.parsing + (s.queued || 0) + (state.points.models ? 0 : 1);
}

let framed = false;
// The camera is framed in the model's local east-north-up frame, wherever on Earth it is: the local vertical
// (the WGS 84 normal at the model's centre) is the camera's up, and the camera looks at the centre from the
// south-south-west, VIEW_PITCH_DEG below the local horizon. A tileset not on the globe (a local frame) takes
// its +Z as up. state.view() reports the framing for tests: the camera up against the local vertical, the
// pitch below the horizon, and the centre's latitude / longitude.
const VIEW_PITCH_DEG = 45;
const view = { upDot: null, pitchDeg: null, lat: null, lon: null, localUp: null };
function localAxes(centre) {
  const east = new THREE.Vector3(1, 0, 0), north = new THREE.Vector3(0, 1, 0), up = new THREE.Vector3(0, 0, 1);
  const ell = tiles.ellipsoid;
  if (ell && centre.length() > 0.5 * Math.min(ell.radius.x, ell.radius.y, ell.radius.z)) {
    const cart = {};
    ell.getPositionToCartographic(centre, cart);
    ell.getEastNorthUpAxes(cart.lat, cart.lon, east, north, up);
    view.lat = THREE.MathUtils.radToDeg(cart.lat); view.lon = THREE.MathUtils.radToDeg(cart.lon);
  }
  return { east, north, up };
}
function frameCamera() {
  const sphere = new THREE.Sphere();
  if (!tiles.getBoundingSphere(sphere)) return false;
  tiles.group.updateMatrixWorld(true);
  const m = tiles.group.matrixWorld;  // the sphere is in the tileset's (ECEF) frame
  const { east, north, up } = localAxes(sphere.center);
  const centre = sphere.center.clone().applyMatrix4(m);
  for (const v of [east, north, up]) v.transformDirection(m);
  const r = Math.max(sphere.radius, 1);
  const pitch = THREE.MathUtils.degToRad(VIEW_PITCH_DEG);
  const back = north.clone().multiplyScalar(-0.94).addScaledVector(east, -0.34).normalize();
  const dir = back.multiplyScalar(Math.cos(pitch)).addScaledVector(up, Math.sin(pitch));
  camera.up.copy(up);
  camera.position.copy(centre).addScaledVector(dir, 2.0 * r);
  camera.near = r / 200; camera.far = r * 50; camera.updateProjectionMatrix();
  camera.lookAt(centre);
  // OrbitControls keeps the up it was built with: orbit about the local vertical instead
  controls._quat.setFromUnitVectors(camera.up, new THREE.Vector3(0, 1, 0));
  controls._quatInverse.copy(controls._quat).invert();
  controls.target.copy(centre);
  controls.update();
  view.localUp = up.toArray();
  return true;
}
state.view = () => {
  const up = new THREE.Vector3().fromArray(view.localUp || [0, 1, 0]);
  const look = new THREE.Vector3();
  camera.getWorldDirection(look);
  const camUp = new THREE.Vector3(0, 1, 0).applyQuaternion(camera.quaternion);  // the image's up, in the world
  return { upDot: +camera.up.dot(up).toFixed(6), imageUpDot: +camUp.dot(up).toFixed(4),
           pitchDeg: +THREE.MathUtils.radToDeg(Math.asin(-look.dot(up))).toFixed(2), lat: view.lat, lon: view.lon };
};

document.getElementById('mode').addEventListener('change', (e) => {
  mode = e.target.value;
  tiles.group.traverse((o) => { if (o.isMesh) applyMode(o); });
});

const raycaster = new THREE.Raycaster();
function pickAt(x, y) {
  const ndc = new THREE.Vector2((x / innerWidth) * 2 - 1, -(y / innerHeight) * 2 + 1);
  raycaster.setFromCamera(ndc, camera);
  const hit = raycaster.intersectObject(tiles.group, true)[0];
  if (!hit) return null;
  const { meshFeatures, structuralMetadata } = hit.object.userData;
  if (!meshFeatures || !structuralMetadata) return { face: hit.faceIndex, metadata: false };
  const [id] = meshFeatures.getFeatures(hit.faceIndex, hit.barycoord);
  const table = meshFeatures.getFeatureInfo()[0].propertyTable;
  const row = structuralMetadata.getPropertyTableData(table, id);
  let tile = hit.object; while (tile && !tile.userData.ms3dUri) tile = tile.parent;
  const infos = meshFeatures.getFeatureInfo();
  const q = infos.findIndex((f) => f.label === 'face_quality');
  const quality = q >= 0 ? structuralMetadata.getPropertyTableData(infos[q].propertyTable,
    meshFeatures.getFeatures(hit.faceIndex, hit.barycoord)[q]) : null;
  return { face: hit.faceIndex, feature: id, grade: row.grade, source: row.source, region: row.region,
           deviation_m: quality ? quality.deviation_m : null, confidence: quality ? quality.confidence : null,
           distance: +hit.distance.toFixed(2) };
}
state.pickAt = pickAt;
if (params.get('label') === '1') setupLabelling({ tiles, camera, controls, scene, renderer, raycaster, state });
// Measure mode (the "measure" checkbox): two clicks on the model give the distance, the height difference
// along the local vertical and the horizontal distance between the points; a line joins them.
const measureState = { points: [], line: null };
state.measure = null;
function measureAt(x, y) {
  const ndc = new THREE.Vector2((x / innerWidth) * 2 - 1, -(y / innerHeight) * 2 + 1);
  raycaster.setFromCamera(ndc, camera);
  const hit = raycaster.intersectObject(tiles.group, true)[0];
  if (!hit) return null;
  if (measureState.points.length === 2) measureState.points = [];
  measureState.points.push(hit.point.clone());
  if (measureState.line) { scene.remove(measureState.line); measureState.line = null; }
  if (measureState.points.length < 2) { state.measure = { points: [hit.point.toArray()] }; return state.measure; }
  const [a, b] = measureState.points;
  const m = measureBetween(a.toArray(), b.toArray(), view.localUp || [0, 1, 0]);
  measureState.line = new THREE.Line(new THREE.BufferGeometry().setFromPoints([a, b]),
    new THREE.LineBasicMaterial({ color: 0xffd400, depthTest: false }));
  measureState.line.renderOrder = 10;
  scene.add(measureState.line);
  state.measure = { ...m, points: [a.toArray(), b.toArray()] };
  return state.measure;
}
state.measureAt = measureAt;
renderer.domElement.addEventListener('click', (e) => {
  if (document.getElementById('measure').checked) {
    const m = measureAt(e.clientX, e.clientY);
    document.getElementById('pick').textContent = !m ? 'nothing there'
      : m.distance === undefined ? 'click the second point' : describeMeasure(m);
    return;
  }
  const p = pickAt(e.clientX, e.clientY);
  state.pick = p;
  document.getElementById('pick').textContent = p
    ? `grade  ${p.grade}\nsource ${p.source}\nregion ${p.region}\nface   ${p.face} (feature ${p.feature})` +
      (p.deviation_m !== null && p.deviation_m !== undefined
        ? `\nscan   ${Number.isFinite(p.deviation_m) ? (100 * p.deviation_m).toFixed(1) + ' cm' : 'no MLS near'}` +
          `\np(bad) ${Number.isFinite(p.confidence) ? p.confidence.toFixed(2) : 'not graded'}` : '')
    : 'nothing there';
});
// ?measure=x1,y1,x2,y2 (screen pixels): measure between those two points once the view has settled
const measureParam = (params.get('measure') || '').split(',').map(Number);

addEventListener('resize', () => {
  camera.aspect = innerWidth / innerHeight; camera.updateProjectionMatrix();
  renderer.setSize(innerWidth, innerHeight); tiles.setResolutionFromRenderer(camera, renderer);
});

let settled = 0;
function loop() {
  requestAnimationFrame(loop);
  if (!framed && tiles.root) framed = frameCamera();
  controls.update();
  camera.updateMatrixWorld();
  tiles.update();
  const pointsBusy = framed ? updatePoints() + updateBefore() : 0;
  renderer.render(scene, camera);
  const s = tiles.stats;
  const busy = s.downloading + s.parsing + (s.queued || 0) + pointsBusy;
  settled = framed && state.models > 0 && busy === 0 ? settled + 1 : 0;
  if (settled > 20 && !state.ready) {
    if (measureParam.length === 4 && measureParam.every(Number.isFinite)) {
      measureAt(measureParam[0], measureParam[1]); measureAt(measureParam[2], measureParam[3]);
    }
    state.ready = true;
  }
  const f = state.faces;
  document.getElementById('status').textContent =
    `${state.models} tile contents loaded; their faces: good ${f.good} · bad ${f.bad} · rebuilt ${f.rebuilt} · unknown ${f.unknown}` +
    (state.points.shown ? ` · ${state.points.count} MLS points` : '') +
    (busy ? ` · loading ${busy}` : '');
}
loop();
