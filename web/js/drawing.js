// Drawings: a dropped SVG, DXF, PNG or JPEG becomes a laser job. drawing.read lists its layers
// (one per colour, one per image) and their shapes, drawn here over the machine's travel;
// each layer gets its mode, speed, power and passes; drawing.generate stores the job, which is
// then selected like any other: its toolpath, time, fit and Frame, then Start.

import { pageToken } from "./api.js";
import { $, el, report, toast } from "./util.js";

export const DRAWING_TYPES = [".svg", ".dxf", ".png", ".jpg", ".jpeg"];
const INLINE_BYTES = 700 * 1024; // base64 of this fits an /api message (1 MB); larger: POST /upload
const MODES = { line: "Line (cut)", fill: "Fill", image: "Image" };
const DITHERS = { grayscale: "Grayscale", "floyd-steinberg": "Floyd–Steinberg", jarvis: "Jarvis",
  stucki: "Stucki", threshold: "Threshold" };

export function isDrawing(name) {
  const lower = name.toLowerCase();
  return DRAWING_TYPES.some((suffix) => lower.endsWith(suffix));
}

export class DrawingView {
  /** @param onMade called with the stored job's name */
  constructor(api, onMade) {
    this.api = api;
    this.onMade = onMade;
    this.axes = null;
    this.drawing = null;
    this.source = null;
    this.dialog = $("#drawing-dialog");
    this.canvas = $("#drawing-canvas");
    $("#drawing-generate").addEventListener("click", (event) => { event.preventDefault(); this.generate(); });
    $("#drawing-cancel").addEventListener("click", () => this.dialog.close());
    $("#drawing-material").addEventListener("change", () => this.useMaterial($("#drawing-material").value));
    $("#drawing-material-save").addEventListener("click", () => this.saveMaterial());
    $("#drawing-width").addEventListener("change", () => this.resize(Number($("#drawing-width").value)));
    this.materials = {};
    api.on("notify_drawing_progress", ({ name, task, fraction }) => {
      if (this.source?.name === name) this.status(`${task === "read" ? "Reading" : "Making the job"}… ${Math.round(100 * fraction)}%`);
    });
  }

  setMachine(axes) {
    this.axes = axes;
  }

  status(text) {
    $("#drawing-status").textContent = text;
  }

  /** Read the file, ask the server for its layers, and show them. */
  async open(file) {
    this.source = { name: file.name, params: await this.sourceParams(file) };
    if (!this.source.params) return;
    $("#drawing-width-field").hidden = true;
    $("#drawing-title").textContent = file.name;
    this.drawing = null;
    $("#drawing-layers").replaceChildren();
    $("#drawing-warnings").replaceChildren();
    $("#drawing-generate").disabled = true;
    this.dialog.showModal();
    this.status("Reading…");
    try {
      this.drawing = await this.api.call("drawing.read", { name: file.name, ...this.source.params });
    } catch (error) {
      this.status(error.message);
      report(error);
      return;
    }
    this.showSize();
    this.showWarnings(this.drawing.warnings);
    this.showLayers();
    await this.loadMaterials();
    $("#drawing-generate").disabled = false;
    await this.loadThumbnails();
    this.paint();
  }

  showSize() {
    this.status(`${this.drawing.width_mm.toFixed(1)} × ${this.drawing.height_mm.toFixed(1)} mm, placed at the work origin`);
    const image = this.drawing.layers.some((layer) => layer.image !== null);
    $("#drawing-width-field").hidden = !image;
    if (image) $("#drawing-width").value = this.drawing.width_mm.toFixed(1);
  }

  /** An image read again at another width (its height follows). */
  async resize(widthMm) {
    if (!(widthMm > 0)) return;
    this.source.params.width_mm = widthMm;
    try {
      const drawing = await this.api.call("drawing.read", { name: this.source.name, ...this.source.params });
      const settings = this.settings();
      this.drawing = drawing;
      for (const layer of drawing.layers) Object.assign(layer.settings, settings[layer.name] || {});
      this.showSize();
      this.showLayers();
      await this.loadThumbnails();
      this.paint();
    } catch (error) {
      report(error);
    }
  }

  /** base64 in the call for a small file; a larger one goes to POST /upload first. */
  async sourceParams(file) {
    if (file.size <= INLINE_BYTES) {
      const url = await new Promise((resolve, reject) => {
        const reader = new FileReader();
        reader.onload = () => resolve(reader.result);
        reader.onerror = () => reject(reader.error);
        reader.readAsDataURL(file);
      });
      return { base64: String(url).split(",", 2)[1] };
    }
    const token = pageToken();
    const response = await fetch(`/upload?name=${encodeURIComponent(file.name)}${token ? `&token=${encodeURIComponent(token)}` : ""}`,
      { method: "POST", body: file });
    const body = await response.json().catch(() => ({}));
    if (!response.ok || body.error) {
      report(body.error || { message: `upload failed (HTTP ${response.status})` });
      return null;
    }
    return { file: body.result.name };
  }

  showWarnings(warnings) {
    $("#drawing-warnings").replaceChildren(...warnings.map((text) => el("li", {}, text)));
  }

  showLayers() {
    const rows = this.drawing.layers.map((layer) => this.layerRow(layer));
    $("#drawing-layers").replaceChildren(...rows);
  }

  layerRow(layer) {
    const s = layer.settings;
    const number = (key, value, attrs) => el("input", { type: "number", value, "data-key": key,
      "aria-label": `${layer.name} ${key}`, onchange: () => this.paint(), ...attrs });
    const choice = (key, options, value) => el("select", { "data-key": key, "aria-label": `${layer.name} ${key}`,
      onchange: () => this.paint() }, Object.entries(options).map(([v, label]) =>
      el("option", { value: v, selected: v === value ? "" : undefined }, label)));
    const image = layer.image !== null;
    const modes = image ? { image: MODES.image } : { line: MODES.line, fill: MODES.fill };
    const what = image ? `${layer.image[0]} × ${layer.image[1]} px` : `${layer.shapes} shapes`;
    return el("tr", { "data-layer": layer.name }, [
      el("td", {}, el("input", { type: "checkbox", checked: s.enabled ? "" : undefined, "data-key": "enabled",
        "aria-label": `Cut layer ${layer.name}`, onchange: () => this.paint() })),
      el("td", { class: "layer-name" }, [el("span", { class: "swatch", style: `background:${image ? "#888" : layer.name}` }),
        el("span", {}, [el("b", {}, image ? "image" : layer.name), el("small", {}, what)])]),
      el("td", {}, choice("mode", modes, s.mode)),
      el("td", {}, number("speed_mm_min", s.speed_mm_min, { min: 1, max: 120000, step: 100 })),
      el("td", {}, number("power_pct", s.power_pct, { min: 0, max: 100, step: 1 })),
      el("td", {}, number("passes", s.passes, { min: 1, max: 100, step: 1 })),
      el("td", {}, number("interval_mm", s.interval_mm, { min: 0.01, max: 10, step: 0.01 })),
      el("td", {}, image ? choice("dither", DITHERS, s.dither) : number("angle_deg", s.angle_deg, { min: -360, max: 360, step: 5 })),
    ]);
  }

  // -- the material library: layer settings by name, kept on the machine ----------------------
  async loadMaterials() {
    try {
      this.materials = await this.api.call("material.list");
    } catch (error) {
      report(error);
      return;
    }
    const select = $("#drawing-material");
    const chosen = select.value;
    select.replaceChildren(el("option", { value: "" }, "Layer defaults"),
      ...Object.keys(this.materials).sort().map((name) => el("option", { value: name, selected: name === chosen ? "" : undefined }, name)));
  }

  /** Fill the table from a material: each layer it names takes its settings. */
  useMaterial(name) {
    if (!name) {
      this.showLayers();
    } else {
      for (const [layer, values] of Object.entries(this.materials[name] || {})) {
        const row = $("#drawing-layers").querySelector(`tr[data-layer="${CSS.escape(layer)}"]`);
        if (!row) continue;
        for (const [key, value] of Object.entries(values)) {
          const input = row.querySelector(`[data-key="${key}"]`);
          if (!input) continue;
          if (input.type === "checkbox") input.checked = Boolean(value);
          else input.value = String(value);
        }
      }
      $("#drawing-material-name").value = name;
    }
    this.paint();
  }

  async saveMaterial() {
    const name = $("#drawing-material-name").value.trim();
    if (!name) {
      report({ message: "name the material first (e.g. 3 mm plywood)" });
      return;
    }
    try {
      this.materials = await this.api.call("material.save", { name, layers: this.settings() });
      toast(`Saved the material ${name}`, "ok");
      $("#drawing-material").value = "";
      await this.loadMaterials();
      $("#drawing-material").value = name;
    } catch (error) {
      report(error);
    }
  }

  /** Each layer's settings from the table. */
  settings() {
    const layers = {};
    for (const row of $("#drawing-layers").querySelectorAll("tr")) {
      const values = {};
      for (const input of row.querySelectorAll("[data-key]")) {
        const key = input.dataset.key;
        values[key] = input.type === "checkbox" ? input.checked : input.type === "number" ? Number(input.value) : input.value;
      }
      layers[row.dataset.layer] = values;
    }
    return layers;
  }

  async generate() {
    const button = $("#drawing-generate");
    button.disabled = true;
    this.status("Making the job…");
    try {
      const made = await this.api.call("drawing.generate", { name: this.source.name, ...this.source.params,
        layers: this.settings() });
      toast(`Made ${made.job.name}: ${made.lines.toLocaleString("en-US")} lines`, "ok");
      this.dialog.close();
      this.onMade(made.job.name);
    } catch (error) {
      this.status(error.message);
      report(error);
    } finally {
      button.disabled = false;
    }
  }

  async loadThumbnails() {
    this.thumbnails = new Map();
    for (const layer of this.drawing.layers) {
      if (!layer.thumbnail) continue;
      const image = new Image();
      image.src = `data:image/png;base64,${layer.thumbnail}`;
      await image.decode().catch(() => null);
      this.thumbnails.set(layer.name, image);
    }
  }

  /** The machine's travel, a 50 mm grid, and each enabled layer in its colour. */
  paint() {
    const canvas = this.canvas;
    const ratio = window.devicePixelRatio || 1;
    const width = canvas.clientWidth;
    const height = canvas.clientHeight;
    canvas.width = width * ratio;
    canvas.height = height * ratio;
    const g = canvas.getContext("2d");
    g.setTransform(ratio, 0, 0, ratio, 0, 0);
    g.fillStyle = "#0b1016";
    g.fillRect(0, 0, width, height);
    if (!this.axes || !this.drawing) return;
    const [ax, ay] = this.axes;
    const spanX = ax.max_mm - ax.min_mm;
    const spanY = ay.max_mm - ay.min_mm;
    const scale = Math.min((width - 20) / spanX, (height - 20) / spanY);
    const left = (width - spanX * scale) / 2;
    const bottom = (height + spanY * scale) / 2;
    const toX = (x) => left + (x - ax.min_mm) * scale;
    const toY = (y) => bottom - (y - ay.min_mm) * scale;
    g.strokeStyle = "#1c2733";
    g.lineWidth = 1;
    for (let x = Math.ceil(ax.min_mm / 50) * 50; x <= ax.max_mm; x += 50) {
      g.beginPath(); g.moveTo(toX(x), toY(ay.min_mm)); g.lineTo(toX(x), toY(ay.max_mm)); g.stroke();
    }
    for (let y = Math.ceil(ay.min_mm / 50) * 50; y <= ay.max_mm; y += 50) {
      g.beginPath(); g.moveTo(toX(ax.min_mm), toY(y)); g.lineTo(toX(ax.max_mm), toY(y)); g.stroke();
    }
    g.strokeStyle = "#3b4b5e";
    g.strokeRect(toX(ax.min_mm), toY(ay.max_mm), spanX * scale, spanY * scale);
    const settings = this.settings();
    for (const layer of this.drawing.layers) {
      const chosen = settings[layer.name] || layer.settings;
      if (!chosen.enabled) continue;
      const thumbnail = this.thumbnails?.get(layer.name);
      if (thumbnail) {
        const { min, max } = layer.bounds;
        const [x, y, w, h] = [toX(min[0]), toY(max[1]), (max[0] - min[0]) * scale, (max[1] - min[1]) * scale];
        g.drawImage(thumbnail, x, y, w, h);
        g.strokeStyle = "#8c9aab";
        g.strokeRect(x, y, w, h);
        continue;
      }
      const colour = visible(layer.name);
      g.strokeStyle = colour;
      g.fillStyle = `${colour}55`;
      g.lineWidth = 1.2;
      g.beginPath();
      for (const path of layer.paths) {
        g.moveTo(toX(path[0]), toY(path[1]));
        for (let i = 2; i < path.length; i += 2) g.lineTo(toX(path[i]), toY(path[i + 1]));
      }
      if (chosen.mode === "fill") g.fill("evenodd");
      g.stroke();
    }
  }
}

/** A layer's colour, lightened when too dark to see on the dark canvas. */
function visible(colour) {
  const value = parseInt(colour.slice(1), 16);
  return Math.max(value >> 16, (value >> 8) & 255, value & 255) < 96 ? "#e6edf3" : colour;
}
