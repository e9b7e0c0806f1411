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
    document.getElementById('upload-form').reset();
    await refresh();
  } catch (err) {
    state.textContent = '';
    showProblem(uploadError, err);
  } finally {
    button.disabled = false;
  }
}

function actionButton(job) {
  if (!FINISHED.has(job.status)) {
    const b = el('button', 'cancel', job.cancel_requested ? 'Canceling…' : 'Cancel');
    b.disabled = job.cancel_requested;
    b.addEventListener('click', () => act(job, b));
    return b;
  }
  if (job.artifacts_deleted) return el('span', 'muted', 'files deleted');
  const b = el('button', 'delete', 'Delete files');
  b.title = 'Delete the input and the artifacts (the record is kept)';
  b.addEventListener('click', () => act(job, b));
  return b;
}

async function act(job, button) {
  button.disabled = true;
  clearProblem(jobsError);
  try {
    await apiFetch(`/v1/jobs/${job.id}`, { method: 'DELETE' });
  } catch (err) {
    showProblem(jobsError, err);
  }
  await refresh();
}

function jobRow(job) {
  const tr = el('tr');
  tr.dataset.jobId = job.id;
  tr.dataset.status = job.status;
  const link = el('a', '', job.id.slice(0, 8));
  link.href = `/jobs/${job.id}`;
  const name = el('div', 'muted', job.input.filename);
  const idCell = el('td');
  idCell.append(link, name);
  const status = el('td', `status status-${job.status}`, job.status);
  const prog = el('td', 'progress');
  const bar = el('progress');
  bar.max = 1;
  bar.value = job.progress.fraction || 0;
  prog.append(bar, el('div', 'progress-text', progressText(job)));
  if (job.error) prog.append(el('div', 'job-error', `${job.error.code}: ${job.error.message}`));
  const lossCell = el('td');
  const chart = el('canvas', 'sparkline');
  lossCell.append(chart);
  const created = el('td', 'muted', new Date(job.created_at).toLocaleString());
  const actions = el('td');
  actions.append(actionButton(job));
  tr.append(idCell, status, prog, lossCell, created, actions);
  return { tr, chart };
}

async function refresh() {
  clearTimeout(pollTimer);
  const seq = ++refreshSeq;
  let active = false;
  try {
    const page = await apiJson('/v1/jobs?limit=50');
    if (seq !== refreshSeq) return;
    clearProblem(jobsError);
    const rows = page.items.map((job) => ({ job, ...jobRow(job) }));
    tbody.replaceChildren(...rows.map((r) => r.tr));
    for (const { job, chart } of rows) drawLossChart(chart, recordLoss(job), job.progress.iterations);
    document.getElementById('jobs-empty').hidden = page.items.length > 0;
    active = page.items.some((job) => !FINISHED.has(job.status));
  } catch (err) {
    showProblem(jobsError, err);
    if (err.status === 401) return; // polls again once a key is entered (the key bar calls refresh)
  }
  if (seq === refreshSeq) pollTimer = setTimeout(refresh, active ? ACTIVE_POLL_MS : IDLE_POLL_MS);
}

document.getElementById('upload-form').addEventListener('submit', submit);
initKeyBar(refresh);
refresh();
