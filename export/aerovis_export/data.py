"""Data for export: calibration MCTS (INT8 ranges, descriptor scale) and training pairs (QAT).

Both come from the project's own pipelines, so exported models see exactly what training saw:
calibration MCTS from :func:`aerovis_train.data.compute_mcts` on canonical sequences, training pairs
from :func:`aerovis_train.training.make_dataset` (labels, correspondences, crops).

A data source is a simulator preset name (``tiny``, ``bench``, ``train``: generated into the cache on
first use), a folder of canonical ``.h5`` sequences, or one ``.h5`` file.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from aerovis_slam.errors import DataError
from aerovis_slam.io.sequence import Sequence
from aerovis_slam.mcts import events_per_window


def resolve_sequences(source: str | Path) -> list[Path]:
    """Sequence files of a data source (preset name, folder of ``.h5``, or one ``.h5``).

    Raises:
        DataError: no such file or folder, or a folder without sequences.
    """
    from aerovis_train.eval.cli import _sequences  # the evaluation's resolver: one rule for every tool

    return _sequences(str(source))


def _fit(size: int, limit: int, multiple: int) -> int:
    return min(size, limit) // multiple * multiple


def calibration_mcts(source: str | Path, mcts_kind: str, mcts_params, *, frames: int, height: int, width: int,
                     size_multiple: int, dynamic_hw: bool, cam: str | None = None) -> list[np.ndarray]:
    """``frames`` MCTS (C, h, w) float32 spread evenly over the sequences and their duration.

    Each sequence contributes about ``frames / n_sequences`` surfaces at evenly spaced times after
    the MCTS warm-up (the longest window filled), alternating between its cameras unless ``cam`` is
    given. Surfaces are centre-cropped to one common size: the export resolution when the bundle is
    not ``dynamic_hw`` (sequences smaller than it are skipped), else the largest multiples of
    ``size_multiple`` that fit every sequence and the export resolution.

    Raises:
        DataError: no sequence is large enough, or no events.
    """
    from aerovis_train.data import MctsSpec, compute_mcts

    spec = MctsSpec(mcts_kind, tuple(float(p) for p in mcts_params))
    paths = resolve_sequences(source)
    usable: list[tuple[Path, list[str]]] = []
    crop_h, crop_w = height, width
    for p in paths:
        with Sequence(p) as seq:
            cams = [c for c in seq.cameras if seq.num_events(c) > 0 and (cam is None or c == cam)]
            sizes = [seq.sensor_size(c) for c in cams]
        if not cams:
            continue
        w = min(s[0] for s in sizes)
        h = min(s[1] for s in sizes)
        if dynamic_hw:
            if _fit(h, height, size_multiple) == 0 or _fit(w, width, size_multiple) == 0:
                continue
            crop_h, crop_w = min(crop_h, _fit(h, height, size_multiple)), min(crop_w, _fit(w, width, size_multiple))
        elif h < height or w < width:
            continue
        usable.append((p, cams))
    if not usable:
        raise DataError(source, f"no sequence with events is at least {height}x{width} (the bundle's fixed resolution)"
                        if not dynamic_hw else f"no sequence with events is at least {size_multiple}x{size_multiple}")
    per_seq = max(1, math.ceil(frames / len(usable)))
    out: list[np.ndarray] = []
    for p, cams in usable:
        with Sequence(p) as seq:
            for i in range(per_seq):
                if len(out) >= frames:
                    break
                c = cams[i % len(cams)]
                w, h = seq.sensor_size(c)
                t0, t1 = seq.time_range(c)
                if spec.kind == "ne":
                    n_warm = min(int(events_per_window(spec.params, w, h).max()), seq.num_events(c) - 1)
                    t0 = int(seq.events_by_index(c, n_warm, n_warm + 1).t[0])
                else:
                    t0 = min(t1, t0 + int(max(spec.params) * 1000))
                tau = int(round(t0 + (t1 - t0) * (i + 1) / (per_seq + 1)))
                m = compute_mcts(seq, c, tau, spec)
                y0, x0 = (h - crop_h) // 2, (w - crop_w) // 2
                out.append(np.ascontiguousarray(m[:, y0:y0 + crop_h, x0:x0 + crop_w], np.float32))
    return out


def qat_batches(source: str | Path, model_cfg: dict, size_multiple: int, *, steps: int, batch_size: int | None = None,
                overrides: list[str] | None = None, seed: int = 0, crop: tuple[int, int] | None = None):
    """A DataLoader of ``steps`` training batches (pairs with labels and correspondences) for QAT.

    The training config is ``conf/config.yaml`` composed with ``overrides`` (e.g. ``data.supervision=epipolar``,
    ``data.num_workers=0``), its model section replaced by ``model_cfg``; the crop is ``data.crop``
    shrunk to fit the smallest sequence and to multiples of ``size_multiple``, or exactly ``crop`` (a
    graph of fixed resolution trains at that resolution).

    Returns:
        (loader, settings dict for the report).
    """
    from omegaconf import OmegaConf

    from aerovis_train.benchmarks import compose_config
    from aerovis_train.data import make_loader
    from aerovis_train.training import loader_workers, make_dataset

    paths = resolve_sequences(source)
    cfg = compose_config(list(overrides or []) + [f"seed={int(seed)}"])
    OmegaConf.set_struct(cfg, False)
    cfg.model = OmegaConf.create(model_cfg)
    min_w = min_h = None
    for p in paths:
        with Sequence(p) as seq:
            for c in seq.cameras:
                w, h = seq.sensor_size(c)
                min_w, min_h = min(w, min_w or w), min(h, min_h or h)
    if crop is not None:
        if crop[0] > min_h or crop[1] > min_w:
            raise DataError(source, f"QAT at a fixed {crop[0]}x{crop[1]} needs sequences at least that large; the smallest is {min_h}x{min_w}")
        crop = [int(crop[0]), int(crop[1])]
    else:
        crop = [int(v) for v in cfg.data.crop] if cfg.data.get("crop") else [min_h, min_w]
        crop = [_fit(crop[0], min_h, size_multiple), _fit(crop[1], min_w, size_multiple)]
    if min(crop) == 0:
        raise DataError(source, f"sequences of {min_h}x{min_w} pixels are smaller than one {size_multiple}x{size_multiple} input")
    cfg.data.crop = crop
    bs = int(batch_size or cfg.data.batch_size)
    ds = make_dataset(cfg, paths, size_multiple, samples_per_epoch=max(1, steps) * bs)
    loader = make_loader(ds, bs, loader_workers(cfg), shuffle=True)
    settings = {"data": str(source), "sequences": len(paths), "crop": crop, "batch_size": bs,
                "supervision": str(cfg.data.supervision), "overrides": list(overrides or [])}
    return loader, settings
