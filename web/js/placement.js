// Placement and the controls a laser user reaches for before and during a cut: work zero per
// axis or all, go to zero, G54-G59, the selected job's size and fit at the current placement,
// Frame, the feed/rapid/power overrides and a button per switch module (air assist) and the
// spindle. Every action is an API call that runs through the machine's ordered line path.

import { $, $$, el, callApi, report, toast } from "./util.js";

const FIT_CHIP = { true: "Fits", false: "Does not fit" };

export class PlacementView {
  constructor(api, log, toolpath) {
    this.api = api;
    this.log = log;
    this.toolpath = toolpath;
    this.selected = null;
    this.place = null;
    this.wcoKey = "";
    this.status = null;
    this.spindleOn = false;
    $$("[data-zero]").forEach((button) => {
      button.addEventListener("click", () => this.act("Zero", "machine.set_zero", { axes: button.dataset.zero }));
    });
    $("#zero-all").addEventListener("click", () => this.act("Zero", "machine.set_zero", { axes: "" }));
    $("#go-zero").addEventListener("click", () => this.act("Go to zero", "machine.go_to_zero"));
    $("#wcs-select").addEventListener("change", (event) => this.act("WCS", "machine.wcs", { wcs: event.target.value }));
    $("#job-frame").addEventListener("click", () => this.frame());
    $$("[data-override]").forEach((button) => {
      button.addEventListener("click", () => this.override(button.dataset.override));
    });
  }

  async act(label, method, params = {}) {
    return callApi(this.api, this.log, label, method, params);
  }

  // -- the selected job at the current placement ---------------------------------------------
  async select(name) {
    this.selected = name;
    await this.refresh();
  }

  async refresh() {
    const name = this.selected;
    if (!name) return;
    let place = null;
    try {
      place = await this.api.call("job.place", { name });
    } catch (error) {
      report(error);
    }
    if (name !== this.selected) return;
    this.place = place;
    this.show();
  }

  show() {
    const place = this.place;
    $("#job-place").hidden = !place;
    this.toolpath.setPlacement(place);
    if (!place) return;
    const size = place.size_mm;
    const z = size.Z ? ` × ${size.Z.toFixed(1)} (Z)` : "";
    $("#job-size").textContent = size.X === undefined ? "no moves"
      : `${place.name}: ${size.X.toFixed(1)} × ${size.Y.toFixed(1)}${z} mm`;
    const chip = $("#job-fit");
    chip.textContent = FIT_CHIP[place.fits];
    chip.dataset.fit = String(place.fits);
    $("#job-fit-text").textContent = place.fits ? "" : place.message;
  }

  async frame() {
    if (!this.selected) return;
    const result = await this.act("Frame", "job.frame", { name: this.selected });
    if (result) toast(result.stopped ? "Frame stopped" : `Framing ${result.name}`, "ok");
  }

  // -- overrides, switches and spindle ---------------------------------------------------------
  override(spec) {
    const [kind, change] = spec.split(":");
    const now = this.status?.overrides?.[kind] ?? 100;
    const value = change.startsWith("=") ? Number(change.slice(1)) : now + Number(change);
    const clamped = kind === "rapid" ? value : Math.max(10, Math.min(200, value));
    this.act("Override", "machine.override", { [kind]: clamped });
  }

  update(status) {
    this.status = status;
    const o = status.overrides;
    $("#ov-feed").textContent = `${o.feed}%`;
    $("#ov-spindle").textContent = `${o.spindle}%`;
    $$("[data-override^='rapid:']").forEach((button) => {
      button.setAttribute("aria-pressed", String(button.dataset.override === `rapid:=${o.rapid}`));
    });
    const select = $("#wcs-select");
    if (document.activeElement !== select) select.value = status.modal.wcs;
    const key = `${status.wco.join(",")}|${status.modal.wcs}`;
    if (key !== this.wcoKey) {
      this.wcoKey = key;
      this.refresh();
    }
    this.accessories(status.modules || {});
  }

  /** A toggle per switch module and one for a spindle, pressed when on. */
  accessories(modules) {
    const box = $("#accessories");
    const wanted = [];
    for (const [name, state] of Object.entries(modules)) {
      if (name.startsWith("switch.") && state.on_gcode) {
        wanted.push({ id: name, label: name.slice(7), on: state.on, lines: state.on ? state.off_gcode : state.on_gcode });
      } else if (name === "spindle") {
        const on = Boolean(state.rpm || state.on);
        wanted.push({ id: name, label: "spindle", on, lines: on ? "M5" : `M3 S${state.max_rpm ?? 1000}` });
      }
    }
    const signature = JSON.stringify(wanted.map(({ id, on }) => [id, on]));
    if (signature === box.dataset.signature) return;
    box.dataset.signature = signature;
    box.replaceChildren(...wanted.map((item) => el("button", {
      class: "btn btn-toggle", type: "button", "data-module": item.id, "aria-pressed": String(item.on),
      title: `${item.label}: ${item.lines}`,
      onclick: () => this.act(item.label, "gcode.send", { lines: [item.lines] }),
    }, `${item.label[0].toUpperCase()}${item.label.slice(1)} ${item.on ? "on" : "off"}`)));
  }
}
