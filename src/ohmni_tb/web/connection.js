// The daemon's WebSocket protocol (docs/daemon.md, "Messages"), from the browser.
//
// One JSON object per text frame. The page sends `subscribe` and `call`; the daemon
// answers with `hello` first, then `sample` (or `batch` of samples), `result`, `error`
// and `lease`. A browser cannot set `Authorization` on a WebSocket: the token goes as a
// subprotocol, `ohmni.token.<base64url>`, beside `ohmni` (the one the daemon picks), so
// it stays out of the URL.

const PROTOCOL = "ohmni";
const TOKEN_PREFIX = "ohmni.token.";

/** The token as base64url without padding (any text survives, and the header stays a token). */
function base64url(text) {
  const bytes = new TextEncoder().encode(text);
  let binary = "";
  for (const byte of bytes) binary += String.fromCharCode(byte);
  return btoa(binary).replace(/\+/g, "-").replace(/\//g, "_").replace(/=+$/, "");
}

/** The daemon's WebSocket URL for this page: the same host and port. */
export function daemonUrl(location) {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  return `${scheme}//${location.host}/`;
}

/**
 * Whether the daemon needs a token the page does not have (or has wrong): `"ok"`,
 * `"token"` (show the login), or `"unreachable"`.
 */
export async function checkAccess(token) {
  const headers = token ? { Authorization: `Bearer ${token}` } : {};
  try {
    const response = await fetch("/auth", { headers, cache: "no-store" });
    if (response.status === 204) return "ok";
    if (response.status === 401) return "token";
    return "unreachable";
  } catch {
    return "unreachable";
  }
}

/** An `error` message from the daemon, as an exception. */
export class DaemonError extends Error {
  constructor(code, message, method) {
    super(message);
    this.code = code;
    this.method = method;
  }
}

/**
 * One connection to the daemon. Events (EventTarget): `open`, `hello` (detail: the hello
 * message), `sample` (detail: {topic, data, dropped}), `lease` (detail: the message),
 * `refused` (detail: a DaemonError for a call nobody awaits), `close` (detail:
 * {opened, code}).
 */
export class Connection extends EventTarget {
  constructor(url, token) {
    super();
    this.url = url;
    this.token = token;
    this.socket = null;
    this.hello = null;
    this.nextId = 1;
    this.pending = new Map();
    this.opened = false;
    // Frames that were not a message this page knows (counted, not dropped unseen).
    this.unreadable = 0;
  }

  connect() {
    const protocols = [PROTOCOL];
    if (this.token) protocols.push(TOKEN_PREFIX + base64url(this.token));
    const socket = new WebSocket(this.url, protocols);
    this.socket = socket;
    socket.addEventListener("open", () => {
      this.opened = true;
      this.dispatchEvent(new Event("open"));
    });
    socket.addEventListener("message", (event) => this.receive(event.data));
    socket.addEventListener("close", (event) => {
      for (const { reject, method } of this.pending.values()) {
        if (reject) reject(new DaemonError("closed", "the connection closed", method));
      }
      this.pending.clear();
      this.dispatchEvent(
        new CustomEvent("close", { detail: { opened: this.opened, code: event.code } }),
      );
    });
  }

  get connected() {
    return this.socket !== null && this.socket.readyState === WebSocket.OPEN;
  }

  /** Bytes the browser still holds for the daemon (a slow link: don't queue commands). */
  get backlog() {
    return this.socket ? this.socket.bufferedAmount : 0;
  }

  close() {
    if (this.socket) this.socket.close(1000, "page closed");
  }

  /** Call `method` and wait for its result; rejects with a DaemonError. */
  call(method, args = {}) {
    return new Promise((resolve, reject) => {
      const id = this.send({ op: "call", method, args }, { resolve, reject, method });
      if (id === null) reject(new DaemonError("closed", "not connected", method));
    });
  }

  /** Call `method` without waiting: a refusal comes as a `refused` event. */
  post(method, args = {}) {
    return this.send({ op: "call", method, args }, { method }) !== null;
  }

  subscribe(topic, options = {}) {
    return new Promise((resolve, reject) => {
      const id = this.send({ op: "subscribe", topic, ...options }, { resolve, reject, method: "subscribe" });
      if (id === null) reject(new DaemonError("closed", "not connected", "subscribe"));
    });
  }

  send(message, waiter) {
    if (!this.connected) return null;
    const id = this.nextId++;
    this.pending.set(id, waiter);
    this.socket.send(JSON.stringify({ ...message, id }));
    return id;
  }

  receive(text) {
    let message;
    try {
      message = JSON.parse(text);
    } catch {
      this.unreadable += 1;
      return;
    }
    switch (message.op) {
      case "hello":
        this.hello = message;
        this.dispatchEvent(new CustomEvent("hello", { detail: message }));
        break;
      case "sample":
        this.dispatchEvent(new CustomEvent("sample", { detail: message }));
        break;
      case "batch":
        for (const sample of message.samples) {
          this.dispatchEvent(new CustomEvent("sample", { detail: sample }));
        }
        break;
      case "lease":
        this.dispatchEvent(new CustomEvent("lease", { detail: message }));
        break;
      case "result": {
        const waiter = this.pending.get(message.id);
        this.pending.delete(message.id);
        if (waiter && waiter.resolve) waiter.resolve(message.data);
        break;
      }
      case "error": {
        const waiter = this.pending.get(message.id);
        this.pending.delete(message.id);
        const error = new DaemonError(message.code, message.message, waiter ? waiter.method : null);
        if (waiter && waiter.reject) waiter.reject(error);
        else this.dispatchEvent(new CustomEvent("refused", { detail: error }));
        break;
      }
      default:
        this.unreadable += 1;
        break;
    }
  }
}
