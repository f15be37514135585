"""Parity of a bundle with the PyTorch model it came from, on held-out sequences.

Both detectors run the evaluation protocol of :mod:`aerovis_train.eval.pose` (MCTS along the GT,
SuperEvent pairs, top-k = max(H, W) / 2 keypoints with threshold 0, mutual nearest neighbours, RANSAC)
on the same frames and pairs:

* ``keypoint_repeatability``: fraction of the PyTorch model's top-k keypoints that the bundle
  reproduces within 1 px (pooled over all frames);
* ``descriptor_cosine``: mean cosine similarity of the two descriptors at those matched keypoints
  (each model's own descriptor at its own keypoint, as the runtime sees it);
* ``auc10_torch`` / ``auc10_onnx``: rotation AUC@10 (percent) of each on the same pairs.

Targets of issue 6 on the ``bench`` preset: FP32/FP16 repeatability >= 0.95, cosine >= 0.99 and AUC@10
within 1 point; INT8 AUC@10 within 2 points.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import numpy as np

from aerovis_slam.bundle import BundleDetector
from aerovis_slam.errors import DataError
from aerovis_slam.keypoints import Keypoints

TARGETS = {"fp32": {"keypoint_repeatability": 0.95, "descriptor_cosine": 0.99, "auc10_abs_diff": 1.0},
           "fp16": {"keypoint_repeatability": 0.95, "descriptor_cosine": 0.99, "auc10_abs_diff": 1.0},
           "int8": {"auc10_abs_diff": 2.0}}
MATCH_PX = 1.0


class _CachedDetector:
    """A detector whose results are remembered by input content (the second evaluation pass of the
    same frames costs nothing)."""

    def __init__(self, det):
        self.det = det
        self.name = det.name
        self.mcts_kind, self.mcts_params = det.mcts_kind, det.mcts_params
        self.size_multiple = det.size_multiple
        self._cache: dict[tuple[bytes, int | None], Keypoints] = {}

    def __call__(self, mcts: np.ndarray, top_k: int | None = None) -> Keypoints:
        key = (hashlib.blake2b(np.ascontiguousarray(mcts).tobytes(), digest_size=16).digest(), top_k)
        if key not in self._cache:
            self._cache[key] = self.det(mcts, top_k=top_k)
        return self._cache[key]


class _ParityProbe:
    """Runs the bundle for the evaluation and, on the same MCTS, compares it with the torch model."""

    def __init__(self, onnx_det: BundleDetector, torch_det: _CachedDetector):
        self.onnx, self.torch = onnx_det, torch_det
        self.name = onnx_det.name
        self.mcts_kind, self.mcts_params = onnx_det.mcts_kind, onnx_det.mcts_params
        self.size_multiple = onnx_det.size_multiple
        self.n_ref = 0
        self.n_matched = 0
        self.cosines: list[np.ndarray] = []
        self.frames = 0

    def __call__(self, mcts: np.ndarray) -> Keypoints:
        k = max(mcts.shape[-2:]) // 2  # the protocol's budget, applied to both before comparing
        ref = self.torch(mcts, top_k=k)
        got = self.onnx(mcts, top_k=k)
        self.frames += 1
        self.n_ref += len(ref)
        if len(ref) and len(got):
            # at most max(H, W) / 2 points per image: a dense distance matrix is small
            d2 = ((ref.xy[:, None, :] - got.xy[None, :, :]) ** 2).sum(-1)
            idx = d2.argmin(1)
            dist = np.sqrt(d2[np.arange(len(ref)), idx])
            ok = dist <= MATCH_PX
            self.n_matched += int(ok.sum())
            self.cosines.append(np.sum(ref.descriptors[ok] * got.descriptors[idx[ok]], axis=1))
        return got


def compute_parity(model, model_cfg: dict, bundle_dir: str | Path, sequences: list[Path], *, cam: str = "cam0",
                   rate_hz: float | None = 20.0, max_pairs: int | None = 40, max_dt_s: float = 2.0,
                   max_angle_deg: float = 45.0, threads: int | None = None, progress: bool = True) -> dict:
    """Parity figures of a bundle against its PyTorch model (see the module docstring).

    Sequences without pairs (no 45 deg rotation within 2 s) and, for a bundle of fixed resolution,
    sequences of another size are skipped and listed.

    Raises:
        DataError: no sequence yields pairs.
    """
    from tqdm.auto import tqdm

    from aerovis_train.eval.learned import TorchDetector
    from aerovis_train.eval.pose import evaluate_sequence, summarize

    onnx_det = BundleDetector(bundle_dir, threads=threads, threshold=0.0)
    b = onnx_det.bundle
    torch_det = _CachedDetector(TorchDetector(model, model_cfg, threshold=0.0, nms_radius=b.nms_radius))
    probe = _ParityProbe(onnx_det, torch_det)
    kw = dict(cam=cam, rate_hz=rate_hz, max_pairs=max_pairs, max_dt_s=max_dt_s, max_angle_deg=max_angle_deg, progress=False)
    pairs_torch, pairs_onnx, used, skipped = [], [], [], []
    for p in tqdm(sequences, desc=f"parity {b.name} {b.precision}", unit="seq", file=sys.stderr, disable=not progress, leave=False):
        try:
            if not b.dynamic_hw:
                from aerovis_slam.io.sequence import Sequence

                with Sequence(p) as seq:
                    w, h = seq.sensor_size(cam)
                m = b.size_multiple
                if (h - h % m, w - w % m) != (b.height, b.width):
                    skipped.append(f"{p.name}: {h - h % m}x{w - w % m} after cropping, the bundle takes only {b.height}x{b.width}")
                    continue
            r_onnx = evaluate_sequence(p, probe, **kw)
            r_torch = evaluate_sequence(p, torch_det, **kw)
        except DataError as exc:
            if "no frame pairs" not in str(exc):
                raise
            skipped.append(f"{p.name}: no frame pairs")
            continue
        used.append(p.name)
        pairs_onnx.extend(r_onnx["per_pair"])
        pairs_torch.extend(r_torch["per_pair"])
    if not used:
        raise DataError(sequences[0].parent if sequences else None, f"parity: no sequence yields pairs ({'; '.join(skipped)})")
    s_torch, s_onnx = summarize(pairs_torch), summarize(pairs_onnx)
    cos = np.concatenate(probe.cosines) if probe.cosines else np.zeros(0)
    result = {
        "keypoint_repeatability": probe.n_matched / max(probe.n_ref, 1),
        "descriptor_cosine": float(cos.mean()) if len(cos) else float("nan"),
        "auc10_torch": s_torch["auc10"],
        "auc10_onnx": s_onnx["auc10"],
        "auc5_torch": s_torch["auc5"], "auc5_onnx": s_onnx["auc5"],
        "auc20_torch": s_torch["auc20"], "auc20_onnx": s_onnx["auc20"],
        "matches_torch": s_torch["matches"], "matches_onnx": s_onnx["matches"],
        "pairs": s_onnx["pairs"], "frames": probe.frames, "keypoints_compared": probe.n_ref,
        "sequences": used, "skipped": skipped,
        "protocol": {"cam": cam, "rate_hz": rate_hz, "max_pairs_per_sequence": max_pairs, "max_dt_s": max_dt_s,
                     "max_angle_deg": max_angle_deg, "top_k": "max(H, W) // 2", "threshold": 0.0, "match_px": MATCH_PX},
        "precision": b.precision, "target": b.target,
    }
    result.update(check_targets(result, b.precision))
    return result


def check_targets(parity: dict, precision: str) -> dict:
    """``{"targets": ..., "meets_targets": bool}`` against the issue's targets for ``precision``."""
    t = TARGETS[precision]
    ok = abs(parity["auc10_torch"] - parity["auc10_onnx"]) <= t["auc10_abs_diff"]
    if "keypoint_repeatability" in t:
        ok &= parity["keypoint_repeatability"] >= t["keypoint_repeatability"]
        ok &= parity["descriptor_cosine"] >= t["descriptor_cosine"]
    return {"targets": t, "meets_targets": bool(ok)}
