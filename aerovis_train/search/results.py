"""``docs/results.md``: the measured tables, generated from the outputs of the commands that measure them.

    aerovis-search results --compare RUN/compare [--ablation RUN/seeds ...] [--search MULTIRUN_DIR ...] [--out docs/results.md]

Inputs (nothing is re-measured here, so the page always shows what the commands wrote):

* ``--compare``: the folder (or ``compare.json``) of ``aerovis-eval compare --data bench
  --onnx-latency --out DIR``: every model and baseline on the same pairs.
* ``--ablation``: another ``aerovis-eval compare`` folder, of several training runs (seeds) of one
  network on each time surface (``--ablation-methods REGEX`` picks them by label): one trained model
  per side says little when two seeds of one recipe differ by several points. Repeatable (each
  ``--ablation`` with its own ``--ablation-methods`` and ``--ablation-title``, in the same order), so
  that the runs of several networks or recipes stand side by side.
* ``--classical``: ``aerovis-eval compare --classical-mcts KIND`` folders: the classical detectors on
  another time surface (with learned models on the same pairs).
* ``--ceiling``: an ``aerovis-eval compare --oracle-noise-px ...`` folder: what perfect matches of each
  method's keypoints reach under the same protocol.
* ``--recipes``: a compare folder with several training runs of two recipes (``--recipe NAME=REGEX``
  twice picks each recipe's runs by label): their mean AUC@10 compared as in ``--ablation``.
* ``--search``: folders of searches (``python train.py -m ...`` or ``aerovis-search optuna``); their
  leaderboards are (re)built by :func:`aerovis_train.search.leaderboard.summarize_dir`.
* ``--keep HEADING``: a section of the page as it stands, carried over verbatim (for measurements
  whose inputs are gone from this machine); the page names what it kept.

Sections: all methods; the MCTS_Ne vs MCTS_dt ablation (SuperEvent+ vs SuperEvent, and over seeds); SuperLitE vs
SuperEvent+ accuracy and speed; the classical baselines (on the same and on other time surfaces); the
protocol's ceiling; kept sections; each search's leaderboard and Pareto plot.
Each section names the command that reproduces it and states, for the issue's targets and the
paper's claims, whether this run meets them.
"""

from __future__ import annotations

import json
import os
import shlex
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
            "untimed run (`aerovis_slam.bundle.benchmark_bundles`): ONNX Runtime's intra-op threads spin after a run, so a "
            "model's first run after a switch shares the cores with the previous model's threads.")


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


def _compare_run_groups(cmp: dict, a: list[dict], b: list[dict]) -> dict:
    """Two groups of training runs (rows of one comparison) by their mean AUC@10: the means, their
    spread, how many (a run, b run) pairings ``a`` wins, the relative gain of ``a`` and its interval,
    resampling both the start frames and the runs (:func:`bootstrap_ci`; None without per-pair results)."""
    auc = {"a": np.array([r["auc10"] for r in a], np.float64), "b": np.array([r["auc10"] for r in b], np.float64)}
    mean = {k: float(v.mean()) for k, v in auc.items()}
    gain = 100.0 * (mean["a"] - mean["b"]) / mean["b"] if mean["b"] > 0 else None
    ci, clusters = None, None
    errs = {"a": [_pair_errors(cmp, r["method"]) for r in a], "b": [_pair_errors(cmp, r["method"]) for r in b]}
    if all(e is not None for v in errs.values() for e in v) and len({len(e[0]) for v in errs.values() for e in v}) == 1:
        cluster = errs["a"][0][1]
        ci = bootstrap_ci(np.stack([e[0] for e in errs["a"]]), np.stack([e[0] for e in errs["b"]]), cluster,
                          lambda x, y: 100.0 * (x - y) / y if y > 0 else np.nan)
        clusters = len(np.unique(cluster))

    def spread(k):
        v = auc[k]
        sd = f" ± {v.std(ddof=1):.1f}" if len(v) > 1 else ""
        return f"{mean[k]:.1f}{sd} % over {len(v)} run{'s' if len(v) > 1 else ''} ({v.min():.1f}-{v.max():.1f})"

    return {"mean": mean, "gain": gain, "ci": ci, "wins": int(sum(x > y for x in auc["a"] for y in auc["b"])),
            "pairings": len(a) * len(b), "spread": {k: spread(k) for k in auc},
            "ci_txt": "" if ci is None else (f" (95 % interval {ci[0]:+.1f} to {ci[1]:+.1f} %, bootstrap over {clusters} start "
                                             "frames and the runs of each side)")}


def _run_rows(rows: list[tuple[str, dict]]) -> list[str]:
    """Table lines of training runs, each with the name of its group."""
    lines = []
    for group, r in rows:
        src = Path(r["source"]) if r.get("source") else None
        # train.py writes every run's weights as <run>/model.pt: the folder tells runs apart
        name = "" if src is None else f"`{src.parent.name}/{src.name}`" if src.name == "model.pt" else f"`{src.name}`"
        lines.append(f"| {r['method']} | {group} | {_f(r['auc5'])} | {_f(r['auc10'])} | {_f(r['auc20'])} | {_f(r['matches'])} | "
                     f"{_f(r['inlier_ratio'], 3)} | {name} |")
    return lines


def _pattern(text: str, option: str):
    import re

    try:
        return re.compile(text)
    except re.error as exc:
        raise DataError(None, f"{option} {text!r} is not a regular expression ({exc})") from None


def section_seed_ablation(cmp: dict, methods: str | None = None, title: str | None = None) -> tuple[str, dict]:
    """MCTS_Ne vs MCTS_dt over several training runs per time surface (e.g. seeds).

    ``title``: what the runs are (e.g. the network), appended to the section heading, so that
    sections of different networks can stand side by side.

    Every learned method of the comparison (those whose label matches the regular expression
    ``methods``, when given) is grouped by the time surface it reads (its row's ``mcts``); the
    groups' mean AUC@10 are compared, with an interval that resamples both the start frames and the
    runs (:func:`bootstrap_ci`).
    """
    pattern = _pattern(methods, "--ablation-methods") if methods is not None else None
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
    lines += _run_rows([("MCTS_Ne", r) for r in groups["ne"]] + [("MCTS_dt", r) for r in groups["dt"]])
    g = _compare_run_groups(cmp, groups["ne"], groups["dt"])
    gain, ci = g["gain"], g["ci"]
    verdict = {"ne_beats_dt": g["mean"]["a"] > g["mean"]["b"], "gain_pct": gain, "gain_ci95": ci,
               "runs": {k: len(v) for k, v in groups.items()}, "auc10_mean": {"ne": g["mean"]["a"], "dt": g["mean"]["b"]},
               "ne_wins": g["wins"]}
    lines += ["", f"AUC@10, mean ± standard deviation: MCTS_Ne {g['spread']['a']}, MCTS_dt {g['spread']['b']}. "
                  f"MCTS_Ne is higher in {g['wins']} of the {g['pairings']} (MCTS_Ne run, MCTS_dt run) pairings.",
              "",
              f"Relative AUC@10 gain of MCTS_Ne (means): {'n/a' if gain is None else f'{gain:+.1f}'} %{g['ci_txt']} (paper: +{PAPER_NE_GAIN} %). "
              f"Target (MCTS_Ne beats MCTS_dt in AUC@10): {_met(verdict['ne_beats_dt'])}"
              + (" on the means, but the interval includes 0" if ci and ci[0] <= 0 <= ci[1] else "") + ".", ""]
    return "\n".join(lines), verdict


def section_recipes(cmp: dict, recipes: list[str], title: str | None = None) -> tuple[str, dict]:
    """Two training recipes (e.g. two losses) over several runs each (e.g. seeds), on the pairs of one
    comparison: ``recipes`` is ``["NAME=REGEX", "NAME=REGEX"]``, each picking its runs by label. The
    first recipe's mean AUC@10 is compared with the second's as :func:`section_seed_ablation` does;
    the comparison's other methods (e.g. a shipped model, ORB) are listed as references, and every
    run's AUC@10 is given per sequence."""
    if len(recipes) != 2 or any("=" not in x for x in recipes):
        raise DataError(None, f"--recipe needs exactly two NAME=REGEX values, got {recipes}")
    named = [(n.strip(), _pattern(rx, f"--recipe {n}")) for n, rx in (x.split("=", 1) for x in recipes)]
    groups = {n: [r for r in cmp["rows"] if rx.search(r["method"])] for n, rx in named}
    (na, a), (nb, b) = groups.items()
    lines = [f"## {na} vs {nb} over several training runs" + (f": {title}" if title else ""), "",
             f"Command: `{cmp['command']}` ({cmp.get('created', 'date unknown')}); {cmp['pairs']} pairs, the same for every run; "
             + "; ".join(f"{n}: labels matching `{rx.pattern}`" for n, rx in named) + ".", ""]
    verdict: dict = {"a_beats_b": None, "gain_pct": None, "gain_ci95": None, "runs": {na: len(a), nb: len(b)}}
    empty = [n for n, v in groups.items() if not v]
    if empty:
        lines += [f"Not measured: no run of {' or '.join(empty)} in this comparison.", ""]
        return "\n".join(lines), verdict
    picked = {id(r) for r in a + b}
    others = [r for r in cmp["rows"] if id(r) not in picked]
    lines += ["| run | recipe | AUC@5 | AUC@10 | AUC@20 | matches/pair | inlier ratio | weights |", "|---|---|---:|---:|---:|---:|---:|---|"]
    lines += _run_rows([(na, r) for r in a] + [(nb, r) for r in b] + [("reference", r) for r in others])
    results = cmp.get("results") or {}
    ordered = [r["method"] for r in a + b + others if results.get(r["method"])]
    if ordered:
        seqs = list(dict.fromkeys(Path(x["sequence"]).stem for m in ordered for x in results[m]))
        auc = {(m, Path(x["sequence"]).stem): x.get("auc10") for m in ordered for x in results[m]}
        lines += ["", "AUC@10 per sequence:", "", "| run | " + " | ".join(seqs) + " |", "|---|" + "---:|" * len(seqs)]
        lines += [f"| {m} | " + " | ".join(_f(auc.get((m, q))) for q in seqs) + " |" for m in ordered]
    g = _compare_run_groups(cmp, a, b)
    verdict = {"a_beats_b": g["mean"]["a"] > g["mean"]["b"], "gain_pct": g["gain"], "gain_ci95": g["ci"],
               "runs": {na: len(a), nb: len(b)}, "auc10_mean": {na: g["mean"]["a"], nb: g["mean"]["b"]}, "wins": g["wins"]}
    gain = g["gain"]
    lines += ["", f"AUC@10, mean ± standard deviation: {na} {g['spread']['a']}, {nb} {g['spread']['b']}. "
                  f"{na} is higher in {g['wins']} of the {g['pairings']} ({na} run, {nb} run) pairings.", "",
              f"Relative AUC@10 gain of {na} over {nb} (means): {'n/a' if gain is None else f'{gain:+.1f}'} %{g['ci_txt']}"
              + ("; the interval includes 0" if g["ci"] and g["ci"][0] <= 0 <= g["ci"][1] else "") + ".", ""]
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


def _surface(kind: str) -> str:
    """A row's ``mcts`` as the page names it: ``ne`` -> MCTS_Ne, ``dt`` -> MCTS_dt."""
    return {"ne": "MCTS_Ne", "dt": "MCTS_dt"}.get(kind, f"MCTS_{kind}")


def _same_pairs(a: dict, b: dict) -> bool:
    """Whether two comparisons scored the same pairs (same sequences, start frames and pair count)."""
    return (a.get("pairs") == b.get("pairs") and list(a.get("sequences") or []) == list(b.get("sequences") or [])
            and (a.get("t_start_us") or {}) == (b.get("t_start_us") or {}))


def section_classical_surface(cmp: dict, main: dict | None = None) -> tuple[str, dict]:
    """The classical baselines of a second comparison on another time surface (``aerovis-eval compare
    --classical-mcts KIND``), with the learned models it ran on the same pairs, against the classical
    rows of the main comparison ``main`` (compared only where both scored the same pairs)."""
    rows = cmp["rows"]
    classical = [r for r in rows if r.get("kind") == "classical"]
    learned = [r for r in rows if r.get("kind") == "learned"]
    surfaces = sorted({r["mcts"] for r in classical})
    name = " and ".join(_surface(k) for k in surfaces) or "no classical detector"
    lines = [f"## Classical baselines on {name}", "",
             f"The classical detectors on {name}" + (", with the learned models of that run" if learned else "")
             + f", from a second comparison. Command: `{cmp['command']}` ({cmp.get('created', 'date unknown')}); "
             f"{cmp['pairs']} pairs" + ("" if main is None else (", the same as in the tables above" if _same_pairs(cmp, main)
                                                                  else ", not the pairs of the tables above")) + ".", "",
             "| method | MCTS | AUC@5 | AUC@10 | AUC@20 | matches/pair | inlier ratio |", "|---|---|---:|---:|---:|---:|---:|"]
    for r in [*learned, *classical]:
        lines.append(f"| {r['method']} | {r['mcts']} | {_f(r['auc5'])} | {_f(r['auc10'])} | {_f(r['auc20'])} | {_f(r['matches'])} | "
                     f"{_f(r['inlier_ratio'], 3)} |")
    lines.append("")
    verdict: dict = {"surfaces": surfaces, "learned_beat_classical": None, "against_main": {}}
    if main is not None and _same_pairs(cmp, main):
        base = {r["method"]: r for r in main["rows"] if r.get("kind") == "classical"}
        diffs = [(r, base[r["method"]]) for r in classical if r["method"] in base and base[r["method"]]["mcts"] != r["mcts"]]
        verdict["against_main"] = {r["method"]: {"auc10": r["auc10"], "auc10_main": b["auc10"], "mcts_main": b["mcts"]} for r, b in diffs}
        if diffs:
            lines.append("AUC@10 on this surface against the tables above: "
                         + "; ".join(f"{r['method']} {_f(r['auc10'])} % on {_surface(r['mcts'])} against {_f(b['auc10'])} % on {_surface(b['mcts'])}"
                                     for r, b in diffs) + ".")
    if learned and classical:
        worst = min(learned, key=lambda r: r["auc10"])
        best = max(classical, key=lambda r: r["auc10"])
        ok = worst["auc10"] > best["auc10"]
        verdict.update(learned_beat_classical=ok, worst_learned=worst["method"], best_classical=best["method"])
        lines.append(f"Every learned model above every classical one on these surfaces: {_met(ok)} (weakest learned: "
                     f"{worst['method']} {_f(worst['auc10'])} % on {_surface(worst['mcts'])}, strongest classical: {best['method']} "
                     f"{_f(best['auc10'])} % on {_surface(best['mcts'])}).")
    lines.append("")
    return "\n".join(lines), verdict


CEILING_REFERENCE_PX = 1.0  # the noise level the ceiling's statements quote: about an event keypoint's own error


def section_ceiling(cmp: dict, main: dict | None = None) -> tuple[str, dict]:
    """What perfect matches of each method's keypoints reach under the same protocol, from an
    ``aerovis-eval compare --oracle-noise-px ...`` run (rows with ``oracle``; see
    :func:`aerovis_train.eval.pose.summarize_oracle`), and how each method's own matches fare
    against the same truth. The statements quote the level nearest :data:`CEILING_REFERENCE_PX`."""
    from aerovis_train.eval.compare import oracle_table

    rows = [r for r in cmp["rows"] if r.get("oracle")]
    levels = [o["noise_px"] for o in rows[0]["oracle"]]
    ref = min(range(len(levels)), key=lambda k: abs(levels[k] - CEILING_REFERENCE_PX))
    level_txt = " / ".join(f"{x:g}" for x in levels)
    lines = ["## The protocol's ceiling: perfect matches of each method's keypoints", "",
             "Each pair is scored a second time with the method's own keypoints of the first frame matched perfectly: every "
             "keypoint's scene point (the simulator's rendered depth) is projected into the second frame where it is in view and "
             f"not hidden, both keypoints of a match get Gaussian noise of {level_txt} px per axis, and the matches go through "
             "the same plain RANSAC and scoring (which keeps its best minimal five-point model unrefined, so with inexact positions "
             "any model within the threshold can win). \"All in view\" matches every such keypoint; \"as many as own inliers\" keeps, per "
             "pair, as many of them as the method's own RANSAC inliers. Detector scores and descriptors drop out: what is left "
             "is where the keypoints are, how many are in view, the pixel noise and the unrefined RANSAC. The same run checks "
             "each method's own matches against the truth: a match is correct within r px when its second keypoint lies that "
             "close to where its first keypoint's scene point appears.", "",
             f"Command: `{cmp['command']}` ({cmp.get('created', 'date unknown')}); {cmp['pairs']} pairs"
             + ("" if main is None else (", the same as in the tables above" if _same_pairs(cmp, main) else ", not the pairs of the tables above"))
             + ". AUC@10 in percent, per pair figures pooled over the sequences:", "",
             oracle_table(rows)]
    ceiling = {r["method"]: r["oracle"][ref]["auc10"] for r in rows}
    at_inliers = {r["method"]: r["oracle"][ref]["auc10_at_inliers"] for r in rows}
    verdict: dict = {"noise_px": levels[ref], "ceiling_auc10": ceiling, "ceiling_auc10_at_inliers": at_inliers}

    # per sequence: own AUC@10 / ceiling / ceiling at the own inlier count; matches, inliers, correct, error per pair
    results = cmp.get("results") or {}
    per_seq = {r["method"]: {Path(x["sequence"]).stem: x for x in results.get(r["method"], []) if x.get("oracle")} for r in rows}
    seqs = list(dict.fromkeys(q for m in per_seq.values() for q in m))
    if seqs:
        pairs = {q: next(m[q]["pairs"] for m in per_seq.values() if q in m) for q in seqs}
        lines += [f"Per sequence: AUC@10 own / perfect matches at {levels[ref]:g} px, all in view / as many as own inliers; then "
                  "matches, RANSAC inliers, correct within 3 px and their error, per pair:", "",
                  "| method | " + " | ".join(f"{q} ({pairs[q]} pairs)" for q in seqs) + " |", "|---|" + "---|" * len(seqs)]
        for m, by in per_seq.items():
            cells = []
            for q in seqs:
                x = by.get(q)
                if x is None:
                    cells.append("")
                    continue
                inl = [p["inliers"] for p in x.get("per_pair", []) if p.get("inliers") is not None]
                o = x["oracle"][ref]
                cells.append(f"{_f(x['auc10'])} / {_f(o['auc10'])} / {_f(o['auc10_at_inliers'])}; {_f(x['matches'], 0)}, "
                             f"{_f(float(np.mean(inl)) if inl else None, 0)}, {_f(x.get('correct_matches_3px'))}, "
                             f"{_f(x.get('correct_error_px'), 2)} px")
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")

    def span(values):
        return f"{min(values):.1f}-{max(values):.1f}"

    notes = [f"With perfect matches AUC@10 is {span(ceiling.values())} % at {levels[ref]:g} px of noise whichever method's "
             "keypoints are matched (all in view; " + ", ".join(f"{span([r['oracle'][k]['auc10'] for r in rows])} % at {levels[k]:g} px"
                                                                 for k in range(len(levels)) if k != ref) + ")."]
    by = _rows_by_method(cmp)
    lite, orb = by.get("superlite"), by.get("orb")
    if lite and orb and lite.get("oracle"):
        target = 2.0 * orb["auc10"]
        c, ci = ceiling["superlite"], at_inliers["superlite"]
        verdict.update(target_auc10=target, target_pct_of_ceiling=100.0 * target / c if c > 0 else None)
        notes.append(f"Twice ORB's AUC@10 ({_f(target)} %, #4's target) is {_f(100.0 * target / c if c > 0 else None, 0)} % of "
                     f"SuperLitE's ceiling at {levels[ref]:g} px ({_f(c)} %); with as many perfect matches as SuperLitE's RANSAC "
                     f"keeps, the ceiling is {_f(ci)} %.")
    notes.append("Own AUC@10 as a share of the ceiling at " + f"{levels[ref]:g} px: "
                 + ", ".join(f"{r['method']} {_f(100.0 * r['auc10'] / ceiling[r['method']] if ceiling[r['method']] > 0 else None, 0)} %"
                             for r in rows) + ".")
    if all(r.get("correct_matches_3px") is not None for r in rows):
        notes.append("Own matches within 3 px of the truth, per pair: "
                     + ", ".join(f"{r['method']} {_f(r['correct_matches_3px'])} of {_f(r['matches'])} "
                                 f"({_f(100.0 * r['correct_matches_3px'] / r['matches'] if r['matches'] else None, 0)} %)" for r in rows)
                     + "; their median error " + ", ".join(f"{r['method']} {_f(r.get('correct_error_px'), 2)} px" for r in rows) + ".")
    if seqs:
        notes.append(f"Ceiling at {levels[ref]:g} px per sequence, over the methods: "
                     + "; ".join(f"{q} {span([by_m[q]['oracle'][ref]['auc10'] for by_m in per_seq.values() if q in by_m])} %"
                                 for q in seqs) + ".")
    lines += ["What the figures say:", "", *[f"- {n}" for n in notes], ""]
    return "\n".join(lines), verdict


def keep_section(page: str | os.PathLike, heading: str) -> str:
    """The section of an existing results page whose ``## `` heading starts with ``heading``, verbatim
    (up to the next ``## `` heading); DataError naming the page and the heading when there is none."""
    page = Path(page)
    try:
        text = page.read_text()
    except OSError as exc:
        raise DataError(page, f"cannot keep section {heading!r}: the page cannot be read ({exc})") from None
    found, lines = False, []
    for line in text.splitlines():
        if line.startswith("## "):
            if found:
                break
            found = line[3:].startswith(heading)
        if found:
            lines.append(line)
    if not found:
        raise DataError(page, f"no section headed '## {heading}...' to keep")
    return "\n".join(lines).rstrip() + "\n"


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


def _as_list(x) -> list:
    """``None`` -> ``[]``, one value -> ``[value]``, a list or tuple as a list (repeatable options)."""
    if x is None:
        return []
    return list(x) if isinstance(x, (list, tuple)) else [x]


def write_results(out: str | os.PathLike, compare: str | os.PathLike | None = None, searches: list[str] | None = None,
                  top: int = 20, ablation: str | os.PathLike | list | None = None, ablation_methods: str | list | None = None,
                  ablation_title: str | list | None = None, classical: list[str] | None = None, ceiling: str | os.PathLike | None = None,
                  keep: list[str] | None = None, recipes: str | os.PathLike | None = None, recipe: list[str] | None = None,
                  recipes_title: str | None = None) -> dict:
    """Generate the results page; returns ``{"out", "verdicts", "searches", "kept"}``.

    ``ablation``: a second ``aerovis-eval compare`` folder holding several training runs per time
    surface (see :func:`section_seed_ablation`; ``ablation_methods`` selects its methods by label,
    ``ablation_title`` names them in the heading), or a list of such folders, one section each, with
    lists of methods and titles in the same order (shorter lists: the missing ones unset). ``classical``: compare folders of the classical
    detectors on another time surface (:func:`section_classical_surface`). ``ceiling``: a compare folder
    run with ``--oracle-noise-px`` (:func:`section_ceiling`). ``recipes``: a compare folder with several runs
    of two training recipes, picked by ``recipe`` (``["NAME=REGEX", "NAME=REGEX"]``; :func:`section_recipes`). ``keep``: headings of sections of the page
    at ``out`` to carry over verbatim (:func:`keep_section`), placed after the generated sections and
    before the searches. Every input is read before the page is written, so bad input leaves it as it was."""
    out = Path(out)
    ablations = _as_list(ablation)
    ablation_methods, ablation_title = _as_list(ablation_methods), _as_list(ablation_title)
    if len(ablation_methods) > len(ablations) or len(ablation_title) > len(ablations):
        raise DataError(Path(str(ablations[-1] if ablations else "--ablation")),
                        f"{len(ablations)} --ablation folder(s) but {len(ablation_methods)} --ablation-methods and "
                        f"{len(ablation_title)} --ablation-title: at most one of each per --ablation, in the same order")
    ablation_methods += [None] * (len(ablations) - len(ablation_methods))
    ablation_title += [None] * (len(ablations) - len(ablation_title))
    cmd = ("aerovis-search results" + (f" --compare {compare}" if compare else "")
           + "".join(f" --ablation {a}" + (f" --ablation-methods {shlex.quote(m)}" if m else "")
                     + (f" --ablation-title {shlex.quote(t)}" if t else "")
                     for a, m, t in zip(ablations, ablation_methods, ablation_title))
           + "".join(f" --classical {c}" for c in classical or []) + (f" --ceiling {ceiling}" if ceiling else "")
           + (f" --recipes {recipes}" if recipes else "") + "".join(f" --recipe {shlex.quote(x)}" for x in recipe or [])
           + (f" --recipes-title {shlex.quote(recipes_title)}" if recipes_title else "")
           + "".join(f" --keep {shlex.quote(k)}" for k in keep or [])
           + "".join(f" --search {s}" for s in searches or []) + f" --out {out}")
    kept = [keep_section(out, k) for k in keep or []]
    main = load_compare(compare) if compare else None
    others = [load_compare(c) for c in classical or []]
    seed_runs = [load_compare(a) for a in ablations]
    recipe_cmp = load_compare(recipes) if recipes else None
    oracle = None
    if ceiling:
        oracle = load_compare(ceiling)
        if not any(r.get("oracle") for r in oracle["rows"]):
            raise DataError(Path(ceiling), "no row has field 'oracle': run `aerovis-eval compare --oracle-noise-px 0 0.5 1 2 --out DIR` "
                                           "on a simulated preset")
    data = sorted({str(Path(x).parent) for c in (main, *others, oracle, recipe_cmp) if c for x in c.get("sequences", [])})
    parts = ["# Results", "",
             f"Generated by `{cmd}` on {time.strftime('%Y-%m-%d')} from the outputs of the commands named in each section; "
             "regenerate rather than edit. Data: the simulator's `bench` preset (seed 0) unless a command says otherwise"
             + (f" (sequences from {', '.join(f'`{Path(d).name}`' for d in data)})" if data else "") + "."
             + (" Carried over verbatim from the page as it stood, because their inputs are no longer on the machine that "
                "generated it (each names its own command and date): " + "; ".join(f"\"{k}\"" for k in keep) + "." if keep else ""), ""]
    verdicts: dict = {}
    if main is not None:
        parts.append(section_all(main))
        per_seq = section_per_sequence(main)
        if per_seq:
            parts.append(per_seq)
        for fn in (section_ablation, section_lite, section_classical):
            text, v = fn(main)
            parts.append(text)
            verdicts[fn.__name__.removeprefix("section_")] = v
    else:
        parts += ["## Comparisons", "", "Not measured: run `aerovis-eval compare --data bench --onnx-latency --out DIR` and pass "
                  "`--compare DIR`.", ""]
    for i, other in enumerate(others):
        text, v = section_classical_surface(other, main)
        parts.append(text)
        verdicts[f"classical_surface{i + 1}" if len(others) > 1 else "classical_surface"] = v
    if oracle is not None:
        text, v = section_ceiling(oracle, main)
        parts.append(text)
        verdicts["ceiling"] = v
    for i, (runs, methods, title) in enumerate(zip(seed_runs, ablation_methods, ablation_title)):
        text, v = section_seed_ablation(runs, methods, title)
        parts.append(text)
        verdicts[f"seed_ablation{i + 1}" if len(seed_runs) > 1 else "seed_ablation"] = v
    if recipe_cmp is not None:
        text, v = section_recipes(recipe_cmp, list(recipe or []), recipes_title)
        parts.append(text)
        verdicts["recipes"] = v
    parts += kept
    done = []
    for i, s in enumerate(searches or []):
        summary = summarize_dir(s)
        png = None
        if summary["outputs"].get("png"):
            n = i + 1
            while any(f"{out.stem}_search{n}_pareto.png" in k for k in kept):  # a kept search section's plot stays
                n += 1
            name = f"{out.stem}_search{n}_pareto.png"
            atomic_write(out.with_name(name), lambda tmp, src=summary["outputs"]["png"]: shutil.copyfile(src, tmp))
            png = name
        parts.append(section_search(summary, png, top))
        done.append(summary["outputs"]["json"])
    write_text(out, "\n".join(parts).rstrip() + "\n")
    return {"out": str(out), "verdicts": verdicts, "searches": done, "kept": list(keep or [])}
