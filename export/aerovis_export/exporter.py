"""``export_bundle``: a trained keypoint network -> a model bundle directory (see :mod:`aerovis_slam.bundle`).

Stages: load the checkpoint -> float32 ONNX (opset 18, dense outputs, dynamic batch and, where the
exporter proves it, dynamic H/W) -> precision (FP16 conversion, or INT8 by QAT / PTQ) -> descriptor
int8 scale from calibration MCTS -> ``metadata.json`` -> validation through the runtime loader ->
``parity.json`` against the PyTorch model -> atomic rename of ``DIR.partial`` to ``DIR`` -> optional
TensorRT engine.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from tqdm.auto import tqdm

from aerovis_slam.bundle import (
    BUNDLE_FORMAT,
    BUNDLE_FORMAT_VERSION,
    ENGINE_NAME,
    INPUT_NAME,
    METADATA_NAME,
    ONNX_NAME,
    OUTPUT_NAMES,
    PARITY_NAME,
    PRECISIONS,
    TARGETS,
    Bundle,
    file_sha256,
)
from aerovis_slam.errors import DataError
from aerovis_slam.fileio import atomic_write_json
from aerovis_slam.keypoints import extract_keypoints
from aerovis_slam.mcts import CHANNEL_ORDER, channel_names

from .onnx_tools import OPSET, check_onnx, convert_fp16, example_input, export_onnx

DEFAULT_QAT_STEPS = 200


def aerovis_version() -> str:
    """The installed aerovis version (package metadata, else the runtime's ``__version__``)."""
    try:
        from importlib.metadata import version

        return version("aerovis")
    except Exception:  # noqa: BLE001 - not installed as a distribution (e.g. a source checkout on sys.path)
        from aerovis_slam import __version__

        return __version__


def _json_safe(d: Mapping[str, Any]) -> dict:
    out = {}
    for k, v in d.items():
        try:
            json.dumps(v)
            out[k] = v
        except TypeError:
            out[k] = str(v)
    return out


def _load(model_or_name, model_cfg: dict | None):
    """(model in eval mode, model_cfg, source dict) from a name/path or a KeypointNet."""
    from aerovis_train.checkpoints import load_model
    from aerovis_train.models import KeypointNet

    if isinstance(model_or_name, (str, os.PathLike)):
        from aerovis_train.checkpoints import SHIPPED

        try:
            model, cfg, meta = load_model(model_or_name)
        except RuntimeError as exc:  # load_state_dict: tensors of another shape under the same names
            first = str(exc).strip().splitlines()
            raise DataError(model_or_name, f"weights do not fit the model its config describes ({first[-1].strip() if first else exc})") from None
        # a shipped name is recorded as such: the absolute path of one installation means nothing elsewhere
        shipped = str(model_or_name) in SHIPPED
        source = _json_safe({"checkpoint": f"{model_or_name} (shipped: aerovis_train/weights/{model_or_name}.pt)" if shipped else meta.get("path"), "sha256": meta.get("sha256"), "global_step": meta.get("global_step"),
                             "epoch": meta.get("epoch"), "val_auc10": meta.get("val_auc10")})
        where = meta.get("path")
    elif isinstance(model_or_name, KeypointNet):
        model = model_or_name.eval()
        cfg = dict(model_cfg) if model_cfg else {"name": model.name, "encoder": model.encoder_name, "in_channels": model.in_channels,
                                                 "descriptor_dim": model.descriptor_dim, "head_width": model.head_width, "mcts": model.mcts}
        source = {"checkpoint": None, "sha256": None, "note": "in-memory model"}
        where = None
    else:
        raise TypeError(f"model_or_name must be a checkpoint path, a shipped name or a KeypointNet, not {type(model_or_name).__name__}")
    if not cfg.get("mcts"):
        raise DataError(where, f"model config of {cfg.get('name')!r} has no `mcts` section: the bundle must say which time surface it takes")
    return model, cfg, source, where


def _descriptor_scale(session, frames: list[np.ndarray], *, threshold: float, nms_radius: int, border: int) -> tuple[float, float]:
    """127 / the largest absolute descriptor component at detected keypoints on calibration MCTS.

    Descriptors of the deployed model (this session) at its own keypoints (top-k = max(H, W) / 2),
    i.e. exactly what the runtime quantises. Returns (scale, max abs component).
    """
    peak = 0.0
    for x in frames:
        scores, grid = session.run(list(OUTPUT_NAMES), {INPUT_NAME: np.asarray(x, np.float32)[None]})
        kp = extract_keypoints(scores[0], grid[0], nms_radius=nms_radius, threshold=threshold, top_k=max(x.shape[-2:]) // 2, border=border)
        vals = kp.descriptors if len(kp) else grid[0].reshape(grid.shape[1], -1).T  # no keypoint at all: the dense grid
        if len(vals):
            peak = max(peak, float(np.abs(vals).max()))
    if not np.isfinite(peak) or peak <= 0:
        raise DataError(None, "descriptor scale: the calibration MCTS gave no finite non-zero descriptor")
    return 127.0 / peak, peak


def _ort_session(path: Path):
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])


def _write_json(path: Path, obj: dict) -> None:
    atomic_write_json(path, obj, indent=1)


def export_bundle(
    model_or_name,
    out_dir: str | os.PathLike,
    *,
    precision: str = "fp32",
    height: int = 240,
    width: int = 424,
    batch: int = 2,
    target: str = "cpu",
    ptq: bool = False,
    qat_steps: int = DEFAULT_QAT_STEPS,
    qat_lr: float = 1e-5,
    qat_batch: int | None = None,
    qat_overrides: list[str] | None = None,
    calibration: str | os.PathLike = "train",
    calibration_frames: int = 64,
    parity_data: str | os.PathLike | None = "bench",
    parity_pairs: int | None = 40,
    parity_rate_hz: float | None = 20.0,
    parity_max_dt_s: float = 2.0,
    parity_max_angle_deg: float = 45.0,
    dynamic_hw: bool = True,
    reduce_range: bool = False,
    threshold: float = 0.01,
    nms_radius: int = 2,
    border: int = 4,
    engine: bool = False,
    timing_cache: str | os.PathLike | None = None,
    force: bool = False,
    model_cfg: dict | None = None,
    seed: int = 0,
    progress: bool = True,
) -> Path:
    """Export a keypoint network to a bundle directory; returns the directory.

    Args:
        model_or_name: shipped name (``superlite``...), a slim ``.pt`` / ``train.py`` ``.ckpt``, or a KeypointNet.
        out_dir: bundle directory to create (built as ``out_dir.partial``, then renamed).
        precision: ``fp32``, ``fp16`` (half weights, float IO, softmax/normalisation in FP32) or ``int8``.
        height, width: export resolution (multiples of the model's size multiple); with ``dynamic_hw``
            the graph also takes other multiples.
        batch: nominal batch (2: a stereo pair); the ONNX batch axis is dynamic.
        target: ``cpu`` or ``tensorrt`` (INT8 flavour: U8S8 or symmetric S8S8).
        ptq: INT8 by ONNX Runtime post-training quantisation instead of QAT.
        qat_steps, qat_lr, qat_batch, qat_overrides: QAT fine-tuning (see :func:`aerovis_export.quantize.quantize_qat`
            and :func:`aerovis_export.data.qat_batches`).
        calibration: data source (preset / folder / ``.h5``) of QAT pairs, INT8 calibration and the descriptor scale.
        calibration_frames: calibration MCTS count.
        parity_data: held-out data source for ``parity.json`` (None: parity not computed, recorded as such).
        parity_pairs, parity_rate_hz, parity_max_dt_s, parity_max_angle_deg: the evaluation protocol for parity.
        dynamic_hw: try a graph that takes any multiple of the size multiple.
        reduce_range: 7-bit INT8 variant for CPUs without VNNI (see :mod:`aerovis_export.quantize`).
        threshold, nms_radius, border: runtime post-processing recorded in the metadata.
        engine: build a TensorRT engine into the bundle afterwards.
        timing_cache: TensorRT timing cache file (default under ``~/.cache/aerovis/tensorrt``).
        force: replace an existing ``out_dir``.
        model_cfg: config of an in-memory KeypointNet (ignored for checkpoints).
    Raises:
        DataError: bad checkpoint, resolution, data source, or an existing ``out_dir`` without ``force``.
        aerovis_export.tensorrt.EngineUnavailable: ``engine`` without TensorRT or GPU (the bundle is complete).
    """
    t_start = time.time()
    out = Path(out_dir)
    if precision not in PRECISIONS:
        raise DataError(None, f"--precision must be one of {list(PRECISIONS)}, not {precision!r}")
    if target not in TARGETS:
        raise DataError(None, f"--target must be one of {list(TARGETS)}, not {target!r}")
    if batch < 1:
        raise DataError(None, f"--batch must be at least 1, got {batch}")
    if out.exists() and not force:
        raise DataError(out, "exists already; pass --force to replace it")
    model, cfg, source, where = _load(model_or_name, model_cfg)
    m = int(model.size_multiple)
    for axis, v in (("height", height), ("width", width)):
        if v <= 0 or v % m:
            raise DataError(where, f"--{axis} {v} is not a positive multiple of {m}: {cfg['name']} ({cfg['encoder']}) takes sides that "
                                   f"are multiples of {m} (e.g. {max(m, v // m * m)})")
    mcts = cfg["mcts"]
    mcts_params = [float(p) for p in mcts.get("params") or []]
    torch.manual_seed(seed)

    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)
    partial.mkdir(parents=True)
    qat = precision == "int8" and not ptq
    stages = ([] if qat else ["onnx"]) + ({"fp16": ["fp16"], "int8": ["calibrate", "ptq" if ptq else "qat"]}.get(precision, []))
    stages += ["scale", "validate"]
    stages += ["parity"] if parity_data is not None else []
    bar = tqdm(total=len(stages), desc=f"export {cfg['name']} {precision}", unit="stage", file=sys.stderr, disable=not progress)

    def stage(name: str) -> None:
        bar.set_postfix_str(name)

    try:
        # -- float32 graph ---------------------------------------------------------------------
        from aerovis_train.models import ExportWrapper

        fp32 = partial / "fp32.onnx"
        dyn, fallback = dynamic_hw, None
        if not qat:  # (QAT traces and exports its own quantised graph)
            stage("onnx fp32")
            _, dyn, fallback = export_onnx(ExportWrapper(model), fp32, in_channels=model.in_channels, height=height, width=width,
                                           size_multiple=m, dynamic_hw=dynamic_hw)
            bar.update()
        onnx_path = partial / ONNX_NAME
        quant: dict | None = None
        calib: list[np.ndarray] | None = None

        def calib_frames() -> list[np.ndarray]:
            from .data import calibration_mcts

            return calibration_mcts(calibration, mcts["kind"], mcts_params, frames=calibration_frames, height=height, width=width,
                                    size_multiple=m, dynamic_hw=dyn)

        if precision == "fp32":
            os.replace(fp32, onnx_path)
        elif precision == "fp16":
            stage("fp16")
            kept = convert_fp16(fp32, onnx_path)
            quant = {"method": "fp16", "tool": "onnxconverter_common.float16.convert_float_to_float16(keep_io_types=True)",
                     "kept_float32": kept}
            bar.update()
        else:
            stage("calibration MCTS")
            calib = calib_frames()
            bar.update()
            if ptq:
                stage("PTQ")
                from .quantize import quantize_ptq

                quant = quantize_ptq(fp32, onnx_path, calib, target=target, reduce_range=reduce_range)
            else:
                stage("QAT")
                from .data import qat_batches
                from .quantize import quantize_qat

                loader, data_settings = qat_batches(calibration, cfg, m, steps=qat_steps, batch_size=qat_batch, overrides=qat_overrides,
                                                    seed=seed, crop=None if dynamic_hw else (height, width))
                quant, dyn = quantize_qat(model, cfg, onnx_path, target=target, height=height, width=width, size_multiple=m, dynamic_hw=dynamic_hw,
                                          train_batches=loader, steps=qat_steps, lr=qat_lr, calibration=calib[:16],
                                          reduce_range=reduce_range, progress=progress)
                quant["training_data"] = data_settings
            bar.update()
        fp32.unlink(missing_ok=True)
        onnx_model = check_onnx(onnx_path)
        if onnx_model.opset_import[0].version != OPSET:
            raise DataError(onnx_path, f"exported with opset {onnx_model.opset_import[0].version}, expected {OPSET}")

        # -- descriptor scale and a direct check against torch on the example input ------------
        stage("descriptor scale")
        session = _ort_session(onnx_path)
        if calib is None:
            calib = calib_frames()
        scale, peak = _descriptor_scale(session, calib, threshold=threshold, nms_radius=nms_radius, border=border)
        example = example_input(model.in_channels, height, width, m, dynamic_hw=False)  # a stereo batch at the export size
        with torch.no_grad():
            ref = ExportWrapper(model)(example)
        got = session.run(list(OUTPUT_NAMES), {INPUT_NAME: example.numpy()})
        check = {name: float(np.abs(g - r.numpy()).max()) for name, g, r in zip(OUTPUT_NAMES, got, ref)}
        if precision == "fp32" and max(check.values()) > 1e-3:
            # float32 graphs differ from torch only by summation order (~1e-7); more is an exporter bug
            raise DataError(onnx_path, f"the float32 ONNX model disagrees with torch on the example input: max abs diff {check}")
        bar.update()

        # -- metadata, validated by the runtime's own loader -------------------------------------
        stage("validate")
        meta = {
            "format": BUNDLE_FORMAT, "format_version": BUNDLE_FORMAT_VERSION,
            "name": cfg["name"], "encoder": cfg["encoder"], "in_channels": int(model.in_channels),
            "mcts": {"kind": mcts["kind"], "params": mcts_params, "channel_order": CHANNEL_ORDER,
                     "channels": channel_names(mcts["kind"], mcts_params)},
            "height": int(height), "width": int(width), "batch": int(batch), "cell": int(model.cell), "size_multiple": m,
            "dynamic_hw": bool(dyn), "dynamic_hw_fallback_reason": fallback if dynamic_hw and not dyn else None,
            "descriptor_dim": int(model.descriptor_dim), "descriptor_scale": scale, "descriptor_max_abs": peak,
            "threshold": float(threshold), "nms_radius": int(nms_radius), "border": int(border),
            "precision": precision, "target": target, "quantization": quant,
            "inputs": {INPUT_NAME: ["batch", int(model.in_channels), "height", "width"]},
            "outputs": {"scores": ["batch", "height", "width"], "descriptors": ["batch", int(model.descriptor_dim), "height/8", "width/8"]},
            "opset": OPSET, "source": source, "model_config": _json_safe(cfg),
            "files": {ONNX_NAME: file_sha256(onnx_path)},
            "export_check_max_abs_diff": check,
            "aerovis_version": aerovis_version(), "torch_version": torch.__version__, "onnx_version": onnx.__version__,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        }
        _write_json(partial / METADATA_NAME, meta)
        Bundle.load(partial)
        bar.update()

        # -- parity against torch -------------------------------------------------------------
        if parity_data is not None:
            stage("parity")
            from .data import resolve_sequences
            from .parity import compute_parity

            par = compute_parity(model, cfg, partial, resolve_sequences(parity_data), rate_hz=parity_rate_hz, max_pairs=parity_pairs,
                                 max_dt_s=parity_max_dt_s, max_angle_deg=parity_max_angle_deg, progress=progress)
            par["data"] = str(parity_data)
            bar.update()
        else:
            par = {"computed": False, "reason": "no parity data given (--no-parity)"}
        _write_json(partial / PARITY_NAME, par)
    except BaseException:
        bar.close()
        shutil.rmtree(partial, ignore_errors=True)
        raise
    bar.close()

    # -- atomic publication -------------------------------------------------------------------
    if out.exists():
        old = out.with_name(out.name + ".old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(out, old)
        os.replace(partial, out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(partial, out)
    meta["export_wall_s"] = round(time.time() - t_start, 1)
    _write_json(out / METADATA_NAME, meta)  # files unchanged: the hash still holds
    if engine:
        add_engine(out, timing_cache=timing_cache)
    return out


def add_engine(bundle_dir: str | os.PathLike, *, timing_cache: str | os.PathLike | None = None) -> dict:
    """Build ``model.engine`` into an existing bundle and record it in its metadata.

    Raises:
        aerovis_export.tensorrt.EngineUnavailable: no TensorRT or no CUDA GPU (the bundle is left as it was).
    """
    from .tensorrt import build_engine

    bundle = Bundle.load(bundle_dir)
    info = build_engine(bundle.onnx_path, bundle.path / ENGINE_NAME, precision=bundle.precision, batch=bundle.batch,
                        in_channels=bundle.in_channels, height=bundle.height, width=bundle.width, timing_cache=timing_cache)
    meta = dict(bundle.meta)
    meta["files"] = {**meta["files"], ENGINE_NAME: file_sha256(bundle.path / ENGINE_NAME)}
    meta["tensorrt"] = info
    _write_json(bundle.path / METADATA_NAME, meta)
    return info
