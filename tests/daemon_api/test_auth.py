"""Who may connect: the token beyond loopback, browsers' origins, and the token file."""

from __future__ import annotations

import asyncio
import logging
import os
import stat
from pathlib import Path

import pytest
from typer.testing import CliRunner
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from ohmni_tb import Robot
from ohmni_tb.cli import app
from ohmni_tb.client import RobotClient
from ohmni_tb.daemon import auth
from ohmni_tb.daemon.server import RobotServer
from ohmni_tb.errors import ConfigError, TransportError

from ._serving import start_serving, stop_serving

TOKEN = "x" * 20 + "-a-test-token"


def test_a_new_token_file_is_made_readable_by_its_owner_only(tmp_path: Path) -> None:
    path = tmp_path / "ohmni" / "daemon-token"
    token = auth.load_or_create_token(path)
    assert len(token) >= 40
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    # The same token on every later start.
    assert auth.load_or_create_token(path) == token
    assert auth.load_or_create_token(tmp_path / "other") != token


def test_a_token_file_others_can_read_is_refused_with_the_fix(tmp_path: Path) -> None:
    path = tmp_path / "daemon-token"
    path.write_text(TOKEN)
    path.chmod(0o644)
    with pytest.raises(
        ConfigError, match=rf"readable by others \(mode 0644\): run `chmod 600 {path}`"
    ):
        auth.load_or_create_token(path)
    path.chmod(0o600)
    assert auth.load_or_create_token(path) == TOKEN


def test_a_short_token_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "daemon-token"
    path.write_text("short\n")
    path.chmod(0o600)
    with pytest.raises(ConfigError, match="5 characters: at least 16"):
        auth.read_token(path)


def test_the_default_token_file_is_in_the_users_config_dir(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path))
    assert auth.default_token_path() == tmp_path / "ohmni" / "daemon-token"


def test_the_token_is_read_from_the_header_or_the_query_and_compared_exactly() -> None:
    assert auth.presented_token("/", f"Bearer {TOKEN}") == TOKEN
    assert auth.presented_token(f"/?token={TOKEN}", None) == TOKEN
    assert auth.presented_token("/", "Basic abc") is None
    assert auth.presented_token("/", None) is None
    assert auth.check_token(TOKEN, TOKEN)
    assert not auth.check_token(TOKEN[:-1], TOKEN)
    assert not auth.check_token(TOKEN + "x", TOKEN)
    assert not auth.check_token(None, TOKEN)


async def test_with_a_token_no_token_or_a_wrong_one_is_refused_and_logged(
    robot: Robot, caplog: pytest.LogCaptureFixture
) -> None:
    async with RobotServer(robot, port=0, token=TOKEN) as server:
        with caplog.at_level(logging.WARNING, logger="ohmni_tb.daemon"):
            with pytest.raises(TransportError, match=r"refused the connection \(HTTP 401\)"):
                async with RobotClient.connect(server.url):
                    pass
            with pytest.raises(TransportError, match="needs its token"):
                async with RobotClient.connect(server.url, token=TOKEN[:-1] + "y"):
                    pass
        assert "refused: no token" in caplog.text
        assert "refused: a wrong token" in caplog.text
        assert server.clients == []
        # The right one, as a header or (a browser) in the URL.
        async with RobotClient.connect(server.url, token=TOKEN) as client:
            assert client.latest("robot_state") is not None
        async with connect(f"{server.url}/?token={TOKEN}") as ws:
            assert '"op":"hello"' in str(await ws.recv())


async def test_the_token_comes_from_the_environment_when_not_given(
    robot: Robot, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(auth.TOKEN_ENV, TOKEN)
    async with (
        RobotServer(robot, port=0, token=TOKEN) as server,
        RobotClient.connect(server.url) as client,
    ):
        assert client.hello.protocol >= 2


async def test_a_browser_from_an_origin_not_allowed_is_refused(
    robot: Robot, caplog: pytest.LogCaptureFixture
) -> None:
    async with RobotServer(robot, port=0, origins=("http://localhost:8080",)) as server:
        with (
            caplog.at_level(logging.WARNING, logger="ohmni_tb.daemon"),
            pytest.raises(InvalidStatus) as refused,
        ):
            async with connect(server.url, origin="http://evil.example"):  # type: ignore[arg-type]  # a str is an Origin
                pass
        assert refused.value.response.status_code == 403
        assert "origin 'http://evil.example' is not allowed" in caplog.text
        async with connect(server.url, origin="http://localhost:8080") as ws:  # type: ignore[arg-type]  # the same
            assert '"op":"hello"' in str(await ws.recv())
        # Programs send no Origin: they are not browsers.
        async with RobotClient.connect(server.url):
            pass


def test_ohmni_serve_beyond_loopback_makes_the_token_and_requires_it(tmp_path: Path) -> None:
    token_file = tmp_path / "daemon-token"
    proc, url = start_serving("--listen", "0.0.0.0:0", "--token-file", str(token_file))
    try:
        assert url.startswith("ws://0.0.0.0:")
        assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
        token = token_file.read_text().strip()
        local = url.replace("0.0.0.0", "127.0.0.1")

        async def use() -> None:
            with pytest.raises(TransportError, match="HTTP 401"):
                async with RobotClient.connect(local):
                    pass
            async with RobotClient.connect(local, token=token) as client:
                assert client.latest("robot_state") is not None

        asyncio.run(use())
    finally:
        log = stop_serving(proc)
    assert f"clients need the token in {token_file}" in log
    assert token not in log  # the secret itself is never printed


def test_ohmni_serve_refuses_a_token_file_others_can_read(tmp_path: Path) -> None:
    token_file = tmp_path / "daemon-token"
    token_file.write_text(TOKEN)
    os.chmod(token_file, 0o640)
    result = CliRunner().invoke(
        app, ["serve", "--port", "sim://", "--listen", "0.0.0.0:0", "--token-file", str(token_file)]
    )
    assert result.exit_code == 2
    assert "chmod 600" in result.output
