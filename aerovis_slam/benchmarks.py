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


def bench_read(n_events: int = 6_000_000, width: int = 424, height: int = 240, repeats: int = 3) -> dict:
    """How fast a replay can read a canonical sequence's events, per event compression, in one run.

    The same two cameras' streams (``n_events`` each, :func:`synthetic_edge_stream`, 10 Mev/s per
    camera) are written once per :data:`~aerovis_slam.io.sequence.EVENT_COMPRESSION` choice and read
    back by the runtime's :class:`~aerovis_slam.slam.preprocessing.EventReader` (one thread per
    camera, its 200k-event chunks), ``repeats`` times, alternating the files. The files are in the
    page cache, so this measures decoding, not the disk.

    * ``read_mev_s``: both cameras' events per second of wall time (best of ``repeats``): the
      stereo event rate a replay from such a file can keep up with. ``target_mev_s`` is the paper's
      rate cap of 35 Mev/s per camera, for two cameras.
    * ``write_mev_s``, ``bytes_per_event``: what the choice costs when a file is written.
    """
    import tempfile
    from pathlib import Path

    from .io.sequence import EVENT_COMPRESSION, SequenceWriter
    from .slam.preprocessing import EventReader

    streams = {cam: synthetic_edge_stream(width, height, n_events, seed=seed) for cam, seed in (("cam0", 0), ("cam1", 1))}
    result: dict = {"benchmark": "read", "events_per_camera": n_events, "resolution": [width, height]}
    with tempfile.TemporaryDirectory(prefix="aerovis-bench-read-") as tmp:
        paths = {}
        for codec in EVENT_COMPRESSION:
            paths[codec] = Path(tmp) / f"{codec}.h5"
            t0 = time.perf_counter()
            with SequenceWriter(paths[codec], sensor_sizes={c: (width, height) for c in streams}, event_compression=codec) as w:
                for cam, ev in streams.items():
                    for i in range(0, n_events, 1 << 20):
                        w.add_events(cam, ev[i : i + (1 << 20)])
            result[codec] = {"write_mev_s": round(2 * n_events / (time.perf_counter() - t0) / 1e6, 1),
                             "bytes_per_event": round(paths[codec].stat().st_size / (2 * n_events), 2), "read_mev_s": 0.0}
        for _ in range(repeats):
            for codec, path in paths.items():
                t0 = time.perf_counter()
                reader = EventReader(path)
                try:
                    n, open_cams = 0, list(streams)
                    while open_cams:  # both cameras in turn, as the feeder takes them
                        for cam in list(open_cams):
                            chunk = reader.get(cam)
                            if chunk is None:
                                open_cams.remove(cam)
                            else:
                                n += len(chunk)
                finally:
                    reader.close()
                if n != 2 * n_events:
                    raise RuntimeError(f"{path.name}: read {n} events, wrote {2 * n_events}")
                rate = n / (time.perf_counter() - t0) / 1e6
                result[codec]["read_mev_s"] = round(max(result[codec]["read_mev_s"], rate), 1)
    result["read_speedup"] = round(result["blosc-lz4"]["read_mev_s"] / result["gzip"]["read_mev_s"], 2)
    result["target_mev_s"] = 70.0
    result["meets_target"] = bool(result["blosc-lz4"]["read_mev_s"] >= result["target_mev_s"])
    return result


def bench_blas(bundle=None, *, height: int = 240, width: int = 424, products_ms: float = 30.0, repeats: int = 30,
               warmup: int = 3) -> dict:
    """What numpy's BLAS threads cost the detector between frames (``SlamConfig.blas_threads``), in one run.

    Each repeat runs the runtime's descriptor products (:func:`~aerovis_slam.keypoints.cosine_similarity`
    of 400 map and 250 frame int8 descriptors, as the frontend's matching does; as many as take about
    ``products_ms`` with the BLAS's own threads), then one stereo inference of the bundle (default:
    the shipped SuperLitE) at ``height`` x ``width``, timed. The BLAS's own threads, one thread, and
    inference alone (no products: the floor) take turns within each repeat, so load from elsewhere
    hits all three alike.

    * ``infer_ms_p50``: per setting, the inference's median.
    * ``products_ms_p50``: per setting, what the products themselves took.
    * ``slowdown``: ``infer_ms_p50`` over the floor's. ``target_slowdown`` 1.1: with one BLAS thread
      the detector should run as fast between frames as alone.
    """
    from .bundle import BundleDetector, default_bundle_path, synthetic_mcts
    from .environment import blas_libraries, blas_thread_limit
    from .keypoints import cosine_similarity

    det = BundleDetector(bundle or default_bundle_path())
    det.bundle.check_size(height, width)
    x = synthetic_mcts(det.bundle, 2, height=height, width=width)
    rng = np.random.default_rng(0)
    dim = det.bundle.descriptor_dim
    map_desc = rng.integers(-127, 128, (400, dim), dtype=np.int8)
    frame_desc = rng.integers(-127, 128, (250, dim), dtype=np.int8)
    own_threads = max((b["num_threads"] or 1 for b in blas_libraries()), default=None)

    def products(n: int) -> float:
        t0 = time.perf_counter()
        for _ in range(n):
            cosine_similarity(frame_desc, map_desc)
        return (time.perf_counter() - t0) * 1e3

    per_ms = max(products(50) / 50, 1e-3)
    n_products = max(1, int(round(products_ms / per_ms)))
    limits = {"blas_own_threads": None, "blas_1_thread": 1}
    infer: dict[str, list[float]] = {k: [] for k in (*limits, "alone")}
    prod: dict[str, list[float]] = {k: [] for k in limits}
    for r in range(warmup + repeats):
        for key, threads in limits.items():
            with blas_thread_limit(threads):
                ms = products(n_products)
                det.dense(x)
            if r >= warmup:
                prod[key].append(ms)
                infer[key].append(det.last_latency_ms)
        det.dense(x)  # alone: the floor
        if r >= warmup:
            infer["alone"].append(det.last_latency_ms)
    p50 = {k: round(float(np.median(v)), 2) for k, v in infer.items()}
    result = {"benchmark": "blas", "bundle": str(det.bundle.path), "resolution": [width, height], "batch": 2,
              "products_per_frame": n_products, "blas_own_threads": own_threads,
              "infer_ms_p50": p50, "products_ms_p50": {k: round(float(np.median(v)), 2) for k, v in prod.items()},
              "slowdown": {k: round(p50[k] / p50["alone"], 2) for k in prod}, "target_slowdown": 1.1,
              "blas": blas_libraries()}
    result["meets_target"] = bool(result["slowdown"]["blas_1_thread"] <= result["target_slowdown"])
    return result
