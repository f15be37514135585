"""Preprocessing: stereo events into per-camera timestamp buffers, only where the IMU covers them.

Paper Fig. 1: events are time-synchronised with the IMU (an event is ingested only once an IMU
sample at or after its timestamp exists, so the state at its time can be propagated; later events
wait), update a per-camera latest-timestamp buffer, and the frontend freezes the buffers and
computes the MCTS on demand.

* :class:`EventReader`: background threads (one per camera) that read event chunks from the
  canonical sequence (HDF5 decompression off the processing thread), in bounded queues.
* :class:`EventFeeder`: pulls chunks and ingests events up to a requested time into
  :class:`~aerovis_slam.mcts.TimestampBuffer` (with the sensor-to-buffer :class:`PixelMap` and the
  event-rate cap), freezes copies, and computes the stereo MCTS batch for the detector.
* :class:`LivePreprocessor`: a thread that keeps the buffers current at wall-clock speed
  (the ``live`` mode); the frontend snapshots them under a lock.
"""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path

import numpy as np

from ..events import EventArray
from ..io.sequence import Sequence
from ..mcts import TimestampBuffer
from ..noise_filter import BackgroundActivityFilter
from .cameras import StereoCameras

_END = object()


class EventReader:
    """Reads the events of ``cam0`` and ``cam1`` in chunks, one background thread per camera.

    One thread per camera (each with its own file handle): with a single thread alternating between
    the cameras, a full queue of one camera would block the reads the consumer waits for on the
    other (a deadlock when the frontend jumps far ahead, as in async mode at 25 Mev/s).

    Args:
        path: canonical sequence file.
        chunk_events: events per chunk. prefetch: chunks queued per camera.
        stop_event: ends the threads early when set (also set by :meth:`close`).
        time_shift_us: per camera, µs added to every timestamp (the camera's
            ``timeshift_cam_imu_us``: its events then carry IMU-clock times); missing: 0.
    """

    def __init__(self, path: str | Path, *, chunk_events: int = 200_000, prefetch: int = 4,
                 cams: tuple[str, str] = ("cam0", "cam1"), stop_event: threading.Event | None = None,
                 time_shift_us: dict[str, int] | None = None):
        self.path = Path(path)
        self.cams = cams
        self.time_shift_us = {c: int((time_shift_us or {}).get(c, 0)) for c in cams}
        self.chunk_events = int(chunk_events)
        self.queues = {c: queue.Queue(maxsize=max(int(prefetch), 1)) for c in cams}
        self._stop = threading.Event()
        self._outer_stop = stop_event
        self.error: BaseException | None = None
        self._threads = {c: threading.Thread(target=self._run, args=(c,), name=f"aerovis-event-reader-{c}", daemon=True)
                         for c in cams}
        for t in self._threads.values():
            t.start()

    def _stopped(self) -> bool:
        return self._stop.is_set() or (self._outer_stop is not None and self._outer_stop.is_set())

    def _put(self, cam: str, item) -> bool:
        while not self._stopped():
            try:
                self.queues[cam].put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def _run(self, cam: str) -> None:
        try:
            with Sequence(self.path) as seq:
                n = seq.num_events(cam) if cam in seq.cameras else 0
                pos = 0
                while pos < n and not self._stopped():
                    stop = min(pos + self.chunk_events, n)
                    ev = seq.events_by_index(cam, pos, stop)
                    if self.time_shift_us[cam]:
                        ev = EventArray(ev.t + self.time_shift_us[cam], ev.x, ev.y, ev.p)
                    pos = stop
                    if not self._put(cam, ev):
                        return
                self._put(cam, _END)
        except BaseException as exc:  # handed to the consumer, which re-raises it
            self.error = exc
            try:
                self.queues[cam].put_nowait(_END)
            except queue.Full:
                pass

    def get(self, cam: str, timeout: float = 0.1):
        """Next chunk of ``cam`` (an :class:`EventArray`), or None at the end of the stream."""
        while True:
            if self.error is not None:
                raise self.error
            try:
                item = self.queues[cam].get(timeout=timeout)
            except queue.Empty:
                if self._stopped() or not self._threads[cam].is_alive():
                    if self.error is not None:
                        raise self.error
                    if self.queues[cam].empty():
                        return None
                continue
            if self.error is not None:
                raise self.error
            return None if item is _END else item

    def close(self) -> None:
        """Stop the threads and wait for them (idempotent)."""
        self._stop.set()
        for q in self.queues.values():  # unblock a put waiting on a full queue
            try:
                while True:
                    q.get_nowait()
            except queue.Empty:
                pass
        for t in self._threads.values():
            t.join(timeout=5.0)

    @property
    def alive(self) -> bool:
        return any(t.is_alive() for t in self._threads.values())


#: Bound of :func:`observation_time`'s lag: after a stretch without events the N-th
#: newest event can be seconds old, while the keypoints then show edges that moved since (such
#: frames carry few new events and are propagated with the IMU anyway).
MAX_OBSERVATION_LAG_US = 50_000


def observation_time(buffers: list[TimestampBuffer], tau: int, events_per_px: float) -> int:
    """The time (µs) whose scene the keypoints of the time surfaces at ``tau`` show.

    ``tau`` less the mean over the cameras of how far each buffer's N-th newest event lies behind
    it (N = ``events_per_px`` x the buffer's pixels), at most :data:`MAX_OBSERVATION_LAG_US`;
    ``tau`` itself when ``events_per_px`` is 0 or a camera holds no more than N events yet. See
    ``observation_lag_events_per_px`` in :class:`~aerovis_slam.slam.config.DetectorConfig`.
    """
    if events_per_px <= 0:
        return int(tau)
    lags = []
    for b in buffers:
        n = int(round(events_per_px * b.width * b.height))
        if b.count <= n:
            return int(tau)
        lags.append(max(0, int(tau) - b.timestamp_at_offset(n)))
    return int(tau) - min(int(round(float(np.mean(lags)))), MAX_OBSERVATION_LAG_US)


class EventFeeder:
    """Ingest events of both cameras up to a time; freeze buffers; compute the stereo MCTS.

    Args:
        reader: chunk source. cams: the camera models (pixel maps, sizes).
        mcts_kind, mcts_params: the detector's time surface (``ne``: events per pixel; ``dt``: ms).
        rate_cap_ev_s: per-camera event-rate cap (None: off).
        noise_filter_us: background-activity filter's window per camera (µs, sensor pixels; None: off),
            applied before the rate cap.

    Attributes:
        ingested_until: time (µs) up to which every event has been ingested (-inf before the first call).
        events_in: events read per camera; ``exhausted``: both streams ended.
        noise_filters: the per-camera filters (None when off); their ``removed`` counts what they dropped.
    """

    def __init__(self, reader: EventReader, cams: StereoCameras, *, mcts_kind: str, mcts_params,
                 rate_cap_ev_s: float | None = None, observation_lag_events_per_px: float = 0.0,
                 noise_filter_us: int | None = None):
        self.reader = reader
        self.cams = cams
        self.mcts_kind = mcts_kind
        self.mcts_params = tuple(float(p) for p in mcts_params)
        if mcts_kind not in ("ne", "dt"):
            raise ValueError(f"mcts_kind must be 'ne' or 'dt', got {mcts_kind!r}")
        ring_px = self.mcts_params if mcts_kind == "ne" else (1e-9,)
        self.observation_lag_events_per_px = float(observation_lag_events_per_px)
        if self.observation_lag_events_per_px > 0:  # the ring must reach back to the N-th newest event
            ring_px = tuple(ring_px) + (self.observation_lag_events_per_px,)
        self.buffers = [TimestampBuffer(c.buffer_width, c.buffer_height, pixel_map=c.pixel_map, events_per_px=ring_px,
                                        max_rate_ev_s=rate_cap_ev_s) for c in cams.cams]
        self.noise_filters = None if noise_filter_us is None else [
            BackgroundActivityFilter(c.pixel_map.sensor_width, c.pixel_map.sensor_height, dt_us=int(noise_filter_us))
            for c in cams.cams]
        self._pending: list[EventArray | None] = [None, None]
        self._ended = [False, False]
        self.ingested_until = -(2**62)
        self.events_in = [0, 0]
        self.lock = threading.Lock()
        C = 2 * len(self.mcts_params)
        self._out = [np.empty((C, c.buffer_height, c.buffer_width), np.float32) for c in cams.cams]

    @property
    def exhausted(self) -> bool:
        return all(self._ended) and all(p is None or len(p) == 0 for p in self._pending)

    def advance_to(self, t_us: int) -> int:
        """Ingest every event with ``t <= t_us`` of both cameras (blocking on the reader). Returns events ingested."""
        total = 0
        for i, cam in enumerate(self.cams.cams):
            while True:
                chunk = self._pending[i]
                if chunk is None or len(chunk) == 0:
                    if self._ended[i]:
                        break
                    chunk = self.reader.get(cam.name)
                    if chunk is None:
                        self._ended[i] = True
                        self._pending[i] = None
                        break
                    self.events_in[i] += len(chunk)
                k = int(np.searchsorted(chunk.t, t_us, side="right"))
                if k:
                    part = EventArray(chunk.t[:k], chunk.x[:k], chunk.y[:k], chunk.p[:k])
                    if self.noise_filters is not None:
                        part = self.noise_filters[i](part)
                    with self.lock:
                        self.buffers[i].ingest(part)
                    total += k
                if k < len(chunk):
                    self._pending[i] = EventArray(chunk.t[k:], chunk.x[k:], chunk.y[k:], chunk.p[k:])
                    break
                self._pending[i] = None
        self.ingested_until = max(self.ingested_until, int(t_us))
        return total

    def snapshot(self) -> tuple[list[TimestampBuffer], int]:
        """Frozen copies of both buffers and the time they are complete up to (µs)."""
        with self.lock:
            bufs = [b.copy() for b in self.buffers]
            # In live mode one camera's packet may already be in while the other's is being
            # ingested: the snapshot time must not precede either buffer's newest event.
            return bufs, max([self.ingested_until] + [b.last_t for b in bufs])

    def mcts_batch(self, buffers: list[TimestampBuffer], tau: int) -> np.ndarray:
        """The detector's input at ``tau``: float32 (2, C, H, W), each camera cropped top-left to its model size."""
        out = []
        for i, (b, cam) in enumerate(zip(buffers, self.cams.cams)):
            if self.mcts_kind == "ne":
                m = b.mcts_ne(tau, self.mcts_params, out=self._out[i])
            else:
                m = b.mcts_dt(tau, self.mcts_params, out=self._out[i])
            out.append(m[:, :cam.height, :cam.width])
        return np.stack(out)

    @property
    def dropped_rate_cap(self) -> int:
        return int(sum(b.dropped_rate_cap for b in self.buffers))

    @property
    def dropped_noise_filter(self) -> int:
        return 0 if self.noise_filters is None else int(sum(f.removed for f in self.noise_filters))


class LivePreprocessor:
    """Keeps an :class:`EventFeeder` current at wall-clock speed on its own thread (``live`` mode).

    The sequence clock runs at ``t_start_us + (wall - wall_start)``; every ``period_s`` (the sensor's
    packet rate) the thread ingests events up to the newest IMU-covered time not after it.

    Args:
        feeder: the buffers to keep current. coverage: callable ``now_us -> newest IMU-covered time``.
        t_start_us, t_end_us: replay span. stop_event: ends the thread when set.
    """

    def __init__(self, feeder: EventFeeder, coverage, t_start_us: int, t_end_us: int, *, period_s: float = 0.001,
                 stop_event: threading.Event | None = None):
        self.feeder = feeder
        self.coverage = coverage
        self.t_start_us, self.t_end_us = int(t_start_us), int(t_end_us)
        self.period_s = period_s
        self._stop = threading.Event()
        self._outer_stop = stop_event
        self.error: BaseException | None = None
        self.wall_start = time.perf_counter()
        self.busy_s = 0.0
        self.done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="aerovis-preprocess", daemon=True)
        self._thread.start()

    def now_us(self) -> int:
        """The replayed sensor clock."""
        return self.t_start_us + int((time.perf_counter() - self.wall_start) * 1e6)

    def _run(self) -> None:
        try:
            while not self._stop.is_set() and not (self._outer_stop is not None and self._outer_stop.is_set()):
                now = min(self.now_us(), self.t_end_us)
                target = self.coverage(now)
                if target > self.feeder.ingested_until:
                    t0 = time.perf_counter()
                    self.feeder.advance_to(target)
                    self.busy_s += time.perf_counter() - t0
                if now >= self.t_end_us:
                    break
                time.sleep(self.period_s)
        except BaseException as exc:
            self.error = exc
        finally:
            self.done.set()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
