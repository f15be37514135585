"""Multi-channel time surfaces (MCTS): the one implementation shared by training and runtime.

The whole state is a per-pixel, per-polarity buffer of the latest event timestamp
(``2 x H x W`` int64 µs) plus a ring of the most recent timestamps of all events (needed to find
``t_(I - N_k)`` for the constant-event-count windows). From these, at any time ``tau`` at or
after the newest ingested event:

* time surface (paper eq. 2): ``TS_{p,dt}(x, y) = max(0, 1 - (tau - t_p(x, y)) / dt)``, where
  ``t_p(x, y)`` is the newest event of polarity ``p`` at the pixel (only the newest matters, since
  the value decreases with age; a pixel without events in ``[tau - dt, tau]`` is 0).
* ``MCTS_dt`` (SuperEvent): fixed windows ``dt_k`` in {1, 3, 10, 30, 100} ms -> 10 channels.
* ``MCTS_Ne`` (AERO-VIS, paper eq. 3): ``dt_k = tau - t_(I - N_k)`` with ``I`` the index of the
  newest event and ``N_k = ceil(rho_k * H * W)``, ``rho_k`` in {0.03, 0.1, 0.3, 1.0} events per
  pixel -> 8 channels. With fewer than ``N_k + 1`` events seen, the window reaches back to the
  first event. ``dt_k`` is at least 1 µs (all events sharing one timestamp would give 0).

Channel order (paper eq. 1, stored in every exported model's metadata as ``"polarity-major"``):
``channel = p * K + k``: first the K OFF (p = 0, the paper's -1) surfaces from the shortest to the
longest window, then the K ON (p = 1) surfaces.

Ingest and MCTS are numba kernels: one pass over the events (index computation, bounds and order
checks, buffer and ring writes fused) and one pass over the buffer writing all channels, because a
numpy expression per channel re-reads the buffer and materialises temporaries (about 7x the
memory-traffic floor; the fused kernel is close to it, see ``aerovis-bench mcts``).

Spatial mapping (:class:`PixelMap`): integer or fractional downsampling (e.g. 1280x720 -> 424x240)
and undistortion/rectification are one lookup table from sensor pixel to buffer pixel, applied
during ingest. An optional event-rate cap thins bursts deterministically.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba
import numpy as np

from .calib import CameraCalibration
from .errors import DataError
from .events import EventArray

MCTS_NE_EVENTS_PER_PX: tuple[float, ...] = (0.03, 0.1, 0.3, 1.0)
MCTS_DT_WINDOWS_MS: tuple[float, ...] = (1.0, 3.0, 10.0, 30.0, 100.0)
CHANNEL_ORDER = "polarity-major"  # channel = p * K + k
NO_EVENT = np.int64(-(2**62))  # "never": far enough in the past that every surface is 0


def channel_names(kind: str, params: Sequence[float]) -> list[str]:
    """Human-readable channel names in storage order, e.g. ``["off_ne0.03", ..., "on_ne1"]``."""
    tag = {"ne": "ne", "dt": "dt"}[kind]
    unit = "" if kind == "ne" else "ms"
    return [f"{pol}_{tag}{v:g}{unit}" for pol in ("off", "on") for v in params]


def events_per_window(events_per_px: Sequence[float], width: int, height: int) -> np.ndarray:
    """``N_k = ceil(rho_k * H * W)`` (int64 (K,)): events per MCTS_Ne window at this resolution."""
    # round first: 0.3 * 640 * 480 is 92159.99999999999 in floating point, and ceil must not add one
    return np.array([math.ceil(round(r * width * height, 6)) for r in events_per_px], dtype=np.int64)


def warm_up_requirement(kind: str, params: Sequence[float], width: int, height: int) -> tuple[int, float]:
    """What an MCTS needs to be complete: (events since the start, µs since the first event).

    MCTS_Ne (``kind`` 'ne', ``params`` in events per pixel): the longest window reaches back
    ``max(N_k)`` events before the newest, so ``max(N_k) + 1`` events. MCTS_dt ('dt', ms): one
    event and the longest window since it. The runtime's warm-up
    (:meth:`TimestampBuffer.is_complete`) and ``aerovis-eval pose``'s first frame use this rule.
    """
    if kind == "ne":
        return int(events_per_window(params, width, height).max()) + 1, 0.0
    if kind == "dt":
        return 1, max(float(w) for w in params) * 1000.0
    raise ValueError(f"MCTS kind must be 'ne' or 'dt', got {kind!r}")


# --------------------------------------------------------------------------------------------
# numba kernels
# --------------------------------------------------------------------------------------------
@numba.njit(cache=True, nogil=True)
def _ingest_kernel(t, x, y, p, lut, in_width, in_height, ts_flat, plane, ring, ring_pos, last_t):
    """Write events into the buffer and ring. Returns (accepted, new ring_pos, new last_t, error).

    error: 0 ok; -(i+1) event i has a decreasing timestamp; -(n+1+i) event i is outside the
    sensor or has a polarity other than 0/1. Nothing after the bad event is written.
    """
    n = t.shape[0]
    cap = ring.shape[0]
    use_lut = lut.shape[0] > 0
    accepted = 0
    for i in range(n):
        ti = t[i]
        if ti < last_t:
            return accepted, ring_pos, last_t, -(i + 1)
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        pi = np.int64(p[i])
        if xi >= in_width or yi >= in_height or pi < 0 or pi > 1:
            return accepted, ring_pos, last_t, -(n + 1 + i)
        last_t = ti
        idx = yi * in_width + xi
        if use_lut:
            idx = np.int64(lut[idx])
            if idx < 0:
                continue
        ts_flat[pi * plane + idx] = ti
        ring[ring_pos] = ti
        ring_pos += 1
        if ring_pos == cap:
            ring_pos = 0
        accepted += 1
    return accepted, ring_pos, last_t, 0


@numba.njit(cache=True, nogil=True)
def _surfaces_kernel(ts_flat, plane, tau, inv_dt, out):
    """out[p*K + k, i] = max(0, 1 - (tau - ts[p, i]) * inv_dt[k]) for all pixels i, one pass."""
    K = inv_dt.shape[0]
    for pol in range(2):
        base = pol * plane
        for i in range(plane):
            age = np.float32(tau - ts_flat[base + i])
            for k in range(K):
                v = np.float32(1.0) - age * inv_dt[k]
                out[pol * K + k, i] = v if v > np.float32(0.0) else np.float32(0.0)


@numba.njit(cache=True, nogil=True)
def _memory_floor_kernel(ts_flat, plane, K, out):
    """Same reads and writes as :func:`_surfaces_kernel` with no arithmetic: the traffic floor."""
    for pol in range(2):
        base = pol * plane
        for i in range(plane):
            v = np.float32(ts_flat[base + i])
            for k in range(K):
                out[pol * K + k, i] = v


# --------------------------------------------------------------------------------------------
# pixel mapping
# --------------------------------------------------------------------------------------------
class PixelMap:
    """Sensor pixel -> buffer pixel lookup (downsampling, undistortion, rectification).

    Attributes:
        sensor_width, sensor_height: input (sensor) resolution.
        width, height: output (buffer) resolution.
        lut: int32 (sensor_height * sensor_width,) flat output index, -1 = dropped; ``None`` for
            the identity map.
        K: (3, 3) intrinsics of the output image (None when unknown).
    """

    def __init__(self, sensor_width: int, sensor_height: int, width: int, height: int, lut: np.ndarray | None, K=None):
        self.sensor_width, self.sensor_height = int(sensor_width), int(sensor_height)
        self.width, self.height = int(width), int(height)
        if lut is not None:
            lut = np.ascontiguousarray(lut, dtype=np.int32).ravel()
            if lut.shape[0] != self.sensor_width * self.sensor_height:
                raise ValueError(f"lut has {lut.shape[0]} entries, expected {self.sensor_width * self.sensor_height}")
        self.lut = lut
        self.K = None if K is None else np.asarray(K, dtype=np.float64)

    @classmethod
    def identity(cls, width: int, height: int, K=None) -> "PixelMap":
        return cls(width, height, width, height, None, K)

    @classmethod
    def downsample(cls, sensor_width: int, sensor_height: int, width: int, height: int, K=None) -> "PixelMap":
        """Area-binning to ``width x height`` (any, also fractional, factor): ``x_out = floor(x * W_out / W_in)``.

        ``K`` (sensor intrinsics) is mapped to the output's intrinsics when given.
        """
        if width > sensor_width or height > sensor_height:
            raise ValueError(f"downsampling cannot enlarge {sensor_width}x{sensor_height} to {width}x{height}")
        xs = (np.arange(sensor_width, dtype=np.int64) * width) // sensor_width
        ys = (np.arange(sensor_height, dtype=np.int64) * height) // sensor_height
        lut = (ys[:, None] * width + xs[None, :]).astype(np.int32)
        K_out = None
        if K is not None:
            sx, sy = width / sensor_width, height / sensor_height
            K = np.asarray(K, dtype=np.float64)
            # pixel centres: continuous coordinate u maps to (u + 0.5) * s - 0.5
            K_out = np.array([[K[0, 0] * sx, 0, (K[0, 2] + 0.5) * sx - 0.5], [0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5], [0, 0, 1]])
        return cls(sensor_width, sensor_height, width, height, lut, K_out)

    @classmethod
    def from_calibration(cls, cam: CameraCalibration, width: int | None = None, height: int | None = None, *, rectify: bool = False) -> "PixelMap":
        """Undistort (and with ``rectify``, rectify) events into a pinhole image of ``width x height``.

        Each sensor pixel centre is mapped through the inverse distortion (OpenCV) and rounded to
        the nearest output pixel; pixels landing outside are dropped. The output intrinsics are the
        calibration's ``P_rect`` (rectified) or ``K``, scaled to the output size.
        """
        width = width or cam.width
        height = height or cam.height
        u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64), np.arange(cam.height, dtype=np.float64))
        pts = cam.undistort_points(np.stack([u.ravel(), v.ravel()], axis=1), rectify=rectify)
        sx, sy = width / cam.width, height / cam.height
        xo = np.rint((pts[:, 0] + 0.5) * sx - 0.5).astype(np.int64)
        yo = np.rint((pts[:, 1] + 0.5) * sy - 0.5).astype(np.int64)
        inside = (xo >= 0) & (xo < width) & (yo >= 0) & (yo < height)
        lut = np.where(inside, yo * width + xo, -1).astype(np.int32)
        K_in = cam.P_rect[:, :3] if (rectify and cam.P_rect is not None) else cam.K
        K_out = np.array([[K_in[0, 0] * sx, 0, (K_in[0, 2] + 0.5) * sx - 0.5], [0, K_in[1, 1] * sy, (K_in[1, 2] + 0.5) * sy - 0.5], [0, 0, 1]])
        return cls(cam.width, cam.height, width, height, lut, K_out)


# --------------------------------------------------------------------------------------------
# the buffer
# --------------------------------------------------------------------------------------------
class TimestampBuffer:
    """Latest-timestamp buffer of one camera, from which MCTS are computed at any time.

    Args:
        width, height: buffer (MCTS) resolution in pixels.
        pixel_map: sensor -> buffer mapping; identity (sensor = buffer size) when None.
        events_per_px: the MCTS_Ne windows this buffer must serve; sizes the ring to
            ``max(N_k) + 1`` timestamps.
        max_rate_ev_s: event-rate cap in events per second (None: no cap). Events above the cap
            are thinned evenly within each ingested packet (a token bucket refilled at the cap,
            holding at most 10 ms of budget), as the paper's drone capped its sensor at 35 Mev/s.

    Attributes:
        ts: (2, H, W) int64 newest timestamp per polarity and pixel (:data:`NO_EVENT` if none).
        count: number of events accepted so far. ``last_t``: newest accepted timestamp (µs);
            ``first_t``: the first accepted one (µs).
        dropped_rate_cap: events dropped by the rate cap.

    Example:
        >>> buf = TimestampBuffer(4, 2, events_per_px=(0.5,))
        >>> buf.ingest(EventArray([0, 10, 20, 30], [0, 1, 2, 3], [0, 0, 1, 1], [1, 1, 0, 1]))
        4
        >>> ne = buf.mcts_ne(tau=30, events_per_px=(0.5,))  # N = 4 -> window back to the first event
        >>> ne.shape, float(ne[1, 1, 3]), round(float(ne[1, 0, 1]), 4)  # ON: newest -> 1, t=10 -> 1 - 20/30
        ((2, 2, 4), 1.0, 0.3333)
    """

    def __init__(
        self,
        width: int,
        height: int,
        *,
        pixel_map: PixelMap | None = None,
        events_per_px: Sequence[float] = MCTS_NE_EVENTS_PER_PX,
        max_rate_ev_s: float | None = None,
    ):
        self.width, self.height = int(width), int(height)
        self.pixel_map = pixel_map or PixelMap.identity(width, height)
        if (self.pixel_map.width, self.pixel_map.height) != (self.width, self.height):
            raise ValueError(f"pixel_map outputs {self.pixel_map.width}x{self.pixel_map.height}, buffer is {width}x{height}")
        self._lut = self.pixel_map.lut if self.pixel_map.lut is not None else np.empty(0, np.int32)
        self.plane = self.width * self.height
        self.ring_capacity = int(events_per_window(events_per_px, width, height).max()) + 1
        self.max_rate_ev_s = max_rate_ev_s
        self.ts = np.empty((2, self.height, self.width), dtype=np.int64)
        self.ring = np.empty(self.ring_capacity, dtype=np.int64)
        self.reset()

    def reset(self) -> None:
        """Forget all events."""
        self.ts.fill(NO_EVENT)
        self.ring.fill(NO_EVENT)
        self.count = 0
        self.last_t = int(NO_EVENT)
        self.first_t = int(NO_EVENT)
        self._ring_pos = 0
        self.dropped_rate_cap = 0
        self._budget = None
        self._budget_t = None

    # -- ingest -------------------------------------------------------------------------
    def ingest(self, events: EventArray) -> int:
        """Add a packet of sensor events (time-sorted, continuing the stream). Returns events accepted.

        Raises:
            DataError: a timestamp decreases, or an event lies outside the sensor or has a bad
                polarity. Events before the bad one are kept, nothing after it.
        """
        t, x, y, p = events.t, events.x, events.y, events.p
        if len(t) == 0:
            return 0
        if self.max_rate_ev_s is not None:
            t, x, y, p = self._apply_rate_cap(t, x, y, p)
        accepted, self._ring_pos, last_t, err = _ingest_kernel(
            t, x, y, p, self._lut, self.pixel_map.sensor_width, self.pixel_map.sensor_height,
            self.ts.reshape(-1), self.plane, self.ring, self._ring_pos, np.int64(self.last_t))
        if self.count == 0 and accepted:
            self.first_t = int(t[0])
        self.count += int(accepted)
        self.last_t = int(last_t)
        if err:
            n = len(t)
            i = -err - 1
            if i < n:
                raise DataError(None, f"event timestamps decrease at index {i} of the packet: {t[i]} µs after {self.last_t} µs")
            i -= n
            raise DataError(None, f"event {i} of the packet is outside the {self.pixel_map.sensor_width}x{self.pixel_map.sensor_height} "
                                  f"sensor or has polarity other than 0/1: x={x[i]}, y={y[i]}, p={p[i]}")
        return int(accepted)

    def _apply_rate_cap(self, t, x, y, p):
        t0, t1 = int(t[0]), int(t[-1])
        burst = self.max_rate_ev_s * 0.01  # at most 10 ms of budget saved up
        if self._budget is None:
            self._budget, self._budget_t = burst, t0
        self._budget = min(burst, self._budget + (t1 - self._budget_t) * 1e-6 * self.max_rate_ev_s)
        self._budget_t = t1
        n = len(t)
        if n <= self._budget:
            self._budget -= n
            return t, x, y, p
        keep_n = max(int(self._budget), 0)
        # evenly spaced subset: event i is kept when floor((i+1) r) > floor(i r), r = keep/n
        r = keep_n / n
        i = np.arange(n)
        keep = np.floor((i + 1) * r) > np.floor(i * r)
        self._budget -= keep_n
        self.dropped_rate_cap += n - int(keep.sum())
        return t[keep], x[keep], y[keep], p[keep]

    # -- time surfaces ------------------------------------------------------------------
    def _check_tau(self, tau: int | None) -> int:
        if tau is None:
            if self.count == 0:
                raise DataError(None, "no events ingested yet: an MCTS needs at least one event or an explicit tau")
            return self.last_t
        tau = int(tau)
        if self.count and tau < self.last_t:
            raise DataError(None, f"MCTS requested at tau={tau} µs but events up to {self.last_t} µs were already ingested; "
                                  "ingest only events up to tau (the buffer cannot forget newer events)")
        return tau

    def timestamp_at_offset(self, n_back: int) -> int:
        """``t_(I - n_back)``: timestamp of the event ``n_back`` places before the newest (clamped to the first)."""
        if self.count == 0:
            raise DataError(None, "no events ingested yet")
        if n_back >= self.ring_capacity:
            raise ValueError(f"ring holds {self.ring_capacity} timestamps; cannot look {n_back} events back "
                             "(construct the buffer with the events_per_px you need)")
        n_back = min(n_back, self.count - 1)
        return int(self.ring[(self._ring_pos - 1 - n_back) % self.ring_capacity])

    def ne_windows_us(self, tau: int | None = None, events_per_px: Sequence[float] = MCTS_NE_EVENTS_PER_PX) -> np.ndarray:
        """MCTS_Ne window lengths ``dt_k = tau - t_(I - N_k)`` in µs (float64 (K,), at least 1)."""
        tau = self._check_tau(tau)
        n_k = events_per_window(events_per_px, self.width, self.height)
        return np.array([max(tau - self.timestamp_at_offset(int(n)), 1) for n in n_k], dtype=np.float64)

    def surfaces(self, tau: int, windows_us: Sequence[float], out: np.ndarray | None = None) -> np.ndarray:
        """Time surfaces for arbitrary windows (µs): float32 (2K, H, W), polarity-major."""
        tau = self._check_tau(tau)
        windows = np.asarray(windows_us, dtype=np.float64)
        if np.any(windows <= 0):
            raise ValueError(f"time windows must be positive, got {windows.tolist()}")
        K = len(windows)
        if out is None:
            out = np.empty((2 * K, self.height, self.width), dtype=np.float32)
        elif out.shape != (2 * K, self.height, self.width) or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(f"out must be C-contiguous float32 {(2 * K, self.height, self.width)}, got {out.dtype} {out.shape}")
        inv_dt = (1.0 / windows).astype(np.float32)
        _surfaces_kernel(self.ts.reshape(-1), self.plane, np.int64(tau), inv_dt, out.reshape(2 * K, self.plane))
        return out

    def is_complete(self, tau: int, kind: str, params: Sequence[float]) -> bool:
        """Whether the MCTS at ``tau`` (µs) is complete (:func:`warm_up_requirement`): before that
        the long channels show only the events since the start, a surface the detectors never saw
        in training."""
        events, span_us = warm_up_requirement(kind, params, self.width, self.height)
        return self.count >= events and int(tau) - self.first_t >= span_us

    def mcts_ne(self, tau: int | None = None, events_per_px: Sequence[float] = MCTS_NE_EVENTS_PER_PX, out=None) -> np.ndarray:
        """MCTS with constant event count (paper eq. 3): float32 (2K, H, W), K = len(events_per_px).

        Args:
            tau: time of the surface in µs (default: the newest event). Must not precede ingested events.
            events_per_px: normalised event counts rho_k (events per pixel of this buffer).
            out: optional preallocated output (reused by the runtime to avoid page faults).
        """
        tau = self._check_tau(tau)
        if self.count == 0:  # no events at all: every surface is 0, whatever the windows
            return self.surfaces(tau, np.ones(len(events_per_px)), out)
        return self.surfaces(tau, self.ne_windows_us(tau, events_per_px), out)

    def mcts_dt(self, tau: int | None = None, windows_ms: Sequence[float] = MCTS_DT_WINDOWS_MS, out=None) -> np.ndarray:
        """MCTS with fixed time windows (SuperEvent): float32 (2K, H, W), windows in ms."""
        tau = self._check_tau(tau)
        return self.surfaces(tau, np.asarray(windows_ms, dtype=np.float64) * 1000.0, out)

    def copy(self) -> "TimestampBuffer":
        """An independent snapshot (the frontend freezes the state it runs the network on)."""
        other = object.__new__(TimestampBuffer)
        other.__dict__.update(self.__dict__)
        other.ts = self.ts.copy()
        other.ring = self.ring.copy()
        return other


def mcts_from_events(
    events: EventArray,
    width: int,
    height: int,
    tau: int | None = None,
    *,
    kind: str = "ne",
    params: Sequence[float] | None = None,
    pixel_map: PixelMap | None = None,
) -> np.ndarray:
    """One MCTS from a slice of events ending at or before ``tau`` (convenience for datasets).

    Only the events that can reach a channel matter: for MCTS_Ne the last ``max(N_k) + 1`` events,
    for MCTS_dt those within the longest window; pass at least that many.

    Args:
        events: time-sorted events with ``t <= tau``.
        width, height: buffer resolution.
        tau: time of the surface (µs); default: the last event.
        kind: ``"ne"`` (8 channels by default) or ``"dt"`` (10 channels by default).
        params: ``events_per_px`` for ``ne``, ``windows_ms`` for ``dt``.
        pixel_map: sensor -> buffer map (identity when None).
    Returns:
        float32 (2K, height, width).
    """
    if kind == "ne":
        params = tuple(params or MCTS_NE_EVENTS_PER_PX)
        buf = TimestampBuffer(width, height, pixel_map=pixel_map, events_per_px=params)
        buf.ingest(events)
        return buf.mcts_ne(tau, params)
    if kind == "dt":
        params = tuple(params or MCTS_DT_WINDOWS_MS)
        buf = TimestampBuffer(width, height, pixel_map=pixel_map, events_per_px=(1e-9,))
        buf.ingest(events)
        return buf.mcts_dt(tau, params)
    raise ValueError(f"kind must be 'ne' or 'dt', not {kind!r}")
