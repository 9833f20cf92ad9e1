'use strict';
/*
 * ohmni_tb bus capture: a tb-node plugin that logs every byte tb-node writes to the
 * robot's serial bus and every byte it reads from it, with the time, for
 * `ohmni bus convert LOG OUTPUT` and then `ohmni bus monitor --capture OUTPUT`.
 *
 * LOG FORMAT (the contract with the Python module ohmni_tb.capture.tbnode):
 *   UTF-8 text, one JSON object a line, each line ending in "\n", in the order the
 *   bytes were written or received:
 *     {"t":1718000000.000125,"dir":"tx","hex":"ffff09000432cc3b04"}
 *   "t"    when, in seconds since the Unix epoch, with microseconds. A monotonic clock
 *          (process.hrtime) anchored to the wall clock once, when the plugin loads: the
 *          times within one run of tb-node never go back.
 *   "dir"  "tx": bytes tb-node wrote to the port; "rx": bytes it received from it.
 *   "hex"  the bytes, two lowercase hex digits each, no separators.
 *
 * INSTALL: copy this file into tb-node's plugins directory, then restart tb-node:
 *   /data/data/com.ohmnilabs.telebot_rtc/files/plugins/
 *   setprop ctl.stop tb-node; setprop ctl.start tb-node
 * The log goes to LOG_PATH below (or to the path in $OHMNI_BUS_CAPTURE_LOG), appended to.
 *
 * REMOVE: delete the file from the plugins directory and restart tb-node. Without a
 * restart, the bot_shell command `bus_capture stop` puts tb-node's port back as it was
 * and closes the log; `bus_capture` alone reports what was logged.
 *
 * WHAT IT ASSUMES (tb-node's plugin API is public; its internals are not):
 *   - tb-node loads each .js file of its plugins directory when it starts and builds
 *     the exported class with its bot object: `new Plugin(botnode)`;
 *   - botnode._serial._sport is tb-node's open port, a node-serialport object: every
 *     byte tb-node sends (sendCustom, sendBatteryQuery, ...) goes through its
 *     write(data, ...), and every byte received comes out of it as a 'data' event.
 *     tb-node may open a new port object (botnode._serial.createSerial()): the plugin
 *     looks every second and follows it.
 * If an assumption does not hold, the plugin says so once on tb-node's console and
 * logs nothing; tb-node runs as before.
 *
 * WHAT IT GUARANTEES: tb-node's bytes and timing stay as they are. The wrapped write
 * calls the original with the same arguments and returns what it returns; what it
 * throws reaches tb-node as before (and those bytes, never sent, are not logged).
 * Received bytes are seen by wrapping the port's emit: no listener is added, so the
 * stream's mode does not change. The log is written in the background, a batch at a
 * time: a failed write is counted (its lines are lost) and logging carries on; lines
 * waiting for a slow disk beyond MAX_PENDING_BYTES, and everything past MAX_LOG_BYTES,
 * are dropped and counted. Nothing here throws into tb-node.
 */

var fs = require('fs');

var TAG = 'ohmni-bus-capture';
var LOG_PATH = process.env.OHMNI_BUS_CAPTURE_LOG ||
  '/data/data/com.ohmnilabs.telebot_rtc/files/ohmni-bus-capture.ndjson';
// The log stops growing here: days of tb-node's own polling (a few MB an hour).
var MAX_LOG_BYTES = 256 * 1024 * 1024;
// Lines waiting for the disk; beyond this new lines are dropped (and counted).
var MAX_PENDING_BYTES = 4 * 1024 * 1024;
// The log is written this often, or as soon as this much waits.
var FLUSH_MS = 200;
var FLUSH_BYTES = 64 * 1024;
// How often the plugin looks for tb-node's port (it may open a new one).
var FOLLOW_MS = 1000;
var BOT_SHELL = '/data/data/com.ohmnilabs.telebot_rtc/files/assets/node-files/bot_shell';

var hr0 = process.hrtime();
var wall0 = Date.now() / 1000;

function nowSeconds() {
  var d = process.hrtime(hr0);
  return wall0 + d[0] + d[1] / 1e9;
}

function toBuffer(data, encoding) {
  if (Buffer.isBuffer(data)) return data;
  if (typeof data === 'string') {
    return Buffer.from ? Buffer.from(data, encoding || 'utf8') : new Buffer(data, encoding || 'utf8');
  }
  // An array of byte values, or a typed array.
  return Buffer.from ? Buffer.from(data) : new Buffer(data);
}

function BusCapturePlugin(botnode) {
  if (!(this instanceof BusCapturePlugin)) return new BusCapturePlugin(botnode);
  var self = this;
  self._botnode = botnode;
  self._port = null;
  self._originalWrite = null;
  self._wrappedWrite = null;
  self._originalEmit = null;
  self._wrappedEmit = null;
  self._ownWrite = false;
  self._ownEmit = false;
  self._fd = null;
  self._opening = false;
  self._writing = false;
  self._pending = [];
  self._pendingBytes = 0;
  self._stopped = false;
  self._said = {};
  self.stats = {
    path: LOG_PATH, attached: false, ports: 0, tx_chunks: 0, rx_chunks: 0,
    tx_bytes: 0, rx_bytes: 0, lines: 0, log_bytes: 0, dropped_lines: 0,
    write_errors: 0, lost_lines: 0, errors: 0
  };
  self._flushTimer = setInterval(function () { self._flush(); }, FLUSH_MS);
  self._followTimer = setInterval(function () { self._follow(); }, FOLLOW_MS);
  [self._flushTimer, self._followTimer].forEach(function (timer) {
    if (timer && timer.unref) timer.unref();
  });
  self._addShellCommand();
  self._follow();
  console.log(TAG, 'loaded: logging the bus to', LOG_PATH);
}

// Say something on tb-node's console once per topic, so a broken assumption does not
// flood it.
BusCapturePlugin.prototype._sayOnce = function (topic, text) {
  if (this._said[topic]) return;
  this._said[topic] = true;
  console.log(TAG, text);
};

// Find tb-node's port; wrap a new one, let go of one that was replaced.
BusCapturePlugin.prototype._follow = function () {
  if (this._stopped) return;
  var serial = this._botnode && this._botnode._serial;
  var port = serial && serial._sport;
  if (port === this._port) return;
  this._release();
  if (!port || typeof port.write !== 'function' || typeof port.emit !== 'function') {
    this._sayOnce('no-port', 'no serial port at botnode._serial._sport yet: waiting');
    return;
  }
  this._wrap(port);
};

BusCapturePlugin.prototype._wrap = function (port) {
  var self = this;
  var originalWrite = port.write;
  var originalEmit = port.emit;
  var own = Object.prototype.hasOwnProperty;
  self._ownWrite = own.call(port, 'write');
  self._ownEmit = own.call(port, 'emit');
  self._wrappedWrite = function (data, encoding) {
    var t = nowSeconds();
    // Called first, outside any try: what it throws reaches tb-node untouched, and
    // bytes it refused are not logged.
    var result = originalWrite.apply(this, arguments);
    try {
      self._note('tx', toBuffer(data, typeof encoding === 'string' ? encoding : undefined), t);
    } catch (err) {
      self.stats.errors += 1;
    }
    return result;
  };
  self._wrappedEmit = function (event, chunk) {
    if (event === 'data') {
      try {
        self._note('rx', toBuffer(chunk), nowSeconds());
      } catch (err) {
        self.stats.errors += 1;
      }
    }
    return originalEmit.apply(this, arguments);
  };
  port.write = self._wrappedWrite;
  port.emit = self._wrappedEmit;
  self._port = port;
  self._originalWrite = originalWrite;
  self._originalEmit = originalEmit;
  self.stats.attached = true;
  self.stats.ports += 1;
  console.log(TAG, 'following tb-node\'s serial port');
};

// Put the port's own write and emit back (only where they are still ours: another
// plugin that wrapped them after us keeps its wrapper, and ours then only stops logging).
BusCapturePlugin.prototype._release = function () {
  var port = this._port;
  if (!port) return;
  restore(port, 'write', this._wrappedWrite, this._originalWrite, this._ownWrite);
  restore(port, 'emit', this._wrappedEmit, this._originalEmit, this._ownEmit);
  this._port = null;
  this.stats.attached = false;
};

function restore(port, name, wrapped, original, wasOwn) {
  if (port[name] !== wrapped) return;
  if (wasOwn) port[name] = original;
  else delete port[name];  // the prototype's method shows through again
}

BusCapturePlugin.prototype._note = function (dir, buffer, t) {
  if (this._stopped || this._port === null) return;
  if (dir === 'tx') {
    this.stats.tx_chunks += 1;
    this.stats.tx_bytes += buffer.length;
  } else {
    this.stats.rx_chunks += 1;
    this.stats.rx_bytes += buffer.length;
  }
  if (buffer.length === 0) return;
  var line = '{"t":' + t.toFixed(6) + ',"dir":"' + dir + '","hex":"' +
    buffer.toString('hex') + '"}\n';
  if (this._pendingBytes + line.length > MAX_PENDING_BYTES ||
      this.stats.log_bytes + this._pendingBytes + line.length > MAX_LOG_BYTES) {
    this.stats.dropped_lines += 1;
    this._sayOnce('dropped', 'log full or disk too slow: dropping lines (counted)');
    return;
  }
  this._pending.push(line);
  this._pendingBytes += line.length;
  if (this._pendingBytes >= FLUSH_BYTES) this._flush();
};

// Write what waits, one batch at a time, in the background.
BusCapturePlugin.prototype._flush = function (done) {
  var self = this;
  if (self._writing || self._opening) return;
  if (self._fd === null) {
    if (self._pending.length === 0) {
      if (done) done();
      return;
    }
    self._opening = true;
    fs.open(LOG_PATH, 'a', function (err, fd) {
      self._opening = false;
      if (err) {
        self.stats.write_errors += 1;
        self.stats.lost_lines += self._pending.length;
        self._pending = [];
        self._pendingBytes = 0;
        self._sayOnce('open', 'cannot open ' + LOG_PATH + ': ' + err.message +
          ' (lines lost are counted; tried again with the next lines)');
        if (done) done();
        return;
      }
      self._fd = fd;
      self._flush(done);
    });
    return;
  }
  if (self._pending.length === 0) {
    if (done) done();
    return;
  }
  var lines = self._pending.length;
  var buffer = toBuffer(self._pending.join(''));
  self._pending = [];
  self._pendingBytes = 0;
  self._writing = true;
  self._writeAll(buffer, 0, function (err) {
    self._writing = false;
    if (err) {
      self.stats.write_errors += 1;
      self.stats.lost_lines += lines;
      self._sayOnce('write', 'cannot write ' + LOG_PATH + ': ' + err.message +
        ' (lines lost are counted; logging goes on)');
    } else {
      self.stats.lines += lines;
      self.stats.log_bytes += buffer.length;
    }
    if (done || self._pendingBytes >= FLUSH_BYTES) self._flush(done);
  });
};

BusCapturePlugin.prototype._writeAll = function (buffer, offset, callback) {
  var self = this;
  fs.write(self._fd, buffer, offset, buffer.length - offset, null, function (err, written) {
    if (err) return callback(err);
    if (offset + written < buffer.length) return self._writeAll(buffer, offset + written, callback);
    callback(null);
  });
};

// Stop logging: tb-node's port as it was, the last lines written, the log closed.
BusCapturePlugin.prototype.stop = function (callback) {
  var self = this;
  if (self._stopped) {
    if (callback) callback();
    return;
  }
  self._release();
  self._stopped = true;
  clearInterval(self._flushTimer);
  clearInterval(self._followTimer);
  var finish = function () {
    if (self._writing || self._opening) return setTimeout(finish, 10);
    self._flush(function () {
      if (self._fd === null) {
        if (callback) callback();
        return;
      }
      var fd = self._fd;
      self._fd = null;
      fs.close(fd, function () {
        if (callback) callback();
      });
    });
  };
  finish();
};

// `bus_capture` on bot_shell reports; `bus_capture stop` stops logging. Skipped without
// bot_shell (the plugin works without it).
BusCapturePlugin.prototype._addShellCommand = function () {
  var self = this;
  var BotShell;
  try {
    BotShell = require(BOT_SHELL);
  } catch (err) {
    return;
  }
  if (!BotShell || !BotShell.prototype) return;
  BotShell.prototype.cmd_bus_capture = function (params) {
    var shell = this;
    var say = function (text) {
      if (typeof shell.log === 'function') shell.log(TAG, text);
      else console.log(TAG, text);
    };
    if (params && params[0] === 'stop') {
      self.stop(function () { say('stopped; ' + JSON.stringify(self.stats)); });
      return;
    }
    say(JSON.stringify(self.stats));
  };
};

module.exports = BusCapturePlugin;
