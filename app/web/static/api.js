// The page's only way to the service: the public API (/v1/...), with the API key the user entered
// once (kept in sessionStorage: gone when the tab closes, never sent anywhere but this origin).
// Errors come back as application/problem+json; ApiProblem carries its title and detail.

const KEY_ITEM = 'ribpull.apiKey';
const LOSS_PREFIX = 'ribpull.loss.';
export const FINISHED = new Set(['succeeded', 'failed', 'canceled']);

export function getKey() { return sessionStorage.getItem(KEY_ITEM) || ''; }

export function setKey(key) {
  if (key) sessionStorage.setItem(KEY_ITEM, key); else sessionStorage.removeItem(KEY_ITEM);
}

export class ApiProblem extends Error {
  constructor(status, problem) {
    super(`${problem.title}: ${problem.detail}`);
    this.status = status;
    this.title = problem.title || `HTTP ${status}`;
    this.detail = problem.detail || '';
    this.code = problem.code || '';
  }
}

function authHeaders() {
  const key = getKey();
  return key ? { Authorization: `Bearer ${key}` } : {};
}

/** fetch(path) with the key; resolves to the Response when ok, else throws ApiProblem. */
export async function apiFetch(path, { method = 'GET', body } = {}) {
  let r;
  try {
    r = await fetch(path, { method, body, headers: authHeaders(), cache: 'no-store' });
  } catch (err) {
    throw new ApiProblem(0, { title: 'No answer from the service', detail: String(err.message || err) });
  }
  if (r.ok) return r;
  let problem;
  try {
    problem = await r.json();
  } catch {
    problem = { title: r.statusText || `HTTP ${r.status}`, detail: `the service answered ${r.status}` };
  }
  if (r.status === 401) document.dispatchEvent(new CustomEvent('ribpull:unauthorized', { detail: problem }));
  throw new ApiProblem(r.status, problem);
}

export async function apiJson(path, options) { return (await apiFetch(path, options)).json(); }

/** Show an error (ApiProblem or anything thrown) in `box`: the problem's title, then its detail. */
export function showProblem(box, err) {
  const title = err instanceof ApiProblem ? err.title : 'Error';
  const detail = err instanceof ApiProblem ? err.detail : String(err && err.message ? err.message : err);
  const strong = document.createElement('strong');
  strong.className = 'problem-title';
  strong.textContent = title;
  const span = document.createElement('span');
  span.className = 'problem-detail';
  span.textContent = detail;
  box.replaceChildren(strong, document.createTextNode(' '), span);
  box.hidden = false;
}

export function clearProblem(box) { box.hidden = true; box.replaceChildren(); }

/** Append the job's (iteration, loss) to its loss history in sessionStorage; returns the history.
 * The API reports the latest loss only, so the curve is what this tab has seen while polling. */
export function recordLoss(job) {
  const item = LOSS_PREFIX + job.id;
  let hist = [];
  try { hist = JSON.parse(sessionStorage.getItem(item) || '[]'); } catch { hist = []; }
  const p = job.progress || {};
  if (p.stage === 'fit' && Number.isFinite(p.iteration) && Number.isFinite(p.loss)) {
    const last = hist[hist.length - 1];
    if (!last || p.iteration > last[0]) {
      hist.push([p.iteration, p.loss]);
      sessionStorage.setItem(item, JSON.stringify(hist));
    }
  }
  return hist;
}

/** "fit 120/250 · loss 0.1248" style text of a job's progress. */
export function progressText(job) {
  const p = job.progress || {};
  const parts = [];
  if (p.stage) parts.push(p.iteration != null && p.iterations ? `${p.stage} ${p.iteration}/${p.iterations}` : p.stage);
  if (Number.isFinite(p.loss)) parts.push(`loss ${p.loss.toPrecision(4)}`);
  if (job.cancel_requested && !FINISHED.has(job.status)) parts.push('cancel requested');
  return parts.join(' · ');
}

export function formatBytes(n) {
  if (!Number.isFinite(n)) return '';
  const units = ['B', 'KiB', 'MiB', 'GiB'];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) { n /= 1024; i += 1; }
  return `${n.toFixed(i ? 1 : 0)} ${units[i]}`;
}

/** Download an artifact with the key (a plain link cannot send the Authorization header). */
export async function downloadArtifact(href, name) {
  const blob = await (await apiFetch(href)).blob();
  const url = URL.createObjectURL(blob);
  const a = document.createElement('a');
  a.href = url;
  a.download = name;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

/** Create an element with a class and text. */
export function el(tag, className = '', text = '') {
  const node = document.createElement(tag);
  if (className) node.className = className;
  if (text) node.textContent = text;
  return node;
}
