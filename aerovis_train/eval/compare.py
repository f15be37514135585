"""``aerovis-eval compare``: learned models and classical baselines in one run, on the same pairs.

    aerovis-eval compare --data DIR|SEQ.h5|PRESET [--models superlite superevent_plus superevent|PATH|LABEL=PATH ...]
                         [--detectors orb sift gftt_brief] [--classical-mcts ne|dt] [--onnx-latency]
                         [--rate-hz 20] [--max-pairs N] [--top-k N] [--oracle-noise-px PX ...] [--out DIR] [--quiet]

Every method is evaluated by the SuperEvent relative-pose protocol (:mod:`.pose`) on the same
frames and therefore the same pairs: a learned model on the time surface it was trained on
(MCTS_Ne for SuperLitE and SuperEvent+, MCTS_dt for SuperEvent), a classical baseline on
``--classical-mcts`` (MCTS_Ne by default, the surface of the AERO-VIS models). The surfaces warm
up differently (MCTS_dt needs its longest window, 100 ms, MCTS_Ne a number of events), so each
sequence's first frame is the latest of all the surfaces' first frames (``t_start_us`` of
:func:`~aerovis_train.eval.pose.plan_frames`); a sequence on which any method's plan has no pair is
left out for all. The run checks that every method saw exactly the same pairs.

Default models are the shipped ``superlite``, ``superevent_plus`` and ``superevent``; those whose
weights are not installed are listed as missing (a checkpoint path can stand in, labelled
``LABEL=PATH``). Output: one table (Markdown on stderr) and one JSON line per method on stdout::

    {"method": "superlite", "auc5": ..., "auc10": ..., "auc20": ..., "matches": ..., "inlier_ratio": ...,
     "latency_ms": ..., ...}

AUC in percent (rotation error, the SuperEvent metric), ``matches`` per pair, ``inlier_ratio`` the
mean over pairs, ``latency_ms`` the detector's mean time per frame in this run (learned models in
PyTorch eager mode on this machine, one MCTS at the sequence's resolution; classical ones in
OpenCV; a bundle directory given as a model runs in ONNX Runtime). ``--onnx-latency`` adds
``onnx_fp32_ms``: the ONNX Runtime FP32 latency of a stereo batch of 2 at one resolution for all
models (424x240 cropped to what every compared model accepts: 400x240 with a MaxViT model among
them), timed round-robin for all models in one run (see :func:`onnx_figures`). ``--out DIR`` writes
``compare.json`` (summaries, per-sequence and per-pair results, the command), ``compare.md``,
``compare.csv`` and, with ``--onnx-latency``, the timed bundles under ``DIR/bundles``.

Given a folder of real time-surface pairs (the layout of :mod:`.real_pairs`), every method is scored as
``aerovis-eval pairs`` scores it instead (``matches``, ``correct``, ``precision`` per row); learned models
of a time surface other than the pairs' MCTS_dt are left out and listed.
"""

from __future__ import annotations

import csv
import io
import json
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from aerovis_slam.errors import DataError
from aerovis_slam.io.sequence import Sequence

from .cli import UsageError, load_model_arg, _sequences, pooled_summary
from .pose import evaluate_sequence, plan_frames

DEFAULT_MODELS = ("superlite", "superevent_plus", "superevent")
DEFAULT_DETECTORS = ("orb", "sift", "gftt_brief")
JSON_KEYS = ("method", "auc5", "auc10", "auc20", "matches", "inlier_ratio", "latency_ms")
#: what ``--oracle-noise-px`` adds to a row (summaries of :func:`~aerovis_train.eval.pose.summarize`)
TRUTH_KEYS = ("correct_matches_1px", "correct_matches_3px", "correct_error_px", "keypoints_in_view", "repeatable_1px",
              "repeatable_3px", "oracle")


@dataclass
class Method:
    """One row of the comparison.

    Attributes:
        label: the ``method`` name in tables.
        detector: a learned detector object, or a classical detector's name.
        kind: ``"learned"`` or ``"classical"``.
        source: weights file of a learned model (None for classical ones).
        mcts_kind, mcts_params: the time surface it is evaluated on.
    """

    label: str
    detector: object
    kind: str
    source: str | None
    mcts_kind: str
    mcts_params: tuple | None
    extra: dict = field(default_factory=dict)


def resolve_models(specs: list[str]) -> tuple[list[Method], list[str]]:
    """Learned methods from ``NAME``, ``PATH`` or ``LABEL=PATH`` specs (a path: a ``.pt``/``.ckpt``
    checkpoint, run in PyTorch, or an exported bundle directory, run in ONNX Runtime); shipped names
    whose weights are not installed are returned as missing instead of failing the run."""
    from aerovis_train.checkpoints import SHIPPED, WEIGHTS_DIR, file_sha256, resolve

    methods, missing = [], []
    for spec in specs:
        # LABEL=PATH, unless the whole spec is an existing path that happens to contain "="
        label, _, target = spec.partition("=") if "=" in spec and not Path(spec).exists() else ("", "", spec)
        if target in SHIPPED and not (WEIGHTS_DIR / f"{target}.pt").exists():
            missing.append(target)
            continue
        det = load_model_arg(target)
        if not label:
            label = target if target in SHIPPED else det.name
        det.name = label
        path = resolve(target)
        bundle = getattr(det, "bundle", None)  # a BundleDetector: its ONNX graph is what runs
        extra = ({"sha256": bundle.meta["files"][bundle.onnx_path.name], "runtime": f"onnxruntime {bundle.precision}"} if bundle is not None
                 else {"sha256": file_sha256(path), "runtime": "torch"})
        methods.append(Method(label, det, "learned", str(path), det.mcts_kind, tuple(det.mcts_params), extra))
    labels = [m.label for m in methods]
    dup = sorted({x for x in labels if labels.count(x) > 1})
    if dup:
        raise UsageError(f"--models: several models are called {dup}; name them with LABEL=PATH")
    return methods, missing


def common_starts(seqs: list[Path], methods: list[Method], *, cam: str, rate_hz: float | None, max_dt_s: float,
                  max_angle_deg: float) -> tuple[dict[Path, int], list[str]]:
    """Per sequence, the first frame time (µs) at which every method's time surface is warm; the
    sequences on which some surface's plan yields no pair are returned as skipped (with reason)."""
    surfaces = sorted({(m.mcts_kind, m.mcts_params) for m in methods}, key=str)
    starts, skipped = {}, []
    for p in seqs:
        try:
            with Sequence(p) as seq:
                firsts = [int(plan_frames(seq, cam, mcts_kind=k, mcts_params=params, rate_hz=rate_hz, max_dt_s=max_dt_s,
                                          max_angle_deg=max_angle_deg).times_us[0]) for k, params in surfaces]
                t0 = max(firsts)
                # the common start must still leave pairs for every surface
                for k, params in surfaces:
                    plan_frames(seq, cam, mcts_kind=k, mcts_params=params, rate_hz=rate_hz, max_dt_s=max_dt_s,
                                max_angle_deg=max_angle_deg, t_start_us=t0)
        except DataError as exc:
            if len(seqs) == 1 or "no frame pairs" not in str(exc):
                raise
            skipped.append(str(p))
            print(f"aerovis-eval: skipping {exc}", file=sys.stderr)
            continue
        starts[p] = t0
    if not starts:
        raise DataError(seqs[0].parent if len(seqs) > 1 else seqs[0], "no sequence yields frame pairs for every method")
    return starts, skipped


def run_compare(data: str, methods: list[Method], *, cam: str = "cam0", rate_hz: float | None = 20.0, max_pairs: int | None = None,
                top_k: int | None = None, ransac_px: float | None = None, estimator: str = "ransac", max_dt_s: float = 2.0,
                max_angle_deg: float = 45.0, onnx_latency: bool = False, bundle_dir: str | Path | None = None,
                progress: bool = True, oracle_noise_px=()) -> dict:
    """Evaluate ``methods`` on the same pairs of ``data`` (sequence, folder or preset name).

    With ``onnx_latency`` every learned method also gets ONNX Runtime figures (:func:`onnx_figures`);
    its bundles are kept in ``bundle_dir`` when given. With ``oracle_noise_px`` (simulated data) each
    row also carries the protocol's ceiling for the method's keypoints and its correct matches
    (:func:`~aerovis_train.eval.pose.evaluate_sequence`).

    Returns:
        ``{"rows": [one summary per method, JSON_KEYS first], "sequences": [...], "skipped": [...],
        "pairs": N, "results": {method: per-sequence results with per-pair errors}}``.
    Raises:
        DataError: bad data, or no sequence with pairs for every method.
        RuntimeError: methods ended up with different pairs (a bug: the plans must agree).
    """
    if not methods:
        raise UsageError("nothing to compare: no model weights found and no --detectors given")
    seqs = _sequences(data)
    starts, skipped = common_starts(seqs, methods, cam=cam, rate_hz=rate_hz, max_dt_s=max_dt_s, max_angle_deg=max_angle_deg)
    rows, all_results, pair_keys = [], {}, {}
    for m in methods:
        t0 = time.perf_counter()
        results = [evaluate_sequence(p, m.detector, cam=cam, mcts_kind=m.mcts_kind, mcts_params=m.mcts_params, rate_hz=rate_hz,
                                     ransac_px=ransac_px, top_k=top_k, max_pairs=max_pairs, max_dt_s=max_dt_s,
                                     max_angle_deg=max_angle_deg, estimator=estimator, progress=progress, t_start_us=t_start,
                                     oracle_noise_px=oracle_noise_px)
                   for p, t_start in starts.items()]
        keys = [(r["sequence"], pp["t0_us"], pp["t1_us"]) for r in results for pp in r["per_pair"]]
        pair_keys[m.label] = keys
        summary = pooled_summary(results, data, skipped)
        row = {"method": m.label, **{k: summary[k] for k in JSON_KEYS[1:]}, "kind": m.kind, "mcts": m.mcts_kind,
               "pairs": summary["pairs"], "auc5_max": summary["auc5_max"], "auc10_max": summary["auc10_max"],
               "auc20_max": summary["auc20_max"], "sequences": summary["sequences"], "frames": summary["frames"],
               "mcts_ms": summary["mcts_ms"], "resolution": summary["resolution"], "top_k": summary["top_k"],
               "ransac_px": summary["ransac_px"], "source": m.source, **m.extra, "eval_s": round(time.perf_counter() - t0, 1),
               **{k: summary[k] for k in TRUTH_KEYS if k in summary}}
        if m.kind == "learned" and hasattr(m.detector, "model"):
            from aerovis_train.models import count_parameters

            row["parameters"] = count_parameters(m.detector.model)
        rows.append(row)
        all_results[m.label] = results
    first = methods[0].label
    for label, keys in pair_keys.items():
        if keys != pair_keys[first]:
            raise RuntimeError(f"methods {first} and {label} were evaluated on different pairs ({len(pair_keys[first])} vs {len(keys)})")
    learned = [(m, r) for m, r in zip(methods, rows) if m.kind == "learned"]
    if onnx_latency and learned:
        figures = onnx_figures([m for m, _ in learned], calibration=next(iter(starts)), keep_dir=bundle_dir)
        for (m, r) in learned:
            r.update(figures[m.label])
    return {"rows": rows, "sequences": [str(p) for p in starts], "skipped": skipped, "pairs": len(pair_keys[first]),
            "t_start_us": {str(p): t for p, t in starts.items()}, "results": all_results}


def onnx_figures(methods: list[Method], *, calibration: Path, keep_dir: str | Path | None = None, repeats: int = 20,
                 warmup: int = 3) -> dict[str, dict]:
    """ONNX Runtime latency of each learned method, timed together.

    Every PyTorch model is exported to an FP32 bundle of a stereo batch at one common resolution: 424x240
    cropped to the least common multiple of the models' size multiples (:func:`common_latency_resolution`:
    400x240 as soon as a MaxViT model, whose sides are multiples of 40, is among them), so that speed
    ratios compare the same input (:func:`aerovis_train.search.metrics.export_fp32_bundle`). A bundle
    given as the model is timed as it is (its own precision and resolution). All bundles are then timed
    round-robin in one :func:`aerovis_slam.bundle.benchmark_bundles` run, so that load from other
    processes hits them alike and their ratios stay meaningful on a busy machine.

    Returns:
        Per label: ``onnx_fp32_ms`` (median inference of an FP32 bundle; ``onnx_ms`` and
        ``onnx_precision`` for a bundle of another precision) and ``onnx`` (the full record), or
        ``onnx_error`` when the export failed (the accuracy figures stand without it).
    """
    import tempfile

    from aerovis_slam.bundle import benchmark_bundles
    from aerovis_train.search.metrics import LATENCY_HEIGHT, LATENCY_WIDTH, export_fp32_bundle, latency_record

    out: dict[str, dict] = {}
    models = [m.detector.model for m in methods if getattr(m.detector, "bundle", None) is None]
    height, width = common_latency_resolution(models)
    with tempfile.TemporaryDirectory(prefix="aerovis-compare-") as tmp:
        root = Path(keep_dir) if keep_dir is not None else Path(tmp)
        timed: list[tuple[Method, Path, dict]] = []
        for m in methods:
            bundle = getattr(m.detector, "bundle", None)
            if bundle is not None:
                info = {"resolution": [bundle.width, bundle.height], "requested": None, "batch": bundle.batch,
                        "precision": bundle.precision, "note": "the given bundle, as exported"}
                timed.append((m, bundle.path, info))
                continue
            try:
                path, info = export_fp32_bundle(m.detector.model, root / f"{m.label}_fp32", calibration=calibration,
                                                height=height, width=width)
                if (height, width) != (LATENCY_HEIGHT, LATENCY_WIDTH):  # the record says why not the full 424x240
                    info["requested"] = [LATENCY_WIDTH, LATENCY_HEIGHT]
                    info["note"] = info["note"] or (f"{LATENCY_WIDTH}x{LATENCY_HEIGHT} cropped to {width}x{height}, "
                                                    "the size every compared model accepts")
            except Exception as exc:  # noqa: BLE001 - reported per model; the others are still timed
                print(f"aerovis-eval: {m.label}: ONNX latency not measured ({type(exc).__name__}: {exc})", file=sys.stderr)
                out[m.label] = {"onnx_fp32_ms": None, "onnx_error": f"{type(exc).__name__}: {exc}"}
                continue
            timed.append((m, path, info))
        stats = benchmark_bundles([p for _, p, _ in timed], repeats=repeats, warmup=warmup) if timed else []
        for (m, path, info), st in zip(timed, stats):
            rec = latency_record(st, info, threads=None, bundle=str(path) if keep_dir is not None or info["requested"] is None else None)
            key = "onnx_fp32_ms" if info["precision"] == "fp32" else "onnx_ms"
            out[m.label] = {key: rec["latency_ms"], "onnx": rec, **({} if key == "onnx_fp32_ms" else {"onnx_precision": info["precision"]})}
    return out


def common_latency_resolution(models) -> tuple[int, int]:
    """(height, width) at which :func:`onnx_figures` times all ``models``: the latency resolution (424x240)
    cropped to the least common multiple of their ``size_multiple`` (8 for the convolutional encoders,
    40 for MaxViT), i.e. the largest size every one of them accepts.

    Example:
        >>> from types import SimpleNamespace as M
        >>> common_latency_resolution([M(size_multiple=8)]), common_latency_resolution([M(size_multiple=8), M(size_multiple=40)])
        ((240, 424), (240, 400))
    """
    import math

    from aerovis_train.search.metrics import latency_resolution

    return latency_resolution(math.lcm(1, *(int(getattr(m, "size_multiple", 8)) for m in models)))


def onnx_resolution_text(rows: list[dict]) -> str:
    """How the rows' ONNX figures were timed, e.g. ``2x400x240``; per-row sizes differ only where a
    bundle was given as the model (``mixed``)."""
    sizes = {(r["onnx"]["batch"], *r["onnx"]["resolution"]) for r in rows if r.get("onnx")}
    if not sizes:
        return "not timed"
    return "x".join(str(v) for v in sizes.pop()) if len(sizes) == 1 else "mixed sizes: see compare.json"


def _f(v, digits: int = 1) -> str:
    return "n/a" if v is None else f"{v:.{digits}f}"


def markdown_table(rows: list[dict]) -> str:
    """The comparison as a Markdown table (ONNX column only when measured)."""
    onnx = any("onnx_fp32_ms" in r for r in rows)
    head = "| method | kind | MCTS | AUC@5 | AUC@10 | AUC@20 | matches/pair | inlier ratio | latency (ms/frame) |"
    rule = "|---|---|---|---:|---:|---:|---:|---:|---:|"
    if onnx:
        head += f" ONNX FP32 (ms, {onnx_resolution_text(rows)}) |"
        rule += "---:|"
    lines = [head, rule]
    for r in rows:
        line = (f"| {r['method']} | {r['kind']} | {r['mcts']} | {_f(r['auc5'])} | {_f(r['auc10'])} | {_f(r['auc20'])} | "
                f"{_f(r['matches'])} | {_f(r['inlier_ratio'], 3)} | {_f(r['latency_ms'], 2)} |")
        if onnx:
            line += f" {_f(r.get('onnx_fp32_ms'))} |"
        lines.append(line)
    return "\n".join(lines) + "\n"


def oracle_table(rows: list[dict]) -> str:
    """The ``--oracle-noise-px`` figures as a Markdown table ("" when the rows have none): each method's
    correct matches and the AUC@10 of perfect matches of its keypoints at each noise level."""
    if not rows or "oracle" not in rows[0]:
        return ""
    levels = " / ".join(f"{o['noise_px']:g}" for o in rows[0]["oracle"])
    lines = [f"| method | AUC@10 | matches/pair | correct within 1 / 3 px | their error (px) | keypoints in view | "
             f"repeatable within 1 / 3 px | perfect matches, all in view, AUC@10 at {levels} px | as many as own inliers, same levels |",
             "|---|---:|---:|---|---:|---:|---|---|---|"]
    for r in rows:
        o = r["oracle"]
        lines.append(f"| {r['method']} | {_f(r['auc10'])} | {_f(r['matches'])} | {_f(r['correct_matches_1px'])} / "
                     f"{_f(r['correct_matches_3px'])} | {_f(r['correct_error_px'], 2)} | {_f(o[0]['matches'], 0)} | "
                     f"{_f(r.get('repeatable_1px'))} / {_f(r.get('repeatable_3px'))} | "
                     + " / ".join(_f(x["auc10"]) for x in o) + " | " + " / ".join(_f(x["auc10_at_inliers"]) for x in o) + " |")
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict]) -> str:
    fields = [*JSON_KEYS, "kind", "mcts", "pairs", "auc5_max", "auc10_max", "auc20_max", "parameters", "onnx_fp32_ms", "source"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow(r)
    return buf.getvalue()


def print_rows(rows: list[dict]) -> None:
    """One JSON line per row on stdout."""
    for r in rows:
        print(json.dumps(r))
    sys.stdout.flush()


def command_line(argv: list[str] | None) -> str:
    """The command as run, for the records an ``--out`` folder keeps."""
    return "aerovis-eval " + " ".join(shlex.quote(a) for a in (argv if argv is not None else sys.argv[1:]))


def add_parser(sub) -> None:
    """The ``compare`` subcommand of ``aerovis-eval``."""
    from aerovis_slam.classical import DETECTORS

    from .pose import ESTIMATORS

    p = sub.add_parser("compare", help="learned models and classical baselines in one run on the same pairs: one table, one JSON line each")
    p.add_argument("--data", required=True, help="canonical sequence (.h5), a folder of them (pooled), a simulator preset (bench, tiny), "
                                                 "or a folder of real time-surface pairs (aerovis-eval pairs: matches, correct, precision)")
    p.add_argument("--models", nargs="*", default=list(DEFAULT_MODELS),
                   help="shipped names, checkpoints (.pt/.ckpt), exported bundle folders, or LABEL=PATH "
                        "(default: the three shipped models; missing ones are listed)")
    p.add_argument("--detectors", nargs="*", default=list(DEFAULT_DETECTORS), choices=sorted(DETECTORS),
                   help="classical baselines (default: orb sift gftt_brief)")
    p.add_argument("--classical-mcts", choices=("ne", "dt"), default="ne", help="time surface of the classical baselines (default ne)")
    p.add_argument("--cam", default="cam0", help="camera (default cam0)")
    p.add_argument("--rate-hz", type=float, default=20.0, help="frames per second along the GT (0: at every GT timestamp)")
    p.add_argument("--max-pairs", type=int, default=None, help="evaluate only the first N pairs of each sequence")
    p.add_argument("--top-k", type=int, default=None, help="keypoints per frame (default max(H, W) // 2)")
    p.add_argument("--ransac-px", type=float, default=None, help="RANSAC threshold in px (default 1 up to 346 px wide, else 3)")
    p.add_argument("--estimator", choices=sorted(ESTIMATORS), default="ransac", help="essential-matrix estimator (default ransac)")
    p.add_argument("--max-dt-s", type=float, default=2.0, help="pair window in seconds (protocol: 2)")
    p.add_argument("--max-angle-deg", type=float, default=45.0, help="largest rotation threshold in degrees (protocol: 45)")
    p.add_argument("--onnx-latency", action="store_true",
                   help="also export each learned model and time ONNX Runtime FP32 on a stereo batch at 424x240 "
                        "(400x240 when a MaxViT model is compared: one size for all)")
    p.add_argument("--oracle-noise-px", type=float, nargs="+", default=[], metavar="PX",
                   help="also score every pair with perfect matches of each method's keypoints plus this much noise, and "
                        "count each method's correct matches (simulated data; see aerovis-eval pose --help)")
    p.add_argument("--out", help="folder for compare.json, compare.md, compare.csv (and bundles/ with --onnx-latency)")
    p.add_argument("--quiet", action="store_true", help="no progress bars or table on stderr")


def main_compare(args, argv: list[str] | None) -> int:
    """Run ``aerovis-eval compare`` with parsed ``args``: JSON lines on stdout, the table on stderr."""
    import os

    from aerovis_train.search.metrics import write_json, write_text

    from aerovis_slam.environment import host_description, software_versions

    host = {**host_description(), "loadavg_start": os.getloadavg(), "environment": software_versions(training=True)}
    methods, missing = resolve_models(args.models) if args.models else ([], [])
    if missing:
        print(f"aerovis-eval: compare: no weights installed for {', '.join(missing)} (aerovis_train/weights/<name>.pt): left out; "
              f"pass a checkpoint as LABEL=PATH to include it", file=sys.stderr)
    methods += [Method(d, d, "classical", None, args.classical_mcts, None) for d in args.detectors]
    from .real_pairs import is_real_pairs_folder

    if is_real_pairs_folder(args.data):
        return _compare_real_pairs(args, argv, methods, missing, host)
    out = run_compare(args.data, methods, cam=args.cam, rate_hz=None if args.rate_hz == 0 else args.rate_hz, max_pairs=args.max_pairs,
                      top_k=args.top_k, ransac_px=args.ransac_px, estimator=args.estimator, max_dt_s=args.max_dt_s,
                      max_angle_deg=args.max_angle_deg, onnx_latency=args.onnx_latency,
                      bundle_dir=Path(args.out) / "bundles" if args.out else None, progress=not args.quiet,
                      oracle_noise_px=args.oracle_noise_px)
    rows = out["rows"]
    host["loadavg_end"] = os.getloadavg()
    table = markdown_table(rows)
    ceiling = oracle_table(rows)
    if ceiling:
        table += "\nThe protocol's ceiling for each method's keypoints (aerovis-eval pose --help, --oracle-noise-px):\n\n" + ceiling
    if not args.quiet:
        print(f"\n{out['pairs']} pairs on {len(out['sequences'])} sequence(s) of {args.data}, the same for every method"
              + (f"; missing: {', '.join(missing)}" if missing else "") + "\n" + table, file=sys.stderr)
    print_rows(rows)
    if args.out:
        d = Path(args.out)
        command = command_line(argv)
        write_json(d / "compare.json", {"command": command, "data": str(args.data), "pairs": out["pairs"], "sequences": out["sequences"],
                                        "skipped": out["skipped"], "missing": missing, "t_start_us": out["t_start_us"], "rows": rows,
                                        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "host": host, "config": vars(args),
                                        "results": out["results"]})
        write_text(d / "compare.md", f"`{command}`\n\n{out['pairs']} pairs on {len(out['sequences'])} sequence(s)"
                   + (f"; missing: {', '.join(missing)}" if missing else "") + "\n\n" + table)
        write_text(d / "compare.csv", csv_text(rows))
    return 0


def _compare_real_pairs(args, argv, methods: list[Method], missing: list[str], host: dict) -> int:
    """``compare`` on a folder of real time-surface pairs (:mod:`.pairs`): the same methods scored by
    correct matches and precision instead of pose AUC. The pairs' surface is MCTS_dt (the published
    layout); learned models of another surface are left out and listed."""
    import os

    from aerovis_train.search.metrics import write_json, write_text

    from .pairs import pooled_table, run_pairs, surface_mismatch

    kind = "dt"
    usable, left_out = [], []
    for m in methods:
        why = surface_mismatch(m.detector, kind) if m.kind == "learned" else None
        if why:
            left_out.append({"method": m.label, "reason": why})
            print(f"aerovis-eval: compare: {why}: left out", file=sys.stderr)
        else:
            usable.append(m)
    if not usable:
        raise UsageError(f"nothing to compare on {args.data}: no method runs on its MCTS_dt time surfaces")
    results = run_pairs(args.data, [(m.label, m.detector) for m in usable], kind=kind, top_k=args.top_k, progress=not args.quiet)
    rows = []
    for m, r in zip(usable, results):
        rows.append({**r["summary"], "kind": m.kind, "mcts": kind, "source": m.source, **m.extra})
    host["loadavg_end"] = os.getloadavg()
    table = pooled_table(rows)
    head = (f"{rows[0]['pairs']} real pairs of {args.data}, the same for every method; correct: symmetric epipolar distance "
            f"below {rows[0]['correct_px']:g} px" + (f"; left out: {', '.join(x['method'] for x in left_out)}" if left_out else "")
            + (f"; missing: {', '.join(missing)}" if missing else ""))
    if not args.quiet:
        print(f"\n{head}\n\n{table}", file=sys.stderr)
    print_rows(rows)
    if args.out:
        d = Path(args.out)
        command = command_line(argv)
        write_json(d / "compare.json", {"command": command, "data": str(args.data), "kind": "real_pairs", "pairs": rows[0]["pairs"],
                                        "left_out": left_out, "missing": missing, "rows": rows,
                                        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "host": host, "config": vars(args),
                                        "results": {m.label: r for m, r in zip(usable, results)}})
        write_text(d / "compare.md", f"`{command}`\n\n{head}\n\n{table}")
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=["method", "kind", "pairs", "matches", "correct", "precision", "keypoints", "latency_ms",
                                            "source"], lineterminator="\n", extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
        write_text(d / "compare.csv", buf.getvalue())
    return 0
