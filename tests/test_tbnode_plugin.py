"""The tb-node plugin the package ships (``ohmni_tb/capture/tbnode_plugin.js``): in the
wheel, valid JavaScript, writing the log format the Python reader reads, and harmless
to tb-node. Run under Node.js when it is installed, with a stand-in for tb-node's bot
object and its serial port."""

from __future__ import annotations

import fnmatch
import json
import re
import shutil
import subprocess
import tomllib
from pathlib import Path
from typing import Any

import pytest

import ohmni_tb
from ohmni_tb.capture import tbnode
from ohmni_tb.capture.tbnode import FIELDS, RX, TX, LogReader, parse_record, plugin_source

ROOT = Path(__file__).resolve().parent.parent
PLUGIN = Path(tbnode.__file__).with_name(tbnode.PLUGIN_FILE)
NODE = shutil.which("node") or shutil.which("nodejs")
needs_node = pytest.mark.skipif(NODE is None, reason="Node.js is not installed (which node)")


def test_the_plugin_ships_as_package_data() -> None:
    assert PLUGIN.is_file()
    assert plugin_source() == PLUGIN.read_text(encoding="utf-8")
    # setuptools puts in the wheel and the sdist what package-data names.
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    patterns = config["tool"]["setuptools"]["package-data"]["ohmni_tb"]
    inside = PLUGIN.relative_to(Path(ohmni_tb.__file__).parent).as_posix()
    assert any(fnmatch.fnmatch(inside, pattern) for pattern in patterns), patterns


def test_the_plugin_header_and_code_name_the_readers_fields() -> None:
    source = plugin_source()
    header = source[source.index("LOG FORMAT") : source.index("INSTALL")]
    # The keys the header documents, and the ones the code writes, are the reader's.
    assert re.findall(r'^ \*   "(\w+)" ', header, re.M) == list(FIELDS)
    written = re.findall(r'"(\w+)":', source[source.index("var line = ") :].split(";")[0])
    assert written == list(FIELDS)
    assert f'"{TX}":' in header
    assert f'"{RX}":' in header
    # The header's example is a record the reader takes.
    (example,) = re.findall(r"^ \*     (\{.*\})$", header, re.M)
    record = parse_record(example, 1)
    assert record.sent
    assert record.data == bytes.fromhex("ffff09000432cc3b04")


@needs_node
def test_the_plugin_is_valid_javascript() -> None:
    assert NODE is not None
    result = subprocess.run(
        [NODE, "--check", str(PLUGIN)], capture_output=True, text=True, timeout=30, check=False
    )
    assert result.returncode == 0, result.stderr


# A stand-in for tb-node: a node-serialport-like port (write on the prototype, 'data'
# events), the bot object holding it, the plugin built the way tb-node builds plugins.
_HARNESS = r"""
'use strict';
var EventEmitter = require('events');
var util = require('util');
function Port(failWrites) {
  EventEmitter.call(this);
  this.written = [];
  this.failWrites = failWrites;
}
util.inherits(Port, EventEmitter);
Port.prototype.write = function (data, callback) {
  if (this.failWrites) throw new Error('port is closed');
  this.written.push(Buffer.from(data).toString('hex'));
  if (callback) callback(null);
  return 'drained';
};
var scenario = JSON.parse(process.argv[3]);
var Plugin = require(process.argv[2]);
var port = new Port(false);
var botnode = { _serial: { _sport: port } };
var seen = [];
port.on('data', function (chunk) { seen.push(chunk.toString('hex')); });
var plugin = new Plugin(botnode);
var out = { returns: [], thrown: [] };
scenario.steps.forEach(function (step) {
  if (step[0] === 'write') {
    out.returns.push(port.write(step[1] === 'array' ? step[2] : Buffer.from(step[2], 'hex')));
  } else if (step[0] === 'data') port.emit('data', Buffer.from(step[1], 'hex'));
  else if (step[0] === 'newport') {
    // tb-node opens a new port object: the plugin follows it.
    var old = port;
    port = new Port(step[1]);
    port.on('data', function (chunk) { seen.push(chunk.toString('hex')); });
    botnode._serial._sport = port;
    plugin._follow();
    out.oldRestored = !Object.prototype.hasOwnProperty.call(old, 'write') &&
      !Object.prototype.hasOwnProperty.call(old, 'emit');
    old.write(Buffer.from('ee', 'hex'));  // the old port is not logged any more
  } else if (step[0] === 'writefails') {
    try { port.write(Buffer.from(step[1], 'hex')); } catch (err) { out.thrown.push(err.message); }
  }
});
plugin.stop(function () {
  out.stats = plugin.stats;
  out.written = port.written;
  out.seen = seen;
  out.restored = !Object.prototype.hasOwnProperty.call(port, 'write') &&
    !Object.prototype.hasOwnProperty.call(port, 'emit');
  console.log(JSON.stringify(out));
});
"""


def _run_plugin(tmp_path: Path, steps: list[list[Any]], log: Path) -> dict[str, Any]:
    assert NODE is not None
    harness = tmp_path / "harness.js"
    harness.write_text(_HARNESS, encoding="utf-8")
    result = subprocess.run(
        [NODE, str(harness), str(PLUGIN), json.dumps({"steps": steps})],
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
        env={"OHMNI_BUS_CAPTURE_LOG": str(log), "PATH": "/usr/bin:/bin"},
    )
    assert result.returncode == 0, result.stderr
    out: dict[str, Any] = json.loads(result.stdout.splitlines()[-1])
    return out


@needs_node
def test_the_plugin_logs_what_tb_node_writes_and_reads_and_changes_nothing(
    tmp_path: Path,
) -> None:
    log = tmp_path / "capture.ndjson"
    request = "ffff09000432cc3b04"
    reply = "ffff0f00447c823b04393000000000"
    out = _run_plugin(
        tmp_path,
        [
            ["write", "buffer", request],
            ["data", reply[:10]],
            ["data", reply[10:]],
            ["write", "array", [0xFF, 0xFF, 0x07, 0xFD, 0x09, 0xF2, 0x0C]],
        ],
        log,
    )
    # tb-node's side: the same bytes went out, the same return values came back, its own
    # listener got every chunk, and the port is as it was once the plugin stopped.
    assert out["written"] == [request, "ffff07fd09f20c"]
    assert out["returns"] == ["drained", "drained"]
    assert out["seen"] == [reply[:10], reply[10:]]
    assert out["restored"] is True
    # The log: every chunk, in order, read back by the Python reader.
    reader = LogReader()
    records = reader.feed(log.read_bytes()) + reader.finish()
    assert reader.summary.skipped == 0
    assert [(r.sent, r.data.hex()) for r in records] == [
        (True, request),
        (False, reply[:10]),
        (False, reply[10:]),
        (True, "ffff07fd09f20c"),
    ]
    times = [r.t_s for r in records]
    assert times == sorted(times)
    assert times[0] > 1.5e9  # Unix time
    assert reader.summary.span_s < 5.0
    assert (reader.summary.tx_packets, reader.summary.rx_packets) == (2, 1)
    assert out["stats"]["lines"] == 4
    assert out["stats"]["write_errors"] == 0


@needs_node
def test_the_plugin_follows_a_new_port_and_passes_write_errors_on(tmp_path: Path) -> None:
    log = tmp_path / "capture.ndjson"
    out = _run_plugin(
        tmp_path,
        [["write", "buffer", "aa"], ["newport", True], ["writefails", "bb"], ["data", "cc"]],
        log,
    )
    assert out["oldRestored"] is True
    assert out["thrown"] == ["port is closed"]  # tb-node sees its port's error as before
    assert out["stats"]["ports"] == 2
    lines = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
    # Not the old port's "ee": it is no longer tb-node's; not "bb": the port refused it.
    assert [(line["dir"], line["hex"]) for line in lines] == [(TX, "aa"), (RX, "cc")]


@needs_node
def test_a_log_that_cannot_be_written_is_counted_and_tb_node_goes_on(tmp_path: Path) -> None:
    log = tmp_path / "no-such-directory" / "capture.ndjson"
    out = _run_plugin(tmp_path, [["write", "buffer", "ffff07fd09f20c"], ["data", "aa"]], log)
    assert out["written"] == ["ffff07fd09f20c"]
    assert out["seen"] == ["aa"]
    assert out["stats"]["write_errors"] == 1
    assert out["stats"]["lost_lines"] == 2
    assert out["stats"]["lines"] == 0
    assert not log.parent.exists()
