"""Online stereo feature tracker: rectified grey image pairs in, stereo observations out.

:meth:`StereoTracker.step` takes one (left, right) pair and returns the ids and pixels
``uL vL uR vR`` of the tracks seen in both images. Per frame:

1. temporal: the live left points are followed from the previous left image with pyramidal
   Lucas-Kanade (``cv2.calcOpticalFlowPyrLK``) seeded with a prediction (``predict_flow``: each
   point's stereo 3-D point moved by the last camera motion, else its last image motion), then
   tracked back, the way back seeded as far from its answer as the way there was
   (``p1 - (seed - p0)``) so the check does not start at the answer it tests; a point whose
   round trip misses its start by more than ``fb_threshold_px``, or that leaves the
   ``border_px`` frame, ends;
2. refinement (``affine_window`` > 0): the position is refined by aligning the patch the track
   was born with (affine warp, :mod:`frontend.affine`), so frame-to-frame LK drift does not
   accumulate; a track whose patch no longer matches (``affine_max_residual``), that the
   refinement moves more than ``affine_max_shift_px`` from the LK result, or whose patch area
   has grown or shrunk beyond ``max_patch_scale`` times its first frame's ends;
3. outliers: a fundamental matrix is fitted to the temporal matches (``cv2.findFundamentalMat``,
   MAGSAC or RANSAC, >= 8 matches, else skipped); matches farther than
   ``fundamental_threshold_px`` from their epipolar line end;
4. detection (:mod:`frontend.detect`): Shi-Tomasi corners of the half-size image, refined with
   ``cv2.cornerSubPix``, at least ``min_distance_px`` from live tracks, not about to leave the
   image (the nearest track's motion; with ``birth_lookahead_frames`` > 1 the corner's stereo
   point, at the nearest track's disparity, moved that many times by the last camera motion
   must stay inside both images), optionally (``min_isotropy``) with texture in every direction
   over the tracking patch, added emptiest grid cell first (at most ``per_cell_budget`` a cell)
   until ``target_tracks`` would be live;
5. stereo: every left point is followed into the right image with LK seeded at ``(u - d, v)``:
   ``d`` is a track's last disparity, or for a new point block matching of the shrunk pair
   (``stereo_seed_scale``), else its nearest track's disparity; then tracked back (within
   ``stereo_back_threshold_px``) and refined like the left point (the right patch is aligned with
   the same first patch). Accepted if ``|vL - vR| <= stereo_row_tolerance_px`` and
   ``stereo_min_disparity_px < uL - uR <= stereo_max_disparity_px``, inside the border;
6. motion (:mod:`frontend.motion`): the camera motion since the previous frame is estimated by
   PnP RANSAC of the tracked points' previous stereo 3-D points (it predicts the next frame);
   with ``motion_threshold_px`` > 0 points that did not move like fixed 3-D points end, and with
   ``verify_births`` new points must also project onto themselves in the previous frame.

Track life: a track lives while it passes every test in every frame. A tracked point without a
valid stereo match in a frame **ends** (it is not kept as a left-only track): the estimator
marginalizes a landmark the first step it is not observed, so an id is only ever seen in
consecutive frames and, once gone, never comes back. A new track gets its id once it has been
followed ``confirm_frames`` frames (0: in the frame it is born), from a counter that only grows
(:attr:`StereoTracker.num_ids`); each frame's ids are returned in increasing order.

Speed: OpenCV's Python binding cannot take the pyramids of ``cv2.buildOpticalFlowPyramid`` in
``calcOpticalFlowPyrLK`` (opencv issue 4777), so every LK call builds its own (0.1-0.3 ms an
image); the cost that matters is per point and pyramid level, so predicted points run with
``lk_levels_tracked`` levels and only unpredicted ones with the full ``lk_levels``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from . import affine, detect, motion as rigid
from .config import TrackerConfig

__all__ = ["StereoTracker", "FrameStats"]

_FUNDAMENTAL = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.FM_RANSAC}

#: Block size (px, odd) of the block matcher that seeds new points' disparity; cv2.StereoBM
#: refuses images not larger than it.
_BM_BLOCK = 7


@dataclass
class FrameStats:
    """What happened to the tracks in one :meth:`StereoTracker.step`."""

    frame: int = 0
    live_in: int = 0  # tracks alive before this frame
    lost_border: int = 0  # left the image (predicted or tracked beyond the border)
    lost_temporal: int = 0  # LK failed or its round trip was too long, inside the image
    lost_appearance: int = 0  # patch no longer matches its first frame (affine refinement)
    lost_fundamental: int = 0  # off their epipolar line
    lost_stereo: int = 0  # tracked, but no valid stereo match in this frame
    lost_motion: int = 0  # did not move like a fixed 3-D point (stereo + PnP check)
    unverified: int = 0  # new points whose stereo point does not project onto them in the previous frame
    detected: int = 0  # new corners tried in the right image
    born: int = 0  # ... of which got a stereo match (tracks, emitted once confirmed)
    new_ids: int = 0  # tracks confirmed in this frame (ids issued)
    emitted: int = 0  # observations returned (confirmed tracks)

    def describe(self) -> str:
        return (
            f"frame {self.frame}: {self.emitted} emitted, {self.new_ids} new ids, {self.born} born of "
            f"{self.detected} detected; lost {self.lost_border} leaving the image, {self.lost_temporal} temporal, {self.lost_appearance} appearance, "
            f"{self.lost_fundamental} epipolar, {self.lost_stereo} stereo, {self.lost_motion} motion; "
            f"{self.unverified} new points failed the check in the previous frame"
        )


@dataclass
class _Tracks:
    """State of a set of tracks (arrays aligned by row)."""

    ids: np.ndarray  # (n,) int64 (-1: candidate without an id yet)
    left: np.ndarray  # (n,2) float32 last left pixel
    motion: np.ndarray  # (n,2) float32 expected left motion to the next frame, px
    disparity: np.ndarray  # (n,) float32 last (for a new point: guessed) disparity uL - uR
    warp: np.ndarray  # (n,2,2) float64 affine part of first patch -> current left image
    age: np.ndarray  # (n,) int64 frames followed since birth (0: born in the last frame stepped)
    templates: affine.Templates | None  # first patches (None: refinement off)

    def __len__(self) -> int:
        return self.ids.shape[0]

    def take(self, index) -> "_Tracks":
        return _Tracks(self.ids[index], self.left[index], self.motion[index], self.disparity[index],
                       self.warp[index], self.age[index], None if self.templates is None else self.templates.take(index))

    @staticmethod
    def concat(a: "_Tracks", b: "_Tracks") -> "_Tracks":
        templates = None if a.templates is None else affine.Templates.concat([a.templates, b.templates])
        return _Tracks(*(np.concatenate([getattr(a, f), getattr(b, f)]) for f in ("ids", "left", "motion", "disparity", "warp", "age")),
                       templates)

    @staticmethod
    def empty(template_size: int) -> "_Tracks":
        return _Tracks(np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros((0, 2), np.float32),
                       np.zeros(0, np.float32), np.zeros((0, 2, 2)), np.zeros(0, np.int64),
                       affine.Templates.empty(template_size) if template_size else None)


class StereoTracker:
    """KLT stereo tracker for rectified pairs of a camera ``K`` (3,3) with ``baseline`` (m).

    ``K`` and ``baseline`` triangulate the stereo points for the camera-motion estimate (the
    prediction of the next frame) and the motion checks; without them (None) those are skipped
    and tracks are predicted by their last image motion.
    """

    def __init__(self, config: TrackerConfig | None = None, K=None, baseline: float | None = None) -> None:
        self.config = (config if config is not None else TrackerConfig()).validate()
        self.K = None if K is None else np.array(K, dtype=np.float64).reshape(3, 3)
        self.baseline = None if baseline is None else float(baseline)
        cfg = self.config
        self._win = (cfg.lk_window, cfg.lk_window)
        self._criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.lk_iterations, cfg.lk_epsilon)
        self._subpix_criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.01)
        self._next_id = 0
        self._frame = 0
        self._size: tuple[int, int] | None = None  # (width, height)
        self._prev_left: np.ndarray | None = None
        self._tracks = _Tracks.empty(cfg.affine_window)
        self._cur_T_prev: np.ndarray | None = None  # last frame-to-frame motion of the left camera
        self._pose_ok = False  # _cur_T_prev was estimated in the current frame
        self._block_matcher = None  # cv2.StereoBM for the disparity seeds of new points
        self._predicted = False  # the tracks' motion comes from that pose (else image motion)
        self.last_stats = FrameStats()

    # ------------------------------------------------------------------ public
    @property
    def num_ids(self) -> int:
        """Number of ids issued so far (ids are 0 .. num_ids - 1)."""
        return self._next_id

    @property
    def frame_index(self) -> int:
        """Number of frames stepped so far."""
        return self._frame

    def step(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Track one rectified pair (8-bit grey, same size every frame, each side at least
        ``config.min_image_side`` px, else ValueError): returns the live tracks' ids (n,) int64,
        increasing, and pixels (n,4) float64 ``uL vL uR vR``; a frame without trackable texture
        (all black, say) gives none, ids (0,) and pixels (0,4), and the next frame starts new tracks."""
        left, right = self._check_images(left, right)
        cfg = self.config
        refine = cfg.affine_window > 0
        left_f = left.astype(np.float32) if refine else None
        right_f = right.astype(np.float32) if refine else None
        live = self._tracks
        stats = FrameStats(frame=self._frame, live_in=len(live))
        p0 = np.zeros((0, 2), np.float32)

        if len(live) and self._prev_left is not None:
            # unpredicted: new points whose motion is a neighbour's guess, or every point without prediction
            unsure = ((live.age == 0) & (not self._predicted)) | (not cfg.predict_flow)
            p1, ok, out = self._track_temporal(self._prev_left, left, live.left, live.motion, unsure)
            stats.lost_border = int((~ok & out).sum())
            stats.lost_temporal = int((~ok & ~out).sum())
            keep = np.flatnonzero(ok)
            live, p0, p1 = live.take(keep), live.left[keep], p1[keep]
            if refine:
                live.warp, p1, good = self._refine(left_f, live.templates, live.warp, p1)
                stats.lost_appearance = int((~good).sum())
                live, p0, p1 = live.take(good), p0[good], p1[good]
            inlier = self._epipolar_inliers(p0, p1)
            stats.lost_fundamental = int((~inlier).sum())
            live, p0, p1 = live.take(inlier), p0[inlier], p1[inlier]
            live.motion = (p1 - p0).astype(np.float32)
            live.left = p1.astype(np.float32)

        left_half = cv2.pyrDown(left)
        new = self._detect(left, left_half, left_f, live)
        stats.detected = len(new)
        n_old = len(live)
        both = _Tracks.concat(live, new)
        right_pts, ok = self._match_stereo(left, left_half, right, right_f, both, n_old)
        stats.lost_stereo = int((~ok[:n_old]).sum())
        stats.lost_motion = self._check_motion(both, p0, right_pts, ok, n_old)
        stats.unverified = self._verify_births(both, right_pts, ok, n_old, left)
        stats.born = int(ok[n_old:].sum())
        survivors = int(ok[:n_old].sum())

        both = both.take(ok)
        right_pts = right_pts[ok]
        both.disparity = (both.left[:, 0] - right_pts[:, 0]).astype(np.float32)
        both.age[:survivors] += 1
        confirm = np.flatnonzero((both.ids < 0) & (both.age >= cfg.confirm_frames))
        both.ids[confirm] = np.arange(self._next_id, self._next_id + confirm.size)
        self._next_id += confirm.size
        stats.new_ids = int(confirm.size)
        self._predicted = self._predict_motion(both, right_pts, self._pose_ok)
        self._tracks = both
        self._prev_left = left
        self._frame += 1
        emit = np.flatnonzero(both.ids >= 0)
        emit = emit[np.argsort(both.ids[emit], kind="stable")]
        stats.emitted = int(emit.size)
        self.last_stats = stats
        pixels = np.empty((emit.size, 4), dtype=np.float64)
        pixels[:, :2] = both.left[emit]
        pixels[:, 2:] = right_pts[emit]
        return both.ids[emit].copy(), pixels

    # ------------------------------------------------------------------ steps
    def _check_images(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        left, right = np.asarray(left), np.asarray(right)
        for name, img in (("left", left), ("right", right)):
            if img.dtype != np.uint8 or img.ndim != 2:
                raise ValueError(f"{name} image must be 8-bit grey (H, W) uint8, got {img.dtype} {img.shape}")
        if left.shape != right.shape:
            raise ValueError(f"left {left.shape} and right {right.shape} images differ in size")
        size = (left.shape[1], left.shape[0])
        if min(size) < self.config.min_image_side:
            raise ValueError(f"images {size[0]}x{size[1]} are too small to track: each side needs at least "
                             f"{self.config.min_image_side} px (TrackerConfig.min_image_side)")
        if self._size is None:
            self._size = size
        elif size != self._size:
            raise ValueError(f"image size changed from {self._size} to {size}")
        return np.ascontiguousarray(left), np.ascontiguousarray(right)

    def _lk(self, img0: np.ndarray, img1: np.ndarray, p0: np.ndarray, seed: np.ndarray, levels: int):
        """LK from ``img0`` at ``p0`` (n,2) into ``img1`` starting at ``seed``: (p1 (n,2), ok (n,))."""
        if p0.shape[0] == 0:
            return np.zeros((0, 2), np.float32), np.zeros(0, bool)
        p1, status, _ = cv2.calcOpticalFlowPyrLK(
            img0, img1, np.ascontiguousarray(p0, dtype=np.float32).reshape(-1, 1, 2),
            np.ascontiguousarray(seed, dtype=np.float32).reshape(-1, 1, 2),
            winSize=self._win, maxLevel=int(levels), criteria=self._criteria,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        return p1.reshape(-1, 2), status.reshape(-1).astype(bool)

    def _inside(self, p: np.ndarray) -> np.ndarray:
        b = self.config.border_px
        w, h = self._size
        return (p[:, 0] >= b) & (p[:, 0] <= w - 1 - b) & (p[:, 1] >= b) & (p[:, 1] <= h - 1 - b)

    def _lk_pair(self, img0: np.ndarray, img1: np.ndarray, p0: np.ndarray, seed: np.ndarray, unsure: np.ndarray):
        """LK there and back (p1, ok, back): ``lk_levels_tracked`` levels, the full ``lk_levels``
        for the points flagged ``unsure`` (no reliable prediction). The way back is seeded as far
        from ``p0`` as the way there was from its result."""
        cfg = self.config
        p1 = np.zeros_like(p0, dtype=np.float32)
        back = np.zeros_like(p0, dtype=np.float32)
        ok = np.zeros(p0.shape[0], dtype=bool)
        for group, levels in ((~unsure, cfg.lk_levels_tracked), (unsure, cfg.lk_levels)):
            if not group.any():
                continue
            q0, sd = p0[group], seed[group]
            q1, fine = self._lk(img0, img1, q0, sd, levels)
            qb, fine_back = self._lk(img1, img0, q1, q1 - (sd - q0), levels)
            p1[group], back[group], ok[group] = q1, qb, fine & fine_back
        return p1, ok, back

    def _track_temporal(self, prev: np.ndarray, cur: np.ndarray, p0: np.ndarray, motion: np.ndarray, unsure: np.ndarray):
        """(p1 (n,2), ok (n,), out (n,)): forward LK, backward check, inside the border; ``out``:
        the prediction or the tracked point lies beyond the border."""
        cfg = self.config
        seed = p0 + motion if cfg.predict_flow else p0
        p1, ok, back = self._lk_pair(prev, cur, p0, seed, unsure)
        round_trip = np.linalg.norm(back - p0, axis=1)
        inside = self._inside(p1)
        out = ~self._inside(seed) | (ok & ~inside)
        return p1, ok & (round_trip <= cfg.fb_threshold_px) & inside, out

    def _refine(self, img_f: np.ndarray, templates: affine.Templates, warp: np.ndarray, p: np.ndarray):
        """(warp, refined p, ok): align the first patches at the LK positions ``p``."""
        cfg = self.config
        warp, t, residual = affine.align(img_f, templates, warp, p, cfg.affine_iterations)
        scale = np.abs(np.linalg.det(warp))  # area scale of the patch relative to its first frame
        ok = (residual <= cfg.affine_max_residual) & (np.linalg.norm(t - p, axis=1) <= cfg.affine_max_shift_px)
        ok &= (scale >= 1.0 / cfg.max_patch_scale) & (scale <= cfg.max_patch_scale) & self._inside(t)
        return warp, t.astype(np.float32), ok

    def _epipolar_inliers(self, p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
        cfg = self.config
        n = p0.shape[0]
        if cfg.fundamental_method == "off" or n < 8:
            return np.ones(n, dtype=bool)
        try:
            _, mask = cv2.findFundamentalMat(
                np.ascontiguousarray(p0, np.float32), np.ascontiguousarray(p1, np.float32),
                _FUNDAMENTAL[cfg.fundamental_method], cfg.fundamental_threshold_px, cfg.fundamental_confidence,
            )
        except cv2.error:  # e.g. all points (nearly) identical
            mask = None
        if mask is None or mask.size != n:  # degenerate configuration: keep everything
            return np.ones(n, dtype=bool)
        return mask.reshape(-1).astype(bool)

    def _subpix(self, img: np.ndarray, p: np.ndarray) -> np.ndarray:
        w = self.config.subpix_window
        if w == 0 or p.shape[0] == 0:
            return p
        q = cv2.cornerSubPix(img, np.ascontiguousarray(p, np.float32).reshape(-1, 1, 2), (w, w), (-1, -1),
                             self._subpix_criteria)
        return q.reshape(-1, 2)

    def _detect(self, img: np.ndarray, half: np.ndarray, img_f: np.ndarray | None, live: _Tracks) -> _Tracks:
        """Candidate tracks at new corners (:mod:`frontend.detect`), with the disparity and motion of
        their nearest live track as predictions (``new_point_disparity_px`` and no motion when none
        is live). Corners nearer than ``min_distance_px`` to a live track, or that the neighbour's
        motion would carry out of the image, are skipped."""
        cfg = self.config
        want = cfg.target_tracks - len(live)
        if want <= 0:
            return _Tracks.empty(cfg.affine_window)
        w, h = self._size
        p, _, cell = detect.grid_corners(half, self._size, cfg.grid_cols, cfg.grid_rows, cfg.gftt_quality,
                                         cfg.gftt_min_response, cfg.min_distance_px, cfg.gftt_block_size)
        keep = self._inside(p)
        tree = cKDTree(live.left) if len(live) else None
        if tree is not None and keep.any():
            dist, nearest = tree.query(p)
            keep &= (dist >= cfg.min_distance_px) & self._inside(p + live.motion[nearest])
            if cfg.birth_lookahead_frames > 1 and self._pose_ok and keep.any():
                idx = np.flatnonzero(keep)
                keep[idx] = self._stays_in_view(p[idx], live.disparity[nearest[idx]], cfg.birth_lookahead_frames)
        if img_f is not None and cfg.min_isotropy > 0 and keep.any():
            idx = np.flatnonzero(keep)
            keep[idx] = affine.isotropy(img_f, p[idx], cfg.affine_window) >= cfg.min_isotropy
        p, cell = p[keep], cell[keep]
        count = np.bincount(detect.cell_index(live.left, w, h, cfg.grid_cols, cfg.grid_rows), minlength=cfg.cells)
        p = self._subpix(img, p[detect.select(cell, count, cfg.per_cell_budget, want)])
        p = p[self._inside(p)]
        n = p.shape[0]
        if tree is None:
            disparity = np.full(n, cfg.new_point_disparity_px, np.float32)
            motion = np.zeros((n, 2), np.float32)
        else:
            _, nearest = tree.query(p)
            disparity, motion = live.disparity[nearest], live.motion[nearest]
        templates = None
        if img_f is not None:
            templates, textured = affine.make_templates(img_f, p, cfg.affine_window)
            p, disparity, motion = p[textured], disparity[textured], motion[textured]
            templates = templates.take(textured)
            n = p.shape[0]
        warp = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
        return _Tracks(np.full(n, -1, np.int64), p, motion.astype(np.float32), disparity.astype(np.float32), warp,
                       np.zeros(n, np.int64), templates)

    def _stays_in_view(self, p: np.ndarray, disparity: np.ndarray, frames: int) -> np.ndarray:
        """(n,) bool: the stereo points of the left pixels ``p`` (n,2) at ``disparity`` (n,), moved
        ``frames`` times by the last camera motion (constant velocity), stay in front and inside
        the border of both images."""
        d = np.maximum(disparity.astype(np.float64), 1e-3)
        pixels = np.stack([p[:, 0], p[:, 1], p[:, 0] - d, p[:, 1]], axis=1)
        points = rigid.triangulate(pixels, self.K, self.baseline, np.eye(4))
        ok = np.ones(p.shape[0], dtype=bool)
        moved = np.eye(4)
        for _ in range(frames):
            moved = self._cur_T_prev @ moved
            projected, front = rigid.project_stereo(points, self.K, self.baseline, moved)
            ok &= front & self._inside(projected[:, :2]) & self._inside(projected[:, 2:])
        return ok

    def _check_motion(self, tracks: _Tracks, p0: np.ndarray, right: np.ndarray, ok: np.ndarray, n_old: int) -> int:
        """Estimate the camera motion since the previous frame (PnP RANSAC of the tracked points,
        triangulated there from the left pixel ``p0`` and the last disparity; used to predict the
        next frame) and, if ``motion_threshold_px`` > 0, end (clear ``ok`` of) the points that did
        not move like fixed 3-D points: projected with that motion into both images, farther than
        the threshold from where they were tracked. Returns the number ended."""
        cfg = self.config
        self._pose_ok = False
        idx = np.flatnonzero(ok[:n_old])
        if self.K is None or self.baseline is None or idx.size < 6:
            return 0
        prev = np.zeros((idx.size, 4))
        prev[:, :2] = p0[idx]
        prev[:, 2] = p0[idx, 0] - tracks.disparity[idx]
        prev[:, 3] = p0[idx, 1]
        p_in_prev = rigid.triangulate(prev, self.K, self.baseline, np.eye(4))
        cur_left = tracks.left[idx].astype(np.float64)
        pose = rigid.estimate_pose(p_in_prev, cur_left, self.K, cfg.pose_ransac_px, self._cur_T_prev)
        self._pose_ok = pose is not None
        if pose is None:
            return 0
        self._cur_T_prev = pose
        if cfg.motion_threshold_px == 0:
            return 0
        projected, front = rigid.project_stereo(p_in_prev, self.K, self.baseline, pose)
        err_left = np.linalg.norm(projected[:, :2] - cur_left, axis=1)
        err_right = np.linalg.norm(projected[:, 2:] - right[idx], axis=1)
        bad = ~front | (np.maximum(err_left, err_right) > cfg.motion_threshold_px)
        ok[idx[bad]] = False
        return int(bad.sum())

    def _verify_births(self, tracks: _Tracks, right: np.ndarray, ok: np.ndarray, n_old: int, left: np.ndarray) -> int:
        """Check the stereo match of new points in the previous frame: their 3-D point, moved back
        by this frame's camera motion, must project where LK finds them in the previous left
        image (within ``birth_threshold_px``). Clears ``ok`` of those that fail; returns how many.
        Skipped without a previous frame or a motion estimate."""
        cfg = self.config
        idx = n_old + np.flatnonzero(ok[n_old:])
        if not (cfg.verify_births and self._pose_ok and idx.size and self._prev_left is not None):
            return 0
        pixels = np.concatenate([tracks.left[idx], right[idx]], axis=1).astype(np.float64)
        p_in_cur = rigid.triangulate(pixels, self.K, self.baseline, np.eye(4))
        prev_T_cur = np.linalg.inv(self._cur_T_prev)
        expected, front = rigid.project_stereo(p_in_cur, self.K, self.baseline, prev_T_cur)
        found, fine = self._lk(left, self._prev_left, tracks.left[idx], expected[:, :2], cfg.lk_levels_tracked)
        fine &= front & (np.linalg.norm(found - expected[:, :2], axis=1) <= cfg.birth_threshold_px)
        ok[idx[~fine]] = False
        return int((~fine).sum())

    def _predict_motion(self, tracks: _Tracks, right: np.ndarray, pose_ok: bool) -> bool:
        """Set the tracks' expected image motion to the next frame by moving their stereo points
        with this frame's camera motion (constant velocity); returns False (motion left as is:
        last image motion, or a neighbour's for new points) without a motion estimate."""
        if not pose_ok or len(tracks) == 0:
            return False
        pixels = np.concatenate([tracks.left, right], axis=1).astype(np.float64)
        p_in_cam = rigid.triangulate(pixels, self.K, self.baseline, np.eye(4))
        projected, front = rigid.project_stereo(p_in_cam, self.K, self.baseline, self._cur_T_prev)
        guess = (projected[:, :2] - tracks.left).astype(np.float32)
        tracks.motion = np.where(front[:, None] & np.isfinite(guess), guess, tracks.motion)
        return True

    def _coarse_disparity(self, left_half: np.ndarray, right: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Disparity (n,) at the full-size pixels ``p`` from block matching (``cv2.StereoBM``) of
        the pair shrunk ``stereo_seed_scale`` times (``cv2.pyrDown``); NaN where the matcher gives
        none (no texture, not unique) and everywhere when the shrunk pair is no larger than the
        matcher's block."""
        cfg = self.config
        levels = int(np.log2(cfg.stereo_seed_scale))
        ls, rs = left_half, right
        for _ in range(levels - 1):
            ls = cv2.pyrDown(ls)
        for _ in range(levels):
            rs = cv2.pyrDown(rs)
        if min(ls.shape) <= _BM_BLOCK:
            return np.full(p.shape[0], np.nan, np.float32)
        if self._block_matcher is None:
            blocks = max(1, int(np.ceil(cfg.stereo_max_disparity_px / cfg.stereo_seed_scale / 16)))
            self._block_matcher = cv2.StereoBM_create(numDisparities=16 * blocks, blockSize=_BM_BLOCK)
            self._block_matcher.setUniquenessRatio(5)
            self._block_matcher.setTextureThreshold(5)
        disparity = self._block_matcher.compute(ls, rs)  # int16, 1/16 px, < 0 where invalid
        scale = cfg.stereo_seed_scale
        x = np.clip(np.rint(p[:, 0] / scale).astype(np.int64), 0, disparity.shape[1] - 1)
        y = np.clip(np.rint(p[:, 1] / scale).astype(np.int64), 0, disparity.shape[0] - 1)
        d = disparity[y, x].astype(np.float32) / 16.0
        return np.where(d > 0, d * scale, np.nan).astype(np.float32)

    def _match_stereo(self, left, left_half, right, right_f, tracks: _Tracks, n_tracked: int):
        """(right pixels (n,2), ok (n,)): LK left -> right along the row, back-checked, refined."""
        cfg = self.config
        pl = tracks.left
        unsure = np.arange(len(tracks)) >= n_tracked  # new points: disparity of a neighbour
        if cfg.stereo_seed_scale and unsure.any():
            coarse = self._coarse_disparity(left_half, right, pl[unsure])
            found = np.isfinite(coarse)
            tracks.disparity[np.flatnonzero(unsure)[found]] = coarse[found]
            unsure[np.flatnonzero(unsure)[found]] = False
        seed = pl.copy()
        seed[:, 0] -= tracks.disparity
        pr, ok, back = self._lk_pair(left, right, pl, seed, unsure)
        ok &= np.linalg.norm(back - pl, axis=1) <= cfg.stereo_back_threshold_px
        if right_f is not None and ok.any():
            idx = np.flatnonzero(ok)
            _, pr[idx], ok[idx] = self._refine(right_f, tracks.templates.take(idx), tracks.warp[idx], pr[idx])
        d = pl[:, 0] - pr[:, 0]
        ok &= self._inside(pr) & (np.abs(pl[:, 1] - pr[:, 1]) <= cfg.stereo_row_tolerance_px)
        ok &= (d > cfg.stereo_min_disparity_px) & (d <= cfg.stereo_max_disparity_px)
        return pr, ok

