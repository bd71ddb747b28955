"""Progress on a terminal of unknown or zero size: plain lines, never silence."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import struct
import subprocess
import sys
import termios

import click
import pytest
from click.testing import CliRunner

from geocd.cli import common
from geocd.cli.common import add_common_options, session
from tests.cli.test_conventions import _dems


def _command() -> click.Command:
    @click.command()
    def stage_cmd():
        p = session().progress("stage")
        for i in range(11):
            p(i / 10, f"step {i}")
        p.close()
        click.echo(session().mode)

    return add_common_options(stage_cmd)


class _Tty:
    """A stream that says it is a terminal."""

    def isatty(self) -> bool:
        return True

    def fileno(self) -> int:
        return 2


@pytest.mark.parametrize(
    "size,env,fits",
    [
        ((0, 0), {}, False),  # a pty of size 0x0
        ((0, 40), {}, False),  # stty cols 0
        ((120, 40), {"COLUMNS": "0"}, False),
        ((120, 0), {}, False),
        ((120, 40), {}, True),
        ((120, 40), {"COLUMNS": "100"}, True),
    ],
)
def test_a_bar_needs_a_terminal_of_known_size(monkeypatch, size, env, fits):
    monkeypatch.setattr(common.os, "get_terminal_size", lambda fd=None: os.terminal_size(size))
    monkeypatch.delenv("COLUMNS", raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    assert common._bar_fits(_Tty()) is fits


def test_unknown_size_gets_a_bar_never():
    class NoFileno(_Tty):
        def fileno(self) -> int:
            raise OSError("no file descriptor")

    assert common._bar_fits(NoFileno()) is False


def test_auto_progress_on_a_zero_column_terminal_writes_lines(monkeypatch):
    monkeypatch.setattr(common, "_isatty", lambda stream: True)
    monkeypatch.setattr(common.os, "get_terminal_size", lambda fd=None: os.terminal_size((0, 0)))
    r = CliRunner().invoke(_command(), ["--progress", "auto"])
    assert r.exit_code == 0, r.output
    assert r.stdout.strip() == "lines"
    lines = [l for l in r.stderr.splitlines() if l.startswith("geocd: [")]
    assert len(lines) >= 10 and "stage 100% step 10" in lines[-1], r.stderr


def test_forced_bar_on_a_zero_column_terminal_writes_lines(monkeypatch):
    monkeypatch.setattr(common, "_isatty", lambda stream: True)
    monkeypatch.setattr(common.os, "get_terminal_size", lambda fd=None: os.terminal_size((0, 0)))
    r = CliRunner().invoke(_command(), ["--progress", "bar"])
    assert r.exit_code == 0 and r.stdout.strip() == "lines"
    assert "geocd: [" in r.stderr


def _read_all(fd: int, proc: subprocess.Popen) -> str:
    chunks = []
    while True:
        ready, _, _ = select.select([fd], [], [], 0.5)
        if ready:
            try:
                data = os.read(fd, 65536)
            except OSError:  # the child closed its end
                break
            if not data:
                break
            chunks.append(data)
        elif proc.poll() is not None:
            break
    return b"".join(chunks).decode("utf-8", "replace")


@pytest.mark.slow
def test_real_pty_of_size_zero_gets_progress_lines(tmp_path):
    """`geocd demdiff` with stderr on a pty whose size is 0x0 prints its progress as plain lines."""
    pa, pb = _dems(tmp_path)
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 0, 0, 0, 0))
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "geocd", "demdiff", pa.name, pb.name, "--no-plots"],
            cwd=tmp_path,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=slave,
            env=env,
        )
        os.close(slave)
        err = _read_all(master, proc)
        proc.wait(timeout=300)
    finally:
        os.close(master)
    assert proc.returncode == 0, err
    assert sum(1 for l in err.splitlines() if l.startswith("geocd: [")) >= 3, err
