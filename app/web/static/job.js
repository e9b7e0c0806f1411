// `/jobs/{id}`: the job's progress while it runs (stage, iteration, loss curve, cancel); once it has
// succeeded, the 3D view of mesh.glb + skeleton.glb, the surface metrics and every artifact's link.

import {
  ApiProblem, FINISHED, apiFetch, apiJson, clearProblem, downloadArtifact, el, formatBytes, progressText,
  recordLoss, showProblem,
} from './api.js';
import { initKeyBar } from './keybar.js';
import { drawLossChart } from './losschart.js';

const POLL_MS = 1000;
const jobId = decodeURIComponent(window.location.pathname.split('/').filter(Boolean).pop() || '');
const problemBox = document.getElementById('job-problem');
let pollTimer = null;
let resultShown = false;

/** Surface metrics shown (metrics.json key -> label); lengths in mm. */
const SURFACE_ROWS = [
  ['cd_l1_mm', 'Chamfer L1 (mm)'], ['cd_l2_mm2', 'Chamfer L2 (mm²)'], ['hausdorff_mm', 'Hausdorff (mm)'],
  ['normal_consistency', 'normal consistency'], ['fscore', 'F-score'], ['precision', 'precision'],
  ['recall', 'recall'], ['tau_mm', 'F-score threshold τ (mm)'], ['n_samples', 'samples per side'],
];
const MESH_ROWS = [
  ['components', 'mesh components'], ['watertight', 'watertight'], ['n_vertices', 'vertices'],
  ['n_faces', 'faces'], ['area_mm2', 'area (mm²)'], ['volume_mm3', 'volume (mm³)'],
];

function fmt(v) {
  if (typeof v === 'number') return Number.isInteger(v) ? String(v) : v.toPrecision(4);
  return v == null ? '—' : String(v);
}

function showSummary(job) {
  document.getElementById('job-id').textContent = job.id;
  const status = document.getElementById('job-status');
  status.textContent = job.status;
  status.className = `status status-${job.status}`;
  document.body.dataset.status = job.status;
  const params = Object.entries(job.params || {}).filter(([, v]) => v !== null && v !== undefined)
    .map(([k, v]) => `${k}=${JSON.stringify(v)}`).join(', ');
  document.getElementById('job-summary').textContent =
    `${job.input.filename} (${job.input.format}, ${job.input.points} points, ${formatBytes(job.input.bytes)}) · `
    + `created ${new Date(job.created_at).toLocaleString()} · ${params}`;
}

function showProgress(job) {
  const section = document.getElementById('progress-section');
  const running = !FINISHED.has(job.status);
  const history = recordLoss(job);
  section.hidden = !running && !history.length;
  document.getElementById('job-progress').value = job.progress.fraction || 0;
  document.getElementById('progress-text').textContent = progressText(job) || job.status;
  const cancel = document.getElementById('cancel');
  cancel.hidden = !running;
  cancel.disabled = job.cancel_requested;
  drawLossChart(document.getElementById('loss-chart'), history, job.progress.iterations);
}

function showOutcome(job) {
  if (job.status === 'failed' && job.error) {
    showProblem(problemBox, new ApiProblem(0, { title: `Job failed (${job.error.code})`, detail: job.error.message }));
  } else if (job.status === 'canceled') {
    showProblem(problemBox, new ApiProblem(0, { title: 'Job canceled', detail: 'it was canceled before it finished' }));
  } else if (job.status === 'succeeded' && job.artifacts_deleted) {
    showProblem(problemBox, new ApiProblem(0, { title: 'Files deleted', detail: "this job's artifacts were deleted" }));
  }
}

function showDownloads(job) {
  const list = document.getElementById('downloads');
  list.replaceChildren(...job.artifacts.map((a) => {
    const li = el('li');
    const link = el('a', '', a.name);
    link.href = a.href;
    link.download = a.name;
    link.addEventListener('click', (ev) => {
      ev.preventDefault(); // the key travels in a header, which a plain link cannot send
      downloadArtifact(a.href, a.name).catch((err) => showProblem(problemBox, err));
    });
    li.append(link, el('span', 'muted', ` ${formatBytes(a.bytes)} · ${a.media_type}`));
    return li;
  }));
}

function showMetrics(metrics) {
  const rows = [];
  const add = (label, value) => {
    const tr = el('tr');
    tr.append(el('th', '', label), el('td', '', fmt(value)));
    rows.push(tr);
  };
  add('reference', metrics.reference);
  for (const [k, label] of SURFACE_ROWS) if (metrics.surface && k in metrics.surface) add(label, metrics.surface[k]);
  for (const [k, label] of MESH_ROWS) if (metrics.mesh && k in metrics.mesh) add(label, metrics.mesh[k]);
  add('iterations run', metrics.iterations_run);
  if (metrics.timings_s) add('pipeline time (s)', metrics.timings_s.total);
  document.querySelector('#surface-metrics tbody').replaceChildren(...rows);
}

async function artifactBytes(job, name) {
  return (await apiFetch(`/v1/jobs/${job.id}/artifacts/${name}`)).arrayBuffer();
}

async function showResult(job) {
  resultShown = true;
  document.getElementById('result-section').hidden = false;
  showDownloads(job);
  const viewerState = document.getElementById('viewer-state');
  const names = new Set(job.artifacts.map((a) => a.name));
  try {
    const metrics = await apiJson(`/v1/jobs/${job.id}/artifacts/metrics.json`);
    showMetrics(metrics);
    if (!names.has('mesh.glb')) throw new Error('this job produced no mesh.glb');
    let createViewer;
    try {
      ({ createViewer } = await import('./viewer.js'));
    } catch (err) {
      throw new Error(`3D view unavailable: this server has no three.js files (run \`make web\` on it): ${err.message}`);
    }
    const hasSkeleton = names.has('skeleton.glb') && names.has('skeleton.json');
    const [meshGlb, skeletonGlb, skeleton] = await Promise.all([
      artifactBytes(job, 'mesh.glb'),
      hasSkeleton ? artifactBytes(job, 'skeleton.glb') : null,
      hasSkeleton ? apiJson(`/v1/jobs/${job.id}/artifacts/skeleton.json`) : null,
    ]);
    const viewer = await createViewer(document.getElementById('viewer'), {
      meshGlb, skeletonGlb, skeleton, metrics, infoBox: document.getElementById('rib-info'),
      ribList: document.getElementById('rib-list'),
    });
    document.getElementById('show-surface').addEventListener('change', (ev) => viewer.setSurfaceVisible(ev.target.checked));
    document.getElementById('reset-view').addEventListener('click', () => viewer.resetView());
    document.getElementById('show-all').addEventListener('change', (ev) => viewer.setAllRibsVisible(ev.target.checked));
    viewerState.remove();
  } catch (err) {
    viewerState.textContent = err instanceof ApiProblem ? `${err.title}: ${err.detail}` : String(err.message || err);
    viewerState.className = 'problem';
  }
}

async function poll() {
  clearTimeout(pollTimer);
  let job;
  try {
    job = await apiJson(`/v1/jobs/${encodeURIComponent(jobId)}`);
  } catch (err) {
    showProblem(problemBox, err);
    if (err.status === 0 || err.status >= 500) pollTimer = setTimeout(poll, POLL_MS * 5);
    return;
  }
  clearProblem(problemBox);
  showSummary(job);
  showProgress(job);
  showOutcome(job);
  if (job.status === 'succeeded' && !job.artifacts_deleted && !resultShown) await showResult(job);
  if (!FINISHED.has(job.status)) pollTimer = setTimeout(poll, POLL_MS);
}

document.getElementById('cancel').addEventListener('click', async (ev) => {
  ev.target.disabled = true;
  try {
    await apiFetch(`/v1/jobs/${encodeURIComponent(jobId)}`, { method: 'DELETE' });
  } catch (err) {
    showProblem(problemBox, err);
  }
  poll();
});
document.getElementById('job-id').textContent = jobId;
initKeyBar(poll);
poll();
