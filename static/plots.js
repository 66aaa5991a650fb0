// Line plots on a canvas for the page's accuracy and speed panel. Plain JS, no dependency:
// the page works offline and loads nothing at run time.
"use strict";

const Plots = (() => {
  const PAD = { left: 46, right: 10, top: 8, bottom: 34 };
  const INK = "#1d2733", GRID = "#e3e8ee", MUTED = "#6b7785";

  // The canvas at its CSS size times the device pixel ratio (sharp lines), cleared.
  function prepare(canvas) {
    const ratio = window.devicePixelRatio || 1;
    const width = canvas.clientWidth || 320, height = canvas.clientHeight || 240;
    canvas.width = Math.round(width * ratio);
    canvas.height = Math.round(height * ratio);
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, width, height);
    ctx.font = "11px system-ui, sans-serif";
    return { ctx, width, height };
  }

  function message(canvas, text) {
    const { ctx, width, height } = prepare(canvas);
    ctx.fillStyle = MUTED;
    ctx.textAlign = "center";
    ctx.fillText(text, width / 2, height / 2);
  }

  // Round tick positions (steps of 1, 2 or 5 times a power of ten) covering [lo, hi].
  function ticks(lo, hi, count = 4) {
    const raw = (hi - lo) / count;
    const power = 10 ** Math.floor(Math.log10(raw));
    const step = [1, 2, 5, 10].map((m) => m * power).find((s) => s >= raw) || raw;
    const out = [];
    for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) out.push(Math.abs(v) < step * 1e-9 ? 0 : v);
    return { values: out, digits: Math.max(0, -Math.floor(Math.log10(step))) };
  }

  // [lo, hi] widened so that a single value or a flat line still spans something.
  function span(values, fromZero) {
    let lo = Math.min(...values), hi = Math.max(...values);
    if (fromZero) lo = Math.min(lo, 0);
    if (hi - lo < 1e-9) { lo -= 0.5; hi += 0.5; }
    return [lo, hi];
  }

  // series: [{points: [[x, y] or null (a gap)], color, dash, width}]; options: xLabel, yLabel,
  // equal (same scale on both axes: a top view), yFromZero.
  function lines(canvas, series, { xLabel = "", yLabel = "", equal = false, yFromZero = false } = {}) {
    const points = series.flatMap((s) => s.points).filter((p) => p && Number.isFinite(p[0]) && Number.isFinite(p[1]));
    if (!points.length) return message(canvas, "nothing to plot yet");
    const { ctx, width, height } = prepare(canvas);
    const plotW = width - PAD.left - PAD.right, plotH = height - PAD.top - PAD.bottom;
    let [x0, x1] = span(points.map((p) => p[0]), false);
    let [y0, y1] = span(points.map((p) => p[1]), yFromZero);
    if (equal) {
      const scale = Math.max((x1 - x0) / plotW, (y1 - y0) / plotH);
      const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
      [x0, x1] = [cx - (scale * plotW) / 2, cx + (scale * plotW) / 2];
      [y0, y1] = [cy - (scale * plotH) / 2, cy + (scale * plotH) / 2];
    }
    const X = (x) => PAD.left + ((x - x0) / (x1 - x0)) * plotW;
    const Y = (y) => PAD.top + plotH - ((y - y0) / (y1 - y0)) * plotH;
    drawAxes(ctx, { x0, x1, y0, y1, X, Y, plotW, plotH, xLabel, yLabel, height });
    for (const s of series) drawSeries(ctx, s, X, Y);
  }

  function drawAxes(ctx, a) {
    ctx.lineWidth = 1;
    ctx.setLineDash([]);
    ctx.fillStyle = MUTED;
    const xt = ticks(a.x0, a.x1), yt = ticks(a.y0, a.y1);
    ctx.textAlign = "center";
    for (const v of xt.values) {
      ctx.strokeStyle = GRID;
      line(ctx, a.X(v), PAD.top, a.X(v), PAD.top + a.plotH);
      ctx.fillText(v.toFixed(xt.digits), a.X(v), PAD.top + a.plotH + 13);
    }
    ctx.textAlign = "right";
    for (const v of yt.values) {
      ctx.strokeStyle = GRID;
      line(ctx, PAD.left, a.Y(v), PAD.left + a.plotW, a.Y(v));
      ctx.fillText(v.toFixed(yt.digits), PAD.left - 4, a.Y(v) + 4);
    }
    ctx.strokeStyle = INK;
    ctx.strokeRect(PAD.left, PAD.top, a.plotW, a.plotH);
    ctx.fillStyle = INK;
    ctx.textAlign = "center";
    ctx.fillText(a.xLabel, PAD.left + a.plotW / 2, a.height - 4);
    ctx.save();
    ctx.translate(11, PAD.top + a.plotH / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.fillText(a.yLabel, 0, 0);
    ctx.restore();
  }

  function line(ctx, xa, ya, xb, yb) {
    ctx.beginPath();
    ctx.moveTo(xa, ya);
    ctx.lineTo(xb, yb);
    ctx.stroke();
  }

  function drawSeries(ctx, s, X, Y) {
    ctx.strokeStyle = s.color;
    ctx.lineWidth = s.width || 1.5;
    ctx.setLineDash(s.dash || []);
    ctx.beginPath();
    let open = false;
    for (const p of s.points) {
      if (!p || !Number.isFinite(p[0]) || !Number.isFinite(p[1])) { open = false; continue; }
      if (open) ctx.lineTo(X(p[0]), Y(p[1]));
      else ctx.moveTo(X(p[0]), Y(p[1]));
      open = true;
    }
    ctx.stroke();
  }

  return { lines, message };
})();
