"""Two ``aerovis-slam bench`` outputs compared, sequence by sequence, against the runs' own spread.

Sync runs are chaotic: ``--repeats`` runs of one model (the unperturbed run and runs with seeded
keypoint noise of +-0.2 px) scatter by +-0.3-0.5 points of ATE % on a handheld sequence, and one run
in eight may diverge (docs/slam.md). Whether model B beats model A is then a question about two sets
of runs per sequence, not about two numbers. :func:`compare_benches` answers it with the statistic the
paper's Table I uses, the median over runs (a run that is not ``ok`` counts as infinitely bad, so a
divergence cannot be averaged away and does not swamp the other runs either), and a bootstrap interval
of the difference that resamples each side's runs independently (the runs of two models are not
paired: the same noise seed leads two models' chaotic runs to unrelated results).

Written with numpy rather than ``scipy.stats.bootstrap``: the overall statistic needs a stratified
resample (each sequence's runs within that sequence, both sides independently, then the mean over
sequences of the medians), and medians over runs that hold +inf; a few lines do both directly.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import DataError
from .bench import ate_values, spread_cells

KEYS = ("ate_pct", "ate_pct_final")


def load_bench(bench_dir: str | os.PathLike) -> list[dict]:
    """The rows of ``bench_dir/bench.json`` (written by ``aerovis-slam bench``).

    Raises:
        DataError: naming the file when it is missing, not JSON, or not a list of rows with
            ``sequence``, ``mode``, ``detector`` and ``status``.
    """
    path = Path(bench_dir)
    if path.is_dir():
        path = path / "bench.json"
    if not path.exists():
        raise DataError(path, "no such file (an `aerovis-slam bench --out DIR` folder holds one)")
    try:
        rows = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(path, f"not readable as JSON ({exc})") from None
    need = ("sequence", "mode", "detector", "status")
    if not isinstance(rows, list) or not all(isinstance(r, dict) and all(k in r for k in need) for r in rows):
        raise DataError(path, f"expected a list of runs, each with {', '.join(need)}")
    return rows


def _cells(rows: list[dict], mode: str, detector: str | None, where: str) -> tuple[str, dict[str, list[dict]]]:
    """(detector name, sequence -> runs in repeat order) of one detector in one mode of a bench."""
    cells = {k: runs for k, runs in spread_cells(rows).items() if k[2] == mode}  # (sequence, detector, mode)
    names = list(dict.fromkeys(k[1] for k in cells))
    if detector is None:
        if len(names) != 1:
            raise DataError(where, f"{len(names)} detectors in mode {mode!r} ({', '.join(names) or 'none'}): name one")
        detector = names[0]
    elif detector not in names:
        raise DataError(where, f"no runs of detector {detector!r} in mode {mode!r} (it has: {', '.join(names) or 'none'})")
    return detector, {k[0]: runs for k, runs in cells.items() if k[1] == detector}


def compare_benches(rows_a: list[dict], rows_b: list[dict], *, mode: str = "sync", detector_a: str | None = None,
                    detector_b: str | None = None, key: str = "ate_pct", n_boot: int = 4000, seed: int = 0,
                    where_a: str = "A", where_b: str = "B") -> dict:
    """Model B against model A on the sequences both benches ran in ``mode``.

    Args:
        rows_a, rows_b: ``bench.json`` rows (:func:`load_bench`).
        detector_a, detector_b: which detector of each bench (None: the only one in ``mode``).
        key: ``ate_pct`` (live outputs) or ``ate_pct_final`` (the final trajectory).
        n_boot: bootstrap resamples; ``seed`` their generator's seed.

    Returns:
        JSON-ready dict: ``detector_a``, ``detector_b``, ``mode``, ``key``, ``n_boot``, ``seed``;
        ``sequences``, one dict per sequence in both benches:

        * ``runs_a``, ``runs_b``: ATE % per run, or the run's status where it is not ``ok``;
        * ``median_a``, ``median_b``: None when half or more of the runs failed;
        * ``difference``: median B - median A (points of ATE %; negative where B is better);
        * ``interval``: [low, high], the 95 % bootstrap interval of that difference (a bound None
          where failures leave it unbounded);
        * ``b_lower``: the share of (A run, B run) pairs in which B's run is lower (ties count half;
          0.5: no difference);

        and ``overall``: ``mean_of_medians_a``, ``mean_of_medians_b``, their ``difference`` and its
        ``interval``.
    """
    if key not in KEYS:
        raise ValueError(f"key must be one of {KEYS}, got {key!r}")
    det_a, cells_a = _cells(rows_a, mode, detector_a, where_a)
    det_b, cells_b = _cells(rows_b, mode, detector_b, where_b)
    seqs = [s for s in cells_a if s in cells_b]
    if not seqs:
        raise DataError(where_b, f"no sequence in common with {where_a} in mode {mode!r}")
    rng = np.random.default_rng(seed)
    out_seq, med_a, med_b, boot_a, boot_b = [], [], [], [], []
    for s in seqs:
        a, b = ate_values(cells_a[s], key), ate_values(cells_b[s], key)
        ma, mb = float(np.median(a)), float(np.median(b))  # +inf once half the runs failed
        med_a.append(ma)
        med_b.append(mb)
        # resampled medians of each side (n_boot,), drawn independently: the runs are not paired
        boot_a.append(np.median(a[rng.integers(0, len(a), (n_boot, len(a)))], axis=1))
        boot_b.append(np.median(b[rng.integers(0, len(b), (n_boot, len(b)))], axis=1))
        out_seq.append({
            "sequence": s, "runs_a": _runs(cells_a[s], a), "runs_b": _runs(cells_b[s], b),
            "median_a": _finite(ma), "median_b": _finite(mb), "difference": _finite(mb - ma),
            "interval": _interval(_difference(boot_b[-1], boot_a[-1])),
            "b_lower": float(np.mean(b[None, :] < a[:, None]) + 0.5 * np.mean(b[None, :] == a[:, None])),
        })
    ma, mb = float(np.mean(med_a)), float(np.mean(med_b))
    overall = {"mean_of_medians_a": _finite(ma), "mean_of_medians_b": _finite(mb), "difference": _finite(mb - ma),
               "interval": _interval(_difference(np.mean(boot_b, axis=0), np.mean(boot_a, axis=0)))}
    return {"detector_a": det_a, "detector_b": det_b, "mode": mode, "key": key, "n_boot": int(n_boot), "seed": int(seed),
            "sequences": out_seq, "overall": overall}


def _runs(rows: list[dict], values: np.ndarray) -> list[float | str]:
    """Per run: its ATE %, or its status where it is not ``ok`` (``diverged``, ``failed``, ...)."""
    return [float(v) if np.isfinite(v) else (r["status"] if r["status"] != "ok" else "no ATE") for r, v in zip(rows, values)]


def _difference(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``b - a`` of resampled medians; nan (no warning) where both are inf: neither side has a median."""
    with np.errstate(invalid="ignore"):
        return b - a


def _finite(x: float) -> float | None:
    """``x`` as a float, None where it is inf (no median) or nan (inf - inf: neither side has one)."""
    return float(x) if np.isfinite(x) else None


def _interval(diff: np.ndarray) -> list[float | None]:
    """2.5 and 97.5 percentiles of the resampled differences (order statistics, so that a resample in
    which one side has no median, half its runs failed, counts as an infinite difference). A bound is
    None (unbounded) when more than 2.5 % of the resamples are infinite that way. Resamples in which
    neither side has a median say nothing about the difference and are left out."""
    diff = diff[~np.isnan(diff)]  # inf - inf
    if len(diff) == 0:
        return [None, None]
    lo, hi = np.percentile(diff, [2.5, 97.5], method="inverted_cdf")
    return [_finite(lo), _finite(hi)]


def format_comparison(result: dict, label_a: str = "A", label_b: str = "B") -> str:
    """Markdown: one row per sequence (runs, medians, difference with its interval, share of run pairs
    in which B is lower) and the mean over sequences."""
    def num(x):
        return "failed" if x is None else f"{x:.2f}"

    def runs(xs):
        return ", ".join(x if isinstance(x, str) else num(x) for x in xs)

    def signed(x):
        return "n/a" if x is None else f"{x:+.2f}"

    def ci(iv):
        return " to ".join("unbounded" if x is None else f"{x:+.2f}" for x in iv)

    what = "live" if result["key"] == "ate_pct" else "final trajectory"
    lines = [f"{label_b} ({result['detector_b']}) against {label_a} ({result['detector_a']}), {result['mode']} mode, "
             f"ATE % of the path ({what}); median over runs, a run that is not ok counts as failed; "
             f"95 % bootstrap interval of the difference ({result['n_boot']} resamples of each side's runs).", "",
             f"| sequence | {label_a} runs | {label_b} runs | median {label_a} | median {label_b} | difference | 95 % interval | {label_b} lower in |",
             "|---|---|---|---:|---:|---:|---|---:|"]
    for r in result["sequences"]:
        lines.append(f"| {r['sequence']} | {runs(r['runs_a'])} | {runs(r['runs_b'])} | {num(r['median_a'])} | {num(r['median_b'])} "
                     f"| {signed(r['difference'])} | {ci(r['interval'])} | {100 * r['b_lower']:.0f} % |")
    o = result["overall"]
    lines.append(f"| mean over {len(result['sequences'])} sequences | | | {num(o['mean_of_medians_a'])} | "
                 f"{num(o['mean_of_medians_b'])} | {signed(o['difference'])} | {ci(o['interval'])} | |")
    return "\n".join(lines) + "\n"
