"""Real-pair evaluation (``aerovis-eval pairs``): the published layout, the epipolar scorer, bad input.

The constructed pairs below come from a known camera pair (intrinsics K, relative pose R, t), so the
true fundamental matrix ``F = K^-T [t]_x R K^-1`` is known and every distance can be computed by hand.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aerovis_slam.geometry import symmetric_epipolar_distance
from aerovis_slam.keypoints import Keypoints
from aerovis_train.eval import cli
from aerovis_train.eval.real_pairs import (
    evaluate_real_pairs,
    fit_reference,
    list_pairs,
    load_time_surface,
    score_matches,
)

W, H = 346, 260
K = np.array([[220.0, 0, 172.0], [0, 220.0, 131.0], [0, 0, 1]])


def skew(t):
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def rot_y(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


R_10 = rot_y(4.0)                   # camera 1 from camera 0
T_10 = np.array([0.3, 0.04, 0.08])  # metres
F_TRUE = np.linalg.inv(K).T @ skew(T_10) @ R_10 @ np.linalg.inv(K)


def scene(n, seed=0):
    """n points in view of both cameras: their pixels (x0, x1), (n, 2) each."""
    rng = np.random.default_rng(seed)
    X = np.column_stack([rng.uniform(-1.5, 1.5, 4 * n), rng.uniform(-1.0, 1.0, 4 * n), rng.uniform(2.0, 8.0, 4 * n)])
    x0 = (K @ X.T).T
    x0 = x0[:, :2] / x0[:, 2:]
    X1 = (R_10 @ X.T).T + T_10
    x1 = (K @ X1.T).T
    x1 = x1[:, :2] / x1[:, 2:]
    ok = np.all((x0 > 20) & (x0 < [W - 20, H - 20]) & (x1 > 20) & (x1 < [W - 20, H - 20]), axis=1)
    return x0[ok][:n], x1[ok][:n]


def write_surface(path: Path, mcts: np.ndarray) -> None:
    """The published format: one CSR matrix per channel as object arrays (written with numpy only)."""
    data, indices, indptr, shapes = [], [], [], []
    for ch in mcts:
        rows, cols = np.nonzero(ch)
        data.append(ch[rows, cols].astype(np.float32))
        indices.append(cols.astype(np.int32))
        indptr.append(np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=ch.shape[0]))]).astype(np.int32))
        shapes.append(ch.shape)
    obj = lambda xs: np.array(xs + [None], dtype=object)[:-1]  # noqa: E731 - a 1-D object array of arrays
    np.savez(path, data=obj(data), indices=obj(indices), indptr=obj(indptr), shapes=np.array(shapes, dtype=object))


def write_pair(rec: Path, x0, x1, frames=("000010", "000020"), marker=(0.25, 0.75), n_extra0=0):
    """A recording folder with one pair: time surfaces marked at pixel (0, 0) to tell the frames apart,
    and pseudo ground truth matching x0[i] <-> x1[i] (plus ``n_extra0`` unmatched keypoints)."""
    (rec / "time_surfaces").mkdir(parents=True, exist_ok=True)
    (rec / "sg_matches").mkdir(parents=True, exist_ok=True)
    for frame, xy, mark in zip(frames, (x0, x1), marker):
        mcts = np.zeros((10, H, W), np.float32)
        for x, y in np.rint(xy).astype(int):
            mcts[2, y - 1:y + 2, x - 1:x + 2] = 0.8
        mcts[0, 0, 0] = mark
        write_surface(rec / "time_surfaces" / f"{frame}.npz", mcts)
    kp0 = np.vstack([x0, np.full((n_extra0, 2), 5.0)]).astype(np.float32)
    matches0 = np.concatenate([np.arange(len(x0)), -np.ones(n_extra0, int)]).astype(np.int64)
    np.savez(rec / "sg_matches" / f"{frames[0]}_{frames[1]}.npz", keypoints0=kp0, keypoints1=np.asarray(x1, np.float32),
             matches0=matches0, matches1=np.arange(len(x1)))


class OracleDetector:
    """Keypoints at the given pixels with one-hot descriptors (point i matches point i); the frame is
    told by the marker at pixel (0, 0). A second-frame offset moves chosen points off the truth."""

    name = "oracle"

    def __init__(self, frames: dict[float, np.ndarray]):
        self.frames = frames

    def __call__(self, mcts):
        xy = self.frames[round(float(mcts[0, 0, 0]), 2)]
        n = len(xy)
        return Keypoints(np.asarray(xy, np.float32), np.linspace(1.0, 0.5, n, dtype=np.float32), np.eye(n, dtype=np.float32))


def epipolar_normal_offset(F, x0, x1, px):
    """x1 moved by ``px`` along the normal of x0's epipolar line in image 1 (its distance to that line becomes px)."""
    line = np.hstack([x0, np.ones((len(x0), 1))]) @ F.T
    n = line[:, :2] / np.linalg.norm(line[:, :2], axis=1, keepdims=True)
    return x1 + px * n


def test_symmetric_epipolar_distance_matches_hand_computed_values():
    # rectified stereo (K = I, t along x): epipolar lines are the rows, so each point lies |y1 - y0|
    # from the other's line and the symmetric distance is sqrt(2) |y1 - y0|
    F = skew([1.0, 0.0, 0.0])
    x0 = np.array([[10.0, 20.0], [5.0, 5.0], [40.0, 7.0]])
    x1 = np.array([[15.0, 23.0], [100.0, 5.0], [2.0, 6.5]])
    expected = np.sqrt(2) * np.array([3.0, 0.0, 0.5])
    np.testing.assert_allclose(symmetric_epipolar_distance(F, x0, x1), expected, atol=1e-12)
    # F is defined up to scale: the distance is not
    np.testing.assert_allclose(symmetric_epipolar_distance(-7.5 * F, x0, x1), expected, atol=1e-12)


def test_true_correspondences_lie_on_their_epipolar_lines_and_offsets_are_measured():
    x0, x1 = scene(50)
    np.testing.assert_allclose(symmetric_epipolar_distance(F_TRUE, x0, x1), 0.0, atol=1e-9)
    # moved 3 px off the line in image 1: d1 = 3 exactly, and d0 = d1 |l1| / |l0| (one algebraic error,
    # two line normalisations), so the symmetric distance is 3 sqrt(1 + (|l1| / |l0|)^2)
    moved = epipolar_normal_offset(F_TRUE, x0, x1, 3.0)
    h0, h1 = np.hstack([x0, np.ones((50, 1))]), np.hstack([moved, np.ones((50, 1))])
    l1, l0 = (h0 @ F_TRUE.T)[:, :2], (h1 @ F_TRUE)[:, :2]
    ratio = np.linalg.norm(l1, axis=1) / np.linalg.norm(l0, axis=1)
    np.testing.assert_allclose(symmetric_epipolar_distance(F_TRUE, x0, moved), 3.0 * np.sqrt(1 + ratio**2), rtol=1e-9)


def test_score_matches_counts_matches_below_the_threshold():
    F = skew([1.0, 0.0, 0.0])
    xy0 = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0], [40.0, 40.0]])
    xy1 = np.array([[50.0, 10.0], [60.0, 21.0], [70.0, 31.5], [80.0, 43.0]])  # |dy| 0, 1, 1.5, 3: sqrt(2) |dy| = 0, 1.41, 2.12, 4.24
    s = score_matches(F, xy0, xy1, np.array([[0, 0], [1, 1], [2, 2], [3, 3]]), correct_px=2.0)
    assert (s["matches"], s["correct"], s["precision"]) == (4, 2, 0.5)
    assert score_matches(F, xy0, xy1, np.zeros((0, 2), int))["precision"] is None


def test_fit_reference_recovers_known_geometry_from_noisy_matches_with_outliers():
    rng = np.random.default_rng(1)
    x0, x1 = scene(200, seed=1)
    noisy1 = x1[:120] + rng.normal(0, 0.5, (120, 2))  # SuperPoint-like localisation noise
    wrong = rng.uniform([0, 0], [W, H], (40, 2))      # 25 % outliers
    ref = fit_reference(np.vstack([x0[:120], x0[120:160]]), np.vstack([noisy1, wrong]))
    # one-sided distances of the inliers are N(0, 0.5 px): 95 % within the 1 px threshold
    assert ref.inliers >= 0.85 * 120 and ref.matches == 160
    # on correspondences it never saw, the fitted F is far inside the noise: an F estimated from
    # ~110 matches at 0.5 px predicts lines to about 0.5 sqrt(8 / 110) ~ 0.13 px
    held_out = symmetric_epipolar_distance(ref.F, x0[160:], x1[160:])
    assert np.median(held_out) < 0.5


def test_evaluate_real_pairs_scores_an_oracle_and_its_displaced_matches(tmp_path):
    x0, x1 = scene(60, seed=2)
    write_pair(tmp_path / "seqA", x0, x1)
    det = OracleDetector({0.25: x0, 0.75: x1})
    r = evaluate_real_pairs(tmp_path, det, progress=False)
    s = r["summary"]
    assert (s["pairs"], s["skipped"], s["matches"], s["correct"], s["precision"]) == (1, 0, 60, 60, 1.0)
    # 20 of the second frame's keypoints moved 5 px off their epipolar lines: symmetric distance >= 5 px
    moved = x1.copy()
    moved[:20] = epipolar_normal_offset(F_TRUE, x0[:20], x1[:20], 5.0)
    s = evaluate_real_pairs(tmp_path, OracleDetector({0.25: x0, 0.75: moved}), progress=False)["summary"]
    assert (s["matches"], s["correct"]) == (60, 40) and s["precision"] == pytest.approx(40 / 60)
    # top-k keeps the highest scores: the first 10 keypoints of each frame
    s = evaluate_real_pairs(tmp_path, det, top_k=10, progress=False)["summary"]
    assert (s["matches"], s["correct"], s["keypoints"]) == (10, 10, 10)


def test_layout_round_trip_and_frame_names_with_underscores(tmp_path):
    x0, x1 = scene(30, seed=3)
    write_pair(tmp_path / "ds" / "rec_1", x0, x1, frames=("cam_0010", "cam_0020"))
    pairs = list_pairs(tmp_path)
    assert [(p.recording, p.frame0, p.frame1) for p in pairs] == [("ds/rec_1", "cam_0010", "cam_0020")]
    mcts = load_time_surface(pairs[0].surface0)
    assert mcts.shape == (10, H, W) and mcts.dtype == np.float32
    x, y = np.rint(x0[0]).astype(int)
    assert mcts[2, y, x] == np.float32(0.8) and mcts[0, 0, 0] == np.float32(0.25)


def test_cli_pairs_prints_one_line_per_method_and_skips_pairs_without_geometry(tmp_path, capsys):
    x0, x1 = scene(60, seed=4)
    write_pair(tmp_path / "good", x0, x1)
    write_pair(tmp_path / "few", x0[:6], x1[:6])  # 6 pseudo ground-truth matches: no fundamental matrix
    out = tmp_path / "res" / "pairs.json"
    assert cli.main(["pairs", "--data", str(tmp_path), "--detector", "orb", "gftt_brief", "--out", str(out), "--quiet"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["method"] for x in lines] == ["orb", "gftt_brief"]
    for x in lines:
        assert (x["pairs"], x["skipped"]) == (1, 1)
        assert 0 <= x["correct"] <= x["matches"] and x["precision"] == pytest.approx(x["correct"] / x["matches"] if x["matches"] else 0)
    saved = json.loads(out.read_text())
    assert saved["methods"][0]["skipped"][0]["pair"] == "few/000010_000020"


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0], err
    return err[0]


def test_cli_pairs_bad_input_gets_one_line_naming_file_and_field(tmp_path, capsys):
    x0, x1 = scene(40, seed=5)
    rec = tmp_path / "rec"
    write_pair(rec, x0, x1)
    args = ["pairs", "--data", str(tmp_path), "--detector", "orb", "--quiet"]
    match_file = rec / "sg_matches" / "000010_000020.npz"
    good = dict(np.load(match_file))

    np.savez(match_file, **{k: v for k, v in good.items() if k != "matches0"})
    assert cli.main(args) == 2
    msg = _one_line_error(capsys)
    assert str(match_file) in msg and "'matches0'" in msg

    np.savez(match_file, **{**good, "matches0": good["matches0"] + 1000})
    assert cli.main(args) == 2
    assert "indexes outside keypoints1" in _one_line_error(capsys)

    np.savez(match_file, **good)
    surface = rec / "time_surfaces" / "000020.npz"
    write_surface(surface, np.zeros((8, H, W), np.float32))  # 8 channels: not the 10 of MCTS_dt
    assert cli.main(args) == 2
    msg = _one_line_error(capsys)
    assert str(surface) in msg and "8 channels" in msg

    surface.write_bytes(b"PK\x03\x04 not really a zip")
    assert cli.main(args) == 2
    assert str(surface) in _one_line_error(capsys)

    assert cli.main(["pairs", "--data", str(tmp_path / "none"), "--detector", "orb"]) == 2
    assert "no such folder" in _one_line_error(capsys)
    assert cli.main(["pairs", "--data", str(tmp_path), "--detector", "orb", "--correct-px", "nan"]) == 2
    assert "--correct-px" in _one_line_error(capsys)


class _Evil:
    def __reduce__(self):
        return (Path.touch, (Path(self.target),))


def test_pickled_code_in_a_time_surface_is_refused(tmp_path, capsys):
    x0, x1 = scene(40, seed=6)
    rec = tmp_path / "rec"
    write_pair(rec, x0, x1)
    evil = _Evil()
    evil.target = str(tmp_path / "pwned")
    surface = rec / "time_surfaces" / "000010.npz"
    arr = np.empty(1, dtype=object)
    arr[0] = evil
    np.savez(surface, data=arr, indices=arr, indptr=arr, shapes=arr)
    np.load(surface, allow_pickle=True)["data"]  # the payload is a working exploit for a trusting loader
    assert (tmp_path / "pwned").exists()
    (tmp_path / "pwned").unlink()
    assert cli.main(["pairs", "--data", str(tmp_path), "--detector", "orb", "--quiet"]) == 2
    assert "refusing to load" in _one_line_error(capsys)
    assert not (tmp_path / "pwned").exists()


def test_models_of_another_surface_are_refused(tmp_path, capsys):
    x0, x1 = scene(40, seed=7)
    write_pair(tmp_path / "rec", x0, x1)
    assert cli.main(["pairs", "--data", str(tmp_path), "--model", "superlite"]) == 2
    msg = _one_line_error(capsys)
    assert "MCTS_Ne" in msg and "MCTS_dt" in msg


def test_published_real_pairs_load_and_fit(shared_data):
    root = shared_data / "real_pairs"
    pairs = list_pairs(root)
    assert len(pairs) == 3
    for p in pairs:
        mcts = load_time_surface(p.surface0)
        assert mcts.shape == (10, 260, 346) and 0.0 <= mcts.min() and mcts.max() <= 1.0
    r = evaluate_real_pairs(root, "orb", progress=False)
    for pp in r["per_pair"]:
        ref = pp["reference"]
        # SuperPoint keypoints on 346x260 frames: the fitted F explains most of them within its 1 px threshold
        assert ref["inliers"] >= 0.5 * ref["matches"] and ref["residual_px"] < 1.0


def test_compare_on_a_real_pairs_folder_gives_the_same_rows(tmp_path, capsys):
    x0, x1 = scene(60, seed=8)
    write_pair(tmp_path / "data" / "rec", x0, x1)
    data, out = str(tmp_path / "data"), tmp_path / "cmp"
    assert cli.main(["pairs", "--data", data, "--detector", "orb", "--quiet"]) == 0
    alone = json.loads(capsys.readouterr().out)
    # superlite (MCTS_Ne) is left out with its reason; orb's row is the pairs command's
    assert cli.main(["compare", "--data", data, "--models", "superlite", "--detectors", "orb", "--out", str(out), "--quiet"]) == 0
    cap = capsys.readouterr()
    rows = [json.loads(x) for x in cap.out.splitlines()]
    assert [r["method"] for r in rows] == ["orb"] and "superlite" in cap.err and "left out" in cap.err
    for key in ("pairs", "matches", "correct", "precision"):
        assert rows[0][key] == alone[key]
    saved = json.loads((out / "compare.json").read_text())
    assert saved["kind"] == "real_pairs" and saved["left_out"][0]["method"] == "superlite"
    assert (out / "compare.md").read_text().count("| orb |") == 1


def test_a_bundle_scores_as_its_checkpoint_does(tmp_path, capsys):
    from aerovis_slam.bundle import DEFAULT_BUNDLE_DIR

    if not (DEFAULT_BUNDLE_DIR / "model.onnx").exists():
        pytest.skip(f"no default bundle at {DEFAULT_BUNDLE_DIR}")
    x0, x1 = scene(60, seed=9)
    rec = tmp_path / "rec"
    write_pair(rec, x0, x1)
    for f in (rec / "time_surfaces").glob("*.npz"):  # MCTS_Ne pairs: 8 channels
        write_surface(f, load_time_surface(f)[:8])
    assert cli.main(["pairs", "--data", str(tmp_path), "--mcts", "ne", "--model", str(DEFAULT_BUNDLE_DIR), "superlite", "--quiet"]) == 0
    bundle, torch_model = (json.loads(x) for x in capsys.readouterr().out.splitlines())
    # the default bundle is the shipped SuperLitE in FP32 (parity-checked at export): the same keypoints and matches
    assert bundle["keypoints"] == torch_model["keypoints"] and bundle["matches"] == torch_model["matches"]
    assert bundle["correct"] == torch_model["correct"]


def test_each_reference_is_fitted_once_for_all_methods(tmp_path, capsys, monkeypatch):
    import aerovis_train.eval.real_pairs as rp

    x0, x1 = scene(40, seed=10)
    write_pair(tmp_path / "a", x0, x1)
    write_pair(tmp_path / "b", x0, x1)
    calls = []
    real_fit = rp.fit_reference
    monkeypatch.setattr(rp, "fit_reference", lambda *a, **k: calls.append(1) or real_fit(*a, **k))
    assert cli.main(["pairs", "--data", str(tmp_path), "--detector", "orb", "sift", "gftt_brief", "--quiet"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 3 and len(calls) == 2  # two pairs, three methods
