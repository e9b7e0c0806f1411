// `/`: the upload form and the key's jobs with live status, progress and loss curve; cancel and delete.

import {
  FINISHED, apiFetch, apiJson, clearProblem, el, progressText, recordLoss, showProblem,
} from './api.js';
import { initKeyBar } from './keybar.js';
import { drawLossChart } from './losschart.js';

const ACTIVE_POLL_MS = 1000;
const IDLE_POLL_MS = 5000;
const tbody = document.querySelector('#jobs tbody');
const jobsError = document.getElementById('jobs-error');
const uploadError = document.getElementById('upload-error');
let pollTimer = null;
let refreshSeq = 0; // only the newest refresh schedules the next poll (a click may start one mid-poll)

/** "1-24, 30" -> [1, ..., 24, 30]; throws with a message the user can act on. */
export function parseLabels(text) {
  const out = [];
  for (const part of text.split(',').map((s) => s.trim()).filter(Boolean)) {
    const m = part.match(/^(\d+)(?:\s*-\s*(\d+))?$/);
    if (!m) throw new Error(`labels: '${part}' is not a number or a range like 1-24`);
    const a = Number(m[1]);
    const b = m[2] === undefined ? a : Number(m[2]);
    if (b < a) throw new Error(`labels: the range '${part}' runs backwards`);
    for (let v = a; v <= b; v += 1) out.push(v);
  }
  return out;
}

function formParams() {
  const params = {};
  const preset = document.getElementById('preset').value;
  if (preset) params.preset = preset;
  const iterations = document.getElementById('iterations').value.trim();
  if (iterations) {
    const n = Number(iterations);
    if (!Number.isInteger(n) || n < 1) throw new Error(`iterations: '${iterations}' is not a whole number of at least 1`);
    params.iterations = n;
  }
  const units = document.getElementById('units').value;
  if (units !== 'mm') params.units = units;
  const labels = parseLabels(document.getElementById('labels').value);
  if (labels.length) params.labels = labels;
  return params;
}

async function submit(ev) {
  ev.preventDefault();
  clearProblem(uploadError);
  const state = document.getElementById('upload-state');
  const button = document.getElementById('submit');
  const file = document.getElementById('file').files[0];
  let params;
  try {
    if (!file) throw new Error('choose a file first');
    params = formParams();
  } catch (err) {
    showProblem(uploadError, err);
    return;
  }
  const body = new FormData();
  body.append('file', file, file.name);
  body.append('params', JSON.stringify(params));
  button.disabled = true;
  state.textContent = `uploading ${file.name} ...`;
  try {
    const job = await apiJson('/v1/jobs', { method: 'POST', body });
    state.textContent = `submitted job ${job.id.slice(0, 8)}`;
    // clear the file (preset, iterations, labels and units stay for the next run), unless another was chosen meanwhile
    const input = document.getElementById('file');
    if (input.files[0] === file) input.value = '';
    await refresh();
  } catch (err) {
    state.textContent = '';
    showProblem(uploadError, err);
  } finally {
    button.disabled = false;
  }
}

/** What the row's action is: Cancel (queued/running), Delete files (finished), or nothing left to do. */
function actionKind(job) {
  if (!FINISHED.has(job.status)) return job.cancel_requested ? 'canceling' : 'cancel';
  return job.artifacts_deleted ? 'deleted' : 'delete';
}

function actionButton(job, kind) {
  if (kind === 'deleted') return el('span', 'muted', 'files deleted');
  const b = el('button', kind === 'delete' ? 'delete' : 'cancel',
    { cancel: 'Cancel', canceling: 'Canceling…', delete: 'Delete files' }[kind]);
  b.disabled = kind === 'canceling';
  if (kind === 'delete') b.title = 'Delete the input and the artifacts (the record is kept)';
  b.addEventListener('click', () => act(job.id, b));
  return b;
}

async function act(jobId, button) {
  button.disabled = true;
  clearProblem(jobsError);
  try {
    await apiFetch(`/v1/jobs/${jobId}`, { method: 'DELETE' });
  } catch (err) {
    showProblem(jobsError, err);
  }
  await refresh();
}

/** The table row of a job, made once and updated in place on every poll (so a click is never lost
 * to a re-render). */
const rows = new Map();

function makeRow(job) {
  const tr = el('tr');
  tr.dataset.jobId = job.id;
  const link = el('a', '', job.id.slice(0, 8));
  link.href = `/jobs/${job.id}`;
  const idCell = el('td');
  idCell.append(link, el('div', 'muted', job.input.filename));
  const status = el('td');
  const prog = el('td', 'progress');
  const bar = el('progress');
  bar.max = 1;
  const text = el('div', 'progress-text');
  const error = el('div', 'job-error');
  prog.append(bar, text, error);
  const lossCell = el('td');
  const chart = el('canvas', 'sparkline');
  lossCell.append(chart);
  const actions = el('td');
  tr.append(idCell, status, prog, lossCell, el('td', 'muted', new Date(job.created_at).toLocaleString()), actions);
  return { tr, status, bar, text, error, chart, actions, kind: null };
}

function updateRow(row, job) {
  row.tr.dataset.status = job.status;
  row.status.className = `status status-${job.status}`;
  row.status.textContent = job.status;
  row.bar.value = job.progress.fraction || 0;
  row.text.textContent = progressText(job);
  row.error.textContent = job.error ? `${job.error.code}: ${job.error.message}` : '';
  const kind = actionKind(job);
  if (kind !== row.kind) {
    row.actions.replaceChildren(actionButton(job, kind));
    row.kind = kind;
  }
  drawLossChart(row.chart, recordLoss(job), job.progress.iterations, { compact: true });
}

async function refresh() {
  clearTimeout(pollTimer);
  const seq = ++refreshSeq;
  let active = false;
  try {
    const page = await apiJson('/v1/jobs?limit=50');
    if (seq !== refreshSeq) return;
    clearProblem(jobsError);
    const ids = page.items.map((job) => job.id);
    for (const job of page.items) {
      if (!rows.has(job.id)) rows.set(job.id, makeRow(job));
      updateRow(rows.get(job.id), job);
    }
    for (const id of [...rows.keys()]) if (!ids.includes(id)) rows.delete(id);
    const shown = [...tbody.children].map((tr) => tr.dataset.jobId);
    if (shown.join() !== ids.join()) tbody.replaceChildren(...ids.map((id) => rows.get(id).tr));
    document.getElementById('jobs-empty').hidden = page.items.length > 0;
    active = page.items.some((job) => !FINISHED.has(job.status));
  } catch (err) {
    showProblem(jobsError, err);
    if (err.status === 401) return; // polls again once a key is entered (the key bar calls refresh)
  }
  if (seq === refreshSeq) pollTimer = setTimeout(refresh, active ? ACTIVE_POLL_MS : IDLE_POLL_MS);
}

/** Dropping a file on the upload section puts it in the form (anywhere else it is ignored, so the
 * browser does not navigate away to the dropped file). */
function initDrop() {
  const zone = document.getElementById('upload-section');
  const input = document.getElementById('file');
  for (const type of ['dragover', 'drop']) window.addEventListener(type, (ev) => ev.preventDefault());
  zone.addEventListener('dragover', () => zone.classList.add('dragging'));
  zone.addEventListener('dragleave', () => zone.classList.remove('dragging'));
  zone.addEventListener('drop', (ev) => {
    zone.classList.remove('dragging');
    const { files } = ev.dataTransfer || {};
    if (!files || !files.length) return;
    input.files = files;
    document.getElementById('upload-state').textContent = `ready: ${files[0].name}`;
  });
}

document.getElementById('upload-form').addEventListener('submit', submit);
initDrop();
initKeyBar(refresh);
refresh();
