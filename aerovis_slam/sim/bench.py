"""Simulator speed benchmark: a 10 s, 320x240 stereo handheld sequence written to disk.

``ratio_to_realtime`` = wall time / simulated time (target <= 10 on a 2-core CPU box). The
wall time includes scene and trajectory generation, rendering, event generation, IMU and the
compressed HDF5 write; ``render_s`` and ``events_s`` split the loop.

Example (slow, so not a doctest)::

    from aerovis_slam.sim.bench import run_sim_benchmark
    print(run_sim_benchmark())
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path


def run_sim_benchmark(duration_s: float = 10.0, seed: int = 0, progress: bool = False) -> dict:
    """Generate the benchmark sequence into a temporary folder and time it.

    Returns:
        ``{"duration_s", "wall_s", "ratio_to_realtime", "render_s", "events_s", "events",
        "steps", "resolution"}``.
    """
    from .simulator import SequenceSpec, write_sequence

    spec = SequenceSpec("bench_handheld", rig="prophesee640_stereo", rig_scale=0.5, scene_seed=1000 + seed,
                        trajectory="handheld", trajectory_seed=1000 + seed, duration_s=duration_s, noise_seed=seed)
    with tempfile.TemporaryDirectory(prefix="aerovis-sim-bench-") as tmp:
        _warm_up()
        t0 = time.perf_counter()
        row = write_sequence(spec, Path(tmp) / "bench.h5", progress=progress)
        wall = time.perf_counter() - t0
    return {"duration_s": duration_s, "wall_s": round(wall, 2), "ratio_to_realtime": round(wall / duration_s, 2),
            "render_s": row["render_s"], "events_s": row["events_s"], "events": row["events"],
            "steps": row["steps"], "resolution": row["resolution"]}


def _warm_up() -> None:
    """Compile (or load from cache) the numba kernels outside the timed region."""
    from .simulator import SequenceSpec, simulate

    simulate(SequenceSpec("warmup", rig="tiny_stereo", duration_s=0.01, frame_rate_hz=0))


if __name__ == "__main__":
    import json

    print(json.dumps(run_sim_benchmark(progress=True)))
