// Small helpers shared by the UI modules: DOM, formatting, toasts and confirmation dialogs.

export const $ = (selector, root = document) => root.querySelector(selector);
export const $$ = (selector, root = document) => [...root.querySelectorAll(selector)];

/** Create an element: el("li", {class: "x", onclick: fn}, [children or text]). */
export function el(tag, attrs = {}, children = []) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (key === "class") node.className = value;
    else if (key === "html") node.innerHTML = value;
    else if (value !== undefined && value !== null && value !== false) node.setAttribute(key, value);
  }
  for (const child of [].concat(children)) {
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

/** An inline SVG icon from a path string. */
export function icon(path) {
  const span = document.createElement("span");
  span.innerHTML = `<svg viewBox="0 0 24 24" aria-hidden="true"><path d="${path}"/></svg>`;
  return span.firstChild;
}

export const ICONS = {
  play: "M7 5l12 7-12 7z",
  trash: "M4 7h16M9 7V4h6v3M6 7l1 13h10l1-13",
  file: "M6 3h8l4 4v14H6zM14 3v4h4",
};

export function fixed(value, digits = 3) {
  return Number.isFinite(value) ? value.toFixed(digits) : "—";
}

/** 1234567 -> "1 234 567" (thin spaces keep columns tidy). */
export function grouped(value) {
  return Math.round(value).toLocaleString("en-US").replaceAll(",", "\u2009");
}

/** Seconds as m:ss or h:mm:ss. */
export function duration(seconds) {
  if (seconds === null || seconds === undefined || !Number.isFinite(seconds)) return "–";
  const total = Math.max(0, Math.round(seconds));
  const h = Math.floor(total / 3600);
  const m = Math.floor((total % 3600) / 60);
  const s = String(total % 60).padStart(2, "0");
  return h ? `${h}:${String(m).padStart(2, "0")}:${s}` : `${m}:${s}`;
}

export function bytes(size) {
  if (size < 1024) return `${size} B`;
  if (size < 1024 * 1024) return `${(size / 1024).toFixed(1)} KB`;
  return `${(size / 1024 / 1024).toFixed(1)} MB`;
}

export function when(epochSeconds) {
  const date = new Date(epochSeconds * 1000);
  const today = new Date();
  const sameDay = date.toDateString() === today.toDateString();
  return sameDay
    ? date.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" })
    : date.toLocaleDateString([], { month: "short", day: "numeric" });
}

/** A short message in the corner; kind is "info", "ok" or "error". */
export function toast(message, kind = "info", ms = 4000) {
  const node = el("div", { class: `toast ${kind}`, role: kind === "error" ? "alert" : "status" }, message);
  $("#toasts").append(node);
  setTimeout(() => node.remove(), ms);
}

/** Show an API error as a toast (and return it, for chaining). */
export function report(error) {
  const meaning = error?.data?.meaning;
  const text = error?.message || String(error);
  toast(meaning && !text.includes(meaning) ? `${text} — ${meaning}` : text, "error", 6000);
  return error;
}

/** Ask before something irreversible; resolves true when confirmed. */
export function confirmAction(title, text, okLabel = "OK") {
  const dialog = $("#confirm-dialog");
  $("#confirm-title").textContent = title;
  $("#confirm-text").textContent = text;
  $("#confirm-ok").textContent = okLabel;
  dialog.returnValue = "";
  dialog.showModal();
  return new Promise((resolve) => {
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "ok"), { once: true });
  });
}

/** Run an API call; errors become toasts and console lines (null then). */
export async function callApi(api, log, label, method, params = {}) {
  try {
    return await api.call(method, params);
  } catch (error) {
    log?.error(`${label}: ${error.message}`);
    report(error);
    return null;
  }
}
