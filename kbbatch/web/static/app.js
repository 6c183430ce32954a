// kbbatch review: the page. Plain ES module, no build step, no network beyond this server.
// Crops are kept in source pixels, as the manifest stores them; the stage shows them in percent.

const token = document.querySelector('meta[name="kbbatch-token"]').content;
const $ = (id) => document.getElementById(id);
const SVG = 'http://www.w3.org/2000/svg';
const POLL_MS = 1000;

const state = {
  overview: null,   // GET /api/photos
  photos: [],       // its photos, in name order
  selected: null,   // name of the photo in the editor
  drafts: {},       // name -> edited manifest entry (not yet saved)
  bases: {},        // name -> the manifest entry a draft started from (the save checks it)
  plans: {},        // name -> {start, end} crops shown (source px)
  previews: {},     // name -> {key, url} of the last rendered preview
};

async function api(path, body) {
  const options = body === undefined ? {} : {
    method: 'POST', body: JSON.stringify(body),
    headers: {'Content-Type': 'application/json', 'X-KBBatch-Token': token},
  };
  const response = await fetch(path, options);
  const data = await response.json();
  if (!response.ok) throw new Error(data.error || response.statusText);
  return data;
}

// A photo's name as its bytes in a URL: a file name that is not UTF-8 reaches the page with
// lone surrogates for its stray bytes (Python's surrogateescape), which encodeURIComponent
// refuses (URIError), and the whole photo list failed to show.
const urlName = (name) => Array.from(name, (ch) => {
  const code = ch.codePointAt(0);
  return code >= 0xDC80 && code <= 0xDCFF
    ? `%${(code - 0xDC00).toString(16).toUpperCase().padStart(2, '0')}` : encodeURIComponent(ch);
}).join('');
const imageUrl = (name, kind = 'image') => `/api/photos/${urlName(name)}/${kind}`;
const photo = (name) => state.photos.find((p) => p.name === name);
const clone = (value) => JSON.parse(JSON.stringify(value));

function entryOf(name) {
  // The entry that would be saved for this photo: the draft, else the manifest's.
  return state.drafts[name] ?? clone(photo(name).entry ?? {});
}

function settingsOf(name) {
  const entry = entryOf(name);
  const presetName = entry.preset ?? state.overview.default_preset;
  const preset = state.overview.presets[presetName] ?? state.overview.presets[state.overview.default_preset];
  return {presetName, preset, entry};
}

function edit(name, change) {
  const entry = entryOf(name);
  change(entry);
  // What the draft started from: the server refuses the save if the manifest's entry has
  // changed since (by hand, or in another review), rather than write over that change.
  if (!(name in state.drafts)) state.bases[name] = clone(photo(name).entry ?? null);
  state.drafts[name] = entry;
  updateSaveButton();
  drawThumb(name);
}

// -- the grid --------------------------------------------------------------------------------

function buildGrid() {
  const grid = $('grid');
  grid.replaceChildren();
  for (const p of state.photos) {
    const figure = document.createElement('figure');
    figure.dataset.name = p.name;
    figure.innerHTML = '<div class="frame"><img loading="lazy" alt=""></div><figcaption></figcaption>';
    figure.querySelector('img').src = imageUrl(p.name);
    figure.querySelector('.frame').append(document.createElementNS(SVG, 'svg'));
    figure.addEventListener('click', () => select(p.name));
    grid.append(figure);
    drawThumb(p.name);
  }
}

function rect(crop, colour, strokePx) {
  const r = document.createElementNS(SVG, 'rect');
  r.setAttribute('x', crop.center_x - crop.width / 2);
  r.setAttribute('y', crop.center_y - crop.height / 2);
  r.setAttribute('width', crop.width);
  r.setAttribute('height', crop.height);
  r.setAttribute('fill', 'none');
  r.setAttribute('stroke', colour);
  r.setAttribute('stroke-width', strokePx);
  return r;
}

function drawThumb(name) {
  const p = photo(name);
  const figure = document.querySelector(`figure[data-name="${CSS.escape(name)}"]`);
  if (!figure) return;
  const entry = entryOf(name);
  const plan = state.plans[name];
  figure.classList.toggle('excluded', Boolean(entry.exclude));
  figure.classList.toggle('failed', p.status === 'failed');
  const svg = figure.querySelector('svg');
  svg.replaceChildren();
  if (plan && p.width_px) {
    svg.setAttribute('viewBox', `0 0 ${p.width_px} ${p.height_px}`);
    svg.setAttribute('preserveAspectRatio', 'none');
    const stroke = Math.max(p.width_px, p.height_px) / 100;
    svg.append(rect(plan.start, 'var(--start)', stroke), rect(plan.end, 'var(--end)', stroke));
  }
  const origin = entry.exclude ? 'excluded' : entry.start ? 'edited' : p.status === 'pending' ? 'planning…' : 'auto';
  const text = p.status === 'failed' ? `${name}: ${p.error}` : `${name} · ${origin}`;
  figure.querySelector('figcaption').textContent = (name in state.drafts ? '* ' : '') + text;
  figure.title = text;
}

// -- loading and progress --------------------------------------------------------------------

async function refresh() {
  const overview = await api('/api/photos');
  const first = state.overview === null;
  state.overview = overview;
  state.photos = overview.photos;
  for (const p of state.photos) {
    // Plans the page changed (edited, or re-planned for another preset) stay until saved.
    if (!(p.name in state.drafts) && p.plan) state.plans[p.name] = {start: p.plan.start, end: p.plan.end};
  }
  const {done, total} = overview.progress;
  $('progress').max = Math.max(total, 1);
  $('progress').value = done;
  $('progress-text').textContent = done < total ? `planning ${done} / ${total} photos`
    : `${total} photo(s) planned`;
  $('folder').textContent = overview.folder;
  if (first) {
    fillPresets();
    buildGrid();
    if (state.photos.length) select(state.photos[0].name);
    else $('progress-text').textContent = 'no photos in this folder';
  } else {
    state.photos.forEach((p) => drawThumb(p.name));
    if (state.selected) showEditor();
  }
  if (done < total) setTimeout(refresh, POLL_MS);
}

function fillPresets() {
  const select = $('preset');
  for (const name of Object.keys(state.overview.presets)) {
    const option = document.createElement('option');
    option.value = name;
    option.textContent = name === state.overview.default_preset ? `${name} (default)` : name;
    select.append(option);
  }
}

// -- the editor ------------------------------------------------------------------------------

function select(name) {
  state.selected = name;
  document.querySelectorAll('figure').forEach((f) => f.classList.toggle('selected', f.dataset.name === name));
  document.querySelector(`figure[data-name="${CSS.escape(name)}"]`)?.scrollIntoView({block: 'nearest'});
  $('photo').src = imageUrl(name);
  $('depth').hidden = true;
  $('show-depth').checked = false;
  $('preview').removeAttribute('src');
  $('preview').load();
  $('preview-status').textContent = '';
  showEditor();
}

function showEditor() {
  const name = state.selected;
  const p = photo(name);
  const {presetName, preset, entry} = settingsOf(name);
  $('photo-title').textContent = p.status === 'failed' ? `${name}: ${p.error}` : name;
  $('preset').value = presetName;
  // Never under the cursor of someone typing (the page refreshes while it plans).
  if (document.activeElement !== $('duration') || name !== $('duration').dataset.photo) {
    $('duration').value = entry.duration_s ?? preset.duration_s;
    $('duration').dataset.photo = name;
  }
  $('easing').value = entry.easing ?? preset.easing;
  $('exclude').checked = Boolean(entry.exclude);
  placeCrops();
}

function placeCrops() {
  const p = photo(state.selected);
  const plan = state.plans[state.selected];
  for (const which of ['start', 'end']) {
    const box = $(`crop-${which}`);
    box.hidden = !(plan && p.width_px);
    if (box.hidden) continue;
    const crop = plan[which];
    box.style.left = `${(crop.center_x - crop.width / 2) / p.width_px * 100}%`;
    box.style.top = `${(crop.center_y - crop.height / 2) / p.height_px * 100}%`;
    box.style.width = `${crop.width / p.width_px * 100}%`;
    box.style.height = `${crop.height / p.height_px * 100}%`;
  }
}

const round2 = (value) => Math.round(value * 100) / 100;

function fitted(crop, aspect, widthPx, heightPx) {
  // The crop with the preset's aspect, no larger than the photo, moved inside it.
  const width = Math.max(16, Math.min(crop.width, widthPx, heightPx * aspect));
  const height = width / aspect;
  const cx = Math.min(Math.max(crop.center_x, width / 2), widthPx - width / 2);
  const cy = Math.min(Math.max(crop.center_y, height / 2), heightPx - height / 2);
  return {center_x: round2(cx), center_y: round2(cy), width: round2(width), height: round2(height)};
}

function commitCrops(name) {
  // The crops shown are in the photo's pixels as it is now: the size saved with them says so
  // (kept from an older entry, a photo resized since had its new crops scaled a second time).
  const plan = state.plans[name];
  const p = photo(name);
  edit(name, (entry) => {
    entry.units = 'px';
    if (p.width_px) entry.photo_size = {width: p.width_px, height: p.height_px};
    else delete entry.photo_size;
    delete entry.photo_sha256;  // the digest of the photo another plan was made on
    entry.start = {...plan.start};
    entry.end = {...plan.end};
  });
}

function startDrag(event) {
  const box = event.currentTarget;
  const name = state.selected;
  const p = photo(name);
  const plan = state.plans[name];
  if (!plan || !p.width_px) return;
  event.preventDefault();
  const which = box.dataset.which;
  const resizing = event.target.classList.contains('handle');
  const pxPerScreen = p.width_px / $('stage').getBoundingClientRect().width;
  const origin = {x: event.clientX, y: event.clientY, crop: {...plan[which]}};
  const {preset} = settingsOf(name);
  box.setPointerCapture(event.pointerId);
  const move = (e) => {
    const dx = (e.clientX - origin.x) * pxPerScreen;
    const dy = (e.clientY - origin.y) * pxPerScreen;
    const c = origin.crop;
    let crop;
    if (resizing) {  // the top-left corner stays, the aspect is the preset's
      const width = Math.max(16, c.width + Math.max(dx, dy * preset.aspect));
      const left = c.center_x - c.width / 2;
      const top = c.center_y - c.height / 2;
      const limit = Math.min(p.width_px - left, (p.height_px - top) * preset.aspect);
      const w = Math.min(width, limit);
      crop = {center_x: left + w / 2, center_y: top + w / preset.aspect / 2, width: w, height: w / preset.aspect};
    } else {
      crop = {...c, center_x: c.center_x + dx, center_y: c.center_y + dy};
    }
    plan[which] = fitted(crop, preset.aspect, p.width_px, p.height_px);
    placeCrops();
  };
  const stop = () => {
    box.removeEventListener('pointermove', move);
    box.removeEventListener('pointerup', stop);
    box.removeEventListener('pointercancel', stop);
    commitCrops(name);
  };
  box.addEventListener('pointermove', move);
  box.addEventListener('pointerup', stop);
  box.addEventListener('pointercancel', stop);
}

async function showAutoPlan(name) {
  // The automatic plan under the entry's current settings (preset, planner, depth).
  const entry = entryOf(name);
  const {start, end, units, ...settings} = entry;
  try {
    const {plan} = await api('/api/auto-plan', {name, entry: settings});
    state.plans[name] = {start: plan.start, end: plan.end};
  } catch (error) {
    $('preview-status').textContent = error.message;
  }
  drawThumb(name);
  if (name === state.selected) placeCrops();
}

function changePreset() {
  const name = state.selected;
  const value = $('preset').value;
  edit(name, (entry) => {
    if (value === state.overview.default_preset) delete entry.preset;
    else entry.preset = value;
    delete entry.duration_s;
    delete entry.easing;
  });
  const p = photo(name);
  const {preset, entry} = settingsOf(name);
  if (entry.start && p.width_px) {
    const plan = state.plans[name];
    plan.start = fitted(plan.start, preset.aspect, p.width_px, p.height_px);
    plan.end = fitted(plan.end, preset.aspect, p.width_px, p.height_px);
    commitCrops(name);
  } else {
    showAutoPlan(name);
  }
  showEditor();
}

function changeDuration() {
  const seconds = parseFloat($('duration').value);
  edit(state.selected, (entry) => {
    if (Number.isFinite(seconds) && seconds > 0) entry.duration_s = seconds;
    else delete entry.duration_s;
  });
}

function swapCrops() {
  const name = state.selected;
  const plan = state.plans[name];
  if (!plan) return;
  state.plans[name] = {start: plan.end, end: plan.start};
  commitCrops(name);
  placeCrops();
}

function resetToAuto() {
  const name = state.selected;
  edit(name, (entry) => {
    delete entry.start;
    delete entry.end;
    delete entry.units;
    delete entry.photo_size;
    delete entry.photo_sha256;
  });
  showAutoPlan(name);
}

// -- preview ---------------------------------------------------------------------------------

async function preview() {
  const name = state.selected;
  const entry = entryOf(name);
  const key = JSON.stringify(entry);
  const video = $('preview');
  if (state.previews[name]?.key === key && video.getAttribute('src') === state.previews[name].url) {
    if (video.paused) video.play(); else video.pause();
    return;
  }
  $('preview-status').textContent = 'rendering the preview…';
  try {
    const {url} = await api('/api/preview', {name, entry});
    state.previews[name] = {key, url};
    if (name !== state.selected) return;
    video.src = url;
    await video.play();
    $('preview-status').textContent = 'preview (low resolution, plays in a loop)';
  } catch (error) {
    $('preview-status').textContent = `preview failed: ${error.message}`;
  }
}

// -- save ------------------------------------------------------------------------------------

function updateSaveButton() {
  const count = Object.keys(state.drafts).length;
  $('save-button').classList.toggle('dirty', count > 0);
  $('save-button').textContent = count ? `Save (${count} changed)` : 'Save';
}

async function save() {
  const entries = {};
  for (const [name, entry] of Object.entries(state.drafts)) {
    entries[name] = Object.keys(entry).length ? entry : null;
  }
  try {
    const bases = {};
    for (const name of Object.keys(entries)) bases[name] = state.bases[name] ?? null;
    const result = await api('/api/save', {entries, bases});
    state.drafts = {};
    state.bases = {};
    updateSaveButton();
    $('saved').innerHTML = '';
    const code = document.createElement('code');
    code.textContent = result.command;
    $('saved').append(`Saved ${result.entries} entr${result.entries === 1 ? 'y' : 'ies'} to ${result.manifest}. Render with `, code);
    $('saved').dataset.manifest = result.manifest;
    await refresh();
  } catch (error) {
    $('saved').textContent = `not saved: ${error.message}`;
  }
}

// -- wiring ----------------------------------------------------------------------------------

function step(offset) {
  const index = state.photos.findIndex((p) => p.name === state.selected);
  const next = state.photos[index + offset];
  if (next) select(next.name);
}

document.addEventListener('keydown', (event) => {
  if (event.target.closest('input, select, textarea, button')) return;
  if (event.key === 'ArrowRight' || event.key === 'ArrowDown') step(1);
  else if (event.key === 'ArrowLeft' || event.key === 'ArrowUp') step(-1);
  else if (event.key === ' ') preview();
  else return;
  event.preventDefault();
});
window.addEventListener('beforeunload', (event) => {
  if (Object.keys(state.drafts).length) event.preventDefault();
});
$('crop-start').addEventListener('pointerdown', startDrag);
$('crop-end').addEventListener('pointerdown', startDrag);
$('preset').addEventListener('change', changePreset);
$('duration').addEventListener('change', changeDuration);
$('easing').addEventListener('change', () => edit(state.selected, (e) => { e.easing = $('easing').value; }));
$('exclude').addEventListener('change', () => edit(state.selected, (e) => {
  if ($('exclude').checked) e.exclude = true; else delete e.exclude;
}));
$('show-depth').addEventListener('change', () => {
  $('depth').hidden = !$('show-depth').checked;
  if (!$('depth').hidden) $('depth').src = imageUrl(state.selected, 'depth');
});
$('swap').addEventListener('click', swapCrops);
$('reset').addEventListener('click', resetToAuto);
$('preview-button').addEventListener('click', preview);
$('save-button').addEventListener('click', save);
refresh().catch((error) => { $('progress-text').textContent = `cannot load: ${error.message}`; });
