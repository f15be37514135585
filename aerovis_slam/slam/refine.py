"""Track refinement: each landmark observation aligned to the landmark's anchor view by Lucas-Kanade.

A detector places a keypoint anew in every frame, and on event time surfaces where it lands depends on
the local surface shape, which changes with the motion (a constant-event-count surface holds a trail
behind every edge): along a track the keypoint wanders around the scene point by an offset that
persists over many frames and drifts along edges (docs/slam.md, "Perfect tracks": the runtime's error
with the detector's own keypoints is above that of 1 px of independent noise on the handheld
sequences). Those slowly varying offsets bias the estimate where independent noise would average out.

The refinement keeps, per landmark and camera, an *anchor*: the image and the keypoint position where
the landmark was first observed in that camera (a keyframe's stereo pair for new landmarks). Every
later observation matched to the landmark is moved to where the anchor's patch aligns best in the
current image (pyramidal Lucas-Kanade, ``cv2.calcOpticalFlowPyrLK``, started at the detected
position), so all observations of a track refer to one scene point, as the anchor's did. The detector
still decides which keypoints exist and what matches what; only positions change, and only within
``max_shift_px`` of the detection, after a forward-backward check (the alignment back from the
current image must return to the anchor within ``max_fb_px``). An observation that fails keeps its
detected position (its anchor stays). An anchor older than ``max_anchor_age_s`` is replaced by the
current observation as detected, so that a long track starts over from a recent view.

Measured on the ``bench`` preset (docs/slam.md, "Track refinement"): SuperLitE's median distance to
the scene point of the first sighting drops from 1.25-1.82 px to 0.41-1.17 px, and its four-run ATE
means by 19-48 % on six sequences of seven (shake_rapid, whose shaking turns the surfaces' trails
around within a track, gets worse).

Images are the frame's channel means of the MCTS (values in [0, 1]), as 8-bit for OpenCV's tracker
(:func:`alignment_images`; ``refinement.windows`` keeps only the shortest windows).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .backend import Observations


@dataclass
class RefinementStats:
    """Counts over a run: observations ``refined`` (aligned to their anchor), ``rejected`` (an alignment
    was tried and failed: kept at the detection), ``anchors`` set, and the summed shift of the refined
    ones from their detections (px)."""

    refined: int = 0
    rejected: int = 0
    anchors: int = 0
    shift_sum_px: float = 0.0

    def as_dict(self) -> dict:
        n = max(self.refined, 1)
        return {"observations_refined": self.refined, "observations_kept_at_detection": self.rejected,
                "anchors": self.anchors, "mean_shift_px": self.shift_sum_px / n}


def to_uint8(image: np.ndarray) -> np.ndarray:
    """A time-surface image with values in [0, 1] as contiguous uint8 (OpenCV's tracker takes 8-bit)."""
    return np.ascontiguousarray(np.clip(np.rint(np.asarray(image, np.float32) * 255.0), 0, 255).astype(np.uint8))


def alignment_images(surfaces: np.ndarray, windows: int | None = None) -> np.ndarray:
    """The images the refinement aligns: each camera's mean over MCTS channels.

    Args:
        surfaces: (cameras, C, H, W) time surfaces, polarity-major (``channel = p * K + k``, K = C / 2,
            window ``k = 0`` the shortest), values in [0, 1].
        windows: average only the ``windows`` shortest windows of each polarity (None, or K or more:
            every channel).
    Returns:
        (cameras, H, W) float32 channel means.
    """
    surfaces = np.asarray(surfaces)
    K = surfaces.shape[1] // 2
    if windows is None or windows >= K:
        return surfaces.mean(axis=1, dtype=np.float32)
    if windows < 1:
        raise ValueError(f"windows must be >= 1 (the shortest MCTS windows) or None, got {windows}")
    picked = np.concatenate([surfaces[:, :windows], surfaces[:, K:K + windows]], axis=1)
    return picked.mean(axis=1, dtype=np.float32)


class TrackRefiner:
    """Anchors and refines landmark observations (see the module docstring).

    Per frame: :meth:`begin_frame` with the frame's images, then :meth:`refine` on the observations
    matched to existing landmarks and :meth:`anchor` on those of new landmarks.

    Args:
        window_px: side of the Lucas-Kanade window (odd, pixels at the MCTS resolution).
        max_shift_px: a refined position farther than this from the detection is rejected.
        max_fb_px: forward-backward error above this rejects the refinement.
        max_anchor_age_s: anchors older than this are replaced by the current observation.
        levels: pyramid levels above the full resolution (0: the detection is within a few pixels).
    """

    def __init__(self, window_px: int = 13, max_shift_px: float = 6.0, max_fb_px: float = 2.0,
                 max_anchor_age_s: float = 5.0, levels: int = 0):
        self.win = (int(window_px), int(window_px))
        self.max_shift = float(max_shift_px)
        self.max_fb = float(max_fb_px)
        self.max_age_us = int(max_anchor_age_s * 1e6)
        self.levels = int(levels)
        self.criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 0.01)
        self.anchors: dict[tuple[int, int], tuple[int, np.ndarray]] = {}  # (landmark, cam) -> (image key, xy)
        self.images: dict[int, tuple[int, np.ndarray]] = {}  # image key -> (t µs, uint8 image)
        self._users: dict[int, int] = {}  # image key -> anchors that use it (an unused image is dropped)
        self._key = 0
        self._t: int | None = None
        self._frame: list = [None, None]  # the current frame's images as given
        self._frame_keys: list[int | None] = [None, None]  # their keys once stored
        self.stats = RefinementStats()

    def begin_frame(self, t_us: int, images) -> None:
        """The frame at ``t_us`` (µs): its (left, right) images (H, W), time-surface values in [0, 1]."""
        self._t = int(t_us)
        self._frame = list(images)
        self._frame_keys = [None, None]

    def _current(self, cam: int) -> int:
        """Key of the current frame's image of ``cam``, stored on first use."""
        if self._frame_keys[cam] is None:
            self._key += 1
            self.images[self._key] = (self._t, to_uint8(self._frame[cam]))
            self._frame_keys[cam] = self._key
        return self._frame_keys[cam]

    def anchor(self, obs: Observations) -> None:
        """Make the observations ``obs`` of the current frame the anchors of their (landmark, camera)."""
        for c in (0, 1):
            rows = np.flatnonzero(obs.cam == c)
            if len(rows) == 0:
                continue
            k = self._current(c)
            for i in rows:
                key = (int(obs.landmark[i]), c)
                old = self.anchors.get(key)
                if old is not None:
                    self._users[old[0]] -= 1
                self.anchors[key] = (k, obs.xy[i].copy())
                self._users[k] = self._users.get(k, 0) + 1
            self.stats.anchors += len(rows)

    def refine(self, obs: Observations) -> Observations:
        """``obs`` of the current frame with positions aligned to their anchors (a copy; shapes kept).
        Observations whose alignment fails keep their position (the anchor stays: measured on
        handheld_office, re-anchoring there raised the median error against the ground truth from 1.28
        to 1.48 px); those without a (fresh enough) anchor become their landmark's anchor."""
        n = len(obs)
        if n == 0:
            return obs
        xy = obs.xy.copy()
        new_anchor = np.zeros(n, bool)
        for c in (0, 1):
            groups: dict[int, list[int]] = {}
            for i in np.flatnonzero(obs.cam == c):
                a = self.anchors.get((int(obs.landmark[i]), c))
                if a is None or self._t - self.images[a[0]][0] > self.max_age_us:
                    new_anchor[i] = True
                elif self.images[a[0]][0] != self._t:
                    groups.setdefault(a[0], []).append(i)
            for k, idx in groups.items():
                idx = np.asarray(idx)
                ok, p1, shift = self._align(self.images[k][1], self.images[self._current(c)][1],
                                            np.stack([self.anchors[(int(obs.landmark[i]), c)][1] for i in idx]), obs.xy[idx])
                xy[idx[ok]] = p1[ok]
                self.stats.refined += int(ok.sum())
                self.stats.rejected += int((~ok).sum())
                self.stats.shift_sum_px += float(shift[ok].sum())
        out = Observations(obs.landmark, obs.cam, xy, obs.shape.copy(), obs.stereo_pair.copy())
        if new_anchor.any():
            self.anchor(out.subset(new_anchor))
        self._prune()
        return out

    def _align(self, ref: np.ndarray, cur: np.ndarray, xy_ref: np.ndarray, xy_guess: np.ndarray):
        """Lucas-Kanade from ``ref`` to ``cur`` started at the detections, with the forward-backward
        check. Returns (ok (M,), aligned pixels (M, 2), shift from the detection (M,))."""
        p0 = np.ascontiguousarray(xy_ref, np.float32).reshape(-1, 1, 2)
        guess = np.ascontiguousarray(xy_guess, np.float32).reshape(-1, 1, 2)
        p1, st, _ = cv2.calcOpticalFlowPyrLK(ref, cur, p0, guess.copy(), winSize=self.win, maxLevel=self.levels,
                                             criteria=self.criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        pb, stb, _ = cv2.calcOpticalFlowPyrLK(cur, ref, p1, p0.copy(), winSize=self.win, maxLevel=self.levels,
                                              criteria=self.criteria, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        p1, pb = p1.reshape(-1, 2), pb.reshape(-1, 2)
        shift = np.linalg.norm(p1 - guess.reshape(-1, 2), axis=1)
        ok = (st.ravel() == 1) & (stb.ravel() == 1) & np.isfinite(p1).all(1) & (shift <= self.max_shift)
        ok &= np.linalg.norm(pb - p0.reshape(-1, 2), axis=1) <= self.max_fb
        return ok, p1.astype(np.float64), shift

    def _prune(self) -> None:
        """Forget images older than the anchor age, with their anchors (those landmarks re-anchor), and
        images no anchor uses any more (a drone run would otherwise hold ~500 frames, 50 MB, of which
        ~100 are anchors)."""
        old = {k for k, (t, _) in self.images.items() if self._t - t > self.max_age_us}
        if old:
            self.anchors = {key: a for key, a in self.anchors.items() if a[0] not in old}
        unused = old | {k for k in self.images if self._users.get(k, 0) <= 0 and k not in self._frame_keys}
        if unused:
            self.images = {k: v for k, v in self.images.items() if k not in unused}
            self._users = {k: n for k, n in self._users.items() if k not in unused}
