"""Leaderboard and Pareto front of a search: every ``metrics.json`` under a folder.

``summarize_dir(MULTIRUN_DIR)`` (``aerovis-search summarize``) reads the jobs of a Hydra multirun
folder (or an Optuna study folder, or any folder of runs), ranks them by validation AUC@10
(ties: lower latency first), marks the Pareto front of AUC@10 (higher is better) against ONNX
Runtime latency (lower is better), and writes beside them:

* ``leaderboard.csv``: one row per job, every field;
* ``leaderboard.md``: the same as a Markdown table (the overrides that vary between jobs only);
* ``pareto.png``: AUC@10 against latency, the front drawn as a staircase and labelled;
* ``search_summary.json``: the command that ran the search (from Hydra's ``multirun.yaml`` or
  the Optuna driver's ``study.json``), the ranked jobs and the front.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shlex
from pathlib import Path

import numpy as np

from aerovis_slam.errors import DataError
from aerovis_slam.fileio import atomic_write

from .metrics import METRICS_FILE, load_metrics, write_json, write_text

CSV_FIELDS = ("rank", "job", "config", "model", "encoder", "descriptor_dim", "encoder_conf", "parameters", "gflops", "auc5", "auc10",
              "auc20", "latency_ms", "latency_resolution", "pareto", "steps", "train_wall_s", "overrides", "latency_error")


def pareto_front(auc: np.ndarray | list, latency: np.ndarray | list) -> np.ndarray:
    """Which points are on the Pareto front of maximal ``auc`` and minimal ``latency``.

    A point is dominated when another has ``auc >= `` and ``latency <=`` with one of them
    strict; the front is every point with a finite value of both that nothing dominates (equal
    points are all on it). Points with a NaN in either are never on it.

    Example:
        >>> pareto_front([30, 40, 25, 40, 10], [10, 20, 15, 30, 5]).tolist()
        [True, True, False, False, True]
    """
    a = np.asarray(auc, np.float64)
    t = np.asarray(latency, np.float64)
    if a.shape != t.shape or a.ndim != 1:
        raise ValueError(f"auc and latency must be 1-D of one length, got {a.shape} and {t.shape}")
    ok = np.isfinite(a) & np.isfinite(t)
    # O(n^2) pairwise test: searches have tens to hundreds of jobs
    ge = (a[None, :] >= a[:, None]) & (t[None, :] <= t[:, None])  # [i, j]: j at least as good as i in both
    strict = (a[None, :] > a[:, None]) | (t[None, :] < t[:, None])
    dominated = (ge & strict & ok[None, :]).any(axis=1)
    return ok & ~dominated


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def _parse_override(o: str) -> tuple[str, str]:
    key, _, value = o.partition("=")
    return key.lstrip("+~"), value


def varying_overrides(jobs: list[dict]) -> list[str]:
    """Override keys whose value differs between jobs (or that some jobs lack), in first-seen order."""
    seen: dict[str, set] = {}
    order: list[str] = []
    parsed = [dict(_parse_override(o) for o in (j.get("overrides") or [])) for j in jobs]
    for p in parsed:
        for k, v in p.items():
            if k not in seen:
                seen[k] = set()
                order.append(k)
    for k in order:
        seen[k] = {p.get(k) for p in parsed}
    return [k for k in order if len(seen[k]) > 1]


def read_jobs(root: str | os.PathLike) -> list[dict]:
    """Every ``metrics.json`` under ``root`` (recursively), each with ``job`` = its folder relative to root.

    Raises:
        DataError: ``root`` is no folder, holds no ``metrics.json``, or one of them is not a metrics file.
    """
    root = Path(root)
    if not root.is_dir():
        raise DataError(root, "not a folder (give the multirun folder of a search, e.g. multirun/2026-01-01_12-00-00)")
    paths = sorted(root.rglob(METRICS_FILE), key=lambda p: [int(s) if s.isdigit() else s for s in p.relative_to(root).parts])
    if not paths:
        raise DataError(root, f"holds no {METRICS_FILE} (jobs write it when they finish; are they still running?)")
    jobs = []
    for p in paths:
        m = load_metrics(p)
        rel = p.parent.relative_to(root).as_posix()
        jobs.append({**m, "job": rel if rel != "." else p.parent.name, "metrics_path": str(p)})
    return jobs


def rank_jobs(jobs: list[dict]) -> list[dict]:
    """Jobs ranked by AUC@10 (descending; missing last), ties by latency (ascending; missing last),
    then by job name; each gets ``rank`` (1-based), ``pareto`` (bool) and ``config`` (its
    varying overrides as ``key=value`` words, or its architecture when it has no overrides)."""
    if not jobs:
        return []
    keys = varying_overrides(jobs)
    front = pareto_front([_num(j.get("auc10")) for j in jobs], [_num(j.get("latency_ms")) for j in jobs])
    rows = []
    for j, on_front in zip(jobs, front):
        ov = dict(_parse_override(o) for o in (j.get("overrides") or []))
        config = " ".join(f"{k}={ov[k]}" for k in keys if k in ov)
        if not config:
            config = f"encoder={j.get('encoder')} descriptor_dim={j.get('descriptor_dim')}"
        rows.append({**j, "pareto": bool(on_front), "config": config})

    def key(r):
        auc, lat = _num(r.get("auc10")), _num(r.get("latency_ms"))
        return (math.isnan(auc), -auc if not math.isnan(auc) else 0.0, math.isnan(lat), lat if not math.isnan(lat) else 0.0, r["job"])

    rows.sort(key=key)
    for i, r in enumerate(rows, 1):
        r["rank"] = i
    return rows


def _fmt(v, digits: int = 1) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    return f"{v:.{digits}f}"


def markdown_table(rows: list[dict], top: int | None = None) -> str:
    """The leaderboard as a Markdown table (the first ``top`` rows; all by default)."""
    head = ("| rank | job | config | params (M) | GFLOP | AUC@5 | AUC@10 | AUC@20 | latency (ms) | Pareto | steps |\n"
            "|---:|---|---|---:|---:|---:|---:|---:|---:|:---:|---:|\n")
    lines = []
    for r in rows[:top] if top else rows:
        lines.append(f"| {r['rank']} | {r['job']} | {r['config'].replace('|', '/')} | {r['parameters'] / 1e6:.2f} | {r['flops'] / 1e9:.2f} | "
                     f"{_fmt(r.get('auc5'))} | {_fmt(r.get('auc10'))} | {_fmt(r.get('auc20'))} | {_fmt(r.get('latency_ms'))} | "
                     f"{'yes' if r['pareto'] else ''} | {r.get('steps', 'n/a')} |")
    return head + "\n".join(lines) + "\n"


def csv_text(rows: list[dict]) -> str:
    """The leaderboard as CSV (:data:`CSV_FIELDS`; empty cells for missing values)."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        lat = r.get("latency") or {}
        w.writerow({
            **{k: r.get(k) for k in ("rank", "job", "config", "model", "encoder", "descriptor_dim", "parameters", "auc5", "auc10", "auc20",
                                      "latency_ms", "pareto", "steps", "train_wall_s", "latency_error")},
            "encoder_conf": json.dumps(r.get("encoder_conf") or {}, sort_keys=True),
            "gflops": round(r["flops"] / 1e9, 4),
            "latency_resolution": "x".join(str(v) for v in lat.get("resolution", [])) or None,
            "overrides": " ".join(r.get("overrides") or []),
        })
    return buf.getvalue()


def plot_pareto(rows: list[dict], path: str | os.PathLike, title: str = "") -> Path | None:
    """``pareto.png``: AUC@10 against latency, Pareto front as a staircase with labels. None when
    no job has both values (nothing to plot)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = [r for r in rows if not math.isnan(_num(r.get("auc10"))) and not math.isnan(_num(r.get("latency_ms")))]
    if not pts:
        return None
    fig, ax = plt.subplots(figsize=(7.5, 5), dpi=110)
    lat = np.array([r["latency_ms"] for r in pts])
    auc = np.array([r["auc10"] for r in pts])
    front = np.array([r["pareto"] for r in pts])
    ax.scatter(lat[~front], auc[~front], c="0.6", s=28, label="dominated")
    order = np.argsort(lat[front])
    fl, fa = lat[front][order], auc[front][order]
    ax.step(fl, fa, where="post", c="C3", lw=1.5, zorder=2)
    ax.scatter(fl, fa, c="C3", s=44, zorder=3, label="Pareto front")
    for r in pts:
        if r["pareto"]:
            ax.annotate(r["config"] or r["job"], (r["latency_ms"], r["auc10"]), textcoords="offset points", xytext=(5, 4), fontsize=7)
    res = {tuple((r.get("latency") or {}).get("resolution") or []) for r in pts}
    res_txt = ", ".join("x".join(map(str, x)) for x in sorted(res) if x) or "424x240"
    ax.set_xlabel(f"ONNX Runtime FP32 latency, stereo batch of 2 at {res_txt} (ms)")
    ax.set_ylabel("validation AUC@10 (%)")
    if lat.max() / max(lat.min(), 1e-9) > 8:
        ax.set_xscale("log")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title(title or f"{len(pts)} jobs; Pareto front marked", fontsize=10)
    fig.tight_layout()
    try:
        return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png"))
    finally:
        plt.close(fig)


def search_command(root: str | os.PathLike) -> str | None:
    """The command that ran the search in ``root``: from Hydra's ``multirun.yaml`` (a sweep of
    ``train.py``) or the Optuna driver's ``study.json``; None when neither is there."""
    root = Path(root)
    study = root / "study.json"
    if study.is_file():
        try:
            return json.loads(study.read_text()).get("command")
        except json.JSONDecodeError:
            return None
    mr = root / "multirun.yaml"
    if mr.is_file():
        from omegaconf import OmegaConf

        try:
            task = OmegaConf.load(mr).hydra.overrides.task
        except Exception:  # noqa: BLE001 - a foreign or damaged multirun.yaml just leaves the command unknown
            return None
        return "python train.py -m " + " ".join(shlex.quote(str(t)) for t in task)
    return None


def summarize_dir(root: str | os.PathLike, out_dir: str | os.PathLike | None = None, top: int | None = None) -> dict:
    """Leaderboard (CSV, Markdown), Pareto plot and ``search_summary.json`` of the jobs under ``root``.

    Args:
        root: a multirun / study folder with one ``metrics.json`` per finished job.
        out_dir: where to write (default ``root``).
        top: rows of the Markdown table (default all).
    Returns:
        The summary written to ``search_summary.json`` (``root``, ``command``, ``jobs``,
        ``with_latency``, ``best``, ``pareto`` (job names, by latency), ``leaderboard`` rows, ``outputs``).
    """
    root = Path(root)
    out = Path(out_dir) if out_dir else root
    rows = rank_jobs(read_jobs(root))
    command = search_command(root)
    outputs = {"csv": str(write_text(out / "leaderboard.csv", csv_text(rows))),
               "markdown": str(write_text(out / "leaderboard.md", markdown_table(rows, top)))}
    png = plot_pareto(rows, out / "pareto.png", title=f"{root.name}: {len(rows)} jobs, Pareto front of AUC@10 vs latency")
    outputs["png"] = str(png) if png else None
    front = sorted((r for r in rows if r["pareto"]), key=lambda r: r["latency_ms"])
    keep = ("rank", "job", "config", "model", "encoder", "descriptor_dim", "encoder_conf", "parameters", "flops", "auc5", "auc10", "auc20",
            "latency_ms", "latency", "pareto", "steps", "train_wall_s", "best_val_auc10", "overrides", "latency_error", "host",
            "metrics_path")
    summary = {
        "root": str(root),
        "command": command,
        "jobs": len(rows),
        "with_latency": sum(r.get("latency_ms") is not None for r in rows),
        "best": rows[0]["job"] if rows and rows[0].get("auc10") is not None else None,
        "pareto": [r["job"] for r in front],
        "leaderboard": [{k: r.get(k) for k in keep} for r in rows],
        "outputs": outputs,
    }
    outputs["json"] = str(out / "search_summary.json")
    write_json(out / "search_summary.json", summary)
    return summary
