// The live studio: draws the frame as its units arrive (Server-Sent Events
// from /studio/events; a high-quality frame's pixels fetched from
// /studio/tiles when drawn), one slider per knob, the scene's text editable.
//
// A tile is one unit of an interleaved pixel set: pixel (x, y) belongs to set
// (y mod B)·B + (x mod B); the unit holds set rows first_row + i·row_stride,
// each row the set's columns left to right. Until a pixel's set has arrived it
// shows the nearest stored pixel of a coarser lattice (spacing 2, 4, … 64),
// as the coordinator's Canvas::preview does, or, before any of those, the
// first pixel of its B×B block that arrived; so the first unit already shows
// the whole frame at 1/B resolution, whichever set it is.
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
  // generation → performance.now() of: the input that asked for it (asked),
  // the change's answer, its first tile's event (arrived), its first
  // drawing and its drawing whole (first, complete).
  moments: {},
  /** The asked frames: {generation, quality, preview, answered, arrived,
   * first, complete}, each in ms after the input (null: not yet). */
  get timings() {
    return Object.entries(this.moments).filter(([, m]) => m.asked !== undefined).map(([g, m]) => {
      const after = (t) => (t === undefined ? null : t - m.asked);
      return { generation: Number(g), quality: m.quality, preview: Boolean(m.preview), answered: after(m.answered),
        arrived: after(m.arrived), first: after(m.first), complete: after(m.complete) };
    });
  },
  framesDrawn: 0,     // canvas updates
  view: null,         // the last /studio/scene answer
  version: 0,         // the version of the text and values the sliders show
  textBase: 0,        // the version the text box's text was made on
  conflict: null,     // the last edit another tab's edit refused
  exposure: 0,        // the display's exposure in stops
  histogram: null,    // the luminance histogram last drawn
  // Per slider input event (the last INPUTS_KEPT): ms from the event's
  // time stamp (when the browser took the input) to the end of its handler,
  // so a main thread busy placing tiles counts.
  inputs: [],
};
const INPUTS_KEPT = 4096;
// This tab, as its edits name it: the server's `scene` events carry it back,
// so the tab tells its own edits from other tabs'.
const TAB = Math.random().toString(36).slice(2) + Date.now().toString(36);

let token = sessionStorage.getItem('hypertexture-token') || '';
const $ = (id) => document.getElementById(id);
const image = $('image');
const context = image.getContext('2d');
// The picture: each pixel shows its own value once its set has arrived,
// until then the nearest stored pixel of a coarser lattice (spacing 2, 4, …
// 64). `level` holds, per pixel, log2 of the spacing of the pixel it shows
// (0: its own); a tile updates only the pixels it improves.
const NONE = 255;
// A pixel of a B×B block none of whose lattice sources has arrived shows the
// first pixel of the block that has: so the frame is whole from the first
// tile whichever set it is.
const FALLBACK = 7;
let level = new Uint8Array(0);
let blockFilled = new Uint8Array(0);   // per B×B block: FALLBACK filled
let shown = null;                      // ImageData drawn
// While a frame refines, the canvas is drawn at most every DRAW_EVERY_MS,
// and the tiles received since the last drawing are placed then (the browser
// shares the machine with the workers). An interactive frame's first tile is
// drawn at once; a high-quality frame, watched rather than steered, keeps the
// interactive image on the canvas until its first drawing, so the page works
// little while the workers render it. A frame's last tile is drawn at once.
const DRAW_EVERY_MS = { interactive: 100, high: 1000 };
let backlog = [];                      // tiles received, not yet placed
let fetching = false;                  // pixels of backlog tiles on their way
let fresh = false;                     // a new frame, its image not cleared yet
let rafPending = false;
let drawTimer = null;
let lastDraw = -Infinity;
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
  if (!response.ok) throw Object.assign(new Error(answer.error), { status: response.status });
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
  if (f.frame !== undefined) showFrameNumber(f.frame);
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
  // A high-quality frame after an image of the same size: that image stays
  // until the first drawing, DRAW_EVERY_MS from now.
  lastDraw = f.quality === 'high' && shown && studio.framesDrawn > 0 ? performance.now() : -Infinity;
  backlog = [];
  setWorkers.length = 0;
  fresh = true;
}

/** Clears the image for a new frame: at its first drawing, so that a
 * high-quality frame costs the page nothing until then. */
function clearImage() {
  fresh = false;
  const w = studio.width, h = studio.height, b = studio.interleave;
  if (!shown) shown = context.createImageData(w, h);
  shown.data.fill(0);
  if (level.length !== w * h) level = new Uint8Array(w * h);
  level.fill(NONE);
  const blocks = Math.ceil(w / b) * Math.ceil(h / b);
  if (blockFilled.length !== blocks) blockFilled = new Uint8Array(blocks);
  blockFilled.fill(0);
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
  const pixels = typeof t.pixels === 'string' ? decode(t.pixels) : t.pixels;
  let source = 0;
  for (let i = 0; i < t.row_count; i++) {
    const y = oy + (t.first_row + i * t.row_stride) * b;
    if (y >= h) break;
    for (let c = 0; c < columns; c++, source += 4) place(ox + c * b, y, pixels, source);
  }
  setWorkers[t.set] = t.worker;
}

/** Pixel (x, y) arrives: it is shown by every pixel of the 2^k block at
 * (x, y) (for each spacing 2^k ≤ 64 that divides x and y) whose own source
 * lies on a coarser lattice, as Canvas::preview does. */
function place(x, y, pixels, source) {
  const w = studio.width, h = studio.height, out = shown.data;
  let top = 0;
  while (top < 6 && x % (2 << top) === 0 && y % (2 << top) === 0) top++;
  const x1 = Math.min(w, x + (1 << top)), y1 = Math.min(h, y + (1 << top));
  const r = pixels[source], g = pixels[source + 1], bl = pixels[source + 2], a = pixels[source + 3];
  const b = studio.interleave, across = Math.ceil(w / b);
  const block = Math.floor(y / b) * across + Math.floor(x / b);
  if (!blockFilled[block]) {
    blockFilled[block] = 1;
    const bx = x - (x % b), by = y - (y % b);
    for (let qy = by; qy < Math.min(h, by + b); qy++) {
      for (let qx = bx, q = qy * w + bx; qx < Math.min(w, bx + b); qx++, q++) {
        if (level[q] === NONE) {
          level[q] = FALLBACK;
          const o = q * 4;
          out[o] = r; out[o + 1] = g; out[o + 2] = bl; out[o + 3] = a;
        }
      }
    }
  }
  for (let qy = y; qy < y1; qy++) {
    const dy = qy - y;
    let q = qy * w + x;
    for (let qx = x; qx < x1; qx++, q++) {
      const d = Math.max(qx - x, dy);
      const k = d === 0 ? 0 : 32 - Math.clz32(d);   // the least k with d < 2^k
      if (k < level[q]) {
        level[q] = k;
        const o = q * 4;
        out[o] = r; out[o + 1] = g; out[o + 2] = bl; out[o + 3] = a;
      }
    }
  }
}

function moment(generation) {
  return studio.moments[generation] ??= {};
}

/** Fetches the pixels of the backlog's tiles that came without them (a
 * high-quality frame's), in one request: tiles `from` up to `to` of the
 * frame, in the order recorded, which the backlog holds from its first such
 * tile on. */
async function fetchPixels(need) {
  const g = studio.generation;
  const from = need[0].index, to = need[need.length - 1].index + 1;
  // The token goes in the header: only the event stream takes it in its URL.
  const query = `generation=${g}&from=${from}&to=${to}`;
  const response = await fetch('/studio/tiles?' + query, { headers: headers(false) });
  if (!response.ok) throw new Error(`tiles ${from}..${to}: ${response.status}`);
  const bytes = new Uint8Array(await response.arrayBuffer());
  if (g !== studio.generation) return;
  const range = backlog.filter((t) => t.index >= from && t.index < to);
  const total = range.reduce((n, t) => n + t.bytes, 0);
  if (range.length !== to - from || total !== bytes.length) {
    throw new Error(`tiles ${from}..${to}: ${bytes.length} bytes for ${range.length} tiles of ${total}`);
  }
  let offset = 0;
  for (const t of range) {
    t.pixels = bytes.subarray(offset, offset + t.bytes);
    offset += t.bytes;
  }
}

function draw() {
  rafPending = false;
  if (fetching) return;   // drawn again once the pixels are here
  const need = backlog.filter((t) => t.pixels === undefined);
  if (need.length) {
    fetching = true;
    fetchPixels(need)
      .catch((e) => {
        // A superseded frame's tiles are gone; those of this one are dropped.
        console.warn(e);
        backlog = backlog.filter((t) => t.pixels !== undefined);
      })
      .finally(() => {
        fetching = false;
        if (backlog.length) draw();
      });
    return;
  }
  if (fresh) clearImage();
  for (const t of backlog) placeTile(t);
  backlog = [];
  lastDraw = performance.now();
  showStatusNow();
  present(studio.complete);
  studio.drawn = studio.complete;
  studio.framesDrawn++;
  const m = moment(studio.generation);
  m.first ??= lastDraw;
  if (studio.complete) m.complete ??= lastDraw;
  $('frame-progress').value = studio.units ? studio.received / studio.units : 0;
  const seconds = studio.serverSeconds !== null ? ` in ${studio.serverSeconds.toFixed(2)} s` : '';
  $('frame-info').textContent =
    `${studio.quality} · ${studio.received}/${studio.units} units${studio.complete ? ' · done' + seconds : ''}`;
  drawSets();
  drawCompare();
  drawBounds();
}

function schedule() {
  if (studio.complete || lastDraw === -Infinity) {
    // The frame's first tile and its last are drawn now.
    clearTimeout(drawTimer);
    drawTimer = null;
    draw();
    return;
  }
  const wait = lastDraw + (DRAW_EVERY_MS[studio.quality] ?? 100) - performance.now();
  if (wait <= 0) {
    clearTimeout(drawTimer);
    drawTimer = null;
    if (!rafPending) {
      rafPending = true;
      requestAnimationFrame(draw);
    }
  } else if (!drawTimer && !rafPending) {
    drawTimer = setTimeout(() => { drawTimer = null; schedule(); }, wait);
  }
}

// ---- Exposure and histogram ------------------------------------------------

// Exposure is the page's own: the frame's sRGB bytes, decoded to linear
// light, times 2^stops, encoded back (each channel through a 256-entry
// table). The scene, the farm's pixels and Render final stay as they are.
const exposureInput = $('exposure');
const HISTOGRAM_BINS = 64;
let exposureTable = null;              // byte → exposed byte; null at 0 stops
let exposed = null;                    // ImageData drawn when exposed

function srgbToLinear(v) {
  return v <= 0.04045 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4;
}

function linearToSrgb(v) {
  return v <= 0.0031308 ? v * 12.92 : 1.055 * v ** (1 / 2.4) - 0.055;
}

/** The table of `stops` of exposure, or null for none. */
function exposureTableOf(stops) {
  if (stops === 0) return null;
  const k = 2 ** stops, table = new Uint8ClampedArray(256);
  for (let v = 0; v < 256; v++) table[v] = Math.round(linearToSrgb(Math.min(1, srgbToLinear(v / 255) * k)) * 255);
  return table;
}

/** Bytes `from`..`to` of the RGBA `pixels` written exposed into `out`
 * (alpha as it is). */
function expose(pixels, out, from, to) {
  const t = exposureTable;
  for (let i = from; i < to; i += 4) {
    out[i] = t[pixels[i]]; out[i + 1] = t[pixels[i + 1]]; out[i + 2] = t[pixels[i + 2]]; out[i + 3] = pixels[i + 3];
  }
}

/** Draws the frame on the canvas through the exposure, and the histogram
 * of what it shows when `histogram`. */
function present(histogram) {
  let out = shown;
  if (exposureTable) {
    if (!exposed || exposed.width !== shown.width || exposed.height !== shown.height) {
      exposed = new ImageData(shown.width, shown.height);
    }
    expose(shown.data, exposed.data, 0, shown.data.length);
    out = exposed;
  }
  context.putImageData(out, 0, 0);
  if (histogram) drawHistogram(out.data);
}

/** The luminance of `pixels` (linear Rec. 709 weights, binned by its sRGB
 * code) in HISTOGRAM_BINS bins, drawn as bars whose heights are the square
 * roots of the counts, the fullest bin full height (so a large flat
 * background leaves the object's bins visible). */
function drawHistogram(pixels) {
  const bins = new Uint32Array(HISTOGRAM_BINS);
  const linear = new Float64Array(256);
  for (let v = 0; v < 256; v++) linear[v] = srgbToLinear(v / 255);
  for (let i = 0; i < pixels.length; i += 4) {
    const y = 0.2126 * linear[pixels[i]] + 0.7152 * linear[pixels[i + 1]] + 0.0722 * linear[pixels[i + 2]];
    bins[Math.min(HISTOGRAM_BINS - 1, Math.floor(linearToSrgb(y) * HISTOGRAM_BINS))]++;
  }
  const canvas = $('histogram'), g = canvas.getContext('2d');
  const most = Math.max(1, ...bins), w = canvas.width / HISTOGRAM_BINS, h = canvas.height;
  g.clearRect(0, 0, canvas.width, h);
  g.fillStyle = '#d9a35b';
  bins.forEach((n, b) => {
    const bar = n ? Math.max(1, Math.round(Math.sqrt(n / most) * h)) : 0;
    g.fillRect(b * w, h - bar, w, bar);
  });
  studio.histogram = Array.from(bins);
}

exposureInput.addEventListener('input', () => {
  const stops = Number(exposureInput.value);
  $('exposure-shown').textContent = `${stops > 0 ? '+' : ''}${format(stops)}`;
  exposureTable = exposureTableOf(stops);
  studio.exposure = stops;
  if (shown && studio.framesDrawn) {
    present(true);
    drawCompare();
  }
});

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

// The server renders a begun interactive frame to its end while the next
// one starts behind it: the next frame's first tiles are held until the
// frame shown is whole (at most EARLY_MAX_MS), so that each value of a drag
// is drawn whole before the next replaces it.
let early = [];
let earlyTimer = null;
const EARLY_MAX_MS = 250;

/** Whether the interactive frame shown is still coming, with an
 * interactive one waiting for it. */
function finishing() {
  return studio.quality === 'interactive' && pending?.quality === 'interactive' &&
    !studio.complete && studio.received > 0;
}

function hold(t) {
  early.push(t);
  if (earlyTimer === null) earlyTimer = setTimeout(startEarly, EARLY_MAX_MS);
}

/** Starts the frame whose tiles were held, with them. */
function startEarly() {
  clearTimeout(earlyTimer);
  earlyTimer = null;
  const tiles = early;
  early = [];
  if (!pending || !tiles.length || tiles[0].generation !== pending.generation) return;
  startFrame(pending);
  for (const t of tiles) accept(t);
}

/** A tile of the frame shown. */
function accept(t) {
  backlog.push(t);
  studio.received++;
  if (studio.received === studio.units) studio.complete = true;
  schedule();
  frameProgress();
  if (studio.complete && early.length) startEarly();
}

function listen() {
  // An EventSource cannot send a header: the one URL that carries the token.
  const source = new EventSource('/studio/events' + (token ? '?token=' + encodeURIComponent(token) : ''));
  source.addEventListener('frame', (e) => {
    // The picture shown stays until the new frame's first tile.
    pending = JSON.parse(e.data);
    // A frame the service started itself (the high-quality one, once the
    // edits rest) is timed from its announcement.
    const m = moment(pending.generation);
    m.asked ??= performance.now();
    m.quality ??= pending.quality;
    m.preview ??= pending.preview;
  });
  source.addEventListener('tile', (e) => receive(JSON.parse(e.data)));
  source.addEventListener('snapshots', (e) => showSnapshots(JSON.parse(e.data).snapshots));
  source.addEventListener('scenes', () => {
    if (browserShown) refreshScenes();
  });
  // Another tab's edit: its text, values and ranges (this tab's own edits
  // come back in the answer to its request).
  source.addEventListener('scene', (e) => {
    const { tab, view } = JSON.parse(e.data);
    if (tab !== TAB) others(view);
  });
  // Connected, or connected again: edits made meanwhile are fetched.
  source.addEventListener('open', () => {
    call('GET', '/studio/scene').then(others, () => {});
  });
  // A high-quality frame's tiles, several at once, without their pixels.
  source.addEventListener('tiles', (e) => {
    for (const t of JSON.parse(e.data).tiles) receive(t);
  });
  function receive(t) {
    moment(t.generation).arrived ??= performance.now();
    if (pending && pending.generation === t.generation) {
      if (finishing()) {
        hold(t);
        return;
      }
      startFrame(pending);
    }
    if (t.generation !== studio.generation) return;
    accept(t);
  }
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
  source.addEventListener('status', (e) => {
    applyStatus(JSON.parse(e.data));
    // While a high-quality frame renders, the tables wait for its drawing
    // (or STATUS_WAIT_MS): a layout costs the workers' cores.
    const waiting = studio.quality === 'high' && !studio.complete;
    if (!waiting || performance.now() - statusShown >= STATUS_WAIT_MS) showStatusNow();
  });
}

const STATUS_WAIT_MS = 2000;
const SHOWN_JOBS = 200;                // the newest jobs the table shows
const statusJobs = new Map();          // every job the status events told of, by id
let statusWorkers = [];
let statusChanged = false;             // told of changes not shown yet
let statusShown = -Infinity;

/** A status event carries changes: the workers when they changed, the jobs
 * new or changed, and the ids of jobs gone (`full`: every job, the first). */
function applyStatus(s) {
  if (s.full) statusJobs.clear();
  if (s.workers) statusWorkers = s.workers;
  for (const j of s.jobs ?? []) statusJobs.set(j.id, j);
  for (const id of s.gone ?? []) statusJobs.delete(id);
  statusChanged = true;
}

function showStatusNow() {
  if (!statusChanged) return;
  const jobs = [...statusJobs.values()].sort((a, b) => b.id - a.id).slice(0, SHOWN_JOBS);
  showStatus({ workers: statusWorkers, jobs });
  statusChanged = false;
  statusShown = performance.now();
}

/** Replaces the rows of `table` when they changed (a layout costs the
 * workers' cores). */
function setRows(table, html) {
  const body = $(table).tBodies[0];
  if (body.dataset.html !== html) {
    body.dataset.html = html;
    body.innerHTML = html;
  }
}

function showStatus(s) {
  setRows('workers', s.workers.map((w) =>
    `<tr><td><span style="color:${colour(w.name)}">■</span> ${escape(w.name)}</td><td class="num">${w.threads}</td>` +
    `<td class="num">${Math.round(w.pixels_per_second).toLocaleString()}</td><td class="num">${w.units}</td></tr>`).join(''));
  setRows('jobs', s.jobs.map((j) =>
    `<tr><td class="num">${j.id}</td><td class="state-${j.state}">${j.state}</td><td>${escape(j.scene_name)}</td>` +
    `<td class="num">${j.units_done}/${j.units_total}</td><td>${escape(j.out)}</td></tr>`).join(''));
}

// ---- The scene: knobs, parameters, curves and text --------------------------

const paramValues = {};   // parameters moved since the text was last replaced
let dragging = null;      // the curve handle being dragged

/** A labelled slider (`<input type=range>` with its `<output>`) in `box`. */
function slider(box, id, label, min, max, step, onInput) {
  const row = document.createElement('div');
  row.className = 'knob';
  row.innerHTML = `<label for="${escape(id)}">${escape(label)}</label>` +
    `<input type="range" id="${escape(id)}" min="${min}" max="${max}" step="${step}">` +
    `<output for="${escape(id)}"></output>`;
  box.appendChild(row);
  const input = row.querySelector('input');
  input.addEventListener('input', (e) => {
    onInput(input);
    studio.inputs.push(performance.now() - e.timeStamp);
    if (studio.inputs.length > INPUTS_KEPT) studio.inputs.shift();
  });
  return input;
}

/** A slider's range as the server gives it (it widens as values grow). */
function setRange(input, min, max, step) {
  if (input.min !== String(min)) input.min = min;
  if (input.max !== String(max)) input.max = max;
  if (input.step !== String(step)) input.step = step;
}

/** The slider this tab's pointer holds: another tab's edit leaves it be. */
let holding = null;
document.addEventListener('pointerdown', (e) => { holding = e.target; });
document.addEventListener('pointerup', () => { holding = null; });
function held(input) {
  return input === holding;
}

function setSlider(input, value) {
  input.value = value;
  input.nextElementSibling.textContent = format(value);
  input.setAttribute('aria-valuetext', format(value));
}

const GROUPS = { march: 'March', object: 'Object', modulation: 'Modulation', distortion: 'Distortion',
  camera: 'Camera', lights: 'Lights', shading: 'Shading', background: 'Background' };

/** Readable labels: `camera.eye[1]` → `eye y`; `modulation[0].Fur.frequency`
 * → `Fur frequency` (the second modulation: `#2 Fur frequency`);
 * `lights.sources[0].Directional.direction[0]` → `light 1 direction x`;
 * `march.bounds.min[2]` → `bounds min z`. */
function paramLabel(id, group) {
  let rest = id.slice(group.length).replace(/^\./, '')
    .replace(/^sources\[(\d+)\]\.\w+\./, (_, n) => `light ${Number(n) + 1} `)
    .replace(/^\[(\d+)\]\./, (_, n) => (n === '0' ? '' : `#${Number(n) + 1} `))
    .replace(/^projection\.\w+\.fov_y$/, 'field of view');
  const component = /\[(\d)\]$/.exec(rest);
  if (component) {
    const key = rest.slice(0, component.index).split('.').pop();
    const names = /colour|ambient/i.test(key) ? 'rgb' : 'xyz';
    rest = rest.slice(0, component.index) + ' ' + (names[Number(component[1])] ?? component[1]);
  }
  return rest.replace(/\[(\d+)\]/g, ' $1').replace(/[._]/g, ' ').replace(/\s+/g, ' ').trim() || group;
}

// ---- Colours: a picker for each colour's three sliders ------------------------

/** Whether `id` is the last component (`[2]`) of a colour whose three
 * components are sliders: `background.Colour[2]`, `lights.ambient[2]`. */
function colourTriple(id) {
  const m = /^(.*\.(?:\w*colour\w*|ambient)(?:\[\d+\])?)\[2\]$/i.exec(id);
  return Boolean(m) && [0, 1].every((k) => document.getElementById(`param-${m[1]}[${k}]`));
}

const hex2 = (v) => Math.round(Math.min(1, Math.max(0, linearToSrgb(v))) * 255).toString(16).padStart(2, '0');

/** A colour picker for the linear colour at `base` (its components
 * `base[0..2]`): a pick writes the three values in one edit. */
function colourPicker(box, base, group) {
  const row = document.createElement('div');
  row.className = 'knob';
  const id = 'pick-' + base;
  const name = paramLabel(base, group);
  row.innerHTML = `<label for="${escape(id)}">${escape(/colour/i.test(name) ? name : name + ' colour')}</label>` +
    `<input type="color" id="${escape(id)}">`;
  box.appendChild(row);
  const input = row.querySelector('input');
  input.addEventListener('input', () => {
    const values = {};
    const sliders = [0, 1, 2].map((k) => document.getElementById(`param-${base}[${k}]`));
    sliders.forEach((s, k) => {
      const code = parseInt(input.value.slice(1 + 2 * k, 3 + 2 * k), 16);
      values[`${base}[${k}]`] = Number(srgbToLinear(code / 255).toPrecision(6));
      s.value = values[`${base}[${k}]`];
    });
    paramMoved(values, null);
    sliders.forEach((s) => setSlider(s, Number(s.value)));
  });
}

/** Sets the picker of the colour at `base` to its sliders' values. */
function showPickedColour(base) {
  const picker = document.getElementById('pick-' + base);
  if (!picker || held(picker)) return;
  picker.value = '#' + [0, 1, 2].map((k) => hex2(Number(document.getElementById(`param-${base}[${k}]`).value))).join('');
}

function curveLabel(id) {
  return id.replace(/\.points$/, '').replace(/\.Curve$/, '').replace(/\[(\d+)\]/g, ' $1').replace(/\./g, ' ');
}

/** Shows the scene; `text`: replace the text box, `sliders`: set the sliders. */
function showScene(view, { text, sliders }) {
  studio.view = view;
  showHistory(view);
  studio.version = Math.max(studio.version, view.version);
  if (view.frame !== undefined && !pending) showFrameNumber(view.frame);
  $('scene-name').textContent = view.name;
  document.title = `${view.browser?.path ?? view.name} · hypertexture studio`;
  $('save').disabled = !view.savable;
  $('error').textContent = view.error || '';
  if (text) {
    $('text').value = view.text;
    studio.textBase = view.version;
  }

  const knobNames = view.knobs.map((k) => k.name).join(',');
  const box = $('knobs');
  const rebuilt = box.dataset.names !== knobNames;
  if (rebuilt) {
    box.dataset.names = knobNames;
    box.innerHTML = '';
    for (const k of view.knobs) {
      slider(box, 'knob-' + k.name, k.name, k.min, k.max, (k.max - k.min) / 1000, (input) => moved(k.name, input));
    }
    if (!view.knobs.length) box.textContent = 'This scene has no knobs.';
  }
  for (const k of view.knobs) {
    setRange($('knob-' + k.name), k.min, k.max, (k.max - k.min) / 1000);
    if (!sliders && !rebuilt) continue;
    if (held($('knob-' + k.name))) continue;
    setSlider($('knob-' + k.name), k.value);
    knobValues[k.name] = k.value;
  }

  const paramIds = view.params.map((p) => p.id).join(',');
  const params = $('params');
  const paramsRebuilt = params.dataset.ids !== paramIds;
  if (paramsRebuilt) {
    params.dataset.ids = paramIds;
    params.innerHTML = '';
    for (const key of Object.keys(paramValues)) delete paramValues[key];
    let group = null;
    let box = params;
    for (const p of view.params) {
      if (p.group !== group) {
        group = p.group;
        if (group === 'camera') {
          // The camera is steered in the image; its values fold away.
          box = document.createElement('details');
          box.id = 'camera-values';
          const summary = document.createElement('summary');
          summary.textContent = 'Camera values (drag the image to orbit, shift-drag to pan, wheel to dolly, F to frame)';
          box.appendChild(summary);
          params.appendChild(box);
        } else {
          box = params;
          const h = document.createElement('h3');
          h.textContent = GROUPS[group] || group;
          params.appendChild(h);
        }
      }
      const input = slider(box, 'param-' + p.id, paramLabel(p.id, p.group), p.min, p.max, p.step,
        (i) => paramMoved({ [p.id]: Number(Number(i.value).toPrecision(6)) }, i));
      input.dataset.param = p.id;
      if (p.comment) input.previousElementSibling.title = p.comment;
      if (colourTriple(p.id)) colourPicker(box, p.id.slice(0, -3), p.group);
    }
  }
  for (const p of view.params) {
    const input = document.getElementById('param-' + p.id);
    setRange(input, p.min, p.max, p.step);
    if (!sliders && !paramsRebuilt) continue;
    if (held(input)) continue;
    setSlider(input, p.value);
    if (p.id in paramValues) paramValues[p.id] = p.value;
    if (colourTriple(p.id)) showPickedColour(p.id.slice(0, -3));
  }
  showDistortions(view.distortions ?? []);
  showGrids(view.grids ?? []);
  if (!dragging) showCurves(view.curves);
  else {
    // The dragged curve keeps its points; its line takes the new samples.
    for (const c of view.curves) {
      const mine = curves.find((m) => m.id === c.id && m.points.length === c.points.length);
      if (mine) {
        Object.assign(mine, samplesOf(c));
        placeCurve(mine);
      }
    }
  }
}

function format(v) {
  return Number(v.toPrecision(4)).toString();
}

// ---- Curves: colour and alpha maps, 1D shape transfer functions --------------

const SVG = 'http://www.w3.org/2000/svg';
const CURVE_W = 280, CURVE_H = 120, PAD = 8;
let curves = [];          // the curves shown, with their control points

/** The values of a curve's points, for comparing. */
function curveKey(c) {
  return c.id + ':' + c.points.map((p) => [p.x.value, p.y?.value, p.rgb].join('/')).join(';');
}

/** A curve's samples (the renderer's own values, from the server). */
function samplesOf(c) {
  return { interpolation: c.interpolation, from: c.from, to: c.to, values: c.values, colours: c.colours };
}

function showCurves(list) {
  // Unchanged curves stay as drawn (a handle keeps its focus); their line
  // takes the server's samples.
  if (list.length === curves.length && list.every((c, i) => curveKey(c) === curveKey(curves[i]))) {
    list.forEach((c, i) => {
      Object.assign(curves[i], samplesOf(c));
      placeCurve(curves[i]);
    });
    return;
  }
  const focused = document.activeElement?.closest?.('svg')?.id;
  const point = document.activeElement?.dataset?.point;
  curves = list.map((c) => ({ id: c.id, ...samplesOf(c), points: c.points.map((p) => ({
    x: { ...p.x }, y: p.y && { ...p.y }, rgb: p.rgb && [...p.rgb] })) }));
  const box = $('curves');
  box.innerHTML = '';
  for (const c of curves) {
    const figure = document.createElement('figure');
    figure.className = 'curve';
    const caption = document.createElement('figcaption');
    caption.textContent = curveLabel(c.id);
    const svg = document.createElementNS(SVG, 'svg');
    svg.setAttribute('viewBox', `0 0 ${CURVE_W} ${CURVE_H}`);
    svg.setAttribute('width', CURVE_W);
    svg.setAttribute('height', CURVE_H);
    svg.setAttribute('role', 'group');
    svg.setAttribute('aria-label', curveLabel(c.id) + ': drag a control point, or focus it and use the arrow keys; ' +
      'double-click to add a point, Delete to delete the focused one');
    svg.id = 'curve-' + c.id;
    figure.append(caption, svg, curveTools(c));
    box.appendChild(figure);
    c.svg = svg;
    c.selected = Math.min(selectedPoints[c.id] ?? 0, c.points.length - 1);
    svg.addEventListener('dblclick', (e) => addPointAt(c, e));
    drawCurve(c);
  }
  if (!curves.length) box.textContent = 'This scene has no curves.';
  if (focused && point !== undefined) document.getElementById(focused)?.querySelector(`[data-point="${point}"]`)?.focus();
}

/** The curve's domain: [0, 1] on each axis, widened to take every point
 * and every sampled value (a spline overshoots its points). */
function domain(c) {
  const xs = c.points.map((p) => p.x.value);
  const ys = c.points.filter((p) => p.y).map((p) => p.y.value).concat(c.values ?? []);
  return {
    x0: Math.min(0, ...xs), x1: Math.max(1, ...xs),
    y0: Math.min(0, ...ys), y1: Math.max(1, ...ys),
  };
}

function toScreen(c, d, p) {
  const sx = PAD + (p.x.value - d.x0) / (d.x1 - d.x0) * (CURVE_W - 2 * PAD);
  const sy = p.y ? CURVE_H - PAD - (p.y.value - d.y0) / (d.y1 - d.y0) * (CURVE_H - 2 * PAD) : CURVE_H / 2;
  return [sx, sy];
}

function rgbCss(rgb) {
  return `rgb(${rgb.map((v) => Math.round(Math.min(1, Math.max(0, v)) ** (1 / 2.2) * 255)).join(',')})`;
}

function drawCurve(c) {
  const svg = c.svg;
  const d = c.domain ?? (c.domain = domain(c));
  svg.replaceChildren();
  const frame = document.createElementNS(SVG, 'rect');
  frame.setAttribute('x', PAD); frame.setAttribute('y', PAD);
  frame.setAttribute('width', CURVE_W - 2 * PAD); frame.setAttribute('height', CURVE_H - 2 * PAD);
  frame.setAttribute('class', 'curve-frame');
  svg.appendChild(frame);
  const colour = c.points.every((p) => p.rgb);
  if (colour) {
    // The colour map as a strip, its stops at the control points.
    const gradient = document.createElementNS(SVG, 'linearGradient');
    gradient.id = 'gradient-' + c.id.replace(/[^A-Za-z0-9_-]/g, '_');
    c.gradient = gradient;
    const defs = document.createElementNS(SVG, 'defs');
    defs.appendChild(gradient);
    const strip = document.createElementNS(SVG, 'rect');
    strip.setAttribute('x', PAD); strip.setAttribute('y', CURVE_H / 2 - 18);
    strip.setAttribute('width', CURVE_W - 2 * PAD); strip.setAttribute('height', 36);
    strip.setAttribute('fill', `url(#${gradient.id})`);
    svg.append(defs, strip);
  } else {
    c.line = document.createElementNS(SVG, 'polyline');
    c.line.setAttribute('class', 'curve-line');
    svg.appendChild(c.line);
  }
  c.handles = c.points.map((p, i) => {
    const handle = document.createElementNS(SVG, 'circle');
    handle.setAttribute('r', 6);
    handle.setAttribute('class', 'handle');
    handle.setAttribute('tabindex', '0');
    handle.setAttribute('role', 'slider');
    handle.setAttribute('aria-label', `${curveLabel(c.id)}, point ${i + 1}`);
    handle.dataset.point = i;
    if (p.rgb) handle.setAttribute('fill', rgbCss(p.rgb));
    handle.addEventListener('pointerdown', (e) => {
      e.preventDefault();
      handle.setPointerCapture(e.pointerId);
      dragging = { c, i, pointer: e.pointerId };
      selectPoint(c, i);
    });
    handle.addEventListener('focus', () => selectPoint(c, i));
    handle.addEventListener('dblclick', (e) => e.stopPropagation());
    handle.addEventListener('pointermove', (e) => {
      if (!dragging || dragging.pointer !== e.pointerId) return;
      const r = svg.getBoundingClientRect();
      const sx = (e.clientX - r.left) * CURVE_W / r.width;
      const sy = (e.clientY - r.top) * CURVE_H / r.height;
      movePoint(c, i, d.x0 + (sx - PAD) / (CURVE_W - 2 * PAD) * (d.x1 - d.x0),
        d.y0 + (CURVE_H - PAD - sy) / (CURVE_H - 2 * PAD) * (d.y1 - d.y0));
    });
    const end = () => { dragging = null; };
    handle.addEventListener('pointerup', end);
    handle.addEventListener('pointercancel', end);
    handle.addEventListener('keydown', (e) => {
      if (e.key === 'Delete' || e.key === 'Backspace') {
        e.preventDefault();
        deletePoint(c, i);
        return;
      }
      const step = (d.x1 - d.x0) / 100;
      const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowDown: [0, -step], ArrowUp: [0, step] };
      const m = moves[e.key];
      if (!m) return;
      e.preventDefault();
      movePoint(c, i, p.x.value + m[0], p.y ? p.y.value + m[1] : 0);
    });
    svg.appendChild(handle);
    return handle;
  });
  placeCurve(c);
}

/** Puts the curve's line, colour stops and handles where its points are
 * (the elements stay: a dragged handle keeps its pointer capture). */
function placeCurve(c) {
  const d = c.domain;
  const n = Math.max(c.values?.length ?? 0, c.colours?.length ?? 0);
  const keyAt = (i) => c.from + (i / (n - 1)) * (c.to - c.from);
  if (c.line) {
    const line = c.values?.length
      ? c.values.map((y, i) => toScreen(c, d, { x: { value: keyAt(i) }, y: { value: y } }).join(','))
      : c.points.map((p) => toScreen(c, d, p).join(','));
    c.line.setAttribute('points', line.join(' '));
  }
  if (c.gradient) {
    // One stop a sample: the map as the renderer evaluates it (a step map
    // shows its steps).
    const stops = c.colours?.length
      ? c.colours.map((rgb, i) => [keyAt(i), rgb])
      : c.points.map((p) => [p.x.value, p.rgb]);
    c.gradient.replaceChildren(...stops.map(([x, rgb]) => {
      const stop = document.createElementNS(SVG, 'stop');
      stop.setAttribute('offset', (x - d.x0) / (d.x1 - d.x0));
      stop.setAttribute('stop-color', rgbCss(rgb));
      return stop;
    }));
  }
  showCurveTools(c);
  c.handles.forEach((handle, i) => {
    const p = c.points[i];
    handle.classList.toggle('selected', i === c.selected);
    if (p.rgb) handle.setAttribute('fill', rgbCss(p.rgb));
    const [x, y] = toScreen(c, d, p);
    handle.setAttribute('cx', x);
    handle.setAttribute('cy', y);
    handle.setAttribute('aria-valuenow', p.x.value);
    handle.setAttribute('aria-valuetext', p.y ? `x ${format(p.x.value)}, y ${format(p.y.value)}` : `x ${format(p.x.value)}`);
  });
}

/** Moves control point `i` of `c` to (x, y), x kept between its neighbours
 * and both inside the curve's domain, and asks for the frame. */
function movePoint(c, i, x, y) {
  const d = c.domain;
  const eps = (d.x1 - d.x0) / 1000;
  const lo = i > 0 ? c.points[i - 1].x.value + eps : d.x0;
  const hi = i + 1 < c.points.length ? c.points[i + 1].x.value - eps : d.x1;
  const p = c.points[i];
  const round = (v) => Number(v.toPrecision(4));
  p.x.value = round(Math.min(hi, Math.max(lo, x)));
  const change = { [p.x.id]: p.x.value };
  if (p.y) {
    p.y.value = round(Math.min(d.y1, Math.max(d.y0, y)));
    change[p.y.id] = p.y.value;
  }
  placeCurve(c);
  paramMoved(change, null);
}

// ---- Editing a curve's shape: points added and deleted, its interpolation, --------
// ---- a colour stop's colour ------------------------------------------------------

const selectedPoints = {};   // curve id → the index of its selected point
const INTERPOLATIONS = ['Linear', 'Spline', 'Step'];

/** The row under a curve: its interpolation, Delete point and, on a colour
 * map, the picker of the selected stop's colour. */
function curveTools(c) {
  const row = document.createElement('div');
  row.className = 'curve-tools';
  const pick = c.points.every((p) => p.rgb)
    ? `<label for="${escape('stop-' + c.id)}">stop colour</label><input type="color" id="${escape('stop-' + c.id)}">`
    : '';
  row.innerHTML = `<label for="${escape('interp-' + c.id)}">interpolation</label>` +
    `<select id="${escape('interp-' + c.id)}">${INTERPOLATIONS.map((w) => `<option>${w}</option>`).join('')}</select>` +
    pick + `<button type="button" id="${escape('delete-' + c.id)}">Delete point</button>`;
  const select = row.querySelector('select');
  select.value = c.interpolation;
  select.addEventListener('change', () => {
    shapeEdited([{ op: 'set', path: c.id.replace(/\.points$/, '.interpolation'), to: select.value }]);
  });
  row.querySelector('button').addEventListener('click', () => deletePoint(c, c.selected));
  const picker = row.querySelector('input[type=color]');
  if (picker) picker.addEventListener('input', () => stopPicked(c, picker));
  return row;
}

/** Sets the tools under `c` to its interpolation and selected point. */
function showCurveTools(c) {
  const select = document.getElementById('interp-' + c.id);
  if (select && select.value !== c.interpolation) select.value = c.interpolation;
  const remove = document.getElementById('delete-' + c.id);
  if (remove) remove.disabled = c.points.length < 2;
  const picker = document.getElementById('stop-' + c.id);
  const p = c.points[c.selected];
  if (picker && p?.rgb && !held(picker)) picker.value = '#' + p.rgb.map(hex2).join('');
  if (picker) picker.setAttribute('aria-label', `${curveLabel(c.id)}, colour of stop ${c.selected + 1}`);
}

function selectPoint(c, i) {
  c.selected = i;
  selectedPoints[c.id] = i;
  placeCurve(c);
}

/** A structural edit of the text: its own undo step, made on the version
 * shown, with the values moved but not sent yet written first. */
function shapeEdited(edits) {
  const asked = performance.now();
  newGesture();
  const change = { ...current('interactive'), edits };
  for (const key of Object.keys(paramValues)) delete paramValues[key];
  send(change, asked, true);
}

/** A double-click in a curve's frame adds a point there: on a scalar curve
 * at the pointer's value, on a colour map with the map's colour at its key. */
function addPointAt(c, e) {
  const d = c.domain;
  const r = c.svg.getBoundingClientRect();
  const sx = (e.clientX - r.left) * CURVE_W / r.width;
  const sy = (e.clientY - r.top) * CURVE_H / r.height;
  // A double-click is no finer than a pixel: keys and values on a 0.01 grid.
  const round = (v) => Math.round(v * 100) / 100;
  const x = round(Math.min(1, Math.max(0, d.x0 + (sx - PAD) / (CURVE_W - 2 * PAD) * (d.x1 - d.x0))));
  if (c.points.some((p) => p.x.value === x)) return;
  const edit = { op: 'add_point', curve: c.id, x };
  if (c.points.every((p) => p.rgb)) {
    const n = c.colours?.length ?? 0;
    const at = n ? Math.round((x - c.from) / (c.to - c.from) * (n - 1)) : -1;
    edit.rgb = (c.colours?.[Math.min(n - 1, Math.max(0, at))] ?? c.points[0].rgb).map((v) => Number(v.toPrecision(4)));
  } else {
    edit.y = round(Math.min(d.y1, Math.max(d.y0, d.y0 + (CURVE_H - PAD - sy) / (CURVE_H - 2 * PAD) * (d.y1 - d.y0))));
  }
  selectedPoints[c.id] = c.points.filter((p) => p.x.value < x).length;
  shapeEdited([edit]);
}

function deletePoint(c, i) {
  if (c.points.length < 2 || i === undefined || i < 0 || i >= c.points.length) return;
  selectedPoints[c.id] = Math.max(0, i - 1);
  shapeEdited([{ op: 'delete_point', curve: c.id, index: i }]);
}

/** The picked colour of the selected stop: its three numbers in one edit. */
function stopPicked(c, picker) {
  const p = c.points[c.selected];
  if (!p?.rgb) return;
  const values = {};
  p.rgb = [0, 1, 2].map((k) => {
    const code = parseInt(picker.value.slice(1 + 2 * k, 3 + 2 * k), 16);
    const v = Number(srgbToLinear(code / 255).toPrecision(6));
    values[`${c.id}[${c.selected}][1][${k}]`] = v;
    return v;
  });
  placeCurve(c);
  paramMoved(values, null);
}

// ---- Distortion terms and 2D shape transfer grids ---------------------------------

const FIELDS = ['Boundary', 'Radial', 'Constant', 'Curl', 'Perturbed'];

/** Each distortion's vector field, and each term's operator and switch. */
function showDistortions(list) {
  const box = $('distortions');
  const key = JSON.stringify(list);
  if (box.dataset.key === key) return;
  box.dataset.key = key;
  box.innerHTML = '';
  for (const d of list) {
    const h = document.createElement('h3');
    h.textContent = d.id === 'distortion' ? 'Distortion' : paramLabel(d.id, '');
    box.appendChild(h);
    const row = document.createElement('div');
    row.className = 'term';
    row.innerHTML = `<label for="${escape('field-' + d.id)}">vector field</label>` +
      `<select id="${escape('field-' + d.id)}">${FIELDS.map((w) => `<option>${w}</option>`).join('')}</select>`;
    const field = row.querySelector('select');
    field.value = d.field;
    field.addEventListener('change', () => shapeEdited([{ op: 'set', path: d.id + '.field', to: field.value }]));
    box.appendChild(row);
    d.terms.forEach((t, k) => {
      const term = document.createElement('div');
      term.className = 'term';
      term.innerHTML = `<span>term ${k + 1} (${escape(t.transfer)})</span>` +
        `<select id="${escape('operator-' + t.id)}" aria-label="term ${k + 1} operator"><option>Sum</option><option>Blend</option></select>` +
        `<label><input type="checkbox" id="${escape('enabled-' + t.id)}"> enabled</label>`;
      const operator = term.querySelector('select');
      operator.value = t.operator;
      operator.addEventListener('change', () => shapeEdited([{ op: 'set', path: t.id + '.operator', to: operator.value }]));
      const enabled = term.querySelector('input');
      enabled.checked = t.enabled;
      enabled.addEventListener('change', () => shapeEdited([{ op: 'set', path: t.id + '.enabled', to: String(enabled.checked) }]));
      box.appendChild(term);
    });
  }
}

const CELL_MAX = 24;
let grids = [];           // the grids shown, with their values
let painting = null;      // the grid a stroke of the brush paints

/** Gilet & Dischler's 2D shape transfer functions: each grid's cells as
 * grey levels (noise left to right, object density 0 at the top, 1 at the
 * bottom), painted with a brush of a value and a size. */
function showGrids(list) {
  const box = $('grids');
  const key = list.map((g) => `${g.id}:${g.rows}x${g.columns}`).join(',');
  if (box.dataset.key === key) {
    if (!painting) list.forEach((g, i) => { grids[i].values = [...g.values]; drawGrid(grids[i]); });
    return;
  }
  box.dataset.key = key;
  box.innerHTML = '';
  grids = list.map((g) => ({ ...g, values: [...g.values] }));
  for (const g of grids) {
    const figure = document.createElement('figure');
    figure.className = 'curve';
    const cell = Math.max(4, Math.min(CELL_MAX, Math.floor(264 / g.columns)));
    figure.innerHTML = `<figcaption>${escape(curveLabel(g.id.replace(/\.Grid\.rows$/, '')))}: ` +
      'noise →, object density ↓ (paint with the brush)</figcaption>' +
      `<canvas id="${escape('grid-' + g.id)}" width="${g.columns * cell}" height="${g.rows * cell}" class="grid"></canvas>` +
      `<div class="curve-tools"><label for="${escape('brush-' + g.id)}">brush value</label>` +
      `<input type="range" id="${escape('brush-' + g.id)}" min="0" max="1" step="0.05" value="1">` +
      `<output>1</output><label for="${escape('brush-size-' + g.id)}">size</label>` +
      `<input type="range" id="${escape('brush-size-' + g.id)}" min="0" max="3" step="1" value="0"></div>`;
    box.appendChild(figure);
    g.cell = cell;
    g.canvas = figure.querySelector('canvas');
    [g.brush, g.size] = figure.querySelectorAll('input[type=range]');
    g.brush.addEventListener('input', () => { g.brush.nextElementSibling.textContent = g.brush.value; });
    g.canvas.addEventListener('pointerdown', (e) => {
      e.preventDefault();
      g.canvas.setPointerCapture(e.pointerId);
      painting = { g, pointer: e.pointerId };
      paint(g, e);
    });
    g.canvas.addEventListener('pointermove', (e) => {
      if (painting?.pointer === e.pointerId) paint(g, e);
    });
    const end = () => { painting = null; };
    g.canvas.addEventListener('pointerup', end);
    g.canvas.addEventListener('pointercancel', end);
    drawGrid(g);
  }
}

function drawGrid(g) {
  const ctx = g.canvas.getContext('2d');
  for (let j = 0; j < g.rows; j++) {
    for (let i = 0; i < g.columns; i++) {
      const v = Math.round(Math.min(1, Math.max(0, g.values[j * g.columns + i])) * 255);
      ctx.fillStyle = `rgb(${v},${v},${v})`;
      ctx.fillRect(i * g.cell, j * g.cell, g.cell - 1, g.cell - 1);
    }
  }
}

/** Paints the cells under the pointer (and those within the brush's size)
 * with the brush's value: their numbers in one edit. */
function paint(g, e) {
  const r = g.canvas.getBoundingClientRect();
  const i = Math.floor((e.clientX - r.left) / r.width * g.columns);
  const j = Math.floor((e.clientY - r.top) / r.height * g.rows);
  const size = Number(g.size.value);
  const value = Number(g.brush.value);
  const values = {};
  for (let jj = j - size; jj <= j + size; jj++) {
    for (let ii = i - size; ii <= i + size; ii++) {
      if (jj < 0 || ii < 0 || jj >= g.rows || ii >= g.columns) continue;
      if (g.values[jj * g.columns + ii] === value) continue;
      g.values[jj * g.columns + ii] = value;
      values[`${g.id}[${jj}][${ii}]`] = value;
    }
  }
  if (!Object.keys(values).length) return;
  drawGrid(g);
  paramMoved(values, null);
}

// ---- The frame of a sequence: a slider and Play ----------------------------------

const frameInput = $('frame-number');
let playing = null;    // the timer that steps the frames while playing

/** Shows frame `n` on the slider (widened to hold it), unless held. */
function showFrameNumber(n) {
  studio.frame = n;
  if (n > Number(frameInput.max)) frameInput.max = n;
  if (held(frameInput)) return;
  frameInput.value = n;
  $('frame-shown').textContent = n;
}

function frameMoved(n) {
  const asked = performance.now();
  showFrameNumber(n);
  send({ ...current('interactive'), frame: n }, asked, true);
}

frameInput.addEventListener('input', () => frameMoved(Number(frameInput.value)));
$('play').addEventListener('click', () => {
  if (playing !== null) {
    clearInterval(playing);
    playing = null;
  } else {
    // The next frame once the one shown is drawn whole.
    playing = setInterval(() => {
      if (inFlight || gated() || queued || !studio.drawn) return;
      frameMoved((Number(frameInput.value) + 1) % (Number(frameInput.max) + 1));
    }, 40);
  }
  $('play').textContent = playing === null ? 'Play' : 'Pause';
  $('play').setAttribute('aria-pressed', String(playing !== null));
});

// ---- The camera in the image: orbit, pan, dolly, frame --------------------------

/** The camera's vectors from the scene's numbers (null when the text does
 * not write them all). */
function cameraNow() {
  const get = (name) => {
    const v = [0, 1, 2].map((i) => studio.view?.params.find((p) => p.id === `camera.${name}[${i}]`)?.value);
    return v.every((x) => x !== undefined) ? v.map((x, i) => paramValues[`camera.${name}[${i}]`] ?? x) : null;
  };
  const eye = get('eye'), lookAt = get('look_at'), up = get('up');
  return eye && lookAt && up ? { eye, lookAt, up } : null;
}

const add = (a, b) => a.map((x, i) => x + b[i]);
const sub = (a, b) => a.map((x, i) => x - b[i]);
const scale = (a, k) => a.map((x) => x * k);
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => scale(a, 1 / Math.hypot(...a));

/** `v` turned by `angle` about the unit axis `k` (Rodrigues). */
function rotate(v, k, angle) {
  const c = Math.cos(angle), s = Math.sin(angle);
  return add(add(scale(v, c), scale(cross(k, v), s)), scale(k, dot(k, v) * (1 - c)));
}

/** Sends the camera's eye and look_at (the up vector stays the scene's). */
function moveCamera(eye, lookAt) {
  const values = {};
  const round = (v) => Number(v.toPrecision(6));
  eye.forEach((v, i) => { values[`camera.eye[${i}]`] = round(v); });
  lookAt.forEach((v, i) => { values[`camera.look_at[${i}]`] = round(v); });
  for (const [id, v] of Object.entries(values)) {
    const input = document.getElementById('param-' + id);
    if (input) setSlider(input, v);
  }
  paramMoved(values, null);
}

/** Orbits the eye about look_at: across the image turns about the up
 * vector, up and down about the camera's right, stopping short of the
 * poles so that the up vector never flips. */
function orbit(cam, dx, dy) {
  const up = unit(cam.up);
  let offset = sub(cam.eye, cam.lookAt);
  offset = rotate(offset, up, -dx * 0.01);
  const right = unit(cross(offset, up));
  const turned = rotate(offset, right, dy * 0.01);
  const pole = Math.abs(dot(unit(turned), up));
  if (pole < 0.995) offset = turned;
  moveCamera(add(cam.lookAt, offset), cam.lookAt);
}

/** Pans eye and look_at together in the image's plane. */
function pan(cam, dx, dy) {
  const forward = sub(cam.lookAt, cam.eye);
  const distance = Math.hypot(...forward);
  const right = unit(cross(forward, cam.up));
  const upward = unit(cross(right, forward));
  const k = distance / Math.max(1, image.getBoundingClientRect().height);
  const shift = add(scale(right, -dx * k), scale(upward, dy * k));
  moveCamera(add(cam.eye, shift), add(cam.lookAt, shift));
}

/** Dollies the eye toward look_at (`steps` < 0) or away. */
function dolly(cam, steps) {
  const offset = sub(cam.eye, cam.lookAt);
  moveCamera(add(cam.lookAt, scale(offset, Math.exp(steps * 0.1))), cam.lookAt);
}

/** Frames the march's bounds: look_at at their centre, the eye along its
 * present direction far enough for the bounding sphere to fill the view. */
function frameBounds(cam) {
  const min = [0, 1, 2].map((i) => studio.view?.params.find((p) => p.id === `march.bounds.min[${i}]`)?.value);
  const max = [0, 1, 2].map((i) => studio.view?.params.find((p) => p.id === `march.bounds.max[${i}]`)?.value);
  if (![...min, ...max].every((x) => x !== undefined)) return;
  const centre = scale(add(min, max), 0.5);
  const radius = Math.hypot(...sub(max, min)) / 2;
  const fov = studio.view.params.find((p) => p.id.endsWith('fov_y'))?.value ?? 50;
  const distance = (radius / Math.sin((fov * Math.PI) / 360)) * 1.05;
  moveCamera(add(centre, scale(unit(sub(cam.eye, cam.lookAt)), distance)), centre);
}

let steering = null;   // the pointer dragging in the image
image.addEventListener('pointerdown', (e) => {
  if (!cameraNow()) return;
  e.preventDefault();
  image.setPointerCapture(e.pointerId);
  steering = { pointer: e.pointerId, x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 1 };
});
image.addEventListener('pointermove', (e) => {
  if (!steering || steering.pointer !== e.pointerId) return;
  const cam = cameraNow();
  const dx = e.clientX - steering.x, dy = e.clientY - steering.y;
  if (!cam || (dx === 0 && dy === 0)) return;
  steering.x = e.clientX;
  steering.y = e.clientY;
  if (steering.pan) pan(cam, dx, dy);
  else orbit(cam, dx, dy);
});
const stopSteering = () => { steering = null; };
image.addEventListener('pointerup', stopSteering);
image.addEventListener('pointercancel', stopSteering);
image.addEventListener('wheel', (e) => {
  const cam = cameraNow();
  if (!cam) return;
  e.preventDefault();
  dolly(cam, Math.sign(e.deltaY));
}, { passive: false });
image.tabIndex = 0;
image.addEventListener('keydown', (e) => {
  const cam = cameraNow();
  if (!cam) return;
  const keys = { ArrowLeft: [-10, 0], ArrowRight: [10, 0], ArrowUp: [0, -10], ArrowDown: [0, 10] };
  if (e.key === 'f' || e.key === 'F') frameBounds(cam);
  else if (keys[e.key]) (e.shiftKey ? pan : orbit)(cam, ...keys[e.key]);
  else if (e.key === '+' || e.key === '-') dolly(cam, e.key === '+' ? -1 : 1);
  else return;
  e.preventDefault();
});

// ---- Sending changes ----------------------------------------------------------

let inFlight = false;
let queued = null;
// While a slider moves, the next frame waits for the one in flight to show
// its first tile (or, if it is slow, for GATE_MAX_MS): a frame replaced
// before its first tile would never be seen. The server renders a begun
// interactive frame to its end with the next one queued behind it, so the
// workers never wait for the page between the frames of a drag.
let waitingFor = null;
let gateTimer = null;
let gateSince = 0;
const GATE_MAX_MS = 2000;

function gated() {
  return waitingFor !== null;
}

function release() {
  waitingFor = null;
  clearTimeout(gateTimer);
  flush();
}

/** Called as tiles arrive: the frame the gate waits for has begun. */
function frameProgress() {
  if (waitingFor !== null && studio.generation === waitingFor && studio.received > 0) release();
}

function checkGate() {
  if (performance.now() - gateSince >= GATE_MAX_MS) release();
  else gateTimer = setTimeout(checkGate, 50);
}

function flush() {
  if (!inFlight && !gated() && queued) {
    const [c, a, f] = queued;
    queued = null;
    // A slider's change waiting behind this tab's own is made on the
    // version that answer brought (the sliders show it), not the one before.
    send(f ? { ...c, base: studio.version } : c, a, f);
  }
}

/** Whether the text box holds edits not sent yet (or on their way). */
function textDirty() {
  return editTimer !== null || $('text').value !== studio.view?.text;
}

/** Shows a view newer than this tab's: every slider (but one held) and,
 * unless this tab's text has edits of its own, the text. */
function others(view) {
  if (view.version <= studio.version) return;
  const switched = studio.view !== null && view.name !== studio.view.name;
  if (switched) sceneSwitched();
  showScene(view, { text: switched || !textDirty(), sliders: true });
}

/** An edit refused because another tab changed the same value or lines:
 * the page shows why; "Take theirs" shows the current state, "Keep mine"
 * sends this tab's text over it. */
function conflict(message, change) {
  studio.conflict = message;
  $('conflict-message').textContent = message;
  $('conflict').hidden = false;
  $('keep-mine').hidden = change.text === undefined;
  $('keep-mine').onclick = () => {
    $('conflict').hidden = true;
    send({ ...change, text: $('text').value, base: studio.version }, performance.now(), false);
  };
}

$('take-theirs').addEventListener('click', () => {
  $('conflict').hidden = true;
  clearTimeout(editTimer);
  editTimer = null;
  call('GET', '/studio/scene').then((view) => showScene(view, { text: true, sliders: true }),
    (e) => { $('error').textContent = e.message; });
});

/** Sends a change (from a slider, or from the text) made on version
 * `change.base`; while one is in flight, only the latest waits. */
function send(change, asked, fromSlider) {
  if (inFlight || gated()) {
    // A structural edit waiting is kept: the change after it carries it.
    const before = queued?.[0];
    if (before?.edits?.length) {
      change = { ...change, params: { ...before.params, ...change.params },
        edits: [...before.edits, ...(change.edits ?? [])] };
    }
    queued = [change, asked, fromSlider];
    return;
  }
  inFlight = true;
  call('POST', '/studio/scene', { ...change, tab: TAB }).then((view) => {
    const m = moment(view.generation);
    m.asked ??= asked;
    m.answered ??= performance.now();
    m.quality ??= change.quality ?? 'high';
    $('conflict').hidden = true;
    // The text as sent, merged with other tabs' edits, replaces the box's
    // unless typing went on meanwhile.
    const sentText = change.text !== undefined && $('text').value === change.text && editTimer === null;
    showScene(view, { text: (fromSlider && !textDirty()) || sentText, sliders: !fromSlider });
    if (change.quality === 'interactive') {
      if (fromSlider) {
        waitingFor = view.generation;
        gateSince = performance.now();
        clearTimeout(gateTimer);
        gateTimer = setTimeout(checkGate, 50);
        frameProgress();
      }
    }
  }, (error) => {
    if (error.status === 409) conflict(error.message, change);
    else $('error').textContent = error.message;
  }).finally(() => {
    inFlight = false;
    flush();
  });
}

/** The sliders' values as a change at `quality`. */
function current(quality) {
  // While a pointer holds a control, a preview: the quarter of the pixels
  // on the 2×-coarser lattice, so that a drag shows more of its values.
  const preview = quality === 'interactive' && holding !== null;
  return { knobs: { ...knobValues }, params: { ...paramValues }, quality, base: studio.version, gesture, preview };
}

function moved(name, input) {
  const asked = performance.now();
  const value = Number(input.value);
  knobValues[name] = value;
  setSlider(input, value);
  send(current('interactive'), asked, true);
}

function paramMoved(values, input) {
  const asked = performance.now();
  Object.assign(paramValues, values);
  if (input) setSlider(input, Number(input.value));
  send(current('interactive'), asked, true);
}

let editTimer = null;
$('text').addEventListener('input', () => {
  const asked = performance.now();
  clearTimeout(editTimer);
  editTimer = setTimeout(() => {
    editTimer = null;
    for (const key of Object.keys(paramValues)) delete paramValues[key];
    send({ text: $('text').value, quality: 'interactive', base: studio.textBase, gesture: typing() }, asked, false);
  }, 150);
});

/** Saves the text; a file changed on disk since is not written over
 * unless `over`: the page offers Reload and Save over it instead. */
function save(over) {
  $('changed-on-disk').hidden = true;
  call('POST', over ? '/studio/save?over=true' : '/studio/save').then(
    (r) => {
      $('action-result').textContent = r.saved;
      if (browserShown) refreshScenes();
    },
    (e) => {
      $('action-result').textContent = e.message;
      if (e.status === 409) $('changed-on-disk').hidden = false;
    });
}

$('save').addEventListener('click', () => save(false));
$('save-over').addEventListener('click', () => save(true));
$('reload').addEventListener('click', () => {
  $('changed-on-disk').hidden = true;
  call('POST', '/studio/reload').then((view) => {
    showScene(view, { text: true, sliders: true });
    $('action-result').textContent = 'reloaded the file';
  }, (e) => { $('action-result').textContent = e.message; });
});

$('enlarge').addEventListener('click', () => {
  const on = document.body.classList.toggle('enlarged');
  $('enlarge').setAttribute('aria-pressed', String(on));
  $('enlarge').textContent = on ? 'Shrink' : 'Enlarge';
});

$('final').addEventListener('click', () => {
  call('POST', '/studio/final').then(({ job, number }) => {
    $('action-result').textContent = `job ${job.id} queued → ${job.out}`;
    watchFinal(job, number);
  }, (e) => { $('action-result').textContent = e.message; });
});

/** Follows a final render's job; once written, shows its image with a
 * download link. */
function watchFinal(job, number) {
  setTimeout(() => call('GET', `/api/v1/jobs/${job.id}`).then(async (now) => {
    if (now.state === 'queued' || now.state === 'running') {
      const percent = now.units_total ? Math.floor((100 * now.units_done) / now.units_total) : 0;
      $('action-result').textContent = `job ${job.id} ${now.state} ${percent}% → ${job.out}`;
      watchFinal(job, number);
      return;
    }
    if (now.state !== 'done') {
      $('action-result').textContent = `job ${job.id} ${now.state}${now.error ? ': ' + now.error : ''}`;
      return;
    }
    const response = await fetch(`/studio/final/${number}`, { headers: headers(false) });
    if (!response.ok) {
      $('action-result').textContent = (await response.json()).error;
      return;
    }
    const url = URL.createObjectURL(await response.blob());
    const name = job.out.split('/').pop();
    $('final-image').src = url;
    $('final-link').href = url;
    $('final-link').download = name;
    $('final-link').textContent = `download ${name}`;
    $('final-figure').hidden = false;
    $('action-result').textContent = `job ${job.id} done → ${job.out}`;
  }, (e) => { $('action-result').textContent = e.message; }), 500);
}

// ---- Undo, redo, snapshots and the A/B view --------------------------------------
// One history for every tab, kept by the server: an undo is an edit that sets
// the text back byte for byte, and every tab follows it. The edits of one
// gesture (a drag of a slider, a curve's point or the camera, a burst of
// typing, a key) are one step.

let gesture = null;
let gestures = 0;
let typingGesture = null;
let lastTyped = -Infinity;
let lastWheel = -Infinity;

function newGesture() {
  gesture = `${TAB}.${++gestures}`;
}

/** Whether `target` edits text (its own undo is the browser's). */
function isTextField(target) {
  return target instanceof HTMLTextAreaElement ||
    (target instanceof HTMLInputElement && ['text', 'search', 'password'].includes(target.type));
}

/** The gesture of a text edit: a new one after a second without typing. */
function typing() {
  const now = performance.now();
  if (!typingGesture || now - lastTyped > 1000) typingGesture = `${TAB}.${++gestures}`;
  lastTyped = now;
  return typingGesture;
}

document.addEventListener('pointerdown', newGesture, true);
document.addEventListener('keydown', (e) => {
  if (!isTextField(e.target) && !e.ctrlKey && !e.metaKey && !e.altKey) newGesture();
}, true);
document.addEventListener('wheel', () => {
  if (performance.now() - lastWheel > 500) newGesture();
  lastWheel = performance.now();
}, { capture: true, passive: true });

/** Undo (`back`) or redo, for every tab. */
function stepHistory(back) {
  clearTimeout(editTimer);
  editTimer = null;
  call('POST', `/studio/${back ? 'undo' : 'redo'}?tab=${encodeURIComponent(TAB)}`).then(
    (view) => showScene(view, { text: true, sliders: true }),
    (e) => { $('action-result').textContent = e.message; });
}

document.addEventListener('keydown', (e) => {
  if (!(e.ctrlKey || e.metaKey) || e.altKey || isTextField(e.target)) return;
  const key = e.key.toLowerCase();
  if (key === 'z') stepHistory(!e.shiftKey);
  else if (key === 'y') stepHistory(false);
  else return;
  e.preventDefault();
});
$('undo').addEventListener('click', () => stepHistory(true));
$('redo').addEventListener('click', () => stepHistory(false));

function showHistory(view) {
  if (view.undo !== undefined) {
    $('undo').disabled = view.undo === 0;
    $('redo').disabled = view.redo === 0;
    $('undo').title = `Ctrl+Z: ${view.undo} step${view.undo === 1 ? '' : 's'} back`;
    $('redo').title = `Ctrl+Shift+Z or Ctrl+Y: ${view.redo} step${view.redo === 1 ? '' : 's'} forward`;
  }
  if (view.snapshots) showSnapshots(view.snapshots);
  drawBounds();
  offerBrowser(view);
}

studio.snapshots = [];
studio.compare = null;   // the A/B view: {id, split (the first column of B), drawn}

function button(label, onClick) {
  const b = document.createElement('button');
  b.type = 'button';
  b.textContent = label;
  b.addEventListener('click', onClick);
  return b;
}

function showSnapshots(list) {
  studio.snapshots = list;
  const box = $('snapshots');
  box.innerHTML = '';
  for (const s of list) {
    const item = document.createElement('li');
    item.dataset.id = s.id;
    const label = document.createElement('span');
    const state = s.ready ? '' : s.error ? ` · ${s.error}` : ' · rendering…';
    label.textContent = `${s.name} · version ${s.version}${state}`;
    const restore = button('Restore', () => {
      call('POST', `/studio/snapshots/${s.id}/restore?tab=${encodeURIComponent(TAB)}`).then(
        (view) => showScene(view, { text: true, sliders: true }),
        (e) => { $('action-result').textContent = e.message; });
    });
    const ab = button('A/B', () => openCompare(s));
    ab.className = 'compare-open';
    ab.disabled = !s.ready;
    item.append(label, restore, ab);
    box.appendChild(item);
  }
}

$('snapshot-form').addEventListener('submit', (e) => {
  e.preventDefault();
  call('POST', '/studio/snapshots', { name: $('snapshot-name').value }).then(({ snapshots }) => {
    $('snapshot-name').value = '';
    showSnapshots(snapshots);
  }, (error) => { $('action-result').textContent = error.message; });
});

const compareCanvas = $('compare');
const compareContext = compareCanvas.getContext('2d');
let compare = null;      // {id, name, width, height, pixels, split}
let splitting = null;    // the pointer dragging the split

/** Shows snapshot `s` (A, left of the split) against the current image (B). */
async function openCompare(s) {
  const response = await fetch(`/studio/snapshots/${s.id}/pixels`, { headers: headers(false) });
  if (!response.ok) {
    $('action-result').textContent = (await response.json()).error;
    return;
  }
  const pixels = new Uint8ClampedArray(await response.arrayBuffer());
  compare = { id: s.id, name: s.name, width: s.width, height: s.height, pixels, split: Math.floor(s.width / 2) };
  compareCanvas.width = s.width;
  compareCanvas.height = s.height;
  compareCanvas.hidden = false;
  $('split').hidden = false;
  $('compare-bar').hidden = false;
  image.hidden = true;
  $('bounds').setAttribute('hidden', '');
  $('compare-info').textContent = `A: ${s.name} (version ${s.version}) · B: the current image`;
  drawCompare();
}

function closeCompare() {
  compare = null;
  studio.compare = null;
  compareCanvas.hidden = true;
  $('split').hidden = true;
  $('compare-bar').hidden = true;
  image.hidden = false;
  drawBounds();
}
$('compare-close').addEventListener('click', closeCompare);

/** Puts the snapshot's columns left of the split and the current image's
 * from the split on into the A/B canvas. */
function drawCompare() {
  if (!compare) return;
  const { width, height, pixels, split } = compare;
  const out = new ImageData(width, height);
  const live = studio.width === width && studio.height === height
    ? context.getImageData(0, 0, width, height).data : null;
  for (let y = 0; y < height; y++) {
    const row = y * width * 4, cut = row + split * 4, end = row + width * 4;
    if (exposureTable) expose(pixels, out.data, row, cut);
    else out.data.set(pixels.subarray(row, cut), row);
    if (live) out.data.set(live.subarray(cut, end), cut);
  }
  compareContext.putImageData(out, 0, 0);
  $('compare-info').dataset.sizes = live ? 'same' : 'differ';
  placeSplit();
  studio.compare = { id: compare.id, split, drawn: studio.framesDrawn };
}

/** Where the image is drawn in the A/B canvas's box (it keeps its aspect). */
function compareBox() {
  const r = compareCanvas.getBoundingClientRect();
  const scale = Math.min(r.width / compare.width, r.height / compare.height);
  return { r, scale, left: r.left + (r.width - compare.width * scale) / 2,
    top: r.top + (r.height - compare.height * scale) / 2 };
}

function placeSplit() {
  const { scale, left, top } = compareBox();
  const stage = $('stage').getBoundingClientRect();
  const line = $('split');
  line.style.left = `${left - stage.left + compare.split * scale}px`;
  line.style.top = `${top - stage.top}px`;
  line.style.height = `${compare.height * scale}px`;
}

function splitAt(clientX) {
  const { scale, left } = compareBox();
  compare.split = Math.max(0, Math.min(compare.width, Math.round((clientX - left) / scale)));
  drawCompare();
}

compareCanvas.tabIndex = 0;
compareCanvas.addEventListener('pointerdown', (e) => {
  if (!compare) return;
  e.preventDefault();
  compareCanvas.setPointerCapture(e.pointerId);
  splitting = e.pointerId;
  splitAt(e.clientX);
});
compareCanvas.addEventListener('pointermove', (e) => {
  if (compare && splitting === e.pointerId) splitAt(e.clientX);
});
const stopSplitting = () => { splitting = null; };
compareCanvas.addEventListener('pointerup', stopSplitting);
compareCanvas.addEventListener('pointercancel', stopSplitting);
compareCanvas.addEventListener('keydown', (e) => {
  if (!compare || (e.key !== 'ArrowLeft' && e.key !== 'ArrowRight')) return;
  const step = (e.shiftKey ? 10 : 1) * (e.key === 'ArrowLeft' ? -1 : 1);
  compare.split = Math.max(0, Math.min(compare.width, compare.split + step));
  drawCompare();
  e.preventDefault();
});
window.addEventListener('resize', () => { if (compare) placeSplit(); });

// ---- The march's bounds over the image ------------------------------------------
// The box the rays are marched through, drawn over the image (Bounds, or
// always while the server warns that an object goes on past it).

let boundsShown = false;

/** The 12 edges of the bounds projected into the image (pixel coordinates),
 * through the camera the renderer uses (perspective or orthographic; `up`
 * is (0, 1, 0) when the text leaves it out, as for the renderer); null when
 * the text does not write the bounds or the camera. */
function boundsEdges(view) {
  const value = (id) => paramValues[id] ?? view.params.find((p) => p.id === id)?.value;
  const vec = (name) => [0, 1, 2].map((i) => value(`${name}[${i}]`));
  const min = vec('march.bounds.min'), max = vec('march.bounds.max');
  const eye = vec('camera.eye'), lookAt = vec('camera.look_at');
  const written = vec('camera.up');
  const upIn = written.every((x) => x === undefined) ? [0, 1, 0] : written;
  const fov = value('camera.projection.Perspective.fov_y');
  const height = value('camera.projection.Orthographic.height');
  const perspective = fov !== undefined;
  const half = perspective ? Math.tan((fov * Math.PI) / 360) : height / 2;
  if (![...min, ...max, ...eye, ...lookAt, ...upIn, half].every((x) => x !== undefined)) return null;
  const forward = unit(sub(lookAt, eye));
  const right = unit(cross(forward, upIn));
  const up = cross(right, forward);
  const aspect = studio.width / studio.height;
  const project = (p) => {
    const d = sub(p, eye);
    return [dot(d, right), dot(d, up), dot(d, forward)];
  };
  // Perspective divides by the depth; an orthographic view does not.
  const toPixel = ([x, y, z]) => {
    const depth = perspective ? z : 1;
    return [
      ((x / (depth * half * aspect)) + 1) / 2 * studio.width,
      (1 - y / (depth * half)) / 2 * studio.height,
    ];
  };
  const corner = (i) => [0, 1, 2].map((a) => ((i >> a) & 1 ? max[a] : min[a]));
  const edges = [];
  for (let i = 0; i < 8; i++) {
    for (const a of [0, 1, 2]) {
      const j = i | (1 << a);
      if (j === i) continue;
      let p = project(corner(i)), q = project(corner(j));
      if (perspective) {
        // The part in front of the eye.
        const near = 1e-3;
        if (p[2] < near && q[2] < near) continue;
        const cut = (a0, b0) => {
          const t = (near - a0[2]) / (b0[2] - a0[2]);
          return a0.map((v, k) => v + (b0[k] - v) * t);
        };
        if (p[2] < near) p = cut(p, q);
        else if (q[2] < near) q = cut(q, p);
      }
      edges.push([toPixel(p), toPixel(q)]);
    }
  }
  return edges;
}

function drawBounds() {
  const view = studio.view;
  const svg = $('bounds');
  const warned = Boolean(view?.warning);
  $('warning').textContent = view?.warning || '';
  $('warning').hidden = !warned;
  const edges = view && (boundsShown || warned) && studio.width ? boundsEdges(view) : null;
  studio.boundsDrawn = edges ? edges.length : 0;
  // An SVG element has no `hidden` property: the attribute is set.
  const off = !edges || compare !== null;
  svg.toggleAttribute('hidden', off);
  if (off) return;
  svg.setAttribute('viewBox', `0 0 ${studio.width} ${studio.height}`);
  svg.classList.toggle('warned', warned);
  svg.innerHTML = edges.map(([[x1, y1], [x2, y2]]) =>
    `<line x1="${x1}" y1="${y1}" x2="${x2}" y2="${y2}"></line>`).join('');
  const r = image.getBoundingClientRect(), stage = $('stage').getBoundingClientRect();
  const scale = Math.min(r.width / studio.width, r.height / studio.height);
  svg.style.left = `${r.left - stage.left + (r.width - studio.width * scale) / 2}px`;
  svg.style.top = `${r.top - stage.top + (r.height - studio.height * scale) / 2}px`;
  svg.style.width = `${studio.width * scale}px`;
  svg.style.height = `${studio.height * scale}px`;
}

$('show-bounds').addEventListener('click', () => {
  boundsShown = !boundsShown;
  $('show-bounds').setAttribute('aria-pressed', String(boundsShown));
  drawBounds();
});
window.addEventListener('resize', drawBounds);

call('GET', '/studio/scene').then((view) => {
  showScene(view, { text: true, sliders: true });
  listen();
}, (e) => { $('error').textContent = e.message; });

// ---- The scene browser ------------------------------------------------------
// The browsed directory's scenes (GET /studio/scenes), each with its
// thumbnail, fetched once per key (a new key: the scene's text or files
// changed). A `scenes` event says a thumbnail is ready. Opening a scene
// switches every tab: its text, controls, history and snapshots.

studio.scenes = [];        // the last listing
studio.thumbnails = {};    // path → {key, url} of each thumbnail loaded
let browserShown = false;
let browserOffered = false;
let listing = false;       // a listing on its way
let listAgain = false;     // another asked meanwhile

function showBrowser(on) {
  browserShown = on;
  $('browser').hidden = !on;
  $('scenes-toggle').setAttribute('aria-pressed', String(on));
  if (on) refreshScenes();
}
$('scenes-toggle').addEventListener('click', () => showBrowser(!browserShown));

/** Shows the browser's button (and, the first time, the browser itself
 * when the studio was started on a directory); marks the live scene. */
function offerBrowser(view) {
  $('scenes-toggle').hidden = !view.browser;
  if (view.browser && !browserOffered) {
    browserOffered = true;
    if (view.browser.first) showBrowser(true);
  }
  markLive();
}

async function refreshScenes() {
  if (listing) {
    listAgain = true;
    return;
  }
  listing = true;
  try {
    const { root, scenes } = await call('GET', '/studio/scenes');
    studio.scenes = scenes;
    $('browser-root').textContent = root;
    listScenes(scenes);
    await Promise.all(scenes.filter((s) => s.ready && studio.thumbnails[s.path]?.key !== s.key)
      .map(loadThumbnail));
  } catch (e) {
    $('browser-message').textContent = e.message;
  } finally {
    listing = false;
    if (listAgain) {
      listAgain = false;
      refreshScenes();
    }
  }
}

async function loadThumbnail(s) {
  const response = await fetch('/studio/scenes/thumbnail?path=' + encodeURIComponent(s.path),
    { headers: headers(false) });
  if (!response.ok) return;
  const url = URL.createObjectURL(await response.blob());
  const old = studio.thumbnails[s.path];
  if (old) URL.revokeObjectURL(old.url);
  studio.thumbnails[s.path] = { key: s.key, url };
  for (const img of document.querySelectorAll('#scene-list img')) {
    if (img.dataset.path === s.path) img.src = url;
  }
}

function listScenes(scenes) {
  const box = $('scene-list');
  box.innerHTML = '';
  for (const s of scenes) {
    const item = document.createElement('li');
    const b = document.createElement('button');
    b.type = 'button';
    b.className = 'scene';
    b.dataset.path = s.path;
    b.title = s.title ? `${s.path}: ${s.title}` : s.path;
    const img = document.createElement('img');
    img.dataset.path = s.path;
    img.alt = s.title || s.name;
    const thumb = studio.thumbnails[s.path];
    if (thumb && thumb.key === s.key) img.src = thumb.url;
    img.hidden = Boolean(s.error);
    const name = document.createElement('span');
    name.className = 'scene-name';
    name.textContent = s.path;
    b.append(img, name);
    if (s.error) {
      const error = document.createElement('span');
      error.className = 'scene-error';
      error.textContent = s.error;
      b.append(error);
    }
    b.addEventListener('click', () => openScene(s.path, false));
    item.append(b);
    box.append(item);
  }
  markLive();
}

function markLive() {
  const live = studio.view?.browser?.path;
  for (const b of document.querySelectorAll('#scene-list button.scene')) {
    const on = b.dataset.path === live;
    b.classList.toggle('live', on);
    if (on) b.setAttribute('aria-current', 'true');
    else b.removeAttribute('aria-current');
  }
}

/** Opens scene `path` for every tab; unsaved edits of the scene shown are
 * refused unless `discard`: the browser offers "Discard and open". */
function openScene(path, discard) {
  $('discard-open').hidden = true;
  $('browser-message').textContent = '';
  call('POST', '/studio/open', { path, base: studio.version, discard, tab: TAB }).then((view) => {
    sceneSwitched();
    showScene(view, { text: true, sliders: true });
  }, (e) => {
    $('browser-message').textContent = e.message;
    if (e.status === 409 && e.message.startsWith('unsaved edits')) {
      $('discard-open').hidden = false;
      $('discard-open').onclick = () => openScene(path, true);
    }
  });
}

/** Another scene is shown: nothing of the one before is sent with it. */
function sceneSwitched() {
  clearTimeout(editTimer);
  editTimer = null;
  queued = null;
  for (const key of Object.keys(knobValues)) delete knobValues[key];
  for (const key of Object.keys(paramValues)) delete paramValues[key];
  $('conflict').hidden = true;
  $('changed-on-disk').hidden = true;
  if (compare) closeCompare();
}
