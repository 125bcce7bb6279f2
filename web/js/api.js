// The JSON-RPC 2.0 client for /api: requests as promises, notifications as events, and
// automatic reconnection with back-off. See docs/API.md for the methods.

export class RpcError extends Error {
  constructor(error) {
    super(error.message);
    this.code = error.code;
    this.data = error.data;
  }
}

export class Api extends EventTarget {
  /** @param {string} url ws:// or wss:// address of /api */
  constructor(url) {
    super();
    this.url = url;
    this.socket = null;
    this.nextId = 1;
    this.pending = new Map();
    this.handlers = new Map();
    this.delayMs = 500;
    this.connected = false;
  }

  connect() {
    const socket = new WebSocket(this.url);
    this.socket = socket;
    socket.addEventListener("open", () => {
      this.connected = true;
      this.delayMs = 500;
      this.dispatchEvent(new Event("open"));
    });
    socket.addEventListener("message", (event) => this.receive(event.data));
    socket.addEventListener("close", () => this.closed(socket));
  }

  closed(socket) {
    if (socket !== this.socket) return;
    const wasConnected = this.connected;
    this.connected = false;
    for (const { reject } of this.pending.values()) {
      reject(new RpcError({ code: -32001, message: "connection lost" }));
    }
    this.pending.clear();
    if (wasConnected) this.dispatchEvent(new Event("close"));
    setTimeout(() => this.connect(), this.delayMs);
    this.delayMs = Math.min(this.delayMs * 2, 5000);
  }

  receive(text) {
    let message;
    try {
      message = JSON.parse(text);
    } catch {
      return;
    }
    if (message.method) {
      for (const handler of this.handlers.get(message.method) || []) handler(message.params);
      return;
    }
    const waiter = this.pending.get(message.id);
    if (!waiter) return;
    this.pending.delete(message.id);
    if (message.error) waiter.reject(new RpcError(message.error));
    else waiter.resolve(message.result);
  }

  /** Call a method; resolves with its result, rejects with an RpcError. */
  call(method, params = {}) {
    if (!this.connected) {
      return Promise.reject(new RpcError({ code: -32001, message: "not connected" }));
    }
    const id = this.nextId++;
    this.socket.send(JSON.stringify({ jsonrpc: "2.0", id, method, params }));
    return new Promise((resolve, reject) => this.pending.set(id, { resolve, reject }));
  }

  /** Listen to a notification (notify_status_update, notify_telemetry, ...). */
  on(method, handler) {
    if (!this.handlers.has(method)) this.handlers.set(method, []);
    this.handlers.get(method).push(handler);
  }
}

/** The token from the page's address (?token=...), if any. */
export function pageToken() {
  return new URLSearchParams(location.search).get("token");
}

/** ws(s)://host/api, carrying the page's token. */
export function apiUrl() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  const token = pageToken();
  return `${scheme}//${location.host}/api${token ? `?token=${encodeURIComponent(token)}` : ""}`;
}
