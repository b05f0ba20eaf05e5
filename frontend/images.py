"""Rectified stereo image sequences in the KITTI odometry layout.

A directory holds ``image_0/NNNNNN.png`` (left), ``image_1/NNNNNN.png`` (right, the same file
names), ``calib.txt`` with ``P0:`` and ``P1:`` rows (3x4 rectified projection matrices, 12 numbers
row-major; other rows such as ``P2:`` or ``Tr:`` are ignored) and ``times.txt`` (seconds, one a
line: at least one a frame, the first n for n frames). Both cameras share K (``P[:, :3]``); the
left one is the reference (``P0[:, 3] = 0``) and the right one sits
``baseline = -P1[0,3] / P1[0,0]`` metres along its x axis.

:func:`open_stereo_directory` checks the layout, calibration and time stamps and reads the first
pair (image size); frames are then read lazily, one pair at a time. Every problem raises
:class:`~backend.errors.InputError` with one line naming the file and what is wrong.
:func:`paired_frame_names`, :func:`stereo_intrinsics` and :func:`stereo_directory` serve the KITTI raw
layout too (:mod:`~vislam.frontend.raw_drive`).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from ..backend.errors import InputError
from ..backend.data.files import note_input
from ..backend.data.textio import content_lines, finite_numbers, read_lines

__all__ = ["StereoDirectory", "open_stereo_directory", "read_calibration", "read_times", "read_grey",
           "stereo_intrinsics", "paired_frame_names", "stereo_directory"]

LEFT_DIR, RIGHT_DIR = "image_0", "image_1"

#: Relative tolerance of "P0 and P1 have the same K" and of the zero translations.
_K_TOL = 1e-6


def read_calibration(path: Path) -> tuple[np.ndarray, float]:
    """(K (3,3), baseline (m)) from the ``P0:``/``P1:`` rows of a KITTI ``calib.txt``."""
    path = Path(path)
    lines = read_lines(path, "missing (need P0: and P1: rows)")
    rows: dict[str, np.ndarray] = {}
    for number, line in enumerate(lines, start=1):
        key, sep, values = line.partition(":")
        key = key.strip()
        if not sep or key not in ("P0", "P1"):
            continue
        if key in rows:
            raise InputError(f"{path}: line {number}: '{key}:' given twice")
        try:
            P = np.array(values.split(), dtype=np.float64)
        except ValueError:
            raise InputError(f"{path}: line {number}: '{key}:' has a value that is not a number") from None
        if P.shape != (12,):
            raise InputError(f"{path}: line {number}: '{key}:' needs 12 numbers (3x4 row-major), got {P.size}")
        if not np.isfinite(P).all():
            raise InputError(f"{path}: line {number}: '{key}:' has a non-finite value")
        rows[key] = P.reshape(3, 4)
    for key in ("P0", "P1"):
        if key not in rows:
            raise InputError(f"{path}: no '{key}:' row (need P0: and P1: 3x4 projection matrices)")
    return stereo_intrinsics(path, rows["P0"], rows["P1"])


def stereo_intrinsics(path: Path, P_left: np.ndarray, P_right: np.ndarray,
                      names: tuple[str, str] = ("P0", "P1")) -> tuple[np.ndarray, float]:
    """(K (3,3), baseline (m)) of a rectified pair from its 3x4 projection matrices.

    ``K = P_left[:, :3]``; ``baseline = -P_right[0,3] / P_right[0,0]``. InputError naming ``path``
    and the rows (``names``) unless K is a camera matrix shared by both, ``P_left[:, 3] = 0``,
    ``P_right[1:, 3] = 0`` and the baseline is finite and > 0.
    """
    left, right = names
    P0, P1 = P_left, P_right
    K = P0[:, :3].copy()
    scale = float(np.abs(K).max())
    if not (K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0 and np.array_equal(K[2], [0.0, 0.0, 1.0])):
        raise InputError(f"{path}: {left}[:, :3] is not a camera matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    if not np.allclose(P1[:, :3], K, rtol=0.0, atol=_K_TOL * scale):
        raise InputError(f"{path}: {left} and {right} disagree in K (P[:, :3]); the images must be rectified with one K")
    if np.abs(P0[:, 3]).max() > _K_TOL * scale:
        raise InputError(f"{path}: {left}[:, 3] must be 0 (the left camera is the reference), got {P0[:, 3].tolist()}")
    if np.abs(P1[1:, 3]).max() > _K_TOL * scale:
        raise InputError(f"{path}: {right}[1:, 3] must be 0 (a horizontal rectified baseline), got {P1[1:, 3].tolist()}")
    with np.errstate(over="ignore"):
        baseline = float(-P1[0, 3] / P1[0, 0])
    if not (np.isfinite(baseline) and baseline > 0):
        raise InputError(f"{path}: baseline -{right}[0,3]/{right}[0,0] = {baseline:.6g} m must be a finite number > 0 "
                         "(right camera to the right)")
    return K, baseline


def read_times(path: Path, n_frames: int) -> np.ndarray:
    """(n_frames,) strictly increasing seconds: the first ``n_frames`` stamps of ``times.txt`` (one
    number a line; lines after them are not read, as with a longer IMU CSV)."""
    path = Path(path)
    values, numbers = [], []
    for number, text in content_lines(read_lines(path, "missing (need one time stamp a frame)")):
        if len(values) == n_frames:
            break
        values.extend(finite_numbers([text], f"{path}: line {number}", "time stamp"))
        numbers.append(number)
    if len(values) < n_frames:
        raise InputError(f"{path}: {len(values)} time stamps for {n_frames} frames (need at least one a frame)")
    t = np.array(values, dtype=np.float64)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(
            f"{path}: line {numbers[i]}: time stamps not strictly increasing ({t[i]:.9g} after {t[i - 1]:.9g})"
        )
    return t


#: The most pixels a frame may have (an 8K camera has 33 million): a PNG of a few kB can declare
#: 50000 x 50000 pixels, gigabytes once decoded
MAX_PIXELS = 100_000_000


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG's header (its IHDR chunk) without decoding it; None when the file
    is not a PNG (the decoder then says what it is)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def read_grey(path: Path) -> np.ndarray:
    """An 8-bit grey image (colour is converted); InputError if it cannot be decoded or declares
    more than :data:`MAX_PIXELS` pixels (checked from its header before decoding)."""
    size = png_size(path)
    if size is not None and size[0] * size[1] > MAX_PIXELS:
        raise InputError(f"{path}: declares {size[0]}x{size[1]} pixels, more than the {MAX_PIXELS:,} a frame may have "
                         f"({size[0] * size[1] / 2**30:.1f} GiB decoded)")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        why = "missing" if not Path(path).exists() else "unreadable (not a decodable image)"
        raise InputError(f"{path}: {why}")
    if img.dtype != np.uint8:
        raise InputError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    return img


@dataclass(frozen=True, eq=False)
class StereoDirectory:
    """A checked KITTI-layout directory; images are read on demand."""

    root: Path
    left_paths: tuple[Path, ...]
    right_paths: tuple[Path, ...]
    times: np.ndarray  # (n,) seconds, strictly increasing
    K: np.ndarray  # (3,3)
    baseline: float  # m
    image_size: tuple[int, int]  # (width, height) of every image

    def __len__(self) -> int:
        return len(self.left_paths)

    def read(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """(left, right) grey images of frame ``index``; InputError if unreadable or mis-sized."""
        left, right = read_grey(self.left_paths[index]), read_grey(self.right_paths[index])
        w, h = self.image_size
        for path, img in ((self.left_paths[index], left), (self.right_paths[index], right)):
            if img.shape != (h, w):
                raise InputError(
                    f"{path}: size {img.shape[1]}x{img.shape[0]} differs from {w}x{h} "
                    f"(the first left image {self.left_paths[0].name})"
                )
        return left, right

    def frames(self, start: int = 0, stop: int | None = None, prefetch: bool = True) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """Yield (index, left, right) for frames ``start..stop-1``; with ``prefetch`` the next pair
        is decoded on a worker thread while the caller works on this one (two pairs in memory)."""
        indices = range(start, len(self) if stop is None else min(stop, len(self)))
        if not prefetch:
            for i in indices:
                yield (i, *self.read(i))
            return
        with ThreadPoolExecutor(max_workers=1, thread_name_prefix="vislam-images") as pool:
            pending = pool.submit(self.read, indices[0]) if len(indices) else None
            for n, i in enumerate(indices):
                left, right = pending.result()
                pending = pool.submit(self.read, indices[n + 1]) if n + 1 < len(indices) else None
                yield i, left, right


def _png_names(folder: Path, layout: str) -> list[str]:
    if not folder.is_dir():
        what = "not a directory" if folder.exists() else "missing directory"
        raise InputError(f"{folder}: {what} ({layout})")
    return sorted((p.name for p in folder.iterdir() if p.suffix.lower() == ".png" and not p.name.startswith(".")),
                  key=frame_order)


def frame_order(name: str) -> tuple:
    """The sort key of a frame's file name: by the number of a name made of digits (``2.png`` before
    ``10.png``, as a recorder numbers frames without padding; ``000002.png`` as KITTI pads them),
    after them other names in text order."""
    stem = name.rsplit(".", 1)[0]
    return (0, int(stem), name) if stem.isascii() and stem.isdigit() else (1, 0, name)


def paired_frame_names(root: Path, left: str, right: str, layout: str) -> list[str]:
    """The .png names of ``root/left`` in frame order (:func:`frame_order`; at least 2), each with a
    right image of the same name in ``root/right``; InputError naming the folder otherwise
    (``layout`` describes the expected one)."""
    left_names = _png_names(root / left, layout)
    right_names = _png_names(root / right, layout)
    if not left_names:
        raise InputError(f"{root / left}: empty sequence (no .png frames)")
    if len(left_names) < 2:
        raise InputError(f"{root / left}: one frame ({left_names[0]}); a sequence needs at least 2 (one step of motion)")
    if len(left_names) != len(right_names):
        raise InputError(
            f"{root / right}: {len(right_names)} frames but {left}/ has {len(left_names)} (need one right image per left image)"
        )
    if left_names != right_names:
        name = next(a for a, b in zip(left_names, right_names) if a != b)
        raise InputError(f"{root / right}: no {name} to pair with {left}/{name} (file names must match)")
    return left_names


def stereo_directory(root: Path, left: str, right: str, names: list[str], times: np.ndarray, K: np.ndarray,
                     baseline: float) -> StereoDirectory:
    """The :class:`StereoDirectory` of frames ``names`` in ``root/left`` and ``root/right``, after
    reading the first pair (its size is every frame's; InputError if left and right differ). Both
    folders become inputs of the run, read whole (``files.note_input``)."""
    note_input(root / left, contents=True)
    note_input(root / right, contents=True)
    left0 = read_grey(root / left / names[0])
    right0 = read_grey(root / right / names[0])
    if left0.shape != right0.shape:
        raise InputError(
            f"{root / right / names[0]}: size {right0.shape[1]}x{right0.shape[0]} differs from "
            f"the left image's {left0.shape[1]}x{left0.shape[0]}"
        )
    return StereoDirectory(
        root=root,
        left_paths=tuple(root / left / n for n in names),
        right_paths=tuple(root / right / n for n in names),
        times=times,
        K=K,
        baseline=baseline,
        image_size=(int(left0.shape[1]), int(left0.shape[0])),
    )


def open_stereo_directory(path) -> StereoDirectory:
    """Check a KITTI-layout directory (folders, equal frame lists, calib.txt, times.txt, first pair)."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"{root}: {'not a directory' if root.exists() else 'missing directory'}")
    layout = f"KITTI layout: {LEFT_DIR}/ left and {RIGHT_DIR}/ right .png frames"
    names = paired_frame_names(root, LEFT_DIR, RIGHT_DIR, layout)
    K, baseline = read_calibration(root / "calib.txt")
    times = read_times(root / "times.txt", len(names))
    return stereo_directory(root, LEFT_DIR, RIGHT_DIR, names, times, K, baseline)
