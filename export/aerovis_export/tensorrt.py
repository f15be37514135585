"""TensorRT engines for a bundle (``aerovis-export ... --engine``), with a persistent timing cache.

Two builder APIs (REFERENCE.md section 7):

* TensorRT 11 removed ``BuilderFlag.FP16``/``INT8`` and calibrators: networks are strongly typed and
  the precision is the ONNX graph's own (FP16 tensors, Q/DQ nodes), which is how bundles carry it.
* TensorRT 10 keeps the flag API: the network is weakly typed and ``FP16`` (and ``INT8`` for a Q/DQ
  graph, explicit quantisation) let the builder pick those kernels.

The engine has one optimisation profile: batch 1 to the bundle's batch, at its resolution. The
timing cache (kernel timings) is tied to the GPU, CUDA and TensorRT versions, so its file name
carries the TensorRT version; a cache TensorRT rejects is replaced.
Without TensorRT or without a CUDA GPU, :class:`EngineUnavailable` says so in one sentence.
"""

from __future__ import annotations

import os
from pathlib import Path


class EngineUnavailable(RuntimeError):
    """TensorRT or a CUDA GPU is missing: no engine can be built here (the ONNX bundle is unaffected)."""


class EngineBuildError(RuntimeError):
    """TensorRT was present but failed to parse or build the network."""


def default_timing_cache(trt_version: str) -> Path:
    """``$AEROVIS_CACHE/tensorrt/timing-<version>.cache`` (or under ``~/.cache/aerovis``)."""
    env = os.environ.get("AEROVIS_CACHE")
    root = Path(env).expanduser() if env else Path.home() / ".cache" / "aerovis"
    return root / "tensorrt" / f"timing-{trt_version}.cache"


def _import_tensorrt():
    try:
        import tensorrt as trt
    except ImportError:
        raise EngineUnavailable("TensorRT is not installed (pip install tensorrt on a machine with a CUDA GPU)") from None
    return trt


def build_engine(onnx_path: str | os.PathLike, engine_path: str | os.PathLike, *, precision: str, batch: int, in_channels: int,
                 height: int, width: int, timing_cache: str | os.PathLike | None = None, workspace_mib: int = 1024) -> dict:
    """Build and serialise a TensorRT engine of ``onnx_path``.

    Returns:
        ``{"engine", "tensorrt_version", "api", "timing_cache", "profile"}`` for the metadata.
    Raises:
        EngineUnavailable: no TensorRT, or no CUDA GPU.
        EngineBuildError: parsing or building failed (TensorRT's errors included).
    """
    trt = _import_tensorrt()
    logger = trt.Logger(trt.Logger.WARNING)
    try:
        builder = trt.Builder(logger)
    except (TypeError, RuntimeError) as exc:  # no GPU: "pybind11::init(): factory function returned nullptr"
        raise EngineUnavailable(f"TensorRT {trt.__version__} found no usable CUDA GPU ({exc})") from None
    if builder is None:
        raise EngineUnavailable(f"TensorRT {trt.__version__} found no usable CUDA GPU")
    major = int(trt.__version__.split(".")[0])
    strongly_typed = major >= 11
    flags = 0
    if strongly_typed:
        flags |= 1 << int(trt.NetworkDefinitionCreationFlag.STRONGLY_TYPED)
    elif hasattr(trt.NetworkDefinitionCreationFlag, "EXPLICIT_BATCH") and major < 10:
        flags |= 1 << int(trt.NetworkDefinitionCreationFlag.EXPLICIT_BATCH)  # implicit batch is gone in 10
    network = builder.create_network(flags)
    parser = trt.OnnxParser(network, logger)
    if not parser.parse_from_file(str(onnx_path)):
        errors = "; ".join(str(parser.get_error(i)) for i in range(parser.num_errors))
        raise EngineBuildError(f"{onnx_path}: TensorRT cannot parse the model: {errors}")
    config = builder.create_builder_config()
    config.set_memory_pool_limit(trt.MemoryPoolType.WORKSPACE, int(workspace_mib) << 20)
    if not strongly_typed:
        if precision in ("fp16", "int8"):
            config.set_flag(trt.BuilderFlag.FP16)  # int8 graphs keep their float tails in FP16 where allowed
        if precision == "int8":
            config.set_flag(trt.BuilderFlag.INT8)  # explicit quantisation: scales come from the Q/DQ nodes
    cache_path = Path(timing_cache) if timing_cache else default_timing_cache(trt.__version__)
    blob = cache_path.read_bytes() if cache_path.is_file() else b""
    cache = config.create_timing_cache(blob)
    if not config.set_timing_cache(cache, ignore_mismatch=False) and blob:
        cache = config.create_timing_cache(b"")  # stale cache of another GPU/driver: start afresh
        config.set_timing_cache(cache, ignore_mismatch=False)
    profile = builder.create_optimization_profile()
    name = network.get_input(0).name
    shape_min, shape_opt = (1, in_channels, height, width), (batch, in_channels, height, width)
    profile.set_shape(name, shape_min, shape_opt, shape_opt)
    config.add_optimization_profile(profile)
    serialized = builder.build_serialized_network(network, config)
    if serialized is None:
        raise EngineBuildError(f"{onnx_path}: TensorRT {trt.__version__} failed to build the engine (see its log above)")
    engine_path = Path(engine_path)
    tmp = engine_path.with_name(engine_path.name + ".partial")
    tmp.write_bytes(bytes(serialized))
    os.replace(tmp, engine_path)
    cache_path.parent.mkdir(parents=True, exist_ok=True)
    tmp_cache = cache_path.with_name(cache_path.name + ".partial")
    tmp_cache.write_bytes(bytes(config.get_timing_cache().serialize()))
    os.replace(tmp_cache, cache_path)
    return {"engine": engine_path.name, "tensorrt_version": trt.__version__,
            "api": "strongly typed (precision from the ONNX graph)" if strongly_typed else "builder flags",
            "timing_cache": str(cache_path), "profile": {"min": list(shape_min), "opt": list(shape_opt), "max": list(shape_opt)}}
