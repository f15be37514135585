"""INT8 quantisation: quantisation-aware fine-tuning (torchao PT2E) and post-training static
quantisation (ONNX Runtime), both ending in a Q/DQ ONNX graph.

Two flavours by target (REFERENCE.md section 7):

* ``cpu``: uint8 activations (affine, with zero-points) and int8 per-channel symmetric weights (U8S8),
  the fast path of ONNX Runtime on AVX2 CPUs (fused QLinearConv + ReLU);
* ``tensorrt``: symmetric int8 activations and weights, every zero-point 0 (TensorRT rejects others).

QAT flow: ``torch.export`` (training-mode graph, dynamic batch/H/W) -> ``prepare_qat_pt2e`` (fake
quantisers, Conv+BatchNorm fused for QAT) -> BatchNorm statistics frozen -> observer warm-up on
calibration MCTS -> ``steps`` optimiser steps of the project's own training loss
(:meth:`aerovis_train.module.KeypointModule._losses`) on training pairs -> ``convert_pt2e``
(BatchNorm folded, Q/DQ ops) -> ``torch.onnx.export(dynamo=True, opset_version=18)``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import sys
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import nn
from tqdm.auto import tqdm

from aerovis_slam.bundle import INPUT_NAME
from aerovis_slam.errors import DataError

from .onnx_tools import ensure_node_names, example_input, export_onnx, head_output_convolutions, postprocess_nodes, quantization_summary, quiet_exporter

TARGETS = ("cpu", "tensorrt")


class QuantizationError(RuntimeError):
    """A quantisation step failed (the message says which and why)."""


def _check_target(target: str) -> None:
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}, not {target!r}")


def verify_flavour(model: onnx.ModelProto, target: str, where: str | os.PathLike) -> dict:
    """Check that a Q/DQ graph is the flavour ``target`` needs; returns :func:`quantization_summary`.

    Raises:
        QuantizationError: no Q/DQ at all, uint8 or non-zero zero-points for ``tensorrt``, no uint8
            activations for ``cpu``.
    """
    s = quantization_summary(model)
    if s["quantize_linear"] == 0:
        raise QuantizationError(f"{where}: no QuantizeLinear in the graph: nothing was quantised")
    if target == "tensorrt" and (s["nonzero_zero_points"] or "uint8" in s["activation_types"] + s["weight_types"]):
        raise QuantizationError(f"{where}: TensorRT needs symmetric int8 (zero-point 0), got {s}")
    if target == "cpu" and "uint8" not in s["activation_types"]:
        raise QuantizationError(f"{where}: the cpu flavour needs uint8 activations, got {s}")
    return s


# ------------------------------------------------------------------------------------------
# post-training static quantisation (ONNX Runtime)
# ------------------------------------------------------------------------------------------
def quantize_ptq(src: str | os.PathLike, dst: str | os.PathLike, calibration: list[np.ndarray], *, target: str = "cpu",
                 per_channel: bool = True, reduce_range: bool = False) -> dict:
    """ONNX Runtime static quantisation (Q/DQ format) of a float32 bundle graph.

    Args:
        src: float32 ONNX model (input ``mcts``).
        dst: output path.
        calibration: MCTS arrays (C, H, W) or (B, C, H, W) whose activation ranges set the scales
            (MinMax calibration).
        target: ``cpu`` (U8S8) or ``tensorrt`` (symmetric S8S8).
        per_channel: per-output-channel weight scales.
        reduce_range: 7-bit weights (avoids int16 saturation of AVX2 ``vpmaddubsw`` on CPUs
            without VNNI, at some accuracy cost).
    Returns:
        ``{"method": "ptq", ...}`` settings and the :func:`quantization_summary` of the result.
    """
    from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    _check_target(target)
    if not calibration:
        raise DataError(None, "post-training quantisation needs calibration MCTS, got none")

    class _Reader(CalibrationDataReader):
        def __init__(self, arrays: list[np.ndarray]):
            self._it = iter(arrays)

        def get_next(self):
            x = next(self._it, None)
            if x is None:
                return None
            x = np.asarray(x, np.float32)
            return {INPUT_NAME: x[None] if x.ndim == 3 else x}

    with tempfile.TemporaryDirectory(prefix="aerovis-ptq-") as tmp:
        pre = Path(tmp) / "pre.onnx"
        # shape inference + graph optimisation first, as ONNX Runtime recommends for quantisation; its
        # symbolic shape inference fails on the H = 8 * hc dimensions of dynamic-resolution graphs
        # (TypeError in _broadcast_shapes), ONNX's own shape inference suffices for quantisation
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        model = ensure_node_names(onnx.load(str(pre)))
        onnx.save(model, str(pre))
        keep_float = postprocess_nodes(model)
        # and each head's last convolution: its outputs are the logits and raw descriptors, whose
        # ranges MinMax calibration quantises coarsely. For the SuperLitE with the full-resolution
        # detector branch (2026-12-06) quantising them cost 2.4 points of AUC@10 on `bench` (58.8 against
        # 61.2 %, keypoints within 1 px 0.960); kept in float, 61.4 % and 0.982
        keep_float += head_output_convolutions(model, keep_float)
        symmetric = target == "tensorrt"
        quantize_static(
            str(pre), str(dst), _Reader(calibration), quant_format=QuantFormat.QDQ, per_channel=per_channel,
            reduce_range=reduce_range, activation_type=QuantType.QInt8 if symmetric else QuantType.QUInt8,
            weight_type=QuantType.QInt8, nodes_to_exclude=keep_float, calibrate_method=CalibrationMethod.MinMax,
            extra_options={"ActivationSymmetric": symmetric, "WeightSymmetric": True},
        )
    summary = verify_flavour(onnx.load(str(dst)), target, dst)
    return {"method": "ptq", "tool": "onnxruntime.quantization.quantize_static", "format": "QDQ", "target": target,
            "activations": "int8 symmetric" if target == "tensorrt" else "uint8 affine",
            "weights": "int8 symmetric " + ("per-channel" if per_channel else "per-tensor") + (" (7-bit)" if reduce_range else ""),
            "calibration_frames": len(calibration), "calibrate_method": "MinMax", "kept_float": keep_float, **summary}


# ------------------------------------------------------------------------------------------
# quantisation-aware training (torchao PT2E)
# ------------------------------------------------------------------------------------------
class _DenseWithLogits(nn.Module):
    """``x -> (logits, scores, descriptors)`` of a KeypointNet (logits for the training loss)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor):
        return self.net.forward_dense(x)


class _AsKeypointNet(nn.Module):
    """Dict outputs of a traced ``(logits, scores, descriptors)`` graph, as the training loss expects."""

    def __init__(self, gm: nn.Module):
        super().__init__()
        self.gm = gm

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        logits, scores, descriptors = self.gm(x)
        return {"logits": logits, "scores": scores, "descriptors": descriptors}


class _DenseOnly(nn.Module):
    """``x -> (scores, descriptors)`` of a traced graph: the bundle's outputs."""

    def __init__(self, gm: nn.Module):
        super().__init__()
        self.gm = gm

    def forward(self, x: torch.Tensor):
        _, scores, descriptors = self.gm(x)
        return scores, descriptors


@contextlib.contextmanager
def _fold_only_present_convs() -> Iterator[None]:
    """Make ``convert_pt2e``'s Conv+BN folding skip convolution types absent from the graph.

    torchao 0.18 ``_fold_conv_bn_qat`` traces 24 match/replacement patterns with ``torch.export`` for
    each of conv1d, conv2d, conv_transpose1d and conv_transpose2d (96 exports, ~50 s on two busy
    cores) whatever the model holds. A pattern built on an op that is not in the graph cannot match,
    so skipping it changes nothing but the time; these networks only have conv2d.
    """
    import torch.nn.functional as F
    from torchao.quantization.pt2e import qat_utils

    ops = {F.conv1d: torch.ops.aten.conv1d, F.conv2d: torch.ops.aten.conv2d,
           F.conv_transpose1d: torch.ops.aten.conv_transpose1d, F.conv_transpose2d: torch.ops.aten.conv_transpose2d}
    original = qat_utils._fold_conv_bn_qat_helper

    def helper(m, conv_fn, example_inputs, is_cuda):
        packet = ops.get(conv_fn)
        if packet is not None and not any(getattr(n.target, "overloadpacket", None) is packet for n in m.graph.nodes):
            return m
        return original(m, conv_fn, example_inputs, is_cuda)

    qat_utils._fold_conv_bn_qat_helper = helper
    try:
        yield
    finally:
        qat_utils._fold_conv_bn_qat_helper = original


def qat_quantization_config(target: str, *, reduce_range: bool = False):
    """torchao PT2E QAT config for ``target`` (see the module docstring).

    ``cpu``: the x86 default (uint8 affine activations, int8 per-channel symmetric weights; ``reduce_range``
    gives 7-bit activations for CPUs without VNNI). ``tensorrt``: the same structure with symmetric
    int8 activations in [-127, 127] (zero-point 0) and weights in [-127, 127].
    """
    from torchao.quantization.pt2e.quantizer.x86_inductor_quantizer import get_default_x86_inductor_quantization_config

    _check_target(target)
    cfg = get_default_x86_inductor_quantization_config(is_qat=True, reduce_range=reduce_range)
    if target == "cpu":
        return cfg
    act = dataclasses.replace(cfg.input_activation, dtype=torch.int8, quant_min=-127, quant_max=127, qscheme=torch.per_tensor_symmetric)
    weight = dataclasses.replace(cfg.weight, quant_min=-127, quant_max=127)
    return dataclasses.replace(cfg, input_activation=act, output_activation=act, weight=weight)


def quantize_qat(net: nn.Module, model_cfg: dict, dst: str | os.PathLike, *, target: str, height: int, width: int,
                 size_multiple: int, dynamic_hw: bool, train_batches: Iterable[dict], steps: int, lr: float = 1e-5,
                 calibration: list[np.ndarray] | None = None, loss_cfg: dict | None = None, reduce_range: bool = False,
                 progress: bool = True) -> tuple[dict, bool]:
    """Quantisation-aware fine-tuning with torchao PT2E, exported as a Q/DQ ONNX graph.

    Args:
        net: the float KeypointNet (not modified: a copy is traced).
        model_cfg: its model config (``name``, ``encoder``, ... as in ``conf/model``).
        dst: output ONNX path.
        target: ``cpu`` or ``tensorrt``.
        height, width, size_multiple, dynamic_hw: as :func:`aerovis_export.onnx_tools.export_onnx`.
        train_batches: training pairs (dicts of :class:`aerovis_train.data.EventPairDataset` batches),
            cycled if shorter than ``steps``.
        steps: optimiser steps (0: calibration only, i.e. PT2E post-training quantisation).
        lr: Adam learning rate. Adam moves every weight by about ``lr`` per step whatever its gradient, so
            1e-5 over a few hundred steps stays within about one int8 weight step: fine-tuning around the
            trained network (1e-4 moved a tiny test's keypoints more than quantisation itself).
        calibration: MCTS arrays that warm up the observers before the first step.
        loss_cfg: the ``loss`` section of the training config (default: ``conf/config.yaml``'s).
        reduce_range: see :func:`qat_quantization_config`.
    Returns:
        (settings and :func:`quantization_summary` dict, dynamic_hw of the written graph).
    Raises:
        QuantizationError: a dynamic trace failed (use ``dynamic_hw=False`` with training crops of
            ``height`` x ``width``), a non-finite loss, or a graph of the wrong INT8 flavour.
    """
    import copy

    with quiet_exporter():
        from torchao.quantization.pt2e import move_exported_model_to_eval
        from torchao.quantization.pt2e.quantize_pt2e import convert_pt2e, prepare_qat_pt2e
        from torchao.quantization.pt2e.quantizer.x86_inductor_quantizer import X86InductorQuantizer

    from aerovis_train.module import KeypointModule

    from .onnx_tools import dynamic_shapes

    _check_target(target)
    float_net = copy.deepcopy(net).train()  # QAT fuses Conv+BN from the training-mode graph
    in_channels = int(net.in_channels)

    def trace(dyn: bool):
        x = example_input(in_channels, height, width, size_multiple, dyn)
        return torch.export.export(_DenseWithLogits(float_net), (x,), dynamic_shapes=dynamic_shapes(size_multiple, dyn)).module()

    with quiet_exporter():
        try:
            graph = trace(dynamic_hw)
        except Exception as exc:  # noqa: BLE001 - torch.export raises many types
            if not dynamic_hw:
                raise
            # no silent fallback here: the training crops were chosen for a dynamic graph
            raise QuantizationError(f"torch.export cannot trace {model_cfg.get('name')} with dynamic height/width for QAT "
                                    f"({type(exc).__name__}); pass --fixed-hw to train and export at {height}x{width}") from None
        quantizer = X86InductorQuantizer().set_global(qat_quantization_config(target, reduce_range=reduce_range))
        prepared = prepare_qat_pt2e(graph, quantizer)
    # BatchNorm statistics frozen (the QAT recipe's freeze_bn): a few hundred small-batch steps would
    # only add noise to them, and with frozen statistics training sees exactly the folded network
    # that is deployed. Weights, BN affine parameters and quantiser ranges still adapt.
    move_exported_model_to_eval(prepared)

    if calibration:
        with torch.no_grad():
            for x in calibration:
                x = torch.from_numpy(np.asarray(x, np.float32))
                prepared(x[None] if x.ndim == 3 else x)

    if loss_cfg is None:
        from omegaconf import OmegaConf

        from aerovis_train.models import CONF_DIR

        loss_cfg = OmegaConf.to_container(OmegaConf.load(CONF_DIR / "config.yaml").loss, resolve=True)
    # The project's own loss (detector CE + descriptor hinge), through the Lightning module's _losses
    module = KeypointModule({"model": model_cfg, "loss": loss_cfg, "optim": {"lr": lr}})
    module.model = _AsKeypointNet(prepared)
    opt = torch.optim.Adam(prepared.parameters(), lr=lr)
    losses: list[float] = []
    if steps > 0:
        batches: Iterator[dict] = itertools.cycle(train_batches) if not isinstance(train_batches, Iterator) else train_batches
        bar = tqdm(range(steps), desc=f"QAT {model_cfg.get('name')} ({target})", unit="step", file=sys.stderr, disable=not progress, leave=False)
        for _ in bar:
            batch = next(batches)
            loss = module._losses(batch)["loss"]
            if not torch.isfinite(loss):
                raise QuantizationError(f"QAT loss became non-finite ({float(loss)}); lower --qat-lr")
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
            bar.set_postfix(loss=f"{losses[-1]:.3f}")
        bar.close()

    with quiet_exporter(), _fold_only_present_convs():
        converted = convert_pt2e(prepared)
        move_exported_model_to_eval(converted)
        _, dynamic_hw, _ = export_onnx(_DenseOnly(converted), dst, in_channels=in_channels, height=height, width=width,
                                       size_multiple=size_multiple, dynamic_hw=dynamic_hw)
    summary = verify_flavour(onnx.load(str(dst)), target, dst)
    head = float(np.mean(losses[: max(1, len(losses) // 10)])) if losses else None
    tail = float(np.mean(losses[-max(1, len(losses) // 10):])) if losses else None
    info = {"method": "qat", "tool": "torchao.quantization.pt2e (prepare_qat_pt2e, convert_pt2e)", "format": "QDQ", "target": target,
            "activations": "int8 symmetric" if target == "tensorrt" else ("uint8 affine (7-bit)" if reduce_range else "uint8 affine"),
            "weights": "int8 symmetric per-channel", "steps": int(steps), "lr": lr, "batchnorm": "folded (statistics frozen during QAT)",
            "loss_first": head, "loss_last": tail, "calibration_frames": len(calibration or []), **summary}
    return info, dynamic_hw
