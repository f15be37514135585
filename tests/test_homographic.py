"""Self-supervised homographic pairs from real recordings (data.real): the geometry is exact, the
device-side warp agrees with the loader's targets, and a training run mixes them into its batches."""

from __future__ import annotations

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from aerovis_slam.io.sequence import SequenceWriter  # noqa: E402
from aerovis_train.correspondences import cell_centres  # noqa: E402
from aerovis_train.data import MctsSpec  # noqa: E402
from aerovis_train.homographic import (  # noqa: E402
    HomographyRange,
    RealViewDataset,
    apply_homography,
    homography_targets,
    merge_batches,
    sample_homography,
    warp_views,
)

from test_training import _train  # noqa: E402


def blobs_image(points, h, w):
    img = np.zeros((1, 1, h, w), np.float32)
    for x, y in points:
        img[0, 0, y - 2:y + 3, x - 2:x + 3] = 1.0
    return img


def centroid(img, x, y, r=6):
    yi, xi = int(round(y)), int(round(x))
    win = img[yi - r:yi + r + 1, xi - r:xi + r + 1]
    yy, xx = np.mgrid[yi - r:yi + r + 1, xi - r:xi + r + 1]
    return (xx * win).sum() / win.sum(), (yy * win).sum() / win.sum()


def test_kornia_warp_moves_content_where_the_homography_says():
    rng = np.random.default_rng(0)
    h, w = 160, 224
    pts = [(60, 60), (110, 40), (150, 110), (90, 100)]
    for _ in range(5):
        H = sample_homography(rng, h, w)
        out = warp_views({"mcts0": torch.from_numpy(blobs_image(pts, h, w)), "H01": torch.from_numpy(H[None].astype(np.float32))})
        img = out["mcts1"][0, 0].numpy()
        for p in apply_homography(H, pts):
            if 8 <= p[0] < w - 8 and 8 <= p[1] < h - 8:
                # a symmetric 5x5 blob keeps its centre under a near-affine warp: bilinear resampling and the
                # blob's own distortion move its centroid by well under a pixel
                np.testing.assert_allclose(centroid(img, *p), p, atol=0.3)


def test_homography_range_is_respected():
    rng = np.random.default_rng(1)
    h, w = 120, 160
    r = HomographyRange(max_angle_deg=0, scale=(1, 1), translation=0.0, perspective=0.0)
    np.testing.assert_allclose(sample_homography(rng, h, w, r), np.eye(3), atol=1e-9)
    r = HomographyRange(max_angle_deg=10, scale=(0.9, 1.1), translation=0.05, perspective=0.0)
    centre = np.array([[(w - 1) / 2, (h - 1) / 2]])
    for _ in range(20):
        H = sample_homography(rng, h, w, r)
        # a similarity: the centre moves by at most the translation, and lengths scale within the zoom
        shift = apply_homography(H, centre)[0] - centre[0]
        assert np.all(np.abs(shift) <= 0.05 * np.array([w, h]) + 1e-6)
        a, b = apply_homography(H, [[10, 10], [110, 10]])
        assert 90 - 1e-6 <= np.linalg.norm(b - a) <= 110 + 1e-6
    with pytest.raises(ValueError, match="homography range"):
        HomographyRange(scale=(1.2, 0.8))


def test_targets_both_ways_invert_each_other():
    rng = np.random.default_rng(2)
    h, w = 64, 96
    H = sample_homography(rng, h, w)
    warp01, warp10 = homography_targets(H, h, w)
    centres = cell_centres(h, w)
    inside = ~np.isnan(warp01[:, 0])
    np.testing.assert_allclose(warp01[inside], apply_homography(H, centres[inside]), atol=1e-3)
    np.testing.assert_allclose(apply_homography(np.linalg.inv(H), warp01[inside]), centres[inside], atol=1e-3)
    out = apply_homography(H, centres[~inside])
    assert np.all((out[:, 0] < 0) | (out[:, 0] > w - 1) | (out[:, 1] < 0) | (out[:, 1] > h - 1))
    assert np.isnan(warp10).any() or inside.all()


def write_recording(path, w=128, h=96, seconds=0.4, seed=0):
    """A canonical sequence with events only (no GT, frames or calibration), as a converted recording:
    textured blocks sliding diagonally over the sensor, rendered to events by the simulator's camera model."""
    from aerovis_slam.sim.events import EventConfig, video_to_events

    rng = np.random.default_rng(seed)
    tex = rng.uniform(0.1, 0.9, (h // 8 + 2, w // 8 + 2))
    frames, times = [], []
    for k in range(int(seconds * 200)):
        shift = 0.25 * k  # diagonal motion: every edge of the blocks fires
        xs = np.clip(((np.arange(w) + shift) / 8.0).astype(int), 0, tex.shape[1] - 1)
        ys = np.clip(((np.arange(h) + 0.7 * shift) / 8.0).astype(int), 0, tex.shape[0] - 1)
        img = tex[ys[:, None], xs[None, :]]
        frames.append(img)
        times.append(k * 5000)
    ev = video_to_events(np.array(frames), np.array(times, np.int64), EventConfig(threshold=0.15), seed=seed)
    with SequenceWriter(path, sensor_sizes={"cam0": (w, h)}) as wr:
        wr.add_events("cam0", ev)
    return path


def test_real_view_dataset_samples_are_consistent(tmp_path):
    rec = write_recording(tmp_path / "rec.h5")
    ds = RealViewDataset([rec], MctsSpec("dt", (1.0, 3.0, 10.0, 30.0, 100.0)), crop=(64, 96), samples_per_epoch=6, seed=3)
    s = ds[0]
    assert s["mcts0"].shape == (10, 64, 96) and s["labels0"].shape == (8, 12) and s["warp01"].shape == (96, 2)
    assert ds[0]["H01"].numpy().tolist() == s["H01"].numpy().tolist()  # a pure function of (seed, epoch, index)
    # view 1's labels are view 0's corners carried through H: every labelled pixel of view 1 maps back
    # onto one of them (a cell keeps one label of several, so compare with all of view 0's corners)
    from aerovis_slam.classical import mcts_to_image
    from aerovis_train.data import where_events

    H = s["H01"].numpy().astype(np.float64)
    mcts0 = s["mcts0"].numpy()
    corners0 = where_events(ds.labeller(mcts_to_image(mcts0)), mcts0)
    assert len(corners0), "the sliding squares should give corner labels"
    lab1 = s["labels1"].numpy()
    found = 0
    for (cy, cx), c in np.ndenumerate(lab1):
        if c < 64:
            back = apply_homography(np.linalg.inv(H), [(cx * 8 + c % 8, cy * 8 + c // 8)])[0]
            # the label is the warped corner rounded to its pixel (<= 0.71 px), mapped back through H^-1,
            # whose scale is at most 1 / 0.85 plus the perspective's: within 1 px
            assert np.min(np.hypot(*(corners0 - back).T)) < 1.0
            found += 1
    assert found > 0
    batch = warp_views({k: v[None] for k, v in s.items()})
    assert batch["mcts1"].shape == (1, 10, 64, 96) and "H01" not in batch
    merged = merge_batches({k: v for k, v in batch.items()}, batch)
    assert merged["mcts0"].shape[0] == 2


def test_a_recording_too_small_or_too_short_is_refused(tmp_path):
    from aerovis_slam.errors import DataError

    rec = write_recording(tmp_path / "rec.h5", w=64, h=48, seconds=0.1)
    with pytest.raises(DataError, match="smaller than the 96x64 crop"):
        RealViewDataset([rec], MctsSpec("dt", (1.0, 3.0, 10.0, 30.0, 100.0)), crop=(64, 96), samples_per_epoch=2)


def test_training_mixes_real_recordings_into_its_batches(tmp_path, tiny_cache):
    (tmp_path / "real").mkdir()
    rec = write_recording(tmp_path / "real" / "rec.h5", w=96, h=64)
    run = tmp_path / "run"
    res = _train(run, f"data.real=[{rec}]", "data.real_fraction=0.5", "data.crop=[40,56]", "trainer.max_steps=2",
                 "data.batch_size=2", cache=tiny_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "1 of 2 pairs a batch from 1 real camera stream(s)" in res.stdout + res.stderr
    assert json.loads((run / "summary.json").read_text())["steps"] == 2
    bad = _train(tmp_path / "bad", f"data.real=[{rec}]", "data.supervision=epipolar", cache=tiny_cache)
    assert bad.returncode == 2 and "needs data.supervision=depth" in bad.stderr and "Traceback" not in bad.stderr
    bad = _train(tmp_path / "bad2", f"data.real=[{tmp_path / 'none.h5'}]", cache=tiny_cache)
    assert bad.returncode == 2 and "recording not found" in bad.stderr


def test_corners_of_lone_noise_events_are_not_labels():
    from aerovis_train.homographic import SUPPORT_MIN, supported_corners

    img = np.zeros((40, 40), np.uint8)
    img[10, 10] = 255                 # a lone noise event
    img[25:27, 5:20] = 255            # a 2 px edge ending at x = 19: 6 of its pixels in the 5x5 window around (19, 25)
    img[20:25, 19:21] = 255           # a second one meeting it there: 4 more, a corner with 10 active pixels around
    kept = supported_corners(np.array([[10.0, 10.0], [19.0, 25.0]]), img)
    assert SUPPORT_MIN > 1 and kept.tolist() == [[19.0, 25.0]]
