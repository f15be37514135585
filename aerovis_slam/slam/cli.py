"""``aerovis-slam``: run the SLAM runtime, evaluate trajectories, benchmark, build vocabularies.

    aerovis-slam run SEQ.h5 [--model BUNDLE | --detector orb|sift|gftt_brief]
                     [--config realtime|accurate|FILE] [--mode sync|async|live] [--no-loop]
                     [--frame-slots FRAMES.txt] --out DIR [--quiet]
    aerovis-slam eval GT EST.txt [--align se3|sim3|none] [--max-diff S] [--interpolate] [--rpe-delta S]
    aerovis-slam bench [--model BUNDLE] [--detector orb] [--sequences NAME|SEQ.h5 ...] [--preset-seed N]
                       [--modes sync async] [--config NAME|FILE] [--no-loop] [--resume] --out DIR
    aerovis-slam vocab (--model BUNDLE | --detector orb|sift|gftt_brief) [--data train|DIR|SEQ.h5 ...]
                       [--frames N] [--words K] [--out FILE]
    aerovis-slam compare BENCH_A BENCH_B [--mode sync|async] [--detector-a NAME] [--detector-b NAME]
                         [--labels A B] [--final] [--out FILE.md]

``run`` writes ``DIR/traj.txt`` (TUM, body frame; ``traj.partial.txt`` with a header flag when the run
stopped early, e.g. on Ctrl-C), ``DIR/metrics.json``, ``DIR/traj.png`` and ``DIR/frames.txt`` (each
output's frame slot, latency, processing time and backend iteration caps, which ``--frame-slots``
replays) and prints one JSON line;
a complete run also writes ``DIR/traj_final.txt``, the final trajectory (outputs moved with their
keyframes' last estimates and the last loop-closure pose graph; its accuracy is ``final`` in
``metrics.json``).
Without ``--model`` / ``--detector`` it uses the shipped default bundle (SuperLitE fp32).

``eval`` compares two TUM files (or a canonical ``.h5``'s ground truth as GT) with evo and prints
``{"ate_rmse_m", "pairs", "align", ...}``.

``bench`` runs every sequence of the simulator's ``bench`` preset (seed 0, or ``--preset-seed N``: other
rooms and paths of the same kinds; or ``--sequences``) in sync
(``accurate`` setting) and async (``realtime`` setting) mode with the learned detector and the
classical one on the same time surfaces, and writes ``DIR/table.md`` (paper Table I form),
``DIR/bench.json`` and each run's outputs under ``DIR/<sequence>/<detector>-<mode>/``.

``compare`` sets two ``bench --repeats N`` outputs side by side, per sequence: each side's runs, their
medians, B's median minus A's with a 95 % bootstrap interval, and the share of run pairs in which B is
lower; then the mean over sequences (a Markdown table, and one JSON line last).

``vocab`` learns the loop-closure vocabulary of a detector from the ``train`` preset and stores it
under the detector's name in the shipped ``aerovis_slam/slam/data/vocabulary.npz`` (or ``--out``).

Bad input prints one line naming the file and exits with status 2; a run whose pipeline reports a
failure exits with 1 (its outputs are still written); Ctrl-C stops ``run`` cleanly (exit 130).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
from pathlib import Path

from ..errors import DataError

PROG = "aerovis-slam"


def _parser() -> argparse.ArgumentParser:
    from .bench import CLASSICAL

    ap = argparse.ArgumentParser(prog=PROG, description="Stereo event-inertial SLAM: run, evaluate, benchmark.")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run SLAM on one sequence; write traj.txt, metrics.json, traj.png")
    p.add_argument("sequence", help="canonical sequence (.h5)")
    p.add_argument("--model", help="model bundle directory (default: the shipped SuperLitE fp32 bundle)")
    p.add_argument("--detector", choices=CLASSICAL, help="use a classical detector instead of a bundle")
    p.add_argument("--config", default=None, help="realtime | accurate | a YAML file (default: accurate for sync, realtime otherwise)")
    p.add_argument("--mode", choices=("sync", "async", "live"), default=None, help="processing mode (default: the config's)")
    p.add_argument("--no-loop", action="store_true", help="disable loop closure")
    p.add_argument("--frame-slots", metavar="FRAMES.txt", default=None,
                   help="async: process the frame slots (and backend iteration caps) of an earlier run, its "
                        "frames.txt, instead of those this machine's timing picks: that run reproduced")
    p.add_argument("--oracle-noise-px", type=float, default=None, metavar="PX",
                   help="diagnostic on aerovis-sim sequences: landmark observations replaced by true projections "
                        "+ Gaussian noise of PX px (perfect tracks; docs/slam.md)")
    p.add_argument("--keypoint-errors", action="store_true",
                   help="diagnostic on aerovis-sim sequences: measure each landmark observation's distance to the true "
                        "projection of its scene point, by track age (metrics.json pipeline_info.keypoint_errors)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    p = sub.add_parser("eval", help="ATE/RPE of an estimate against a ground truth (TUM files; evo)")
    p.add_argument("gt", help="ground truth: TUM file, or a canonical .h5 with /gt")
    p.add_argument("est", help="estimate: TUM file")
    p.add_argument("--align", choices=("se3", "sim3", "none"), default="se3", help="alignment (default se3)")
    p.add_argument("--max-diff", type=float, default=0.02, help="association tolerance in seconds (default 0.02)")
    p.add_argument("--interpolate", action="store_true", help="interpolate the ground truth at the estimate times instead")
    p.add_argument("--rpe-delta", type=float, default=1.0, help="RPE interval in seconds (default 1)")

    p = sub.add_parser("bench", help="benchmark over the bench preset: Table I (ATE per sequence and mode)")
    p.add_argument("--model", help="learned model bundle (default: the shipped SuperLitE fp32 bundle)")
    p.add_argument("--detector", nargs="*", default=["orb"], choices=CLASSICAL,
                   help="classical detector(s) on the same time surfaces (default orb; none: learned only)")
    p.add_argument("--no-learned", action="store_true", help="benchmark only the classical detector(s)")
    p.add_argument("--sequences", nargs="+", default=None,
                   help="sequence names of the bench preset or .h5 files (default: all of the bench preset)")
    p.add_argument("--preset-seed", type=int, default=0,
                   help="the bench preset generated with this seed (other rooms and paths, cached on first use): "
                        "the settings were tuned on seed 0, so other seeds are held-out data (default 0)")
    p.add_argument("--modes", nargs="+", choices=("sync", "async", "live"), default=["sync", "async"])
    p.add_argument("--config", default=None, help="one setting for all modes (default: accurate for sync, realtime for async)")
    p.add_argument("--no-loop", action="store_true", help="disable loop closure")
    p.add_argument("--resume", action="store_true", help="reuse runs that already have a metrics.json")
    p.add_argument("--repeats", type=int, default=1,
                   help="runs per cell: the first as configured, the others with seeded keypoint noise; the table adds "
                        "mean (min-max) (default 1)")
    p.add_argument("--keypoint-noise-px", type=float, default=0.2,
                   help="uniform keypoint noise of the repeats, +- this many px (default 0.2)")
    p.add_argument("--oracle-noise-px", type=float, nargs="+", default=None, metavar="PX",
                   help="perfect tracks + Gaussian noise of PX px (aerovis-sim sequences; see run); several values "
                        "run each detector at each, side by side in one table")
    p.add_argument("--keypoint-errors", action="store_true",
                   help="aerovis-sim sequences: each run measures its keypoints' distance to their scene points "
                        "(see run); the table adds the medians")
    p.add_argument("--diverge-pct", type=float, default=25.0, help="diverged: ATE above this %% of the path length ...")
    p.add_argument("--diverge-min-m", type=float, default=0.10, help="... and above this many metres")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar or per-run lines")

    p = sub.add_parser("compare", help="two bench outputs side by side: per-sequence medians over runs, differences with intervals")
    p.add_argument("bench_a", help="bench folder (or its bench.json): the reference")
    p.add_argument("bench_b", help="bench folder (or its bench.json): the one compared with it")
    p.add_argument("--mode", choices=("sync", "async"), default="sync")
    p.add_argument("--detector-a", help="detector of bench A (default: its only one in that mode)")
    p.add_argument("--detector-b", help="detector of bench B (default: its only one in that mode)")
    p.add_argument("--labels", nargs=2, metavar=("A", "B"), help="names in the table (default: the folder names)")
    p.add_argument("--final", action="store_true", help="the final trajectories' ATE instead of the live outputs'")
    p.add_argument("--out", help="also write the table to this Markdown file")

    p = sub.add_parser("vocab", help="learn a loop-closure vocabulary for a detector from training sequences")
    p.add_argument("--model", help="model bundle directory (its name keys the vocabulary)")
    p.add_argument("--detector", choices=CLASSICAL, help="classical detector (MCTS_Ne surfaces, as in the runtime)")
    p.add_argument("--data", nargs="+", default=["train"], help="preset name (default train), folders or .h5 files")
    p.add_argument("--frames", type=int, default=8, help="MCTS frames per sequence and camera (default 8)")
    p.add_argument("--words", type=int, default=64, help="vocabulary size (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=None, help="vocabulary file (default: the shipped aerovis_slam/slam/data/vocabulary.npz)")
    p.add_argument("--quiet", action="store_true")
    return ap


def _sequences(items: list[str], preset_default: str, seed: int = 0) -> list[Path]:
    """Files, folders of ``*.h5``, preset names, or sequence names of ``preset_default``; presets
    (and the sequence names of ``preset_default``) generated with ``seed``, cached on first use."""
    from ..sim.cache import ensure_preset
    from ..sim.presets import PRESETS

    out: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_file():
            out.append(p)
        elif p.is_dir():
            found = sorted(p.glob("*.h5"))
            if not found:
                raise DataError(p, "folder holds no .h5 sequences")
            out += found
        elif item in PRESETS:
            out += sorted(ensure_preset(item, seed=seed).glob("*.h5"))
        else:
            folder = ensure_preset(preset_default, seed=seed)
            cand = folder / f"{item}.h5"
            if not cand.is_file():
                names = sorted(q.stem for q in folder.glob("*.h5"))
                raise DataError(p, f"no such file, folder or sequence of preset {preset_default!r} seed {seed} (it has {names})")
            out.append(cand)
    return out


def _config(name: str | None, mode: str | None):
    from .bench import MODE_CONFIG
    from .config import load_config

    return load_config(name or MODE_CONFIG[mode or "sync"])


@contextlib.contextmanager
def _stop_on_sigint(what: str):
    """Within: the first Ctrl-C sets the yielded event (the run ends cleanly, its outputs marked
    partial), a second one raises KeyboardInterrupt. Outside the main thread: no handler."""
    stop = threading.Event()

    def on_sigint(signum, frame):
        if stop.is_set():
            raise KeyboardInterrupt
        stop.set()
        print(f"{PROG}: stopping (Ctrl-C again to abort); {what}", file=sys.stderr)

    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


def cmd_run(args) -> int:
    from .bench import make_detector, read_frames, run_sequence

    seq = Path(args.sequence)
    if not seq.is_file():
        raise DataError(seq, "no such file (expected a canonical sequence .h5)")
    slots = caps = None
    if args.frame_slots is not None:
        if args.mode not in (None, "async"):
            raise DataError(Path(args.frame_slots), f"--frame-slots replays an async run's frames; --mode is {args.mode!r}")
        slots, caps = read_frames(args.frame_slots)
        args.mode = "async"
    config = _config(args.config, args.mode)
    if args.oracle_noise_px is not None:
        config.detector.oracle_noise_px = float(args.oracle_noise_px)
    config.detector.measure_keypoint_errors = bool(args.keypoint_errors)  # with the oracle: refused by run_sequence
    mode = args.mode or config.mode
    detector = make_detector(args.model, args.detector, top_k=getattr(getattr(config, "detector", None), "top_k", None))
    with _stop_on_sigint("the trajectory will be written as partial") as stop:
        metrics = run_sequence(seq, detector, config, args.out, mode=mode, loop=not args.no_loop, progress=not args.quiet,
                               stop_event=stop, frame_slots=slots, frame_caps=caps)
    summary = {k: metrics.get(k) for k in ("sequence", "detector", "mode", "config", "status", "complete", "poses", "ate_rmse_m",
                                           "ate_pct", "path_length_m", "rpe_trans_rmse_m", "rate_hz", "real_time_factor",
                                           "latency_ms_p50", "latency_ms_p90", "loop_closures", "tracking_losses")}
    summary["warnings"] = len(metrics.get("warnings", []))
    summary["out"] = metrics.get("out_dir")
    summary["trajectory_file"] = metrics.get("trajectory_file")
    summary["ate_pct_final"] = (metrics.get("final") or {}).get("ate_pct")
    summary["final_trajectory_file"] = metrics.get("final_trajectory_file")
    # input.warm_up: the outputs start at the first frame with complete time surfaces
    summary["t_first_frame_us"] = (metrics.get("pipeline_info") or {}).get("t_first_frame_us")
    for key in ("oracle", "keypoint_errors"):
        if (metrics.get("pipeline_info") or {}).get(key):
            summary[key] = metrics["pipeline_info"][key]
    print(json.dumps(summary))
    if stop.is_set():
        return 130
    return 0 if str(metrics.get("status", "")).startswith("ok") else 1


def cmd_eval(args) -> int:
    from .trajectory import ate, is_partial, json_ready, read_tum, rpe

    gt_path = Path(args.gt)
    if gt_path.suffix in (".h5", ".hdf5"):
        from ..io.sequence import Sequence

        with Sequence(gt_path) as seq:
            gt = seq.gt
        if gt is None or len(gt) == 0:
            raise DataError(gt_path, "no /gt poses in this sequence")
    else:
        gt = read_tum(gt_path)
    est = read_tum(args.est)
    try:
        r = json_ready(ate(gt, est, align=args.align, max_diff_s=args.max_diff, interpolate=args.interpolate))
    except DataError as exc:
        raise DataError(args.est, f"against {args.gt}: {exc.problem}") from None
    r.update(rpe(gt, est, delta_s=args.rpe_delta))
    r["gt"], r["est"] = str(args.gt), str(args.est)
    r["est_poses"] = len(est)
    r["partial"] = is_partial(args.est)
    print(json.dumps(r))
    return 0


def cmd_bench(args) -> int:
    from tqdm import tqdm

    from .bench import make_detector, run_bench, summarize

    if args.preset_seed < 0:
        raise DataError(None, f"--preset-seed {args.preset_seed}: a preset seed is >= 0")
    seqs = _sequences(args.sequences or ["bench"], "bench", seed=args.preset_seed)
    dets = []
    learned = None
    if not args.no_learned:
        learned = make_detector(args.model, None)
        dets.append(learned)
    for kind in args.detector or []:
        # the classical detectors see the same time surfaces as the learned one
        dets.append(make_detector(None, kind, like=learned))
    if not dets:
        raise DataError(None, "nothing to benchmark: --no-learned with no --detector")
    if args.repeats < 1 or (args.repeats > 1 and not args.keypoint_noise_px > 0):
        raise DataError(None, f"--repeats {args.repeats} --keypoint-noise-px {args.keypoint_noise_px}: repeats must be >= 1, "
                              "and more than one run needs noise > 0 (sync runs would repeat exactly)")
    with _stop_on_sigint("the current run ends as partial, bench.json keeps what was measured") as stop:
        rows = run_bench(seqs, dets, args.out, modes=tuple(args.modes), config=args.config, loop=not args.no_loop,
                         resume=args.resume, progress=not args.quiet, diverge_pct=args.diverge_pct,
                         diverge_min_m=args.diverge_min_m, log=None if args.quiet else tqdm.write, stop_event=stop,
                         repeats=args.repeats, keypoint_noise_px=args.keypoint_noise_px, oracle_noise_px=args.oracle_noise_px,
                         keypoint_errors=args.keypoint_errors)
    summary = {"out": str(Path(args.out)), "runs": len(rows), "ok": sum(r["status"] == "ok" for r in rows),
               "preset_seed": args.preset_seed, "by_detector_mode": summarize(rows)}
    if not args.quiet:
        print((Path(args.out) / "table.md").read_text(), file=sys.stderr)
    summary["stopped"] = stop.is_set()
    print(json.dumps(summary))
    return 130 if stop.is_set() else 0


def cmd_vocab(args) -> int:
    from .bench import make_detector
    from .loop import VOCABULARY_PATH, build_vocabulary, save_vocabulary

    if args.model is None and args.detector is None:
        raise DataError(None, "give --model BUNDLE or --detector KIND: the vocabulary is per descriptor type")
    det = make_detector(args.model, args.detector)
    seqs = _sequences(args.data, "train")
    vocab, meta = build_vocabulary(seqs, det, frames_per_sequence=args.frames, words=args.words, seed=args.seed,
                                   progress=not args.quiet)
    # a bundle's model name keys it ("superlite" serves superlite-fp32 and superlite-int8-cpu alike)
    key = det.bundle.name if hasattr(det, "bundle") else det.name
    out = save_vocabulary(args.out or VOCABULARY_PATH, key, vocab, meta)
    print(json.dumps({"vocabulary": key, "file": str(out), "words": int(vocab.shape[0]), "dim": int(vocab.shape[1]),
                      "descriptors": meta["descriptors"], "sequences": meta["sequences"], "bytes": out.stat().st_size}))
    return 0


def cmd_compare(args) -> int:
    from .compare import compare_benches, format_comparison, load_bench

    res = compare_benches(load_bench(args.bench_a), load_bench(args.bench_b), mode=args.mode, detector_a=args.detector_a,
                          detector_b=args.detector_b, key="ate_pct_final" if args.final else "ate_pct",
                          where_a=args.bench_a, where_b=args.bench_b)
    labels = args.labels or [Path(args.bench_a).name or "A", Path(args.bench_b).name or "B"]
    table = format_comparison(res, *labels)
    if args.out:
        from ..fileio import atomic_write_text

        atomic_write_text(args.out, table)
    print(table)
    print(json.dumps({"a": args.bench_a, "b": args.bench_b, **res}))
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return {"run": cmd_run, "eval": cmd_eval, "bench": cmd_bench, "vocab": cmd_vocab,
                "compare": cmd_compare}[args.command](args)
    except DataError as exc:
        print(f"{PROG} {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG} {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
