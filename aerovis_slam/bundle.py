"""Model bundles: the deployable form of a keypoint network, loaded by the runtime (numpy + ONNX Runtime).

A bundle is a directory written by ``aerovis-export`` (:mod:`aerovis_export`)::

    superlite-fp32/
        model.onnx       dense network: input "mcts" (B, C, H, W) float32 ->
                         "scores" (B, H, W) float32, "descriptors" (B, D, H/8, W/8) float32
        metadata.json    what the runtime needs to feed it and read it (see below)
        parity.json      accuracy against the PyTorch model it came from (written at export)
        model.engine     optional TensorRT engine (``aerovis-export --engine``)

``metadata.json`` (format ``aerovis-bundle``, version 1) holds the model name, input channels, the
time surface (``mcts``: kind ``ne`` or ``dt``, its parameters and channel order), the export
resolution ``height`` x ``width`` and ``batch``, ``cell`` (8), ``size_multiple``, ``dynamic_hw``
(whether the ONNX graph takes any H and W that are multiples of ``size_multiple``), the descriptor
dimension and its int8 ``descriptor_scale``, the post-processing (``threshold``, ``nms_radius``,
``border``), ``precision`` (fp32 | fp16 | int8), ``target`` (cpu | tensorrt), the source checkpoint and
its sha256, the sha256 of ``model.onnx``, the ONNX opset and the aerovis version.

:meth:`Bundle.load` checks all of this against the ONNX graph before anything runs: a corrupt or
replaced ``model.onnx``, metadata that does not match the graph's inputs or outputs, or a missing
field is a :class:`~aerovis_slam.errors.DataError` at load time, never a wrong answer later.

Post-processing (NMS, threshold / top-k, descriptor sampling, int8 quantisation) is the shared one of
:mod:`aerovis_slam.keypoints`; descriptors are L2-normalised floats, or int8 with the bundle's
symmetric scale (compared by cosine similarity, where the scale cancels).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DataError
from .keypoints import CELL, Keypoints, extract_keypoints, quantize_descriptors

BUNDLE_FORMAT = "aerovis-bundle"
BUNDLE_FORMAT_VERSION = 1
ONNX_NAME = "model.onnx"
METADATA_NAME = "metadata.json"
PARITY_NAME = "parity.json"
ENGINE_NAME = "model.engine"
INPUT_NAME = "mcts"
OUTPUT_NAMES = ("scores", "descriptors")
PRECISIONS = ("fp32", "fp16", "int8")
TARGETS = ("cpu", "tensorrt")
DEFAULT_BUNDLE_DIR = Path(__file__).resolve().parent / "bundles" / "superlite-fp32"

# field -> accepted types (bool is an int in Python: checked separately where it matters)
_REQUIRED: dict[str, tuple[type, ...]] = {
    "format": (str,), "format_version": (int,), "name": (str,), "in_channels": (int,), "mcts": (dict,),
    "height": (int,), "width": (int,), "batch": (int,), "cell": (int,), "size_multiple": (int,), "dynamic_hw": (bool,),
    "descriptor_dim": (int,), "descriptor_scale": (int, float), "threshold": (int, float), "nms_radius": (int,),
    "border": (int,), "precision": (str,), "target": (str,), "opset": (int,), "files": (dict,),
}


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _ort():
    try:
        import onnxruntime as ort
    except ImportError as exc:  # pragma: no cover - a runtime dependency
        raise DataError(None, "onnxruntime is not installed (pip install onnxruntime): model bundles need it") from exc
    return ort


class Bundle:
    """A validated bundle directory: ``model.onnx`` + ``metadata.json`` (+ ``parity.json``).

    Attributes:
        path: the bundle directory.
        onnx_path: its ``model.onnx``.
        meta: the parsed ``metadata.json``.
        inputs, outputs: ``{name: shape}`` of the ONNX graph (ints, or strings for symbolic dims).

    Example:
        >>> b = Bundle.load(default_bundle_path())  # doctest: +SKIP
        >>> b.name, b.precision, b.in_channels, b.mcts_kind
        ('superlite', 'fp32', 8, 'ne')
    """

    def __init__(self, path: Path, meta: dict, inputs: dict[str, list], outputs: dict[str, list]):
        self.path = path
        self.onnx_path = path / ONNX_NAME
        self.meta = meta
        self.inputs = inputs
        self.outputs = outputs

    # -- loading and validation -------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> "Bundle":
        """Read and validate a bundle directory.

        Raises:
            DataError: missing folder or file, unreadable or incomplete ``metadata.json``, a
                ``model.onnx`` that is corrupt, was replaced (sha256 differs from the metadata) or whose
                inputs/outputs contradict the metadata.
        """
        path = Path(path)
        if not path.is_dir():
            raise DataError(path, "no such bundle directory (a bundle is a folder with model.onnx and metadata.json; "
                                  "make one with aerovis-export)")
        meta_path, onnx_path = path / METADATA_NAME, path / ONNX_NAME
        if not meta_path.is_file():
            raise DataError(meta_path, "missing: not a model bundle (expected model.onnx + metadata.json from aerovis-export)")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise DataError(meta_path, f"unreadable JSON ({exc})") from None
        _check_metadata(meta_path, meta)
        if not onnx_path.is_file():
            raise DataError(onnx_path, "missing from the bundle")
        want = meta["files"].get(ONNX_NAME)
        if want is not None and file_sha256(onnx_path) != want:
            raise DataError(onnx_path, f"sha256 differs from files.{ONNX_NAME} in {METADATA_NAME}: the file is corrupt or "
                                       "was replaced; re-export the bundle")
        inputs, outputs = _read_graph_signature(onnx_path)
        bundle = cls(path, meta, inputs, outputs)
        bundle._check_graph()
        return bundle

    def _check_graph(self) -> None:
        """The ONNX inputs and outputs must be what the metadata promises."""
        where = self.onnx_path
        if list(self.inputs) != [INPUT_NAME]:
            raise DataError(where, f"graph inputs are {list(self.inputs)}; a bundle has exactly one input {INPUT_NAME!r}")
        if sorted(self.outputs) != sorted(OUTPUT_NAMES):
            raise DataError(where, f"graph outputs are {list(self.outputs)}; a bundle has {list(OUTPUT_NAMES)}")
        shape = self.inputs[INPUT_NAME]
        if len(shape) != 4:
            raise DataError(where, f"input {INPUT_NAME!r} has rank {len(shape)} ({shape}); expected (batch, C, H, W)")
        if shape[1] != self.in_channels:
            raise DataError(where, f"input {INPUT_NAME!r} takes {shape[1]} channels but {METADATA_NAME} says in_channels={self.in_channels}")
        fixed = [isinstance(d, int) for d in shape[2:]]
        if self.dynamic_hw and any(fixed):
            raise DataError(where, f"input {INPUT_NAME!r} has fixed height/width {shape[2:]} but {METADATA_NAME} says dynamic_hw=true")
        if not self.dynamic_hw:
            for axis, d, want in (("height", shape[2], self.height), ("width", shape[3], self.width)):
                if isinstance(d, int) and d != want:
                    raise DataError(where, f"input {INPUT_NAME!r} has {axis} {d} but {METADATA_NAME} says {axis}={want}")
        scores, desc = self.outputs["scores"], self.outputs["descriptors"]
        if len(scores) != 3:
            raise DataError(where, f"output 'scores' has rank {len(scores)} ({scores}); expected (batch, H, W)")
        if len(desc) != 4 or desc[1] != self.descriptor_dim:
            raise DataError(where, f"output 'descriptors' is {desc}; {METADATA_NAME} says (batch, descriptor_dim={self.descriptor_dim}, H/8, W/8)")

    # -- metadata views -----------------------------------------------------------------------
    @property
    def name(self) -> str:
        """Model name (e.g. ``superlite``)."""
        return self.meta["name"]

    @property
    def precision(self) -> str:
        """``fp32``, ``fp16`` or ``int8``."""
        return self.meta["precision"]

    @property
    def target(self) -> str:
        """``cpu`` or ``tensorrt`` (the int8 flavour: uint8 activations for CPUs, symmetric int8 for TensorRT)."""
        return self.meta["target"]

    @property
    def in_channels(self) -> int:
        """MCTS channels the network takes."""
        return int(self.meta["in_channels"])

    @property
    def height(self) -> int:
        """Export height in pixels (the only one when not :attr:`dynamic_hw`)."""
        return int(self.meta["height"])

    @property
    def width(self) -> int:
        """Export width in pixels (the only one when not :attr:`dynamic_hw`)."""
        return int(self.meta["width"])

    @property
    def batch(self) -> int:
        """Nominal batch (2 for a stereo pair); the ONNX batch axis itself is dynamic."""
        return int(self.meta["batch"])

    @property
    def mcts_kind(self) -> str:
        """``"ne"`` (MCTS_Ne, events per pixel) or ``"dt"`` (MCTS_dt, windows in ms)."""
        return self.meta["mcts"]["kind"]

    @property
    def mcts_params(self) -> tuple[float, ...]:
        """Events per pixel (``ne``) or window lengths in ms (``dt``), in channel order."""
        return tuple(float(p) for p in self.meta["mcts"]["params"])

    @property
    def descriptor_dim(self) -> int:
        """Descriptor length D."""
        return int(self.meta["descriptor_dim"])

    @property
    def descriptor_scale(self) -> float:
        """Symmetric int8 scale of unit descriptors: ``int8 = round(desc * scale)``."""
        return float(self.meta["descriptor_scale"])

    @property
    def threshold(self) -> float:
        """Detection threshold on the keypoint probability."""
        return float(self.meta["threshold"])

    @property
    def nms_radius(self) -> int:
        """NMS window is (2 r + 1)^2 pixels."""
        return int(self.meta["nms_radius"])

    @property
    def border(self) -> int:
        """Keypoints closer than this to the image border are dropped."""
        return int(self.meta["border"])

    @property
    def size_multiple(self) -> int:
        """Input height and width must be multiples of this (8, or 40 for MaxViT)."""
        return int(self.meta["size_multiple"])

    @property
    def dynamic_hw(self) -> bool:
        """Whether the ONNX graph takes any H, W that are multiples of :attr:`size_multiple`."""
        return bool(self.meta["dynamic_hw"])

    @property
    def parity(self) -> dict | None:
        """The export's ``parity.json`` (None when absent)."""
        p = self.path / PARITY_NAME
        return json.loads(p.read_text()) if p.is_file() else None

    def check_size(self, height: int, width: int) -> None:
        """Raises DataError unless the network takes (height, width)."""
        m = self.size_multiple
        if height <= 0 or width <= 0 or height % m or width % m:
            raise DataError(self.path, f"{self.name} takes heights and widths that are multiples of {m}, got {height}x{width}")
        if not self.dynamic_hw and (height, width) != (self.height, self.width):
            raise DataError(self.path, f"this {self.name} bundle takes only {self.height}x{self.width} (dynamic_hw is false), got "
                                       f"{height}x{width}; export a bundle at that resolution (aerovis-export --height {height} --width {width})")

    def session(self, threads: int | None = None, providers: Sequence[str] | None = None):
        """A new ONNX Runtime session of ``model.onnx`` (``threads``: intra-op threads, None: ORT's default)."""
        ort = _ort()
        so = ort.SessionOptions()
        so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        so.inter_op_num_threads = 1
        if threads:
            so.intra_op_num_threads = int(threads)
        try:
            return ort.InferenceSession(str(self.onnx_path), so, providers=list(providers or ["CPUExecutionProvider"]))
        except Exception as exc:  # ORT raises its own exception types for bad graphs
            raise DataError(self.onnx_path, f"ONNX Runtime cannot run this model ({type(exc).__name__}: {exc})") from None

    def __repr__(self) -> str:
        hw = "any HxW" if self.dynamic_hw else f"{self.height}x{self.width}"
        return f"Bundle({self.path}, {self.name} {self.precision}/{self.target}, {hw}, mcts_{self.mcts_kind})"


def _check_metadata(where: Path, meta: Any) -> None:
    if not isinstance(meta, dict):
        raise DataError(where, "expected a JSON object")
    if meta.get("format") != BUNDLE_FORMAT:
        raise DataError(where, f"field 'format' is {meta.get('format')!r}; expected {BUNDLE_FORMAT!r}")
    if meta.get("format_version") != BUNDLE_FORMAT_VERSION:
        raise DataError(where, f"field 'format_version' is {meta.get('format_version')!r}; this runtime reads version {BUNDLE_FORMAT_VERSION}")
    for key, types in _REQUIRED.items():
        if key not in meta:
            raise DataError(where, f"field {key!r} is missing")
        value = meta[key]
        ok = isinstance(value, types) and (types == (bool,) or not isinstance(value, bool))
        if not ok:
            raise DataError(where, f"field {key!r} is {value!r}; expected {' or '.join(t.__name__ for t in types)}")
    for key in ("in_channels", "height", "width", "batch", "cell", "size_multiple", "descriptor_dim"):
        if meta[key] <= 0:
            raise DataError(where, f"field {key!r} must be positive, got {meta[key]}")
    if meta["precision"] not in PRECISIONS:
        raise DataError(where, f"field 'precision' is {meta['precision']!r}; expected one of {list(PRECISIONS)}")
    if meta["target"] not in TARGETS:
        raise DataError(where, f"field 'target' is {meta['target']!r}; expected one of {list(TARGETS)}")
    if meta["cell"] != CELL:
        raise DataError(where, f"field 'cell' is {meta['cell']}; the runtime's post-processing uses {CELL}x{CELL} cells")
    if meta["size_multiple"] % meta["cell"]:
        raise DataError(where, f"field 'size_multiple' ({meta['size_multiple']}) must be a multiple of cell ({meta['cell']})")
    for key in ("height", "width"):
        if meta[key] % meta["size_multiple"]:
            raise DataError(where, f"field {key!r} ({meta[key]}) is not a multiple of size_multiple ({meta['size_multiple']})")
    if not (math.isfinite(meta["descriptor_scale"]) and meta["descriptor_scale"] > 0):
        raise DataError(where, f"field 'descriptor_scale' must be a positive number, got {meta['descriptor_scale']}")
    mcts = meta["mcts"]
    if mcts.get("kind") not in ("ne", "dt"):
        raise DataError(where, f"field 'mcts.kind' is {mcts.get('kind')!r}; expected 'ne' or 'dt'")
    params = mcts.get("params")
    if not isinstance(params, list) or not params or not all(isinstance(p, (int, float)) and not isinstance(p, bool) for p in params):
        raise DataError(where, f"field 'mcts.params' is {params!r}; expected a list of numbers")
    if 2 * len(params) != meta["in_channels"]:
        raise DataError(where, f"mcts {mcts['kind']} with {len(params)} params gives {2 * len(params)} channels but in_channels is {meta['in_channels']}")
    from .mcts import CHANNEL_ORDER

    if mcts.get("channel_order") != CHANNEL_ORDER:
        raise DataError(where, f"field 'mcts.channel_order' is {mcts.get('channel_order')!r}; this runtime computes {CHANNEL_ORDER!r} MCTS")


def _read_graph_signature(onnx_path: Path) -> tuple[dict[str, list], dict[str, list]]:
    """``({input: shape}, {output: shape})`` read by ONNX Runtime (graph optimisation off: only parsing)."""
    ort = _ort()
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    so.intra_op_num_threads = 1
    try:
        sess = ort.InferenceSession(str(onnx_path), so, providers=["CPUExecutionProvider"])
    except Exception as exc:  # InvalidProtobuf, Fail, ...: ORT's own exception types
        raise DataError(onnx_path, f"not a loadable ONNX model ({type(exc).__name__}: {str(exc)[:300]})") from None
    for io_ in [*sess.get_inputs(), *sess.get_outputs()]:
        if io_.type != "tensor(float)":
            raise DataError(onnx_path, f"{io_.name!r} is {io_.type}; bundles take and give float32 (tensor(float))")
    return ({i.name: list(i.shape) for i in sess.get_inputs()}, {o.name: list(o.shape) for o in sess.get_outputs()})


class BundleDetector:
    """Run a bundle with ONNX Runtime: dense outputs, keypoints with the shared post-processing.

    Args:
        bundle: a :class:`Bundle` or its directory.
        threads: ONNX Runtime intra-op threads (None: its default, one per physical core).
        top_k: default keypoint budget per image (None: every NMS maximum above the threshold).
        threshold: detection threshold (None: the bundle's). The relative-pose evaluation uses 0 with
            a top-k budget, as its :class:`~aerovis_train.eval.learned.TorchDetector`.
        providers: ONNX Runtime execution providers (default CPU).

    Attributes:
        name, mcts_kind, mcts_params, size_multiple: as the bundle's (what the SLAM frontend and the
            evaluation need to compute the right time surface).
        last_latency_ms: inference time of the last call; ``last_total_ms`` adds the post-processing.
    """

    def __init__(self, bundle: Bundle | str | Path, *, threads: int | None = None, top_k: int | None = None,
                 threshold: float | None = None, providers: Sequence[str] | None = None):
        self.bundle = bundle if isinstance(bundle, Bundle) else Bundle.load(bundle)
        b = self.bundle
        self.name = f"{b.name}-{b.precision}" + (f"-{b.target}" if b.precision == "int8" else "")
        self.mcts_kind, self.mcts_params, self.size_multiple = b.mcts_kind, b.mcts_params, b.size_multiple
        self.top_k = top_k
        self.threshold = b.threshold if threshold is None else float(threshold)
        self.nms_radius, self.border, self.descriptor_scale = b.nms_radius, b.border, b.descriptor_scale
        self.threads = threads
        self._session = b.session(threads, providers)
        self.last_latency_ms = 0.0
        self.last_total_ms = 0.0

    def dense(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, C, H, W) float32 -> scores (B, H, W) float32, descriptor grid (B, D, H/8, W/8) float32.

        H and W must be multiples of ``size_multiple`` (and the export resolution when the bundle is
        not ``dynamic_hw``); :meth:`detect` crops for you.
        """
        x = np.ascontiguousarray(batch, dtype=np.float32)
        if x.ndim != 4 or x.shape[1] != self.bundle.in_channels:
            raise ValueError(f"{self.name} expects (B, {self.bundle.in_channels}, H, W) MCTS, got shape {x.shape}")
        self.bundle.check_size(x.shape[2], x.shape[3])
        t0 = time.perf_counter()
        scores, desc = self._session.run(list(OUTPUT_NAMES), {INPUT_NAME: x})
        self.last_latency_ms = (time.perf_counter() - t0) * 1e3
        return scores, desc

    def _crop(self, batch: np.ndarray) -> np.ndarray:
        # top-left crop to the size multiple (as the evaluation's TorchDetector): keypoint
        # coordinates stay those of the full image
        h, w = batch.shape[-2:]
        m = self.size_multiple
        return batch[..., : h - h % m, : w - w % m]

    def detect(self, batch: np.ndarray, *, top_k: int | None = None, quantize: bool = True) -> list[Keypoints]:
        """(B, C, H, W) MCTS (e.g. a stereo pair) -> one :class:`Keypoints` per image.

        Images are cropped top-left to multiples of ``size_multiple``; ``quantize=True`` gives int8
        descriptors with the bundle's scale (compare them with
        :func:`aerovis_slam.keypoints.cosine_similarity`), else unit float32 descriptors.
        """
        t0 = time.perf_counter()
        scores, grids = self.dense(self._crop(np.asarray(batch)))
        k = top_k if top_k is not None else self.top_k
        out = []
        for s, g in zip(scores, grids):
            kp = extract_keypoints(s, g, nms_radius=self.nms_radius, threshold=self.threshold, top_k=k, border=self.border)
            if quantize:
                kp = Keypoints(kp.xy, kp.scores, quantize_descriptors(kp.descriptors, self.descriptor_scale))
            out.append(kp)
        self.last_total_ms = (time.perf_counter() - t0) * 1e3
        return out

    def __call__(self, mcts: np.ndarray, top_k: int | None = None) -> Keypoints:
        """One (C, H, W) MCTS -> :class:`Keypoints` with float descriptors (the evaluation's detector contract)."""
        mcts = np.asarray(mcts)
        if mcts.ndim != 3:
            raise ValueError(f"{self.name} expects one (C, H, W) MCTS, got shape {mcts.shape}")
        kp = self.detect(mcts[None], top_k=top_k, quantize=False)[0]
        self.last_latency_ms = self.last_total_ms  # the evaluation reports the whole detector time per frame
        return kp


def synthetic_mcts(bundle: Bundle, batch: int | None = None, *, seed: int = 0, height: int | None = None,
                   width: int | None = None) -> np.ndarray:
    """(B, C, H, W) float32 MCTS of a synthetic moving-edge event stream at the bundle's resolution
    (or ``height`` x ``width``).

    Benchmark input with the sparsity of real time surfaces (post-processing time depends on how many
    local maxima the scores have; inference time does not depend on the values).
    """
    from .benchmarks import synthetic_edge_stream
    from .mcts import events_per_window, mcts_from_events

    b = batch or bundle.batch
    h, w = height or bundle.height, width or bundle.width
    if bundle.mcts_kind == "ne":
        n = int(events_per_window(bundle.mcts_params, w, h).max()) + 1
    else:  # about 2 events per pixel within the longest window
        n = 2 * w * h
    dur = int(max(bundle.mcts_params) * 1000 * 2) if bundle.mcts_kind == "dt" else 200_000
    out = [mcts_from_events(synthetic_edge_stream(w, h, n, duration_us=dur, seed=seed + i), w, h, kind=bundle.mcts_kind,
                            params=bundle.mcts_params) for i in range(b)]
    return np.stack(out).astype(np.float32)


def benchmark_bundles(bundles: Sequence[Bundle | str | Path], *, repeats: int = 50, warmup: int = 5,
                      threads: int | None = None, height: int | None = None, width: int | None = None,
                      block: int = 5) -> list[dict]:
    """Latency of each bundle for its batch at its resolution, measured in one run.

    Repeats go round-robin over the bundles in blocks (``block`` runs of bundle 1, ``block`` runs of
    bundle 2, ..., then bundle 1 again) so that load from other processes hits all of them alike and
    their ratios stay meaningful on a busy machine. Each block starts with one untimed run: ONNX
    Runtime's intra-op threads spin for a while after a run (``session.intra_op.allow_spinning``, on
    by default and in the runtime), so the previous session's threads still hold the cores during
    the first run after a switch. On 2 cores that first run of a 60 ms network takes about 95 ms;
    timing every switch (blocks of 1) measured the switching rather than the network.
    ``height`` x ``width`` replaces the bundles' own resolution (to compare models at one size; every
    bundle must take it, see :meth:`Bundle.check_size`).

    Returns:
        One dict per bundle: ``bundle``, ``model``, ``precision``, ``target``, ``batch``, ``height``,
        ``width``, ``latency_ms_p50`` / ``latency_ms_p90`` (ONNX Runtime inference alone),
        ``total_ms_p50`` (inference + NMS, top-k = max(H, W) / 2, descriptor sampling and int8
        quantisation for the whole batch), ``threads``, ``repeats``, ``block``.
    """
    if repeats < 1 or warmup < 0 or block < 1:
        raise ValueError(f"repeats and block must be at least 1 and warmup at least 0, got repeats={repeats}, warmup={warmup}, block={block}")
    dets = [BundleDetector(b, threads=threads) for b in bundles]
    if height or width:
        for d in dets:
            d.bundle.check_size(height or d.bundle.height, width or d.bundle.width)
    inputs = [synthetic_mcts(d.bundle, height=height, width=width) for d in dets]
    infer: list[list[float]] = [[] for _ in dets]
    total: list[list[float]] = [[] for _ in dets]
    for d, x in zip(dets, inputs):
        for _ in range(warmup):
            d.detect(x, top_k=max(x.shape[-2:]) // 2)
    switch_run = len(dets) > 1  # one bundle alone never switches
    while dets and len(infer[0]) < repeats:
        for i, (d, x) in enumerate(zip(dets, inputs)):
            n = min(block, repeats - len(infer[i]))
            for r in range(switch_run + n):
                d.detect(x, top_k=max(x.shape[-2:]) // 2)
                if r >= switch_run:
                    infer[i].append(d.last_latency_ms)
                    total[i].append(d.last_total_ms)
    out = []
    for d, x, inf, tot in zip(dets, inputs, infer, total):
        b = d.bundle
        out.append({"bundle": str(b.path), "model": b.name, "precision": b.precision, "target": b.target,
                    "batch": int(x.shape[0]), "height": int(x.shape[2]), "width": int(x.shape[3]),
                    "latency_ms_p50": round(float(np.percentile(inf, 50)), 3),
                    "latency_ms_p90": round(float(np.percentile(inf, 90)), 3),
                    "total_ms_p50": round(float(np.percentile(tot, 50)), 3),
                    "threads": threads, "repeats": repeats, "block": block})
    return out


def benchmark_bundle(bundle: Bundle | str | Path, *, repeats: int = 50, warmup: int = 5, threads: int | None = None) -> dict:
    """``{"latency_ms_p50", "latency_ms_p90", "total_ms_p50", ...}`` for the bundle's batch at its resolution
    (see :func:`benchmark_bundles`)."""
    return benchmark_bundles([bundle], repeats=repeats, warmup=warmup, threads=threads)[0]


def default_bundle_path() -> Path:
    """The shipped default bundle (SuperLitE, fp32, dynamic resolution) inside the package.

    Raises:
        DataError: when this installation lacks it (regenerate with ``python -m aerovis_export.default_bundle``).
    """
    if not (DEFAULT_BUNDLE_DIR / METADATA_NAME).is_file():
        raise DataError(DEFAULT_BUNDLE_DIR, "the shipped default bundle is missing from this installation "
                                            "(regenerate it with `python -m aerovis_export.default_bundle`)")
    return DEFAULT_BUNDLE_DIR
