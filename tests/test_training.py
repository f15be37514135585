"""Supervision with known answers (correspondences, labels, losses) and the training job itself
(every model config for a few steps on the `tiny` preset, resume, bad input)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="training needs the train extra (torch)")

from aerovis_train.correspondences import (  # noqa: E402
    IGNORE,
    UNMATCHED,
    ViewGeometry,
    cell_centres,
    grid_targets_depth,
    keypoint_matches_depth,
    keypoint_matches_epipolar,
    pixel_targets_depth,
)
from aerovis_train.labels import CornerLabeller, cell_labels, cross_view_consistent, soft_cell_labels  # noqa: E402
from aerovis_train.losses import (descriptor_loss_depth, descriptor_loss_dual_softmax, descriptor_loss_epipolar, detector_loss,  # noqa: E402
                                  repeatability_loss)

from conftest import REPO_ROOT, dead_pid, randomise_batchnorm  # noqa: E402

K = np.array([[100.0, 0, 47.5], [0, 100, 31.5], [0, 0, 1]])
W, H = 96, 64


def wall_views(tx=0.1, depth=2.0):
    """Two cameras facing a fronto-parallel wall at `depth` m; camera 1 is `tx` m to the right."""
    T1 = np.eye(4)
    T1[0, 3] = tx
    d = np.full((H, W), depth)
    return ViewGeometry(K, np.eye(4), d, (W, H)), ViewGeometry(K, T1, d.copy(), (W, H))


def test_depth_matches_known_shift():
    v0, v1 = wall_views(tx=0.1, depth=2.0)  # disparity f * b / z = 5 px to the left
    xy0 = np.array([[30.0, 20.0], [60.0, 40.0], [3.0, 10.0], [70.0, 10.0]])
    xy1 = np.array([[55.0, 40.0], [25.0, 20.0], [80.0, 50.0]])  # (60,40) and (30,20) shifted by -5 px, one distractor
    m = keypoint_matches_depth(xy0, xy1, v0, v1, pos_px=3, neg_px=5)
    assert m[0] == 1 and m[1] == 0
    assert m[2] == IGNORE  # (3, 10) moves to (-2, 10): outside view 1, no label either way
    assert m[3] == UNMATCHED  # visible at (65, 10) and nothing within 5 px there
    # grid: each cell centre lands exactly 5 px to the left
    warped, vis = grid_targets_depth(v0, v1)
    c = cell_centres(H, W)
    ok = c[:, 0] - 5 > -0.5
    np.testing.assert_allclose(warped[ok], c[ok] - [5, 0], atol=1e-5)
    assert (vis == ok).all()


def test_occlusion_hides_points():
    v0, v1 = wall_views(tx=0.1, depth=2.0)
    v1.depth[:, :] = 1.0  # something at 1 m in front of the wall in view 1
    m = keypoint_matches_depth(np.array([[30.0, 20.0]]), np.array([[25.0, 20.0]]), v0, v1)
    assert m[0] == IGNORE


def test_epipolar_matches_and_labels():
    v0, v1 = wall_views(tx=0.1)
    # pure sideways motion: epipolar lines are the image rows
    xy0 = np.array([[30.0, 20.0], [30.0, 45.0]])
    xy1 = np.array([[12.0, 20.0], [50.0, 55.0]])
    m = keypoint_matches_epipolar(xy0, xy1, v0, v1, pos_px=2, neg_px=6)
    assert m[0] == 0  # same row, whatever the disparity
    assert m[1] == UNMATCHED  # rows 45 vs 20/55: > 6 px from every line
    rng = np.random.default_rng(0)
    labels = cell_labels(np.array([[9.0, 2.0], [40.0, 17.0]]), H, W, rng)
    assert labels.shape == (8, 12) and labels[0, 1] == 2 * 8 + 1 and labels[2, 5] == 1 * 8 + 0
    assert (labels == 64).sum() == 8 * 12 - 2
    keep = cross_view_consistent(np.array([[30.0, 20.0], [60.0, 40.0]]), np.array([[25.5, 20.0]]), v0, v1, radius_px=2)
    assert keep.tolist() == [True, False]


def test_soft_cell_labels_keep_the_subpixel_position():
    """The bilinear target's centroid is the label's position; across a cell border the mass stays in
    the label's own cell (renormalised); one label per cell, the rest is dustbin; rows are distributions."""
    rng = np.random.default_rng(0)
    xy = np.array([[9.25, 2.75], [40.0, 17.0], [15.4, 30.2], [-3.0, 5.0]])  # the last is outside: dropped
    t = soft_cell_labels(xy, H, W, rng)
    assert t.shape == (65, H // 8, W // 8) and t.dtype == np.float32
    np.testing.assert_allclose(t.sum(0), 1.0, atol=1e-6)
    ys, xs = np.mgrid[0:8, 0:8]

    def centroid(cy, cx):
        p = t[:64, cy, cx].reshape(8, 8) / t[:64, cy, cx].sum()
        return 8 * cx + (p * xs).sum(), 8 * cy + (p * ys).sum()

    # inside a cell: the four weights (0.75*0.25, 0.25*0.25, 0.75*0.75, 0.25*0.75) put the centroid on the label
    np.testing.assert_allclose(centroid(0, 1), (9.25, 2.75), atol=1e-6)
    assert t[2 * 8 + 1, 0, 1] == pytest.approx(0.75 * 0.25) and t[3 * 8 + 2, 0, 1] == pytest.approx(0.25 * 0.75)
    # an integer label is the one-hot class that cell_labels gives
    assert t[1 * 8 + 0, 2, 5] == pytest.approx(1.0) and t[64, 2, 5] == 0.0
    # x = 15.4 rounds to pixel 15 (cell 1); pixel 16 is in cell 2, so all of x's mass stays on column 15
    np.testing.assert_allclose(centroid(3, 1), (15.0, 30.2), atol=1e-6)
    assert t[:, :, 2].sum() == pytest.approx(H // 8) and t[64, :, 2].min() == 1.0  # nothing leaked into cell column 2
    assert (t[64] == 1.0).sum() == (H // 8) * (W // 8) - 3
    # one label per cell: two in the same cell leave one distribution, not a mixture
    t2 = soft_cell_labels(np.array([[1.0, 1.0], [5.5, 5.0]]), H, W, np.random.default_rng(1))
    assert sorted(np.round(t2[:64, 0, 0][t2[:64, 0, 0] > 0], 6).tolist()) in ([1.0], [0.5, 0.5])


def test_subpixel_corner_labels():
    """cornerSubPix labels find a corner between pixels; goodFeaturesToTrack's integer corner sits
    inside the dark square (its Shi-Tomasi response peaks about a block from the corner point)."""
    size, up = 64, 10  # rendered at 10x and area-averaged: an anti-aliased 8-bit edge, as the simulator renders
    yy, xx = np.mgrid[0 : size * up, 0 : size * up]
    rng = np.random.default_rng(0)
    refined_err, integer_err = [], []
    for _ in range(8):
        corner = (30 + rng.random(), 27 + rng.random())  # the dark square's corner at a random sub-pixel position
        # pixel centres at integers: the fine sample (i + 0.5) / up - 0.5 lies in pixel i // up
        fine = ((xx + 0.5) / up - 0.5 >= corner[0]) & ((yy + 0.5) / up - 0.5 >= corner[1])
        img = (255 * (1 - fine.reshape(size, up, size, up).mean((1, 3)))).astype(np.uint8)
        integer = CornerLabeller(max_corners=1)(img)[0]
        refined = CornerLabeller(max_corners=1, subpixel_window=3)(img)[0]
        assert np.abs(integer - np.rint(integer)).max() == 0  # whole pixels
        refined_err.append(np.linalg.norm(refined - corner))
        integer_err.append(np.linalg.norm(integer - corner))
    # 8-bit quantisation of the edge profile (1/255 of a pixel's area) and the 7x7 window's discrete
    # gradients leave cornerSubPix a few tenths of a pixel; the integer corner is off by more than a pixel
    assert max(refined_err) < 0.3 and min(integer_err) > 1.0
    with pytest.raises(ValueError, match="subpixel_window"):
        CornerLabeller(subpixel_window=-1)


def test_losses_vanish_for_perfect_predictions():
    hc, wc = H // 8, W // 8
    labels = torch.randint(0, 65, (2, hc, wc))
    logits = torch.nn.functional.one_hot(labels, 65).permute(0, 3, 1, 2).float() * 50
    assert float(detector_loss(logits, labels)) < 1e-6
    # soft targets: one-hot distributions give the same loss as the classes; a split target is
    # minimised by logits whose softmax is that split (cross-entropy = its entropy, log 2 for halves)
    onehot = torch.nn.functional.one_hot(labels, 65).permute(0, 3, 1, 2).float()
    assert float(detector_loss(logits, onehot)) < 1e-6
    half = torch.zeros(1, 65, 1, 1)
    half[0, [3, 4]] = 0.5
    split_logits = torch.full((1, 65, 1, 1), -50.0)
    split_logits[0, [3, 4]] = 0.0
    assert float(detector_loss(split_logits, half)) == pytest.approx(np.log(2), abs=1e-6)
    # descriptors: view 1 is view 0 shifted by one cell; orthogonal one-hot codes per cell
    n = hc * wc
    codes = torch.eye(n).T.reshape(1, n, hc, wc)  # D = n, cell i has code e_i
    desc0 = codes
    desc1 = torch.roll(codes, shifts=-1, dims=3)  # cell (r, c) of view 1 holds code of (r, c + 1) of view 0
    desc1[..., -1] = 0.0  # the last column would wrap around to codes of column 0, which leaves view 1
    c = torch.from_numpy(cell_centres(H, W)).float()
    warped = (c - torch.tensor([8.0, 0.0]))[None]  # view-0 cell centre lands one cell to the left
    warped[0, c[:, 0] < 8] = float("nan")
    kw = dict(pos_px=6.0, neg_px=12.0, pos_margin=1.0, neg_margin=0.2, pos_weight=0.5)
    assert float(descriptor_loss_depth(desc0, desc1, warped, **kw)) < 1e-6
    # the same descriptors with no relation to the geometry are penalised
    shuffled = desc1[:, torch.randperm(n)]
    assert float(descriptor_loss_depth(desc0, shuffled, warped, **kw)) > 0.2
    # epipolar (pure sideways motion: rows are the lines): identity descriptors satisfy it
    lines = torch.zeros(1, n, 3)
    lines[0, :, 1], lines[0, :, 2] = 1.0, -c[:, 1]  # y - y_i = 0
    assert float(descriptor_loss_epipolar(desc0, desc0, lines, pos_px=4.0, neg_px=12.0)) < 1e-6


def test_dual_softmax_descriptor_loss_known_values():
    """The matching cross-entropy: 0 in the limit of perfect codes, log(N) for codes that say nothing,
    and the neighbours of a true match left out of its softmax."""
    hc, wc = H // 8, W // 8
    n = hc * wc
    codes = torch.eye(n).T.reshape(1, n, hc, wc)
    desc1 = torch.roll(codes, shifts=-1, dims=3)
    desc1[..., -1] = 0.0
    c = torch.from_numpy(cell_centres(H, W)).float()
    warped = (c - torch.tensor([8.0, 0.0]))[None]
    warped[0, c[:, 0] < 8] = float("nan")
    # perfect orthogonal codes: the true cell's logit is 1/T, every other one 0 (neighbours within 12 px are
    # left out: the 4-neighbours at 8 px and diagonals at 11.3 px), so each softmax gives
    # -log(e^(1/T) / (e^(1/T) + K)) with K the cells still in it: at T = 0.01 below 1e-30
    assert float(descriptor_loss_dual_softmax(codes, desc1, warped, temperature=0.01)) < 1e-6
    # identical descriptors everywhere: every logit equal, so the loss is the log of the cells left in each softmax
    flat = torch.ones(1, 4, hc, wc) / 2.0
    got = float(descriptor_loss_dual_softmax(flat, flat, warped, temperature=0.1))
    dist = torch.cdist(torch.nan_to_num(warped[0], nan=1e9), c)
    near, tgt = dist.min(1)
    has = near <= 6.0
    target = torch.nn.functional.one_hot(tgt, n).bool() & has[:, None]
    kept = ~((dist <= 12.0) & ~target)  # what each softmax sums over
    row = [float(kept[i].sum()) for i in torch.nonzero(has).flatten().tolist()]
    col = [float(kept[:, j].sum()) for j in tgt[has].tolist()]
    assert min(row) < n  # some neighbours are left out
    assert got == pytest.approx(0.5 * (np.log(row).mean() + np.log(col).mean()), rel=1e-5)
    # no visible cell: no matches, no loss
    assert float(descriptor_loss_dual_softmax(codes, desc1, torch.full_like(warped, float("nan")))) == 0.0


def test_pixel_targets_land_where_the_wall_moves():
    """Every pixel of a wall 2 m away, seen from 0.1 m to the right, lands f * b / z = 5 px to the left;
    the columns that leave view 1 (x - 5 < -0.5) are NaN."""
    v0, v1 = wall_views(tx=0.1, depth=2.0)
    flow = pixel_targets_depth(v0, v1)
    assert flow.shape == (H, W, 2) and flow.dtype == np.float32
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    inside = xs - 5 > -0.5
    np.testing.assert_allclose(flow[inside][:, 0], xs[inside] - 5, atol=1e-4)
    np.testing.assert_allclose(flow[inside][:, 1], ys[inside], atol=1e-4)
    assert np.isnan(flow[~inside]).all()


def test_repeatability_loss_known_values():
    """1 - cosine similarity of patches of the two maps after the warp: 0 for maps that move with the
    scene, 1 - 1/sqrt(2) for a patch whose second map covers half of the first, 0 with nothing visible."""
    rng = np.random.default_rng(0)
    s0 = torch.from_numpy(rng.random((1, H, W))).float()
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    identity = torch.stack([xs, ys], -1)[None]
    assert float(repeatability_loss(s0, s0, identity)) == pytest.approx(0.0, abs=1e-6)
    # the second view sees the scene 5 px to the left (the wall above): its map is the first one shifted, and
    # bilinear sampling at whole pixels reads it back exactly
    s1 = torch.zeros_like(s0)
    s1[..., : W - 5] = s0[..., 5:]
    flow = identity - torch.tensor([5.0, 0.0])
    flow[:, :, :5] = float("nan")  # these pixels leave view 1
    assert float(repeatability_loss(s0, s1, flow)) == pytest.approx(0.0, abs=1e-6)
    # the same maps without the shift in the warp are far from alike
    assert float(repeatability_loss(s0, s1, identity)) > 0.1
    # one 8x8 patch: the first map 1 everywhere, the second 1 on its left half: cos = 32 / sqrt(64 * 32)
    a, b = torch.ones(1, 8, 8), torch.zeros(1, 8, 8)
    b[..., :4] = 1.0
    ident8 = identity[:, :8, :8]
    assert float(repeatability_loss(a, b, ident8)) == pytest.approx(1 - 1 / np.sqrt(2), rel=1e-6)
    # nothing visible: no patch, no loss (and no NaN)
    assert float(repeatability_loss(a, b, torch.full_like(ident8, float("nan")))) == 0.0
    # finite gradients where patches are empty or left out (sqrt at 0 once gave NaN there and killed a run)
    s0g, s1g = s0.clone().requires_grad_(), s1.clone().requires_grad_()
    half = flow.clone()
    half[:, :, W // 2:] = float("nan")
    repeatability_loss(s0g, torch.zeros_like(s1g) + 0 * s1g, half).backward()
    assert torch.isfinite(s0g.grad).all() and torch.isfinite(s1g.grad).all()


def _train(tmp_path, *overrides, cache=None):
    """Run train.py; with ``cache``, on the simulator's `tiny` preset generated there."""
    sim = ["data.preset=tiny", f"data.cache_dir={cache}", "data.val_sequences=1"] if cache else []
    cmd = [sys.executable, str(REPO_ROOT / "train.py"), *sim, "data.samples_per_epoch=4", "data.batch_size=2", "data.num_workers=0",
           "val.max_pairs=3", "val.rate_hz=20", "metrics.latency=false",  # ONNX latency is tested in test_search.py
           f"hydra.run.dir={tmp_path}", *overrides]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path.parent)


@pytest.fixture(scope="module")
def sim_cache(tiny_cache):
    return tiny_cache  # the session's `tiny` preset (conftest.py)


@pytest.fixture(scope="module")
def superlite_run(tmp_path_factory, sim_cache):
    """(run dir, finished process) of the default model trained for 2 steps on `tiny` with the
    default validation (both cameras). Several tests read it (each train.py costs ~10 s, most of
    it importing torch and Lightning); a test that continues training works on a copy."""
    run = tmp_path_factory.mktemp("superlite") / "run"
    return run, _train(run, "data.crop=[40,56]", "trainer.max_steps=2", cache=sim_cache)


@pytest.mark.parametrize("model,crop", [("superlite", "[40,56]"), ("superevent_plus", "[40,40]"), ("superevent", "[40,40]")])
def test_every_model_config_trains(tmp_path, sim_cache, model, crop, request):
    if model == "superlite":  # the default model's run is shared with the tests below
        run, res = request.getfixturevalue("superlite_run")
    else:
        run = tmp_path / "run"
        res = _train(run, f"model={model}", f"data.crop={crop}", "trainer.max_steps=2", cache=sim_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["model"] == model and summary["steps"] == 2
    assert (run / "checkpoints" / "last.ckpt").exists() and (run / "model.pt").exists()
    assert (run / "config.yaml").exists()
    from aerovis_train.checkpoints import load_model

    net, cfg, meta = load_model(run / "model.pt")
    assert cfg["name"] == model and len(meta["sha256"]) == 64
    # Lightning's records once each, through Hydra's logging (Lightning's own console handler removed)
    output = res.stdout + res.stderr
    assert output.count("Seed set to 0") == 1, output[:3000]


def test_resume_continues_from_last_checkpoint(tmp_path, sim_cache, superlite_run):
    """A 2-step run continued to 4 steps, in a copy of its folder (a run moved elsewhere resumes too)."""
    import shutil

    first_run, first = superlite_run
    assert first.returncode == 0, first.stderr[-3000:]
    run = tmp_path / "run"
    shutil.copytree(first_run, run)
    second = _train(run, "data.crop=[40,56]", "trainer.max_steps=4", cache=sim_cache)
    assert second.returncode == 0, second.stderr[-3000:]
    assert "resuming from" in second.stdout
    assert json.loads((run / "summary.json").read_text())["steps"] == 4  # 2 restored + 2 new, not 4 new


def _fit_with_checkpoints(tmp_path, every_min: float, crash_at_step: int | None = None):
    """A small Lightning model (4 steps an epoch, 3 epochs) whose validation score falls every
    epoch, so the first epoch (step 4) stays the best, trained with train.py's checkpoint callbacks.
    ``crash_at_step``: the training step that raises (an interrupted run)."""
    import lightning as L
    from lightning.pytorch.demos.boring_classes import BoringModel

    from aerovis_train.checkpoints import AtomicCheckpointIO
    from aerovis_train.training import checkpoint_callbacks

    class Worsening(BoringModel):
        def training_step(self, batch, batch_idx):
            if self.global_step == crash_at_step:
                raise RuntimeError("interrupted")
            return super().training_step(batch, batch_idx)

        def on_validation_epoch_end(self):
            self.log("val/auc10", 50.0 - self.current_epoch)

    best, last = checkpoint_callbacks(tmp_path, every_min)
    trainer = L.Trainer(max_epochs=3, limit_train_batches=4, limit_val_batches=1, callbacks=[best, last],
                        plugins=[AtomicCheckpointIO()], logger=False, enable_progress_bar=False,
                        enable_model_summary=False, num_sanity_val_steps=0, accelerator="cpu")
    trainer.fit(Worsening())


def _step(path) -> int:
    import torch

    return int(torch.load(path, map_location="cpu", weights_only=False)["global_step"])


def test_last_checkpoint_is_the_newest_state_not_the_best(tmp_path):
    """last.ckpt (what a resumed run continues from) is written after every validation, also when it
    brings no new best: after three epochs of four steps it holds step 12 while best.ckpt holds
    step 4 (Lightning's save_last on the best callback left last.ckpt at the best, and a timed
    second callback wrote last-v1.ckpt)."""
    _fit_with_checkpoints(tmp_path, every_min=60.0)
    assert sorted(p.name for p in tmp_path.glob("*.ckpt")) == ["best.ckpt", "last.ckpt"]
    assert (_step(tmp_path / "best.ckpt"), _step(tmp_path / "last.ckpt")) == (4, 12)


@pytest.mark.parametrize("every_min,expected", [(60.0, 4), (0.0, 6)])
def test_interrupted_run_keeps_the_newest_last_checkpoint(tmp_path, every_min, expected):
    """A run that fails at step 6 (mid second epoch) leaves last.ckpt at the first epoch's validation
    (step 4) when the timer is not due, and at step 6 when it is due after every step."""
    with pytest.raises(RuntimeError, match="interrupted"):
        _fit_with_checkpoints(tmp_path, every_min, crash_at_step=6)
    assert _step(tmp_path / "last.ckpt") == expected


def test_ddp_trains_with_two_processes(tmp_path, sim_cache):
    """trainer=ddp (as on GPUs) with two CPU processes (gloo; SyncBatchNorm needs GPUs): the job
    finishes, last.ckpt holds the final step (its timer is broadcast, so both processes save
    together), and only the first process writes the outputs and prints the summary, so
    summary.json names the metrics.json that process wrote."""
    import torch

    run = tmp_path / "run"
    res = _train(run, "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2", "trainer.precision=32",
                 "trainer.sync_batchnorm=false", "checkpoint_every_min=0", "data.crop=[40,56]", "trainer.max_steps=3",
                 cache=sim_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("best val AUC@10") == 1
    summary = json.loads((run / "summary.json").read_text())
    assert summary["steps"] == 3 and summary["metrics"] == str(run / "metrics.json")
    assert json.loads((run / "metrics.json").read_text())["val_pairs"] > 0
    assert torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["global_step"] == 3


def test_validation_pools_both_cameras_and_warns_when_few_pairs(tmp_path, sim_cache, superlite_run):
    """The default validation scores cam0 and cam1 of each held-out sequence: with val.max_pairs=3
    (per sequence and camera) the one tiny validation sequence gives 3 pairs from one camera and 6
    from both (the shared default run); 6 pairs are below val.min_pairs, which is said once."""
    one = _train(tmp_path / "one", "data.crop=[40,56]", "trainer.max_steps=1", "val.cam=cam0", cache=sim_cache)
    assert one.returncode == 0, one.stderr[-3000:]
    both_run, both = superlite_run
    assert both.returncode == 0, both.stderr[-3000:]
    pairs = {k: json.loads((run / "metrics.json").read_text())["val_pairs"] for k, run in (("one", tmp_path / "one"), ("both", both_run))}
    assert pairs == {"one": 3.0, "both": 6.0}
    assert both.stderr.count("validation scores only 6 pairs (val.min_pairs=100)") == 1


def test_weights_last_keeps_the_final_step(tmp_path, sim_cache):
    """weights=last: model.pt holds the final step's weights (those of last.ckpt, step 4 of two
    2-step epochs), whichever epoch validated best, and says so; an unknown choice is refused."""
    import torch

    from aerovis_train.checkpoints import lightning_model_state

    run = tmp_path / "run"
    res = _train(run, "weights=last", "data.crop=[40,56]", "trainer.max_steps=4", cache=sim_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    slim = torch.load(run / "model.pt", map_location="cpu", weights_only=False)
    last = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert (slim["meta"]["selection"], slim["meta"]["global_step"], int(last["global_step"])) == ("last", 4, 4)
    for k, v in lightning_model_state(last).items():
        assert torch.equal(slim["state_dict"][k], v), k
    summary = json.loads((run / "summary.json").read_text())
    metrics = json.loads((run / "metrics.json").read_text())
    # the kept weights' own validation score, re-measured in metrics.json, is what the job reports
    assert summary["weights_selection"] == "last" and summary["weights_val_auc10"] == pytest.approx(metrics["auc10"])
    assert slim["meta"]["val_auc10"] == pytest.approx(metrics["auc10"])
    bad = _train(tmp_path / "bad", "weights=newest", cache=sim_cache)
    assert bad.returncode == 2 and "weights='newest': expected one of best, last" in bad.stderr and "Traceback" not in bad.stderr


def test_descriptor_loss_terms_are_parsed_and_checked_in_one_place():
    """loss.descriptor is split into its terms by one function, which train() (before a run) and the module
    (on each batch) both call: unknown settings and the dual softmax without depth are refused by it."""
    from aerovis_train.losses import descriptor_loss_terms

    assert descriptor_loss_terms("hinge", "epipolar") == ["hinge"]
    assert descriptor_loss_terms("hinge+dual_softmax", "depth") == ["hinge", "dual_softmax"]
    with pytest.raises(ValueError, match="expected one of hinge, dual_softmax, hinge\\+dual_softmax"):
        descriptor_loss_terms("triplet", "depth")
    for kind in ("dual_softmax", "hinge+dual_softmax"):
        with pytest.raises(ValueError, match="needs data.supervision=depth"):
            descriptor_loss_terms(kind, "epipolar")


def test_combined_descriptor_loss_is_the_weighted_sum():
    """loss.descriptor=hinge+dual_softmax: the descriptor term is hinge + dual_softmax_weight * dual
    softmax, each as its own setting computes it on the same batch, with depth targets of a known wall."""
    from omegaconf import OmegaConf

    from aerovis_train.models import CONF_DIR
    from aerovis_train.module import KeypointModule

    base = OmegaConf.load(CONF_DIR / "config.yaml")
    cfg = {"model": OmegaConf.to_container(OmegaConf.load(CONF_DIR / "model" / "superlite.yaml"), resolve=True),
           "loss": OmegaConf.to_container(base.loss), "optim": OmegaConf.to_container(base.optim), "val": {}}
    v0, v1 = wall_views(tx=0.05)
    w01, _ = grid_targets_depth(v0, v1)
    w10, _ = grid_targets_depth(v1, v0)
    torch.manual_seed(0)
    hc, wc = H // 8, W // 8
    batch = {"mcts0": torch.rand(2, 8, H, W), "mcts1": torch.rand(2, 8, H, W),
             "warp01": torch.from_numpy(np.stack([w01] * 2)).float(), "warp10": torch.from_numpy(np.stack([w10] * 2)).float(),
             "labels0": torch.randint(0, 65, (2, hc, wc)), "labels1": torch.randint(0, 65, (2, hc, wc))}
    desc = {}
    module = KeypointModule(cfg).eval()  # eval: BatchNorm's running statistics, so every call sees the same network
    with torch.no_grad():
        for kind in ("hinge", "dual_softmax", "hinge+dual_softmax"):
            module.cfg["loss"].update(descriptor=kind, dual_softmax_weight=0.25)
            desc[kind] = float(module._losses(batch)["desc"])
    assert desc["hinge"] > 0 and desc["dual_softmax"] > 0
    assert desc["hinge+dual_softmax"] == pytest.approx(desc["hinge"] + 0.25 * desc["dual_softmax"], rel=1e-5)


def test_dual_softmax_descriptor_loss_trains(tmp_path, sim_cache):
    """loss.descriptor=dual_softmax: a short run on depth supervision logs a finite descriptor loss;
    an unknown loss, or the dual softmax on pose-only supervision, is refused before training."""
    run = tmp_path / "run"
    res = _train(run, "loss.descriptor=dual_softmax", "loss.desc_weight=1.0", "data.crop=[40,56]", "trainer.max_steps=2", "trainer.log_every_n_steps=1",
                 cache=sim_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    logged = list(csv.DictReader((next(run.rglob("metrics.csv"))).open()))
    desc = [float(r["train/desc"]) for r in logged if r.get("train/desc")]
    assert desc and all(np.isfinite(desc)) and min(desc) > 0  # a cross-entropy over many cells is never 0 at the start
    bad = _train(tmp_path / "bad", "loss.descriptor=triplet", cache=sim_cache)
    assert bad.returncode == 2 and "loss.descriptor='triplet': expected one of hinge, dual_softmax" in bad.stderr
    bad = _train(tmp_path / "bad2", "loss.descriptor=dual_softmax", "data.supervision=epipolar", cache=sim_cache)
    assert bad.returncode == 2 and "needs data.supervision=depth" in bad.stderr and "Traceback" not in bad.stderr


def test_repeatability_loss_trains(tmp_path, sim_cache):
    """loss.repeatability=1: a short run logs the repeatability term, which lies in [0, 1] (1 - the cosine
    similarity of non-negative maps); on pose-only supervision it is refused before training."""
    run = tmp_path / "run"
    res = _train(run, "loss.repeatability=1.0", "data.crop=[40,56]", "trainer.max_steps=2", "trainer.log_every_n_steps=1",
                 cache=sim_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    logged = list(csv.DictReader((next(run.rglob("metrics.csv"))).open()))
    rep = [float(r["train/rep"]) for r in logged if r.get("train/rep")]
    assert rep and all(0.0 < x <= 1.0 for x in rep)
    bad = _train(tmp_path / "bad", "loss.repeatability=1.0", "data.supervision=epipolar", cache=sim_cache)
    assert bad.returncode == 2 and "loss.repeatability=1.0 needs data.supervision=depth" in bad.stderr and "Traceback" not in bad.stderr


def test_fine_tuning_starts_from_the_given_weights(tmp_path, sim_cache):
    """init_weights=superlite: training starts from the shipped weights (one step at learning rate 0
    leaves every parameter exactly as shipped; BatchNorm's running statistics do move, so buffers are
    not compared); weights of another architecture are refused with both names."""
    import torch

    from aerovis_train.checkpoints import load_model

    run = tmp_path / "run"
    res = _train(run, "init_weights=superlite", "data.crop=[40,56]", "optim.lr=0.0", "trainer.max_steps=1", cache=sim_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "initialised from" in res.stdout
    ship, _, _ = load_model("superlite")
    tuned, _, _ = load_model(run / "model.pt")
    tuned_params = dict(tuned.named_parameters())
    for k, a in ship.named_parameters():
        assert torch.equal(a, tuned_params[k]), k
    # the start is recorded in the run's weights: the shipped file, by its hash
    from aerovis_train.checkpoints import WEIGHTS_DIR, file_sha256

    meta = torch.load(run / "model.pt", map_location="cpu", weights_only=False)["meta"]
    assert meta["init_weights"]["sha256"] == file_sha256(WEIGHTS_DIR / "superlite.pt") and meta["descriptor_loss"] == "hinge"
    # in-process (train.py turns this DataError into exit status 2, see the test below)
    from aerovis_slam.errors import DataError
    from aerovis_train.benchmarks import compose_config
    from aerovis_train.models import build_model
    from aerovis_train.training import init_from_weights

    plus = compose_config(["model=superevent_plus"]).model
    with pytest.raises(DataError, match=r"superlite model .*do not fit this run's superevent_plus"):
        init_from_weights(build_model(plus), "superlite", plus)


def test_pixel_detector_branch_starts_from_weights_without_it(tmp_path, capsys):
    """init_weights of a network without model.detector_pixel into one with it: every loaded parameter is
    kept and the new branch starts at zero, so the outputs are the loaded network's exactly."""
    import torch
    from omegaconf import OmegaConf

    from aerovis_train.benchmarks import compose_config
    from aerovis_train.checkpoints import load_model, save_slim
    from aerovis_train.models import build_model
    from aerovis_train.training import init_from_weights

    plain_cfg = compose_config(["model=superlite", "model.detector_pixel=null"]).model
    plain = build_model(plain_cfg)
    randomise_batchnorm(plain)
    start = save_slim(OmegaConf.to_container(plain_cfg, resolve=True), plain.state_dict(), tmp_path / "plain.pt")
    cfg = compose_config(["model=superlite", "model.detector_pixel={width:8,depth:2}"]).model
    net = build_model(cfg)
    init_from_weights(net, str(start), cfg)
    assert "new branch starts at zero" in capsys.readouterr().err
    ship, _, _ = load_model(start)
    net.eval()
    x = torch.rand(1, 8, 48, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        a, b = ship(x), net(x)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_descriptor_only_fine_tune_keeps_the_keypoints(tmp_path, sim_cache):
    """optim.train_only=[descriptor]: after steps on both sides of a validation, the encoder and detector
    head, BatchNorm statistics included, are bit-identical to the start weights, so the keypoints are; the
    descriptor head has moved. An unknown part is refused."""
    import torch

    from aerovis_train.checkpoints import load_model

    run = tmp_path / "run"
    # 4 samples of 2: two steps an epoch, a validation after each, so step 3 follows a validation
    res = _train(run, "init_weights=superlite", "optim.train_only=[descriptor]", "optim.lr=0.01", "data.crop=[40,56]",
                 "trainer.max_steps=3", "weights=last", cache=sim_cache)
    assert res.returncode == 0, res.stderr[-3000:]
    ship, _, _ = load_model("superlite")
    tuned, _, _ = load_model(run / "model.pt")
    tuned_state = tuned.state_dict()
    moved = [k for k, v in ship.state_dict().items() if not torch.equal(v, tuned_state[k])]
    assert moved and all(k.startswith("descriptor.") for k in moved), moved
    assert any(k.startswith("descriptor.out.") for k in moved)  # the learning part did learn (lr 0.01, 3 steps)
    meta = torch.load(run / "model.pt", map_location="cpu", weights_only=False)["meta"]
    assert meta["train_only"] == ["descriptor"]
    bad = _train(tmp_path / "bad", "optim.train_only=[neck]", cache=sim_cache)
    assert bad.returncode == 2 and "optim.train_only must name some of ['encoder', 'detector', 'descriptor', 'detector_pixel']" in bad.stderr
    # without start weights the frozen parts would stay random: allowed, and said
    scratch = _train(tmp_path / "scratch", "optim.train_only=[descriptor]", "data.crop=[40,56]", "trainer.max_steps=1", cache=sim_cache)
    assert scratch.returncode == 0 and "encoder, detector, detector_pixel keep their random initialisation" in scratch.stderr


def test_bad_training_input_is_explained(tmp_path):
    """train.py reports bad input as one line and exit status 2, no traceback (one run shows the
    path; the other refusals are DataErrors checked in-process, here and in the tests above)."""
    from aerovis_slam.errors import DataError
    from aerovis_train.benchmarks import compose_config
    from aerovis_train.training import fit_crop

    cfg = compose_config(["model=superevent_plus", "data.crop=[40,56]", "data.crop_fit=error"])
    with pytest.raises(DataError, match=r"data.crop=\[40, 56\] must be a multiple of 40 for encoder maxvit"):
        fit_crop(cfg, 40)
    cfg.data.crop_fit = "shrink"
    assert fit_crop(cfg, 40) == (40, 40)
    from aerovis_slam.io.sequence import SequenceWriter
    from aerovis_slam.events import EventArray

    nogt = tmp_path / "nogt.h5"
    with SequenceWriter(nogt, sensor_sizes={"cam0": (64, 48)}) as w:
        w.add_events("cam0", EventArray([1, 2], [0, 1], [0, 1], [0, 1]))
    res = _train(tmp_path / "run2", "data=sequences", f"data.train=[{nogt}]", f"data.val=[{nogt}]", "data.crop=[40,56]")
    assert res.returncode == 2 and "nogt.h5: no /gt poses" in res.stderr and "Traceback" not in res.stderr


def test_decoded_event_cache_gives_the_same_samples(tmp_path, sim_cache):
    """data.event_cache: the copies are built when the dataset is made; pairs drawn through them equal
    those read from the compressed files (MCTS, frames, depth: every tensor of every sample); one
    complete copy per sequence is left, no temporary folder (a killed run's is deleted), and a second
    dataset reuses the copies."""
    import torch

    from aerovis_slam import fileio
    from aerovis_slam.mcts import MCTS_NE_EVENTS_PER_PX
    from aerovis_slam.sim.cache import ensure_preset
    from aerovis_train.data import EventPairDataset, MctsSpec
    from aerovis_train.decoded import cache_key

    paths = sorted(ensure_preset("tiny", str(sim_cache), progress=False).glob("*.h5"))
    # the build folder of a run killed while decoding the first sequence (its process has ended)
    (tmp_path / "decoded").mkdir()
    left = tmp_path / "decoded" / f".{cache_key(paths[0])}.{fileio._host()}-{dead_pid()}.abc.tmp"
    left.mkdir()
    (left / "left_t.npy").write_bytes(b"\0" * 1024)
    kw = dict(crop=(40, 56), samples_per_epoch=6, seed=3)
    plain = EventPairDataset(paths, MctsSpec("ne", MCTS_NE_EVENTS_PER_PX), **kw)
    cached = EventPairDataset(paths, MctsSpec("ne", MCTS_NE_EVENTS_PER_PX), event_cache=tmp_path / "decoded", **kw)
    assert len(list((tmp_path / "decoded").iterdir())) == len(paths)  # built before any sample, not by the workers
    for i in range(6):
        a, b = plain[i], cached[i]
        assert a.keys() == b.keys()
        for k in a:  # exact, NaN (cells without a correspondence) included
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, equal_nan=True, msg=k)
    folders = sorted(p.name for p in (tmp_path / "decoded").iterdir())
    assert folders == sorted({cache_key(p) for p in paths})  # complete copies only, no .tmp folder
    mtimes = {f: (tmp_path / "decoded" / f).stat().st_mtime_ns for f in folders}
    again = EventPairDataset(paths, MctsSpec("ne", MCTS_NE_EVENTS_PER_PX), event_cache=tmp_path / "decoded", **kw)
    again[0]
    assert {f: (tmp_path / "decoded" / f).stat().st_mtime_ns for f in folders} == mtimes


def test_non_finite_time_surface_is_refused_naming_the_file(sim_cache, monkeypatch):
    """A time surface with NaN (a corrupt timestamp, say) stops the loader with the sequence, camera
    and frame named, before any loss sees it."""
    from aerovis_slam.errors import DataError
    from aerovis_slam.mcts import MCTS_NE_EVENTS_PER_PX
    from aerovis_slam.sim.cache import ensure_preset
    from aerovis_train import data
    from aerovis_train.data import EventPairDataset, MctsSpec

    paths = sorted(ensure_preset("tiny", str(sim_cache), progress=False).glob("*.h5"))[:1]
    ds = EventPairDataset(paths, MctsSpec("ne", MCTS_NE_EVENTS_PER_PX), crop=(40, 56), samples_per_epoch=2, seed=0)
    ds[0]  # fine as it is
    real = data.mcts_from_events

    def poisoned(*args, **kwargs):
        out = real(*args, **kwargs)
        out[0, 3, 5] = np.nan
        return out

    monkeypatch.setattr(data, "mcts_from_events", poisoned)
    with pytest.raises(DataError, match=rf"{paths[0].name}.*non-finite values in the MCTS of cam\d at frame \d+"):
        ds[0]


_LOADER_THREADS_SCRIPT = """
import cv2, numpy as np, torch
from aerovis_train.data import make_loader
frame = (np.random.default_rng(0).random((960, 1280)) * 255).astype(np.uint8)
cv2.setNumThreads(2)
for _ in range(10):  # this process uses OpenCV's thread pool before the loaders fork
    cv2.goodFeaturesToTrack(frame, 500, 0.01, 5)
class Threads(torch.utils.data.Dataset):
    def __len__(self):
        return 4
    def __getitem__(self, i):
        cv2.goodFeaturesToTrack(frame[:240, :320], 100, 0.01, 5)
        return cv2.getNumThreads()
for _ in range(3):
    print([int(n) for batch in make_loader(Threads(), 1, 2, False) for n in batch], flush=True)
"""


def test_loader_workers_run_opencv_on_one_thread():
    """Loader workers run OpenCV single-threaded, also when the process used OpenCV's pool before
    forking them and makes several loaders in a row (changing the setting inside the workers
    deadlocked there; a subprocess with a timeout turns such a hang into a failure)."""
    res = subprocess.run([sys.executable, "-c", _LOADER_THREADS_SCRIPT], capture_output=True, text=True, timeout=120,
                         cwd=REPO_ROOT)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split("\n")[:3] == ["[1, 1, 1, 1]"] * 3


def test_loader_settings_follow_the_trainer(monkeypatch, tmp_path):
    """data.num_workers=auto and data.event_cache=auto: one worker and no decoded copies on the CPU;
    on GPUs the cores less one per GPU process, shared, at most 10 a process, and decoded copies in
    the cache; explicit values win."""
    import os

    from aerovis_train.benchmarks import compose_config
    from aerovis_train.training import event_cache_dir, loader_workers

    monkeypatch.setenv("AEROVIS_CACHE", str(tmp_path))
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)))
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 4)
    cpu = compose_config([])
    assert (loader_workers(cpu), event_cache_dir(cpu)) == (1, None)
    gpu = compose_config(["trainer=gpu"])
    assert (loader_workers(gpu), event_cache_dir(gpu)) == (10, tmp_path / "decoded")  # min(10, 16 - 1)
    ddp = compose_config(["trainer=ddp"])  # devices=-1: the 4 GPUs, 4 cores each, one for the process
    assert loader_workers(ddp) == 3
    assert loader_workers(compose_config(["trainer=ddp", "trainer.devices=[0,1]"])) == 7
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    assert loader_workers(gpu) == 1  # never none
    explicit = compose_config(["trainer=gpu", "data.num_workers=3", "data.event_cache=false"])
    assert (loader_workers(explicit), event_cache_dir(explicit)) == (3, None)
    assert event_cache_dir(compose_config([f"data.event_cache={tmp_path / 'mine'}"])) == tmp_path / "mine"


def test_rolled_view_moves_image_and_pose_together():
    """A view turned 30 deg about its optical axis: a bright pixel of the MCTS lands where the pose
    and depth put its 3D point (warp_with_depth from the original view), the depth there is
    unchanged (a roll keeps z), and the corners nothing maps to have no depth."""
    from aerovis_train.correspondences import warp_with_depth
    from aerovis_train.data import roll_view

    view, _ = wall_views()
    mcts = np.zeros((2, H, W), np.float32)
    mcts[1, 20, 70] = 1.0  # (x, y) = (70, 20)
    frame = np.zeros((H, W), np.uint8)
    rolled_mcts, rolled_frame, rolled = roll_view(mcts, frame, view, np.radians(30.0))
    assert rolled_mcts.shape == mcts.shape and rolled_mcts.dtype == np.float32 and rolled_frame.shape == frame.shape
    xy1, vis = warp_with_depth(np.array([[70.0, 20.0]]), view, rolled)
    assert vis[0]
    # the blob's bilinear spread: its intensity-weighted centre is the warped point (within 0.5 px)
    ys, xs = np.nonzero(rolled_mcts[1])
    wts = rolled_mcts[1][ys, xs]
    centre = np.array([np.sum(xs * wts), np.sum(ys * wts)]) / wts.sum()
    np.testing.assert_allclose(centre, xy1[0], atol=0.5)
    # and the rotation is a real 30 deg one about the principal point (47.5, 31.5)
    v0, v1 = np.array([70 - 47.5, 20 - 31.5]), xy1[0] - [47.5, 31.5]
    angle = np.degrees(np.arctan2(v0[0] * v1[1] - v0[1] * v1[0], v0 @ v1))
    assert abs(abs(angle) - 30.0) < 1e-6 and np.linalg.norm(v1) == pytest.approx(np.linalg.norm(v0))
    r, c = int(round(xy1[0, 1])), int(round(xy1[0, 0]))
    assert rolled.depth[r, c] == pytest.approx(2.0)
    assert np.isnan(rolled.depth[0, 0]) and np.isnan(rolled.depth[-1, -1])


def test_roll_augmentation_keeps_pairs_supervised(sim_cache):
    """data.roll_deg: samples still carry correspondences (cells of view 0 matched in the turned
    view 1), and roll_deg=0 draws nothing extra, so its samples are those of a dataset without it."""
    from aerovis_slam.mcts import MCTS_NE_EVENTS_PER_PX
    from aerovis_slam.sim.cache import ensure_preset
    from aerovis_train.data import EventPairDataset, MctsSpec

    paths = sorted(ensure_preset("tiny", str(sim_cache), progress=False).glob("*.h5"))
    kw = dict(crop=(40, 56), samples_per_epoch=4, seed=5, stereo_fraction=0.0)
    spec = MctsSpec("ne", MCTS_NE_EVENTS_PER_PX)
    plain, off, rolled = (EventPairDataset(paths, spec, **kw), EventPairDataset(paths, spec, roll_deg=0.0, **kw),
                          EventPairDataset(paths, spec, roll_deg=40.0, **kw))
    matched = 0
    for i in range(4):
        a, b, r = plain[i], off[i], rolled[i]
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, equal_nan=True, msg=k)
        assert not torch.equal(a["mcts1"], r["mcts1"])
        matched += int(torch.isfinite(r["warp01"]).all(-1).sum())
    assert matched > 0


def test_soft_label_samples_are_the_integer_labels_spread(sim_cache):
    """data.label_subpixel: the same sub-pixel corners as soft targets (distributions over 65 classes)
    peak on the class the integer targets give them: the nearest pixel carries the largest bilinear weight."""
    from aerovis_slam.mcts import MCTS_NE_EVENTS_PER_PX
    from aerovis_slam.sim.cache import ensure_preset
    from aerovis_train.data import EventPairDataset, MctsSpec

    paths = sorted(ensure_preset("tiny", str(sim_cache), progress=False).glob("*.h5"))
    kw = dict(crop=(40, 56), samples_per_epoch=4, seed=5, stereo_fraction=0.0, labeller=CornerLabeller(subpixel_window=3))
    spec = MctsSpec("ne", MCTS_NE_EVENTS_PER_PX)
    hard, soft = EventPairDataset(paths, spec, **kw), EventPairDataset(paths, spec, soft_labels=True, **kw)
    labelled = 0
    for i in range(4):
        a, b = hard[i], soft[i]
        for key in ("labels0", "labels1"):
            assert b[key].dtype == torch.float32 and b[key].shape == (65, *a[key].shape)
            torch.testing.assert_close(b[key].sum(0), torch.ones(a[key].shape))
            assert torch.equal(b[key].argmax(0), a[key])
            labelled += int((a[key] < 64).sum())
    assert labelled > 0


def test_training_benchmark_reports_what_it_measured(sim_cache):
    """aerovis-bench train on the tiny preset: per model the loader it timed (auto: one worker on the
    CPU, no decoded copies), at least 10 prefetch queues (2 batches a worker) of timed steps, and
    rates that agree with each other (samples/s = batch / step time; the wait a fraction)."""
    from aerovis_train.benchmarks import bench_train

    res = bench_train(steps_min=2, overrides=["data.preset=tiny", f"data.cache_dir={sim_cache}", "data.val_sequences=1",
                                              "data.batch_size=2", "data.crop=[40,40]"])
    assert res["device"] == "cpu"
    for name in ("superlite", "superevent_plus"):
        r = res[name]
        assert (r["num_workers"], r["event_cache"], r["steps"], r["warmup_steps"]) == (1, False, 20, 3)
        assert 0.0 <= r["data_wait_fraction"] <= 1.0
        # step_s is rounded to the millisecond: batch = samples/s x step_s within samples/s x 0.5 ms
        assert abs(r["samples_per_s"] * r["step_s"] - r["batch_size"]) <= r["samples_per_s"] * 0.0005 + 1e-3
