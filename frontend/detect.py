"""Corner candidates for new tracks: Shi-Tomasi on the half-size image, ranked per grid cell.

One ``cv2.goodFeaturesToTrackWithQuality`` call on the image shrunk by ``cv2.pyrDown`` (a
quarter of the pixels, and corners of a slightly coarser scale, which track better under motion)
returns every local maximum of the minimum-eigenvalue response with its strength; the ``grid``
then keeps, per cell, the corners at least ``quality`` times as strong as the cell's strongest
(so a dim cell still gets its own best corners) and above an absolute floor (so flat sky or
sensor noise gets none). :func:`select` picks among the candidates the ones to track, emptiest
cell first. Positions are mapped back to full size (pyrDown's pixel (x, y) is centred on the
full image's (2x, 2y)) and refined there by the caller.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["cell_index", "grid_corners", "select"]


def cell_index(p: np.ndarray, width: int, height: int, cols: int, rows: int) -> np.ndarray:
    """Grid cell (row-major) of each full-size pixel (n,2)."""
    q = np.clip((p[:, 0] * cols // width).astype(np.int64), 0, cols - 1)
    r = np.clip((p[:, 1] * rows // height).astype(np.int64), 0, rows - 1)
    return r * cols + q


def grid_corners(half: np.ndarray, full_size: tuple[int, int], cols: int, rows: int, quality: float,
                 min_response: float, min_distance_px: float, block_size: int):
    """Corners of the half-size image ``half`` as full-size pixels (m,2) float32, with their
    response (m,) and grid cell (m,), sorted by cell then by decreasing response."""
    corners, response = cv2.goodFeaturesToTrackWithQuality(
        half, 0, 1e-4, max(1.0, min_distance_px / 2.0), None, blockSize=block_size,
    )
    if corners is None or len(corners) == 0:
        return np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64)
    p = corners.reshape(-1, 2).astype(np.float32) * 2.0
    response = response.reshape(-1).astype(np.float32)
    w, h = full_size
    cell = cell_index(p, w, h, cols, rows)
    strongest = np.zeros(cols * rows, np.float32)
    np.maximum.at(strongest, cell, response)
    keep = (response >= min_response) & (response >= quality * strongest[cell])
    p, response, cell = p[keep], response[keep], cell[keep]
    order = np.lexsort((-response, cell))
    return p[order], response[order], cell[order]


def select(cell: np.ndarray, live_count: np.ndarray, budget: int, want: int) -> np.ndarray:
    """Indices of the candidates to track (``cell`` (m,) sorted, strongest first within a cell):
    at most ``budget - live_count[c]`` in cell c and ``want`` in all, filled emptiest cell first
    (the k-th candidate of a cell holding n tracks ranks n + k; among equal ranks, lower k first)."""
    if cell.size == 0 or want <= 0:
        return np.zeros(0, np.int64)
    rank = np.arange(cell.size) - np.searchsorted(cell, cell)  # position within its cell
    level = live_count[cell] + rank
    eligible = np.flatnonzero(level < budget)
    order = eligible[np.lexsort((rank[eligible], level[eligible]))]
    return order[:want]
