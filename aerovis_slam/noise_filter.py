"""Background-activity noise filter for event streams (Delbruck 2008, "Frame-free dynamic digital
vision"; the ``BackgroundActivityNoiseFilter`` of iniVation's dv-processing and Prophesee's
``ActivityNoiseFilterAlgorithm`` work the same way).

A pixel that fires because of leak or shot noise fires alone: no neighbour fired shortly before.
An edge moving over the sensor makes neighbouring pixels fire within a short time of each other.
So an event passes when one of the (2r+1)^2 - 1 pixels around it (its own pixel excluded) fired
within ``dt`` before it; every event, passed or not, updates its pixel's time. With a noise rate of
``f`` Hz per pixel a noise event survives with probability about ``1 - exp(-8 f dt)`` (r = 1): 1.6 %
at 0.2 Hz and 10 ms, the simulator's leak-and-shot level in a textureless room.

Written here rather than taken from dv-processing: that is an optional C++ dependency of the
dataset readers, and the runtime ingests events in chunks on its own thread; the kernel is one
sequential pass per chunk (numba), with the per-pixel state kept between chunks, so the result does
not depend on how the stream was chunked.

Example:
    >>> f = BackgroundActivityFilter(8, 8, dt_us=1000)
    >>> ev = EventArray([0, 10, 500, 5000, 5010], [3, 4, 6, 1, 1], [3, 3, 6, 1, 2], [1, 1, 0, 1, 1])
    >>> f(ev).x.tolist()  # (4,3) follows its neighbour (3,3); (6,6) and (1,1) alone; (1,2) follows (1,1)
    [4, 1]
"""

from __future__ import annotations

import numba
import numpy as np

from .events import EventArray

__all__ = ["BackgroundActivityFilter"]

_NEVER = np.int64(-(2**62))


@numba.njit(cache=True, nogil=True)
def _filter_kernel(x, y, t, last, width, height, dt_us, radius, keep):  # pragma: no cover (numba)
    for i in range(len(t)):
        xi, yi, ti = np.int64(x[i]), np.int64(y[i]), t[i]
        if xi >= width or yi >= height:  # out of the sensor: left for the ingest to report and drop
            keep[i] = True
            continue
        ok = False
        for yy in range(max(yi - radius, 0), min(yi + radius + 1, height)):
            row = yy * width
            for xx in range(max(xi - radius, 0), min(xi + radius + 1, width)):
                if (xx != xi or yy != yi) and ti - last[row + xx] <= dt_us:
                    ok = True
                    break
            if ok:
                break
        keep[i] = ok
        last[yi * width + xi] = ti


class BackgroundActivityFilter:
    """Streaming background-activity filter for one camera (sensor pixel coordinates).

    Args:
        width, height: sensor size in pixels (events are in sensor coordinates, before any
            downsampling or rectification).
        dt_us: support window: an event passes when a neighbour fired at most this long before it (µs).
        radius: neighbourhood half-size in pixels (1: the 8 neighbours).

    Attributes:
        seen, removed: events given to the filter and events it removed, over all calls.
    """

    def __init__(self, width: int, height: int, *, dt_us: int, radius: int = 1):
        if width < 1 or height < 1:
            raise ValueError(f"sensor size must be positive, got {width}x{height}")
        if dt_us <= 0:
            raise ValueError(f"dt_us must be positive, got {dt_us}")
        if radius < 1:
            raise ValueError(f"radius must be at least 1 pixel, got {radius}")
        self.width, self.height = int(width), int(height)
        self.dt_us, self.radius = int(dt_us), int(radius)
        self._last = np.full(self.width * self.height, _NEVER, np.int64)
        self.seen = 0
        self.removed = 0

    def keep_mask(self, events: EventArray) -> np.ndarray:
        """(N,) bool: which events pass, in stream order (the filter's state advances over them)."""
        keep = np.empty(len(events), np.bool_)
        if len(events):
            _filter_kernel(events.x, events.y, events.t, self._last, self.width, self.height, self.dt_us, self.radius,
                           keep)
        self.seen += len(events)
        self.removed += int(len(events) - np.count_nonzero(keep))
        return keep

    def __call__(self, events: EventArray) -> EventArray:
        """The events that pass (a new :class:`EventArray`; the input is not changed)."""
        keep = self.keep_mask(events)
        if keep.all():
            return events
        return EventArray(events.t[keep], events.x[keep], events.y[keep], events.p[keep])

    @property
    def removed_fraction(self) -> float:
        return self.removed / self.seen if self.seen else 0.0
