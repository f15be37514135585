"""``aerovis-eval``: evaluation of keypoint detectors on canonical sequences.

    aerovis-eval pose --data SEQ.h5|DIR (--detector orb|sift|gftt_brief | --model NAME_OR_PATH)
                      [--cam cam0] [--mcts ne|dt] [--rate-hz 20] [--max-pairs N] [--top-k N]
                      [--ransac-px PX] [--estimator ransac] [--max-dt-s 2] [--max-angle-deg 45]
                      [--oracle-noise-px PX ...] [--out FILE.json] [--quiet]

    aerovis-eval compare --data DIR|PRESET [--models ...] [--detectors ...] [--onnx-latency] [--out DIR]

    aerovis-eval lag --data SEQ.h5|DIR|PRESET [--model ...] [--detector ...] [--out DIR]

    aerovis-eval pairs --data DIR [--model ...] [--detector ...] [--top-k N] [--out FILE.json]

``pose`` runs the SuperEvent relative-pose protocol (:mod:`aerovis_train.eval.pose`). With a
folder, every ``*.h5`` in it (not recursive) is evaluated and the pairs of all sequences are
pooled into one AUC, as the published numbers pool a dataset's sequences. It prints ONE JSON
line on stdout (AUC in percent), a short human summary and tqdm progress on stderr; ``--out``
writes the same summary plus per-sequence results and per-pair errors.

``--oracle-noise-px`` scores every pair a second time with perfect matches of the method's own
keypoints (each first-frame keypoint's scene point, by the simulator's depth, and its exact
projection in the second frame, plus noise): the AUC the protocol allows for those keypoints, with
all of them in view matched and with as many as the method's RANSAC inliers. Its ``oracle`` rows
go into the JSON line (:func:`~aerovis_train.eval.pose.oracle_pair_errors`).

``compare`` (:mod:`aerovis_train.eval.compare`) evaluates the shipped models and the classical
baselines in one run on the same pairs: one table, one JSON line per method.

``pairs`` (:mod:`aerovis_train.eval.pairs`) scores methods on real time-surface pairs whose
pseudo ground truth comes from intensity frames (correct matches and precision by epipolar distance).

``lag`` (:mod:`aerovis_train.eval.lag`) measures how far behind its time stamp a detector's
keypoints show the scene, on data with intensity frames and depth (the simulator's).

Bad input (missing file, no GT or calibration, no pair) prints one message naming the file and
exits with status 2. Only ``--model`` imports the learned-model loader (torch / onnxruntime).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from aerovis_slam.errors import DataError

from aerovis_slam.classical import DETECTORS
from .pose import ESTIMATORS, summarize

PROG = "aerovis-eval"


class UsageError(Exception):
    """A problem with the command line or the environment (message printed, exit status 2)."""


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description="Evaluate event keypoint detectors; each command prints one JSON line.")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pose", help="relative-pose AUC (SuperEvent protocol) on one sequence or a folder of sequences")
    p.add_argument("--data", required=True, help="canonical sequence (.h5) or a folder of them (pooled)")
    p.add_argument("--detector", nargs="+", default=[], choices=sorted(DETECTORS),
                   help="classical baseline(s) on the same time surfaces")
    p.add_argument("--model", nargs="+", default=[],
                   help="learned model(s): shipped name (superlite, superevent_plus, superevent), model.pt, train.py .ckpt or a bundle directory (aerovis-export)")
    p.add_argument("--cam", default="cam0", help="camera (default cam0)")
    p.add_argument("--mcts", choices=("ne", "dt"), default=None,
                   help="time surface: MCTS_Ne or MCTS_dt (default: the model's own, ne for classical detectors)")
    p.add_argument("--rate-hz", type=float, default=20.0, help="frames per second along the GT (0: at every GT timestamp)")
    p.add_argument("--max-pairs", type=int, default=None, help="evaluate only the first N pairs of each sequence")
    p.add_argument("--top-k", type=int, default=None, help="keypoints per frame (default max(H, W) // 2)")
    p.add_argument("--ransac-px", type=float, default=None, help="RANSAC threshold in px (default 1 up to 346 px wide, else 3)")
    p.add_argument("--estimator", choices=sorted(ESTIMATORS), default="ransac",
                   help="essential-matrix estimator (default ransac, the protocol's; usac_accurate refines)")
    p.add_argument("--max-dt-s", type=float, default=2.0, help="pair window in seconds (protocol: 2)")
    p.add_argument("--max-angle-deg", type=float, default=45.0, help="largest rotation threshold in degrees (protocol: 45)")
    p.add_argument("--oracle-noise-px", type=float, nargs="+", default=[], metavar="PX",
                   help="also score every pair with perfect matches of the method's keypoints plus this much noise "
                        "(px per axis; several values allowed): the protocol's ceiling for those keypoints. "
                        "Simulated sequences only (their scene is rendered for the true depth)")
    p.add_argument("--out", help="write summary, per-sequence and per-pair results to this JSON file")
    p.add_argument("--quiet", action="store_true", help="no progress bar or human summary")
    from .compare import add_parser as add_compare
    from .lag import add_parser as add_lag
    from .pairs import add_parser as add_pairs

    add_compare(sub)
    add_lag(sub)
    add_pairs(sub)
    return ap


def _sequences(data: str) -> list[Path]:
    """A sequence, a folder of sequences, or a simulator preset name (generated on first use)."""
    from aerovis_slam.sim.presets import PRESETS

    path = Path(data)
    if not path.exists() and data in PRESETS:
        from aerovis_slam.sim.cache import ensure_preset

        path = ensure_preset(data)
    if path.is_dir():
        seqs = sorted(p for p in path.glob("*.h5") if p.is_file())
        if not seqs:
            raise DataError(path, "folder holds no .h5 sequences")
        return seqs
    if not path.exists():
        raise DataError(path, "no such file or folder")
    return [path]


def load_model_arg(name_or_path: str):
    """A ``--model`` argument (shipped name, checkpoint or bundle folder) as a detector; a model that
    cannot be loaded is a :class:`UsageError` naming the argument."""
    from .learned import load_detector

    try:
        return load_detector(name_or_path)
    except DataError:
        raise
    except (OSError, ValueError, KeyError, RuntimeError) as exc:
        raise UsageError(f"--model {name_or_path}: could not load the model ({type(exc).__name__}: {exc})") from None


def _pose(args) -> list[dict]:
    """Every method of the command line on the same sequences and pairs: one summary each."""
    if not args.detector and not args.model:
        raise UsageError("give at least one --model or --detector")
    seqs = _sequences(args.data)
    methods = [(m, load_model_arg(m)) for m in args.model] + [(d, d) for d in args.detector]
    summaries, outputs = [], []
    for label, detector in methods:
        summary, results = _pose_one(args, seqs, label, detector)
        summaries.append(summary)
        outputs.append({"summary": summary, "sequences": results})
    if args.out:
        Path(args.out).write_text(json.dumps({"config": vars(args), "methods": outputs}, indent=1))
    return summaries


def _pose_one(args, seqs: list[Path], label: str, detector) -> tuple[dict, list[dict]]:
    from .pose import evaluate_sequence
    common = dict(cam=args.cam, mcts_kind=args.mcts, rate_hz=None if args.rate_hz == 0 else args.rate_hz,
                  ransac_px=args.ransac_px, top_k=args.top_k, max_pairs=args.max_pairs, max_dt_s=args.max_dt_s,
                  max_angle_deg=args.max_angle_deg, estimator=args.estimator, progress=not args.quiet,
                  oracle_noise_px=args.oracle_noise_px)
    own_kind = getattr(detector, "mcts_kind", None)
    if args.mcts and own_kind and args.mcts != own_kind:
        if args.detector:  # a comparison: --mcts sets the classical detectors' surface, models keep their own
            common = {**common, "mcts_kind": None}
        else:
            raise UsageError(f"--mcts {args.mcts}: model {label} was trained on MCTS_{own_kind}; leave --mcts out to use it")
    results, skipped = [], []
    for p in seqs:
        try:
            results.append(evaluate_sequence(p, detector, **common))
        except DataError as exc:
            if len(seqs) == 1 or "no frame pairs" not in str(exc):
                raise
            skipped.append(str(p))  # in a folder, a sequence without 45 deg of rotation has nothing to score
            print(f"aerovis-eval: skipping {exc}", file=sys.stderr)
    if not results:
        raise DataError(args.data, "no sequence yields frame pairs")
    return pooled_summary(results, args.data, skipped), results


def pooled_summary(results: list[dict], data: str, skipped: list[str]) -> dict:
    """One summary of several :func:`~aerovis_train.eval.pose.evaluate_sequence` results of one method:
    the pairs of all sequences pooled into one AUC, timings averaged over all frames."""
    per_pair = [pp for r in results for pp in r["per_pair"]]
    frames = np.array([r["frames"] for r in results], np.float64)
    summary = {"model": results[0]["model"], "data": str(data), "sequences": len(results), **summarize(per_pair),
               # per-frame timings pooled over all frames of all sequences
               "latency_ms": float(np.average([r["latency_ms"] for r in results], weights=frames)),
               "mcts_ms": float(np.average([r["mcts_ms"] for r in results], weights=frames)),
               "frames": int(frames.sum()), "mcts": results[0]["mcts"], "rate_hz": results[0]["rate_hz"],
               "estimator": results[0]["estimator"], "skipped": skipped}
    for key in ("ransac_px", "top_k", "resolution"):
        values = {json.dumps(r[key]) for r in results}
        summary[key] = results[0][key] if len(values) == 1 else [r[key] for r in results]
    return summary


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "compare":
            from .compare import main_compare

            return main_compare(args, argv)
        if args.command == "lag":
            from .lag import main_lag

            return main_lag(args)
        if args.command == "pairs":
            from .pairs import main_pairs

            return main_pairs(args)
        if args.command == "pose":
            for summary in _pose(args):
                if not args.quiet:
                    print(f"{summary['model']} on {summary['sequences']} sequence(s): {summary['pairs']} pairs, "
                          f"rotation AUC@5/10/20 {summary['auc5']:.1f} / {summary['auc10']:.1f} / {summary['auc20']:.1f} %, "
                          f"max(R,t) {summary['auc5_max']:.1f} / {summary['auc10_max']:.1f} / {summary['auc20_max']:.1f} %, "
                          f"{summary['matches']:.0f} matches/pair, {summary['latency_ms']:.2f} ms/frame", file=sys.stderr)
                    if "correct_matches_3px" in summary:
                        print(f"  its matches within 1 / 3 px of the truth: {summary['correct_matches_1px']:.1f} / "
                              f"{summary['correct_matches_3px']:.1f} per pair (median error of those within 3 px "
                              f"{summary['correct_error_px'] or float('nan'):.2f} px)", file=sys.stderr)
                        print(f"  its keypoints in view: {summary['keypoints_in_view']:.1f} per pair, repeatable within 1 / 3 px "
                              f"{summary['repeatable_1px']:.1f} / {summary['repeatable_3px']:.1f} (a second-frame keypoint "
                              "that close to the true projection: the most a perfect descriptor could match)", file=sys.stderr)
                    for row in summary.get("oracle", []):
                        print(f"  perfect matches of its keypoints + {row['noise_px']:g} px: rotation AUC@5/10/20 "
                              f"{row['auc5']:.1f} / {row['auc10']:.1f} / {row['auc20']:.1f} % ({row['matches']:.0f} in view/pair); "
                              f"as many as its own inliers: {row['auc5_at_inliers']:.1f} / {row['auc10_at_inliers']:.1f} / "
                              f"{row['auc20_at_inliers']:.1f} %", file=sys.stderr)
                print(json.dumps(summary))
                sys.stdout.flush()
            return 0
    except (DataError, UsageError) as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    return 1


if __name__ == "__main__":
    sys.exit(main())
