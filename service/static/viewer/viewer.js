// The try-on viewer's page logic: the form (garments, motion, body), the drape, and the player.
//
// The glb the service returns holds the body (a skinned mesh, node "body"), one node per garment
// (named by its id; morph-target meshes under it) and one animation that drives both: the body's
// skeleton and the garments' morph-target weights, one target per frame. Its asset.extras carry
// fps, frames, the model versions, the options and the phenotypes of the drape.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { MeshoptDecoder } from 'three/addons/libs/meshopt_decoder.module.js';
import * as api from './api.js';

const $ = (id) => document.getElementById(id);
const el = (tag, props = {}, ...children) => {
  const node = Object.assign(document.createElement(tag), props);
  node.append(...children);
  return node;
};

// ------------------------------------------------------------------ the scene
const canvas = $('scene');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true });
renderer.setPixelRatio(window.devicePixelRatio);
const scene = new THREE.Scene();
scene.background = new THREE.Color(0xe9ecef);
scene.add(new THREE.HemisphereLight(0xffffff, 0x8d8d8d, 2.5));
const sun = new THREE.DirectionalLight(0xffffff, 2.0);
sun.position.set(1.5, 3, 2.5);
scene.add(sun);
scene.add(new THREE.GridHelper(4, 8, 0xb0b4ba, 0xcfd3d8)); // the floor, metres (glb: Y-up)
const camera = new THREE.PerspectiveCamera(35, 1, 0.05, 50);
camera.position.set(0, 1.2, 4.5);
const controls = new OrbitControls(camera, canvas);
controls.target.set(0, 0.9, 0);
// EXT_meshopt_compression: glb files compressed with meshopt load too
const loader = new GLTFLoader().setMeshoptDecoder(MeshoptDecoder);
const timer = new THREE.Timer();

// What is on screen: the glTF scene, its animation and the player's state.
const view = { model: null, mixer: null, action: null, duration: 0, fps: 30, frames: 0, playing: true };
// Draw only when something changed (playing, the camera moved, a scrub, a toggle): an idle page costs no CPU.
let dirty = true;
const requestRender = () => { dirty = true; };
controls.addEventListener('change', requestRender);
let renders = 0;

renderer.setAnimationLoop((time) => {
  const width = canvas.clientWidth;
  const height = canvas.clientHeight;
  if (canvas.width !== Math.floor(width * renderer.getPixelRatio()) || canvas.height !== Math.floor(height * renderer.getPixelRatio())) {
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
    dirty = true;
  }
  timer.update(time);
  if (view.mixer && view.playing) {
    view.mixer.update(timer.getDelta());
    showTime();
    dirty = true;
  }
  if (!dirty) return;
  dirty = false;
  renderer.render(scene, camera);
  canvas.dataset.renders = String(++renders); // for tests: how many frames were drawn
});

function dispose(root) {
  root.traverse((node) => {
    node.geometry?.dispose();
    for (const material of [node.material].flat()) material?.dispose();
  });
}

// Point the camera at the body (at t = 0), from the front (+Z in glTF) and a little above.
function frame(root) {
  root.updateMatrixWorld(true);
  const box = new THREE.Box3().setFromObject(root.getObjectByName('body') || root);
  const center = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const fit = Math.max(size.y, size.x / camera.aspect) * 1.15;
  const distance = fit / (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov) / 2));
  controls.target.copy(center);
  camera.position.set(center.x, center.y + 0.1 * size.y, center.z + distance);
  controls.update();
  requestRender();
}

// The clip time in [0, duration): the last key sits at `duration`, where a looping action wraps to 0.
function setTime(t) {
  if (!view.mixer) return;
  view.mixer.setTime(Math.min(Math.max(t, 0), Math.max(view.duration - 1e-4, 0)));
  showTime();
  requestRender();
}

function showTime() {
  const t = view.action ? view.action.time : 0;
  $('scrub').value = String(t);
  const frame = Math.min(Math.round(t * view.fps) + 1, view.frames);
  $('time').textContent = `${t.toFixed(2)} s · frame ${frame}/${view.frames}`;
  canvas.dataset.time = t.toFixed(3);
}

function setPlaying(playing) {
  view.playing = playing;
  $('play').textContent = playing ? 'Pause' : 'Play';
  if (playing) timer.reset();
}

async function showModel(out) {
  const gltf = await loader.parseAsync(out.glb, '');
  if (view.model) {
    view.mixer.stopAllAction();
    scene.remove(view.model);
    dispose(view.model);
  }
  const extras = gltf.parser.json.asset.extras || {};
  Object.assign(view, { model: gltf.scene, fps: extras.fps || 30, frames: extras.frames || 1 });
  scene.add(gltf.scene);
  view.mixer = new THREE.AnimationMixer(gltf.scene);
  const clip = gltf.animations[0];
  view.action = clip ? view.mixer.clipAction(clip).play() : null;
  view.duration = clip ? clip.duration : 0;
  const scrub = $('scrub');
  scrub.max = String(view.duration);
  scrub.step = String(1 / view.fps);
  scrub.disabled = $('play').disabled = !clip;
  setTime(0);
  frame(gltf.scene);
  setPlaying(true);
  showVisibility(gltf.scene, extras.garments || []);
  showFigures(out, extras, gltf.parser.json.extensionsUsed || []);
}

// One checkbox per garment node (and the body) of the loaded glb: hide one to see under it.
function showVisibility(root, garments) {
  const box = $('visibility');
  box.replaceChildren();
  for (const name of [...garments, 'body']) {
    const node = root.getObjectByName(name);
    if (!node) continue;
    const toggle = el('input', { type: 'checkbox', checked: true });
    toggle.dataset.node = name;
    toggle.addEventListener('change', () => {
      node.visible = toggle.checked;
      requestRender();
    });
    box.append(el('label', {}, toggle, ` ${name}`));
  }
}

// ------------------------------------------------------------------ figures
function table(rows, head) {
  const t = el('table');
  if (head) t.append(el('tr', {}, ...head.map((h) => el('th', { textContent: h }))));
  for (const row of rows) t.append(el('tr', {}, ...row.map((cell) => (cell instanceof Node ? el('td', {}, cell) : el('td', { textContent: String(cell) })))));
  return t;
}

// {fit: {tshirt: "x"}, guard: "y"} -> [["fit.tshirt", "x"], ["guard", "y"]]
function flatten(obj, prefix = '') {
  return Object.entries(obj).flatMap(([k, v]) => (v && typeof v === 'object' && !Array.isArray(v)
    ? flatten(v, `${prefix}${k}.`) : [[`${prefix}${k}`, Array.isArray(v) ? v.join(', ') : v]]));
}

function showFigures(out, extras, extensions) {
  const section = (title, ...content) => el('section', {}, el('h3', { textContent: title }), ...content);
  const timing = api.parseServerTiming(out.serverTiming);
  const total = Math.max(...timing.filter((s) => s.name !== 'total').map((s) => s.ms || 0), 1); // the longest stage: a full bar
  const bar = (ms) => el('span', { className: 'bar', style: `width: ${Math.min(100, (100 * (ms || 0)) / total)}%` });
  const parts = [
    section('Answer', table([
      ['route', out.via],
      ['X-Frames', out.frames ?? '–'],
      ['X-Cache', out.cache ?? '–'],
      ['Content-Encoding', out.encoding],
      ['glb bytes', out.glb.byteLength.toLocaleString('en')],
      ['glTF extensions', extensions.join(', ') || '–'],
      ['round trip', `${Math.round(out.wallMs)} ms`],
      ...(out.jobSeconds !== undefined ? [['job, created to finished', `${out.jobSeconds.toFixed(1)} s`]] : []),
    ])),
    section('Server-Timing (ms)', timing.length
      ? Object.assign(table(timing.map((s) => [s.name, s.ms ?? '–', bar(s.ms)])), { className: 'timing' })
      : el('p', { className: 'hint', textContent: 'not sent with this answer (job results carry X-Frames only)' })),
    section('asset.extras', table([['fps', extras.fps], ['frames', extras.frames], ['garments', (extras.garments || []).join(', ')],
      ['in_place', extras.in_place]])),
    section('Model versions', table(flatten(extras.model_versions || {}))),
    section('Options', table(flatten(extras.options || {}))),
    section('Phenotypes', table(flatten(extras.phenotypes || {}).map(([k, v]) => [k, Number(v).toFixed(3)]))),
  ];
  if (extras.collisions) parts.push(section('Collisions', table(flatten(extras.collisions))));
  parts.push(el('details', {}, el('summary', { textContent: 'all of asset.extras' }), el('pre', { textContent: JSON.stringify(extras, null, 2) })));
  $('answer').replaceChildren(...parts);
}

// ------------------------------------------------------------------ status and problems
function setStatus(state, text, fraction) {
  $('status').dataset.state = state;
  $('status-text').textContent = text;
  const progress = $('progress');
  progress.hidden = state !== 'busy';
  if (fraction === null || fraction === undefined) progress.removeAttribute('value'); // indeterminate
  else progress.value = fraction;
}

// An RFC 9457 problem: title, detail and each errors[].detail (with the field it points to);
// fields of the measurement form named by a pointer are marked.
function showProblem(err) {
  const p = err.problem || { title: 'Error', detail: String(err.message || err) };
  const box = $('problem');
  const errors = (p.errors || []).map((e) => el('li', {}, e.pointer ? el('code', { textContent: e.pointer || '/' }) : '', ` ${e.detail}`));
  box.replaceChildren(el('strong', { textContent: p.status ? `${p.title} (${p.status})` : p.title }),
    el('p', { textContent: p.detail || '' }), ...(errors.length ? [el('ul', {}, ...errors)] : []));
  box.hidden = false;
  for (const input of $('fit-form').elements) input.classList.remove('invalid');
  for (const e of p.errors || []) $('fit-form').elements[(e.pointer || '').slice(1)]?.classList.add('invalid');
  setStatus('error', p.title);
}

function clearProblem() {
  $('problem').hidden = true;
  for (const input of $('fit-form').elements) input.classList.remove('invalid');
}

// ------------------------------------------------------------------ the form
const form = { config: null, catalog: [], motions: [], fitted: null };

function renderGarments(garments) {
  // innermost first: by the catalog's layer, then its order
  const sorted = garments.map((g, i) => ({ ...g, i })).sort((a, b) => a.layer - b.layer || a.i - b.i);
  const initial = sorted.some((g) => g.id === 'tshirt') ? 'tshirt' : sorted[0]?.id;
  const list = $('garment-list');
  list.replaceChildren(...sorted.map((g) => {
    const check = el('input', { type: 'checkbox', checked: g.id === initial });
    check.dataset.id = g.id;
    check.addEventListener('change', showOrder);
    const move = (dir, label) => {
      const button = el('button', { type: 'button', textContent: label, title: dir < 0 ? 'inward' : 'outward' });
      button.addEventListener('click', () => {
        const row = button.closest('li');
        if (dir < 0 && row.previousElementSibling) row.previousElementSibling.before(row);
        if (dir > 0 && row.nextElementSibling) row.nextElementSibling.after(row);
        showOrder();
      });
      return button;
    };
    const row = el('li', {}, el('label', {}, check, ` ${g.name}`), el('span', { className: 'hint', textContent: ` layer ${g.layer} · ${g.category}` }),
      move(-1, '↑'), move(1, '↓'));
    row.dataset.layer = g.layer;
    return row;
  }));
  showOrder();
}

// The checked garments in list order: the request's garments, innermost first.
function chosenGarments() {
  return [...$('garment-list').querySelectorAll('input:checked')].map((c) => form.catalog.find((g) => g.id === c.dataset.id));
}

function showOrder() {
  const chosen = chosenGarments();
  $('layer-order').textContent = chosen.length ? chosen.map((g) => g.name).join(' → ') : 'none';
  const inverted = chosen.findIndex((g, i) => i > 0 && g.layer < chosen[i - 1].layer);
  const warning = $('layer-warning');
  warning.hidden = inverted < 0;
  if (inverted >= 0) {
    const [outer, inner] = [chosen[inverted - 1], chosen[inverted]];
    // the service keeps the request's order (a shirt before trousers is tucked in): say what will happen
    warning.textContent = `${outer.name} (layer ${outer.layer}) is listed inside ${inner.name} (layer ${inner.layer}): it will be draped under it`;
  }
}

function renderMotions(motions) {
  const select = $('motion-clip');
  select.replaceChildren(...motions.map((m) => el('option', { value: m.id, textContent: `${m.title} (${m.duration_s.toFixed(1)} s)${m.test_only ? ' · test clip' : ''}` })));
  select.value = motions.some((m) => m.id === 'walk') ? 'walk' : motions[0]?.id;
  const describe = () => {
    const m = motions.find((x) => x.id === select.value);
    $('motion-description').textContent = `${m.description} ${m.frames} frames at ${m.fps} fps.`;
    $('duration-s').max = String(m.duration_s);
    $('start-s').max = String(m.duration_s);
  };
  select.addEventListener('change', describe);
  describe();
}

function renderSliders(phenotypes) {
  $('phenotype-sliders').replaceChildren(...phenotypes.map((p) => {
    const slider = el('input', { type: 'range', min: p.min, max: p.max, step: 0.01, value: p.default, name: p.name });
    const value = el('output', { textContent: Number(p.default).toFixed(2) });
    slider.addEventListener('input', () => { value.textContent = Number(slider.value).toFixed(2); });
    return el('label', { className: 'slider' }, el('span', { textContent: p.name }), slider, value);
  }));
}

function sliderPhenotypes() {
  return Object.fromEntries([...$('phenotype-sliders').querySelectorAll('input')].map((s) => [s.name, Number(s.value)]));
}

function setSliders(phenotypes) {
  for (const slider of $('phenotype-sliders').querySelectorAll('input')) {
    if (slider.name in phenotypes) {
      slider.value = String(phenotypes[slider.name]);
      slider.dispatchEvent(new Event('input'));
    }
  }
}

function bodyMode() {
  return document.querySelector('input[name="body-mode"]:checked').value;
}

function measurementRequest() {
  const f = $('fit-form').elements;
  const out = {};
  for (const name of ['height_cm', 'chest_cm', 'waist_cm', 'hips_cm', 'inseam_cm']) out[name] = Number(f[name].value);
  if (f.weight_kg.value !== '') out.weight_kg = Number(f.weight_kg.value);
  if (f.gender.value) out.gender = f.gender.value;
  return out;
}

// POST /v1/bodies/fit; show the fitted phenotypes, the measurements and the residuals; the
// sliders take the fitted phenotypes (the drape uses them).
async function runFit() {
  clearProblem();
  setStatus('busy', 'Fitting the body…', null);
  const asked = measurementRequest();
  const fit = await api.fitBody(asked);
  form.fitted = fit.phenotypes;
  setSliders(fit.phenotypes);
  const rows = Object.keys(fit.residuals).map((k) => [k, asked[k] ?? '–', fit.measurements[k].toFixed(1),
    fit.residuals[k] === null ? '–' : `${fit.residuals[k] >= 0 ? '+' : ''}${fit.residuals[k].toFixed(2)}`]);
  $('fit-result').replaceChildren(
    el('h3', { textContent: 'Fitted body' }),
    table(rows, ['measurement', 'asked', 'fitted', 'residual']),
    el('p', { className: 'hint', textContent: `every residual within ${fit.tolerance_cm} cm (${fit.tolerance_kg} kg)` }),
    table(Object.entries(fit.phenotypes).map(([k, v]) => [k, v.toFixed(3)]), ['phenotype', 'value']),
  );
  setStatus('idle', 'Body fitted: the drape uses these phenotypes');
  return fit;
}

function drapeRequest(phenotypes) {
  return {
    body: { phenotypes },
    motion: { type: 'clip', clip: $('motion-clip').value, start_s: Number($('start-s').value), duration_s: Number($('duration-s').value),
      in_place: $('in-place').checked },
    garments: chosenGarments().map((g) => ({ id: g.id })),
    format: 'glb',
    options: { fps: Number($('fps').value), normals: $('normals').checked, compression: $('compression').value },
  };
}

let aborter = null;

async function runDrape() {
  clearProblem();
  if (bodyMode() === 'measurements' && !form.fitted) await runFit();
  const request = drapeRequest(sliderPhenotypes());
  const frames = Math.floor(request.motion.duration_s * request.options.fps) + 1;
  aborter = new AbortController();
  $('cancel').hidden = false;
  const t0 = performance.now();
  try {
    const out = await api.drape(request, {
      route: $('route').value, frames, maxFrames: form.config.max_frames, signal: aborter.signal,
      onProgress: ({ phase, fraction }) => setStatus('busy', `${phase}${fraction !== null ? ` ${Math.round(100 * fraction)} %` : ''} (${frames} frames)`, fraction),
    });
    out.wallMs = performance.now() - t0;
    setStatus('busy', 'Loading the glb…', 1);
    await showModel(out);
    setStatus('ready', `Ready: ${view.frames} frames at ${view.fps} fps (${out.via})`);
  } finally {
    $('cancel').hidden = true;
    aborter = null;
  }
}

// Every button reports its failure as a problem and re-enables itself.
function action(button, run) {
  button.addEventListener('click', async (event) => {
    event.preventDefault();
    button.disabled = true;
    try {
      await run();
    } catch (err) {
      showProblem(err);
    } finally {
      button.disabled = false;
    }
  });
}

async function loadCatalog() {
  const [garments, motions, bodyModel, neutral] = await Promise.all([
    api.getJson('/v1/garments'), api.getJson('/v1/motions'), api.getJson('/v1/body-model'), api.getJson('/v1/bodies/measurements'),
  ]);
  form.catalog = garments.garments;
  renderGarments(form.catalog);
  $('max-garments').textContent = String(form.config.max_garments);
  renderMotions(motions.motions);
  renderSliders(bodyModel.phenotypes);
  for (const [name, value] of Object.entries(neutral.measurements)) {
    const input = $('fit-form').elements[name];
    if (input && name !== 'weight_kg') input.value = value.toFixed(1);
  }
  $('drape').disabled = false;
  setStatus('idle', `${form.catalog.length} garments, ${motions.motions.length} motions`);
}

async function init() {
  $('drape').disabled = true;
  for (const radio of document.querySelectorAll('input[name="body-mode"]')) {
    radio.addEventListener('change', () => {
      $('phenotype-sliders').hidden = bodyMode() !== 'phenotypes';
      $('fit-form').hidden = bodyMode() !== 'measurements';
    });
  }
  $('fit-form').addEventListener('input', () => { form.fitted = null; }); // changed since the last fit
  for (const f of [$('fit-form'), $('auth')]) f.addEventListener('submit', (event) => event.preventDefault()); // Enter: no page reload
  action($('fit'), runFit);
  action($('drape'), runDrape);
  $('cancel').addEventListener('click', () => aborter?.abort());
  $('play').addEventListener('click', () => setPlaying(!view.playing));
  $('scrub').addEventListener('input', () => {
    setPlaying(false);
    setTime(Number($('scrub').value));
  });
  try {
    form.config = await api.getJson('/viewer/config.json');
    if (form.config.auth) {
      $('auth').hidden = false;
      const key = $('api-key');
      key.addEventListener('change', async () => {
        api.setApiKey(form.config.api_key_header, key.value);
        try {
          clearProblem();
          await loadCatalog();
        } catch (err) {
          showProblem(err);
        }
      });
      setStatus('idle', `This deployment needs an API key (${form.config.api_key_header})`);
      return;
    }
    await loadCatalog();
  } catch (err) {
    showProblem(err);
  }
}

init();
