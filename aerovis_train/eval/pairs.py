"""``aerovis-eval pairs``: correct matches and precision on real time-surface pairs with pseudo ground truth.

    aerovis-eval pairs --data DIR (--model NAME_OR_PATH ... | --detector orb sift gftt_brief ...)
                       [--mcts dt|ne] [--top-k N] [--correct-px 2] [--out FILE.json] [--quiet]

``DIR`` is a folder of recordings in the published real-pairs layout (``time_surfaces/`` and
``sg_matches/`` per recording, e.g. ``../shared/data/real_pairs``; see
:mod:`aerovis_train.eval.real_pairs`), so a user's own pairs in that layout work alike. Every method
detects on the same time surfaces, matches by mutual nearest neighbours, and is scored against the
fundamental matrix fitted to the pseudo ground truth: a match is correct below ``--correct-px`` of
symmetric epipolar distance.

Output: per method one JSON line on stdout (``matches`` and ``correct`` per pair, ``precision`` =
all correct / all matches, ``pairs``, ``skipped``, ...), and on stderr a per-pair table and the pooled
one. ``--out`` writes the lines and the per-pair results to a JSON file.

The published pairs are MCTS_dt (``--mcts dt``, the default); a learned model trained on another time
surface is refused with one line (its scores on a surface it never saw mean nothing). Classical
detectors run on any surface. Pairs whose pseudo ground truth fits no fundamental matrix are skipped
and counted (``skipped``). Bad files: one line naming the file and field, exit status 2.

Only ``.npz`` files are read, and their object arrays through a loader that unpickles numpy arrays and
nothing else, so a folder from elsewhere cannot run code.
"""

from __future__ import annotations

import json
import sys

from aerovis_slam.fileio import atomic_write_json
from aerovis_slam.mcts import MCTS_DT_WINDOWS_MS, MCTS_NE_EVENTS_PER_PX

from .real_pairs import CORRECT_PX, evaluate_real_pairs

#: the surfaces a pairs folder may hold: its kind -> the project's parameters of that kind
SURFACE_PARAMS = {"dt": tuple(MCTS_DT_WINDOWS_MS), "ne": tuple(MCTS_NE_EVENTS_PER_PX)}
SURFACE_NAMES = {"dt": ("MCTS_dt", "windows", "ms"), "ne": ("MCTS_Ne", "events per pixel", "")}


def add_parser(sub) -> None:
    """The ``pairs`` subcommand of ``aerovis-eval``."""
    from aerovis_slam.classical import DETECTORS

    p = sub.add_parser("pairs", help="correct matches and precision on real time-surface pairs with pseudo ground truth "
                                     "(a folder in the real_pairs layout)")
    p.add_argument("--data", required=True, help="folder of recordings, each with time_surfaces/ and sg_matches/ (e.g. ../shared/data/real_pairs)")
    p.add_argument("--model", nargs="+", default=[],
                   help="learned model(s): shipped name (superevent), model.pt, train.py .ckpt or a bundle directory")
    p.add_argument("--detector", nargs="+", default=[], choices=sorted(DETECTORS), help="classical baseline(s)")
    p.add_argument("--mcts", choices=sorted(SURFACE_PARAMS), default="dt",
                   help="time surface the folder holds, with the project's parameters (default dt: 1, 3, 10, 30, 100 ms, "
                        "as the published pairs)")
    p.add_argument("--top-k", type=int, default=None, help="keypoints per frame (default max(H, W) // 2)")
    p.add_argument("--correct-px", type=float, default=CORRECT_PX,
                   help=f"a match is correct below this symmetric epipolar distance in px (default {CORRECT_PX:g})")
    p.add_argument("--out", help="write the summaries and per-pair results to this JSON file")
    p.add_argument("--quiet", action="store_true", help="no progress bar or tables on stderr")


def surface_mismatch(detector, kind: str) -> str | None:
    """Why a learned ``detector`` cannot be scored on pairs of surface ``kind`` (None if it can)."""
    own_kind = getattr(detector, "mcts_kind", None)
    if own_kind is None:
        return None
    own = tuple(float(v) for v in getattr(detector, "mcts_params", ()))
    want = SURFACE_PARAMS[kind]
    if own_kind != kind or not _same(own, want):
        return f"{detector.name} was trained on {_surface_text(own_kind, own)}; these pairs are {_surface_text(kind, want)}"
    return None


def _surface_text(kind: str, params: tuple) -> str:
    """E.g. ``MCTS_dt (windows 1, 3, 10, 30, 100 ms)``."""
    name, what, unit = SURFACE_NAMES.get(kind, (kind, "parameters", ""))
    return f"{name} ({what} {', '.join(f'{v:g}' for v in params)}{' ' + unit if unit else ''})"


def _same(a: tuple, b: tuple) -> bool:
    return len(a) == len(b) and all(abs(x - y) <= 1e-9 * max(1.0, abs(y)) for x, y in zip(a, b))


def run_pairs(data: str, methods: list[tuple[str, object]], *, kind: str = "dt", top_k: int | None = None,
              correct_px: float = CORRECT_PX, progress: bool = True) -> list[dict]:
    """:func:`~aerovis_train.eval.real_pairs.evaluate_real_pairs` for each ``(label, detector)``; the time
    surfaces must have the channel count of ``kind``. Returns one result per method, its summary's
    ``method`` set to the label."""
    from aerovis_slam.errors import DataError

    from .cli import UsageError

    channels = 2 * len(SURFACE_PARAMS[kind])
    out, references = [], {}
    for i, (label, det) in enumerate(methods):
        try:
            r = evaluate_real_pairs(data, det, top_k=top_k, correct_px=correct_px, channels=channels, progress=progress,
                                    report_skips=i == 0,  # the same pairs are skipped for every method: say it once
                                    references=references)
        except DataError:
            raise
        except (ValueError, RuntimeError) as exc:  # e.g. a bundle exported for another input size
            raise UsageError(f"{label} cannot run on the time surfaces of {data} ({type(exc).__name__}: {exc})") from None
        r["summary"]["method"] = label
        out.append(r)
    return out


def per_pair_table(results: list[dict]) -> str:
    """Markdown: one row per pair and method (matches, correct, precision), then the reference's agreement."""
    lines = ["| pair | method | matches | correct | precision | pseudo-GT matches within the threshold |",
             "|---|---|---:|---:|---:|---:|"]
    for r in results:
        for p in r["per_pair"]:
            ref = p["reference"]
            prec = "n/a" if p["precision"] is None else f"{p['precision']:.3f}"
            lines.append(f"| {p['pair']} | {r['summary']['method']} | {p['matches']} | {p['correct']} | {prec} | "
                         f"{ref['agreeing']} of {ref['matches']} |")
    return "\n".join(lines) + "\n"


def pooled_table(rows: list[dict]) -> str:
    """Markdown: one row per method, pooled over the pairs."""
    lines = ["| method | pairs | matches/pair | correct/pair | precision | keypoints/frame | latency (ms/frame) |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for s in rows:
        lines.append(f"| {s['method']} | {s['pairs']} | {s['matches']:.1f} | {s['correct']:.1f} | {s['precision']:.3f} | "
                     f"{s['keypoints']:.1f} | {s['latency_ms']:.1f} |")
    return "\n".join(lines) + "\n"


def main_pairs(args) -> int:
    """Run ``aerovis-eval pairs`` with parsed ``args``: JSON lines on stdout, tables on stderr."""
    from .cli import UsageError, load_model_arg

    if not args.model and not args.detector:
        raise UsageError("give at least one --model or --detector")
    if args.top_k is not None and args.top_k < 1:
        raise UsageError(f"--top-k {args.top_k}: must be at least 1")
    if not args.correct_px > 0:
        raise UsageError(f"--correct-px {args.correct_px}: must be a positive number of pixels")
    methods = []
    for spec in args.model:
        det = load_model_arg(spec)
        why = surface_mismatch(det, args.mcts)
        if why:
            raise UsageError(f"--model {spec}: {why}; score it on pairs of its own surface")
        methods.append((spec, det))
    methods += [(d, d) for d in args.detector]
    results = run_pairs(args.data, methods, kind=args.mcts, top_k=args.top_k, correct_px=args.correct_px, progress=not args.quiet)
    rows = [r["summary"] for r in results]
    if not args.quiet:
        skipped = results[0]["skipped"]
        print(f"\n{rows[0]['pairs']} pairs of {args.data}" + (f", {len(skipped)} skipped (pseudo ground truth fits no geometry)"
                                                               if skipped else "")
              + f"; correct: symmetric epipolar distance below {args.correct_px:g} px\n\n" + per_pair_table(results)
              + "\n" + pooled_table(rows), file=sys.stderr)
    for s in rows:
        print(json.dumps(s))
    sys.stdout.flush()
    if args.out:
        atomic_write_json(args.out, {"config": vars(args), "methods": results})
    return 0
