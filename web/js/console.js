// The console: type G-code and commands, see each reply and the machine's pushed messages.

import { $, $$, el } from "./util.js";

const MAX_LINES = 600;

export class ConsoleView {
  constructor(api) {
    this.api = api;
    this.log = $("#console-log");
    this.history = [];
    this.cursor = 0;
    const input = $("#console-input");
    $("#console-form").addEventListener("submit", (event) => {
      event.preventDefault();
      const text = input.value;
      if (!text.trim()) return;
      input.value = "";
      this.send(text);
    });
    input.addEventListener("keydown", (event) => this.browse(event, input));
    $("#console-clear").addEventListener("click", () => this.log.replaceChildren());
    $$("#console-quick button").forEach((button) => {
      button.addEventListener("click", () => this.send(button.dataset.cmd));
    });
    api.on("notify_gcode_response", ({ message }) => this.push(message));
  }

  line(text, kind) {
    const stick = this.log.scrollTop + this.log.clientHeight >= this.log.scrollHeight - 8;
    const node = el("div", { class: kind }, text);
    this.log.append(node);
    while (this.log.childElementCount > MAX_LINES) this.log.firstElementChild.remove();
    if (stick) this.log.scrollTop = this.log.scrollHeight;
    return node;
  }

  info(text) { this.line(text, "info"); }
  error(text) { this.line(text, "err"); }

  /** A line pushed by the machine (ALARM:n, [MSG:...]). */
  push(message) {
    this.line(message, message.startsWith("ALARM") ? "alarm-line" : "push");
  }

  /** Send one or more lines; print each with its reply. */
  async send(text) {
    this.history.push(text);
    this.cursor = this.history.length;
    const lines = text.split(/\r?\n/);
    let result;
    try {
      result = await this.api.call("gcode.send", { lines });
    } catch (error) {
      this.line(text, "sent");
      this.error(error.message);
      return;
    }
    for (const item of result.results) {
      this.line(item.line, "sent");
      for (const message of item.messages) this.line(message, "msg");
      if (item.error) {
        const { message, meaning } = item.error;
        const node = this.line(message, "err");
        if (meaning && !message.includes(meaning)) node.append(el("span", { class: "meaning" }, ` — ${meaning}`));
      } else {
        this.line("ok", "ok");
      }
    }
    if (result.skipped) this.info(`${result.skipped} line(s) not sent after the error`);
  }

  /** Up/Down walk through the history of sent commands. */
  browse(event, input) {
    if (event.key !== "ArrowUp" && event.key !== "ArrowDown") return;
    event.preventDefault();
    this.cursor += event.key === "ArrowUp" ? -1 : 1;
    this.cursor = Math.max(0, Math.min(this.history.length, this.cursor));
    input.value = this.history[this.cursor] ?? "";
  }
}
