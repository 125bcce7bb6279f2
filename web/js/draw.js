// Drawing helpers for the toolpath view: the speed palette, the grid, the planned and cut path,
// and the tool. All take a 2D context already scaled to CSS pixels and a view transform
// {scale, tx, ty}: screen x = x * scale + tx, screen y = -y * scale + ty (Y up, like the machine).

const STOPS = ["#818cf8", "#38bdf8", "#34d399", "#facc15", "#fb923c", "#f43f5e"];
export const BUCKETS = 24;
const RAPID = 0;
const CUT = 1;

function hex(color) {
  return [1, 3, 5].map((i) => parseInt(color.slice(i, i + 2), 16));
}

/** BUCKETS colours from slow (indigo) to fast (red). */
export const PALETTE = Array.from({ length: BUCKETS }, (_, i) => {
  const t = (i / (BUCKETS - 1)) * (STOPS.length - 1);
  const k = Math.min(STOPS.length - 2, Math.floor(t));
  const a = hex(STOPS[k]);
  const b = hex(STOPS[k + 1]);
  const f = t - k;
  return a.map((v, j) => Math.round(v + (b[j] - v) * f));
});

/** BUCKETS greys from no power (dark) to full power (white): the power view of a raster. */
export const GREYS = Array.from({ length: BUCKETS }, (_, i) => {
  const v = Math.round(60 + (195 * i) / (BUCKETS - 1));
  return [v, v, v];
});

export const sx = (view, x) => x * view.scale + view.tx;
export const sy = (view, y) => -y * view.scale + view.ty;

/** Whether segment i cuts: a feed move, with the laser on when the job uses the laser. */
export function cuts(path, i) {
  return path.kinds[i] === CUT && (!path.usesPower || path.powers[i] > 0);
}

/** Group segments by colour and opacity so the whole path is a few dozen strokes. */
export function bucketize(path, by = "speed") {
  const { kinds, powers } = path;
  const speeds = by === "power" ? powers : path.speeds;
  path.colourBy = by;
  const maxPower = Math.max(0, ...powers);
  path.usesPower = maxPower > 0;
  let low = Infinity;
  let high = -Infinity;
  kinds.forEach((kind, i) => {
    if (!cuts(path, i)) return;
    low = Math.min(low, speeds[i]);
    high = Math.max(high, speeds[i]);
  });
  if (!Number.isFinite(low)) { low = 0; high = 0; }
  if (by === "power") low = 0; // grey by S: black is off, white is the job's highest S
  const span = high - low;
  const groups = new Map();
  const rapids = [];
  const travels = [];
  kinds.forEach((kind, i) => {
    if (kind === RAPID) rapids.push(i);
    else if (kind === CUT && !cuts(path, i)) travels.push(i);
    if (!cuts(path, i)) return;
    const colour = span >= 1 ? Math.round(((speeds[i] - low) / span) * (BUCKETS - 1)) : BUCKETS >> 1;
    const level = maxPower > 0 ? Math.min(2, Math.floor((3 * powers[i]) / maxPower)) : 2;
    const key = colour * 3 + level;
    if (!groups.has(key)) groups.set(key, []);
    groups.get(key).push(i);
  });
  return { groups, rapids, travels, low, high, maxPower };
}

const ALPHA = [0.5, 0.75, 1.0];

export function drawPath(ctx, view, path, buckets) {
  const p = path.pointArray;
  ctx.lineCap = "round";
  ctx.lineJoin = "round";
  ctx.setLineDash([4, 4]);
  ctx.lineWidth = 1;
  ctx.strokeStyle = "rgba(148, 163, 184, 0.35)";
  strokeSegments(ctx, view, p, buckets.rapids);
  ctx.setLineDash([]);
  ctx.strokeStyle = "rgba(148, 163, 184, 0.28)";
  strokeSegments(ctx, view, p, buckets.travels);
  ctx.lineWidth = 1.4;
  const palette = path.colourBy === "power" ? GREYS : PALETTE;
  for (const [key, indices] of buckets.groups) {
    const [r, g, b] = palette[Math.floor(key / 3)];
    const alpha = path.colourBy === "power" ? 1 : ALPHA[key % 3];
    ctx.strokeStyle = `rgba(${r}, ${g}, ${b}, ${alpha})`;
    strokeSegments(ctx, view, p, indices);
  }
}

/** The part already cut, drawn over the plan (segments first..last-1 that cut). */
export function drawDone(ctx, view, path, first, last) {
  const p = path.pointArray;
  ctx.lineCap = "round";
  ctx.lineJoin = "round";
  ctx.setLineDash([]);
  ctx.lineWidth = 2;
  ctx.strokeStyle = "rgba(255, 244, 230, 0.92)";
  ctx.shadowColor = "rgba(251, 146, 60, 0.8)";
  ctx.shadowBlur = 4;
  const indices = [];
  for (let i = first; i < last; i++) if (cuts(path, i)) indices.push(i);
  strokeSegments(ctx, view, p, indices);
  ctx.shadowBlur = 0;
}

function strokeSegments(ctx, view, p, indices) {
  ctx.beginPath();
  let previous = -2;
  for (const i of indices) {
    if (i !== previous + 1) ctx.moveTo(sx(view, p[2 * i]), sy(view, p[2 * i + 1]));
    ctx.lineTo(sx(view, p[2 * i + 2]), sy(view, p[2 * i + 3]));
    previous = i;
  }
  ctx.stroke();
}

/** A grid whose spacing suits the zoom, the work origin, and the machine's travel. */
export function drawGrid(ctx, view, width, height, travel) {
  const steps = [0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000];
  const step = steps.find((s) => s * view.scale >= 28) || 1000;
  const x0 = Math.floor(-view.tx / view.scale / step) * step;
  const x1 = (width - view.tx) / view.scale;
  const y0 = Math.floor((view.ty - height) / view.scale / step) * step;
  const y1 = view.ty / view.scale;
  ctx.lineWidth = 1;
  for (let x = x0; x <= x1; x += step) line(ctx, sx(view, x), 0, sx(view, x), height, gridColour(x, step));
  for (let y = y0; y <= y1; y += step) line(ctx, 0, sy(view, y), width, sy(view, y), gridColour(y, step));
  line(ctx, sx(view, 0), 0, sx(view, 0), height, "rgba(74, 222, 128, 0.35)");
  line(ctx, 0, sy(view, 0), width, sy(view, 0), "rgba(248, 113, 113, 0.35)");
  if (travel) {
    ctx.setLineDash([6, 5]);
    ctx.strokeStyle = "rgba(96, 165, 250, 0.45)";
    const left = sx(view, travel.x0);
    const top = sy(view, travel.y1);
    ctx.strokeRect(left, top, (travel.x1 - travel.x0) * view.scale, (travel.y1 - travel.y0) * view.scale);
    ctx.setLineDash([]);
    ctx.fillStyle = "rgba(96, 165, 250, 0.6)";
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillText("machine travel", left + 6, top + 14);
  }
  ctx.fillStyle = "rgba(140, 154, 171, 0.8)";
  ctx.font = "11px ui-monospace, monospace";
  ctx.fillText(`grid ${step} mm`, 10, height - 10);
}

function gridColour(value, step) {
  const major = Math.abs(Math.round(value / step) % 5) === 0;
  return major ? "rgba(148, 163, 184, 0.13)" : "rgba(148, 163, 184, 0.055)";
}

function line(ctx, x0, y0, x1, y1, colour) {
  ctx.strokeStyle = colour;
  ctx.beginPath();
  ctx.moveTo(Math.round(x0) + 0.5, Math.round(y0) + 0.5);
  ctx.lineTo(Math.round(x1) + 0.5, Math.round(y1) + 0.5);
  ctx.stroke();
}

/** The tool: a crosshair, glowing with the laser's power. */
export function drawTool(ctx, view, x, y, powerPct) {
  const px = sx(view, x);
  const py = sy(view, y);
  if (powerPct > 0) {
    const radius = 8 + 18 * Math.min(1, powerPct / 100);
    const glow = ctx.createRadialGradient(px, py, 0, px, py, radius);
    glow.addColorStop(0, "rgba(255, 255, 255, 0.95)");
    glow.addColorStop(0.25, "rgba(244, 63, 94, 0.9)");
    glow.addColorStop(1, "rgba(244, 63, 94, 0)");
    ctx.fillStyle = glow;
    ctx.beginPath();
    ctx.arc(px, py, radius, 0, 2 * Math.PI);
    ctx.fill();
  }
  ctx.strokeStyle = powerPct > 0 ? "#fff" : "#e2e8f0";
  ctx.lineWidth = 1.5;
  ctx.beginPath();
  ctx.arc(px, py, 6, 0, 2 * Math.PI);
  ctx.moveTo(px - 12, py); ctx.lineTo(px - 3, py);
  ctx.moveTo(px + 3, py); ctx.lineTo(px + 12, py);
  ctx.moveTo(px, py - 12); ctx.lineTo(px, py - 3);
  ctx.moveTo(px, py + 3); ctx.lineTo(px, py + 12);
  ctx.stroke();
}

/** The selected job's extent at the current placement (job.place, machine mm), drawn in work
 * coordinates: green when it fits the travel, red when it does not, with its size. */
export function drawPlacement(ctx, view, place, wco) {
  const low = place.extent_min_mm;
  const high = place.extent_max_mm;
  if (low.X === undefined) return;
  const x0 = low.X - wco[0];
  const y1 = high.Y - wco[1];
  const w = (high.X - low.X) * view.scale;
  const h = (high.Y - low.Y) * view.scale;
  const colour = place.fits ? "74, 222, 128" : "248, 113, 113";
  ctx.setLineDash([3, 3]);
  ctx.lineWidth = 1.5;
  ctx.strokeStyle = `rgba(${colour}, 0.9)`;
  ctx.fillStyle = `rgba(${colour}, 0.08)`;
  ctx.fillRect(sx(view, x0), sy(view, y1), w, h);
  ctx.strokeRect(sx(view, x0), sy(view, y1), w, h);
  ctx.setLineDash([]);
  ctx.fillStyle = `rgba(${colour}, 0.95)`;
  ctx.font = "11px system-ui, sans-serif";
  const size = `${(high.X - low.X).toFixed(1)} × ${(high.Y - low.Y).toFixed(1)} mm${place.fits ? "" : " · does not fit"}`;
  ctx.fillText(size, sx(view, x0), sy(view, y1) - 5);
}
