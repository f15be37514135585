"""Benchmarks of the runtime's pieces (run through ``aerovis-bench``; never timed tests).

Each returns a JSON-ready dict measured in one run, so ratios compare like with like.
"""

from __future__ import annotations

import os
import time

import numpy as np

from .events import EventArray
from .mcts import MCTS_NE_EVENTS_PER_PX, TimestampBuffer, _memory_floor_kernel


def pin_to_one_core() -> int | None:
    """Restrict this process to one CPU (the benchmarks' "one core"). Returns the core or None."""
    if hasattr(os, "sched_setaffinity"):
        core = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {core})
        return core
    return None


def synthetic_edge_stream(width: int, height: int, n_events: int, *, duration_us: int = 1_000_000, seed: int = 0) -> EventArray:
    """A stream with the structure of real event data: moving edges, not uniform noise.

    A few hundred straight edge segments (10-80 px) translate and rotate slowly across the sensor;
    each time step emits events on the pixels the edges cover, ON on one side and OFF on the other,
    so events are spatially clustered and temporally coherent (what makes buffer writes cache-friendly
    or not, as on a real sensor). Timestamps are sorted µs.
    """
    rng = np.random.default_rng(seed)
    n_edges = 300
    length = rng.uniform(10, 80, n_edges)
    cx, cy = rng.uniform(0, width, n_edges), rng.uniform(0, height, n_edges)
    angle = rng.uniform(0, np.pi, n_edges)
    vx, vy = rng.normal(0, width / 2, n_edges), rng.normal(0, height / 2, n_edges)  # px/s
    omega = rng.normal(0, 1.0, n_edges)  # rad/s
    polarity = rng.integers(0, 2, n_edges)
    t = np.sort(rng.integers(0, duration_us, n_events)).astype(np.int64)
    edge = rng.integers(0, n_edges, n_events)
    s = (rng.random(n_events) - 0.5) * length[edge]
    ts = t * 1e-6
    a = angle[edge] + omega[edge] * ts
    x = (cx[edge] + vx[edge] * ts + s * np.cos(a)) % width
    y = (cy[edge] + vy[edge] * ts + s * np.sin(a)) % height
    return EventArray(t, x.astype(np.uint16), y.astype(np.uint16), polarity[edge].astype(np.int8))


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def bench_mcts(n_events: int = 10_000_000, packet_events: int = 8192, repeats: int = 50) -> dict:
    """Ingest rate into the timestamp buffer and MCTS_Ne time against a memory-traffic floor.

    * ``ingest_mev_s``: million events per second into a 480x640 buffer (sensor packets of
      ``packet_events``; pixel indices, order and bounds checks, buffer and ring writes included).
    * ``mcts_ne_ms``: one 8-channel MCTS_Ne into a preallocated output, per resolution.
    * ``floor_ms``: the same reads of the buffer and writes of the output with no arithmetic.
    """
    core = pin_to_one_core()
    res = {"480x640": (640, 480), "240x424": (424, 240)}
    w, h = res["480x640"]
    stream = synthetic_edge_stream(w, h, n_events)
    packets = [stream[i : i + packet_events] for i in range(0, n_events, packet_events)]
    buf = TimestampBuffer(w, h)
    buf.ingest(packets[0])  # compile / load the kernel before timing
    rates = []
    for _ in range(3):
        buf.reset()
        t0 = time.perf_counter()
        for pk in packets:
            buf.ingest(pk)
        rates.append(n_events / (time.perf_counter() - t0) / 1e6)
    result: dict = {"ingest_mev_s": round(max(rates), 1), "mcts_ne_ms": {}, "floor_ms": {}, "mcts_over_floor": {}}
    for name, (w, h) in res.items():
        b = TimestampBuffer(w, h)
        b.ingest(synthetic_edge_stream(w, h, 2_000_000, seed=1))
        out = np.empty((2 * len(MCTS_NE_EVENTS_PER_PX), h, w), np.float32)
        b.mcts_ne(out=out)
        flat_ts, flat_out = b.ts.reshape(-1), out.reshape(out.shape[0], -1)
        _memory_floor_kernel(flat_ts, b.plane, len(MCTS_NE_EVENTS_PER_PX), flat_out)
        mcts_ms = _median_ms(lambda: b.mcts_ne(out=out), repeats)
        floor_ms = _median_ms(lambda: _memory_floor_kernel(flat_ts, b.plane, len(MCTS_NE_EVENTS_PER_PX), flat_out), repeats)
        result["mcts_ne_ms"][name] = round(mcts_ms, 3)
        result["floor_ms"][name] = round(floor_ms, 3)
        result["mcts_over_floor"][name] = round(mcts_ms / floor_ms, 2)
    result.update({"events": n_events, "packet_events": packet_events, "core": core})
    return result
