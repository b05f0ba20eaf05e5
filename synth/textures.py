"""Procedural grey textures for the image renderer (:mod:`synth.render`).

Every generator is a pure function of its arguments and of the ``numpy.random.Generator`` it is
given (drawing uses OpenCV, which is deterministic), and returns a C-contiguous ``uint8`` image of
``size = (width, height)`` texels (``shape == (height, width)``, the OpenCV image-size order).

The textures are made of edges that meet at corners on several scales (brick joints, window
frames, blocks, glyph strokes) rather than of pixel noise, so that a corner detector and a KLT
tracker find well-localized, trackable features; a little smooth low-contrast noise is added on
top so that flat areas are not perfectly uniform.

``metres_per_texel`` (where a generator takes it) sizes physical details (bricks, windows, lane
lines) for the plane the texture will be mapped onto.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = [
    "checkerboard",
    "checkerboard_corners",
    "bricks",
    "blobs",
    "glyphs",
    "facade",
    "road",
    "verge",
    "skyline",
]

_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)
_GLYPHS = np.array(list("ABCDEFGHJKLMNPQRSTUVWXYZ0123456789#&%+="))


def _size(size) -> tuple[int, int]:
    w, h = (int(v) for v in size)
    if w < 2 or h < 2:
        raise ValueError(f"texture size must be at least 2 x 2 texels, got {size!r}")
    return w, h


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.clip(np.rint(img), 0, 255).astype(np.uint8))


def _smooth_noise(rng: np.random.Generator, h: int, w: int, sigma: float, amplitude: float) -> np.ndarray:
    """Gaussian-blurred white noise scaled to standard deviation ``amplitude`` (float32)."""
    noise = rng.standard_normal((h, w)).astype(np.float32)
    if sigma > 0:
        noise = cv2.GaussianBlur(noise, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
    std = float(noise.std())
    return noise * (amplitude / std if std > 0 else 0.0)


# ------------------------------------------------------------------ checkerboard


def checkerboard(squares=(8, 5), square: int = 32, border: int = 1, dark: int = 0, light: int = 255) -> np.ndarray:
    """A ``squares = (columns, rows)`` checker of ``square``-texel squares (top-left square dark)
    inside a light frame ``border`` squares wide (the quiet zone OpenCV's detector needs).

    Size ``((columns + 2 border) square, (rows + 2 border) square)``; see :func:`checkerboard_corners`.
    """
    cols, rows = (int(v) for v in squares)
    square, border = int(square), int(border)
    if cols < 2 or rows < 2 or square < 1 or border < 0:
        raise ValueError("checkerboard needs >= 2 x 2 squares of >= 1 texel and a border >= 0")
    h, w = (rows + 2 * border) * square, (cols + 2 * border) * square
    img = np.full((h, w), light, dtype=np.uint8)
    j, i = np.mgrid[0:rows, 0:cols]
    cells = np.where((i + j) % 2 == 0, dark, light).astype(np.uint8)
    board = np.kron(cells, np.ones((square, square), dtype=np.uint8))
    img[border * square : (border + rows) * square, border * square : (border + cols) * square] = board
    return img


def checkerboard_corners(squares=(8, 5), square: int = 32, border: int = 1) -> np.ndarray:
    """Inner corners of :func:`checkerboard` in continuous texture coordinates (s, t), shape
    ((columns - 1) (rows - 1), 2), row by row. Texel (i, j) covers [i, i+1] x [j, j+1] (the
    convention of :mod:`synth.render`), so the corner between squares lies on a texel edge."""
    cols, rows = (int(v) for v in squares)
    t, s = np.mgrid[1:rows, 1:cols]
    return (np.stack([s.ravel(), t.ravel()], axis=1) + border) * float(square)


# ------------------------------------------------------------------ building blocks


def _brick_field(
    rng: np.random.Generator, h: int, w: int, brick_w: float, brick_h: float, mortar: float, base: float, spread: float
) -> tuple[np.ndarray, np.ndarray]:
    """(intensity (h,w) float32 of stretcher-bond bricks, mortar mask (h,w) bool); brick rows
    ``brick_h`` texels high, every other row shifted by half a brick."""
    bh, bw = max(float(brick_h), 2.0), max(float(brick_w), 3.0)
    m = max(float(mortar), 1.0)
    y = np.arange(h, dtype=np.float64)
    row_of_y = np.floor(y / bh).astype(np.int64)
    n_rows = int(row_of_y[-1]) + 1
    n_cols = int(np.floor((w + bw) / bw)) + 2
    table = (base + spread * rng.uniform(-1.0, 1.0, (n_rows, n_cols))).astype(np.float32)
    value = np.empty((h, w), dtype=np.float32)
    joint = np.empty((h, w), dtype=bool)
    x = np.arange(w, dtype=np.float64)
    bounds = np.searchsorted(row_of_y, np.arange(n_rows + 1))
    for r in range(n_rows):
        y0, y1 = int(bounds[r]), int(bounds[r + 1])
        xs = x + (r % 2) * 0.5 * bw
        col = np.floor(xs / bw).astype(np.int64)
        value[y0:y1] = table[r, col]
        joint[y0:y1] = (xs - col * bw < m)[None, :]
        joint[y0:y1] |= (y[y0:y1] - r * bh < m)[:, None]
    return value, joint


def bricks(
    rng: np.random.Generator,
    size=(512, 512),
    brick=(36, 12),
    mortar: int = 2,
    base: float = 120.0,
    spread: float = 45.0,
    mortar_level: float = 200.0,
) -> np.ndarray:
    """Stretcher-bond brick wall: bricks of ``brick = (width, height)`` texels with a random
    intensity each (``base +- spread``), light mortar joints ``mortar`` texels wide, and slight
    smooth noise. Every brick contributes 4 mortar T-junction corners."""
    w, h = _size(size)
    value, joint = _brick_field(rng, h, w, float(brick[0]), float(brick[1]), float(mortar), base, spread)
    img = np.where(joint, np.float32(mortar_level), value)
    img += _smooth_noise(rng, h, w, 1.0, 6.0)
    return _to_u8(img)


def _random_shape(rng: np.random.Generator, img: np.ndarray, scale: float, value: int) -> None:
    h, w = img.shape
    cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    kind = rng.integers(0, 4)
    if kind <= 1:  # axis-aligned rectangle (sharp 90 degree corners)
        rw, rh = scale * rng.uniform(0.4, 1.0, 2)
        cv2.rectangle(img, (int(cx - rw / 2), int(cy - rh / 2)), (int(cx + rw / 2), int(cy + rh / 2)), int(value), -1)
    elif kind == 2:  # rotated quadrilateral / triangle
        n = int(rng.integers(3, 5))
        ang = np.sort(rng.uniform(0, 2 * np.pi, n))
        rad = 0.5 * scale * rng.uniform(0.5, 1.0, n)
        pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], axis=1)
        cv2.fillPoly(img, [np.round(pts).astype(np.int32)], int(value), lineType=cv2.LINE_8)
    else:  # ellipse (blob)
        axes = (max(1, int(scale * rng.uniform(0.2, 0.5))), max(1, int(scale * rng.uniform(0.2, 0.5))))
        cv2.ellipse(img, (int(cx), int(cy)), axes, float(rng.uniform(0, 180)), 0, 360, int(value), -1)


def blobs(
    rng: np.random.Generator,
    size=(512, 512),
    scales=(6.0, 160.0),
    density: float = 1.0,
    background: float = 128.0,
) -> np.ndarray:
    """Random rectangles, polygons and ellipses of random grey levels on ``scales`` from small to
    large (log-uniform), painted big to small so that every scale stays visible. The number of
    shapes of each scale grows as 1 / scale^2 (``density`` times a few per area unit)."""
    w, h = _size(size)
    img = np.full((h, w), int(background), dtype=np.uint8)
    lo, hi = (float(v) for v in scales)
    n_octaves = max(1, int(np.ceil(np.log2(hi / lo))))
    for k in range(n_octaves, -1, -1):
        scale = lo * 2.0**k
        count = int(np.ceil(density * 0.25 * w * h / (scale * scale)))
        count = min(count, 1500)
        for _ in range(count):
            _random_shape(rng, img, scale * rng.uniform(0.7, 1.4), int(rng.integers(10, 246)))
    out = img.astype(np.float32) + _smooth_noise(rng, h, w, 1.0, 4.0)
    return _to_u8(out)


def _put_text(rng: np.random.Generator, img: np.ndarray, org, height_px: float, value: int, n_chars: int) -> None:
    font = int(rng.choice(_FONTS))
    base = cv2.getTextSize("A", font, 1.0, 1)[0][1]
    scale = max(height_px / max(base, 1), 0.2)
    thickness = max(1, int(round(scale * rng.uniform(1.0, 2.5))))
    text = "".join(rng.choice(_GLYPHS, n_chars))
    cv2.putText(img, text, (int(org[0]), int(org[1])), font, scale, int(value), thickness, cv2.LINE_8)


def glyphs(
    rng: np.random.Generator,
    size=(512, 512),
    heights=(10.0, 48.0),
    lines: int | None = None,
    background: float | None = None,
) -> np.ndarray:
    """Text-like strokes: lines of random characters (``cv2.putText``, random Hershey fonts,
    heights log-uniform in ``heights`` texels, dark or light on a random background)."""
    w, h = _size(size)
    bg = float(rng.uniform(60, 200)) if background is None else float(background)
    img = np.full((h, w), int(bg), dtype=np.uint8)
    lo, hi = (float(v) for v in heights)
    n_lines = int(lines) if lines is not None else max(1, int(1.5 * h / np.sqrt(lo * hi)))
    for _ in range(n_lines):
        th = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
        value = int(rng.integers(0, 60)) if bg > 128 else int(rng.integers(190, 256))
        n_chars = max(1, int(w / (0.8 * th)))
        _put_text(rng, img, (rng.uniform(-0.3, 0.2) * w, rng.uniform(th, h)), th, value, n_chars)
    out = img.astype(np.float32) + _smooth_noise(rng, h, w, 1.0, 3.0)
    return _to_u8(out)


# ------------------------------------------------------------------ street materials


def facade(rng: np.random.Generator, size=(2048, 1024), metres_per_texel: float = 0.02) -> np.ndarray:
    """A building front: a wall (bricks, or plaster blocks when a brick would be < 3 texels
    high), storeys of windows with frames, glazing bars and sills, a ground floor with doors and
    shop signs (glyph strokes on a plate), a cornice, and drain pipes. Row 0 is the top."""
    w, h = _size(size)
    m = float(metres_per_texel)
    px = lambda metres: max(1, int(round(metres / m)))  # noqa: E731
    wall_level = float(rng.uniform(90, 190))
    if 0.075 / m >= 3.0:
        value, joint = _brick_field(rng, h, w, 0.25 / m, 0.075 / m, max(1.0, 0.012 / m), wall_level, 30.0)
        wall = np.where(joint, np.float32(min(wall_level + 45, 235)), value)
    else:  # plaster / stone blocks
        value, joint = _brick_field(rng, h, w, float(rng.uniform(0.6, 1.5)) / m, 0.5 / m, 1.0, wall_level, 14.0)
        wall = np.where(joint, np.float32(wall_level - 25), value)
    img = _to_u8(wall)

    storey = float(rng.uniform(2.9, 3.6))
    win_w, win_h = float(rng.uniform(0.8, 1.6)), float(rng.uniform(1.2, 1.8))
    pitch = win_w + float(rng.uniform(0.8, 2.2))
    frame_level = int(rng.integers(200, 256)) if wall_level < 150 else int(rng.integers(20, 80))
    ground = px(storey * 1.2)
    # storeys above the ground floor: windows (row 0 = top of the texture = top of the building)
    y_top = h - ground
    offset = float(rng.uniform(0.2, pitch))
    k = 0
    while y_top - px(storey) >= -px(storey):
        y0 = y_top - px(storey) + px(0.8)
        x = offset
        while (x + win_w) / m < w:
            x0, x1 = px(x), px(x + win_w)
            y1 = y0 + px(win_h)
            glass = int(rng.integers(15, 90))
            cv2.rectangle(img, (x0 - px(0.08), y0 - px(0.08)), (x1 + px(0.08), y1 + px(0.08)), frame_level, -1)
            cv2.rectangle(img, (x0, y0), (x1, y1), glass, -1)
            if rng.uniform() < 0.7:  # glazing bars
                xm, ym = (x0 + x1) // 2, y0 + (y1 - y0) // 3
                cv2.line(img, (xm, y0), (xm, y1), frame_level, max(1, px(0.05)))
                cv2.line(img, (x0, ym), (x1, ym), frame_level, max(1, px(0.05)))
            if rng.uniform() < 0.3:  # blind / curtain
                cv2.rectangle(img, (x0, y0), (x1, y0 + int((y1 - y0) * rng.uniform(0.2, 0.7))), int(rng.integers(120, 230)), -1)
            cv2.rectangle(img, (x0 - px(0.15), y1 + px(0.08)), (x1 + px(0.15), y1 + px(0.2)), min(frame_level + 20, 255), -1)
            x += pitch
        y_top -= px(storey)
        k += 1
    # cornice between ground floor and upper storeys
    band = int(rng.integers(40, 230))
    cv2.rectangle(img, (0, h - ground - px(0.35)), (w, h - ground), band, -1)
    # ground floor: doors and shop windows with signs
    x = float(rng.uniform(0.0, 2.0))
    while x / m < w:
        kind = rng.uniform()
        if kind < 0.35:  # door
            dw = float(rng.uniform(1.0, 2.0))
            cv2.rectangle(img, (px(x), h - px(2.3)), (px(x + dw), h), int(rng.integers(10, 120)), -1)
            cv2.rectangle(img, (px(x + 0.15), h - px(2.1)), (px(x + dw - 0.15), h - px(1.2)), int(rng.integers(120, 250)), -1)
            x += dw + float(rng.uniform(0.5, 2.0))
        else:  # shop window with a sign above it
            sw = float(rng.uniform(2.0, 5.0))
            cv2.rectangle(img, (px(x), h - px(2.6)), (px(x + sw), h - px(0.5)), int(rng.integers(10, 90)), -1)
            cv2.rectangle(img, (px(x), h - px(2.6)), (px(x + sw), h - px(0.5)), frame_level, max(1, px(0.06)))
            plate = int(rng.integers(0, 256))
            sy0, sy1 = h - ground + px(0.05), h - px(2.75)
            if sy1 - sy0 > 4:
                sign = np.full((sy1 - sy0, max(px(sw), 2)), plate, dtype=np.uint8)
                _put_text(rng, sign, (px(0.1), 0.8 * sign.shape[0]), 0.6 * sign.shape[0], 255 - plate, max(1, int(sw / 0.45)))
                xe = min(px(x) + sign.shape[1], w)
                img[sy0:sy1, px(x) : xe] = sign[:, : xe - px(x)]
            x += sw + float(rng.uniform(0.3, 1.5))
    # drain pipes
    for _ in range(int(rng.integers(0, 3))):
        xp = int(rng.integers(0, w))
        cv2.line(img, (xp, 0), (xp, h), int(rng.integers(20, 80)), max(1, px(0.1)))
    out = img.astype(np.float32) + _smooth_noise(rng, h, w, max(1.0, 0.03 / m), 5.0)
    return _to_u8(out)


def road(
    rng: np.random.Generator,
    size=(1024, 1024),
    metres_per_texel=(0.012, 0.016),
    halfwidth: float = 8.2,
    carriageway: float = 5.5,
) -> np.ndarray:
    """A street cross-section: texture columns run along the street (``metres_per_texel[0]``),
    rows across it (``[1]``), row 0 at lateral ``-halfwidth`` and the last row at ``+halfwidth``.
    Asphalt with patches, cracks and stains, lane lines at +-1.8 m (dashed on the left), kerbs at
    +-``carriageway`` and paving slabs beyond."""
    w, h = _size(size)
    mx, my = (float(v) for v in metres_per_texel)
    lateral = -halfwidth + (np.arange(h) + 0.5) * my
    asphalt_level = float(rng.uniform(70, 110))
    img = np.full((h, w), asphalt_level, dtype=np.float32)
    img += _smooth_noise(rng, h, w, 1.0, 7.0) + _smooth_noise(rng, h, w, 12.0, 6.0)
    img = _to_u8(img)
    # patches and stains (several scales)
    for _ in range(int(w * h * 4e-5) + 2):
        _random_shape(rng, img, float(np.exp(rng.uniform(np.log(6), np.log(160)))), int(asphalt_level + rng.uniform(-40, 40)))
    # cracks: random polylines
    for _ in range(int(rng.integers(2, 8))):
        p = rng.uniform([0, 0], [w, h])
        pts = [p.copy()]
        for _ in range(int(rng.integers(4, 12))):
            p = p + rng.normal(0, 25, 2)
            pts.append(p.copy())
        cv2.polylines(img, [np.round(pts).astype(np.int32)], False, int(asphalt_level - 45), 1)
    row = lambda y: int(np.clip(np.searchsorted(lateral, y), 0, h - 1))  # noqa: E731
    line_w = max(1, int(round(0.12 / my)))
    dash, gap = max(1, int(round(3.0 / mx))), max(1, int(round(3.0 / mx)))
    paint = int(rng.integers(200, 246))
    # right lane line (solid), left lane line (dashed)
    r = row(-1.8)
    img[r : r + line_w] = paint
    r = row(1.8)
    phase = int(rng.integers(0, dash + gap))
    for x0 in range(-phase, w, dash + gap):
        img[r : r + line_w, max(x0, 0) : max(x0 + dash, 0)] = paint
    # pavement slabs beyond the kerbs (rows [0, kerb_r) and (kerb_l, h))
    slab_level = float(rng.uniform(130, 180))
    value, joint = _brick_field(rng, h, w, 0.6 / mx, 0.6 / my, max(1.0, 0.015 / mx), slab_level, 12.0)
    slabs = _to_u8(np.where(joint, np.float32(slab_level - 35), value))
    kr, kl = row(-carriageway), row(carriageway)
    img[:kr] = slabs[:kr]
    img[kl:] = slabs[kl:]
    kerb = max(1, int(round(0.15 / my)))
    img[max(kr - kerb, 0) : kr] = int(rng.integers(170, 230))
    img[kl : kl + kerb] = int(rng.integers(170, 230))
    out = img.astype(np.float32) + _smooth_noise(rng, h, w, 1.0, 3.0)
    return _to_u8(out)


def verge(rng: np.random.Generator, size=(512, 512)) -> np.ndarray:
    """Open ground beside the buildings (yards, grass, gravel): mid-grey blobs on several scales."""
    w, h = _size(size)
    return blobs(rng, (w, h), scales=(4.0, 120.0), density=0.6, background=float(rng.uniform(90, 140)))


def skyline(
    rng: np.random.Generator,
    size=(256, 512),
    sky: float = 200.0,
    horizon: float = 0.7,
    max_height: float = 0.6,
) -> np.ndarray:
    """Distant backdrop: uniform ``sky`` above building silhouettes (random widths and heights up
    to ``max_height`` of the texture, with lit window dots) standing on a horizon line at
    ``horizon`` (fraction of the height from the top); dim ground with blobs below."""
    w, h = _size(size)
    img = np.full((h, w), int(sky), dtype=np.uint8)
    y_h = int(horizon * h)
    ground_level = float(rng.uniform(80, 120))
    below = blobs(rng, (w, max(h - y_h, 2)), scales=(3.0, 40.0), density=0.5, background=ground_level)
    img[y_h:] = below[: h - y_h]
    x = int(rng.integers(-20, 0))
    while x < w:
        bw = int(rng.integers(max(4, h // 20), max(6, h // 4)))
        bh = int(rng.uniform(0.1, max_height) * h)
        level = int(rng.integers(40, 150))
        cv2.rectangle(img, (x, max(y_h - bh, 0)), (x + bw, y_h), level, -1)
        if rng.uniform() < 0.3:  # antenna / spire
            cv2.line(img, (x + bw // 2, max(y_h - bh - int(0.05 * h), 0)), (x + bw // 2, y_h - bh), level, 1)
        for yy in range(max(y_h - bh, 0) + 3, y_h - 2, 6):
            for xx in range(x + 2, x + bw - 2, 5):
                if rng.uniform() < 0.25:
                    img[yy : yy + 2, max(xx, 0) : max(xx + 2, 0)] = min(level + 70, 255)
        x += bw + int(rng.integers(0, max(2, w // 16)))
    out = img.astype(np.float32)
    y_n = max(y_h - int(max_height * h), 0)
    out[y_n:] += _smooth_noise(rng, h - y_n, w, 1.0, 2.0)
    return _to_u8(out)
