"""Debug pictures of the tracker, one PNG a frame.

A caption band on top says the frame, its tracks and what the marks mean. The left image (below
it) shows every emitted track as a dot with its tail (its last ``tail`` left positions); the right
image (below that) shows the matched right pixel and, along the row, a line from the left pixel's
column to it (the disparity). Colours are per id. Each file is written through ``atomic_write`` (a
temporary name, then a rename, never onto an input of the run), so a reader never sees half a
picture.
"""

from __future__ import annotations

import os
from collections import deque
from pathlib import Path

import cv2
import numpy as np

from ..backend.data.files import atomic_write, check_not_an_input
from ..backend.errors import InputError, OutputError

__all__ = ["TrackDrawer", "check_draw_dir"]


def _colour(track_id: int) -> tuple[int, int, int]:
    """A bright BGR colour that depends only on the id."""
    hue = (track_id * 47) % 180
    bgr = cv2.cvtColor(np.array([[[hue, 220, 255]]], np.uint8), cv2.COLOR_HSV2BGR)[0, 0]
    return int(bgr[0]), int(bgr[1]), int(bgr[2])


def _point(p) -> tuple[int, int]:
    return int(round(float(p[0]))), int(round(float(p[1])))


def write_png_atomic(path: Path, image: np.ndarray) -> None:
    """Encode ``image`` as PNG and write it to ``path`` through ``atomic_write`` (a temporary name,
    then a rename; never onto an input of the run)."""
    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OutputError(f"{path}: PNG encoding failed")
    with atomic_write(path) as tmp:
        tmp.write_bytes(data.tobytes())


def check_draw_dir(out_dir, replace_files: bool = True) -> Path:
    """``out_dir`` as a Path if it is a writable directory or can be made one (its nearest existing
    ancestor is a writable directory), and not an input of the run or inside one (OutputError);
    InputError naming it otherwise. Without ``replace_files`` an existing directory must hold no
    file (``--force`` allows it). Creates nothing."""
    out_dir = Path(out_dir)
    check_not_an_input(out_dir)
    if not replace_files and out_dir.is_dir() and any(p.is_file() for p in out_dir.iterdir()):
        raise OutputError(f"{out_dir}: --draw directory exists and holds files; use --force to write the frame "
                          "pictures into it")
    for path in (out_dir, *out_dir.parents):
        if path.exists():
            if not path.is_dir():
                what = "is not a directory" if path == out_dir else f"cannot be created: {path} is not a directory"
                raise InputError(f"{out_dir}: {what} (--draw needs a directory for the frame pictures)")
            if not os.access(path, os.W_OK | os.X_OK):
                what = "is not writable" if path == out_dir else f"cannot be created: {path} is not writable"
                raise InputError(f"{out_dir}: {what} (--draw needs a directory for the frame pictures)")
            break
    return out_dir


#: Pixel rows of the caption band above each picture (two lines of text)
CAPTION_HEIGHT = 42


class TrackDrawer:
    """Draws frames into ``out_dir`` (created if missing; InputError naming it when that fails);
    call :meth:`draw` once per frame, in order."""

    def __init__(self, out_dir, tail: int = 10) -> None:
        self.out_dir = check_draw_dir(out_dir)
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"{self.out_dir}: cannot create the --draw directory: "
                             f"{' '.join(str(exc.strerror or exc).split())}") from None
        self.tail = int(tail)
        self._history: dict[int, deque] = {}

    def render(self, index: int, left: np.ndarray, right: np.ndarray, ids: np.ndarray, pixels: np.ndarray) -> np.ndarray:
        """The picture (CAPTION_HEIGHT + 2H, W, 3) BGR of frame ``index``: the caption band, the left
        image, the right image; also updates the tails."""
        alive = set(int(i) for i in ids)
        self._history = {i: h for i, h in self._history.items() if i in alive}
        top = cv2.cvtColor(left, cv2.COLOR_GRAY2BGR)
        bottom = cv2.cvtColor(right, cv2.COLOR_GRAY2BGR)
        for track_id, (uL, vL, uR, vR) in zip(ids.tolist(), pixels):
            history = self._history.setdefault(track_id, deque(maxlen=self.tail))
            history.append((uL, vL))
            colour = _colour(track_id)
            if len(history) > 1:
                cv2.polylines(top, [np.round(np.array(history)).astype(np.int32)], False, colour, 1, cv2.LINE_AA)
            cv2.circle(top, _point((uL, vL)), 2, colour, -1, cv2.LINE_AA)
            cv2.line(bottom, _point((uL, vR)), _point((uR, vR)), colour, 1, cv2.LINE_AA)
            cv2.circle(bottom, _point((uR, vR)), 2, colour, -1, cv2.LINE_AA)
        return np.vstack([self.caption(index, len(ids), left.shape[1]), top, bottom])

    def caption(self, index: int, tracks: int, width: int) -> np.ndarray:
        """The band above the pair (:data:`CAPTION_HEIGHT`, width, 3): white text on dark grey, the
        frame, its tracks and what the marks mean, readable over any image."""
        band = np.full((CAPTION_HEIGHT, width, 3), 40, np.uint8)
        lines = (f"frame {index}   tracks {tracks}",
                 f"top: left image, a dot per track, its last {self.tail} positions as a tail;  "
                 "bottom: right image, the match, a line from the left column (disparity)")
        for row, text in enumerate(lines):
            cv2.putText(band, text, (8, 16 + 18 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1,
                        cv2.LINE_AA)
        return band

    def draw(self, index: int, left: np.ndarray, right: np.ndarray, ids: np.ndarray, pixels: np.ndarray) -> Path:
        """Render frame ``index`` and write it as ``out_dir/NNNNNN.png``; returns the path."""
        path = self.out_dir / f"{index:06d}.png"
        write_png_atomic(path, self.render(index, left, right, ids, pixels))
        return path
