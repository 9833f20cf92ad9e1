"""A real MQTT broker for the tests: Eclipse Mosquitto on a free loopback port.

``broker`` lets anyone in; ``secure_broker`` needs a user name and password (a file made
by ``mosquitto_passwd -b``) and keeps each robot to its own prefix (an ACL: the robots
``a`` and ``b`` write under ``ohmni/<user>/``; ``fleet`` reads every robot and commands
them; ``intruder`` may log in but nothing more). Each test gets its own broker, stopped
after it whatever happened. Without ``mosquitto`` (``apt-get install mosquitto``; ``.ci/
run`` does) the tests that need it are skipped.

The async tests here keep real time: a broker in another process answers in real time,
and the virtual clock would run past its replies.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

#: Where Debian puts the broker (root's PATH has /usr/sbin; a user's may not).
_SEARCH = os.pathsep.join([os.environ.get("PATH", ""), "/usr/sbin", "/usr/local/sbin"])
MOSQUITTO = shutil.which("mosquitto", path=_SEARCH)
MOSQUITTO_PASSWD = shutil.which("mosquitto_passwd", path=_SEARCH)
#: The users of ``secure_broker`` and their passwords.
USERS = {
    "a": "robot-a-secret",
    "b": "robot-b-secret",
    "fleet": "fleet-secret",
    "intruder": "intruder-secret",
}
#: The ACL of ``secure_broker``: the example of docs/fleet.md.
ACL = """\
# The fleet's operators: every robot's state and availability, their replies, commands.
user fleet
topic read ohmni/+/state
topic read ohmni/+/availability
topic read ohmni/+/response/#
topic write ohmni/+/cmd/#
topic write ohmni/+/ha/#

# Every robot logs in with its robot_id as user name: its own prefix only.
pattern readwrite ohmni/%u/#
pattern write homeassistant/+/%u/#
"""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
        return port


@dataclass
class Mosquitto:
    """A broker process: :meth:`start`, :meth:`stop` (again and again, on the same port)."""

    config: Path
    port: int
    log: Path
    proc: subprocess.Popen[bytes] | None = field(default=None, repr=False)

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> None:
        assert MOSQUITTO is not None
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen(
                [MOSQUITTO, "-c", str(self.config)], stdout=log, stderr=subprocess.STDOUT
            )
        deadline = time.monotonic() + 10
        while True:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    self.stop()
                    raise AssertionError(
                        f"mosquitto did not start: {self.log.read_text(errors='replace')}"
                    ) from None
                time.sleep(0.02)

    def stop(self) -> None:
        proc, self.proc = self.proc, None
        if proc is None:
            return
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def _broker(directory: Path, *, secure: bool) -> Mosquitto:
    if MOSQUITTO is None or (secure and MOSQUITTO_PASSWD is None):
        pytest.skip("needs mosquitto (apt-get install mosquitto)")
    directory.mkdir(parents=True, exist_ok=True)
    port = free_port()
    # Started as root, mosquitto would become user "mosquitto", who cannot read this
    # test's files: it stays whoever runs the tests (no effect for any other user).
    user = pwd.getpwuid(os.getuid()).pw_name
    lines = [f"listener {port} 127.0.0.1", "persistence false", "log_type error", f"user {user}"]
    if secure:
        assert MOSQUITTO_PASSWD is not None
        passwords = directory / "passwords"
        passwords.touch(mode=0o600)
        for user, password in USERS.items():
            subprocess.run(
                [MOSQUITTO_PASSWD, "-b", str(passwords), user, password],
                check=True,
                capture_output=True,
            )
        acl = directory / "acl"
        acl.write_text(ACL, encoding="utf-8")
        lines += ["allow_anonymous false", f"password_file {passwords}", f"acl_file {acl}"]
    else:
        lines += ["allow_anonymous true"]
    config = directory / "mosquitto.conf"
    config.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return Mosquitto(config, port, directory / "mosquitto.log")


def _running(server: Mosquitto) -> Iterator[Mosquitto]:
    """``server`` started, and stopped after the test whatever happened."""
    server.start()
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def broker(tmp_path: Path) -> Iterator[Mosquitto]:
    """An anonymous broker on a free loopback port, stopped after the test."""
    yield from _running(_broker(tmp_path / "broker", secure=False))


@pytest.fixture
def secure_broker(tmp_path: Path) -> Iterator[Mosquitto]:
    """A broker with passwords (:data:`USERS`) and the robots' ACL (:data:`ACL`)."""
    yield from _running(_broker(tmp_path / "secure", secure=True))
