"""What a user sees in a terminal: ``vislam`` run under a pseudo-terminal, its screen read back."""

from __future__ import annotations

import fcntl
import os
import select
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pytest

from helpers import street_file

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a pseudo-terminal (Linux)")


def screen(argv: list[str], cwd: Path) -> tuple[int, str]:
    """(exit code, everything written to the terminal) of ``vislam ARGV`` with stderr and stdout on a
    pseudo-terminal, as in a shell (tqdm draws its bar there)."""
    main, child = os.openpty()
    fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))  # 40 rows, 120 columns
    proc = subprocess.Popen([sys.executable, "-m", "vislam.tools.cli", *argv], cwd=cwd, stdin=subprocess.DEVNULL,
                            stdout=child, stderr=child)
    os.close(child)
    chunks = []
    while True:
        ready, _, _ = select.select([main], [], [], 120)
        if not ready:
            proc.kill()
            raise AssertionError("no output for 120 s")
        try:
            data = os.read(main, 65536)
        except OSError:  # the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(main)
    return proc.wait(timeout=60), b"".join(chunks).decode("utf-8", "replace")


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory) -> Path:
    return street_file(tmp_path_factory.mktemp("screen"), 200)


def test_the_start_up_lines_and_the_progress_bar_keep_to_their_own_lines(scene_file, tmp_path):
    """The input, the decisions and the notes each start a line of their own; the bar appears once
    the filter steps, after the decisions, and never shares a line with them."""
    rc, text = screen(["run", str(scene_file), "--out", "o"], tmp_path)
    assert rc == 0, text
    lines = text.replace("\r\n", "\n").split("\n")
    decisions = [i for i, line in enumerate(lines) if "extrinsic:" in line or "pixel noise:" in line]
    assert len(decisions) == 2, text
    for i in decisions:
        shown = lines[i].split("\r")[-1]
        assert shown.startswith(("extrinsic:", "pixel noise:")), repr(lines[i])
        assert "filter:" not in lines[i], repr(lines[i])  # no bar drawn before the message on its line
    first_bar = next(i for i, line in enumerate(lines) if "filter:" in line and "step" in line)
    assert first_bar > max(decisions), text
    assert any("200/200" in line for line in lines), text


def test_every_argument_of_every_command_says_what_it_is():
    """``vislam CMD --help`` explains every argument, positional ones included; ``track --set``'s
    example is a tracker option, the only kind it reads."""
    import argparse

    from vislam.tools.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    silent = [f"{name} {action.option_strings or action.dest}" for name, sub in commands.items()
              for action in sub._actions
              if not isinstance(action, argparse._HelpAction) and not (action.help or "").strip()]
    assert not silent, silent
    track_set = next(a for a in commands["track"]._actions if "--set" in a.option_strings)
    assert "tracker." in track_set.help and "noise." not in track_set.help
