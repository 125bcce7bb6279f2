// Jobs: upload (drag and drop or browse; a drawing goes to the drawing view), the stored
// files, and the running job's progress.

import { pageToken } from "./api.js";
import { isDrawing } from "./drawing.js";
import { $, ICONS, bytes, confirmAction, duration, el, icon, report, toast, when } from "./util.js";

const PAUSE_TEXT = (reason) => (!reason || reason === "hold" ? "Held: Continue resumes the job."
  : reason.startsWith("tool change") ? `Tool change: insert ${reason.slice(12)}, then Continue.`
    : `${reason}: the program paused; Continue resumes it.`);
const STATE_LABELS = { running: "Running", paused: "Paused", done: "Done", aborted: "Aborted", failed: "Failed" };

export class JobsView {
  /** @param onSelect called with a file name to preview its toolpath */
  constructor(api, onSelect, onDrawing) {
    this.api = api;
    this.onSelect = onSelect;
    this.onDrawing = onDrawing;
    this.files = [];
    this.selected = null;
    this.job = null;
    this.canControl = true;
    this.bindUpload();
    $("#jobs-refresh").addEventListener("click", () => this.refresh());
    $("#job-pause").addEventListener("click", () => this.call("job.pause"));
    $("#job-resume").addEventListener("click", () => this.call("job.resume"));
    $("#job-abort").addEventListener("click", async () => {
      if (await confirmAction("Abort the job?", "Motion stops at once and the laser turns off.", "Abort")) {
        this.call("job.abort");
      }
    });
    api.on("notify_filelist_changed", () => this.refresh());
    api.on("notify_job_update", ({ job }) => this.showJob(job));
  }

  async call(method, params = {}) {
    try {
      return await this.api.call(method, params);
    } catch (error) {
      report(error);
      return null;
    }
  }

  // -- files ---------------------------------------------------------------------------------
  async refresh() {
    const files = await this.call("job.list");
    if (!files) return;
    this.files = files;
    this.render();
  }

  render() {
    const list = $("#job-files");
    list.replaceChildren();
    if (!this.files.length) {
      list.append(el("li", { class: "empty" }, "No stored jobs yet"));
      return;
    }
    const busy = this.job && ["running", "paused"].includes(this.job.state);
    for (const file of this.files) {
      const run = el("button", { class: "run", type: "button", title: `Run ${file.name}`,
        "aria-label": `Run ${file.name}`, disabled: busy || !this.canControl,
        onclick: (event) => { event.stopPropagation(); this.start(file.name); } }, icon(ICONS.play));
      const remove = el("button", { type: "button", title: `Delete ${file.name}`,
        "aria-label": `Delete ${file.name}`, disabled: !this.canControl,
        onclick: (event) => { event.stopPropagation(); this.remove(file.name); } }, icon(ICONS.trash));
      const item = el("li", { class: file.name === this.selected ? "selected" : "", "data-name": file.name,
        onclick: () => this.select(file.name) }, [
        el("span", { class: "file-icon" }, icon(ICONS.file)),
        el("span", { class: "file-main" }, [
          el("span", { class: "file-name ellipsis" }, file.name),
          el("span", { class: "file-meta" }, `${bytes(file.size_bytes)} · ${when(file.modified_s)}`),
        ]),
        el("span", { class: "file-actions" }, [run, remove]),
      ]);
      list.append(item);
    }
  }

  select(name) {
    this.selected = name;
    this.render();
    this.onSelect(name);
  }

  async start(name) {
    this.select(name);
    const progress = await this.call("job.start", { name });
    if (progress) this.showJob(progress);
  }

  async remove(name) {
    if (!(await confirmAction(`Delete ${name}?`, "The file is removed from the machine.", "Delete"))) return;
    if (await this.call("job.delete", { name })) {
      if (this.selected === name) this.selected = null;
      toast(`Deleted ${name}`, "ok");
      this.refresh();
    }
  }

  // -- upload --------------------------------------------------------------------------------
  bindUpload() {
    const zone = $("#dropzone");
    const input = $("#file-input");
    input.addEventListener("change", () => {
      if (input.files.length) this.upload(input.files[0]);
      input.value = "";
    });
    for (const type of ["dragenter", "dragover"]) {
      zone.addEventListener(type, (event) => { event.preventDefault(); zone.classList.add("over"); });
    }
    for (const type of ["dragleave", "drop"]) {
      zone.addEventListener(type, () => zone.classList.remove("over"));
    }
    zone.addEventListener("drop", (event) => {
      event.preventDefault();
      const file = event.dataTransfer?.files?.[0];
      if (file) this.upload(file);
    });
    // A file dropped anywhere else on the page is not opened by the browser.
    window.addEventListener("dragover", (event) => event.preventDefault());
    window.addEventListener("drop", (event) => event.preventDefault());
  }

  /** POST /upload?name=... with the file as the body, showing progress. */
  upload(file) {
    if (isDrawing(file.name)) {
      this.onDrawing(file);
      return;
    }
    const status = $("#upload-status");
    const token = pageToken();
    const url = `/upload?name=${encodeURIComponent(file.name)}${token ? `&token=${encodeURIComponent(token)}` : ""}`;
    const request = new XMLHttpRequest();
    request.open("POST", url);
    request.upload.addEventListener("progress", (event) => {
      if (event.lengthComputable) status.textContent = `Uploading ${file.name}… ${Math.round(100 * event.loaded / event.total)}%`;
    });
    request.addEventListener("load", () => {
      status.textContent = "";
      let body = {};
      try { body = JSON.parse(request.responseText); } catch { /* not JSON */ }
      if (request.status !== 200 || body.error) {
        report(body.error || { message: `upload failed (HTTP ${request.status})` });
        return;
      }
      toast(`Uploaded ${body.result.name} (${bytes(body.result.size_bytes)})`, "ok");
      this.refresh().then(() => this.select(body.result.name));
    });
    request.addEventListener("error", () => {
      status.textContent = "";
      report({ message: "upload failed: connection error" });
    });
    status.textContent = `Uploading ${file.name}…`;
    request.send(file);
  }

  // -- the current job -----------------------------------------------------------------------
  showJob(job) {
    const wasBusy = this.job && ["running", "paused"].includes(this.job.state);
    this.job = job;
    const box = $("#job-current");
    box.hidden = !job;
    if (!job) return;
    const percent = Math.max(0, Math.min(100, job.percent));
    $("#job-name").textContent = job.name;
    const chip = $("#job-state");
    chip.textContent = STATE_LABELS[job.state] || job.state;
    chip.dataset.job = job.state;
    const bar = $("#job-progress");
    bar.setAttribute("aria-valuenow", percent.toFixed(0));
    bar.dataset.job = job.state;
    $("#job-progress-fill").style.width = `${percent}%`;
    $("#job-percent").textContent = `${percent.toFixed(percent < 100 && percent >= 99.5 ? 1 : 0)}%`;
    $("#job-elapsed").textContent = duration(job.elapsed_s);
    $("#job-remaining").textContent = job.state === "done" ? "0:00" : duration(job.remaining_s);
    const paused = $("#job-paused-for");
    paused.hidden = job.state !== "paused" || !job.paused_for;
    paused.textContent = PAUSE_TEXT(job.paused_for);
    const error = $("#job-error");
    error.hidden = !job.error;
    error.textContent = job.error || "";
    const active = ["running", "paused"].includes(job.state);
    $(".job-actions").hidden = !active;
    $("#job-pause").hidden = job.state === "paused";
    $("#job-resume").hidden = job.state !== "paused";
    $("#job-pause").disabled = !active || !this.canControl;
    $("#job-abort").disabled = !active || !this.canControl;
    if (wasBusy !== active) this.render();
  }

  setControl(canControl) {
    this.canControl = canControl;
    this.render();
  }
}
