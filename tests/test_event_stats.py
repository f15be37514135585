"""Event-stream statistics (``aerovis-data stats``) on streams whose figures are known by construction."""

from __future__ import annotations

import json

import numpy as np
import pytest

from aerovis_slam.events import EventArray
from aerovis_slam.io import cli
from aerovis_slam.io.stats import event_stats, isolated_mask


def ev(rows):
    """EventArray from (t_us, x, y, p) rows, sorted by time."""
    a = np.array(sorted(rows), np.int64).reshape(-1, 4)
    return EventArray(a[:, 0], a[:, 1].astype(np.uint16), a[:, 2].astype(np.uint16), a[:, 3].astype(np.int8))


def test_isolation_looks_both_ways_at_the_eight_neighbours_only():
    events = ev([
        (0, 5, 5, 1), (5_000, 6, 5, 1),          # neighbours 5 ms apart: each supports the other (past and future)
        (100_000, 1, 1, 1), (101_000, 1, 1, 0),  # the same pixel twice: no neighbour, both isolated
        (200_000, 10, 10, 1), (215_000, 11, 11, 0),  # diagonal neighbours 15 ms apart: outside 10 ms, isolated
        (300_000, 15, 15, 1), (310_000, 15, 16, 1),  # exactly 10 ms: inside (the window is inclusive)
    ])
    assert isolated_mask(events, 20, 20, 10_000).tolist() == [False, False, True, True, True, True, False, False]


def test_event_stats_rates_intervals_and_hot_pixels():
    W, H = 10, 8
    rows = [(i * 1000, 2, 2, 1) for i in range(60)]                 # a hot pixel: 60 events, silent neighbours
    rows += [(i * 1000 + 500, 6, y, i % 2) for y in range(H) for i in range(20)]  # an edge: column 6, 20 events a pixel
    rows += [(59_000, 9, 0, 0)]                                     # one lone event, ends the recording at 59 ms
    s = event_stats(ev(rows), W, H)
    n = 60 + 20 * H + 1
    duration = 59_000 / 1e6  # from the first event (0) to the last (the hot pixel's and the lone one's, 59 ms)
    assert s["events"] == n and s["duration_s"] == pytest.approx(duration)
    assert s["events_per_px_s"] == pytest.approx(n / (W * H * duration))
    assert s["on_fraction"] == pytest.approx((60 + 10 * H) / n)
    # the hot pixel and the edge column fire at intervals of exactly 1 ms: every interval is 1000 us
    assert s["iei_us"] == {"p1": 1000.0, "p10": 1000.0, "p50": 1000.0, "p90": 1000.0}
    # a pixel of column 6 has two neighbours with 20 events each (mean 40 / 8 = 5; 20 < 10 x 5): not hot;
    # (2, 2) has 60 events and silent neighbours: hot; the lone event's pixel has fewer than 10
    assert s["hot_pixels"] == 1 and s["hot_pixel_event_fraction"] == pytest.approx(60 / n)
    assert s["active_pixel_fraction"] == pytest.approx((1 + H + 1) / (W * H))
    rates = np.zeros(W * H)
    rates[2 * W + 2], rates[[y * W + 6 for y in range(H)]], rates[9] = 60, 20, 1
    assert s["pixel_rate_hz"]["p99"] == pytest.approx(np.percentile(rates / duration, 99))
    # isolated: the hot pixel's events (a pixel is not its own neighbour) and the lone one
    assert s["isolated_fraction"] == pytest.approx(61 / n)


def test_event_stats_refuses_events_outside_the_sensor():
    with pytest.raises(ValueError, match="outside the 4x4 sensor"):
        event_stats(ev([(0, 4, 0, 1)]), 4, 4)


def test_cli_stats_on_a_real_recording(shared_data, capsys):
    raw = shared_data / "events" / "prophesee_gen3_evt2.raw"
    assert cli.main(["stats", str(raw), "--max-events", "100000"]) == 0
    line = json.loads(capsys.readouterr().out)
    s = line["cameras"]["cam0"]
    assert line["recording"] == str(raw) and (s["width"], s["height"]) == (640, 480)
    assert s["events"] == 100_000 and s["truncated"] is True  # the file holds 521,252 events (shared/data/README.md)
    assert 0 < s["on_fraction"] < 1 and 0 <= s["isolated_fraction"] <= 1


def test_cli_stats_bad_input(tmp_path, capsys):
    assert cli.main(["stats", str(tmp_path / "none.h5")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none.h5" in err[0]
