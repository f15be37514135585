"""``aerovis-sim``: generate simulated event-camera sequences.

Usage::

    aerovis-sim PRESET OUT_DIR [--seed N] [--duration S] [--only NAME ...] [--textures IMG ...] [--workers N]
    aerovis-sim video OUT_DIR --images DIR [--fps F] [--threshold C] [--seed N] [--gt POSES.txt]

``PRESET`` is ``train``, ``bench`` or ``tiny`` (see :mod:`aerovis_slam.sim.presets`). One
canonical ``.h5`` per sequence lands in ``OUT_DIR`` (written as ``.partial`` and renamed when
complete), a summary line per sequence is printed, and ``OUT_DIR/summary.json`` lists them all.
``video`` turns a folder of images (sorted by name; timestamps from ``--fps`` or a
``timestamps.txt`` of seconds beside them) into events, written with the frames as
``OUT_DIR/<folder>.h5``. Errors print one line (no traceback) and exit with status 2.

``--workers N`` simulates N sequences at a time in separate processes (default: one per CPU core,
at most one per sequence). Every sequence draws only on its own seeds, so the files do not depend
on N or on the order in which the sequences finish.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from tqdm import tqdm

from ..errors import DataError
from ..fileio import atomic_write_json, prepare_out_dir


def default_workers(n_sequences: int) -> int:
    """One process per CPU core available to this process, at most one per sequence."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, n_sequences))


def _die_with_parent(parent_pid: int) -> None:
    """Worker-process initializer: end this worker when the process that started it ends.

    A parent stopped by SIGTERM or SIGKILL (a job scheduler, ``timeout``, an out-of-memory kill)
    cannot shut its pool down, and the workers would go on simulating the queued sequences into a
    folder nobody will use, at full CPU, for minutes (seen here). On Linux the kernel can send a
    signal to a process when its parent dies (``prctl(PR_SET_PDEATHSIG)``); the standard library
    has no call for it, so ctypes calls libc. Elsewhere this does nothing. A sequence in progress
    is left as its ``.partial`` file, never as a finished one.
    """
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    pr_set_pdeathsig = 1
    ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent_pid:  # the parent died before the request took effect
        os._exit(1)


def _write_one(spec, path: str) -> dict:
    """Worker-process entry point: simulate one sequence (a module-level function, so it pickles)."""
    from .simulator import write_sequence

    return write_sequence(spec, path, progress=False)


def run_preset(name: str, out_dir: str | os.PathLike, *, seed: int = 0, duration: float | None = None,
               only: list[str] | None = None, textures: list[str] | None = None, progress: bool = True,
               log=None, workers: int | None = None) -> dict:
    """Generate a preset into ``out_dir``; returns (and writes) the summary dict.

    ``textures`` (image files) replace the procedural poster textures of every scene;
    ``log`` (e.g. ``print``) receives one summary line per sequence; ``workers`` sequences are
    simulated at a time in separate processes (None: :func:`default_workers`). The summary lists the
    sequences in preset order whatever the order they finish in.

    Raises:
        DataError: unknown preset or sequence name, unwritable folder, bad rig or texture.
    """
    from .presets import preset_specs
    from .simulator import write_sequence

    specs = preset_specs(name, seed, duration)
    if only:
        unknown = sorted(set(only) - {s.name for s in specs})
        if unknown:
            raise DataError(None, f"--only: no sequence(s) {unknown} in preset {name!r}; it has {[s.name for s in specs]}")
        specs = [s for s in specs if s.name in only]
    if textures:
        from .scene import load_texture_image

        for tex in textures:  # fail before any output is written
            load_texture_image(tex)
        for s in specs:
            s.user_textures = [str(Path(t).resolve()) for t in textures]
    workers = default_workers(len(specs)) if workers is None else int(workers)
    if workers < 1:
        raise DataError(None, f"--workers must be at least 1, got {workers}")
    out = Path(out_dir)
    prepare_out_dir(out)
    t0 = time.perf_counter()
    rows: list[dict | None] = [None] * len(specs)

    def done(i: int, row: dict) -> None:
        row["path"] = f"{specs[i].name}.h5"
        rows[i] = row
        if log is not None:
            log(f"{specs[i].name}: {row['events']:,} events, {row['duration_s']:.1f} s, "
                f"{row['event_rate_mev_s']:.2f} Mev/s, wall {row['wall_s']:.1f} s")

    if workers == 1 or len(specs) == 1:
        bar = tqdm(specs, desc=f"aerovis-sim {name}", unit="seq", disable=not progress)
        for i, spec in enumerate(bar):
            bar.set_postfix_str(spec.name)
            done(i, write_sequence(spec, out / f"{spec.name}.h5", progress=progress))
    else:
        # Processes, not threads: rendering and event generation hold the GIL for most of their time.
        # "spawn" because the caller (a training job) may hold threads that a fork would copy mid-state.
        with ProcessPoolExecutor(max_workers=min(workers, len(specs)), mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_die_with_parent, initargs=(os.getpid(),)) as pool:
            futures = {pool.submit(_write_one, spec, str(out / f"{spec.name}.h5")): i for i, spec in enumerate(specs)}
            try:
                for fut in tqdm(as_completed(futures), total=len(futures), desc=f"aerovis-sim {name} ({workers} processes)",
                                unit="seq", disable=not progress):
                    done(futures[fut], fut.result())
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)  # finished sequences stay; none is half-written
                raise
    import cv2

    from ..environment import software_versions

    summary = {"preset": name, "seed": seed, "duration_override_s": duration, "sequences": rows,
               "total_events": sum(r["events"] for r in rows),
               "total_duration_s": sum(r["duration_s"] for r in rows),
               "wall_s": round(time.perf_counter() - t0, 2),
               # the scenes' text textures are drawn by cv2.putText, whose output changed in 5.1
               # (see aerovis_slam.sim.cache.ensure_preset, which compares it on every use)
               "opencv": cv2.__version__,
               "environment": software_versions()}
    atomic_write_json(out / "summary.json", summary)
    return summary


def run_video(images_dir: str | os.PathLike, out_dir: str | os.PathLike, *, fps: float | None = None,
              threshold: float = 0.2, seed: int = 0, gt: str | os.PathLike | None = None) -> dict:
    """Convert an image folder into events (``OUT_DIR/<folder>.h5``, camera ``cam0``).

    ``gt``: optional TUM-format poses (``t tx ty tz qx qy qz qw`` per line, ``t`` in seconds on
    the same clock as the frames) stored as ``/gt`` (``T_world_body``), relative to the first frame.
    """
    import cv2
    import numpy as np

    from ..io.sequence import SequenceWriter
    from .events import EventConfig, video_to_events

    src = Path(images_dir)
    if not src.is_dir():
        raise DataError(src, "--images must be a folder of image files")
    files = sorted(p for p in src.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"))
    if len(files) < 2:
        raise DataError(src, f"need at least 2 images (.png/.jpg/.bmp/.tif), found {len(files)}")
    stamps = src / "timestamps.txt"
    if fps:
        t_us = np.round(np.arange(len(files)) * 1e6 / fps).astype(np.int64)
    elif stamps.is_file():
        try:
            t_s = np.loadtxt(stamps, ndmin=1)
        except ValueError as exc:
            raise DataError(stamps, f"expected one timestamp in seconds per line ({exc})") from None
        if len(t_s) != len(files):
            raise DataError(stamps, f"{len(t_s)} timestamps for {len(files)} images")
        t_us = np.round((t_s - t_s[0]) * 1e6).astype(np.int64)
    else:
        raise DataError(src, "give --fps or put a timestamps.txt (seconds, one per image) in the folder")
    imgs = []
    for f in files:
        img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise DataError(f, "cannot read image")
        if imgs and img.shape != imgs[0].shape:
            raise DataError(f, f"image size {img.shape[::-1]} differs from the first image's {imgs[0].shape[::-1]}")
        imgs.append(img)
    frames = np.stack(imgs)
    poses = None
    if gt is not None:
        from ..measurements import PoseSamples

        try:
            g = np.loadtxt(gt, ndmin=2, comments="#")
        except (OSError, ValueError) as exc:
            raise DataError(gt, f"expected TUM poses 't tx ty tz qx qy qz qw' per line ({exc})") from None
        if g.shape[1] != 8:
            raise DataError(gt, f"expected 8 columns (t tx ty tz qx qy qz qw), found {g.shape[1]}")
        t0_s = float(np.loadtxt(stamps, ndmin=1)[0]) if (not fps and stamps.is_file()) else 0.0
        poses = PoseSamples(np.round((g[:, 0] - t0_s) * 1e6).astype(np.int64), g[:, 1:])
    events = video_to_events(frames, t_us, EventConfig(threshold=threshold), seed=seed)
    out = Path(out_dir)
    prepare_out_dir(out)
    h, w = frames.shape[1:]
    path = out / f"{src.name}.h5"
    with SequenceWriter(path, sensor_sizes={"cam0": (w, h)}, meta={"generator": "aerovis-sim video", "source": str(src),
                                                                    "threshold": threshold, "seed": seed}) as wr:
        wr.add_events("cam0", events)
        wr.add_frames("cam0", t_us, frames)
        if poses is not None:
            wr.set_gt(poses)
    return {"path": str(path), "events": len(events), "frames": len(files), "duration_s": float(t_us[-1] - t_us[0]) / 1e6}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="aerovis-sim", description="Simulate stereo event cameras, IMU, frames and depth in textured rooms.")
    parser.add_argument("preset", help="train | bench | tiny | video")
    parser.add_argument("out_dir", help="output folder (created if missing)")
    parser.add_argument("--seed", type=int, default=0, help="preset seed (default 0)")
    parser.add_argument("--duration", type=float, default=None, help="override each sequence's duration (s)")
    parser.add_argument("--only", nargs="+", default=None, help="generate only these sequence names")
    parser.add_argument("--textures", nargs="+", default=None, help="image files used as poster textures in every scene")
    parser.add_argument("--images", default=None, help="video mode: folder of frames")
    parser.add_argument("--fps", type=float, default=None, help="video mode: frame rate (else timestamps.txt)")
    parser.add_argument("--threshold", type=float, default=0.2, help="video mode: contrast threshold")
    parser.add_argument("--gt", default=None, help="video mode: TUM-format ground-truth poses (seconds)")
    parser.add_argument("--workers", type=int, default=None,
                        help="sequences simulated at a time, one process each (default: one per CPU core)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars (summary lines stay)")
    args = parser.parse_args(argv)
    try:
        if args.preset == "video":
            if not args.images:
                raise DataError(None, "video mode needs --images FOLDER")
            res = run_video(args.images, args.out_dir, fps=args.fps, threshold=args.threshold, seed=args.seed, gt=args.gt)
            print(f"{res['path']}: {res['events']:,} events from {res['frames']} frames over {res['duration_s']:.2f} s")
            return 0
        summary = run_preset(args.preset, args.out_dir, seed=args.seed, duration=args.duration, only=args.only,
                             textures=args.textures, progress=not args.quiet, log=tqdm.write, workers=args.workers)
    except DataError as exc:
        print(f"aerovis-sim: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("aerovis-sim: interrupted (no partial sequence left behind)", file=sys.stderr)
        return 130
    print(f"{len(summary['sequences'])} sequences, {summary['total_events']:,} events, "
          f"{summary['total_duration_s']:.1f} s simulated in {summary['wall_s']:.1f} s -> {Path(args.out_dir) / 'summary.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
