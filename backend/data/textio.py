"""Line-oriented text input with one-line errors naming the file and the line (pure helpers).

Used by every small text format vislam reads: KITTI ``calib.txt`` and ``times.txt``, the IMU
CSV, the ``--imu-T-cam`` matrix and TUM trajectories.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Iterator

from ..errors import InputError
from ..reading import read_regular_file
from .files import note_input


#: The largest text file read (a trajectory of ten million poses is ~0.7 GiB)
MAX_TEXT_BYTES = 2**30


def read_lines(path, missing: str = "file does not exist") -> list[str]:
    """The lines of a UTF-8 text file (a leading byte-order mark, as some editors write, is
    skipped); InputError naming it (``missing`` says what the file should hold). The file becomes an
    input of the run (``files.note_input``): no output may replace it."""
    note_input(path)
    if not os.path.lexists(path):
        raise InputError(f"{path}: {missing}")
    data = read_regular_file(path, MAX_TEXT_BYTES, "text file")
    try:
        return data.decode("utf-8-sig").splitlines()
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: cannot read as text: {' '.join(str(e).split())}") from None


def content_lines(lines: list[str]) -> Iterator[tuple[int, str]]:
    """(1-based line number, stripped text) of the lines that are neither blank nor ``#`` comments."""
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if text and not text.startswith("#"):
            yield number, text


def text_float(token: str) -> float:
    """``float(token)`` without Python's own literal syntax: the digit separator of ``1_3.17`` is
    no number in a data file (ValueError), so it is never read as 13.17."""
    if "_" in token:
        raise ValueError(f"not a number: {token!r}")
    return float(token)


def finite_numbers(tokens: list[str], where: str, what: str = "value") -> list[float]:
    """The tokens as finite floats; else InputError ``<where>: not a number: 'x'`` or
    ``<where>: non-finite <what> 'nan'``."""
    values = []
    for token in tokens:
        try:
            value = text_float(token)
        except ValueError:
            raise InputError(f"{where}: not a number: {token[:40]!r}") from None
        if not math.isfinite(value):
            raise InputError(f"{where}: non-finite {what} {token!r}")
        values.append(value)
    return values
