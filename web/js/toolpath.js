// The live toolpath view: the job's planned path from the top, coloured by planned speed, the
// part already cut and the tool with its laser power, with zoom (wheel, pinch, buttons) and pan.
//
// The path comes from job.toolpath (work coordinates). Progress follows the tool: each status
// update looks for the tool's position on the segments just ahead of the last match, so the
// cut part is drawn segment by segment, corners included, however sparse the updates.

import { BUCKETS, GREYS, PALETTE, bucketize, cuts, drawDone, drawGrid, drawPath, drawPlacement,
  drawTool } from "./draw.js";
import { $, duration, grouped } from "./util.js";

const MARGIN = 0.08;

export class ToolpathView {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.base = document.createElement("canvas");
    this.baseCtx = this.base.getContext("2d");
    this.view = { scale: 2, tx: 40, ty: 300 };
    this.width = 0;
    this.height = 0;
    this.path = null;
    this.buckets = null;
    this.axes = null;
    this.status = null;
    this.done = 0; // segments fully cut
    this.drawnDone = 0; // segments cut already drawn on the base layer
    this.partial = null; // [x, y] where the tool is on segment `done`
    this.jobKey = null;
    this.baseValid = false;
    this.userMoved = false;
    this.lastMatchMs = 0;
    this.pointers = new Map();
    this.place = null; // job.place: the selected job's extent at the current placement
    this.colourBy = "speed";
    new ResizeObserver(() => this.resize()).observe(canvas.parentElement);
    this.bindInput();
  }

  setMachine(axes) {
    this.axes = axes;
    this.baseValid = false;
    if (!this.path && !this.userMoved) this.fit();
    this.request();
  }

  /** Show a job's planned path (the result of job.toolpath), or nothing. */
  setPath(path) {
    if (path) {
      path.pointArray = Float64Array.from(path.points);
      path.lengths = cumulativeLengths(path.pointArray, path.segments);
      this.buckets = bucketize(path, this.colourBy);
    }
    this.path = path;
    this.done = 0;
    this.drawnDone = 0;
    this.partial = null;
    this.jobKey = null;
    this.baseValid = false;
    $("#view-empty").hidden = Boolean(path);
    $("#legend").hidden = !path;
    const summary = path ? `${path.name} · ${grouped(path.segments)} segments · ${duration(path.duration_s)} planned` : "";
    $("#view-job").textContent = summary;
    this.legend();
    this.userMoved = false;
    this.fit();
    if (this.status) this.update(this.status);
  }

  legend() {
    if (!this.path) return;
    const { low, high } = this.buckets;
    const power = this.colourBy === "power"; // powers are percent of the maximum S
    $("#legend-min").textContent = grouped(low);
    $("#legend-max").textContent = high - low >= 1 ? grouped(high) : "";
    $(".legend-unit").textContent = power ? "% power" : "mm/min";
    $("#legend").classList.toggle("single", high - low < 1);
    const palette = power ? GREYS : PALETTE;
    const greys = "linear-gradient(90deg, rgb(60, 60, 60), rgb(255, 255, 255))";
    $(".legend-bar").style.background = high - low < 1 ? `rgb(${palette[BUCKETS >> 1].join(",")})`
      : power ? greys : "";
  }

  /** Colour the path by planned speed or by laser power (a raster's greys by S). */
  setColourBy(by) {
    this.colourBy = by;
    if (this.path) this.buckets = bucketize(this.path, by);
    this.legend();
    this.baseValid = false;
    this.request();
  }

  /** The selected job's extent at the current placement (job.place), drawn over the bed. */
  setPlacement(place) {
    this.place = place;
    this.baseValid = false;
    if (!this.userMoved) this.fit();
    this.request();
  }

  update(status) {
    const wco = this.status?.wco;
    if (!wco || wco[0] !== status.wco[0] || wco[1] !== status.wco[1]) this.baseValid = false;
    this.status = status;
    this.track(status);
    const [x, y] = status.wpos;
    const power = status.power_pct;
    $("#view-info").textContent = `X ${x.toFixed(2)}  Y ${y.toFixed(2)}${power > 0 ? `  ·  laser ${power.toFixed(0)}%` : ""}`;
    this.request();
  }

  // -- progress ------------------------------------------------------------------------------
  track(status) {
    const path = this.path;
    const job = status.job;
    if (!path || !job || job.name !== path.name) return;
    const key = `${job.name}@${job.started_s}`;
    if (key !== this.jobKey) {
      this.jobKey = key;
      this.setDone(0);
      this.lastMatchMs = performance.now();
    }
    if (job.state === "done") {
      this.setDone(path.segments);
      this.partial = null;
    } else if (job.state === "running" || job.state === "paused") {
      this.follow(status.wpos[0], status.wpos[1]);
    }
  }

  /** Find the tool on the segments ahead of the last match (within a plausible distance). */
  follow(x, y) {
    const path = this.path;
    const p = path.pointArray;
    const now = performance.now();
    const reach = 10 + ((now - this.lastMatchMs) / 1000) * (path.max_speed_mm_min / 60) * 1.5;
    const eps = Math.max(0.05, 2 * (path.tolerance_mm || 0.01));
    const start = this.done;
    for (let i = start; i < path.segments && path.lengths[i] - path.lengths[start] <= reach; i++) {
      const hit = project(p[2 * i], p[2 * i + 1], p[2 * i + 2], p[2 * i + 3], x, y);
      if (hit.distance <= eps) {
        this.setDone(hit.t >= 1 ? i + 1 : i);
        this.partial = hit.t >= 1 ? null : [x, y];
        this.lastMatchMs = now;
        return;
      }
    }
  }

  setDone(count) {
    if (count < this.drawnDone) this.baseValid = false;
    this.done = count;
  }

  // -- view ----------------------------------------------------------------------------------
  resize() {
    const rect = this.canvas.parentElement.getBoundingClientRect();
    if (!rect.width || !rect.height) return;
    this.width = rect.width;
    this.height = rect.height;
    const dpr = window.devicePixelRatio || 1;
    for (const canvas of [this.canvas, this.base]) {
      canvas.width = Math.round(rect.width * dpr);
      canvas.height = Math.round(rect.height * dpr);
    }
    this.baseValid = false;
    if (!this.userMoved) this.fit();
    this.request();
  }

  /** What the view fits: the job and the machine's travel it is placed in. */
  extent() {
    const travel = this.travel();
    if (this.path) {
      const { min, max } = this.path.bounds;
      const job = { x0: min[0], y0: min[1], x1: max[0], y1: max[1] };
      if (!travel) return job;
      return { x0: Math.min(job.x0, travel.x0), y0: Math.min(job.y0, travel.y0),
        x1: Math.max(job.x1, travel.x1), y1: Math.max(job.y1, travel.y1) };
    }
    return travel || { x0: 0, y0: 0, x1: 100, y1: 100 };
  }

  /** The machine's travel in work coordinates (machine limits minus the work offset). */
  travel() {
    if (!this.axes || this.axes.length < 2) return null;
    const wco = this.status?.wco || [0, 0];
    const [ax, ay] = this.axes;
    return { x0: ax.min_mm - wco[0], x1: ax.max_mm - wco[0], y0: ay.min_mm - wco[1], y1: ay.max_mm - wco[1] };
  }

  fit() {
    if (!this.width) return;
    const e = this.extent();
    const w = Math.max(1, e.x1 - e.x0);
    const h = Math.max(1, e.y1 - e.y0);
    const scale = Math.min(this.width / (w * (1 + 2 * MARGIN)), this.height / (h * (1 + 2 * MARGIN)));
    this.view = {
      scale,
      tx: this.width / 2 - ((e.x0 + e.x1) / 2) * scale,
      ty: this.height / 2 + ((e.y0 + e.y1) / 2) * scale,
    };
    this.baseValid = false;
    this.request();
  }

  zoomAt(factor, cx = this.width / 2, cy = this.height / 2) {
    const v = this.view;
    const scale = Math.min(5000, Math.max(0.02, v.scale * factor));
    const f = scale / v.scale;
    this.view = { scale, tx: cx - (cx - v.tx) * f, ty: cy - (cy - v.ty) * f };
    this.userMoved = true;
    this.baseValid = false;
    this.request();
  }

  panBy(dx, dy) {
    this.view.tx += dx;
    this.view.ty += dy;
    this.userMoved = true;
    this.baseValid = false;
    this.request();
  }

  bindInput() {
    const canvas = this.canvas;
    canvas.addEventListener("wheel", (event) => {
      event.preventDefault();
      const rect = canvas.getBoundingClientRect();
      this.zoomAt(Math.exp(-event.deltaY * 0.0015), event.clientX - rect.left, event.clientY - rect.top);
    }, { passive: false });
    canvas.addEventListener("pointerdown", (event) => {
      canvas.setPointerCapture(event.pointerId);
      this.pointers.set(event.pointerId, { x: event.clientX, y: event.clientY });
      canvas.classList.add("dragging");
    });
    canvas.addEventListener("pointermove", (event) => this.pointerMove(event));
    const release = (event) => {
      this.pointers.delete(event.pointerId);
      if (!this.pointers.size) canvas.classList.remove("dragging");
    };
    canvas.addEventListener("pointerup", release);
    canvas.addEventListener("pointercancel", release);
    canvas.addEventListener("dblclick", () => { this.userMoved = false; this.fit(); });
    $("#view-zoom-in").addEventListener("click", () => this.zoomAt(1.4));
    $("#view-zoom-out").addEventListener("click", () => this.zoomAt(1 / 1.4));
    $("#view-fit").addEventListener("click", () => { this.userMoved = false; this.fit(); });
    document.querySelectorAll("[data-colour]").forEach((button) => {
      button.addEventListener("click", () => {
        document.querySelectorAll("[data-colour]").forEach((b) => b.setAttribute("aria-checked", String(b === button)));
        this.setColourBy(button.dataset.colour);
      });
    });
  }

  /** One finger pans; two fingers pinch-zoom around their midpoint. */
  pointerMove(event) {
    const previous = this.pointers.get(event.pointerId);
    if (!previous) return;
    const current = { x: event.clientX, y: event.clientY };
    if (this.pointers.size === 1) {
      this.panBy(current.x - previous.x, current.y - previous.y);
    } else if (this.pointers.size === 2) {
      const other = [...this.pointers.entries()].find(([id]) => id !== event.pointerId)[1];
      const before = Math.hypot(previous.x - other.x, previous.y - other.y);
      const after = Math.hypot(current.x - other.x, current.y - other.y);
      const rect = this.canvas.getBoundingClientRect();
      if (before > 0) {
        this.zoomAt(after / before, (current.x + other.x) / 2 - rect.left, (current.y + other.y) / 2 - rect.top);
      }
    }
    this.pointers.set(event.pointerId, current);
  }

  // -- drawing -------------------------------------------------------------------------------
  request() {
    if (this.frame) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = null;
      this.draw();
    });
  }

  draw() {
    if (!this.width) return;
    const dpr = this.canvas.width / this.width;
    if (!this.baseValid) this.drawBase(dpr);
    if (this.path && this.done > this.drawnDone) {
      this.baseCtx.setTransform(dpr, 0, 0, dpr, 0, 0);
      drawDone(this.baseCtx, this.view, this.path, this.drawnDone, this.done);
      this.drawnDone = this.done;
    }
    const ctx = this.ctx;
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    ctx.drawImage(this.base, 0, 0);
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    const path = this.path;
    if (path && this.partial && this.done < path.segments && cuts(path, this.done)) {
      const p = path.pointArray;
      const i = this.done;
      drawDone(ctx, this.view, { pointArray: Float64Array.of(p[2 * i], p[2 * i + 1], ...this.partial),
        kinds: [1], powers: [1], usesPower: false }, 0, 1);
    }
    if (this.status) drawTool(ctx, this.view, this.status.wpos[0], this.status.wpos[1], this.status.power_pct);
  }

  drawBase(dpr) {
    const ctx = this.baseCtx;
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, this.base.width, this.base.height);
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    drawGrid(ctx, this.view, this.width, this.height, this.travel());
    if (this.place && this.status) drawPlacement(ctx, this.view, this.place, this.status.wco);
    if (this.path) {
      drawPath(ctx, this.view, this.path, this.buckets);
      if (this.done > 0) drawDone(ctx, this.view, this.path, 0, this.done);
    }
    this.drawnDone = this.path ? this.done : 0;
    this.baseValid = true;
  }
}

function cumulativeLengths(p, count) {
  const lengths = new Float64Array(count + 1);
  for (let i = 0; i < count; i++) {
    lengths[i + 1] = lengths[i] + Math.hypot(p[2 * i + 2] - p[2 * i], p[2 * i + 3] - p[2 * i + 1]);
  }
  return lengths;
}

/** Distance from (x, y) to the segment and where along it (t in [0, 1]) it is closest. */
function project(x0, y0, x1, y1, x, y) {
  const dx = x1 - x0;
  const dy = y1 - y0;
  const lengthSq = dx * dx + dy * dy;
  const t = lengthSq > 0 ? Math.max(0, Math.min(1, ((x - x0) * dx + (y - y0) * dy) / lengthSq)) : 1;
  return { t, distance: Math.hypot(x0 + t * dx - x, y0 + t * dy - y) };
}
