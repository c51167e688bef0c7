// Labelling mode of the ms3d viewer (?label=1, served by `ms3d view WORKDIR --label`).
// A click on a face labels its patch with the current brush (good / bad: buttons or keys g / b); shift + drag
// paints; "next least-sure" (key n) flies to the patch the grader is least sure of, and g / b then label it.
// The server owns the patch arithmetic: the page sends the ECEF centroid of the picked face (the tileset's
// frame: the inverse of tiles.group's matrix) to /api/locate and the label to /api/label.
import * as THREE from 'three';

export function setupLabelling({ tiles, camera, controls, scene, renderer, raycaster, state }) {
  const panel = document.getElementById('labelling');
  panel.hidden = false;
  const L = { enabled: true, brush: 1, selected: null, labelled: [], proposals: [], next: 0, errors: [], busy: 0 };
  state.label = L;
  const markers = new THREE.Group();
  scene.add(markers);
  const markerGeo = new THREE.SphereGeometry(0.6, 12, 8);
  const mats = { 0: new THREE.MeshBasicMaterial({ color: 0x1b7a2e }), 1: new THREE.MeshBasicMaterial({ color: 0xc62828 }),
                 sel: new THREE.MeshBasicMaterial({ color: 0xffc107, wireframe: true }) };
  const selMarker = new THREE.Mesh(new THREE.SphereGeometry(1.2, 16, 10), mats.sel);
  selMarker.visible = false;
  markers.add(selMarker);

  const ecefToWorld = (e) => new THREE.Vector3(e[0], e[1], e[2]).applyMatrix4(tiles.group.matrixWorld);
  const worldToEcef = (v) => v.clone().applyMatrix4(tiles.group.matrixWorld.clone().invert()).toArray();

  async function api(method, path, body) {
    const r = await fetch(path, { method, headers: { 'Content-Type': 'application/json' },
                                  body: body === undefined ? undefined : JSON.stringify(body) });
    const doc = await r.json();
    if (!r.ok) { L.errors.push(doc.error); show(`error: ${doc.error}`); throw new Error(doc.error); }
    return doc;
  }

  function show(msg) { document.getElementById('lmsg').textContent = msg; }
  const key = (p) => `${p.i},${p.j},${p.k}`;

  function render() {
    document.getElementById('lbrush').textContent = L.brush ? 'bad' : 'good';
    const n = { 0: 0, 1: 0 };
    L.labelled.forEach((p) => { n[p.label] += 1; });
    document.getElementById('lcount').textContent = `${L.labelled.length} patches labelled (good ${n[0]} · bad ${n[1]})`;
    document.getElementById('llist').textContent = L.labelled.slice(-8).reverse()
      .map((p) => `${p.label ? 'bad ' : 'good'}  (${p.i}, ${p.j}, ${p.k})`).join('\n');
  }

  function select(p, source) {
    L.selected = p;
    if (p && p.ecef) { selMarker.position.copy(ecefToWorld(p.ecef)); selMarker.visible = true; }
    show(p ? `${source} patch (${p.i}, ${p.j}, ${p.k})${p.score !== undefined ? ` score ${p.score.toFixed(3)}` : ''}: g / b to label` : '');
  }

  // the ECEF centroid of the face under the screen point (x, y), or null
  function faceCentroidAt(x, y) {
    const ndc = new THREE.Vector2((x / innerWidth) * 2 - 1, -(y / innerHeight) * 2 + 1);
    raycaster.setFromCamera(ndc, camera);
    const hit = raycaster.intersectObject(tiles.group, true).find((h) => h.object.isMesh && h.face);
    if (!hit) return null;
    const pos = hit.object.geometry.getAttribute('position');
    const c = new THREE.Vector3();
    for (const v of [hit.face.a, hit.face.b, hit.face.c]) c.add(new THREE.Vector3().fromBufferAttribute(pos, v));
    return worldToEcef(c.multiplyScalar(1 / 3).applyMatrix4(hit.object.matrixWorld));
  }

  async function labelPatch(p, label) {
    L.busy += 1;
    try {
      await api('POST', '/api/label', { i: p.i, j: p.j, k: p.k, label });
      L.labelled = L.labelled.filter((q) => key(q) !== key(p));
      L.labelled.push({ i: p.i, j: p.j, k: p.k, label });
      if (p.ecef) {
        const m = new THREE.Mesh(markerGeo, mats[label]);
        m.position.copy(ecefToWorld(p.ecef)); m.name = key(p);
        markers.children.filter((o) => o.name === key(p)).forEach((o) => markers.remove(o));
        markers.add(m);
      }
      render();
      show(`labelled (${p.i}, ${p.j}, ${p.k}) ${label ? 'bad' : 'good'}`);
      return p;
    } finally { L.busy -= 1; }
  }

  // label the patch of the face under (x, y) with `label` (default: the brush); resolves to the patch or null
  async function labelAt(x, y, label = L.brush) {
    const ecef = faceCentroidAt(x, y);
    if (!ecef) { show('nothing there'); return null; }
    L.busy += 1;
    try {
      const p = await api('POST', '/api/locate', { ecef });
      select(p, 'picked');
      return await labelPatch(p, label);
    } finally { L.busy -= 1; }
  }

  function flyTo(ecef) {
    const target = ecefToWorld(ecef);
    const back = camera.position.clone().sub(controls.target);
    back.setLength(Math.min(Math.max(back.length(), 8), 25));
    controls.target.copy(target);
    camera.position.copy(target).add(back);
    controls.update();
  }

  async function nextProposal() {
    if (L.next >= L.proposals.length) {  // fetch more: the server leaves out what is labelled already
      const doc = await api('GET', '/api/proposals?n=20');
      L.proposals = doc.proposals; L.next = 0; L.threshold = doc.threshold;
      if (!L.proposals.length) { show(doc.note || 'no patches left to propose'); return null; }
    }
    const p = L.proposals[L.next++];
    flyTo(p.ecef);
    select(p, `least-sure ${L.next}/${L.proposals.length}:`);
    return p;
  }

  async function labelSelected(label) {
    L.brush = label; render();
    if (!L.selected) return null;
    const p = await labelPatch(L.selected, label);
    if (L.proposals.some((q) => key(q) === key(p))) await nextProposal();
    return p;
  }

  document.getElementById('lgood').addEventListener('click', () => labelSelected(0).catch(() => {}));
  document.getElementById('lbad').addEventListener('click', () => labelSelected(1).catch(() => {}));
  document.getElementById('lnext').addEventListener('click', () => nextProposal().catch(() => {}));
  addEventListener('keydown', (e) => {
    if (e.target.tagName === 'INPUT' || e.target.tagName === 'SELECT') return;
    if (e.key === 'g') labelSelected(0).catch(() => {});
    else if (e.key === 'b') labelSelected(1).catch(() => {});
    else if (e.key === 'n') nextProposal().catch(() => {});
  });

  // click = label the face's patch with the brush (not after an orbit drag); shift + drag paints
  let down = null; let painted = new Set();
  const el = renderer.domElement;
  el.addEventListener('pointerdown', (e) => {
    down = { x: e.clientX, y: e.clientY, paint: e.shiftKey }; painted = new Set();
    controls.enabled = !e.shiftKey;
  });
  el.addEventListener('pointermove', (e) => {
    if (!down || !down.paint || L.busy > 2) return;
    const ecef = faceCentroidAt(e.clientX, e.clientY);
    if (!ecef) return;
    api('POST', '/api/locate', { ecef }).then((p) => {
      if (painted.has(key(p))) return null;
      painted.add(key(p));
      return labelPatch(p, L.brush);
    }).catch(() => {});
  });
  el.addEventListener('pointerup', (e) => {
    const d = down; down = null; controls.enabled = true;
    if (d && Math.hypot(e.clientX - d.x, e.clientY - d.y) < 4) labelAt(e.clientX, e.clientY).catch(() => {});
  });

  api('GET', '/api/labels').then((doc) => { L.labelled = doc.labels; render(); }).catch(() => {});
  render();
  Object.assign(L, { labelAt, labelPatch, nextProposal, labelSelected, faceCentroidAt });
  return L;
}
