// Machine control: hold/resume/reset/unlock/home, the jog pad and the laser's fire button.

import { $, $$, callApi, toast } from "./util.js";
import { stateKey } from "./status.js";

// Which states enable which buttons (data-needs in index.html).
const ENABLED = {
  hold: (s) => ["run", "jog", "home"].includes(s),
  resume: (s) => s === "hold",
  unlock: (s) => s === "alarm",
  home: (s, info) => ["idle", "alarm"].includes(s) && info?.features?.includes("homing"),
  fire: (s, info) => s === "idle" && info?.features?.includes("laser"),
  idle: (s) => s === "idle",
  control: () => true,
};

export class Controls {
  constructor(api, log) {
    this.api = api;
    this.log = log;
    this.info = null;
    this.state = "unknown";
    this.firing = false;
    this.step = 10;
    this.bindButtons();
    this.bindJog();
    this.bindFire();
  }

  setInfo(info) {
    this.info = info;
    const axes = new Set(info.axes.map((axis) => axis.name));
    $$("[data-jog]").forEach((button) => {
      const [, , z] = button.dataset.jog.split(",").map(Number);
      button.hidden = z !== 0 && !axes.has("Z");
    });
    $("#btn-fire").title = info.features.includes("laser") ? "Fire the laser at low power for focusing"
      : "No [laser] module is configured";
    const homing = info.features.includes("homing") ? "Run the homing cycle ($H)" : "No [endstops] module is configured";
    $("#btn-home").title = homing;
    $("#alarm-home").title = homing;
    $("#alarm-home").hidden = !info.features.includes("homing");
  }

  /** Run an API call; errors become toasts and console lines. */
  async act(label, method, params = {}) {
    return callApi(this.api, this.log, label, method, params);
  }

  bindButtons() {
    $("#btn-hold").addEventListener("click", () => this.act("Hold", "machine.hold"));
    $("#btn-resume").addEventListener("click", () => this.act("Resume", "machine.resume"));
    $("#btn-reset").addEventListener("click", () => {
      this.log?.info("Reset (Ctrl-X)");
      this.act("Reset", "machine.reset");
    });
    const unlock = () => this.act("Unlock", "machine.unlock");
    const home = async () => {
      const result = await this.act("Home", "machine.home");
      if (result) toast("Homing finished", "ok");
    };
    $("#btn-unlock").addEventListener("click", unlock);
    $("#alarm-unlock").addEventListener("click", unlock);
    $("#btn-home").addEventListener("click", home);
    $("#alarm-home").addEventListener("click", home);
  }

  bindJog() {
    $$("#jog-steps button").forEach((button) => {
      button.addEventListener("click", () => {
        $$("#jog-steps button").forEach((b) => b.setAttribute("aria-checked", String(b === button)));
        this.step = Number(button.dataset.step);
      });
    });
    $$("[data-jog]").forEach((button) => {
      button.addEventListener("click", () => this.jog(button.dataset.jog.split(",").map(Number)));
    });
    $("#jog-cancel").addEventListener("click", () => this.act("Jog cancel", "machine.jog_cancel"));
    document.addEventListener("keydown", (event) => this.jogKey(event));
  }

  jog([dx, dy, dz]) {
    const feed = Number($("#jog-feed").value) || 1000;
    const params = { feed_mm_min: feed };
    if (dx) params.x = dx * this.step;
    if (dy) params.y = dy * this.step;
    if (dz) params.z = dz * Math.min(this.step, 10);
    this.act("Jog", "machine.jog", params);
  }

  /** Arrow keys jog X/Y and PageUp/PageDown jog Z, unless typing in a field. */
  jogKey(event) {
    if (event.target.closest("input, textarea, dialog") || event.altKey || event.ctrlKey) return;
    const moves = { ArrowLeft: [-1, 0, 0], ArrowRight: [1, 0, 0], ArrowUp: [0, 1, 0],
                    ArrowDown: [0, -1, 0], PageUp: [0, 0, 1], PageDown: [0, 0, -1] };
    if (!moves[event.key] || !["idle", "jog"].includes(this.state)) return;
    event.preventDefault();
    this.jog(moves[event.key]);
  }

  bindFire() {
    const dialog = $("#fire-dialog");
    const power = $("#fire-power");
    power.addEventListener("input", () => { $("#fire-power-out").textContent = `${power.value} %`; });
    $("#btn-fire").addEventListener("click", () => {
      if (this.firing) {
        this.act("Laser off", "laser.off");
        return;
      }
      dialog.returnValue = "";
      dialog.showModal();
    });
    dialog.addEventListener("close", async () => {
      if (dialog.returnValue !== "fire") return;
      const params = { percent: Number(power.value), duration_s: Number($("#fire-duration").value) || 1 };
      const result = await this.act("Fire", "laser.fire", params);
      if (result) this.log?.push(result.messages.join(" "));
    });
  }

  /** Enable what makes sense in this state; show a firing laser. */
  update(status, canControl) {
    this.state = stateKey(status?.state);
    const laser = status?.modules?.laser;
    this.firing = Boolean(laser?.firing);
    const fire = $("#btn-fire");
    fire.classList.toggle("firing", this.firing);
    $("span", fire).textContent = this.firing ? "Stop" : "Fire";
    $$("[data-needs]").forEach((button) => {
      const rule = ENABLED[button.dataset.needs];
      const firingStop = button === fire && this.firing;
      button.disabled = !canControl || !(firingStop || rule(this.state, this.info));
    });
    const jogOk = canControl && ["idle", "jog"].includes(this.state);
    $$(".jog-btn").forEach((button) => { button.disabled = !jogOk; });
    $("#jog-cancel").disabled = !canControl || this.state !== "jog";
  }
}
