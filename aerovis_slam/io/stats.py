"""Statistics of an event stream that compare sensors, recordings and simulator settings.

:func:`event_stats` summarises one camera's events in numbers that differ between real sensors and
a naive simulator: the event rate per pixel, the ON share, how many events fire alone (noise), how
the rate spreads over pixels (hot pixels, textureless regions), and the intervals between
successive events of one pixel (refractory period, bursts). ``aerovis-data stats`` prints them per
recording.

Definitions (``t`` in µs, sensor pixels):

* ``events_per_px_s``: events / (width x height x duration), duration from the first to the last event.
* ``on_fraction``: share of ON events.
* ``isolated_fraction``: share of events with no event at any of the 8 neighbouring pixels within
  ``isolation_us`` (10 ms) before or after them: the background-activity test of
  :class:`~aerovis_slam.noise_filter.BackgroundActivityFilter`, run forwards (support from the past)
  and on the time-reversed stream (support from the future).
* ``pixel_rate_hz``: percentiles over all sensor pixels (silent ones included) of events per second.
* ``active_pixel_fraction``: share of pixels with at least one event.
* ``iei_us``: percentiles of the intervals between successive events of the same pixel.
* ``hot_pixels``: pixels with at least ``HOT_MIN_EVENTS`` (10) events and at least ``HOT_FACTOR`` (10)
  times the mean count of their 8 neighbours: a pixel that fires far more than the pixels beside it,
  which see the same scene (an edge excites its neighbours too; a hot pixel does not).
"""

from __future__ import annotations

import numpy as np

from ..events import EventArray
from ..noise_filter import BackgroundActivityFilter

ISOLATION_US = 10_000
HOT_FACTOR = 10.0
HOT_MIN_EVENTS = 10
RATE_PERCENTILES = (50, 90, 99, 99.9)
IEI_PERCENTILES = (1, 10, 50, 90)


def neighbour_mean(counts: np.ndarray) -> np.ndarray:
    """(H, W) float64: the mean of each pixel's 8 neighbours (mirrored at the border, so every pixel has 8)."""
    c = np.asarray(counts, np.float64)
    padded = np.pad(c, 1, mode="reflect") if min(c.shape) > 1 else np.pad(c, 1, mode="edge")
    H, W = c.shape
    box = sum(padded[dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3))
    return (box - c) / 8.0


def isolated_mask(events: EventArray, width: int, height: int, window_us: int = ISOLATION_US) -> np.ndarray:
    """(N,) bool: events with no event at a neighbouring pixel (3x3, own pixel excluded) within
    ``window_us`` before or after. ``events`` sorted by time, inside the sensor."""
    forward = BackgroundActivityFilter(width, height, dt_us=window_us).keep_mask(events)
    reverse = EventArray(-events.t[::-1], events.x[::-1], events.y[::-1], events.p[::-1])
    backward = BackgroundActivityFilter(width, height, dt_us=window_us).keep_mask(reverse)[::-1]
    return ~(forward | backward)


def event_stats(events: EventArray, width: int, height: int, *, isolation_us: int = ISOLATION_US) -> dict:
    """Statistics of one camera's events (see the module docstring); JSON-ready.

    Args:
        events: time-sorted events of one camera, pixels inside ``width`` x ``height``.
    Raises:
        ValueError: events outside the sensor, or unsorted times.
    """
    n = len(events)
    out: dict = {"width": int(width), "height": int(height), "events": int(n)}
    if n == 0:
        return {**out, "duration_s": 0.0, "events_per_px_s": 0.0}
    t = np.asarray(events.t, np.int64)
    x = np.asarray(events.x, np.int64)
    y = np.asarray(events.y, np.int64)
    if x.max() >= width or y.max() >= height:
        raise ValueError(f"events outside the {width}x{height} sensor (x up to {x.max()}, y up to {y.max()})")
    if np.any(np.diff(t) < 0):
        raise ValueError("event times are not sorted")
    duration_s = max(int(t[-1] - t[0]), 1) / 1e6
    pix = y * width + x
    counts = np.bincount(pix, minlength=width * height)
    rate = counts / duration_s
    # successive events of one pixel: sort by pixel, then time (stable keeps time order within a pixel)
    order = np.argsort(pix, kind="stable")
    same = pix[order][1:] == pix[order][:-1]
    iei = np.diff(t[order])[same]
    hot = (counts >= HOT_MIN_EVENTS) & (counts >= HOT_FACTOR * neighbour_mean(counts.reshape(height, width)).ravel())
    isolated = isolated_mask(events, width, height, isolation_us)
    return {
        **out,
        "duration_s": duration_s,
        "events_per_px_s": float(n / (width * height * duration_s)),
        "on_fraction": float(np.mean(np.asarray(events.p) > 0)),
        "isolated_fraction": float(isolated.mean()),
        "active_pixel_fraction": float(np.mean(counts > 0)),
        "pixel_rate_hz": {f"p{p:g}": float(v) for p, v in zip(RATE_PERCENTILES, np.percentile(rate, RATE_PERCENTILES))},
        "iei_us": ({f"p{p:g}": float(v) for p, v in zip(IEI_PERCENTILES, np.percentile(iei, IEI_PERCENTILES))} if len(iei) else None),
        "hot_pixels": int(hot.sum()),
        "hot_pixel_event_fraction": float(counts[hot].sum() / n),
    }
