// A small live plot of speed and laser power over the last seconds (uPlot, vendored).

import { $, grouped } from "./util.js";

const WINDOW_S = 30;

/** Axis numbers: 2 500 -> "2.5k". */
function compact(value) {
  return value >= 1000 ? `${+(value / 1000).toFixed(1)}k` : String(value);
}
const IDLE_TICK_MS = 250;

export class LivePlot {
  constructor(container) {
    this.container = container;
    this.t = [];
    this.speed = [];
    this.power = [];
    this.last = { speed: 0, power: 0 };
    this.plot = null;
    this.maxSpeed = 1000;
    this.create();
    new ResizeObserver(() => this.resize()).observe(container);
    setInterval(() => this.tick(), IDLE_TICK_MS);
  }

  create() {
    if (!window.uPlot) {
      setTimeout(() => this.create(), 50);
      return;
    }
    const axis = { stroke: "#8c9aab", grid: { stroke: "rgba(148,163,184,0.08)", width: 1 },
                   ticks: { stroke: "rgba(148,163,184,0.15)", width: 1 }, font: "11px system-ui, sans-serif" };
    const options = {
      width: this.container.clientWidth || 300,
      height: this.container.clientHeight || 150,
      legend: { show: false },
      cursor: { show: false },
      padding: [10, 6, 0, 0],
      scales: {
        x: { time: false, range: () => { const now = this.now(); return [now - WINDOW_S, now]; } },
        speed: { range: () => [0, this.maxSpeed] },
        power: { range: [0, 100] },
      },
      axes: [
        { ...axis, size: 26, splits: () => this.splits(),
          values: (u, ticks) => ticks.map((v) => { const s = Math.round(v - this.now()); return s ? `${s}s` : "now"; }) },
        { ...axis, scale: "speed", size: 44, values: (u, ticks) => ticks.map(compact) },
        { ...axis, scale: "power", side: 1, size: 44, grid: { show: false }, values: (u, ticks) => ticks.map((v) => `${v}%`) },
      ],
      series: [
        {},
        { label: "Speed", scale: "speed", stroke: "#22d3ee", width: 1.6, fill: "rgba(34, 211, 238, 0.10)", points: { show: false } },
        { label: "Laser", scale: "power", stroke: "#f43f5e", width: 1.4, fill: "rgba(244, 63, 94, 0.08)", points: { show: false } },
      ],
    };
    this.plot = new window.uPlot(options, [this.t, this.speed, this.power], this.container);
  }

  now() {
    return performance.now() / 1000;
  }

  /** Time ticks every 5 s, counted back from now. */
  splits() {
    const now = this.now();
    return Array.from({ length: WINDOW_S / 5 + 1 }, (_, i) => now - WINDOW_S + 5 * i);
  }

  /** A telemetry sample (notify_telemetry) or a status update. */
  add(speed, power) {
    this.last = { speed, power };
    this.push(speed, power);
    this.plot?.setData([this.t, this.speed, this.power]);
    $("#plot-speed").textContent = grouped(speed);
    $("#plot-power").textContent = power.toFixed(0);
  }

  setMaxSpeed(mmMin) {
    this.maxSpeed = Math.max(100, mmMin);
  }

  push(speed, power) {
    this.t.push(this.now());
    this.speed.push(speed);
    this.power.push(power);
    const cutoff = this.now() - WINDOW_S - 2;
    while (this.t.length && this.t[0] < cutoff) {
      this.t.shift();
      this.speed.shift();
      this.power.shift();
    }
    if (Math.max(...this.speed) > this.maxSpeed) this.maxSpeed *= 1.5;
  }

  /** Keep the plot scrolling while no samples come (the machine is still). */
  tick() {
    const newest = this.t[this.t.length - 1] || 0;
    if (this.now() - newest > IDLE_TICK_MS / 1000) this.push(this.last.speed, this.last.power);
    this.plot?.setData([this.t, this.speed, this.power]);
  }

  resize() {
    if (!this.plot) return;
    this.plot.setSize({ width: this.container.clientWidth, height: this.container.clientHeight || 150 });
  }
}
