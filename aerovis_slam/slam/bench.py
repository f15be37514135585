"""Running the SLAM runtime on sequences and benchmarking it (``aerovis-slam run`` / ``bench``).

:func:`run_sequence` is one run with its outputs: ``traj.txt`` (TUM, ``T_world_body``; named
``traj.partial.txt`` and flagged in its header when the run stopped early), ``metrics.json``
(:mod:`~aerovis_slam.slam.report`) and ``traj.png``.

:func:`run_bench` runs every sequence in every mode with every detector (the learned bundle and a
classical detector on the same time surfaces) and :func:`format_table` writes the results in the
form of the paper's Table I: ATE RMSE in cm per sequence and mode, failures marked. A run counts
as

* ``failed`` when the pipeline reports a failure or raises,
* ``partial`` when it stopped before the end of the sequence,
* ``diverged`` when its ATE RMSE exceeds ``diverge_pct`` % of the path length and ``diverge_min_m``
  (the paper marks crashes and divergence alike as "failed"; keeping the reason helps debugging),
* ``no_gt`` when the sequence has no ground truth, else ``ok``.

With ``repeats`` > 1 every run is repeated with seeded keypoint noise
(:attr:`~aerovis_slam.slam.config.DetectorConfig.keypoint_noise_px`): a sync run is deterministic
but chaotic, and on handheld sequences one run can be off by a factor of two from the next
(docs/slam.md). The table then adds the mean, minimum and maximum over the repeats.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import threading
from pathlib import Path

import numpy as np

from ..environment import describe, software_versions
from ..errors import DataError
from ..measurements import PoseSamples
from .report import compute_metrics, plot_trajectory, write_metrics
from ..fileio import atomic_write_text, prepare_out_dir
from .trajectory import END_ERROR_ALIGN_S, loop_errors, write_tum

TRAJ_FILE = "traj.txt"
FINAL_TRAJ_FILE = "traj_final.txt"  # complete runs only: outputs re-anchored to their keyframes' final estimates
PARTIAL_TRAJ_FILE = "traj.partial.txt"
METRICS_FILE = "metrics.json"
ENVIRONMENT_FILE = "environment.json"  # bench: what its runs were measured with (environment.software_versions)
PLOT_FILE = "traj.png"
FRAMES_FILE = "frames.txt"  # per output: its frame slot, time, latency, processing time, backend caps (read back by read_frames)
CLASSICAL = ("orb", "sift", "gftt_brief")
MODE_CONFIG = {"sync": "accurate", "async": "realtime", "live": "realtime"}  # the paper's two settings
BENCH_FIELDS = ("sequence", "mode", "detector", "status", "ate_rmse_m", "ate_pct", "path_length_m", "rate_hz", "loop_closures",
                "repeat", "keypoint_noise_px", "ate_pct_final", "loops_better_than_drift", "keypoint_error_px",
                "end_error_m", "end_error_m_final")


def make_detector(model: str | os.PathLike | None = None, classical: str | None = None, *, top_k: int | None = None,
                  like=None):
    """The detector of a run: a bundle (``model``; the shipped default when both are None) or a
    classical kind (``orb``, ``sift``, ``gftt_brief``) computed on the same time surface as ``like``
    (a detector) when given.

    Raises:
        DataError: both given, an unknown classical kind, or a bad bundle.
    """
    if model is not None and classical is not None:
        raise DataError(None, "give either --model (a bundle) or --detector (a classical kind), not both")
    if classical is not None:
        if classical not in CLASSICAL:
            raise DataError(None, f"--detector {classical!r}: expected one of {list(CLASSICAL)}")
        from .detectors import StereoClassicalDetector

        kw = {"mcts_kind": like.mcts_kind, "mcts_params": tuple(like.mcts_params)} if like is not None else {}
        return StereoClassicalDetector(classical, **({"top_k": top_k} if top_k else {}), **kw)
    from ..bundle import BundleDetector, default_bundle_path

    return BundleDetector(model if model is not None else default_bundle_path(), top_k=top_k)


def make_loop_closer(detector, config=None):
    """A :class:`~aerovis_slam.slam.loop.LoopCloser` with the shipped vocabulary of ``detector``
    (by name; learnt online when there is none) and the ``loop`` section of ``config`` if it has one."""
    from .loop import LoopCloser, vocabulary_for

    section = getattr(config, "loop", None)
    if dataclasses.is_dataclass(section):
        section = dataclasses.asdict(section)
    return LoopCloser(config=section or None, vocabulary=vocabulary_for(getattr(detector, "name", "")))


def _run_slam(*args, **kwargs):
    """:func:`aerovis_slam.slam.pipeline.run_slam` (one indirection, so tests can stand in for it)."""
    from .pipeline import run_slam

    return run_slam(*args, **kwargs)


def _load_gt(sequence: Path) -> PoseSamples | None:
    from ..io.sequence import Sequence

    with Sequence(sequence) as seq:
        return seq.gt


def write_frames(path: str | os.PathLike, result, *, partial: bool = False) -> Path:
    """``frames.txt``: one line per pose output,
    ``slot_us t_us latency_ms processing_ms tracked iteration_caps`` (slot: the time up to which the
    frame holds events; t: the output's time, both µs on the IMU clock; iteration_caps: the LM
    iteration caps of the backend updates the frame made, comma-separated, ``-`` for none).
    :func:`read_frames` reads slots and caps back to replay an async run."""
    n = len(result.t_us)
    slots, total, tracked = (np.asarray(x).reshape(-1) for x in (result.slot_us, result.stage_ms["total"], result.tracked))
    caps = list(result.iteration_caps)
    if not len(slots) == len(total) == len(tracked) == len(caps) == n:
        raise ValueError(f"write_frames: {n} outputs but {len(slots)} slots, {len(total)} processing times, "
                         f"{len(tracked)} tracking flags, {len(caps)} iteration caps")
    lines = ["# aerovis-slam frames: slot_us t_us latency_ms processing_ms tracked iteration_caps"
             + (" (PARTIAL: the run stopped early)" if partial else ""),
             f"# replay these frames: aerovis-slam run SEQ.h5 --mode async --frame-slots {FRAMES_FILE} ..."]
    lines += [f"{int(slots[i])} {int(result.t_us[i])} {result.latency_ms[i]:.3f} {total[i]:.3f} {int(bool(tracked[i]))} "
              + (",".join(str(int(c)) for c in caps[i]) or "-") for i in range(n)]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_frames(path: str | os.PathLike) -> tuple[np.ndarray, list[list[int]] | None]:
    """Frame slots and backend iteration caps from a ``frames.txt`` (see :func:`write_frames`).

    Returns:
        (M,) int64 slots (µs, first column), and per slot the caps (sixth column), or None when
        the file has no such column (e.g. a hand-made list of one slot per line); ``#`` lines
        are comments.

    Raises:
        DataError: missing file, a line whose slot or caps are not integers, caps on some lines
            only, no slots, or slots that are not strictly increasing.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "no such file (expected a run's frames.txt: one frame slot in µs per line)")
    slots, caps = [], []
    for i, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        try:
            slots.append(int(fields[0]))
        except ValueError:
            raise DataError(path, f"line {i}: first field {fields[0]!r} is not an integer frame slot (µs)") from None
        if len(fields) >= 6:
            try:
                caps.append([] if fields[5] == "-" else [int(c) for c in fields[5].split(",")])
            except ValueError:
                raise DataError(path, f"line {i}: iteration caps {fields[5]!r} are not comma-separated integers or '-'") from None
    if not slots:
        raise DataError(path, "holds no frame slots")
    if caps and len(caps) != len(slots):
        raise DataError(path, f"iteration caps (sixth column) on {len(caps)} of {len(slots)} lines: all or none")
    arr = np.asarray(slots, np.int64)
    bad = np.flatnonzero(np.diff(arr) <= 0)
    if len(bad):
        raise DataError(path, f"frame slots must increase strictly; entry {bad[0] + 2} ({arr[bad[0] + 1]}) "
                              f"follows {arr[bad[0]]}")
    return arr, (caps or None)


def run_sequence(sequence: str | os.PathLike, detector, config, out_dir: str | os.PathLike, *, mode: str | None = None,
                 loop: bool = True, progress: bool = True, stop_event: threading.Event | None = None,
                 plot: bool = True, frame_slots: np.ndarray | None = None,
                 frame_caps: list[list[int]] | None = None) -> dict:
    """Run the SLAM pipeline on one sequence and write its outputs into ``out_dir``.

    Args:
        sequence: canonical ``.h5``.
        detector: see :func:`make_detector`.
        config: a :class:`~aerovis_slam.slam.config.SlamConfig`.
        mode: ``sync`` | ``async`` | ``live`` (default: the config's).
        loop: enable loop closure.
        stop_event: set it to stop early (the outputs then say ``complete: false``).
        frame_slots, frame_caps: async only: process these frame slots with these backend iteration
            caps (an earlier run's ``frames.txt``, see :func:`read_frames`) instead of those the
            simulated clock and the time budget pick: the run replayed exactly.

    Returns:
        The metrics dict (as written to ``metrics.json``), with ``out_dir`` and ``trajectory_file``.
    """
    sequence = Path(sequence)
    det_cfg = getattr(config, "detector", None)
    oracle_px = getattr(det_cfg, "oracle_noise_px", None)
    measure = bool(getattr(det_cfg, "measure_keypoint_errors", False))
    if oracle_px is not None or measure:  # refuse a recording, a bad noise or both diagnostics before any output exists
        from .oracle import check_diagnostics, oracle_spec

        check_diagnostics(oracle_px, measure)
        oracle_spec(sequence, float(oracle_px or 0.0))
    out = prepare_out_dir(out_dir)
    gt = _load_gt(sequence)  # fails early (DataError) on a missing or foreign file
    mode = mode or getattr(config, "mode", "sync")
    closer = make_loop_closer(detector, config) if loop else None
    try:
        kwargs = {} if frame_slots is None else {"frame_slots": frame_slots, "frame_caps": frame_caps}
        result = _run_slam(sequence, detector, config, mode=mode, loop_closer=closer, progress=progress, stop_event=stop_event,
                           **kwargs)
    finally:
        if closer is not None:
            closer.close()
    extra = {"loop": closer.summary() if closer is not None else None,
             # the sensitivity probe (DetectorConfig): recorded so that a perturbed run is never mistaken for a plain one
             "keypoint_noise_px": float(getattr(det_cfg, "keypoint_noise_px", 0.0)),
             "keypoint_noise_seed": int(getattr(det_cfg, "keypoint_noise_seed", 0)),
             # the perfect-tracks diagnostic (oracle.py): None for a run of the detector's own keypoints
             "oracle_noise_px": getattr(det_cfg, "oracle_noise_px", None),
             "keyframes": getattr(result, "keyframes", None), "pipeline_info": getattr(result, "info", None),
             # every value of the setting, not only its name: a run of an edited or custom file stays reproducible
             "settings": config.to_dict() if hasattr(config, "to_dict") else None,
             "environment": software_versions()}
    if closer is not None:
        result.warnings.extend(w for w in closer.warnings if w not in result.warnings)
        if gt is not None:  # each closure judged by the ground truth: did it measure better than the drift it corrected?
            for record, lc in zip(extra["loop"]["closures"], closer.closures):
                record.update(loop_errors(gt, lc.match_t_us, lc.t_us, lc.T_match_query, lc.T_est_match_query) or {})
    metrics, ate_se3, ate_final = compute_metrics(result, gt, sequence=sequence, detector=getattr(detector, "name", None), mode=mode,
                                       config=getattr(config, "name", None), extra=extra)
    complete = bool(result.complete)
    name = TRAJ_FILE if complete else PARTIAL_TRAJ_FILE
    # never leave the other name from an earlier run next to these results
    (out / (PARTIAL_TRAJ_FILE if complete else TRAJ_FILE)).unlink(missing_ok=True)
    header = [f"aerovis-slam trajectory of {sequence.name}: T_world_body (body = IMU frame), t [s] tx ty tz [m] qx qy qz qw",
              f"detector {metrics['detector']}, mode {mode}, config {metrics['config']}, status {result.status}"]
    write_tum(out / name, result.t_us, result.pose7, comments=header, partial=not complete)
    metrics["trajectory_file"] = name
    (out / FINAL_TRAJ_FILE).unlink(missing_ok=True)
    if getattr(result, "pose7_final", None) is not None:
        write_tum(out / FINAL_TRAJ_FILE, result.t_us, result.pose7_final,
                  comments=[header[0].replace("trajectory", "final trajectory"), header[1],
                            "every output moved with its keyframe's last smoother estimate and the last loop-closure pose graph"])
        metrics["final_trajectory_file"] = FINAL_TRAJ_FILE
    write_frames(out / FRAMES_FILE, result, partial=not complete)
    metrics["frames_file"] = FRAMES_FILE
    metrics["frame_slots_replayed"] = frame_slots is not None
    metrics["out_dir"] = str(out)
    write_metrics(out / METRICS_FILE, metrics)
    if plot:
        loops = [c["t_s"] for c in (extra["loop"] or {}).get("closures", [])]
        title = f"{sequence.stem} | {metrics['detector']} | {mode}" + ("" if complete else " | PARTIAL")
        t_init = (extra["pipeline_info"] or {}).get("t_initialized_us")
        plot_trajectory(out / PLOT_FILE, gt, ate_se3, est=PoseSamples(result.t_us, result.pose7), title=title, loop_times_s=loops,
                        init_time_s=None if t_init is None else t_init / 1e6, final_result=ate_final)
    return metrics


def classify(metrics: dict, *, diverge_pct: float = 25.0, diverge_min_m: float = 0.10) -> str:
    """``ok`` | ``failed`` | ``partial`` | ``diverged`` | ``no_gt`` of one run (see the module docstring)."""
    status = str(metrics.get("status", ""))
    if status.startswith("failed") or not (status.startswith("ok") or status.startswith("stopped")):
        return "failed"
    if not metrics.get("complete", False):
        return "partial"  # stopped early (Ctrl-C, or the event stream ended before the sequence)
    ate_m, length = metrics.get("ate_rmse_m"), metrics.get("path_length_m")
    if ate_m is None:
        return "no_gt"
    if ate_m > max(diverge_pct / 100.0 * (length or 0.0), diverge_min_m):
        return "diverged"
    return "ok"


def bench_row(sequence: str, mode: str, detector: str, metrics: dict | None, status: str, *, repeat: int = 0,
              keypoint_noise_px: float = 0.0) -> dict:
    """One ``bench.json`` entry (:data:`BENCH_FIELDS`); ``repeat`` 0 is the unperturbed run."""
    m = metrics or {}
    judged = [c for c in (m.get("loop") or {}).get("closures", []) if "error_m" in c]  # closures with GT errors
    return {"sequence": sequence, "mode": mode, "detector": detector, "status": status,
            "ate_rmse_m": m.get("ate_rmse_m"), "ate_pct": m.get("ate_pct"), "path_length_m": m.get("path_length_m"),
            "rate_hz": m.get("rate_hz"), "loop_closures": m.get("loop_closures", 0), "repeat": int(repeat),
            "keypoint_noise_px": float(keypoint_noise_px),
            # the final trajectory (traj_final.txt) of the same run; the live outputs above are the headline
            "ate_pct_final": (m.get("final") or {}).get("ate_pct"),
            # run with --keypoint-errors: median distance (px) of the observations to their scene points
            "keypoint_error_px": ((m.get("pipeline_info") or {}).get("keypoint_errors") or {}).get("median_px"),
            # closures whose measured relative position beat the odometry's, by the ground truth (None: not judged)
            "loops_better_than_drift": sum(c["error_m"] < c["true_drift_m"] for c in judged) if judged else None,
            # the last output's error after aligning the first 1.5 s (live, final): drift a loop closure removes
            "end_error_m": m.get("end_error_m"), "end_error_m_final": (m.get("final") or {}).get("end_error_m")}


def run_bench(sequences: list[str | os.PathLike], detectors: list, out_dir: str | os.PathLike, *,
              modes: tuple[str, ...] = ("sync", "async"), config: str | None = None, loop: bool = True, resume: bool = False,
              progress: bool = True, diverge_pct: float = 25.0, diverge_min_m: float = 0.10, log=None,
              stop_event: threading.Event | None = None, repeats: int = 1, keypoint_noise_px: float = 0.2,
              oracle_noise_px: float | list[float] | None = None, keypoint_errors: bool = False) -> list[dict]:
    """Run every sequence x detector x mode; write ``bench.json`` and ``table.md`` in ``out_dir``.

    Args:
        detectors: detector objects (each run uses its ``name`` in paths and rows).
        config: one setting for all modes (default: ``accurate`` for sync, ``realtime`` for async,
            the paper's accuracy and real-time settings).
        resume: reuse runs whose ``metrics.json`` exists in their folder.
        log: callable receiving one human line per run (e.g. ``tqdm.write``).
        stop_event: when set, the current run stops early (recorded as ``partial``) and no further run starts.
        repeats: runs per sequence x detector x mode: the first as configured, repeat ``i`` >= 1 with
            keypoint noise of +-``keypoint_noise_px`` px seeded with ``i``.
        oracle_noise_px: the perfect-tracks diagnostic (:attr:`~aerovis_slam.slam.config.DetectorConfig.oracle_noise_px`):
            one value or several, each a variant of every detector, named ``<detector>+oracle<X>px``
            in folders, rows and the table (one table compares the noise levels).
        keypoint_errors: every run measures its observations' distance to their scene points
            (:attr:`~aerovis_slam.slam.config.DetectorConfig.measure_keypoint_errors`; simulated sequences
            only, not with ``oracle_noise_px``); the table adds their medians.

    Returns:
        The ``bench.json`` rows. Each run's outputs are in ``out_dir/<sequence>/<detector>-<mode>/``
        (repeat ``i`` >= 1: ``<detector>-<mode>-r<i>/``).
    """
    from tqdm import tqdm

    from .config import load_config

    if repeats < 1:
        raise ValueError(f"repeats must be at least 1, got {repeats}")
    if repeats > 1 and not keypoint_noise_px > 0:
        raise ValueError(f"repeats > 1 need keypoint_noise_px > 0 (sync runs would repeat exactly), got {keypoint_noise_px}")
    if keypoint_errors:  # refuse the whole benchmark, not each run
        from .oracle import check_diagnostics

        check_diagnostics(oracle_noise_px, keypoint_errors)
    # loaded once: a bad settings file refuses the whole benchmark (DataError: file, field) instead of
    # failing each run, and editing the file while the benchmark runs changes none of its runs
    settings = {mode: load_config(config or MODE_CONFIG[mode]) for mode in modes}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    software = software_versions()  # each run's metrics.json has its own; a resumed run may come from another environment
    atomic_write_text(out / ENVIRONMENT_FILE, json.dumps(software, indent=2) + "\n")
    oracles = [None] if oracle_noise_px is None else [float(x) for x in np.atleast_1d(oracle_noise_px)]
    jobs = [(Path(s), d, m, o, i) for s in sequences for m in modes for d in detectors for o in oracles for i in range(repeats)]
    rows: list[dict] = []
    bar = tqdm(jobs, desc="aerovis-slam bench", unit="run", disable=not progress)
    for seq, det, mode, oracle_px, rep in bar:
        name = getattr(det, "name", str(det)) + ("" if oracle_px is None else f"+oracle{oracle_px:g}px")
        bar.set_postfix_str(f"{seq.stem} {name} {mode}" + (f" repeat {rep}" if repeats > 1 else ""))
        run_dir = out / seq.stem / (f"{name}-{mode}" + (f"-r{rep}" if rep else ""))
        metrics = None
        noise = 0.0
        if resume and (run_dir / METRICS_FILE).is_file():
            metrics = json.loads((run_dir / METRICS_FILE).read_text())
            noise = float(metrics.get("keypoint_noise_px") or 0.0)
        else:
            try:
                cfg = copy.deepcopy(settings[mode])
                if rep:
                    cfg.detector.keypoint_noise_px, cfg.detector.keypoint_noise_seed = float(keypoint_noise_px), rep
                noise = cfg.detector.keypoint_noise_px
                if oracle_px is not None:
                    cfg.detector.oracle_noise_px = oracle_px
                cfg.detector.measure_keypoint_errors = bool(keypoint_errors)
                metrics = run_sequence(seq, det, cfg, run_dir, mode=mode, loop=loop, progress=False, stop_event=stop_event)
            except KeyboardInterrupt:
                raise
            except Exception as exc:  # one crashing run is a "failed" cell, not the end of the benchmark
                metrics = {"status": f"failed: {type(exc).__name__}: {exc}", "complete": False}
        status = classify(metrics, diverge_pct=diverge_pct, diverge_min_m=diverge_min_m)
        rows.append(bench_row(seq.stem, mode, name, metrics, status, repeat=rep, keypoint_noise_px=noise))
        if log is not None:
            r = rows[-1]
            ate_txt = f"{r['ate_rmse_m'] * 100:.2f} cm" if r["ate_rmse_m"] is not None else "-"
            rate_txt = f"{r['rate_hz']:.1f} Hz" if r["rate_hz"] else "-"
            log(f"{seq.stem} {name} {mode}" + (f" repeat {rep}" if repeats > 1 else "")
                + f": {status}, ATE {ate_txt}, {rate_txt}, {r['loop_closures']} loop closure(s)"
                + ("" if status != "failed" else f" ({metrics.get('status')})"))
        # rewrite after every run: an interrupted benchmark keeps what it measured
        atomic_write_text(out / "bench.json", json.dumps(rows, indent=2) + "\n")
        atomic_write_text(out / "table.md", format_table(rows, software=software))
        if stop_event is not None and stop_event.is_set():
            break
    return rows


def _repeat(r: dict) -> int:
    return int(r.get("repeat", 0))  # bench.json files written before repeats existed have none


def spread_cells(rows: list[dict]) -> dict[tuple[str, str, str], list[dict]]:
    """(sequence, detector, mode) -> its rows of every repeat, in repeat order."""
    out: dict[tuple[str, str, str], list[dict]] = {}
    for r in sorted(rows, key=_repeat):
        out.setdefault((r["sequence"], r["detector"], r["mode"]), []).append(r)
    return out


def _mean_ate_pct(runs: list[dict], key: str = "ate_pct") -> float | None:
    """Mean ATE % of path (``key``: ``ate_pct`` live, ``ate_pct_final`` the final trajectory) over
    ``runs`` when every one is ``ok`` (a failure cannot be averaged away)."""
    if not runs or any(r["status"] != "ok" or r.get(key) is None for r in runs):
        return None
    return float(np.mean([r[key] for r in runs]))


def ate_values(runs: list[dict], key: str = "ate_pct") -> np.ndarray:
    """ATE % of path per run (``key``: ``ate_pct`` live, ``ate_pct_final`` the final trajectory), +inf
    for a run that is not ``ok`` (failed, diverged, partial) or has no value: infinitely bad, as the
    paper's Table I counts a failure inside a median."""
    return np.array([float(r[key]) if r["status"] == "ok" and r.get(key) is not None else np.inf for r in runs])


def _median_ate_pct(runs: list[dict], key: str = "ate_pct") -> float | None:
    """Median ATE % of path over ``runs`` as the paper's Table I counts it (the median of 5 runs; a
    system that crashes or diverges in at least 3 of them is marked failed): a run that is not
    ``ok`` counts as infinitely bad (:func:`ate_values`), so the median exists while fewer than half
    the runs failed. None when it does not (or there are no runs)."""
    if not runs:
        return None
    med = float(np.median(ate_values(runs, key)))
    return med if np.isfinite(med) else None


def format_table(rows: list[dict], *, software: dict | None = None) -> str:
    """Markdown tables in the form of the paper's Table I: ATE RMSE [cm] per sequence (rows) and
    detector x mode (columns), the best per row in bold, failures named; then processing rates.
    These show the first (unperturbed) run of each cell; with repeats a third table gives the mean,
    minimum and maximum ATE % over all of them. ``software`` (:func:`~aerovis_slam.environment.software_versions`)
    adds a footer naming what the figures were measured with."""
    all_rows = rows
    rows = [r for r in rows if _repeat(r) == 0]
    dets = list(dict.fromkeys(r["detector"] for r in rows))
    modes = list(dict.fromkeys(r["mode"] for r in rows))
    seqs = list(dict.fromkeys(r["sequence"] for r in rows))
    cols = [(d, m) for d in dets for m in modes]
    cell = {(r["sequence"], r["detector"], r["mode"]): r for r in rows}

    def header(path_column: bool) -> list[str]:
        return ["| Sequence | " + ("path [m] | " if path_column else "") + " | ".join(f"{d} {m}" for d, m in cols) + " |",
                "|---|" + ("---:|" if path_column else "") + "---:|" * len(cols)]

    lines = ["# aerovis-slam bench", "", "RMS of absolute trajectory error (ATE) [cm] after SE(3) alignment; "
             "in brackets: % of the ground-truth path length. Crashed runs are marked failed, diverged ones "
             "diverged; a run that stopped before the end shows its ATE marked partial.", ""]
    lines += header(True)
    for s in seqs:
        length = next((cell[k]["path_length_m"] for k in cell if k[0] == s and cell[k]["path_length_m"]), None)
        oks = [cell[(s, d, m)]["ate_rmse_m"] for d, m in cols if (s, d, m) in cell and cell[(s, d, m)]["status"] == "ok"]
        best = min(oks) if oks else None
        vals = []
        for d, m in cols:
            r = cell.get((s, d, m))
            if r is None:
                vals.append("")
            elif r["status"] in ("failed", "no_gt") or r["ate_rmse_m"] is None:
                vals.append(r["status"])
            else:
                txt = f"{r['ate_rmse_m'] * 100:.2f}" + (f" ({r['ate_pct']:.2f} %)" if r["ate_pct"] is not None else "")
                if r["status"] != "ok":
                    txt = f"{r['status']}: {txt}"
                vals.append(f"**{txt}**" if r["status"] == "ok" and r["ate_rmse_m"] == best and len(oks) > 1 else txt)
        lines.append(f"| {s} | {length:.2f} | " if length else f"| {s} | - | ")
        lines[-1] += " | ".join(vals) + " |"

    def first_run_table(text) -> list[str]:
        """One line per sequence, one cell per detector x mode: ``text(row)`` of its first run ('' without one)."""
        return header(False) + [f"| {s} | " + " | ".join("" if (r := cell.get((s, d, m))) is None else text(r) for d, m in cols) + " |"
                                for s in seqs]

    def rate_cell(r) -> str:
        better = r.get("loops_better_than_drift")
        return f"{r['rate_hz']:.1f} ({r['loop_closures']} LC" + ("" if better is None else f", {better} better") + ")"

    lines += ["", "Processing rate [Hz] (poses per second of processing) and loop closures (LC; better: those whose "
              "measured relative position beat the odometry's, by the ground truth).", ""]
    lines += first_run_table(lambda r: "" if r["rate_hz"] is None else rate_cell(r))
    if any(r.get("ate_pct_final") is not None for r in cell.values()):
        lines += ["", "Final trajectory (`traj_final.txt`: every output moved with its keyframe's last smoother estimate "
                  "and the last loop-closure pose graph, as OKVIS2's final trajectory; not available live): "
                  "ATE [% of path], live outputs above.", ""]
        lines += first_run_table(lambda r: "" if r.get("ate_pct_final") is None or r["status"] != "ok" else f"{r['ate_pct_final']:.2f} %")
    if any(r.get("end_error_m") is not None for r in cell.values()):
        lines += ["", "End error [cm]: the last output's distance from the ground truth after aligning the first "
                  f"{END_ERROR_ALIGN_S:g} s, live (final trajectory): the drift a loop closure removes where a sequence "
                  "returns to its start (compare with a `--no-loop` bench).", ""]
        lines += first_run_table(lambda r: "" if r.get("end_error_m") is None or r["status"] != "ok" else
                                 f"{100 * r['end_error_m']:.1f}" + ("" if r.get("end_error_m_final") is None
                                                                    else f" ({100 * r['end_error_m_final']:.1f})"))
    if any(r.get("keypoint_error_px") is not None for r in cell.values()):
        lines += ["", "Keypoint error (`--keypoint-errors`): median distance [px] of the landmark observations to the "
                  "true projection of the scene point under each landmark's first sighting (after the track refinement, "
                  "where the setting has it on).", ""]
        lines += first_run_table(lambda r: "" if r.get("keypoint_error_px") is None else f"{r['keypoint_error_px']:.2f}")
    spread = spread_cells(all_rows)

    def spread_table(key: str) -> list[str]:
        out = header(False)
        for s in seqs:
            means = {(d, m): _mean_ate_pct(spread.get((s, d, m), []), key) for d, m in cols}
            finite = [v for v in means.values() if v is not None]
            vals = []
            for d, m in cols:
                runs = spread.get((s, d, m), [])
                bad = [r for r in runs if r["status"] != "ok" or r.get(key) is None]
                pct = [r[key] for r in runs if r["status"] == "ok" and r.get(key) is not None]
                med = _median_ate_pct(runs, key)
                med_txt = f"median {med:.2f}" if med is not None else "median failed"
                if not runs:
                    vals.append("")
                elif bad:
                    vals.append(", ".join(f"r{_repeat(r)} {r['status'] if r['status'] != 'ok' else 'no value'}" for r in bad)
                                + (f"; ok: {min(pct):.2f}-{max(pct):.2f}" if pct else "") + f"; {med_txt}")
                else:
                    txt = f"{means[(d, m)]:.2f} ({min(pct):.2f}-{max(pct):.2f}), {med_txt}"
                    vals.append(f"**{txt}**" if len(finite) > 1 and means[(d, m)] == min(finite) else txt)
            out.append(f"| {s} | " + " | ".join(vals) + " |")
        return out

    n_rep = max((len(v) for v in spread.values()), default=1)
    if n_rep > 1:
        noise = max(float(r.get("keypoint_noise_px", 0.0)) for r in all_rows)
        lines += ["", f"Run-to-run spread: ATE [% of path] over {n_rep} runs per cell (the run above, then "
                  f"{n_rep - 1} with +-{noise:g} px of seeded keypoint noise): mean (min-max) and median; the best mean "
                  "per row in bold. A cell with a run that is not ok has no mean and names the runs that failed; "
                  "its median counts them as worst (the paper's Table I: the median of 5 runs, failed when 3 fail).", ""]
        lines += spread_table("ate_pct")
        if any(r.get("ate_pct_final") is not None for r in all_rows):
            lines += ["", "The same runs' final trajectories (`traj_final.txt`): mean (min-max) and median ATE [% of path].", ""]
            lines += spread_table("ate_pct_final")
    if software is not None:
        lines += ["", f"Measured with {describe(software)}; figures move when these versions or the machine change (`environment.json`)."]
    return "\n".join(lines) + "\n"


def summarize(rows: list[dict]) -> dict:
    """Per detector and mode, over the first run of each cell: runs, ok runs, median ATE (cm) and
    median rate over the ok runs, and ``best_on``: on how many sequences it has the lowest ATE of
    all detectors in that mode (a run that is not ``ok`` loses to any ``ok`` one). With repeats also
    ``repeats`` and ``best_on_mean``: the same count by the mean ATE % over all repeats (a cell with
    a failed repeat loses), and ``best_on_median`` by the median (:func:`_median_ate_pct`, the
    paper's statistic)."""
    spread = spread_cells(rows)
    n_rep = max((len(v) for v in spread.values()), default=1)
    rows = [r for r in rows if _repeat(r) == 0]
    out = {}
    wins: dict[tuple[str, str], int] = {}
    for s in dict.fromkeys(r["sequence"] for r in rows):
        for m in dict.fromkeys(r["mode"] for r in rows):
            ok = [r for r in rows if r["sequence"] == s and r["mode"] == m and r["status"] == "ok"]
            if ok:
                best = min(ok, key=lambda r: r["ate_rmse_m"])
                wins[(best["detector"], m)] = wins.get((best["detector"], m), 0) + 1
    for key in dict.fromkeys((r["detector"], r["mode"]) for r in rows):
        rs = [r for r in rows if (r["detector"], r["mode"]) == key]
        ok = [r for r in rs if r["status"] == "ok"]
        out[f"{key[0]}/{key[1]}"] = {
            "runs": len(rs), "ok": len(ok),
            "ate_cm_median": float(np.median([r["ate_rmse_m"] for r in ok]) * 100) if ok else None,
            "rate_hz_median": float(np.median([r["rate_hz"] for r in ok if r["rate_hz"]])) if any(r["rate_hz"] for r in ok) else None,
            "best_on": wins.get(key, 0),
        }
    if n_rep > 1:
        wins_by: dict[str, dict[tuple[str, str], int]] = {"mean": {}, "median": {}}
        for s in dict.fromkeys(r["sequence"] for r in rows):
            for m in dict.fromkeys(r["mode"] for r in rows):
                for stat, fn in (("mean", _mean_ate_pct), ("median", _median_ate_pct)):
                    vals = {k[1]: fn(v) for k, v in spread.items() if k[0] == s and k[2] == m}
                    vals = {d: v for d, v in vals.items() if v is not None}
                    if vals:
                        best = min(vals, key=vals.get)
                        wins_by[stat][(best, m)] = wins_by[stat].get((best, m), 0) + 1
        for key in dict.fromkeys((r["detector"], r["mode"]) for r in rows):
            out[f"{key[0]}/{key[1]}"].update(repeats=n_rep, best_on_mean=wins_by["mean"].get(key, 0),
                                             best_on_median=wins_by["median"].get(key, 0))
    return out
