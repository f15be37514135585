"""The simulator's optional sensor effects (photoreceptor bandwidth, dark shot noise, hot pixels,
timestamp jitter, vignetting, photographs as textures), each against its model's own formula."""

from __future__ import annotations

import numpy as np
import pytest

from aerovis_slam.sim.events import EventConfig, EventGenerator, log_intensity
from aerovis_slam.sim.presets import TRAIN_SENSOR_RANGES, preset_specs
from aerovis_slam.sim.simulator import SequenceSpec, vignette

QUIET = dict(threshold_sigma=0.0, noise=False, refractory_us=0)


def run(gen, L, t_end_us, step_us):
    """Hold the log image ``L`` from 0 to ``t_end_us`` in steps of ``step_us``: all events."""
    out = [gen.step(L, t) for t in range(step_us, t_end_us + 1, step_us)]
    t = np.concatenate([e.t for e in out])
    return t, np.concatenate([e.x for e in out]), np.concatenate([e.y for e in out]), np.concatenate([e.p for e in out])


@pytest.mark.parametrize("intensity", [1.0, 0.2])
def test_photoreceptor_low_pass_delays_crossings_by_its_time_constant(intensity):
    # a step of the log intensity by 0.6 at t = 0, thresholds 0.1: without the filter all six ON
    # crossings fire at the first step; through a first-order low-pass of time constant tau the
    # filtered value reaches k C at t_k = -tau ln(1 - k C / 0.6)
    cfg = EventConfig(threshold=0.1, cutoff_hz=100.0, eps=1e-3, **QUIET)
    gen = EventGenerator(1, 1, cfg, np.random.default_rng(0))
    I0 = intensity / np.exp(0.6)
    L0, L1 = log_intensity(np.array([[I0]]), cfg.eps), log_intensity(np.array([[intensity]]), cfg.eps)
    gen.reset(L0, 0)
    t, _, _, p = run(gen, L1, 40_000, 50)
    f = 100.0 * (min(intensity, 1.0) + 0.1) / 1.1  # the cut-off at the new render's intensity
    tau_us = 1e6 / (2 * np.pi * f)
    dL = float(L1[0, 0] - L0[0, 0])
    k = np.arange(1, int(np.floor(dL / 0.1 + 1e-9)) + 1)
    expected = -tau_us * np.log(1 - k * 0.1 / dL)
    assert p.tolist() == [1] * len(k)
    # the filter is exact at every step end and the crossings are interpolated linearly in between:
    # the error is at most a step (50 us) plus the curvature over one step
    np.testing.assert_allclose(t, expected, atol=60)


def test_without_a_cut_off_a_step_fires_at_once():
    cfg = EventConfig(threshold=0.1, **QUIET)
    gen = EventGenerator(1, 1, cfg, np.random.default_rng(0))
    gen.reset(np.array([[0.0]]), 0)
    t, _, _, _ = run(gen, np.array([[0.6 + 1e-9]]), 50, 50)
    assert len(t) == 6 and t.max() <= 50


def test_shot_noise_rises_in_the_dark_by_its_factor():
    # half the sensor dark (I ~ 0), half at full intensity; no signal (constant images)
    cfg = EventConfig(threshold=10.0, threshold_sigma=0.0, refractory_us=0, leak_hz=0.0, shot_noise_hz=20.0, shot_noise_dark_factor=5.0)
    W, H = 40, 20
    gen = EventGenerator(W, H, cfg, np.random.default_rng(1))
    img = np.ones((H, W))
    img[:, : W // 2] = 0.0
    L = log_intensity(img, cfg.eps)
    gen.reset(L, 0)
    t, x, _, _ = run(gen, L, 2_000_000, 10_000)
    dark, bright = np.sum(x < W // 2), np.sum(x >= W // 2)
    # expected: bright 20 Hz x 400 px x 2 s = 16000; dark (I = 0) 5x that, 80000; Poisson
    # standard deviations 126 and 283, so 3 % bounds are > 10 sigma
    assert bright == pytest.approx(16_000, rel=0.03)
    assert dark / bright == pytest.approx(5.0, rel=0.03)


def test_hot_pixels_fire_at_their_rates_with_one_polarity():
    cfg = EventConfig(threshold=10.0, threshold_sigma=0.0, refractory_us=0, leak_hz=0.0, shot_noise_hz=0.0,
                      hot_pixel_fraction=0.01, hot_pixel_hz=50.0)
    W, H = 100, 100
    gen = EventGenerator(W, H, cfg, np.random.default_rng(2))
    L = np.zeros((H, W))
    gen.reset(L, 0)
    t, x, y, p = run(gen, L, 4_000_000, 20_000)
    pix = y.astype(np.int64) * W + x
    assert set(np.unique(pix)) <= set(gen.hot_pix.tolist())
    # about 1 % of 10000 pixels (binomial sd 10)
    assert 60 <= len(gen.hot_pix) <= 140
    counts = np.bincount(np.searchsorted(gen.hot_pix, pix), minlength=len(gen.hot_pix))
    expected = gen.hot_rate_hz * 4.0
    # each pixel's count is Poisson around rate x 4 s (>= 100 events): within 5 sd of it
    assert np.all(np.abs(counts - expected) <= 5 * np.sqrt(expected))
    for i, hp in enumerate(gen.hot_pix):
        assert set(p[pix == hp].tolist()) == {int(gen.hot_pol[i])}


def test_timestamp_jitter_has_its_standard_deviation_and_keeps_the_stream_sorted():
    # one 10 ms ramp of 0.6 per pixel on 2000 pixels: six crossings each at exact times; with jitter
    # of 300 us the differences to the exact times have that standard deviation (few reach the clip)
    W, H = 100, 20
    exact = EventGenerator(W, H, EventConfig(threshold=0.1, **QUIET), np.random.default_rng(3))
    jittered = EventGenerator(W, H, EventConfig(threshold=0.1, timestamp_jitter_us=300.0, **QUIET), np.random.default_rng(3))
    L0, L1 = np.zeros((H, W)), np.full((H, W), 0.65)
    for g in (exact, jittered):
        g.reset(L0, 0)
    e0, e1 = exact.step(L1, 10_000), jittered.step(L1, 10_000)
    assert len(e0) == len(e1) == 6 * W * H and np.all(np.diff(e1.t) >= 0)
    assert e1.t.min() >= 1 and e1.t.max() <= 10_000
    # compare crossing by crossing: per pixel, the k-th exact against the k-th jittered time
    k0 = np.lexsort((e0.t, e0.y.astype(int) * W + e0.x))
    k1 = np.lexsort((e1.t, e1.y.astype(int) * W + e1.x))
    d = e1.t[k1].astype(float) - e0.t[k0]
    # sorting within a pixel pairs the order statistics, which shrinks the spread a little where
    # neighbouring crossings (1.5-2 ms apart here) swap; 300 us jitter rarely swaps them
    assert np.std(d) == pytest.approx(300.0, rel=0.1) and abs(np.mean(d)) < 20


def test_vignette_follows_cos4():
    class Cam:
        width, height, fx, fy, cx, cy = 201, 101, 100.0, 100.0, 100.0, 50.0

    v = vignette(Cam, 1.0)
    assert v[50, 100] == pytest.approx(1.0)
    # pixel (200, 50): tan theta = 1, cos^4 = 1/4
    assert v[50, 200] == pytest.approx(0.25, abs=1e-6)
    assert vignette(Cam, 0.5)[50, 200] == pytest.approx(1 - 0.5 * 0.75, abs=1e-6)


def test_event_config_refuses_bad_values():
    for bad in (dict(cutoff_hz=-1.0), dict(timestamp_jitter_us=float("nan")), dict(hot_pixel_fraction=1.5),
                dict(shot_noise_dark_factor=0.0)):
        with pytest.raises(ValueError, match="EventConfig"):
            EventConfig(**bad)


def test_train_preset_randomises_the_sensor_and_bench_keeps_it_off():
    train = preset_specs("train")
    default = EventConfig()
    for field in ("cutoff_hz", "shot_noise_dark_factor", "hot_pixel_fraction", "timestamp_jitter_us"):
        values = [getattr(s.events, field) for s in train]
        on = [v for v in values if v != getattr(default, field)]
        share, lo, hi = TRAIN_SENSOR_RANGES[field]
        # present in about `share` of 48 sequences (binomial sd 3.5 at 0.5): 25-75 % leaves > 3.5 sd
        assert 0.25 * len(train) <= len(on) <= 0.75 * len(train)
        assert all(lo <= v <= hi for v in on)
    assert any(s.vignetting > 0 for s in train) and any(s.user_textures for s in train)
    for s in preset_specs("bench"):
        assert s.events == EventConfig(**{k: getattr(s.events, k) for k in ("threshold", "threshold_sigma", "threshold_min",
                                                                          "refractory_us", "noise", "leak_hz", "shot_noise_hz", "eps")})
        assert s.vignetting == 0 and not s.user_textures


def test_photograph_textures_come_from_scikit_image():
    pytest.importorskip("skimage")
    from aerovis_slam.sim.scene import load_texture_image, photo_texture_path

    tex = load_texture_image("skimage:camera")
    assert tex.dtype == np.float32 and 0.06 <= tex.min() and tex.max() <= 0.9 and tex.std() > 0.05
    assert photo_texture_path("coffee").name.startswith("coffee")
    spec = SequenceSpec("photo", rig="tiny_stereo", duration_s=0.1, user_textures=["skimage:coffee"])
    assert spec.to_dict()["user_textures"] == ["skimage:coffee"]


def test_off_thresholds_scale_by_their_ratio_and_set_the_on_share():
    # a pixel brightening by 1.2 and darkening back: 1.2 / 0.2 = 6 ON crossings, 1.2 / 0.1 = 12 OFF ones
    cfg = EventConfig(threshold=0.2, off_threshold_ratio=0.5, **QUIET)
    gen = EventGenerator(1, 1, cfg, np.random.default_rng(0))
    assert gen.c_neg[0, 0] == pytest.approx(0.1) and gen.c_pos[0, 0] == pytest.approx(0.2)
    gen.reset(np.array([[0.0]]), 0)
    on = gen.step(np.array([[1.2 + 1e-9]]), 1000)
    off = gen.step(np.array([[0.0 - 1e-9]]), 2000)
    assert (on.p == 1).sum() == 6 and (off.p == 0).sum() == 12
