"""Scoring keypoint methods on real time-surface pairs with frame-based pseudo ground truth.

The layout is the one published with SuperEvent's example data (``../shared/data/real_pairs``): a
folder of recordings, each holding

* ``time_surfaces/<frame>.npz``: one time surface (C, H, W) as C SciPy CSR matrices (object arrays
  ``data``, ``indices``, ``indptr``, ``shapes``), channel order polarity-major as in
  :mod:`aerovis_slam.mcts` (the published pairs are MCTS_dt, windows 1, 3, 10, 30, 100 ms);
* ``sg_matches/<frame0>_<frame1>.npz``: keypoints of the two synchronised intensity frames
  (``keypoints0`` (N, 2), ``keypoints1`` (M, 2), x = column, y = row) and their matches
  (``matches0`` (N,), an index into ``keypoints1`` or -1), e.g. SuperPoint + SuperGlue. Frames and
  events share one pixel array, so these are correspondences in time-surface pixels.

No intrinsics come with such pairs, so the reference geometry is the fundamental matrix ``F``
(``x1^T F x0 = 0``) fitted to the pseudo ground truth by MAGSAC++ (:func:`fit_reference`). A
method's mutual-nearest-neighbour matches are correct when their symmetric epipolar distance to ``F``
(:func:`aerovis_slam.geometry.symmetric_epipolar_distance`) is below a threshold
(2 px). Epipolar scoring cannot see a wrong match that slides along its epipolar line, so it is an
upper bound on precision; it needs no depth and no calibration, which is why it is the standard for
pairs like these.

Pixel convention as in :mod:`aerovis_slam.keypoints`. Importing this module never imports torch.
"""

from __future__ import annotations

import importlib
import pickle
import sys
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from aerovis_slam.errors import DataError
from aerovis_slam.geometry import symmetric_epipolar_distance
from aerovis_slam.keypoints import Keypoints, keep_top_k, match_keypoints

CORRECT_PX = 2.0          # a match is correct below this symmetric epipolar distance
REFERENCE_RANSAC_PX = 1.0  # the pseudo ground truth is keypoints on sharp frames: 1 px
REFERENCE_MIN_INLIERS = 15  # the 8-point refit needs 8; 15 leaves redundancy to expose a bad fit
SURFACES_DIR, MATCHES_DIR = "time_surfaces", "sg_matches"

# Names a published time-surface file may reference when unpickled (object arrays of float32/int32
# arrays): numpy's array reconstruction and dtypes, under their numpy 1 and numpy 2 module names.
_PICKLE_ALLOWED = {
    ("numpy", "ndarray"), ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
}


class _ArrayOnlyUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and nothing else.

    The published time surfaces are object arrays, which ``np.load`` reads only through pickle, and
    pickle can run arbitrary code. This evaluation is meant to be pointed at other people's pairs, so
    it resolves only numpy's own array constructors and refuses every other global."""

    def find_class(self, module: str, name: str):
        if (module, name) not in _PICKLE_ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} (only numpy arrays are allowed)")
        real = "numpy._core.multiarray" if module.startswith("numpy.") else module
        try:
            return getattr(importlib.import_module(real), name)
        except ImportError:  # numpy 1.x has no numpy._core
            return getattr(importlib.import_module(module), name)


def load_npz(path: str | Path) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz`` file; object arrays are read by a pickle loader restricted to numpy arrays.

    Raises:
        DataError: not a readable ``.npz``, a damaged member, or a pickle that references anything else.
    """
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            for member in zf.namelist():
                key = member[:-4] if member.endswith(".npy") else member
                with zf.open(member) as f:
                    version = np.lib.format.read_magic(f)
                    read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
                    shape, fortran, dtype = read_header(f)
                    if dtype.hasobject:
                        arr = _ArrayOnlyUnpickler(f).load()
                        if not isinstance(arr, np.ndarray):
                            raise ValueError(f"member {member!r} holds a {type(arr).__name__}, not an array")
                    else:
                        arr = np.frombuffer(f.read(), dtype=dtype)
                        if arr.size != int(np.prod(shape)):
                            raise ValueError(f"member {member!r} holds {arr.size} values, its header says {shape}")
                        arr = arr.reshape(shape, order="F" if fortran else "C")
                out[key] = arr
    except FileNotFoundError:
        raise DataError(path, "no such file") from None
    except (zipfile.BadZipFile, ValueError, EOFError, OSError, pickle.UnpicklingError, AttributeError, TypeError) as exc:
        raise DataError(path, f"not a readable .npz of numpy arrays ({type(exc).__name__}: {exc})") from None
    return out


def _field(data: dict, path: Path, key: str) -> np.ndarray:
    if key not in data:
        raise DataError(path, f"missing array {key!r} (has {sorted(data)})")
    return data[key]


def load_time_surface(path: str | Path) -> np.ndarray:
    """One time surface of the published layout -> float32 (C, H, W) in [0, 1].

    The file holds C CSR matrices (``data[c]``, ``indices[c]``, ``indptr[c]``, ``shapes[c] = (H, W)``);
    they are densified here with numpy (scipy is not a dependency of the project and a CSR matrix is
    three arrays).

    Raises:
        DataError: missing arrays, channels of different sizes, or CSR arrays that disagree.
    """
    path = Path(path)
    d = load_npz(path)
    data, indices, indptr, shapes = (_field(d, path, k) for k in ("data", "indices", "indptr", "shapes"))
    C = len(shapes)
    if C == 0 or not (len(data) == len(indices) == len(indptr) == C):
        raise DataError(path, f"expected one data/indices/indptr/shapes entry per channel, got {len(data)}/{len(indices)}/"
                              f"{len(indptr)}/{C}")
    try:
        hw = {(int(s[0]), int(s[1])) for s in shapes}
    except (TypeError, ValueError, IndexError):
        raise DataError(path, "'shapes' must hold one (rows, cols) pair per channel") from None
    if len(hw) != 1:
        raise DataError(path, f"'shapes': all channels must have one size, got {sorted(hw)}")
    H, W = hw.pop()
    if H <= 0 or W <= 0:
        raise DataError(path, f"'shapes': a channel of {H}x{W} pixels")
    out = np.zeros((C, H, W), np.float32)
    for c in range(C):
        ptr = np.asarray(indptr[c], np.int64).ravel()
        cols = np.asarray(indices[c], np.int64).ravel()
        vals = np.asarray(data[c], np.float32).ravel()
        if len(ptr) != H + 1 or ptr[0] != 0 or np.any(np.diff(ptr) < 0) or ptr[-1] != len(cols) or len(cols) != len(vals):
            raise DataError(path, f"channel {c}: CSR arrays disagree (indptr of {len(ptr)} for {H} rows, "
                                  f"{len(cols)} column indices, {len(vals)} values)")
        if len(cols) and (cols.min() < 0 or cols.max() >= W):
            raise DataError(path, f"channel {c}: column indices outside [0, {W})")
        if not np.all(np.isfinite(vals)):
            raise DataError(path, f"channel {c}: non-finite values")
        rows = np.repeat(np.arange(H), np.diff(ptr))
        out[c, rows, cols] = vals
    return out


def load_reference_matches(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo ground-truth correspondences of one pair file: (x0 (M, 2), x1 (M, 2)) float64 pixels.

    Raises:
        DataError: missing arrays, wrong shapes, indices outside ``keypoints1``, or non-finite positions.
    """
    path = Path(path)
    d = load_npz(path)
    kp0, kp1, m0 = (_field(d, path, k) for k in ("keypoints0", "keypoints1", "matches0"))
    for key, kp in (("keypoints0", kp0), ("keypoints1", kp1)):
        if kp.ndim != 2 or kp.shape[1] != 2 or not np.issubdtype(kp.dtype, np.number):
            raise DataError(path, f"{key!r} must be numeric (N, 2) x, y pixels, got {kp.dtype} {kp.shape}")
        if not np.all(np.isfinite(kp)):
            raise DataError(path, f"{key!r} holds non-finite positions")
    if m0.shape != (len(kp0),) or not np.issubdtype(m0.dtype, np.integer):
        raise DataError(path, f"'matches0' must be integer ({len(kp0)},) like 'keypoints0', got {m0.dtype} {m0.shape}")
    if np.any(m0 >= len(kp1)) or np.any(m0 < -1):
        raise DataError(path, f"'matches0' indexes outside keypoints1 (0..{len(kp1) - 1}, or -1 for unmatched)")
    i0 = np.flatnonzero(m0 >= 0)
    return kp0[i0].astype(np.float64), kp1[m0[i0]].astype(np.float64)


@dataclass(frozen=True)
class Reference:
    """The reference geometry of one pair.

    Attributes:
        F: (3, 3) fundamental matrix, ``x1^T F x0 = 0``.
        inliers: pseudo ground-truth matches within :data:`REFERENCE_RANSAC_PX` of it.
        matches: pseudo ground-truth matches in the file.
        residual_px: median symmetric epipolar distance of the inliers (the reference's own floor).
        distance_px: (matches,) symmetric epipolar distance of every pseudo ground-truth match.
    """

    F: np.ndarray
    inliers: int
    matches: int
    residual_px: float
    distance_px: np.ndarray


class NoGeometry(Exception):
    """The pseudo ground truth of a pair does not determine a fundamental matrix (the pair is skipped)."""


def fit_reference(x0: np.ndarray, x1: np.ndarray, *, ransac_px: float = REFERENCE_RANSAC_PX,
                  min_inliers: int = REFERENCE_MIN_INLIERS) -> Reference:
    """Fundamental matrix of pseudo ground-truth correspondences (OpenCV's MAGSAC++, ``ransac_px`` threshold).

    Raises:
        NoGeometry: fewer than ``min_inliers`` correspondences agree on one F (too few matches,
            or matches that fit no epipolar geometry).
    """
    x0 = np.ascontiguousarray(x0, np.float64).reshape(-1, 2)
    x1 = np.ascontiguousarray(x1, np.float64).reshape(-1, 2)
    if len(x0) < min_inliers:
        raise NoGeometry(f"{len(x0)} pseudo ground-truth matches, at least {min_inliers} needed")
    # MAGSAC++ (threshold-free scoring, its own least-squares polish): of OpenCV's estimators the one whose
    # F the most pseudo ground-truth matches agree with on the published pairs (67-79 % within 2 px,
    # against 63-68 % for plain RANSAC at 0.5-2 px); its sampler is seeded, so every run fits the same F.
    F, mask = cv2.findFundamentalMat(x0, x1, cv2.USAC_MAGSAC, ransac_px, 0.9999, 20000)
    if F is None or F.shape != (3, 3) or mask is None or int(mask.sum()) < min_inliers:
        found = 0 if mask is None else int(mask.sum())
        raise NoGeometry(f"only {found} of {len(x0)} pseudo ground-truth matches fit one fundamental matrix within "
                         f"{ransac_px:g} px, at least {min_inliers} needed")
    inl = mask.ravel().astype(bool)
    d = symmetric_epipolar_distance(F, x0, x1)
    return Reference(F=F / np.linalg.norm(F), inliers=int(inl.sum()), matches=len(x0), residual_px=float(np.median(d[inl])),
                     distance_px=d)


@dataclass(frozen=True)
class RealPair:
    """One pair of the layout (paths only; :func:`evaluate_real_pairs` reads it)."""

    recording: str       # the recording folder, relative to the root given
    frame0: str
    frame1: str
    surface0: Path
    surface1: Path
    matches: Path

    @property
    def name(self) -> str:
        return f"{self.recording}/{self.frame0}_{self.frame1}"


def find_recordings(root: str | Path) -> list[Path]:
    """Recording folders under ``root`` (``root`` itself included): those with both ``time_surfaces/`` and ``sg_matches/``."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(root, "no such folder" if not root.exists() else "expected a folder of recordings with time_surfaces/ and sg_matches/")
    found = sorted({p.parent for p in root.rglob(MATCHES_DIR) if p.is_dir() and (p.parent / SURFACES_DIR).is_dir()})
    if not found:
        raise DataError(root, f"no recording folder with {SURFACES_DIR}/ and {MATCHES_DIR}/ under it (layout: see aerovis-eval epipolar --help)")
    return found


def is_real_pairs_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder of this layout (for tools that take several kinds of data)."""
    try:
        return bool(find_recordings(path))
    except DataError:
        return False


def list_pairs(root: str | Path) -> list[RealPair]:
    """Every pair file of every recording under ``root``, in a fixed order, with its two time surfaces.

    A pair file ``<a>_<b>.npz`` names its frames; where frame names contain ``_`` themselves, the split
    whose two time surfaces both exist is taken.

    Raises:
        DataError: a pair file without its time surfaces, or a recording without pair files.
    """
    root = Path(root)
    pairs = []
    for rec in find_recordings(root):
        files = sorted(p for p in (rec / MATCHES_DIR).glob("*.npz") if p.is_file())
        if not files:
            raise DataError(rec / MATCHES_DIR, "holds no <frame0>_<frame1>.npz pair files")
        for f in files:
            stem = f.stem
            splits = [(stem[:i], stem[i + 1:]) for i, ch in enumerate(stem) if ch == "_"]
            found = [(a, b) for a, b in splits if (rec / SURFACES_DIR / f"{a}.npz").is_file() and (rec / SURFACES_DIR / f"{b}.npz").is_file()]
            if len(found) != 1:
                raise DataError(f, f"expected a name <frame0>_<frame1> with both frames in {rec / SURFACES_DIR} as <frame>.npz"
                                   + (f"; {len(found)} ways to split it" if found else ""))
            a, b = found[0]
            pairs.append(RealPair(str(rec.relative_to(root)) if rec != root else rec.name, a, b,
                                  rec / SURFACES_DIR / f"{a}.npz", rec / SURFACES_DIR / f"{b}.npz", f))
    return pairs


def score_matches(F: np.ndarray, xy0: np.ndarray, xy1: np.ndarray, matches: np.ndarray, correct_px: float = CORRECT_PX) -> dict:
    """How many of ``matches`` (index pairs into ``xy0``/``xy1``) agree with ``F`` within ``correct_px``.

    Returns:
        ``matches``, ``correct``, ``precision`` (correct / matches; None without matches) and
        ``distance_px``: the (M,) symmetric epipolar distances.
    """
    matches = np.asarray(matches, np.int64).reshape(-1, 2)
    d = symmetric_epipolar_distance(F, np.asarray(xy0)[matches[:, 0]], np.asarray(xy1)[matches[:, 1]])
    correct = int(np.sum(d < correct_px))
    return {"matches": len(matches), "correct": correct, "precision": correct / len(matches) if len(matches) else None, "distance_px": d}


def _check_surface(path: Path, mcts: np.ndarray, channels: int | None, shape: tuple | None) -> None:
    if channels is not None and mcts.shape[0] != channels:
        raise DataError(path, f"{mcts.shape[0]} channels, the method expects {channels} (its time surface)")
    if shape is not None and mcts.shape != shape:
        raise DataError(path, f"shape {mcts.shape} differs from its pair partner's {shape}")


def reference_of(pair: RealPair, cache: dict | None = None) -> Reference | NoGeometry:
    """The :func:`fit_reference` of one pair, or the :class:`NoGeometry` that refused it; fitted once per
    ``cache`` (a dict the caller keeps across methods)."""
    if cache is not None and pair.matches in cache:
        return cache[pair.matches]
    try:
        ref: Reference | NoGeometry = fit_reference(*load_reference_matches(pair.matches))
    except NoGeometry as exc:
        ref = exc
    if cache is not None:
        cache[pair.matches] = ref
    return ref


def evaluate_real_pairs(root: str | Path, detector, *, top_k: int | None = None, correct_px: float = CORRECT_PX,
                        channels: int | None = None, progress: bool = True, report_skips: bool = True,
                        references: dict | None = None) -> dict:
    """Score one method on every pair under ``root``.

    Each time surface goes through ``detector`` (``mcts (C, H, W) -> Keypoints``, or the name of a
    classical detector), keeping at most ``top_k`` keypoints (default ``max(H, W) // 2``, as the
    relative-pose protocol); the two frames' keypoints are matched by mutual nearest neighbours
    (:func:`aerovis_slam.keypoints.match_keypoints`) and scored against :func:`fit_reference`.

    Args:
        channels: if given, every time surface must have this many channels.
        report_skips: print a line on stderr for each skipped pair.
        references: a dict kept across calls on the same pairs, so that each reference is fitted once.

    Returns:
        ``{"summary": {...}, "per_pair": [...], "skipped": [{"pair", "reason"}]}``; the summary has
        ``method`` (the detector's name), ``pairs``, ``skipped``, ``matches`` and ``correct`` (means per pair), ``precision`` (all
        correct over all matches), ``precision_mean`` (mean of the pairs'), ``keypoints`` (mean per
        frame), ``latency_ms`` (mean per frame).
    Raises:
        DataError: bad files, or no pair with a reference geometry.
    """
    pairs = list_pairs(root)
    name = detector if isinstance(detector, str) else getattr(detector, "name", type(detector).__name__)
    per_pair, skipped, det_ms = [], [], []
    built: dict[int, object] = {}
    for pair in tqdm(pairs, desc=f"{name} pairs", unit="pair", file=sys.stderr, disable=not progress, leave=False):
        ref = reference_of(pair, references)
        if isinstance(ref, NoGeometry):
            skipped.append({"pair": pair.name, "reason": str(ref)})
            if report_skips:
                print(f"aerovis-eval: skipping {pair.matches}: {ref}", file=sys.stderr)
            continue
        mcts0 = load_time_surface(pair.surface0)
        _check_surface(pair.surface0, mcts0, channels, None)
        mcts1 = load_time_surface(pair.surface1)
        _check_surface(pair.surface1, mcts1, channels, mcts0.shape)
        _, H, W = mcts0.shape
        k = int(top_k) if top_k is not None else max(H, W) // 2
        if isinstance(detector, str):  # a classical baseline, built once per budget
            if k not in built:
                from aerovis_slam.classical import make_detector

                built[k] = make_detector(detector, top_k=k)
            det = built[k]
        else:
            det = detector
        kps: list[Keypoints] = []
        for mcts in (mcts0, mcts1):
            t0 = time.perf_counter()
            kp = det(mcts)
            det_ms.append((time.perf_counter() - t0) * 1e3)
            kps.append(keep_top_k(kp, k))
        m = match_keypoints(kps[0], kps[1])
        s = score_matches(ref.F, kps[0].xy, kps[1].xy, m, correct_px)
        per_pair.append({"pair": pair.name, "recording": pair.recording, "frames": [pair.frame0, pair.frame1],
                         "resolution": [W, H], "top_k": k, "keypoints": [len(kps[0]), len(kps[1])],
                         "matches": s["matches"], "correct": s["correct"], "precision": s["precision"],
                         "median_distance_px": float(np.median(s["distance_px"])) if s["matches"] else None,
                         "reference": {"matches": ref.matches, "inliers": ref.inliers, "residual_px": ref.residual_px,
                                       # how much of the pseudo ground truth itself passes the threshold
                                       "agreeing": int(np.sum(ref.distance_px < correct_px))}})
    if not per_pair:
        raise DataError(root, f"none of its {len(pairs)} pairs has pseudo ground truth that fits a geometry")
    return {"summary": summarize_pairs(per_pair, skipped, det_ms, name=name, data=str(root), correct_px=correct_px),
            "per_pair": per_pair, "skipped": skipped}


def summarize_pairs(per_pair: list[dict], skipped: list[dict], det_ms: list[float], *, name: str, data: str,
                    correct_px: float = CORRECT_PX) -> dict:
    """Pooled figures of :func:`evaluate_real_pairs`'s per-pair results (see there)."""
    matches = np.array([p["matches"] for p in per_pair], np.float64)
    correct = np.array([p["correct"] for p in per_pair], np.float64)
    precisions = [p["precision"] for p in per_pair if p["precision"] is not None]
    return {"method": name, "data": data, "pairs": len(per_pair), "skipped": len(skipped),
            "matches": float(matches.mean()), "correct": float(correct.mean()),
            "precision": float(correct.sum() / matches.sum()) if matches.sum() else 0.0,
            "precision_mean": float(np.mean(precisions)) if precisions else 0.0,
            "keypoints": float(np.mean([k for p in per_pair for k in p["keypoints"]])),
            "latency_ms": float(np.mean(det_ms)) if det_ms else 0.0, "correct_px": correct_px,
            "top_k": sorted({p["top_k"] for p in per_pair})}
