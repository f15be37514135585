"""Per-job metrics of an architecture search: ``metrics.json`` beside every job's checkpoint.

``python train.py`` calls :func:`job_metrics` at the end of every job (single runs and sweeps
alike) and writes the result atomically with :func:`write_json`. A ``metrics.json`` holds:

* ``overrides``: the Hydra overrides that define the job (``HydraConfig.get().overrides.task``);
* the architecture (``model``, ``encoder``, ``encoder_conf``, ``descriptor_dim``, ``mcts``);
* ``parameters`` and ``flops`` (one image at the latency resolution, see below; the convention of
  :func:`aerovis_train.models.count_flops`: 2 FLOPs per multiply-add);
* ``auc5``, ``auc10``, ``auc20`` (percent): the relative-pose AUC of the selected checkpoint (the best, or the last with ``weights=last``)
  on the validation split, re-measured with the training job's own validation code;
* ``latency_ms``: ONNX Runtime FP32 latency (median) of a stereo batch of 2 MCTS at 424x240,
  cropped down to the model's size multiple (400x240 for MaxViT, whose sides must be multiples
  of 40; ``latency.resolution`` says what was measured), from a bundle exported in the job with
  :func:`aerovis_export.export_bundle` and timed by :func:`aerovis_slam.bundle.benchmark_bundle`.

Latency depends on the machine and on its load: ``latency.threads`` and ``host`` say where it
was measured; compare latencies only within one search on one machine. ``environment``
(:func:`aerovis_slam.environment.software_versions`) names the commit and library versions.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

from aerovis_slam.environment import host_description, software_versions
from aerovis_slam.fileio import atomic_write_json, atomic_write_text

METRICS_FORMAT = "aerovis-metrics/1"
METRICS_FILE = "metrics.json"
LATENCY_HEIGHT, LATENCY_WIDTH, LATENCY_BATCH = 240, 424, 2


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write JSON atomically (temporary name, then ``os.replace``): readers never see half a file."""
    return atomic_write_json(path, data, default=_json_default)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write text atomically (temporary name, then ``os.replace``)."""
    return atomic_write_text(path, text)


def _json_default(obj):
    # numpy scalars and paths, which json cannot serialise by itself
    if hasattr(obj, "item"):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def latency_resolution(size_multiple: int, height: int = LATENCY_HEIGHT, width: int = LATENCY_WIDTH) -> tuple[int, int]:
    """(height, width) actually measured: the requested size cropped down to ``size_multiple``.

    Example:
        >>> latency_resolution(8), latency_resolution(40)
        ((240, 424), (240, 400))
    """
    h, w = height // size_multiple * size_multiple, width // size_multiple * size_multiple
    if h == 0 or w == 0:
        raise ValueError(f"{width}x{height} is smaller than the model's size multiple {size_multiple}")
    return h, w


def export_fp32_bundle(model, out_dir: str | os.PathLike, *, calibration: str | os.PathLike, model_cfg: dict | None = None,
                       height: int = LATENCY_HEIGHT, width: int = LATENCY_WIDTH, batch: int = LATENCY_BATCH) -> tuple[Path, dict]:
    """Export ``model`` (a KeypointNet) to an FP32 bundle for timing, at ``height x width`` cropped
    down to the model's size multiple, with :func:`aerovis_export.export_bundle`.

    Args:
        calibration: a few MCTS of this data source (a sequence, a folder or a preset) set the
            bundle's int8 descriptor scale; give data the caller already has (a validation sequence),
            so that no preset is generated for it. No parity run: the bundle is only timed.
        model_cfg: the model's config (for the bundle's metadata; derived from the model if None).
    Returns:
        (bundle directory, ``{"resolution": [W, H], "requested": [W, H], "batch", "precision", "note"}``).
    """
    from aerovis_export import export_bundle

    h, w = latency_resolution(int(model.size_multiple), height, width)
    note = None
    if (h, w) != (height, width):
        note = (f"{width}x{height} cropped to {w}x{h}: {getattr(model, 'encoder_name', 'this encoder')} needs sides that are "
                f"multiples of {model.size_multiple}")
    was_training = model.training
    try:
        bundle = export_bundle(model.eval(), Path(out_dir), precision="fp32", height=h, width=w, batch=batch, model_cfg=model_cfg,
                               calibration=calibration, calibration_frames=4, parity_data=None, force=True, progress=False)
    finally:
        model.train(was_training)
    return Path(bundle), {"resolution": [w, h], "requested": [width, height], "batch": int(batch), "precision": "fp32", "note": note}


def latency_record(stats: dict, info: dict, *, threads: int | None, bundle: str | None) -> dict:
    """The ``latency`` entry of ``metrics.json`` from :func:`aerovis_slam.bundle.benchmark_bundles` figures
    and the export ``info`` of :func:`export_fp32_bundle`.

    Returns:
        ``{"latency_ms" (median), "latency_ms_p90", "total_ms_p50" (with post-processing), "resolution": [W, H],
        "requested": [W, H], "batch", "precision", "runtime", "threads", "repeats", "block" (timed runs per
        bundle between switches), "loadavg", "note", "bundle"}``
        (times in ms; ``loadavg``: the machine's 1-minute load average after timing, to judge contention).
    """
    import onnxruntime

    return {
        "latency_ms": float(stats["latency_ms_p50"]),
        "latency_ms_p90": float(stats["latency_ms_p90"]),
        "total_ms_p50": float(stats["total_ms_p50"]),
        **info,
        "runtime": f"onnxruntime {onnxruntime.__version__}",
        "threads": threads,
        "repeats": int(stats["repeats"]),
        "block": stats.get("block"),
        "loadavg": round(os.getloadavg()[0], 2),
        "bundle": bundle,
    }


def onnx_latency(model, *, calibration: str | os.PathLike, model_cfg: dict | None = None, height: int = LATENCY_HEIGHT,
                 width: int = LATENCY_WIDTH, batch: int = LATENCY_BATCH, repeats: int = 20, warmup: int = 3, threads: int | None = None,
                 bundle_dir: str | os.PathLike | None = None) -> dict:
    """ONNX Runtime FP32 latency of ``model`` (a KeypointNet) on a (batch, C, H, W) input: exported by
    :func:`export_fp32_bundle`, timed by :func:`aerovis_slam.bundle.benchmark_bundle` (``repeats``
    timed runs after ``warmup``). ``bundle_dir`` keeps the bundle there (None: a temporary folder).

    Returns:
        :func:`latency_record`.
    """
    import tempfile

    from aerovis_slam.bundle import benchmark_bundle

    with tempfile.TemporaryDirectory(prefix="aerovis-latency-") as tmp:
        out = Path(bundle_dir) if bundle_dir is not None else Path(tmp) / "bundle"
        bundle, info = export_fp32_bundle(model, out, calibration=calibration, model_cfg=model_cfg, height=height, width=width, batch=batch)
        stats = benchmark_bundle(bundle, repeats=repeats, warmup=warmup, threads=threads)
    return latency_record(stats, info, threads=threads, bundle=str(bundle) if bundle_dir is not None else None)


def job_metrics(model, model_cfg: dict, *, val: dict | None, overrides: list[str] | None, calibration: str | os.PathLike,
                metrics_cfg: dict | None = None, extra: dict | None = None, bundle_dir: str | os.PathLike | None = None) -> dict:
    """Everything ``metrics.json`` holds for one job (see the module docstring).

    Args:
        model: the trained KeypointNet (its selected weights; only the architecture matters for
            parameters, FLOPs and latency).
        model_cfg: the resolved ``cfg.model``.
        val: validation summary of the selected checkpoint (``auc5``, ``auc10``, ``auc20``, ``pairs``...)
            or None when the job never validated.
        overrides: the Hydra overrides that define the job.
        calibration: data for the exported bundle's descriptor scale (see :func:`onnx_latency`).
        metrics_cfg: ``cfg.metrics`` (``latency``, ``height``, ``width``, ``batch``, ``repeats``, ``threads``).
        extra: more fields (steps, wall time, paths) copied in as they are.
        bundle_dir: where the latency bundle is kept (None: not kept).
    Returns:
        A JSON-ready dict. A failed latency measurement is recorded (``latency_ms`` None and
        ``latency_error`` with the reason) rather than raised: the trained job stays usable.
    """
    from aerovis_train.models import count_flops, count_parameters

    mc = {"latency": True, "height": LATENCY_HEIGHT, "width": LATENCY_WIDTH, "batch": LATENCY_BATCH, "repeats": 20, "threads": None,
          **(metrics_cfg or {})}
    h, w = latency_resolution(int(model.size_multiple), int(mc["height"]), int(mc["width"]))
    val = val or {}
    out: dict[str, Any] = {
        "format": METRICS_FORMAT,
        "overrides": list(overrides) if overrides is not None else None,
        "model": model_cfg.get("name"),
        "encoder": model_cfg.get("encoder"),
        "encoder_conf": model_cfg.get("encoder_conf") or {},
        "descriptor_dim": int(model_cfg["descriptor_dim"]),
        "head_width": int(model_cfg.get("head_width") or 256),
        "mcts": model_cfg.get("mcts"),
        "size_multiple": int(model.size_multiple),
        "parameters": count_parameters(model),
        "flops": count_flops(model, (1, int(model.in_channels), h, w)),
        "flops_input": [1, int(model.in_channels), h, w],
        "auc5": val.get("auc5"),
        "auc10": val.get("auc10"),
        "auc20": val.get("auc20"),
        "val_pairs": val.get("pairs"),
        "val_matches": val.get("matches"),
        "latency_ms": None,
        "latency": None,
        "latency_error": None,
        "host": host_description(),
        "environment": software_versions(training=True),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    if mc["latency"]:
        try:
            lat = onnx_latency(model, model_cfg=model_cfg, calibration=calibration, height=int(mc["height"]), width=int(mc["width"]), batch=int(mc["batch"]),
                               repeats=int(mc["repeats"]), threads=mc["threads"], bundle_dir=bundle_dir)
            out["latency"], out["latency_ms"] = lat, lat["latency_ms"]
        except Exception as exc:  # noqa: BLE001 - any export/runtime failure is recorded, the job's training is kept
            out["latency_error"] = f"{type(exc).__name__}: {exc}"
    else:
        out["latency_error"] = "metrics.latency=false"  # the reason; readers say "not measured"
    out.update(extra or {})
    return out


def load_metrics(path: str | os.PathLike) -> dict:
    """Read one ``metrics.json``.

    Raises:
        DataError: unreadable file, or not an aerovis metrics file (wrong ``format``).
    """
    from aerovis_slam.errors import DataError

    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise DataError(path, f"not a readable metrics.json ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != METRICS_FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise DataError(path, f"field 'format' should be {METRICS_FORMAT!r}, got {got!r}")
    return data


def retime_jobs(root: str | os.PathLike, *, repeats: int = 20, warmup: int = 3, threads: int | None = None) -> list[dict]:
    """Re-measure the latency of every job under ``root`` on this machine, all bundles in one run.

    Each job's latency was timed by the job itself, on whatever machine ran it and under whatever
    load it had (SLURM nodes of different kinds, a box shared with other jobs). This times the
    bundles the jobs kept (``latency.bundle``) again, round-robin in one
    :func:`aerovis_slam.bundle.benchmark_bundles` run, so that the latencies compare with each other.
    Each ``metrics.json`` is rewritten atomically: ``latency`` and ``latency_ms`` hold the new figures
    (with ``retimed`` = the time of measurement), ``latency_in_job`` keeps the job's own.

    Returns:
        One ``{"job", "latency_ms", "latency_in_job_ms"}`` per retimed job.
    Raises:
        DataError: no job under ``root`` kept its bundle (``metrics.keep_bundle=false``, or no latency measured).
    """
    from aerovis_slam.bundle import benchmark_bundles
    from aerovis_slam.errors import DataError

    root = Path(root)
    jobs = []
    for p in sorted(root.rglob(METRICS_FILE)):
        m = load_metrics(p)
        bundle = (m.get("latency") or {}).get("bundle")
        if bundle and (Path(bundle) / "model.onnx").is_file():
            jobs.append((p, m, Path(bundle)))
    if not jobs:
        raise DataError(root, f"no {METRICS_FILE} under it names a kept bundle (latency.bundle) to time again")
    stats = benchmark_bundles([b for _, _, b in jobs], repeats=repeats, warmup=warmup, threads=threads)
    out = []
    for (p, m, bundle), st in zip(jobs, stats):
        old = m["latency"]
        info = {k: old.get(k) for k in ("resolution", "requested", "batch", "precision", "note")}
        new = {**latency_record(st, info, threads=threads, bundle=str(bundle)), "retimed": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        m["latency_in_job"] = m.get("latency_in_job") or old
        m["latency"], m["latency_ms"] = new, new["latency_ms"]
        write_json(p, m)
        out.append({"job": p.parent.relative_to(root).as_posix(), "latency_ms": new["latency_ms"],
                    "latency_in_job_ms": m["latency_in_job"]["latency_ms"]})
    return out
