"""Files that are not what ``ohmni replay`` and ``ohmni bus monitor --capture`` expect:
cut to the magic bytes, bit-flipped, a zstd bomb, ``/dev/zero``, a FIFO. Each ends in
one line on stderr naming the file and what is wrong, exit code 1, in bounded memory
and without waiting on the file: where memory or a wait is at stake (the bombs, the
endless device, the pipe), the command runs in its own process under a 1 GiB data limit
and a timeout; the others in this process."""

from __future__ import annotations

import os
import resource
import struct
import subprocess
import sys
from collections.abc import Callable
from io import BytesIO
from pathlib import Path

import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import (
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Schema,
)
from mcap.writer import CompressionType, Writer
from typer.testing import CliRunner

from ohmni_tb.cli import app
from ohmni_tb.foxglove.record import RAW_TOPICS
from ohmni_tb.protocol import Command, Packet, encode_packet

MAGIC = b"\x89MCAP0\r\n"
#: What a command may take: ample for a 64 MiB chunk, far below the 4 GiB a bomb asks.
DATA_LIMIT = 1 << 30
BOMB_BYTES = 4 << 30
#: One bus packet (the left drive's firmware tag read), as ``ohmni record --raw`` writes it.
PACKET = (
    b'{"data":"%s"}' % encode_packet(Packet(0, Command.EEP_READ, b"\xf1\x10")).hex(" ").encode()
)
TIMEOUT_S = 60.0


def _limited() -> None:
    resource.setrlimit(resource.RLIMIT_DATA, (DATA_LIMIT, DATA_LIMIT))


def in_process(*args: str) -> tuple[int, str]:
    """``ohmni ARGS`` in this process (typer's CliRunner): exit code and stderr."""
    result = CliRunner().invoke(app, list(args), env={"COLUMNS": "200"})
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result.exit_code, result.stderr


def ohmni(*args: str) -> tuple[int, str]:
    """``ohmni ARGS`` in its own process, its data limited; exit code and stderr."""
    proc = subprocess.run(
        [sys.executable, "-m", "ohmni_tb", *args],
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        preexec_fn=_limited,  # only setrlimit, before exec
        check=False,
        env={**os.environ, "COLUMNS": "200"},
    )
    return proc.returncode, proc.stderr


def records(*items: McapRecord) -> bytes:
    builder = RecordBuilder()
    for item in items:
        item.write(builder)
    return bytes(builder.end())  # type: ignore[no-untyped-call]  # mcap: no hints here


def written(compression: CompressionType, count: int = 50) -> bytes:
    """A raw-bus recording as the mcap writer makes it: chunks, CRCs and an index."""
    out = BytesIO()
    writer = Writer(out, compression=compression)
    writer.start()
    schema = writer.register_schema("raw", "jsonschema", b"{}")
    channel = writer.register_channel(RAW_TOPICS[0], "json", schema)
    for i in range(count):
        writer.add_message(channel, log_time=i * 10**6, data=PACKET, publish_time=i * 10**6)
    writer.finish()  # type: ignore[no-untyped-call]  # mcap: no hints here
    return out.getvalue()


def flipped(data: bytes, marker: bytes) -> bytes:
    """``data`` with the lowest bit of the second byte of the first ``marker`` flipped."""
    at = data.index(marker) + 1
    return data[:at] + bytes([data[at] ^ 0x01]) + data[at + 1 :]


def zstd_rle_frame(size: int) -> bytes:
    """A valid zstd frame of ``size`` zero bytes, declared in its header: RLE blocks of
    128 KiB, 4 bytes each (131 kB for 4 GiB), built without compressing anything."""
    block = 128 << 10
    frame = struct.pack("<IBBQ", 0xFD2FB528, 0xC0, 7 << 3, size)  # 8-byte size, 128 KiB window
    blocks = [((block << 3) | (1 << 1)).to_bytes(3, "little") + b"\0"] * (size // block)
    last = (int.from_bytes(blocks[-1][:3], "little") | 1).to_bytes(3, "little") + b"\0"
    return frame + b"".join(blocks[:-1]) + last


def with_chunk(chunk: Chunk) -> bytes:
    """A recording of one chunk, after its schema and channel, without an index."""
    schema = Schema(id=1, name="raw", encoding="jsonschema", data=b"{}")
    channel = Channel(id=1, topic=RAW_TOPICS[0], message_encoding="json", schema_id=1, metadata={})
    body = records(Header(profile="", library="test"), schema, channel, chunk, DataEnd(0))
    return MAGIC + body + records(Footer(0, 0, 0)) + MAGIC


def bomb(declared: int) -> bytes:
    """A chunk of 4 GiB of zeros compressed to 131 kB, declaring ``declared`` bytes."""
    return with_chunk(
        Chunk(
            compression="zstd",
            data=zstd_rle_frame(BOMB_BYTES),
            message_start_time=0,
            message_end_time=0,
            uncompressed_crc=0,
            uncompressed_size=declared,
        )
    )


def fifo(tmp_path: Path) -> Path:
    if not hasattr(os, "mkfifo"):
        pytest.skip("needs named pipes")
    path = tmp_path / "pipe.mcap"
    os.mkfifo(path)
    return path


def file_of(data: bytes) -> Callable[[Path], Path]:
    def make(tmp_path: Path) -> Path:
        path = tmp_path / "hostile.mcap"
        path.write_bytes(data)
        return path

    return make


#: name: (makes the file, what the error line says)
FILES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "magic only": (file_of(MAGIC), "is not an MCAP recording: it ends after 8 bytes"),
    "zstd chunk bit-flipped": (
        file_of(flipped(written(CompressionType.ZSTD), b"\x28\xb5\x2f\xfd")),
        "does not decompress (zstd",
    ),
    "plain chunk bit-flipped": (
        # "f1 10" becomes "f0 10": still hex, so only the CRC tells.
        file_of(flipped(written(CompressionType.NONE), b"f1 10")),
        "fails its CRC check",
    ),
    "zstd bomb": (file_of(bomb(BOMB_BYTES)), "declares 4294967296 bytes uncompressed: at most"),
    "zstd bomb in a small chunk": (file_of(bomb(1 << 20)), "its zstd frame 4294967296"),
    "/dev/zero": (lambda _: Path("/dev/zero"), "is a character device, not a regular file"),
    "FIFO": (fifo, "is a named pipe (FIFO), not a regular file"),
}
COMMANDS = {
    "replay": ("replay", "{}", "--linger", "0", "--foxglove", "127.0.0.1:0"),
    "bus monitor": ("bus", "monitor", "--capture", "{}", "--quiet"),
}
#: The files whose danger is memory or waiting: read in a process of their own, limited.
OWN_PROCESS = frozenset({"zstd bomb", "zstd bomb in a small chunk", "/dev/zero", "FIFO"})


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX files and limits")
@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("name", FILES)
def test_a_hostile_file_is_one_line_and_exit_1(tmp_path: Path, command: str, name: str) -> None:
    make, says = FILES[name]
    path = make(tmp_path)
    if not path.exists():
        pytest.skip(f"no {path}")
    run = ohmni if name in OWN_PROCESS else in_process
    code, err = run(*(arg.format(path) for arg in COMMANDS[command]))
    assert code == 1, err
    assert "Traceback" not in err
    (line,) = err.strip().splitlines()
    assert line.startswith("error: ")
    assert str(path) in line
    assert says in line


def test_a_cut_recording_is_decoded_up_to_where_it_ends(tmp_path: Path) -> None:
    data = written(CompressionType.ZSTD, count=5)
    path = tmp_path / "cut.mcap"
    # Cut inside the data end record, after the chunk: the index and footer are gone.
    end = data.index(records(DataEnd(0))[:1] + struct.pack("<Q", 4)) + 3
    path.write_bytes(data[:end])
    result = CliRunner().invoke(app, ["bus", "monitor", "--capture", str(path), "--json"])
    assert result.exit_code == 1, result.output
    events = result.stdout.splitlines()
    assert len(events) == 5  # every packet of the chunk, then the error
    assert "EEP_READ" in events[0]
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith(f"error: {path}: the file ends inside the record at byte")
    assert "cut short" in line


def test_a_channel_the_app_cannot_take_is_one_line(tmp_path: Path) -> None:
    out = BytesIO()
    writer = Writer(out)
    writer.start()
    channel = writer.register_channel("/camera", "protobuf", 0)  # protobuf without a schema
    writer.add_message(channel, log_time=0, data=b"\x08\x01", publish_time=0)
    writer.finish()  # type: ignore[no-untyped-call]  # mcap: no hints here
    path = tmp_path / "schemaless.mcap"
    path.write_bytes(out.getvalue())
    code, err = in_process(*(arg.format(path) for arg in COMMANDS["replay"]))
    assert code == 1, err
    assert "Traceback" not in err
    (line,) = err.strip().splitlines()
    assert line.startswith(f"error: {path}: channel '/camera' (protobuf) cannot be served")
