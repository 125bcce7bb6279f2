// motiond web UI: connects to /api, subscribes to status, telemetry, console and job updates,
// and wires the views together. No build step: plain ES modules served as static files.

import { Api, apiUrl } from "./api.js";
import { ConsoleView } from "./console.js";
import { DrawingView } from "./drawing.js";
import { Controls } from "./controls.js";
import { JobsView } from "./jobs.js";
import { PlacementView } from "./placement.js";
import { LivePlot } from "./plot.js";
import { StatusView } from "./status.js";
import { ToolpathView } from "./toolpath.js";
import { $, report } from "./util.js";

const api = new Api(apiUrl());
const statusView = new StatusView();
const consoleView = new ConsoleView(api);
const controls = new Controls(api, consoleView);
const toolpath = new ToolpathView($("#toolpath"));
const plot = new LivePlot($("#plot"));
const placement = new PlacementView(api, consoleView, toolpath);
let info = null;
let canControl = false;
let previewName = null;

async function preview(name) {
  previewName = name;
  placement.select(name);
  $("#view-job").textContent = `Planning ${name}…`;
  try {
    const path = await api.call("job.toolpath", { name });
    if (previewName !== name) return;
    toolpath.setPath(path);
    if (path.error) consoleView.error(`${name}: line ${path.error_line}: ${path.error}`);
  } catch (error) {
    $("#view-job").textContent = "";
    report(error);
  }
}

const drawings = new DrawingView(api, (name) => jobs.refresh().then(() => jobs.select(name)));
const jobs = new JobsView(api, preview, (file) => drawings.open(file).catch(report));

function showStatus(status) {
  statusView.update(status);
  controls.update(status, canControl);
  toolpath.update(status);
  placement.update(status);
  const job = status.job;
  if (job && job.name !== toolpath.path?.name && job.name !== previewName
      && ["running", "paused"].includes(job.state)) {
    preview(job.name);
  }
  if (JSON.stringify(job) !== JSON.stringify(jobs.job)) jobs.showJob(job);
}

api.on("notify_status_update", ({ status }) => showStatus(status));
api.on("notify_telemetry", (sample) => plot.add(sample.speed_mm_min, sample.power_pct));

api.addEventListener("open", async () => {
  statusView.setConnection("open");
  try {
    info = await api.call("server.info");
    canControl = info.can_control;
    statusView.setInfo(info);
    controls.setInfo(info);
    toolpath.setMachine(info.axes);
    drawings.setMachine(info.axes);
    plot.setMaxSpeed(Math.max(...info.axes.slice(0, 2).map((axis) => axis.max_rate_mm_min)) / 4);
    jobs.setControl(canControl);
    consoleView.info(`Connected to ${info.machine} (motiond ${info.version})`);
    const { status } = await api.call("machine.subscribe", { topics: ["status", "telemetry", "console", "job"] });
    showStatus(status);
    await jobs.refresh();
  } catch (error) {
    report(error);
  }
});

api.addEventListener("close", () => {
  statusView.setConnection("closed");
  controls.update(null, false);
  consoleView.info("Connection lost; reconnecting…");
});

statusView.setConnection("connecting");
controls.update(null, false);
api.connect();

// For tests and the curious: the live objects.
window.motiond = { api, toolpath, plot, jobs, controls, placement, drawings, console: consoleView };
