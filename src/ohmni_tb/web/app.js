// The web console: status, live plots, driving and the neck, over the daemon's protocol.
//
// Safety first: the page drives only while it holds the control lease and an input is
// held (the joystick, a drive key), sending `drive` at the control rate; letting go sends
// `stop`, and so do losing focus, hiding the page, leaving it and a lost connection (the
// Robot's watchdog stops the wheels anyway when the commands stop coming). The STOP
// button sends `estop`, which anyone may.

import { Connection, checkAccess, daemonUrl } from "./connection.js";
import { Joystick } from "./joystick.js";
import { RateMeter, TimePlot, TracePlot } from "./plot.js";

const TOKEN_KEY = "ohmni.token";
// The command source the page drives as: a person at the robot (local) overrides it.
const SOURCE = "remote";
// The page's own speed limits at first, within the Robot's.
const START_LINEAR_MPS = 0.4;
const START_ANGULAR_RADPS = 1.2;
// Commands are skipped while the browser still holds this much unsent (a slow link):
// a queue of stale commands would keep the robot going after the hand let go.
const MAX_BACKLOG_BYTES = 4096;
// Reduced rates: enough for the eye and the plots, a small share of the daemon's work.
const SUBSCRIPTIONS = {
  wheel_encoder: { max_hz: 20, queue: 8 },
  wheel_odom: { max_hz: 20, queue: 8 },
  tbcore_status: { max_hz: 2, queue: 4 },
  servo_neck: { max_hz: 5, queue: 4 },
  new_neck: { max_hz: 5, queue: 4 },
  robot_state: { queue: 16 },
  diagnostics: { queue: 4 },
};
const RECONNECT_FIRST_MS = 500;
const RECONNECT_MAX_MS = 4000;
const NECK_MOVE_EVERY_MS = 250;
const NECK_PLAYTIME_S = 0.4;
const NECK_STEPS = 8;
// After a move, the slider shows the target this long before it follows the neck again.
const NECK_SETTLE_MS = 1500;
// A HerkuleX servo's middle position, raw (0 rad before its zero offset).
const HERKULEX_CENTRE_RAW = 512;

const $ = (id) => document.getElementById(id);
const clamp = (value, low, high) => Math.min(high, Math.max(low, value));

const state = {
  connection: null,
  token: null,
  hello: null,
  config: null,
  peer: null,
  holder: null,
  you: false,
  estopped: false,
  neck: "none",
  neckRange: null,
  neckPosition: null,
  neckTarget: null,
  neckDragging: false,
  neckLastMove: -Infinity,
  separation: 0.33,
  reconnectMs: RECONNECT_FIRST_MS,
  reconnectTimer: 0,
};

// -- what is shown -------------------------------------------------------------------------

function setText(id, text) {
  const element = $(id);
  if (element.textContent !== text) element.textContent = text;
}

let noticeTimer = 0;
function notice(text) {
  setText("notice", text);
  clearTimeout(noticeTimer);
  if (text) noticeTimer = setTimeout(() => setText("notice", ""), 6000);
}

function showLink(text, good) {
  setText("link", text);
  $("link").dataset.state = good ? "up" : "down";
}

function showLogin(message) {
  $("console").hidden = true;
  $("login").hidden = false;
  setText("login-error", message);
  showLink("Needs the daemon's token", false);
  $("token").focus();
}

function canDrive() {
  const connection = state.connection;
  return Boolean(
    connection && connection.connected && state.you && !state.estopped && !state.hello?.read_only,
  );
}

function showLease() {
  const readOnly = Boolean(state.hello?.read_only);
  let text;
  if (!state.connection || !state.connection.connected) text = "Not connected";
  else if (readOnly) text = "This daemon is read-only: watch only";
  else if (state.you) text = "You have control";
  else if (state.holder) text = `${state.holder} has control`;
  else text = "Nobody has control";
  setText("lease", text);
  const connected = Boolean(state.connection?.connected) && !readOnly;
  $("take").hidden = !connected || state.you || state.holder !== null;
  $("takeover").hidden = !connected || state.you || state.holder === null;
  $("release").hidden = !connected || !state.you;
  $("clear").disabled = !state.you;
  $("clear-help").hidden = state.you;
  const drive = canDrive();
  // Not allowed to drive any more (the lease gone, an emergency stop, the connection
  // lost): the commands end here, without a stop of this page's own — the daemon
  // stopped the robot as the lease changed hands, and a stop now could cut into the
  // first commands of whoever drives next.
  if (!drive) driver.halt(false);
  joystick.setEnabled(drive);
  document.body.classList.toggle("driving-allowed", drive);
  for (const id of ["neck", "neck-up", "neck-level", "neck-down"]) {
    $(id).disabled = !state.you || state.neck === "none" || readOnly;
  }
  $("estop").disabled = !state.connection?.connected;
}

function showEstop(estopped) {
  state.estopped = estopped;
  $("estop-banner").hidden = !estopped;
  document.body.classList.toggle("estopped", estopped);
  showLease();
}

// -- driving -------------------------------------------------------------------------------

/** Sends `drive` at the control rate while an input is held; `stop` when none is. */
class Driver {
  constructor() {
    this.inputs = new Map();
    this.timer = 0;
    this.periodMs = 20;
  }

  /** An input (`joystick`, `keys`) asks for a fraction of the top speed and turn rate. */
  hold(source, forward, turn) {
    if (!canDrive()) return;
    this.inputs.set(source, [forward, turn]);
    if (!this.timer) {
      this.timer = setInterval(() => this.tick(), this.periodMs);
      this.tick();
    }
  }

  release(source) {
    if (this.inputs.delete(source) && this.inputs.size === 0) this.halt(true);
  }

  /** Stop sending; with `send`, tell the daemon to stop too (anyone may). */
  halt(send) {
    const wasDriving = this.timer !== 0;
    this.inputs.clear();
    clearInterval(this.timer);
    this.timer = 0;
    if (send && wasDriving && state.connection?.connected) state.connection.post("stop");
    showCommand(0, 0);
  }

  twist() {
    let forward = 0;
    let turn = 0;
    for (const [f, t] of this.inputs.values()) {
      forward += f;
      turn += t;
    }
    return [
      clamp(forward, -1, 1) * Number($("speed").value),
      clamp(turn, -1, 1) * Number($("turn").value),
    ];
  }

  tick() {
    if (!canDrive()) {
      this.halt(true);
      return;
    }
    const [linear, angular] = this.twist();
    showCommand(linear, angular);
    if (state.connection.backlog > MAX_BACKLOG_BYTES) return;
    state.connection.post("drive", { linear_mps: linear, angular_radps: angular });
  }
}

function showCommand(linear, angular) {
  const text =
    linear === 0 && angular === 0
      ? "stopped"
      : `${linear.toFixed(2)} m/s, ${angular.toFixed(2)} rad/s`;
  setText("command", text);
}

const driver = new Driver();

const joystick = new Joystick($("joystick"), $("knob"), {
  onMove: (x, y) => driver.hold("joystick", y, -x),
  onRelease: () => driver.release("joystick"),
});

const KEYS = {
  ArrowUp: "forward",
  KeyW: "forward",
  ArrowDown: "back",
  KeyS: "back",
  ArrowLeft: "left",
  KeyA: "left",
  ArrowRight: "right",
  KeyD: "right",
};
const keysDown = new Set();

function typing(target) {
  return target instanceof HTMLElement && target.matches("input, textarea, select");
}

function driveFromKeys() {
  const forward = (keysDown.has("forward") ? 1 : 0) - (keysDown.has("back") ? 1 : 0);
  const turn = (keysDown.has("left") ? 1 : 0) - (keysDown.has("right") ? 1 : 0);
  if (keysDown.size) driver.hold("keys", forward, turn);
  else driver.release("keys");
}

window.addEventListener("keydown", (event) => {
  if (event.ctrlKey || event.altKey || event.metaKey || typing(event.target)) return;
  if (event.code === "Space") {
    // The driver's stop key. A page that only watches keeps space for scrolling: its
    // STOP button stops the robot.
    if (!state.you) return;
    event.preventDefault();
    stopEverything(false);
    if (state.connection?.connected) state.connection.post("stop");
    return;
  }
  const key = KEYS[event.code];
  if (!key || !canDrive()) return;
  event.preventDefault();
  keysDown.add(key);
  driveFromKeys();
});

window.addEventListener("keyup", (event) => {
  const key = KEYS[event.code];
  if (!key || !keysDown.has(key)) return;
  keysDown.delete(key);
  driveFromKeys();
});

/** Every input let go and the commands stopped; `send`: a `stop` too. */
function stopEverything(send) {
  keysDown.clear();
  joystick.release();
  driver.halt(send);
}

window.addEventListener("blur", () => stopEverything(true));
document.addEventListener("visibilitychange", () => {
  if (document.visibilityState === "hidden") stopEverything(true);
});
window.addEventListener("pagehide", () => {
  stopEverything(true);
  const connection = state.connection;
  if (connection?.connected) {
    if (state.you) connection.post("release", { source: SOURCE });
    connection.close();
  }
});

// -- the lease, the stop -------------------------------------------------------------------

async function acquire(steal) {
  try {
    await state.connection.call("acquire", { steal, source: SOURCE });
  } catch (error) {
    notice(error.message);
  }
}

$("take").addEventListener("click", () => acquire(false));
$("takeover").addEventListener("click", () => {
  const holder = state.holder ?? "another client";
  if (window.confirm(`${holder} is driving the robot. Take control from it? The robot stops.`)) {
    acquire(true);
  }
});
$("release").addEventListener("click", async () => {
  stopEverything(true);
  try {
    await state.connection.call("release", { source: SOURCE });
  } catch (error) {
    notice(error.message);
  }
});

$("estop").addEventListener("click", async () => {
  stopEverything(false);
  try {
    await state.connection.call("estop");
    showEstop(true);
  } catch (error) {
    notice(`STOP: ${error.message}`);
  }
});

$("clear").addEventListener("click", async () => {
  try {
    await state.connection.call("clear_estop");
    showEstop(false);
  } catch (error) {
    notice(error.message);
  }
});

function setLease(holder, you) {
  state.holder = holder;
  state.you = you;
  showLease();
}

// -- speed limits --------------------------------------------------------------------------

function limit(value, fallback) {
  return typeof value === "number" && Number.isFinite(value) && value > 0 ? value : fallback;
}

function setupLimits(motion) {
  const linear = limit(motion.max_linear_mps, limit(motion.max_wheel_mps, 1.0));
  const angular = limit(motion.max_angular_radps, 2.0);
  state.separation = motion.wheel_separation_m;
  configureRange("speed", 0.05, linear, 0.05, Math.min(START_LINEAR_MPS, linear));
  configureRange("turn", 0.1, angular, 0.1, Math.min(START_ANGULAR_RADPS, angular));
  setText("speed-limit", `${linear.toFixed(2)} m/s`);
  setText("turn-limit", `${angular.toFixed(2)} rad/s`);
  showSpeeds();
}

function configureRange(id, low, high, step, value) {
  const input = $(id);
  const previous = Number(input.value);
  input.min = String(Math.min(low, high));
  input.max = String(high);
  input.step = String(step);
  const keep = input.dataset.set === "1" ? previous : value;
  input.value = String(clamp(keep, Math.min(low, high), high));
}

function showSpeeds() {
  setText("speed-out", `${Number($("speed").value).toFixed(2)} m/s`);
  setText("turn-out", `${Number($("turn").value).toFixed(2)} rad/s`);
}

for (const id of ["speed", "turn"]) {
  $(id).addEventListener("input", () => {
    $(id).dataset.set = "1";
    showSpeeds();
  });
}

// -- the neck ------------------------------------------------------------------------------

function setupNeck(kind, config) {
  state.neck = kind;
  const input = $("neck");
  $("neck-card").dataset.kind = kind;
  if (kind === "herkulex") {
    state.neckRange = [config.neck_min_raw, config.neck_max_raw];
    input.dir = "ltr"; // up is the high end
  } else if (kind === "worm") {
    state.neckRange = [config.worm_min_raw, config.worm_max_raw];
    input.dir = "rtl"; // up is the low end
  } else {
    state.neckRange = null;
  }
  if (state.neckRange) {
    input.min = String(state.neckRange[0]);
    input.max = String(state.neckRange[1]);
    input.step = kind === "worm" ? "1000" : "1";
    setText("neck-range", `${state.neckRange[0]}…${state.neckRange[1]} raw`);
  } else {
    setText("neck-range", "no neck");
  }
  showLease();
}

/** The neck to `raw` counts, held within its range (nothing beyond it is sent). */
async function moveNeck(raw) {
  if (!state.neckRange) return;
  const target = Math.round(clamp(raw, state.neckRange[0], state.neckRange[1]));
  const args = { target: "neck", raw: target };
  if (state.neck === "herkulex") args.playtime_s = NECK_PLAYTIME_S;
  state.neckTarget = target;
  state.neckLastMove = performance.now();
  $("neck").value = String(target);
  setText("neck-target", `${target} raw`);
  try {
    await state.connection.call("move", args);
  } catch (error) {
    notice(error.message);
  }
}

/** A step up or down from where the neck is going (or is). */
function neckStep(up) {
  if (!state.neckRange) return;
  const [low, high] = state.neckRange;
  const step = (high - low) / NECK_STEPS;
  // HerkuleX: up is the high end; the worm gear: the low end.
  const sign = (state.neck === "herkulex") === up ? 1 : -1;
  const recent = performance.now() - state.neckLastMove < NECK_SETTLE_MS;
  const from = recent && state.neckTarget !== null ? state.neckTarget : state.neckPosition;
  if (from === null) return;
  moveNeck(from + sign * step);
}

$("neck").addEventListener("input", () => {
  state.neckDragging = true;
  setText("neck-target", `${$("neck").value} raw`);
  if (performance.now() - state.neckLastMove >= NECK_MOVE_EVERY_MS) moveNeck(Number($("neck").value));
});
$("neck").addEventListener("change", () => {
  state.neckDragging = false;
  moveNeck(Number($("neck").value));
});
$("neck-up").addEventListener("click", () => neckStep(true));
$("neck-down").addEventListener("click", () => neckStep(false));
$("neck-level").addEventListener("click", () => {
  // The HerkuleX neck's level head is 0 rad: 512 + its zero offset; the worm gear's
  // neutral is 0.
  if (state.neck === "herkulex") moveNeck(HERKULEX_CENTRE_RAW + state.config.neck_zero_offset_raw);
  else moveNeck(0);
});

function showNeck(position, detail) {
  state.neckPosition = position;
  setText("v-neck", `${position} raw${detail}`);
  if (!state.neckDragging && performance.now() - state.neckLastMove > NECK_SETTLE_MS) {
    $("neck").value = String(position);
    setText("neck-target", `${position} raw`);
  }
}

// -- status and plots ----------------------------------------------------------------------

const speeds = new TimePlot($("speeds"), {
  series: [
    { key: "left", colour: "--left" },
    { key: "right", colour: "--right" },
    { key: "left_cmd", colour: "--left", dash: true },
    { key: "right_cmd", colour: "--right", dash: true },
  ],
  windowS: 10,
  minSpan: 0.2,
});
const trace = new TracePlot($("trace"));
const rates = { wheel_encoder: new RateMeter(), wheel_odom: new RateMeter() };

setInterval(() => {
  setText("speeds-rate", `${rates.wheel_encoder.perSecond()} Hz`);
  setText("trace-rate", `${rates.wheel_odom.perSecond()} Hz`);
}, 500);

/** A command source as words: its name, whatever shape the daemon gives it in. */
function sourceText(source) {
  if (source === null) return "none";
  if (typeof source === "object") return String(source.name ?? JSON.stringify(source));
  return String(source);
}

const onSample = {
  wheel_encoder(data) {
    rates.wheel_encoder.tick();
    speeds.push("left", data.stamp_s, data.left_mps);
    speeds.push("right", data.stamp_s, data.right_mps);
    setText("v-wheels", `${data.left_mps.toFixed(2)} · ${data.right_mps.toFixed(2)} m/s`);
  },
  wheel_odom(data) {
    rates.wheel_odom.tick();
    const half = (data.commanded_angular_radps * state.separation) / 2;
    speeds.push("left_cmd", data.stamp_s, data.commanded_linear_mps - half);
    speeds.push("right_cmd", data.stamp_s, data.commanded_linear_mps + half);
    trace.push(data.x_m, data.y_m, data.yaw_rad);
    setText(
      "v-pose",
      `x ${data.x_m.toFixed(2)} m, y ${data.y_m.toFixed(2)} m, ${((data.yaw_rad * 180) / Math.PI).toFixed(0)}°`,
    );
  },
  tbcore_status(data) {
    setText("v-pack", `${data.pack_v.toFixed(2)} V`);
    setText("v-percent", `${data.percent} %`);
    const dock = [data.docked ? "docked" : "not docked", data.charging ? "charging" : "not charging"];
    setText("v-dock", `${dock.join(", ")} · ${data.current_a.toFixed(2)} A`);
    const cells = $("cells").children;
    data.cell_v.forEach((volts, index) => {
      if (cells[index]) cells[index].querySelector("span").textContent = volts.toFixed(3);
    });
    $("battery-bar").value = data.percent;
  },
  robot_state(data) {
    setText("v-robot-link", data.link);
    $("v-robot-link").dataset.state = data.link === "connected" ? "up" : "down";
    setText("v-faults", data.faults.length ? data.faults.join(", ") : "none");
    $("v-faults").dataset.state = data.faults.length ? "down" : "up";
    if (data.estopped !== state.estopped) showEstop(data.estopped);
    setText("v-watchdog", data.watchdog_tripped ? "tripped: no command" : "armed");
    // The command source, where the daemon's Robot tells it.
    const source = data.active_source;
    const hasSource = source !== undefined;
    $("l-source").hidden = !hasSource;
    $("v-source").hidden = !hasSource;
    if (hasSource) setText("v-source", sourceText(source));
    if (data.neck !== state.neck && state.config) setupNeck(data.neck, state.config);
    if (data.event) setText("v-event", data.event);
  },
  diagnostics(data) {
    setText("v-health", data.level);
    $("v-health").dataset.level = data.level;
    const list = $("diagnostics");
    const items = data.entries.map((entry) => {
      const item = document.createElement("li");
      item.dataset.level = entry.level;
      const name = document.createElement("strong");
      name.textContent = entry.name;
      item.append(name, ` ${entry.level}: ${entry.message}`);
      return item;
    });
    list.replaceChildren(...items);
  },
  servo_neck(data) {
    const limit = state.config ? ` of ${state.config.thermal_limit_raw}` : "";
    const degrees = ((data.angle_rad * 180) / Math.PI).toFixed(1);
    showNeck(data.position_raw, ` · ${degrees}° · temperature ${data.temperature_raw}${limit} raw`);
  },
  new_neck(data) {
    const flags = [];
    if (data.flags & 1) flags.push("moving");
    if (data.flags & 2) flags.push("stalled");
    showNeck(data.position_raw, flags.length ? ` · ${flags.join(", ")}` : "");
  },
};

// -- connecting ----------------------------------------------------------------------------

async function start() {
  state.token = sessionStorage.getItem(TOKEN_KEY);
  const access = await checkAccess(state.token);
  if (access === "token") {
    if (state.token) sessionStorage.removeItem(TOKEN_KEY);
    showLogin(state.token ? "The token was refused: enter it again." : "");
    return;
  }
  if (access === "unreachable") {
    showLink("Cannot reach the daemon: trying again", false);
    reconnectLater();
    return;
  }
  connect();
}

function reconnectLater() {
  clearTimeout(state.reconnectTimer);
  state.reconnectTimer = setTimeout(start, state.reconnectMs);
  state.reconnectMs = Math.min(RECONNECT_MAX_MS, state.reconnectMs * 2);
}

function connect() {
  showLink("Connecting…", false);
  const connection = new Connection(daemonUrl(window.location), state.token);
  state.connection = connection;
  connection.addEventListener("hello", (event) => welcome(event.detail));
  connection.addEventListener("sample", (event) => {
    const handle = onSample[event.detail.topic];
    if (handle) handle(event.detail.data);
  });
  connection.addEventListener("lease", (event) => {
    const { holder, you, reason, source } = event.detail;
    // The page holds the lease of its own command source only.
    if (source !== undefined && source !== SOURCE) return;
    if (!you && state.you) notice(`Control ${reason}`);
    setLease(holder, you);
  });
  connection.addEventListener("refused", (event) => {
    const error = event.detail;
    if (error.code === "no_lease") setLease(state.holder, false);
    notice(`${error.method ?? "daemon"}: ${error.message}`);
  });
  connection.addEventListener("close", (event) => {
    if (state.connection !== connection) return;
    stopEverything(false);
    state.you = false;
    document.body.classList.add("stale");
    showLease();
    showLink(
      event.detail.opened
        ? "Disconnected: reconnecting…"
        : "Refused by the daemon: too many clients, or this address is not allowed " +
            "(open the page by IP address or localhost): trying again",
      false,
    );
    reconnectLater();
  });
  connection.connect();
}

async function welcome(hello) {
  const connection = state.connection;
  state.hello = hello;
  state.peer = hello.peer;
  state.reconnectMs = RECONNECT_FIRST_MS;
  document.body.classList.remove("stale");
  $("console").hidden = false;
  $("login").hidden = true;
  const where = hello.simulated ? "simulator" : hello.serves ?? "robot";
  showLink(`Connected · ${where}`, true);
  $("link").title = `ohmni_tb ${hello.version}, protocol ${hello.protocol}, as ${hello.peer}`;
  const hz = hello.topics?.wheel_encoder || 20;
  driver.periodMs = 1000 / clamp(hz, 5, 50);
  setupLimits(hello.motion);
  setText("v-watchdog-s", `${hello.motion.watchdog_s} s`);
  const holder = hello.leases ? (hello.leases[SOURCE] ?? null) : hello.lease;
  setLease(holder, holder !== null && holder === hello.peer);
  speeds.clearData();
  for (const [topic, options] of Object.entries(SUBSCRIPTIONS)) {
    if (!(topic in (hello.topics ?? {}))) continue;
    connection.subscribe(topic, options).catch((error) => notice(error.message));
  }
  try {
    state.config = await connection.call("config");
    const robotState = await connection.call("latest", { topic: "robot_state" });
    setupNeck(robotState ? robotState.neck : "none", state.config);
    for (const topic of ["robot_state", "tbcore_status", "diagnostics"]) {
      const sample = topic === "robot_state" ? robotState : await connection.call("latest", { topic });
      if (sample) onSample[topic](sample);
    }
  } catch (error) {
    notice(error.message);
  }
}

$("login-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const token = $("token").value.trim();
  if (!token) return;
  const access = await checkAccess(token);
  if (access === "token") {
    setText("login-error", "That is not this daemon's token.");
    return;
  }
  if (access === "unreachable") {
    setText("login-error", "Cannot reach the daemon.");
    return;
  }
  sessionStorage.setItem(TOKEN_KEY, token);
  $("token").value = "";
  $("login").hidden = true;
  state.token = token;
  connect();
});

showLease();
start();
