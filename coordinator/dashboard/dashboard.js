// Tessera's dashboard: the farm's jobs and workers, and the selected job's image as it
// assembles, from the coordinator's JSON API (docs/api.md) and its event stream. Plain DOM
// code, no framework and no build step; every text from the server goes in as textContent.
'use strict';

const API = '/api/v1';
const TOKEN_KEY = 'tessera-token';
const $ = (id) => document.getElementById(id);

const state = {
  jobs: new Map(), // id → JobInfo
  seenAt: new Map(), // id → Date.now() when its JobInfo arrived: elapsed and ETA tick on from it
  rows: new Map(), // id → {row, errorRow, cells}
  workers: [],
  selected: null, // job id
  following: true, // until the user picks a job, the page shows the one rendering
  tiles: [], // the selected job's TileInfo, by tile index
  frame: null, // the frame shown, for a frame-range job
  camera: null, // {position, look_at, up}: where the viewpoint controls have moved to
  sceneCamera: null, // the selected job's camera, as the coordinator reported it
  stream: null, // AbortController of the event stream
};

// ---------------------------------------------------------------- token and requests

class Unauthorized extends Error {}

function token() {
  return sessionStorage.getItem(TOKEN_KEY);
}

// `coordinator render` prints http://host/#token=…: the token is taken once and the URL
// cleaned, so it does not linger in the address bar or the history.
function takeTokenFromUrl() {
  const m = location.hash.match(/^#token=(.+)$/);
  if (m) {
    sessionStorage.setItem(TOKEN_KEY, decodeURIComponent(m[1]));
    history.replaceState(null, '', location.pathname);
  }
}

async function errorFrom(resp) {
  let body = null;
  try {
    body = await resp.json();
  } catch (_) {
    // Not JSON: the status line says enough.
  }
  const e = new Error(body && body.error ? body.error : `${resp.status} ${resp.statusText}`);
  e.body = body;
  return e;
}

async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  if (token()) headers.set('Authorization', 'Bearer ' + token());
  const resp = await fetch(API + path, { ...options, headers });
  if (resp.status === 401) {
    askForToken(token() ? (await errorFrom(resp)).message : '');
    throw new Unauthorized('unauthorized');
  }
  if (!resp.ok) throw await errorFrom(resp);
  return resp;
}

function askForToken(message) {
  stopStream();
  showConnection('down', 'needs a token');
  $('token-form').hidden = false;
  $('token-error').textContent = message;
  $('token-input').focus();
}

// ---------------------------------------------------------------- connection

function showConnection(kind, text) {
  const badge = $('connection');
  badge.className = 'badge ' + kind;
  badge.textContent = text;
}

function stopStream() {
  if (state.stream) state.stream.abort();
  state.stream = null;
}

// Loads everything, then follows the event stream; reconnects (and reloads) when it drops.
async function start() {
  stopStream();
  try {
    await resync();
  } catch (e) {
    if (e instanceof Unauthorized) return;
    showConnection('down', 'unreachable; retrying');
    setTimeout(start, 2000);
    return;
  }
  followEvents();
}

async function resync() {
  const jobs = await (await api('/jobs')).json();
  state.workers = await (await api('/workers')).json();
  state.jobs.clear();
  state.rows.clear();
  document.querySelector('#jobs tbody').replaceChildren();
  // The selected job's tiles and preview reload as its info comes in again.
  for (const job of jobs) onJob(job, true);
  renderWorkers();
  follow();
}

async function followEvents() {
  const ctl = new AbortController();
  state.stream = ctl;
  try {
    const resp = await api('/events', { signal: ctl.signal });
    showConnection('live', 'live');
    // Server-sent events over fetch rather than EventSource, which cannot send the token.
    const reader = resp.body.pipeThrough(new TextDecoderStream()).getReader();
    let buffer = '';
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buffer += value;
      let end;
      while ((end = buffer.indexOf('\n\n')) >= 0) {
        handleEvent(buffer.slice(0, end));
        buffer = buffer.slice(end + 2);
      }
    }
  } catch (e) {
    if (e instanceof Unauthorized || ctl.signal.aborted) return;
  }
  if (state.stream !== ctl) return;
  showConnection('down', 'disconnected; retrying');
  setTimeout(start, 1000);
}

function handleEvent(block) {
  let name = 'message';
  const data = [];
  for (const line of block.split('\n')) {
    if (line.startsWith('event:')) name = line.slice(6).trim();
    else if (line.startsWith('data:')) data.push(line.slice(5).replace(/^ /, ''));
  }
  if (data.length === 0) return; // a keep-alive comment
  const value = JSON.parse(data.join('\n'));
  if (name === 'job') onJob(value);
  else if (name === 'tile') onTile(value);
  else if (name === 'workers') {
    state.workers = value;
    renderWorkers();
  } else if (name === 'resync') resync().catch(() => {});
}

// ---------------------------------------------------------------- formatting helpers

function el(tag, props = {}, ...children) {
  const node = document.createElement(tag);
  Object.assign(node, props);
  node.append(...children);
  return node;
}

function duration(s) {
  if (s == null) return '–';
  s = Math.max(0, s);
  if (s < 60) return s.toFixed(1) + ' s';
  const m = Math.floor(s / 60);
  return m < 60 ? `${m} min ${Math.round(s % 60)} s` : `${Math.floor(m / 60)} h ${m % 60} min`;
}

function isActive(job) {
  return job.state === 'queued' || job.state === 'running';
}

// A job's name, with its frames when it renders a range of an animation.
function jobTitle(job) {
  const range = job.spec.frames;
  return range ? `${job.name} · frames ${range.first}–${range.last}` : job.name;
}

// ---------------------------------------------------------------- jobs

// `loading`: one of a whole list, which is followed once it is all in.
function onJob(job, loading = false) {
  const before = state.jobs.get(job.id);
  state.jobs.set(job.id, job);
  state.seenAt.set(job.id, Date.now());
  renderJob(job);
  $('no-jobs').hidden = state.jobs.size > 0;
  if (!loading && (!before || before.state !== job.state)) follow();
  if (job.id !== state.selected) return;
  $('job-error').textContent = job.error || '';
  if (!before || before.state !== job.state) loadTiles(job.id);
  if (!before || before.tiles_done !== job.tiles_done || before.state !== job.state) {
    // A progressive job's image changes once per pass, not per tile.
    if (!job.spec.adaptive || !before || before.passes !== job.passes || before.state !== job.state) {
      refreshPreview();
    }
  }
  if (!before || before.passes !== job.passes) refreshConvergence();
}

function createJobRow(id) {
  const cells = {
    id: el('td', { textContent: id }),
    name: el('td'),
    state: el('td'),
    bar: el('div'),
    label: el('span'),
    elapsed: el('td'),
    eta: el('td'),
    cancel: el('button', { type: 'button', className: 'cancel', textContent: 'Cancel' }),
    retry: el('button', { type: 'button', className: 'retry', textContent: 'Retry' }),
    resubmit: el('button', { type: 'button', className: 'resubmit', textContent: 'Re-submit' }),
  };
  const progress = el('div', { className: 'progress' }, cells.bar, cells.label);
  const row = el(
    'tr',
    { id: 'job-' + id },
    cells.id,
    cells.name,
    cells.state,
    el('td', {}, progress),
    cells.elapsed,
    cells.eta,
    el('td', {}, cells.cancel, cells.retry, cells.resubmit),
  );
  const errorCell = el('td', { colSpan: 7, className: 'error' });
  const errorRow = el('tr', { id: 'job-error-' + id }, errorCell);
  cells.error = errorCell;
  row.addEventListener('click', (ev) => {
    if (!(ev.target instanceof HTMLButtonElement)) pick(id);
  });
  cells.cancel.addEventListener('click', () => jobAction(`/jobs/${id}`, 'DELETE'));
  cells.retry.addEventListener('click', () => jobAction(`/jobs/${id}/retry`, 'POST'));
  cells.resubmit.addEventListener('click', () => jobAction(`/jobs/${id}/resubmit`, 'POST', true));
  // Newest first.
  const body = document.querySelector('#jobs tbody');
  body.prepend(row, errorRow);
  return { row, errorRow, cells };
}

function renderJob(job) {
  let entry = state.rows.get(job.id);
  if (!entry) {
    entry = createJobRow(job.id);
    state.rows.set(job.id, entry);
  }
  const { row, errorRow, cells } = entry;
  row.dataset.state = job.state;
  row.classList.toggle('selected', job.id === state.selected);
  cells.name.textContent = jobTitle(job);
  cells.name.title = job.scene_file;
  cells.state.textContent = job.state;
  cells.state.className = 'state-' + job.state;
  if (job.failures.length) cells.state.textContent += ` (${job.failures.length} tile failures)`;
  const percent = job.tiles_total ? Math.floor((100 * job.tiles_done) / job.tiles_total) : 0;
  cells.bar.style.width = percent + '%';
  cells.label.textContent = `${job.tiles_done}/${job.tiles_total} (${percent}%)`;
  if (job.passes != null) cells.label.textContent += ` · pass ${job.passes}`;
  cells.cancel.hidden = !isActive(job);
  cells.retry.hidden = job.state !== 'failed';
  errorRow.hidden = !job.error;
  cells.error.textContent = job.error ? 'Error: ' + job.error : '';
  renderTimes(job);
}

// Elapsed and ETA move on between updates by the time since the job's info arrived.
function renderTimes(job) {
  const entry = state.rows.get(job.id);
  const since = isActive(job) ? (Date.now() - state.seenAt.get(job.id)) / 1000 : 0;
  const elapsed = job.elapsed_s == null ? null : job.elapsed_s + since;
  const eta = job.eta_s == null ? null : job.eta_s - since;
  entry.cells.elapsed.textContent = duration(elapsed);
  entry.cells.eta.textContent = isActive(job) ? duration(eta) : '–';
}

async function jobAction(path, method, opensJob = false) {
  $('action-error').textContent = '';
  try {
    const job = await (await api(path, { method })).json();
    onJob(job);
    if (opensJob) pick(job.id);
  } catch (e) {
    if (!(e instanceof Unauthorized)) $('action-error').textContent = e.message;
  }
}

// ---------------------------------------------------------------- workers

function renderWorkers() {
  const body = document.querySelector('#workers tbody');
  const now = Date.now();
  body.replaceChildren(
    ...state.workers.map((w) =>
      el(
        'tr',
        {},
        el('td', { textContent: w.name }),
        el('td', { textContent: w.address || '–' }),
        el('td', { textContent: w.state, className: 'state-' + w.state }),
        el('td', { textContent: w.lease ? `job ${w.lease.job_id} tile ${w.lease.tile}` : '–' }),
        el('td', { textContent: w.tiles_done }),
        el('td', { textContent: duration((now - w.last_seen_ms) / 1000) + ' ago' }),
      ),
    ),
  );
  $('no-workers').hidden = state.workers.length > 0;
}

// ---------------------------------------------------------------- preview and tile map

// A job the user chose (a click, a submission, a new view): the page stops following the farm.
function pick(id) {
  state.following = false;
  select(id);
}

// Until the user picks a job, shows the job rendering now (the oldest, if several), else the
// next to run, else the newest: whoever opens the page sees an image without a click.
function follow() {
  if (!state.following) return;
  const jobs = [...state.jobs.values()].sort((a, b) => a.id - b.id);
  const choice =
    jobs.find((j) => j.state === 'running') ||
    jobs.find((j) => j.state === 'queued') ||
    (state.selected == null ? jobs[jobs.length - 1] : null);
  if (choice && choice.id !== state.selected) select(choice.id);
}

function select(id) {
  const job = state.jobs.get(id);
  if (!job) return;
  state.selected = id;
  for (const [other, entry] of state.rows) entry.row.classList.toggle('selected', other === id);
  $('preview-title').textContent = `Job ${id}: ${jobTitle(job)}`;
  $('preview-hint').hidden = true;
  $('preview-frame').hidden = false;
  $('preview-legend').hidden = false;
  $('viewpoint').hidden = false;
  $('job-error').textContent = job.error || '';
  $('tile-detail').textContent = '';
  $('tile-map').replaceChildren();
  const range = job.spec.frames;
  state.frame = range ? range.first : null;
  $('frame-picker').hidden = !range;
  if (range) {
    const options = [];
    for (let f = range.first; f <= range.last; f++) {
      options.push(el('option', { value: f, textContent: f }));
    }
    $('frame-select').replaceChildren(...options);
    $('frame-select').value = String(range.first);
  }
  loadTiles(id);
  refreshPreview();
  refreshConvergence();
  loadCamera(id);
}

// ---------------------------------------------------------------- convergence

// A progressive job's mean spp, estimated error, sample map and error-against-time plot,
// reloaded after every pass.
async function refreshConvergence() {
  const id = state.selected;
  const job = id == null ? null : state.jobs.get(id);
  const box = $('progressive');
  box.hidden = !(job && job.spec.adaptive);
  if (box.hidden) return;
  const rules = job.spec.adaptive;
  const error = job.error_estimate == null ? '–' : job.error_estimate.toFixed(4);
  const spp = job.spp_mean == null ? '–' : job.spp_mean.toFixed(2);
  $('progressive-status').textContent =
    `passes ${job.passes} · mean spp ${spp} (${rules.spp_min}..${rules.spp_max}) · ` +
    `estimated error ${error} (threshold ${rules.noise_threshold})`;
  if (!job.passes) {
    $('convergence-plot').replaceChildren();
    $('sample-map').removeAttribute('src');
    return;
  }
  try {
    const conv = await (await api(`/jobs/${id}/convergence`)).json();
    if (state.selected !== id) return;
    plotConvergence(conv.passes);
    const blob = await (await api(`/jobs/${id}/samples.png`)).blob();
    if (state.selected !== id) return;
    const img = $('sample-map');
    const old = img.dataset.url;
    img.dataset.url = URL.createObjectURL(blob);
    img.src = img.dataset.url;
    img.dataset.passes = job.passes;
    if (old) URL.revokeObjectURL(old);
  } catch (e) {
    if (!(e instanceof Unauthorized)) $('job-error').textContent = 'convergence: ' + e.message;
  }
}

// Estimated error (log scale) against wall time, one point per pass.
function plotConvergence(passes) {
  const svg = $('convergence-plot');
  const ns = 'http://www.w3.org/2000/svg';
  const node = (tag, attrs, text) => {
    const n = document.createElementNS(ns, tag);
    for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, v);
    if (text != null) n.textContent = text;
    return n;
  };
  const points = passes.filter((p) => p.error > 0 && Number.isFinite(p.error));
  const [w, h, left, bottom] = [320, 160, 44, 24];
  const children = [
    node('line', { x1: left, y1: h - bottom, x2: w - 4, y2: h - bottom, stroke: 'currentColor' }),
    node('line', { x1: left, y1: 4, x2: left, y2: h - bottom, stroke: 'currentColor' }),
    node('text', { x: w - 4, y: h - 6, 'text-anchor': 'end', 'font-size': 10 }, 'wall time (s)'),
    node('text', { x: 2, y: 12, 'font-size': 10 }, 'error'),
  ];
  if (points.length) {
    const tMax = Math.max(...points.map((p) => p.wall_s), 1e-3);
    const logs = points.map((p) => Math.log10(p.error));
    const [lo, hi] = [Math.min(...logs), Math.max(...logs)];
    const span = Math.max(hi - lo, 1e-6);
    const x = (t) => left + ((w - 4 - left) * t) / tMax;
    const y = (l) => 4 + ((h - bottom - 4) * (hi - l)) / span;
    const xy = points.map((p, i) => `${x(p.wall_s).toFixed(1)},${y(logs[i]).toFixed(1)}`);
    children.push(node('polyline', { points: xy.join(' '), fill: 'none', stroke: 'currentColor' }));
    for (const [i, p] of points.entries()) {
      const [cx, cy] = xy[i].split(',');
      const dot = node('circle', { cx, cy, r: 2.5, class: 'pass' });
      dot.appendChild(node('title', {}, `pass ${p.pass}: ${p.wall_s.toFixed(2)} s, ` +
        `mean spp ${p.spp_mean.toFixed(2)}, error ${p.error.toFixed(4)}`));
      children.push(dot);
    }
    children.push(node('text', { x: left - 2, y: 12, 'text-anchor': 'end', 'font-size': 9 },
      Math.pow(10, hi).toPrecision(2)));
    children.push(node('text', { x: left - 2, y: h - bottom, 'text-anchor': 'end', 'font-size': 9 },
      Math.pow(10, lo).toPrecision(2)));
  }
  svg.replaceChildren(...children);
  svg.dataset.passes = passes.length;
}

async function loadTiles(id) {
  try {
    // The route answers a page at a time (docs/api.md): read them all, in order.
    const tiles = [];
    for (let total = 1; tiles.length < total; ) {
      const page = await (await api(`/jobs/${id}/tiles?offset=${tiles.length}`)).json();
      if (state.selected !== id) return;
      total = page.tiles_total;
      if (!page.tiles.length) break;
      tiles.push(...page.tiles);
    }
    if (state.selected !== id) return;
    state.tiles = tiles;
    const job = state.jobs.get(id);
    const { width, height } = job.spec.render;
    $('tile-map').replaceChildren(
      ...tiles.map((t) => {
        // A frame-range job holds every frame's tiles: the map shows the frame in view.
        const div = el('div', { id: 'tile-' + t.tile });
        Object.assign(div.style, {
          left: (100 * t.rect.x) / width + '%',
          top: (100 * t.rect.y) / height + '%',
          width: (100 * t.rect.width) / width + '%',
          height: (100 * t.rect.height) / height + '%',
        });
        div.hidden = state.frame != null && t.frame !== state.frame;
        div.addEventListener('mouseenter', () => {
          $('tile-detail').textContent = tileText(state.tiles[t.tile]);
        });
        paintTile(div, t);
        return div;
      }),
    );
  } catch (e) {
    if (!(e instanceof Unauthorized)) $('job-error').textContent = 'tiles: ' + e.message;
  }
}

function tileText(t) {
  let text = `tile ${t.tile} (${t.rect.width}×${t.rect.height} at ${t.rect.x},${t.rect.y}): ${t.state}`;
  if (t.workers.length) text += ' by ' + t.workers.join(' and ');
  if (t.attempts) text += `, ${t.attempts} failed attempt${t.attempts > 1 ? 's' : ''}`;
  return text;
}

function paintTile(div, t) {
  div.className = 'tile ' + t.state;
  div.dataset.state = t.state;
  div.title = tileText(t);
}

// Shows frame `f` of the selected frame-range job: its tiles on the map, its preview.
function showFrame(f) {
  if (state.frame === f) return;
  state.frame = f;
  $('frame-select').value = String(f);
  for (const t of state.tiles) {
    const div = t && $('tile-' + t.tile);
    if (div) div.hidden = t.frame !== f;
  }
  refreshPreview();
}

function onTile(t) {
  if (t.job_id !== state.selected) return;
  if (state.frame != null && t.frame !== state.frame && $('follow-frame').checked) {
    showFrame(t.frame);
  }
  state.tiles[t.tile] = t;
  const div = $('tile-' + t.tile);
  if (div) paintTile(div, t);
}

// One preview request at a time; changes meanwhile ask for one more afterwards.
const preview = { busy: false, again: false, url: null };

async function refreshPreview() {
  if (preview.busy) {
    preview.again = true;
    return;
  }
  const id = state.selected;
  if (id == null) return;
  preview.busy = true;
  try {
    // Asked for once the job is done, the image is the final PNG.
    const final = state.jobs.get(id).state === 'done';
    const frame = state.frame != null ? `?frame=${state.frame}` : '';
    const blob = await (await api(`/jobs/${id}/image${frame}`)).blob();
    if (state.selected === id) {
      const img = $('preview');
      const old = preview.url;
      preview.url = URL.createObjectURL(blob);
      img.src = preview.url;
      img.dataset.job = id;
      img.dataset.final = final;
      if (old) URL.revokeObjectURL(old);
    }
  } catch (e) {
    if (!(e instanceof Unauthorized)) $('job-error').textContent = 'preview: ' + e.message;
  } finally {
    preview.busy = false;
    if (preview.again) {
      preview.again = false;
      setTimeout(refreshPreview, 200);
    }
  }
}

// ---------------------------------------------------------------- viewpoint

const vec = {
  sub: (a, b) => a.map((v, i) => v - b[i]),
  add: (a, b) => a.map((v, i) => v + b[i]),
  scale: (a, s) => a.map((v) => v * s),
  dot: (a, b) => a.reduce((sum, v, i) => sum + v * b[i], 0),
  cross: (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]],
  norm: (a) => vec.scale(a, 1 / Math.hypot(...a)),
  // Rodrigues: `v` turned by `deg` degrees about the unit `axis`, right-handed.
  rotate(v, axis, deg) {
    const t = (deg * Math.PI) / 180;
    const [c, s] = [Math.cos(t), Math.sin(t)];
    const k = vec.dot(axis, v) * (1 - c);
    return vec.add(vec.add(vec.scale(v, c), vec.scale(vec.cross(axis, v), s)), vec.scale(axis, k));
  },
};

async function loadCamera(id) {
  try {
    const cam = await (await api(`/jobs/${id}/camera`)).json();
    if (state.selected !== id) return;
    state.sceneCamera = cam;
    resetView();
  } catch (e) {
    if (!(e instanceof Unauthorized)) $('view-camera').textContent = 'camera: ' + e.message;
  }
}

function resetView() {
  const c = state.sceneCamera;
  if (!c) return;
  state.camera = { position: c.position, look_at: c.look_at, up: c.up };
  showView();
}

function showView() {
  const f = (v) => v.map((x) => x.toFixed(2)).join(', ');
  const c = state.camera;
  $('view-camera').textContent = `camera at (${f(c.position)}) looking at (${f(c.look_at)})`;
}

// Orbits the camera about its look-at point (yaw about its up, pitch about its right) or
// moves it closer or away.
function orbit(kind, amount) {
  const c = state.camera;
  if (!c) return;
  let offset = vec.sub(c.position, c.look_at);
  const up = vec.norm(c.up);
  if (kind === 'zoom') offset = vec.scale(offset, amount);
  else if (kind === 'yaw') offset = vec.rotate(offset, up, amount);
  else {
    const right = vec.norm(vec.cross(vec.scale(offset, -1), up));
    const turned = vec.rotate(offset, right, -amount);
    // Stop short of looking along the up vector, where the camera is undefined.
    if (Math.abs(vec.dot(vec.norm(turned), up)) > Math.cos((5 * Math.PI) / 180)) return;
    offset = turned;
  }
  state.camera = { ...c, position: vec.add(c.look_at, offset) };
  showView();
}

async function renderView(quick) {
  const job = state.jobs.get(state.selected);
  if (!job || !state.camera) return;
  const render = { ...job.spec.render, camera: state.camera };
  if (quick) {
    render.width = Math.max(1, Math.round(render.width / 4));
    render.height = Math.max(1, Math.round(render.height / 4));
    render.spp = 1;
  }
  const base = job.name.replace(/ \((view|quick look)\)$/, '');
  const spec = { ...job.spec, name: `${base} (${quick ? 'quick look' : 'view'})`, render };
  $('action-error').textContent = '';
  try {
    const resp = await api(`/jobs/${job.id}/resubmit`, {
      method: 'POST',
      headers: { 'Content-Type': 'application/json' },
      body: JSON.stringify(spec),
    });
    const created = await resp.json();
    onJob(created);
    pick(created.id);
  } catch (e) {
    if (!(e instanceof Unauthorized)) $('view-camera').textContent = 'refused: ' + e.message;
  }
}

// ---------------------------------------------------------------- submission

function chosenFiles() {
  return [...$('scene-files').files, ...$('scene-folder').files];
}

// A file's path within what was chosen: relative to the chosen folder, or its bare name.
function pathOf(file) {
  return file.webkitRelativePath || file.name;
}

function listScenes() {
  const scenes = chosenFiles()
    .map(pathOf)
    .filter((p) => p.endsWith('.scene'));
  $('scene-select').replaceChildren(...scenes.map((p) => el('option', { value: p, textContent: p })));
}

// The attribute values of the scene that look like file paths: candidates for assets. The
// coordinator names any referenced asset that is still missing.
function assetCandidates(sceneText) {
  const values = [...sceneText.matchAll(/=\s*("([^"]*)"|'([^']*)')/g)].map((m) => m[2] ?? m[3]);
  return [...new Set(values.filter((v) => /[A-Za-z_]/.test(v) && /\.\w+$/.test(v)))];
}

// Finds the asset the scene calls `path`: beside the scene or in its parent folder (as
// `coordinator submit` does), else the one chosen file with that base name.
function findAsset(files, sceneDir, path) {
  const parent = sceneDir.replace(/[^/]*\/$/, '');
  for (const candidate of [sceneDir + path, parent + path]) {
    const file = files.find((f) => pathOf(f) === candidate);
    if (file) return file;
  }
  const base = path.split('/').pop();
  const named = files.filter((f) => f.name === base);
  return named.length === 1 ? named[0] : null;
}

function vec3Field(id) {
  const text = $(id).value.trim();
  if (!text) return null;
  const parts = text.split(',').map(Number);
  if (parts.length !== 3 || parts.some((v) => !Number.isFinite(v))) {
    throw new Error(`${id}: expected three numbers x,y,z, got "${text}"`);
  }
  return parts;
}

function specFromForm() {
  const number = (id) => Number($(id).value);
  const render = {
    width: number('width'),
    height: number('height'),
    spp: number('spp'),
    max_depth: number('depth'),
  };
  const [position, lookAt, up] = [vec3Field('camera-pos'), vec3Field('look-at'), vec3Field('up')];
  if (position || lookAt) {
    if (!position || !lookAt) throw new Error('a camera override needs both its position and its look-at point');
    render.camera = { position, look_at: lookAt, up: up || [0, 1, 0] };
  }
  const spec = { render, tile_size: number('tile-size') };
  if ($('job-name').value.trim()) spec.name = $('job-name').value.trim();
  const frames = $('frames').value.trim();
  if (frames) {
    const match = /^(\d+)\s*\.\.\s*(\d+)$/.exec(frames);
    if (!match) throw new Error(`frames: expected A..B, got "${frames}"`);
    spec.frames = { first: Number(match[1]), last: Number(match[2]) };
  }
  return spec;
}

// "file:line:column: message" for a scene error, the message alone otherwise.
function describeRefusal(e) {
  const b = e.body;
  if (b && b.line != null) {
    const at = `${b.file}:${b.line}:${b.column}`;
    return e.message.startsWith(at) ? e.message : `${at}: ${e.message}`;
  }
  return e.message;
}

async function submitScene(ev) {
  ev.preventDefault();
  $('submit-error').textContent = '';
  $('submit-status').textContent = '';
  try {
    const files = chosenFiles();
    const scene = files.find((f) => pathOf(f) === $('scene-select').value);
    if (!scene) throw new Error('choose the scene file (and its assets) first');
    const spec = specFromForm();
    const text = await scene.text();
    const sceneDir = pathOf(scene).replace(/[^/]*$/, '');
    const form = new FormData();
    form.append('job', new Blob([JSON.stringify(spec)], { type: 'application/json' }));
    form.append('scene', scene, scene.name);
    for (const path of assetCandidates(text)) {
      const file = findAsset(files, sceneDir, path);
      if (file) form.append(path, file, path);
    }
    $('submit-button').disabled = true;
    $('submit-status').textContent = 'uploading…';
    const job = await (await api('/jobs', { method: 'POST', body: form })).json();
    $('submit-status').textContent = `submitted as job ${job.id}`;
    onJob(job);
    pick(job.id);
  } catch (e) {
    $('submit-status').textContent = '';
    if (!(e instanceof Unauthorized)) $('submit-error').textContent = describeRefusal(e);
  } finally {
    $('submit-button').disabled = false;
  }
}

// ---------------------------------------------------------------- start-up

function init() {
  takeTokenFromUrl();
  $('forget-token').hidden = !token();
  $('forget-token').addEventListener('click', () => {
    sessionStorage.removeItem(TOKEN_KEY);
    location.reload();
  });
  $('token-form').addEventListener('submit', (ev) => {
    ev.preventDefault();
    sessionStorage.setItem(TOKEN_KEY, $('token-input').value.trim());
    $('token-form').hidden = true;
    $('forget-token').hidden = false;
    start();
  });
  $('scene-files').addEventListener('change', listScenes);
  $('scene-folder').addEventListener('change', listScenes);
  $('submit-form').addEventListener('submit', submitScene);
  $('frame-select').addEventListener('change', (ev) => {
    $('follow-frame').checked = false;
    showFrame(Number(ev.target.value));
  });
  $('frames-download').addEventListener('click', async (ev) => {
    ev.preventDefault();
    const id = state.selected;
    if (id == null) return;
    try {
      const blob = await (await api(`/jobs/${id}/frames.tar`)).blob();
      const link = el('a', { href: URL.createObjectURL(blob), download: `job-${id}-frames.tar` });
      link.click();
      setTimeout(() => URL.revokeObjectURL(link.href), 10000);
    } catch (e) {
      if (!(e instanceof Unauthorized)) $('job-error').textContent = 'frames: ' + e.message;
    }
  });
  $('show-tiles').addEventListener('change', (ev) => {
    $('tile-map').classList.toggle('hidden', !ev.target.checked);
  });
  for (const button of document.querySelectorAll('[data-orbit]')) {
    const [kind, amount] = button.dataset.orbit.split(',');
    button.addEventListener('click', () => orbit(kind, Number(amount)));
  }
  $('view-reset').addEventListener('click', resetView);
  $('view-quick').addEventListener('click', () => renderView(true));
  $('view-render').addEventListener('click', () => renderView(false));
  setInterval(() => {
    for (const job of state.jobs.values()) renderTimes(job);
    renderWorkers();
  }, 1000);
  start();
}

init();
