// The machine at a glance: connection, state badge, alarm banner, position and readouts.

import { $, el, fixed, grouped } from "./util.js";

const STATE_NAMES = {
  idle: "Idle", run: "Run", hold: "Hold", jog: "Jog", home: "Home", alarm: "Alarm",
  check: "Check", door: "Door", sleep: "Sleep",
};

/** "Hold:0" -> "hold" (the data-state used by the stylesheet). */
export function stateKey(state) {
  return (state || "unknown").split(":")[0].toLowerCase();
}

export class StatusView {
  constructor() {
    this.axes = ["X", "Y", "Z"];
    this.cells = [];
    this.buildRows();
  }

  setInfo(info) {
    $("#machine-name").textContent = info.machine;
    document.title = `motiond — ${info.machine}`;
    this.axes = info.axes.map((axis) => axis.name);
    this.buildRows();
    $("#readonly").hidden = info.can_control;
  }

  buildRows() {
    const body = $("#dro-body");
    body.replaceChildren();
    this.cells = this.axes.map((name) => {
      const work = el("td", { class: "work", "data-axis": name }, "0.000");
      const machine = el("td", { class: "machine" }, "0.000");
      body.append(el("tr", {}, [el("td", { class: "axis" }, name), work, machine]));
      return { work, machine };
    });
  }

  setConnection(state) {
    const node = $("#connection");
    node.dataset.conn = state;
    $(".conn-text", node).textContent =
      { open: "Connected", closed: "Reconnecting…", connecting: "Connecting…" }[state];
    if (state !== "open") this.setState("—", "unknown");
  }

  setState(text, key) {
    const badge = $("#state");
    badge.dataset.state = key;
    badge.textContent = text;
  }

  update(status) {
    const key = stateKey(status.state);
    const detail = status.state.includes(":") && key === "hold"
      ? (status.state.endsWith(":1") ? " …" : "") : "";
    this.setState((STATE_NAMES[key] || status.state) + detail, key);
    this.showAlarm(status.alarm);
    this.cells.forEach((cell, index) => {
      cell.work.textContent = fixed(status.wpos[index]);
      cell.machine.textContent = fixed(status.mpos[index]);
    });
    $("#feed").textContent = grouped(status.speed_mm_min);
    const power = status.power_pct;
    $("#power").textContent = power >= 10 || power === 0 ? power.toFixed(0) : power.toFixed(1);
    $("#power-bar").style.width = `${Math.min(100, power)}%`;
    $(".readout-laser").classList.toggle("on", power > 0);
    $("#queue").textContent = status.queue_depth;
    const o = status.overrides;
    $("#overrides").textContent = `F${o.feed} R${o.rapid} S${o.spindle}`;
    $("#wcs").textContent = status.modal.wcs;
    $("#units").textContent = status.modal.units;
  }

  showAlarm(alarm) {
    const banner = $("#alarm");
    banner.hidden = !alarm;
    if (!alarm) return;
    $("#alarm-title").textContent = `ALARM ${alarm.code}`;
    $("#alarm-meaning").textContent = alarm.meaning || alarm.message;
    $("#alarm-message").textContent =
      alarm.message && alarm.message !== alarm.meaning ? alarm.message : "";
  }
}
