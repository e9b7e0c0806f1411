// The fit's loss curve on a 2D canvas: iteration on x, loss on a log scale on y.

/** Draw `history` ([[iteration, loss], ...]) on `canvas`; `iterations` is the planned count (x range).
 * compact: a sparkline (no axis labels), for the job list. */
export function drawLossChart(canvas, history, iterations, { compact = false } = {}) {
  const ratio = window.devicePixelRatio || 1;
  const w = canvas.clientWidth || 320;
  const h = canvas.clientHeight || 120;
  canvas.width = Math.round(w * ratio);
  canvas.height = Math.round(h * ratio);
  const ctx = canvas.getContext('2d');
  ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
  ctx.clearRect(0, 0, w, h);
  const pts = history.filter(([, loss]) => loss > 0);
  canvas.dataset.points = String(pts.length);
  if (compact && !pts.length) return; // no fit seen: an empty cell, not an empty box
  const pad = compact ? { l: 1, r: 1, t: 2, b: 2 } : { l: 44, r: 8, t: 8, b: 18 };
  ctx.strokeStyle = '#bbb';
  ctx.strokeRect(pad.l, pad.t, w - pad.l - pad.r, h - pad.t - pad.b);
  ctx.fillStyle = '#555';
  ctx.font = '11px sans-serif';
  if (!pts.length) {
    if (!compact) ctx.fillText('loss curve: waiting for the fit', pad.l + 6, h / 2);
    return;
  }
  const xmax = Math.max(iterations || 0, pts[pts.length - 1][0], 1);
  const logs = pts.map(([, loss]) => Math.log10(loss));
  let lo = Math.min(...logs);
  let hi = Math.max(...logs);
  if (hi - lo < 1e-6) { lo -= 0.5; hi += 0.5; }
  const x = (it) => pad.l + (it / xmax) * (w - pad.l - pad.r);
  const y = (lg) => pad.t + (1 - (lg - lo) / (hi - lo)) * (h - pad.t - pad.b);
  ctx.strokeStyle = '#c0392b';
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  pts.forEach(([it], i) => (i ? ctx.lineTo(x(it), y(logs[i])) : ctx.moveTo(x(it), y(logs[i]))));
  ctx.stroke();
  if (compact) return;
  ctx.fillText(Number(10 ** hi).toPrecision(2), 2, pad.t + 9);
  ctx.fillText(Number(10 ** lo).toPrecision(2), 2, h - pad.b);
  ctx.fillText(`iteration ${pts[pts.length - 1][0]} / ${xmax}`, pad.l + 4, h - 4);
}
