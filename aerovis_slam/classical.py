"""Classical keypoint baselines (OpenCV) computed on the same time surfaces as the networks.

Each baseline sees one 8-bit image made from the MCTS by :func:`mcts_to_image` and returns
:class:`~aerovis_slam.keypoints.Keypoints` with at most ``top_k`` keypoints:

* ``orb``: ORB (oFAST corners on an image pyramid, rotated BRIEF): uint8 (N, 32) bit strings,
  matched by Hamming distance.
* ``sift``: SIFT (DoG extrema, 128-D gradient histograms): float32 (N, 128), L2-normalised so
  that cosine mutual-NN matching ranks exactly as SIFT's usual Euclidean matching.
* ``gftt_brief``: Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) described by ORB's rBRIEF at
  a fixed orientation of 0 (``ORB.compute`` on the given keypoints): uint8 (N, 32). Plain BRIEF
  needs opencv-contrib; rBRIEF's learned sampling pattern at orientation 0 is the closest
  stock-OpenCV equivalent. Like BRIEF it is not rotation invariant, which suits the protocol's
  pairs (at most ~45 deg of camera rotation, little of it about the optical axis).

Example:
    >>> mcts = np.zeros((8, 120, 160), np.float32)
    >>> mcts[:, 40:80, 50:110] = 0.8  # a bright rectangle: four corners
    >>> kp = make_detector("gftt_brief", top_k=10)(mcts)
    >>> kp.descriptors.dtype, kp.descriptors.shape[1], len(kp) >= 4
    (dtype('uint8'), 32, True)
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from aerovis_slam.keypoints import Keypoints

ORB_BYTES = 32
SIFT_DIM = 128


def mcts_to_image(mcts: np.ndarray, channel: int | None = None, *, reduce: str = "max") -> np.ndarray:
    """One 8-bit image from a (2K, H, W) polarity-major MCTS for the classical detectors.

    The default is ``255 * max(TS_off_k, TS_on_k)`` with ``k = K // 2``, the middle window: for
    MCTS_dt (1, 3, 10, 30, 100 ms) that is 10 ms, the single time surface of SuperEvent's
    ablation; for MCTS_Ne (0.03, 0.1, 0.3, 1 events/px) it is 0.3 events per pixel. Why:

    * max over polarities: the polarity of an edge flips with the direction of motion and with the
      sign of the contrast, so the union keeps the edge shape whatever the motion, without the
      cancellation a signed difference would cause;
    * a middle window: the shortest windows are sparse and noisy (few events per pixel, corners
      break up), the longest smear edges into wide ramps whose maxima drift; the middle one gives
      thin edges with a short decaying tail, which FAST, DoG and Shi-Tomasi treat as ordinary
      image structure.

    Args:
        mcts: float32 (2K, H, W), values in [0, 1], channel ``p * K + k``.
        channel: window index ``k`` in [0, K) (default ``K // 2``).
        reduce: ``"max"`` (default) or ``"mean"`` over the two polarities.
    Returns:
        uint8 (H, W).
    """
    mcts = np.asarray(mcts)
    if mcts.ndim != 3 or mcts.shape[0] % 2:
        raise ValueError(f"mcts must be (2K, H, W) with an even channel count, got shape {mcts.shape}")
    K = mcts.shape[0] // 2
    k = K // 2 if channel is None else int(channel)
    if not 0 <= k < K:
        raise ValueError(f"channel {k} outside [0, {K})")
    pair = mcts[[k, K + k]]
    if reduce == "max":
        img = pair.max(axis=0)
    elif reduce == "mean":
        img = pair.mean(axis=0)
    else:
        raise ValueError(f"reduce must be 'max' or 'mean', not {reduce!r}")
    return np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)


def _from_cv(kps, desc, dim: int, dtype) -> Keypoints:
    if desc is None or len(kps) == 0:
        return Keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, dim), dtype))
    xy = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
    scores = np.array([k.response for k in kps], np.float32)
    return Keypoints(xy, scores, np.ascontiguousarray(desc, dtype=dtype))


def _top(kp: Keypoints, top_k: int) -> Keypoints:
    order = np.argsort(-kp.scores, kind="stable")[:top_k]
    return Keypoints(kp.xy[order], kp.scores[order], kp.descriptors[order])


class ClassicalDetector:
    """A detector on ``mcts_to_image(mcts)``; see the module docstring for the kinds.

    Args:
        kind: ``orb``, ``sift`` or ``gftt_brief``.
        top_k: keypoint budget per image.
        channel, reduce: passed to :func:`mcts_to_image`.
        **options: detector options, e.g. ``fast_threshold`` (ORB, default 20),
            ``quality_level`` / ``min_distance`` (GFTT, default 0.01 / 3 px),
            ``contrast_threshold`` (SIFT, default 0.04).

    Attributes:
        name: the kind (reported as ``model``).
    """

    def __init__(self, kind: str, top_k: int = 500, channel: int | None = None, reduce: str = "max", **options):
        if kind not in DETECTORS:
            raise ValueError(f"unknown classical detector {kind!r}; choose one of {sorted(DETECTORS)}")
        self.name = kind
        self.kind = kind
        self.top_k = int(top_k)
        self.channel, self.reduce = channel, reduce
        self.options = options
        if kind == "orb":
            self._orb = cv2.ORB_create(nfeatures=self.top_k, fastThreshold=int(options.get("fast_threshold", 20)))
        elif kind == "gftt_brief":
            # edgeThreshold and patchSize 31: the rBRIEF pattern needs a 31x31 patch around each corner.
            self._orb = cv2.ORB_create(nfeatures=self.top_k, edgeThreshold=31, patchSize=31)
        else:
            self._sift = cv2.SIFT_create(nfeatures=self.top_k, contrastThreshold=float(options.get("contrast_threshold", 0.04)))

    def __call__(self, mcts: np.ndarray) -> Keypoints:
        """Keypoints of one MCTS: float32 (2K, H, W) -> :class:`Keypoints` (at most ``top_k``)."""
        img = mcts_to_image(mcts, self.channel, reduce=self.reduce)
        if self.kind == "orb":
            kps, desc = self._orb.detectAndCompute(img, None)
            kp = _from_cv(kps, desc, ORB_BYTES, np.uint8)
        elif self.kind == "sift":
            kps, desc = self._sift.detectAndCompute(img, None)
            kp = _from_cv(kps, desc, SIFT_DIM, np.float32)
            if len(kp):
                kp.descriptors /= np.maximum(np.linalg.norm(kp.descriptors, axis=1, keepdims=True), 1e-12)
        else:
            kp = self._gftt_brief(img)
        return _top(kp, self.top_k)

    def _gftt_brief(self, img: np.ndarray) -> Keypoints:
        quality = float(self.options.get("quality_level", 0.01))
        min_dist = float(self.options.get("min_distance", 3))
        corners = cv2.goodFeaturesToTrack(img, maxCorners=self.top_k, qualityLevel=quality, minDistance=min_dist, blockSize=3)
        if corners is None:
            return _from_cv([], None, ORB_BYTES, np.uint8)
        xy = corners.reshape(-1, 2)
        # goodFeaturesToTrack returns no scores: the Shi-Tomasi response (smaller Hessian-of-
        # structure-tensor eigenvalue) at each corner is what it ranked them by.
        eig = cv2.cornerMinEigenVal(img, blockSize=3)
        resp = eig[np.rint(xy[:, 1]).astype(int), np.rint(xy[:, 0]).astype(int)]
        cv_kps = [cv2.KeyPoint(float(x), float(y), 31.0, 0.0, float(r)) for (x, y), r in zip(xy, resp)]
        # compute() drops keypoints too close to the border for the 31x31 patch: use its returned list
        cv_kps, desc = self._orb.compute(img, cv_kps)
        return _from_cv(cv_kps, desc, ORB_BYTES, np.uint8)


DETECTORS: dict[str, str] = {
    "orb": "ORB (oFAST + rBRIEF), Hamming matching",
    "sift": "SIFT, L2-normalised float descriptors, cosine matching",
    "gftt_brief": "Shi-Tomasi corners + rBRIEF at orientation 0, Hamming matching",
}


def make_detector(name: str, **kw) -> Callable[[np.ndarray], Keypoints]:
    """Build a classical baseline by name (``orb``, ``sift``, ``gftt_brief``); ``kw`` go to :class:`ClassicalDetector`."""
    return ClassicalDetector(name, **kw)
