// The live studio: draws the frame as its units arrive (Server-Sent Events
// from /studio/events), one slider per knob, the scene's text editable.
//
// A tile is one unit of an interleaved pixel set: pixel (x, y) belongs to set
// (y mod B)·B + (x mod B); the unit holds set rows first_row + i·row_stride,
// each row the set's columns left to right. Until a pixel's set has arrived it
// shows the nearest stored pixel of a coarser lattice (spacing 2, 4, … 64),
// as the coordinator's Canvas::preview does, so the first unit already shows
// the whole frame at 1/B resolution.
'use strict';

/** What the page knows, readable by tests and measurements. */
const studio = window.studio = {
  generation: 0,      // the frame shown
  quality: null,      // its quality
  width: 0, height: 0, interleave: 8,
  units: 0,           // units of the frame
  received: 0,        // units received
  complete: false,    // every unit received
  drawn: false,       // every unit received and drawn on the canvas
  serverSeconds: null,
  requested: {},      // generation → performance.now() of the input that asked it
  timings: [],        // {generation, quality, first, complete} ms after the input
  framesDrawn: 0,     // canvas updates
  view: null,         // the last /studio/scene answer
};

let token = sessionStorage.getItem('hypertexture-token') || '';
const $ = (id) => document.getElementById(id);
const image = $('image');
const context = image.getContext('2d');
let rgba = new Uint8ClampedArray(0);   // pixels received, row-major RGBA
let have = new Uint8Array(0);          // 1 where a pixel was received
let shown = null;                      // ImageData drawn
let dirty = false;
let pending = null;                    // the frame event waiting for its first tile
const knobValues = {};
const setWorkers = [];                 // per set: the worker that rendered it last

function headers(json) {
  const h = {};
  if (json) h['Content-Type'] = 'application/json';
  if (token) h['Authorization'] = 'Bearer ' + token;
  return h;
}

async function call(method, path, body) {
  const response = await fetch(path, {
    method,
    headers: headers(body !== undefined),
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  if (response.status === 401) {
    askToken();
    throw new Error('this service needs its token');
  }
  const answer = await response.json();
  if (!response.ok) throw new Error(answer.error);
  return answer;
}

function askToken() {
  const form = $('login');
  form.hidden = false;
  $('token').focus();
}

$('login').addEventListener('submit', (e) => {
  e.preventDefault();
  token = $('token').value.trim();
  sessionStorage.setItem('hypertexture-token', token);
  location.reload();
});

// ---- The image -----------------------------------------------------------

function startFrame(f) {
  pending = null;
  studio.generation = f.generation;
  studio.quality = f.quality;
  studio.units = f.units;
  studio.received = 0;
  studio.complete = false;
  studio.drawn = false;
  studio.serverSeconds = null;
  studio.interleave = f.interleave;
  if (f.width !== studio.width || f.height !== studio.height) {
    studio.width = f.width;
    studio.height = f.height;
    image.width = f.width;
    image.height = f.height;
    shown = null;
  }
  rgba = new Uint8ClampedArray(f.width * f.height * 4);
  have = new Uint8Array(f.width * f.height);
  setWorkers.length = 0;
  drawSets();
}

function decode(base64) {
  const text = atob(base64);
  const bytes = new Uint8Array(text.length);
  for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
  return bytes;
}

function placeTile(t) {
  const w = studio.width, h = studio.height, b = studio.interleave;
  const ox = t.set % b, oy = Math.floor(t.set / b);
  const columns = ox >= w ? 0 : Math.ceil((w - ox) / b);
  const pixels = decode(t.pixels);
  let source = 0;
  for (let i = 0; i < t.row_count; i++) {
    const y = oy + (t.first_row + i * t.row_stride) * b;
    for (let c = 0; c < columns; c++) {
      const x = ox + c * b;
      const p = y * w + x;
      if (y < h) {
        rgba.set(pixels.subarray(source, source + 4), p * 4);
        have[p] = 1;
      }
      source += 4;
    }
  }
  setWorkers[t.set] = t.worker;
}

/** The frame so far, each missing pixel from the nearest coarser lattice. */
function compose() {
  const w = studio.width, h = studio.height;
  if (!shown || shown.width !== w || shown.height !== h) shown = context.createImageData(w, h);
  const out = shown.data;
  if (studio.complete) {
    out.set(rgba);
    return;
  }
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const i = y * w + x;
      let j = -1;
      if (have[i]) {
        j = i;
      } else {
        for (let spacing = 2; spacing <= 64; spacing *= 2) {
          const k = (y - y % spacing) * w + (x - x % spacing);
          if (have[k]) { j = k; break; }
        }
      }
      if (j >= 0) {
        out[i * 4] = rgba[j * 4];
        out[i * 4 + 1] = rgba[j * 4 + 1];
        out[i * 4 + 2] = rgba[j * 4 + 2];
        out[i * 4 + 3] = rgba[j * 4 + 3];
      } else {
        out[i * 4 + 3] = 0;
      }
    }
  }
}

function draw() {
  dirty = false;
  compose();
  context.putImageData(shown, 0, 0);
  studio.drawn = studio.complete;
  studio.framesDrawn++;
  const asked = studio.requested[studio.generation];
  const now = performance.now();
  let timing = studio.timings.find((t) => t.generation === studio.generation);
  if (!timing) {
    timing = { generation: studio.generation, quality: studio.quality, first: null, complete: null };
    studio.timings.push(timing);
  }
  if (asked !== undefined && timing.first === null) timing.first = now - asked;
  if (asked !== undefined && studio.complete && timing.complete === null) timing.complete = now - asked;
  $('frame-progress').value = studio.units ? studio.received / studio.units : 0;
  const seconds = studio.serverSeconds !== null ? ` in ${studio.serverSeconds.toFixed(2)} s` : '';
  $('frame-info').textContent =
    `${studio.quality} · ${studio.received}/${studio.units} units${studio.complete ? ' · done' + seconds : ''}`;
  drawSets();
}

function schedule() {
  if (!dirty) {
    dirty = true;
    requestAnimationFrame(draw);
  }
}

// ---- Which worker rendered which set ---------------------------------------

// Each worker gets the next hue by the golden angle, in the order the page
// first meets it, so that any two workers are told apart.
const palette = new Map();
function colour(name) {
  if (!palette.has(name)) {
    palette.set(name, `hsl(${Math.round((palette.size * 137.508 + 120) % 360)}, 65%, 55%)`);
  }
  return palette.get(name);
}

function drawSets() {
  const canvas = $('sets');
  const g = canvas.getContext('2d');
  const b = studio.interleave || 8;
  const cell = canvas.width / b;
  g.fillStyle = '#111';
  g.fillRect(0, 0, canvas.width, canvas.height);
  const names = new Set();
  for (let s = 0; s < b * b; s++) {
    const name = setWorkers[s];
    if (!name) continue;
    names.add(name);
    g.fillStyle = colour(name);
    g.fillRect((s % b) * cell + 1, Math.floor(s / b) * cell + 1, cell - 2, cell - 2);
  }
  const legend = $('legend');
  const items = [...names].sort().map((n) => `<li><span style="background:${colour(n)}"></span>${escape(n)}</li>`).join('');
  if (legend.innerHTML !== items) legend.innerHTML = items;
}

function escape(s) {
  return String(s).replace(/[&<>"']/g, (c) => `&#${c.charCodeAt(0)};`);
}

// ---- Events ----------------------------------------------------------------

function listen() {
  const source = new EventSource('/studio/events' + (token ? '?token=' + encodeURIComponent(token) : ''));
  source.addEventListener('frame', (e) => {
    // The picture shown stays until the new frame's first tile.
    pending = JSON.parse(e.data);
  });
  source.addEventListener('tile', (e) => {
    const t = JSON.parse(e.data);
    if (pending && pending.generation === t.generation) startFrame(pending);
    if (t.generation !== studio.generation) return;
    placeTile(t);
    studio.received++;
    if (studio.received === studio.units) studio.complete = true;
    schedule();
  });
  source.addEventListener('done', (e) => {
    const d = JSON.parse(e.data);
    if (d.generation === studio.generation) {
      studio.serverSeconds = d.seconds;
      schedule();
    }
  });
  source.addEventListener('error', (e) => {
    if (e.data) $('error').textContent = JSON.parse(e.data).error;
  });
  source.addEventListener('status', (e) => showStatus(JSON.parse(e.data)));
}

function showStatus(s) {
  $('workers').tBodies[0].innerHTML = s.workers.map((w) =>
    `<tr><td><span style="color:${colour(w.name)}">■</span> ${escape(w.name)}</td><td class="num">${w.threads}</td>` +
    `<td class="num">${Math.round(w.pixels_per_second).toLocaleString()}</td><td class="num">${w.units}</td></tr>`).join('');
  $('jobs').tBodies[0].innerHTML = s.jobs.map((j) =>
    `<tr><td class="num">${j.id}</td><td class="state-${j.state}">${j.state}</td><td>${escape(j.scene_name)}</td>` +
    `<td class="num">${j.units_done}/${j.units_total}</td><td>${escape(j.out)}</td></tr>`).join('');
}

// ---- The scene: knobs and text ----------------------------------------------

/** Shows the scene; `text`: replace the text box, `sliders`: set the sliders. */
function showScene(view, { text, sliders }) {
  studio.view = view;
  $('scene-name').textContent = view.name;
  $('save').disabled = !view.savable;
  $('error').textContent = view.error || '';
  if (text) $('text').value = view.text;
  const names = view.knobs.map((k) => k.name).join(',');
  const box = $('knobs');
  const rebuilt = box.dataset.names !== names;
  if (rebuilt) {
    box.dataset.names = names;
    box.innerHTML = '';
    for (const k of view.knobs) {
      const row = document.createElement('div');
      row.className = 'knob';
      const id = 'knob-' + k.name;
      row.innerHTML = `<label for="${escape(id)}">${escape(k.name)}</label>` +
        `<input type="range" id="${escape(id)}" min="${k.min}" max="${k.max}" step="${(k.max - k.min) / 1000}">` +
        `<output for="${escape(id)}"></output>`;
      box.appendChild(row);
      row.querySelector('input').addEventListener('input', (e) => moved(k.name, e.target));
    }
    if (!view.knobs.length) box.textContent = 'This scene has no knobs.';
  }
  for (const k of view.knobs) {
    const input = $('knob-' + k.name);
    if (!sliders && !rebuilt) continue;
    input.value = k.value;
    knobValues[k.name] = k.value;
    input.nextElementSibling.textContent = format(k.value);
    input.setAttribute('aria-valuetext', format(k.value));
  }
}

function format(v) {
  return Number(v.toPrecision(4)).toString();
}

let restTimer = null;
let inFlight = false;
let queued = null;
const REST_MS = 300;

/** Sends a change (from a slider, or from the text); while one is in
 * flight, only the latest waits. */
function send(change, asked, fromSlider) {
  if (inFlight) {
    queued = [change, asked, fromSlider];
    return;
  }
  inFlight = true;
  call('POST', '/studio/scene', change).then((view) => {
    studio.requested[view.generation] ??= asked;
    showScene(view, { text: fromSlider, sliders: !fromSlider });
    if (change.quality === 'interactive') {
      clearTimeout(restTimer);
      restTimer = setTimeout(() => send({ knobs: { ...knobValues }, quality: 'high' }, performance.now(), fromSlider), REST_MS);
    }
  }, (error) => {
    clearTimeout(restTimer);
    $('error').textContent = error.message;
  }).finally(() => {
    inFlight = false;
    if (queued) {
      const [c, a, f] = queued;
      queued = null;
      send(c, a, f);
    }
  });
}

function moved(name, input) {
  const asked = performance.now();
  const value = Number(input.value);
  knobValues[name] = value;
  input.nextElementSibling.textContent = format(value);
  input.setAttribute('aria-valuetext', format(value));
  clearTimeout(restTimer);
  send({ knobs: { ...knobValues }, quality: 'interactive' }, asked, true);
}

let editTimer = null;
$('text').addEventListener('input', () => {
  const asked = performance.now();
  clearTimeout(editTimer);
  clearTimeout(restTimer);
  editTimer = setTimeout(() => send({ text: $('text').value, quality: 'interactive' }, asked, false), 150);
});

$('save').addEventListener('click', () => {
  call('POST', '/studio/save').then((r) => { $('action-result').textContent = r.saved; },
    (e) => { $('action-result').textContent = e.message; });
});

$('final').addEventListener('click', () => {
  if (!studio.view) return;
  call('POST', '/api/v1/jobs', studio.view.final_job).then(
    (job) => { $('action-result').textContent = `job ${job.id} queued → ${job.out}`; },
    (e) => { $('action-result').textContent = e.message; });
});

call('GET', '/studio/scene').then((view) => {
  showScene(view, { text: true, sliders: true });
  listen();
}, (e) => { $('error').textContent = e.message; });
