"""Torch -> ONNX export of the dense network, FP16 conversion, and graph inspection.

* :func:`export_onnx`: opset 18 through ``torch.onnx.export(dynamo=True)`` with a dynamic batch axis
  and, where ``torch.export`` can prove it, dynamic height and width (multiples of the model's
  ``size_multiple``). Only the dense outputs (``scores``, ``descriptors``) are in the graph; NMS and
  top-k stay outside (REFERENCE.md section 7).
* :func:`postprocess_nodes`: the nodes after each head's last convolution (softmax, dustbin slice,
  depth-to-space, descriptor L2 normalisation). FP16 conversion and post-training quantisation keep
  them in FP32, because FP16/int8 probabilities lose weak keypoints.
* :func:`convert_fp16`: half weights and activations, float32 inputs and outputs.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import onnx
import torch
from torch import nn

from aerovis_slam.bundle import INPUT_NAME, OUTPUT_NAMES
from aerovis_slam.errors import DataError

OPSET = 18
# ops at which the backward walk from an output stops: the heads' last layers
_HEAD_OPS = {"Conv", "ConvInteger", "QLinearConv", "Gemm", "MatMul"}


@contextlib.contextmanager
def quiet_exporter() -> Iterator[None]:
    """Silence the exporters' progress prints, deprecation warnings and logging (the CLI shows its own progress)."""
    # torchao's import logs "Failed to load ..._C_mxfp8" (CUDA kernels absent on CPU builds) and torch's pytree
    # a deprecation notice about its enums, and onnx_ir's optimisation passes one INFO line per merged initializer
    # (24 of them at the end of `python train.py model=superlite`, whose Hydra logging shows INFO): noise for an export
    names = ("torch.onnx", "torch.export", "torch._dynamo", "torch.fx", "torch.utils._pytree", "onnxscript", "onnx_ir", "torchao")
    loggers = [logging.getLogger(n) for n in names]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            yield
    finally:
        for lg, lv in zip(loggers, levels):
            lg.setLevel(lv)


def dynamic_shapes(size_multiple: int, dynamic_hw: bool, name: str = "x") -> dict:
    """``torch.export`` dynamic shapes: batch always, H = m * hc and W = m * wc when ``dynamic_hw``."""
    batch = torch.export.Dim("batch", min=1, max=1024)
    if not dynamic_hw:
        return {name: {0: batch}}
    hc, wc = torch.export.Dim("hc", min=1, max=1024), torch.export.Dim("wc", min=1, max=1024)
    return {name: {0: batch, 2: size_multiple * hc, 3: size_multiple * wc}}


def example_input(in_channels: int, height: int, width: int, size_multiple: int, dynamic_hw: bool) -> torch.Tensor:
    """Example input for tracing: batch 2; with ``dynamic_hw`` sides of at least 2 x ``size_multiple``.

    ``torch.export`` specialises dimensions of size 1, so a batch of 1 (or, for a dynamic graph, a side
    equal to one size multiple, i.e. one cell count of 1) would freeze that axis in the graph. A fixed
    graph is traced at exactly ``height`` x ``width``.
    """
    h, w = (max(height, 2 * size_multiple), max(width, 2 * size_multiple)) if dynamic_hw else (height, width)
    return torch.rand(2, in_channels, h, w, generator=torch.Generator().manual_seed(0))


def export_onnx(module: nn.Module, path: str | os.PathLike, *, in_channels: int, height: int, width: int, size_multiple: int,
                dynamic_hw: bool = True) -> tuple[Path, bool, str | None]:
    """Export ``module`` (``x -> (scores, descriptors)``) to ONNX opset 18.

    Tries dynamic height/width first when ``dynamic_hw``; if ``torch.export`` cannot prove the graph
    valid for every multiple of ``size_multiple`` it falls back to a graph of exactly
    ``height`` x ``width``. The batch axis is always dynamic.

    Returns:
        ``(path, dynamic_hw actually used, reason for a fallback or None)``.
    """
    path = Path(path)
    key = _export_key(module, (in_channels, height, width), size_multiple, dynamic_hw)
    if key in _EXPORTED:
        blob, dyn, reason = _EXPORTED[key]
        path.write_bytes(blob)
        return path, dyn, reason
    reason = None
    attempts = [True, False] if dynamic_hw else [False]
    for dyn in attempts:
        example = example_input(in_channels, height, width, size_multiple, dyn)
        try:
            with quiet_exporter():
                program = torch.onnx.export(module, (example,), dynamo=True, opset_version=OPSET,
                                            dynamic_shapes=dynamic_shapes(size_multiple, dyn),
                                            input_names=[INPUT_NAME], output_names=list(OUTPUT_NAMES), verbose=False)
                program.save(str(path))
            _EXPORTED[key] = (path.read_bytes(), dyn, reason)
            return path, dyn, reason
        except Exception as exc:  # torch.export raises many types (UserError, ConstraintViolation, ...)
            if not dyn:
                raise
            reason = f"{type(exc).__name__}: {str(exc).splitlines()[0][:300]}"
    raise AssertionError("unreachable")  # pragma: no cover


# Float32 graphs exported in this process, by architecture, weights and export settings: exporting one
# model at several precisions (tests, the notebook, a script) traces it once (~8 s each otherwise).
_EXPORTED: dict[str, tuple[bytes, bool, str | None]] = {}


def _export_key(module: nn.Module, shape: tuple[int, int, int], size_multiple: int, dynamic_hw: bool) -> str:
    h = hashlib.sha256()
    h.update(repr(module).encode())
    for name, t in module.state_dict().items():
        h.update(name.encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    h.update(repr((tuple(shape), int(size_multiple), bool(dynamic_hw), torch.__version__)).encode())
    return h.hexdigest()


def float_value_names(model: onnx.ModelProto) -> set[str]:
    """Names of the float32 tensors of a graph (inputs, outputs, initializers, inferred intermediates)."""
    inferred = onnx.shape_inference.infer_shapes(model)
    g = inferred.graph
    names = {vi.name for vi in [*g.input, *g.output, *g.value_info] if vi.type.tensor_type.elem_type == onnx.TensorProto.FLOAT}
    names |= {t.name for t in g.initializer if t.data_type == onnx.TensorProto.FLOAT}
    return names


def postprocess_nodes(model: onnx.ModelProto) -> list[str]:
    """Names of the nodes between each head's last convolution and the graph outputs.

    Walks back from every output along float32 tensors (integer shape arithmetic is not followed)
    and stops at a convolution/matmul, so the result is softmax, slice, depth-to-space reshapes and
    the descriptor normalisation: the numerically sensitive tail kept in FP32.
    """
    floats = float_value_names(model)
    producer = {out: node for node in model.graph.node for out in node.output}
    seen: dict[str, onnx.NodeProto] = {}
    stack = [o.name for o in model.graph.output]
    while stack:
        tensor = stack.pop()
        node = producer.get(tensor)
        if node is None or node.op_type in _HEAD_OPS or node.name in seen:
            continue
        seen[node.name] = node
        stack.extend(i for i in node.input if i and i in floats)
    return [n.name for n in model.graph.node if n.name in seen]


def head_output_convolutions(model: onnx.ModelProto, tail: list[str]) -> list[str]:
    """Names of the convolutions whose outputs feed the post-processing ``tail`` (node names, as
    :func:`postprocess_nodes` returns them): each head's last convolution, whose outputs are the
    logits and raw descriptors themselves."""
    feeds = {i for n in model.graph.node if n.name in tail for i in n.input}
    return [n.name for n in model.graph.node if n.op_type in _HEAD_OPS and set(n.output) & feeds]


def ensure_node_names(model: onnx.ModelProto) -> onnx.ModelProto:
    """Give every unnamed node a unique name (block lists and quantiser exclusions go by name)."""
    used = {n.name for n in model.graph.node if n.name}
    for i, node in enumerate(model.graph.node):
        if not node.name:
            name = f"{node.op_type}_{i}"
            while name in used:
                name += "_"
            node.name = name
            used.add(name)
    return model


def convert_fp16(src: str | os.PathLike, dst: str | os.PathLike) -> list[str]:
    """FP16 weights and activations with float32 inputs/outputs; the post-processing tail stays FP32.

    Returns:
        The names of the nodes kept in FP32.
    """
    from onnxconverter_common.float16 import convert_float_to_float16

    model = ensure_node_names(onnx.load(str(src)))
    keep = postprocess_nodes(model)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "the model contains values outside the FP16 range" notices
        half = convert_float_to_float16(model, keep_io_types=True, node_block_list=keep)
    _float32_outputs(half)
    onnx.checker.check_model(half)
    onnx.save(half, str(dst))
    return keep


def _float32_outputs(model: onnx.ModelProto) -> None:
    """Make every graph output float32 again, in place.

    onnxconverter-common 1.16 ignores ``keep_io_types`` for outputs produced by block-listed nodes: it
    appends a Cast to FP16 after them. Such a cast is bypassed (the FP32 tensor becomes the output);
    any other FP16 output gets a Cast to FP32.
    """
    FLOAT, FLOAT16 = onnx.TensorProto.FLOAT, onnx.TensorProto.FLOAT16
    g = model.graph
    producer = {o: n for n in g.node for o in n.output}
    for out in g.output:
        if out.type.tensor_type.elem_type != FLOAT16:
            continue
        node = producer.get(out.name)
        to = next((a.i for a in node.attribute if a.name == "to"), None) if node is not None and node.op_type == "Cast" else None
        if to == FLOAT16:
            src = node.input[0]
            g.node.remove(node)
            for n in g.node:  # the float32 tensor takes the output's name
                n.output[:] = [out.name if o == src else o for o in n.output]
                n.input[:] = [out.name if i == src else i for i in n.input]
            keep_vi = [vi for vi in g.value_info if vi.name != src]
            del g.value_info[:]
            g.value_info.extend(keep_vi)
        else:
            half_name = out.name + "_fp16"
            for n in g.node:
                n.output[:] = [half_name if o == out.name else o for o in n.output]
                n.input[:] = [half_name if i == out.name else i for i in n.input]
            g.node.append(onnx.helper.make_node("Cast", [half_name], [out.name], to=FLOAT, name=f"{out.name}_to_float32"))
        out.type.tensor_type.elem_type = FLOAT


def quantization_summary(model: onnx.ModelProto) -> dict:
    """What a Q/DQ graph quantises: counts of QuantizeLinear/DequantizeLinear, the activation and
    weight integer types, and whether every zero-point is 0 (symmetric, as TensorRT requires).

    Activations are the QuantizeLinear outputs; weights are DequantizeLinear nodes fed by an
    initializer (PT2E stores weights pre-quantised, ONNX Runtime too).
    """
    inits = {t.name: t for t in model.graph.initializer}
    consts = {n.output[0]: n for n in model.graph.node if n.op_type == "Constant"}

    def value(name: str):
        if name in inits:
            return onnx.numpy_helper.to_array(inits[name])
        if name in consts:
            return onnx.numpy_helper.to_array(consts[name].attribute[0].t)
        return None

    act_types, weight_types, bias_types, nonzero_zp = set(), set(), set(), 0
    n_q = n_dq = 0
    for node in model.graph.node:
        if node.op_type not in ("QuantizeLinear", "DequantizeLinear"):
            continue
        zp = value(node.input[2]) if len(node.input) > 2 and node.input[2] else None
        if zp is not None and (zp != 0).any():
            nonzero_zp += 1
        if node.op_type == "QuantizeLinear":
            n_q += 1
            if zp is not None:
                act_types.add(str(zp.dtype))
        else:
            n_dq += 1
            w = value(node.input[0])
            if w is not None:  # int32 constants are biases (scale = input scale x weight scale, zero-point 0)
                (bias_types if w.dtype == np.int32 else weight_types).add(str(w.dtype))
    return {"quantize_linear": n_q, "dequantize_linear": n_dq, "activation_types": sorted(act_types),
            "weight_types": sorted(weight_types), "bias_types": sorted(bias_types), "nonzero_zero_points": nonzero_zp}


def check_onnx(path: str | os.PathLike) -> onnx.ModelProto:
    """Load and check a written model (raises DataError naming the file)."""
    try:
        model = onnx.load(str(path))
        onnx.checker.check_model(model)
    except Exception as exc:  # onnx raises ValidationError, DecodeError, ...
        raise DataError(path, f"the exported ONNX model fails onnx.checker ({type(exc).__name__}: {exc})") from None
    return model
