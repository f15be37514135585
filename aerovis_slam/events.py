"""Event arrays: the in-memory form of an event stream.

Conventions used throughout the project:

* ``t``: int64, microseconds, non-decreasing within a stream.
* ``x``, ``y``: uint16 pixel column and row, ``0 <= x < width``, ``0 <= y < height``.
* ``p``: int8 polarity, ``0`` = OFF (brightness decrease, the paper's -1), ``1`` = ON (+1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import DataError


@dataclass
class EventArray:
    """A chunk of events as structure-of-arrays (all of length N).

    Attributes:
        t: (N,) int64 timestamps in µs.
        x: (N,) uint16 columns.
        y: (N,) uint16 rows.
        p: (N,) int8 polarity, 0 = OFF, 1 = ON.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    p: np.ndarray

    def __post_init__(self) -> None:
        self.t = np.ascontiguousarray(self.t, dtype=np.int64)
        self.x = np.ascontiguousarray(self.x, dtype=np.uint16)
        self.y = np.ascontiguousarray(self.y, dtype=np.uint16)
        self.p = np.ascontiguousarray(self.p, dtype=np.int8)
        n = len(self.t)
        if not (len(self.x) == len(self.y) == len(self.p) == n):
            raise DataError(
                None,
                f"event fields differ in length: t={n}, x={len(self.x)}, y={len(self.y)}, p={len(self.p)}",
            )

    def __len__(self) -> int:
        return len(self.t)

    @classmethod
    def empty(cls) -> "EventArray":
        return cls(np.empty(0, np.int64), np.empty(0, np.uint16), np.empty(0, np.uint16), np.empty(0, np.int8))

    @classmethod
    def concatenate(cls, chunks: list["EventArray"]) -> "EventArray":
        if not chunks:
            return cls.empty()
        return cls(
            np.concatenate([c.t for c in chunks]),
            np.concatenate([c.x for c in chunks]),
            np.concatenate([c.y for c in chunks]),
            np.concatenate([c.p for c in chunks]),
        )

    def __getitem__(self, index) -> "EventArray":
        return EventArray(self.t[index], self.x[index], self.y[index], self.p[index])

    def time_slice(self, t_start_us: int, t_end_us: int) -> "EventArray":
        """Events with ``t_start_us <= t < t_end_us`` (``t`` must be sorted)."""
        i0, i1 = np.searchsorted(self.t, [t_start_us, t_end_us], side="left")
        return self[i0:i1]


def check_events(
    events: EventArray,
    width: int,
    height: int,
    *,
    path=None,
    field: str = "events",
    previous_t: int | None = None,
) -> None:
    """Raise :class:`DataError` unless events are sorted, inside the sensor and of valid polarity.

    Args:
        events: the chunk to check.
        width, height: sensor size in pixels.
        path: file named in the error message.
        field: field named in the error message (e.g. ``/events/cam0``).
        previous_t: last timestamp of the preceding chunk, for a check across chunks.
    """
    if len(events) == 0:
        return
    t = events.t
    if previous_t is not None and t[0] < previous_t:
        raise DataError(path, f"{field}/t decreases across chunks: {t[0]} µs after {previous_t} µs (expected sorted)")
    bad = np.flatnonzero(np.diff(t) < 0)
    if len(bad):
        i = int(bad[0])
        raise DataError(path, f"{field}/t decreases at index {i + 1}: {t[i + 1]} µs after {t[i]} µs (expected sorted)")
    if events.x.max() >= width or events.y.max() >= height:
        n_out = int(np.count_nonzero((events.x >= width) | (events.y >= height)))
        raise DataError(
            path,
            f"{field}: {n_out} events outside the {width}x{height} sensor "
            f"(max x={int(events.x.max())}, max y={int(events.y.max())})",
        )
    if np.any((events.p != 0) & (events.p != 1)):
        raise DataError(path, f"{field}/p must be 0 (OFF) or 1 (ON); found {sorted(set(np.unique(events.p).tolist()))}")
