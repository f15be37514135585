"""Background-activity noise filter (aerovis_slam.noise_filter): its rule on hand-made events, its
independence of chunking, its survival rate on Poisson noise against the formula, and a moving
edge that passes whole."""

from __future__ import annotations

import numpy as np
import pytest

from aerovis_slam.events import EventArray
from aerovis_slam.noise_filter import BackgroundActivityFilter


def _events(t, x, y, p=None):
    t = np.asarray(t, np.int64)
    order = np.argsort(t, kind="stable")
    p = np.ones(len(t), np.int8) if p is None else np.asarray(p, np.int8)
    return EventArray(t[order], np.asarray(x)[order], np.asarray(y)[order], p[order])


def test_rule_on_hand_made_events():
    """An event passes iff one of its 8 neighbours (not its own pixel) fired at most dt before."""
    f = BackgroundActivityFilter(10, 10, dt_us=100)
    ev = _events([0, 50, 100, 150, 300, 301, 1000, 1100, 1101],
                 [5, 5, 6, 8, 0, 0, 9, 9, 9],
                 [5, 5, 5, 5, 0, 1, 9, 9, 8])
    keep = f.keep_mask(ev)
    # (5,5)@0 alone; (5,5)@50 its own pixel only: no; (6,5)@100 neighbour (5,5)@50, 50 us: yes;
    # (8,5)@150 two columns away: no; (0,0)@300 corner, alone: no; (0,1)@301 neighbour (0,0): yes;
    # (9,9)@1000 alone; (9,9)@1100 own pixel: no; (9,8)@1101 neighbour (9,9)@1100: yes
    assert keep.tolist() == [False, False, True, False, False, True, False, False, True]
    assert f.seen == 9 and f.removed == 6
    # exactly dt before passes, one microsecond more does not
    g = BackgroundActivityFilter(4, 4, dt_us=100)
    assert g.keep_mask(_events([0, 100], [1, 2], [1, 1])).tolist() == [False, True]
    g = BackgroundActivityFilter(4, 4, dt_us=100)
    assert g.keep_mask(_events([0, 101], [1, 2], [1, 1])).tolist() == [False, False]
    # a wider neighbourhood: two pixels away supports with radius 2
    h = BackgroundActivityFilter(10, 10, dt_us=100, radius=2)
    assert h.keep_mask(_events([0, 10], [5, 7], [5, 5])).tolist() == [False, True]
    # out-of-sensor coordinates are passed on for the ingest to drop (and report)
    assert BackgroundActivityFilter(4, 4, dt_us=10).keep_mask(_events([0], [7], [1])).tolist() == [True]


def test_result_does_not_depend_on_chunking():
    """The per-pixel state carries over between calls: any split of a stream gives the same events."""
    rng = np.random.default_rng(3)
    n = 20_000
    ev = _events(np.sort(rng.integers(0, 200_000, n)), rng.integers(0, 32, n), rng.integers(0, 24, n),
                 rng.integers(0, 2, n))
    whole = BackgroundActivityFilter(32, 24, dt_us=2_000).keep_mask(ev)
    assert 0.05 < whole.mean() < 0.95  # a case where both outcomes occur
    f = BackgroundActivityFilter(32, 24, dt_us=2_000)
    cuts = np.sort(rng.choice(np.arange(1, n), 40, replace=False))
    parts = [f.keep_mask(EventArray(ev.t[a:b], ev.x[a:b], ev.y[a:b], ev.p[a:b]))
             for a, b in zip(np.r_[0, cuts], np.r_[cuts, n])]
    assert np.array_equal(np.concatenate(parts), whole)
    assert f.removed == int((~whole).sum())
    # __call__ returns the passing events themselves
    out = BackgroundActivityFilter(32, 24, dt_us=2_000)(ev)
    assert np.array_equal(out.t, ev.t[whole]) and np.array_equal(out.x, ev.x[whole]) and np.array_equal(out.p, ev.p[whole])


def test_survival_of_poisson_noise_matches_the_formula():
    """Independent Poisson noise of f Hz per pixel: an event survives when one of its k neighbours
    fired in the dt before it, probability 1 - exp(-k f dt) (k = 8 inside, 5 on an edge, 3 in a
    corner). 1.0 Hz, 20 ms on 64x64 px for 20 s: ~82 k events, expected survival 14.6 %; the
    tolerance is 4 binomial standard errors (~0.5 points)."""
    rng = np.random.default_rng(0)
    w = h = 64
    f_hz, dt_s, T_s = 1.0, 0.02, 20.0
    n = rng.poisson(f_hz * w * h * T_s)
    ev = _events(rng.integers(0, int(T_s * 1e6), n), rng.integers(0, w, n), rng.integers(0, h, n))
    keep = BackgroundActivityFilter(w, h, dt_us=int(dt_s * 1e6)).keep_mask(ev)
    nx = 3 - (ev.x == 0) - (ev.x == w - 1)
    ny = 3 - (ev.y == 0) - (ev.y == h - 1)
    k = (nx * ny - 1).astype(float)
    # the first dt of the stream has no history: negligible (0.1 % of 20 s)
    expected = np.mean(1.0 - np.exp(-k * f_hz * dt_s))
    se = np.sqrt(expected * (1 - expected) / n)
    assert abs(keep.mean() - expected) < 4 * se, (keep.mean(), expected, se)


def test_moving_edge_passes_whole_but_its_first_event():
    """A vertical edge sweeping right at 500 px/s (2 ms per column, dt 5 ms) makes each column
    fire within 0.1 ms, top to bottom: each event has a neighbour that fired just before (the
    pixel above, or the previous column), except the very first."""
    w, h = 40, 30
    t, x, y = [], [], []
    for col in range(w):
        for row in range(h):
            t.append(col * 2_000 + row * 3)
            x.append(col)
            y.append(row)
    keep = BackgroundActivityFilter(w, h, dt_us=5_000).keep_mask(_events(t, x, y))
    assert keep.sum() == w * h - 1 and not keep[0]


def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="dt_us"):
        BackgroundActivityFilter(4, 4, dt_us=0)
    with pytest.raises(ValueError, match="radius"):
        BackgroundActivityFilter(4, 4, dt_us=10, radius=0)
    with pytest.raises(ValueError, match="sensor size"):
        BackgroundActivityFilter(0, 4, dt_us=10)
