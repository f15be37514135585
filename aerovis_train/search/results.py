"""``docs/results.md``: the measured tables, generated from the outputs of the commands that measure them.

    aerovis-search results --compare RUN/compare [--ablation RUN/seeds] [--search MULTIRUN_DIR ...] [--out docs/results.md]

Inputs (nothing is re-measured here, so the page always shows what the commands wrote):

* ``--compare``: the folder (or ``compare.json``) of ``aerovis-eval compare --data bench
  --onnx-latency --out DIR``: every model and baseline on the same pairs.
* ``--ablation``: another ``aerovis-eval compare`` folder, of several training runs (seeds) of one
  network on each time surface (``--ablation-methods REGEX`` picks them by label): one trained model
  per side says little when two seeds of one recipe differ by several points.
* ``--search``: folders of searches (``python train.py -m ...`` or ``aerovis-search optuna``); their
  leaderboards are (re)built by :func:`aerovis_train.search.leaderboard.summarize_dir`.

Sections: all methods; the MCTS_Ne vs MCTS_dt ablation (SuperEvent+ vs SuperEvent, and over seeds); SuperLitE vs
SuperEvent+ accuracy and speed; the classical baselines; each search's leaderboard and Pareto plot.
Each section names the command that reproduces it and states, for the issue's targets and the
paper's claims, whether this run meets them.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np

from aerovis_slam.errors import DataError
from aerovis_slam.fileio import atomic_write

from .leaderboard import markdown_table as leaderboard_table
from .leaderboard import summarize_dir
from .metrics import write_text

PAPER_NE_GAIN = 18.7       # % relative AUC@10, SuperEvent+ over SuperEvent (AERO-VIS)
PAPER_LITE_GAIN = 15.0     # % relative AUC@10, SuperLitE over SuperEvent (AERO-VIS)
TARGET_LITE_RATIO = 85.0   # % of SuperEvent+'s AUC@10 (issue #5)
TARGET_SPEEDUP = 3.5       # x, ONNX Runtime FP32 on this CPU (issue #5)


def load_compare(path: str | os.PathLike) -> dict:
    """``compare.json`` from a folder or file; DataError naming it when absent or not one."""
    p = Path(path)
    if p.is_dir():
        p = p / "compare.json"
    try:
        data = json.loads(p.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(p, f"not a readable compare.json of `aerovis-eval compare --out` ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("rows"), list):
        raise DataError(p, "field 'rows' (one summary per method) missing: not written by `aerovis-eval compare --out`")
    return data


def _pair_errors(cmp: dict, method: str) -> tuple[np.ndarray, np.ndarray] | None:
    """(rotation errors in deg, cluster id per pair) of ``method`` in the comparison's pair order;
    a cluster is the pairs sharing a start frame (see :func:`bootstrap_ci`). None without per-pair results."""
    res = (cmp.get("results") or {}).get(method)
    if not res:
        return None
    errs, keys = [], []
    for r in res:
        for p in r["per_pair"]:
            errs.append(p["rot_err_deg"])
            keys.append((r["sequence"], p["t0_us"]))
    _, cluster = np.unique(np.array([f"{a}@{b}" for a, b in keys]), return_inverse=True)
    return np.asarray(errs, np.float64), cluster


def bootstrap_ci(err_a: np.ndarray, err_b: np.ndarray, cluster: np.ndarray, stat, *, n: int = 2000, seed: int = 0,
                 threshold: float = 10.0) -> tuple[float, float]:
    """95 % confidence interval of ``stat(AUC_a, AUC_b)`` (AUC at ``threshold`` deg, in percent) by a
    paired cluster bootstrap.

    Both methods were scored on the same pairs, so the pairs are resampled jointly (paired: the
    shared difficulty of a pair cancels). The pairs of one start frame share that frame's keypoints
    and overlap in time, so they are not independent: whole start-frame clusters are resampled, not
    single pairs (resampling pairs would give too narrow an interval).

    ``err_a``/``err_b`` are the rotation errors (deg) of one method each, shape (pairs,), or of
    several models each, shape (models, pairs): training runs of one recipe with different seeds.
    Then every resample also draws each side's models with replacement, and a side's AUC is the mean
    over its drawn models, so the interval covers the spread between training runs as well as the
    spread between pairs (one run per side would hide how much a second seed can differ).

    Example:
        >>> a, b = np.array([1.0, 2, 30, 4]), np.array([2.0, 3, 40, 5])
        >>> lo, hi = bootstrap_ci(a, b, np.arange(4), lambda x, y: x - y, n=200)
        >>> bool(lo <= 7.5 <= hi)  # AUC@10 of a minus that of b on all pairs
        True
    """
    from aerovis_train.eval.pose import pose_auc

    rng = np.random.default_rng(seed)
    err_a, err_b = np.atleast_2d(err_a), np.atleast_2d(err_b)
    ids = np.unique(cluster)
    members = [np.flatnonzero(cluster == c) for c in ids]

    def side_auc(errs: np.ndarray, pick: np.ndarray) -> float:
        # a single model draws nothing, so one-model intervals stay those of the plain paired bootstrap
        models = rng.integers(0, len(errs), len(errs)) if len(errs) > 1 else [0]
        return float(np.mean([pose_auc(errs[m, pick], (threshold,))[0] for m in models]))

    vals = []
    for _ in range(n):
        pick = np.concatenate([members[k] for k in rng.integers(0, len(ids), len(ids))])
        vals.append(stat(side_auc(err_a, pick), side_auc(err_b, pick)))
    lo, hi = np.nanpercentile(np.asarray(vals, np.float64), [2.5, 97.5])
    return float(lo), float(hi)


def _ci_text(cmp: dict, a: str, b: str, stat, signed: bool = True) -> tuple[str, tuple[float, float] | None]:
    ea, eb = _pair_errors(cmp, a), _pair_errors(cmp, b)
    if ea is None or eb is None or len(ea[0]) != len(eb[0]):
        return "", None
    lo, hi = bootstrap_ci(ea[0], eb[0], ea[1], stat)
    fmt = "{:+.1f}" if signed else "{:.1f}"
    return (f" (95 % interval {fmt.format(lo)} to {fmt.format(hi)} %, paired bootstrap over {len(np.unique(ea[1]))} start frames)",
            (lo, hi))


def _f(v, d: int = 1) -> str:
    return "n/a" if v is None else f"{v:.{d}f}"


def _met(ok: bool | None) -> str:
    return "not measured" if ok is None else ("**met**" if ok else "**not met**")


def _rows_by_method(cmp: dict) -> dict[str, dict]:
    return {r["method"]: r for r in cmp["rows"]}


def _onnx_timing_note(cmp: dict) -> str:
    """How the run timed its bundles, when its records say (runs before 2026-12-04 do not)."""
    blocks = {(r.get("onnx") or {}).get("block") for r in cmp["rows"]} - {None}
    if len(blocks) != 1:
        return ""
    return (f" The bundles were timed in one run, round-robin in blocks of {blocks.pop()} runs, each block after one "
            "untimed run (`aerovis_slam.bundle.benchmark_bundles`).")


def section_all(cmp: dict) -> str:
    from aerovis_train.eval.compare import markdown_table

    rows = cmp["rows"]
    seqs = ", ".join(Path(s).stem for s in cmp["sequences"])
    left = ", ".join(Path(s).stem for s in cmp.get("skipped", []))
    lines = [
        "## All methods on the same pairs",
        "",
        f"Command: `{cmp['command']}` ({cmp.get('created', 'date unknown')}).",
        "",
        f"{cmp['pairs']} pairs from {len(cmp['sequences'])} sequences ({seqs}), identical for every method"
        + (f"; left out (no 45 deg rotation within 2 s, so the protocol forms no pair): {left}" if left else "") + ".",
        "Rotation AUC in percent (SuperEvent protocol: mutual nearest neighbours, plain RANSAC essential matrix). "
        "`latency` is the detector's time per frame in that run (learned models in PyTorch eager mode, one MCTS at the "
        "sequence's resolution; classical ones in OpenCV); `ONNX FP32` is a stereo batch in ONNX Runtime at the size "
        "in its header, one size for every model: 424x240 cropped to what all of them accept (400x240 with a MaxViT "
        "model, whose sides must be multiples of 40)." + _onnx_timing_note(cmp),
        "",
        markdown_table(rows),
    ]
    if cmp.get("missing"):
        lines += [f"Missing (no weights installed): {', '.join(cmp['missing'])}.", ""]
    learned = [r for r in rows if r.get("kind") == "learned"]
    if learned:
        lines.append("Weights:")
        lines += [f"- `{r['method']}`: `{r.get('source')}`" + (f" (sha256 {r['sha256'][:12]})" if r.get("sha256") else "") for r in learned]
        lines.append("")
    host = cmp.get("host")
    if host:
        la = host.get("loadavg_start")
        lines += [f"Machine: {host.get('machine')}, {host.get('cpus')} CPUs"
                  + (f", load average {la[0]:.1f} at the start (latencies are inflated by other jobs on the machine when it "
                     f"exceeds the core count)" if la else "") + ".", ""]
    return "\n".join(lines)


def section_per_sequence(cmp: dict) -> str:
    """AUC@10 of every method on every sequence (the pooled AUC hides where each kind of detector wins)."""
    results = cmp.get("results") or {}
    methods = [r["method"] for r in cmp["rows"] if results.get(r["method"])]
    if not methods:
        return ""
    seqs = list(dict.fromkeys(Path(x["sequence"]).stem for m in methods for x in results[m]))
    auc = {(m, Path(x["sequence"]).stem): x.get("auc10") for m in methods for x in results[m]}
    pairs = {Path(x["sequence"]).stem: x.get("pairs") for m in methods for x in results[m]}
    head = [f"{q} ({pairs[q]} pairs)" if pairs.get(q) is not None else q for q in seqs]
    lines = ["## Per sequence", "", f"Rotation AUC@10 in percent of each method on each sequence, from the same run (`{cmp['command']}`).", "",
             "| method | " + " | ".join(head) + " |", "|---|" + "---:|" * len(seqs)]
    lines += [f"| {m} | " + " | ".join(_f(auc.get((m, q))) for q in seqs) + " |" for m in methods]
    best = []
    for q in seqs:
        scored = [(auc[(m, q)], m) for m in methods if auc.get((m, q)) is not None]
        if scored:
            best.append(f"{q}: {max(scored)[1]}")
    lines += ["", "Best on each sequence: " + "; ".join(best) + ".", ""]
    return "\n".join(lines)


def section_ablation(cmp: dict) -> tuple[str, dict]:
    by = _rows_by_method(cmp)
    ne, dt = by.get("superevent_plus"), by.get("superevent")
    lines = ["## MCTS_Ne vs MCTS_dt (SuperEvent+ vs SuperEvent)", "",
             "The same network (MaxViT + PAFPN, 256-D descriptors) trained the same way on constant-event-count time surfaces "
             "(MCTS_Ne, 8 channels) and on fixed time windows (MCTS_dt, 10 channels).", "",
             f"Command: `{cmp['command']}`", ""]
    verdict: dict = {"ne_beats_dt": None, "gain_pct": None}
    if ne is None or dt is None:
        lines += [f"Not measured: {'superevent_plus' if ne is None else 'superevent'} is not in this comparison.", ""]
        return "\n".join(lines), verdict
    gain = 100.0 * (ne["auc10"] - dt["auc10"]) / dt["auc10"] if dt["auc10"] > 0 else None
    ci_txt, ci = _ci_text(cmp, ne["method"], dt["method"], lambda x, y: 100.0 * (x - y) / y if y > 0 else np.nan)
    verdict = {"ne_beats_dt": ne["auc10"] > dt["auc10"], "gain_pct": gain, "gain_ci95": ci}
    lines += ["| model | time surface | AUC@5 | AUC@10 | AUC@20 | matches/pair | inlier ratio |",
              "|---|---|---:|---:|---:|---:|---:|"]
    for r, surf in ((ne, "MCTS_Ne"), (dt, "MCTS_dt")):
        lines.append(f"| {r['method']} | {surf} | {_f(r['auc5'])} | {_f(r['auc10'])} | {_f(r['auc20'])} | {_f(r['matches'])} | "
                     f"{_f(r['inlier_ratio'], 3)} |")
    lines += ["",
              f"Relative AUC@10 gain of MCTS_Ne: {_f(gain)} %{ci_txt} (paper: +{PAPER_NE_GAIN} %). "
              f"Target (MCTS_Ne beats MCTS_dt in AUC@10): {_met(verdict['ne_beats_dt'])}"
              + (" on the point estimate, but the interval includes 0: on these pairs the difference is within the noise"
                 if ci and ci[0] <= 0 <= ci[1] else "") + ".",
              "The interval resamples the pairs of one training run per model, not the training: another seed of either "
              "model can move the gain beyond it (compare several runs per time surface with `--ablation`).", ""]
    return "\n".join(lines), verdict


def section_seed_ablation(cmp: dict, methods: str | None = None, title: str | None = None) -> tuple[str, dict]:
    """MCTS_Ne vs MCTS_dt over several training runs per time surface (e.g. seeds).

    ``title``: what the runs are (e.g. the network), appended to the section heading, so that
    sections of different networks can stand side by side.

    Every learned method of the comparison (those whose label matches the regular expression
    ``methods``, when given) is grouped by the time surface it reads (its row's ``mcts``); the
    groups' mean AUC@10 are compared, with an interval that resamples both the start frames and the
    runs (:func:`bootstrap_ci`).
    """
    import re

    try:
        pattern = re.compile(methods) if methods is not None else None
    except re.error as exc:
        raise DataError(None, f"--ablation-methods {methods!r} is not a regular expression ({exc})") from None
    rows = [r for r in cmp["rows"] if r.get("kind") == "learned" and (pattern is None or pattern.search(r["method"]))]
    groups = {k: [r for r in rows if r.get("mcts") == k] for k in ("ne", "dt")}
    lines = ["## MCTS_Ne vs MCTS_dt over several training runs" + (f": {title}" if title else ""), "",
             f"Command: `{cmp['command']}` ({cmp.get('created', 'date unknown')}); {cmp['pairs']} pairs, the same for every run"
             + (f"; the runs: labels matching `{methods}`" if methods else "") + ".", ""]
    verdict: dict = {"ne_beats_dt": None, "gain_pct": None, "gain_ci95": None, "runs": {k: len(v) for k, v in groups.items()}}
    if not groups["ne"] or not groups["dt"]:
        lines += [f"Not measured: no learned {'MCTS_Ne' if not groups['ne'] else 'MCTS_dt'} model among the selected methods.", ""]
        return "\n".join(lines), verdict
    lines += ["| run | time surface | AUC@5 | AUC@10 | AUC@20 | matches/pair | inlier ratio | weights |",
              "|---|---|---:|---:|---:|---:|---:|---|"]
    for k, surf in (("ne", "MCTS_Ne"), ("dt", "MCTS_dt")):
        for r in groups[k]:
            lines.append(f"| {r['method']} | {surf} | {_f(r['auc5'])} | {_f(r['auc10'])} | {_f(r['auc20'])} | {_f(r['matches'])} | "
                         f"{_f(r['inlier_ratio'], 3)} | `{Path(r.get('source') or '?').name}` |")
    auc = {k: np.array([r["auc10"] for r in v], np.float64) for k, v in groups.items()}
    mean = {k: float(v.mean()) for k, v in auc.items()}
    gain = 100.0 * (mean["ne"] - mean["dt"]) / mean["dt"] if mean["dt"] > 0 else None
    wins = int(sum(a > b for a in auc["ne"] for b in auc["dt"]))
    ci, ci_txt = None, ""
    errs = {k: [_pair_errors(cmp, r["method"]) for r in v] for k, v in groups.items()}
    if all(e is not None for v in errs.values() for e in v) and len({len(e[0]) for v in errs.values() for e in v}) == 1:
        ea, eb = np.stack([e[0] for e in errs["ne"]]), np.stack([e[0] for e in errs["dt"]])
        cluster = errs["ne"][0][1]
        ci = bootstrap_ci(ea, eb, cluster, lambda x, y: 100.0 * (x - y) / y if y > 0 else np.nan)
        ci_txt = (f" (95 % interval {ci[0]:+.1f} to {ci[1]:+.1f} %, bootstrap over {len(np.unique(cluster))} start frames "
                  f"and the runs of each side)")
    verdict = {"ne_beats_dt": mean["ne"] > mean["dt"], "gain_pct": gain, "gain_ci95": ci, "runs": {k: len(v) for k, v in groups.items()},
               "auc10_mean": mean, "ne_wins": wins}

    def spread(k):
        v = auc[k]
        sd = f" ± {v.std(ddof=1):.1f}" if len(v) > 1 else ""
        return f"{mean[k]:.1f}{sd} % over {len(v)} run{'s' if len(v) > 1 else ''} ({v.min():.1f}-{v.max():.1f})"

    lines += ["", f"AUC@10, mean ± standard deviation: MCTS_Ne {spread('ne')}, MCTS_dt {spread('dt')}. "
                  f"MCTS_Ne is higher in {wins} of the {len(auc['ne']) * len(auc['dt'])} (MCTS_Ne run, MCTS_dt run) pairings.",
              "",
              f"Relative AUC@10 gain of MCTS_Ne (means): {'n/a' if gain is None else f'{gain:+.1f}'} %{ci_txt} (paper: +{PAPER_NE_GAIN} %). "
              f"Target (MCTS_Ne beats MCTS_dt in AUC@10): {_met(verdict['ne_beats_dt'])}"
              + (" on the means, but the interval includes 0" if ci and ci[0] <= 0 <= ci[1] else "") + ".", ""]
    return "\n".join(lines), verdict


def section_lite(cmp: dict) -> tuple[str, dict]:
    from aerovis_train.eval.compare import onnx_resolution_text

    by = _rows_by_method(cmp)
    lite, plus, se = by.get("superlite"), by.get("superevent_plus"), by.get("superevent")
    lines = ["## SuperLitE vs SuperEvent+: accuracy and speed", "", f"Command: `{cmp['command']}`", ""]
    verdict: dict = {"auc_ratio_pct": None, "speedup": None, "auc_ok": None, "speed_ok": None}
    if lite is None or plus is None:
        lines += [f"Not measured: {'superlite' if lite is None else 'superevent_plus'} is not in this comparison.", ""]
        return "\n".join(lines), verdict
    ratio = 100.0 * lite["auc10"] / plus["auc10"] if plus["auc10"] > 0 else None
    a, b = lite.get("onnx_fp32_ms"), plus.get("onnx_fp32_ms")
    speed = b / a if a and b else None
    ci_txt, ci = _ci_text(cmp, lite["method"], plus["method"], lambda x, y: 100.0 * x / y if y > 0 else np.nan, signed=False)
    verdict = {"auc_ratio_pct": ratio, "auc_ratio_ci95": ci, "speedup": speed,
               "auc_ok": None if ratio is None else ratio >= TARGET_LITE_RATIO, "speed_ok": None if speed is None else speed >= TARGET_SPEEDUP}
    eager = plus["latency_ms"] / lite["latency_ms"] if lite["latency_ms"] else None
    lines += ["| | SuperLitE | SuperEvent+ | SuperLitE / SuperEvent+ |", "|---|---:|---:|---:|",
              f"| AUC@10 (%) | {_f(lite['auc10'])} | {_f(plus['auc10'])} | {_f(ratio)} % |",
              f"| AUC@5 / AUC@20 (%) | {_f(lite['auc5'])} / {_f(lite['auc20'])} | {_f(plus['auc5'])} / {_f(plus['auc20'])} | |",
              f"| parameters (M) | {_f((lite.get('parameters') or 0) / 1e6, 2)} | {_f((plus.get('parameters') or 0) / 1e6, 2)} | |",
              f"| ONNX Runtime FP32, stereo batch ({onnx_resolution_text([lite, plus])}, ms) | {_f(a)} | {_f(b)} | "
              f"{_f(speed, 2) + 'x faster' if speed else 'n/a'} |",
              f"| PyTorch eager, one frame in the evaluation (ms) | {_f(lite['latency_ms'])} | {_f(plus['latency_ms'])} | "
              f"{_f(eager, 2) + 'x faster' if eager else 'n/a'} |", ""]
    if ci_txt:
        lines += [f"AUC@10 ratio {_f(ratio)} %{ci_txt}.", ""]
    if ci and ci[0] <= TARGET_LITE_RATIO <= ci[1]:
        lines.append(f"The interval includes the {TARGET_LITE_RATIO:g} % target: these pairs cannot tell whether it is met.")
    lines.append(f"Targets: AUC@10 at least {TARGET_LITE_RATIO:g} % of SuperEvent+'s: {_met(verdict['auc_ok'])}; "
                 f"at least {TARGET_SPEEDUP:g}x faster in ONNX Runtime FP32: {_met(verdict['speed_ok'])}.")
    if se is not None and se["auc10"] > 0:
        g = 100.0 * (lite["auc10"] - se["auc10"]) / se["auc10"]
        lines.append(f"SuperLitE vs SuperEvent (MCTS_dt) AUC@10: {g:+.1f} % relative (paper: +{PAPER_LITE_GAIN} %).")
    lines += ["The paper reports about 10x on a Jetson Orin NX with TensorRT FP16; a CPU with ONNX Runtime FP32 runs attention "
              "(partitions, transposes, unfused GELUs) relatively worse than a GPU but convolutions relatively better, so the "
              "ratio differs by platform.", ""]
    return "\n".join(lines), verdict


def section_classical(cmp: dict) -> tuple[str, dict]:
    rows = cmp["rows"]
    learned = [r for r in rows if r.get("kind") == "learned"]
    classical = [r for r in rows if r.get("kind") == "classical"]
    lines = ["## Classical baselines on the same time surfaces", "",
             "ORB, SIFT and Shi-Tomasi corners with rBRIEF descriptors (`gftt_brief`) from OpenCV, on an 8-bit image of the "
             "MCTS (`aerovis_slam.classical.mcts_to_image`), matched and scored exactly as the networks.", "",
             f"Command: `{cmp['command']}`", "",
             "| method | MCTS | AUC@5 | AUC@10 | AUC@20 | matches/pair | inlier ratio | latency (ms/frame) |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in classical:
        lines.append(f"| {r['method']} | {r['mcts']} | {_f(r['auc5'])} | {_f(r['auc10'])} | {_f(r['auc20'])} | {_f(r['matches'])} | "
                     f"{_f(r['inlier_ratio'], 3)} | {_f(r['latency_ms'], 2)} |")
    verdict: dict = {"learned_beat_classical": None}
    if learned and classical:
        worst = min(learned, key=lambda r: r["auc10"])
        best = max(classical, key=lambda r: r["auc10"])
        ok = worst["auc10"] > best["auc10"]
        verdict = {"learned_beat_classical": ok, "worst_learned": worst["method"], "best_classical": best["method"]}
        lines += ["", f"Target (every learned model beats every classical baseline in AUC@10): {_met(ok)} "
                      f"(weakest learned: {worst['method']} {_f(worst['auc10'])} %, strongest classical: {best['method']} "
                      f"{_f(best['auc10'])} %)."]
    lines.append("")
    return "\n".join(lines), verdict


def section_search(summary: dict, png: str | None, top: int) -> str:
    steps = [r.get("steps") for r in summary["leaderboard"] if r.get("steps") is not None]
    walls = [r.get("train_wall_s") for r in summary["leaderboard"] if r.get("train_wall_s") is not None]
    budget = ""
    if steps:
        def span(lo, hi, fmt):
            return fmt.format(lo) if fmt.format(lo) == fmt.format(hi) else f"{fmt.format(lo)}-{fmt.format(hi)}"

        budget = (f"Budget per job: {span(min(steps), max(steps), '{}')} training steps"
                  + (f", {span(min(walls) / 60, max(walls) / 60, '{:.1f}')} min of training (validation included)" if walls else "") + ".")
    retimed = [(r.get("latency") or {}).get("retimed") for r in summary["leaderboard"]]
    if any(retimed):
        budget += (f" Latencies: each job's bundle timed again, all together on one machine after the search (`aerovis-search retime {summary['root']}`, "
                   f"{max(x for x in retimed if x)}), rather than by each job under its own load.")
    loads = [(r.get("latency") or {}).get("loadavg") for r in summary["leaderboard"]]
    loads = [x for x in loads if x is not None]
    cpus = next((r["host"].get("cpus") for r in summary["leaderboard"] if r.get("host")), None)
    if loads and cpus and max(loads) > cpus:
        budget += (f" Latencies were timed while the machine was busy (load average up to {max(loads):.1f} on {cpus} CPUs): "
                   "compare them with each other, not with figures from an idle machine.")
    lines = [f"## Search: {Path(summary['root']).name}", "",
             f"Command: `{summary.get('command') or 'unknown (no multirun.yaml or study.json in the folder)'}`, then "
             f"`aerovis-search summarize {summary['root']}`.", "",
             f"{summary['jobs']} jobs, {summary['with_latency']} with a latency. {budget} Validation AUC@10 on the held-out "
             "sequences of the training preset (the selected checkpoint), ONNX Runtime FP32 latency (median) of a stereo batch at "
             "424x240 (400x240 for maxvit). Pareto front: highest AUC@10 for its latency.", "",
             leaderboard_table(summary["leaderboard"], top)]
    if png:
        lines += [f"![Pareto plot of {Path(summary['root']).name}]({png})", ""]
    return "\n".join(lines)


def write_results(out: str | os.PathLike, compare: str | os.PathLike | None = None, searches: list[str] | None = None,
                  top: int = 20, ablation: str | os.PathLike | None = None, ablation_methods: str | None = None,
                  ablation_title: str | None = None) -> dict:
    """Generate the results page; returns ``{"out", "verdicts", "searches"}``.

    ``ablation``: a second ``aerovis-eval compare`` folder holding several training runs per time
    surface (see :func:`section_seed_ablation`; ``ablation_methods`` selects its methods by label,
    ``ablation_title`` names them in the heading)."""
    out = Path(out)
    cmd = ("aerovis-search results" + (f" --compare {compare}" if compare else "")
           + (f" --ablation {ablation}" if ablation else "") + (f" --ablation-methods '{ablation_methods}'" if ablation_methods else "")
           + (f" --ablation-title '{ablation_title}'" if ablation_title else "")
           + "".join(f" --search {s}" for s in searches or []) + f" --out {out}")
    parts = ["# Results", "",
             f"Generated by `{cmd}` on {time.strftime('%Y-%m-%d')} from the outputs of the commands named in each section; "
             "regenerate rather than edit. Data: the simulator's `bench` preset (seed 0) unless a command says otherwise.", ""]
    verdicts: dict = {}
    if compare:
        cmp = load_compare(compare)
        parts.append(section_all(cmp))
        per_seq = section_per_sequence(cmp)
        if per_seq:
            parts.append(per_seq)
        for fn in (section_ablation, section_lite, section_classical):
            text, v = fn(cmp)
            parts.append(text)
            verdicts[fn.__name__.removeprefix("section_")] = v
    else:
        parts += ["## Comparisons", "", "Not measured: run `aerovis-eval compare --data bench --onnx-latency --out DIR` and pass "
                  "`--compare DIR`.", ""]
    if ablation:
        text, v = section_seed_ablation(load_compare(ablation), ablation_methods, ablation_title)
        parts.append(text)
        verdicts["seed_ablation"] = v
    done = []
    for i, s in enumerate(searches or []):
        summary = summarize_dir(s)
        png = None
        if summary["outputs"].get("png"):
            name = f"{out.stem}_search{i + 1}_pareto.png"
            atomic_write(out.with_name(name), lambda tmp, src=summary["outputs"]["png"]: shutil.copyfile(src, tmp))
            png = name
        parts.append(section_search(summary, png, top))
        done.append(summary["outputs"]["json"])
    write_text(out, "\n".join(parts).rstrip() + "\n")
    return {"out": str(out), "verdicts": verdicts, "searches": done}
