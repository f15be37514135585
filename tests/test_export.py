"""Model bundles: ``aerovis-export`` at every precision on the `tiny` preset, parity with the PyTorch
model, the runtime loader's checks (``aerovis_slam.bundle``), BundleDetector against the evaluation's
TorchDetector, ``aerovis-bench detector`` and ``aerovis-eval pose --model BUNDLE``.

Tolerances on `tiny` (two 1 s sequences at 64x48, the pair protocol scaled to 10 deg within 1 s as in
test_eval_pose): AUC@10 pools about 19 pairs, so one pair moves it by up to 100/19 = 5.3 points and the
issue's bench targets (1 point FP32/FP16, 2 points INT8) are below the resolution of this data. AUC
checks therefore allow one pair's weight (FP32/FP16) or two (INT8), while keypoint repeatability and
descriptor cosine, pooled over hundreds of keypoints, are held to the issue's own FP32/FP16 targets.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="export needs the train extra (torch)")
onnx = pytest.importorskip("onnx", reason="export needs the train extra (onnx)")
pytest.importorskip("onnxscript", reason="export needs the train extra (onnxscript)")

from aerovis_export import cli  # noqa: E402
from aerovis_export.onnx_tools import head_output_convolutions, postprocess_nodes  # noqa: E402
from aerovis_slam.bundle import Bundle, BundleDetector, default_bundle_path, file_sha256, synthetic_mcts  # noqa: E402
from aerovis_slam.errors import DataError  # noqa: E402
from aerovis_slam.keypoints import cosine_similarity  # noqa: E402
from aerovis_train.checkpoints import WEIGHTS_DIR, load_model, save_slim  # noqa: E402
from aerovis_train.eval.learned import TorchDetector  # noqa: E402

TINY_PROTOCOL = ["--parity-max-angle-deg", "10", "--parity-max-dt-s", "1"]


def _tensorrt_gpu() -> bool:
    try:
        import tensorrt as trt

        return trt.Builder(trt.Logger(trt.Logger.ERROR)) is not None
    except Exception:  # noqa: BLE001 - not installed, or no GPU (TypeError from a null factory)
        return False


@pytest.fixture(scope="module")
def tiny(tiny_cache) -> Path:
    from aerovis_slam.sim.cache import ensure_preset

    return ensure_preset("tiny", str(tiny_cache), progress=False)


def _export(tiny: Path, out: Path, *extra: str, parity: bool = True, model: str = "superlite", hw=("48", "64")) -> int:
    args = [model, "--height", hw[0], "--width", hw[1], "--out", str(out), "--calib-data", str(tiny), "--calib-frames", "8", "--quiet"]
    args += ["--data", str(tiny), *TINY_PROTOCOL] if parity else ["--no-parity"]
    return cli.main(args + list(extra))


@pytest.fixture(scope="module")
def fp32_bundle(tiny, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bundles") / "superlite-fp32"
    assert _export(tiny, out, "--precision", "fp32") == 0
    return out


@pytest.fixture(scope="module")
def frames(tiny) -> list[np.ndarray]:
    """Four held-out MCTS of the tiny preset at 48x64 (the export's own calibration pipeline)."""
    from aerovis_export.data import calibration_mcts

    return calibration_mcts(tiny, "ne", (0.03, 0.1, 0.3, 1.0), frames=4, height=48, width=64, size_multiple=8, dynamic_hw=True)


def _one_pair(parity: dict) -> float:
    return 100.0 / parity["pairs"]


# ---------------------------------------------------------------------------------------------
# FP32: contents, metadata, parity, runtime detector
# ---------------------------------------------------------------------------------------------
def test_fp32_bundle_contents_and_parity(fp32_bundle):
    assert sorted(p.name for p in fp32_bundle.iterdir()) == ["metadata.json", "model.onnx", "parity.json"]
    assert not fp32_bundle.with_name(fp32_bundle.name + ".partial").exists()
    b = Bundle.load(fp32_bundle)
    m = b.meta
    assert (b.name, b.precision, b.target, b.in_channels, b.descriptor_dim) == ("superlite", "fp32", "cpu", 8, 64)
    assert (b.height, b.width, b.batch, b.size_multiple, b.dynamic_hw) == (48, 64, 2, 8, True)
    assert b.mcts_kind == "ne" and b.mcts_params == (0.03, 0.1, 0.3, 1.0)
    assert m["mcts"]["channel_order"] == "polarity-major" and m["mcts"]["channels"][0] == "off_ne0.03"
    assert m["opset"] == 18 and m["source"]["sha256"] == file_sha256(WEIGHTS_DIR / "superlite.pt")
    assert (m["threshold"], m["nms_radius"]) == (0.01, 2)
    # scale = 127 / largest component; a unit 64-vector's largest component lies in [1/8, 1]
    assert b.descriptor_scale == pytest.approx(127.0 / m["descriptor_max_abs"])
    assert 1 / 8 <= m["descriptor_max_abs"] <= 1.0 + 1e-6
    model = onnx.load(str(b.onnx_path))
    assert model.opset_import[0].version == 18
    assert [o.name for o in model.graph.output] == ["scores", "descriptors"]  # dense outputs only
    assert not {"TopK", "NonMaxSuppression"} & {n.op_type for n in model.graph.node}
    assert [d.dim_param != "" for d in model.graph.input[0].type.tensor_type.shape.dim] == [True, False, True, True]
    p = b.parity
    # The FP32 graph differs from torch only by summation order (~1e-7): the same keypoints (up to
    # near-ties) and descriptors, hence the same matches and the same seeded RANSAC.
    assert p["keypoint_repeatability"] >= 0.99 and p["descriptor_cosine"] >= 0.9999
    assert abs(p["auc10_torch"] - p["auc10_onnx"]) <= _one_pair(p)
    assert p["pairs"] >= 10 and p["meets_targets"]


def test_bundle_detector_matches_torch_detector(fp32_bundle, frames):
    model, cfg, _ = load_model("superlite")
    ref = TorchDetector(model, cfg, threshold=0.0)
    det = BundleDetector(fp32_bundle, threshold=0.0)
    assert (det.mcts_kind, det.mcts_params, det.size_multiple) == ("ne", (0.03, 0.1, 0.3, 1.0), 8)
    for m in frames:
        s_ref, g_ref = ref.dense(m)
        s, g = det.dense(m[None])
        # float32 with different kernel summation orders: ~1e-7 observed
        np.testing.assert_allclose(s[0], s_ref, atol=1e-5)
        np.testing.assert_allclose(g[0], g_ref, atol=1e-5)
        kr, kb = ref(m, top_k=32), det(m, top_k=32)
        # softmax probabilities agree in relative terms (~1e-5 observed, tiny peaks included), so the
        # 3x3 sub-pixel centroids, whose offsets move by at most 2 r = 2 px times the relative weight
        # error, agree to 2e-4 px; that moves the bilinear descriptor weights by 2e-4 / 8 per unit step
        np.testing.assert_allclose(kb.scores, kr.scores, rtol=1e-4)
        np.testing.assert_allclose(kb.xy, kr.xy, atol=1e-3)
        np.testing.assert_allclose(kb.descriptors, kr.descriptors, atol=1e-4)
    # a stereo batch of a size that is no multiple of 8: cropped top-left to 48x64, int8 descriptors
    batch = np.zeros((2, 8, 50, 66), np.float32)
    batch[:, :, :48, :64] = np.stack(frames[:2])
    kps = det.detect(batch)
    assert len(kps) == 2 and all(kp.descriptors.dtype == np.int8 for kp in kps)
    assert all((kp.xy[:, 0] < 64).all() and (kp.xy[:, 1] < 48).all() and (kp.scores > det.threshold).all() for kp in kps)
    floats = det.detect(batch, quantize=False)
    # int8 rounding moves each of the 64 components by at most 0.5 / scale (scale ~ 270): the
    # error vector has norm <= 4 / 270 ~ 0.015, so cosine >= 1 - 0.015^2 / 2 > 0.999
    cos = np.diag(cosine_similarity(kps[0].descriptors.astype(np.float32), floats[0].descriptors))
    assert len(cos) > 0 and cos.min() > 0.999
    assert det.last_latency_ms > 0 and det.last_total_ms >= det.last_latency_ms
    # dynamic resolution: any multiple of 8
    s, g = det.dense(np.stack(frames[:1])[:, :, :40, :56])
    assert s.shape == (1, 40, 56) and g.shape == (1, 64, 5, 7)
    with pytest.raises(DataError, match="multiples of 8, got 40x60"):
        det.dense(np.zeros((1, 8, 40, 60), np.float32))
    with pytest.raises(ValueError, match=r"expects \(B, 8, H, W\) MCTS, got shape \(1, 10, 48, 64\)"):
        det.dense(np.zeros((1, 10, 48, 64), np.float32))


def test_fixed_resolution_bundle_refuses_other_sizes(fp32_bundle, tmp_path):
    fixed = tmp_path / "fixed"
    shutil.copytree(fp32_bundle, fixed)
    meta = json.loads((fixed / "metadata.json").read_text())
    meta["dynamic_hw"] = False
    (fixed / "metadata.json").write_text(json.dumps(meta))
    det = BundleDetector(fixed)
    assert det.dense(np.zeros((1, 8, 48, 64), np.float32))[0].shape == (1, 48, 64)
    with pytest.raises(DataError, match=r"takes only 48x64 \(dynamic_hw is false\), got 40x56"):
        det.dense(np.zeros((1, 8, 40, 56), np.float32))


def _corrupt(src: Path, dst: Path, *, meta=None, onnx_bytes=None) -> Path:
    shutil.copytree(src, dst)
    if meta is not None:
        m = json.loads((dst / "metadata.json").read_text())
        meta(m)
        (dst / "metadata.json").write_text(json.dumps(m))
    if onnx_bytes is not None:
        (dst / "model.onnx").write_bytes(onnx_bytes)
    return dst


def test_bundle_load_errors(fp32_bundle, tmp_path):
    good = (fp32_bundle / "model.onnx").read_bytes()
    cases = [
        (dict(onnx_bytes=good[: len(good) // 2]), r"sha256 differs from files.model.onnx"),
        (dict(onnx_bytes=good[: len(good) // 2], meta=lambda m: m["files"].clear()), "not a loadable ONNX model"),
        (dict(meta=lambda m: m.update(in_channels=10, mcts={**m["mcts"], "params": [1, 2, 3, 4, 5]})),
         "takes 8 channels but metadata.json says in_channels=10"),
        (dict(meta=lambda m: m.update(descriptor_dim=32)), r"descriptor_dim=32"),
        (dict(meta=lambda m: m.pop("threshold")), "field 'threshold' is missing"),
        (dict(meta=lambda m: m.update(height=50)), r"field 'height' \(50\) is not a multiple of size_multiple \(8\)"),
        (dict(meta=lambda m: m.update(dynamic_hw="yes")), "field 'dynamic_hw' is 'yes'; expected bool"),
        (dict(meta=lambda m: m["mcts"].update(channel_order="window-major")), "channel_order"),
        (dict(meta=lambda m: m.update(precision="int4")), "field 'precision' is 'int4'"),
    ]
    for i, (kw, match) in enumerate(cases):
        bad = _corrupt(fp32_bundle, tmp_path / f"bad{i}", **kw)
        with pytest.raises(DataError, match=match) as exc:
            Bundle.load(bad)
        assert str(bad) in str(exc.value)  # the message names the file
    (tmp_path / "bad0" / "metadata.json").write_text("{not json")
    with pytest.raises(DataError, match="unreadable JSON"):
        Bundle.load(tmp_path / "bad0")
    with pytest.raises(DataError, match="no such bundle directory"):
        Bundle.load(tmp_path / "missing")
    with pytest.raises(DataError, match="metadata.json: missing"):
        Bundle.load(tmp_path)


def test_export_refuses_bad_input(tiny, tmp_path, capsys):
    notckpt = tmp_path / "notes.pt"
    notckpt.write_text("not a checkpoint")
    other = tmp_path / "other.pt"
    torch.save({"state_dict": {"w": torch.zeros(3)}, "epoch": 1}, other)
    wrong = tmp_path / "wrong_weights.pt"
    _, cfg, _ = load_model("superlite")
    small = {**cfg, "descriptor_dim": 16}
    from aerovis_train.models import build_model

    save_slim(cfg, build_model(small).state_dict(), wrong)  # a superlite config with another model's weights
    existing = tmp_path / "existing"
    existing.mkdir()
    cases = [
        (str(notckpt), ["--height", "48"], "not a readable torch checkpoint"),
        (str(other), ["--height", "48"], "not an aerovis checkpoint"),
        (str(wrong), ["--height", "48"], "weights do not fit"),
        ("superlite", ["--height", "50"], "--height 50 is not a positive multiple of 8"),
    ]
    for model, hw, message in cases:
        rc = cli.main([model, "--precision", "fp32", *hw, "--width", "64", "--out", str(tmp_path / "out"), "--no-parity", "--quiet"])
        err = capsys.readouterr().err
        assert rc == 2 and message in err and "Traceback" not in err, (model, err)
        assert not (tmp_path / "out").exists() and not (tmp_path / "out.partial").exists()
    rc = cli.main(["superlite", "--precision", "fp32", "--height", "48", "--width", "64", "--out", str(existing), "--no-parity", "--quiet"])
    assert rc == 2 and "exists already; pass --force" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# FP16, INT8 (QAT for CPUs, PTQ for TensorRT), TensorRT engines
# ---------------------------------------------------------------------------------------------
def test_fp16_bundle_keeps_softmax_and_normalisation_in_fp32(tiny, tmp_path, capsys):
    out = tmp_path / "superlite-fp16"
    rc = _export(tiny, out, "--precision", "fp16", "--engine")
    captured = capsys.readouterr()
    if _tensorrt_gpu():
        assert rc == 0 and (out / "model.engine").is_file()
    else:  # no TensorRT/GPU: one sentence, and the ONNX bundle is complete
        assert rc == 3 and "cannot build a TensorRT engine" in captured.err and f"the ONNX bundle at {out} is complete" in captured.err
    b = Bundle.load(out)
    assert b.precision == "fp16"
    model = onnx.shape_inference.infer_shapes(onnx.load(str(b.onnx_path)))
    types = {vi.name: vi.type.tensor_type.elem_type for vi in [*model.graph.value_info, *model.graph.input, *model.graph.output]}
    F32, F16 = onnx.TensorProto.FLOAT, onnx.TensorProto.FLOAT16
    assert {t.data_type for t in model.graph.initializer if t.name.endswith("weight")} == {F16}  # half weights
    assert all(types[x.name] == F32 for x in [*model.graph.input, *model.graph.output])  # float IO
    # the float tail: softmax, the descriptor norm and the division by it (integer shape arithmetic aside)
    tail = [n for n in model.graph.node if n.op_type in ("Softmax", "ReduceL2", "Div") and types[n.input[0]] != onnx.TensorProto.INT64]
    assert sorted(n.op_type for n in tail) == ["Div", "ReduceL2", "Softmax"]
    assert all(types[n.input[0]] == F32 for n in tail)
    p = b.parity
    # the issue's FP16 targets; AUC within one pair's weight (see the module docstring)
    assert p["keypoint_repeatability"] >= 0.95 and p["descriptor_cosine"] >= 0.99
    assert abs(p["auc10_torch"] - p["auc10_onnx"]) <= _one_pair(p)


def _repeatability(bundle: Path, frames: list[np.ndarray]) -> tuple[float, float]:
    """Fraction of the torch model's top-32 keypoints the bundle reproduces within 1 px on ``frames``,
    and the mean descriptor cosine at those keypoints (the parity measures, without the pose protocol)."""
    model, cfg, _ = load_model("superlite")
    ref, det = TorchDetector(model, cfg, threshold=0.0), BundleDetector(bundle, threshold=0.0)
    hits, total, cos = 0, 0, []
    for m in frames:
        kr, kb = ref(m, top_k=32), det(m, top_k=32)
        d = np.linalg.norm(kr.xy[:, None] - kb.xy[None], axis=-1)
        ok = d.min(1) <= 1
        hits, total = hits + int(ok.sum()), total + len(kr)
        cos.append(np.sum(kr.descriptors[ok] * kb.descriptors[d.argmin(1)[ok]], axis=1))
    return hits / total, float(np.concatenate(cos).mean())


def test_int8_qat_cpu_bundle(tiny, tmp_path, frames):
    out = tmp_path / "superlite-int8"
    # no parity.json here: on ~19 tiny pairs the issue's 2-point INT8 AUC target is below one pair's
    # weight (5.3 points), so the keypoint and descriptor measures are checked directly instead
    assert _export(tiny, out, "--precision", "int8", "--target", "cpu", "--qat-steps", "2", "--qat-batch", "2",
                   "--qat-override", "data.num_workers=0", parity=False) == 0
    b = Bundle.load(out)
    q = b.meta["quantization"]
    assert (b.precision, b.target, q["method"], q["steps"]) == ("int8", "cpu", "qat", 2)
    assert q["activation_types"] == ["uint8"] and q["weight_types"] == ["int8"]  # U8S8
    assert np.isfinite(q["loss_first"]) and np.isfinite(q["loss_last"])
    model = onnx.load(str(b.onnx_path))
    ops = [n.op_type for n in model.graph.node]
    assert ops.count("QuantizeLinear") >= 8 and "BatchNormalization" not in ops  # every conv quantised, BN folded
    consumers = {i: n.op_type for n in model.graph.node for i in n.input}
    producers = {o: n.op_type for n in model.graph.node for o in n.output}
    softmax = next(n for n in model.graph.node if n.op_type == "Softmax")
    assert consumers[softmax.output[0]] != "QuantizeLinear"  # probabilities stay float
    assert all(producers[o.name] != "DequantizeLinear" for o in model.graph.output)  # outputs are float ops' results
    # Quantisation of all 8 convolutions plus two fine-tuning steps: most keypoints stay within 1 px
    # (0.93 with 4 steps observed in the full parity check) and descriptors point the same way (0.9994)
    rep, cos = _repeatability(out, frames)
    assert rep >= 0.8 and cos >= 0.98
    kp = BundleDetector(out).detect(np.stack(frames[:2]))
    assert len(kp) == 2 and all(len(k) > 0 and k.descriptors.dtype == np.int8 for k in kp)


def test_int8_ptq_tensorrt_bundle_is_symmetric(tiny, tmp_path, frames):
    out = tmp_path / "superlite-int8-trt"
    assert _export(tiny, out, "--precision", "int8", "--ptq", "--target", "tensorrt", parity=False) == 0
    b = Bundle.load(out)
    q = b.meta["quantization"]
    assert (q["method"], b.target) == ("ptq", "tensorrt") and b.parity == {"computed": False, "reason": "no parity data given (--no-parity)"}
    assert q["nonzero_zero_points"] == 0 and q["activation_types"] == ["int8"] and q["weight_types"] == ["int8"]
    assert any("softmax" in n for n in q["kept_float"]) and any("norm" in n for n in q["kept_float"])
    # each head's last convolution keeps float weights (no DequantizeLinear makes them), every other one is quantised
    model = onnx.load(str(out / "model.onnx"))
    producers = {o: n.op_type for n in model.graph.node for o in n.output}
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    float_convs = {n.name for n in convs if producers.get(n.input[1]) != "DequantizeLinear"}
    assert float_convs == {n for n in q["kept_float"] if n in {c.name for c in convs}} and len(float_convs) == 3
    assert len(convs) - len(float_convs) == 8  # the shipped SuperLitE's 11: encoder 4, heads' first 2, branch's first 2
    rep, cos = _repeatability(out, frames)
    assert rep >= 0.75 and cos >= 0.98  # 0.87 and 0.9998 observed for PTQ on tiny (symmetric int8 of every convolution)


def test_head_output_convolutions_of_the_shipped_superlite():
    """The default bundle's graph (SuperLitE with the full-resolution branch): the convolutions that feed
    the post-processing tail are the three heads' output layers, named by their weights."""
    model = onnx.load(str(default_bundle_path() / "model.onnx"))
    names = head_output_convolutions(model, postprocess_nodes(model))
    weights = {n.name: n.input[1] for n in model.graph.node if n.op_type == "Conv"}
    assert sorted(weights[n] for n in names) == ["net.descriptor.out.weight", "net.detector.out.weight",
                                                 "net.detector_pixel.out.weight"]


def test_tensorrt_engine_builds(fp32_bundle, tmp_path):
    if not _tensorrt_gpu():
        pytest.skip("needs TensorRT and a CUDA GPU (the no-GPU path is checked in the fp16 test)")
    from aerovis_export.exporter import add_engine

    bundle = tmp_path / "with-engine"
    shutil.copytree(fp32_bundle, bundle)
    info = add_engine(bundle, timing_cache=tmp_path / "timing.cache")
    b = Bundle.load(bundle)
    assert (bundle / "model.engine").stat().st_size > 0 and (tmp_path / "timing.cache").is_file()
    assert b.meta["tensorrt"]["profile"]["opt"] == [2, 8, 48, 64] and info["engine"] == "model.engine"


# ---------------------------------------------------------------------------------------------
# MaxViT (SuperEvent/SuperEvent+ encoder), tools, the shipped default bundle
# ---------------------------------------------------------------------------------------------
def test_maxvit_bundle(tiny, tmp_path, capsys):
    from aerovis_train.models import build_model

    torch.manual_seed(3)
    cfg = {"name": "tiny_maxvit", "encoder": "maxvit", "in_channels": 8, "descriptor_dim": 16, "head_width": 32,
           "encoder_conf": {"width_mult": 0.5, "out_channels": 32, "mbconv": False},
           "mcts": {"kind": "ne", "params": [0.03, 0.1, 0.3, 1.0]}}
    net = build_model(cfg).eval()
    ckpt = save_slim(cfg, net.state_dict(), tmp_path / "tiny_maxvit.pt")
    out = tmp_path / "maxvit"
    # --fixed-hw: a real fixed-resolution bundle, and half the export time of a dynamic MaxViT graph
    # (whose symbolic attention partitions torch.export takes ~40 s to prove on this box; the dynamic
    # MaxViT export is exercised by the SuperEvent+ bundle of the benchmark, see the README)
    assert _export(tiny, out, "--precision", "fp32", "--fixed-hw", model=str(ckpt), hw=("40", "40"), parity=False) == 0
    assert _export(tiny, tmp_path / "bad", "--precision", "fp32", model=str(ckpt), parity=False) == 2
    assert "--height 48 is not a positive multiple of 40" in capsys.readouterr().err
    b = Bundle.load(out)
    assert (b.size_multiple, b.dynamic_hw, b.height, b.width, b.descriptor_dim) == (40, False, 40, 40, 16)
    assert b.inputs["mcts"][1:] == [8, 40, 40] and isinstance(b.inputs["mcts"][0], str)  # fixed H, W; dynamic batch
    det = BundleDetector(b)
    x = torch.rand(3, 8, 40, 40, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        ref = net(x)
    s, g = det.dense(x.numpy())
    np.testing.assert_allclose(s, ref["scores"].numpy(), atol=1e-5)  # float32 summation order, as above
    np.testing.assert_allclose(g, ref["descriptors"].numpy(), atol=1e-5)
    with pytest.raises(DataError, match="multiples of 40, got 48x64"):
        det.dense(np.zeros((1, 8, 48, 64), np.float32))
    with pytest.raises(DataError, match=r"takes only 40x40 \(dynamic_hw is false\), got 40x80"):
        det.dense(np.zeros((1, 8, 40, 80), np.float32))
    kps = det.detect(np.random.default_rng(0).random((2, 8, 48, 64), dtype=np.float32))  # cropped top-left to 40x40
    assert len(kps) == 2 and all(kp.xy.max() < 40 for kp in kps if len(kp))


def test_bench_detector_prints_one_line_per_bundle(fp32_bundle, capsys):
    from aerovis_train.bench import main as bench_main

    assert bench_main(["detector", str(fp32_bundle), str(fp32_bundle), "--repeats", "2", "--warmup", "1"]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(lines) == 2
    for r in lines:
        assert {"bundle", "model", "precision", "latency_ms_p50", "latency_ms_p90", "total_ms_p50"} <= set(r)
        assert (r["model"], r["precision"], r["batch"], r["height"], r["width"]) == ("superlite", "fp32", 2, 48, 64)
        # each total includes its inference, so the medians keep that order
        assert 0 < r["latency_ms_p50"] <= r["latency_ms_p90"] and r["total_ms_p50"] >= r["latency_ms_p50"]


def test_benchmark_bundles_times_blocks_after_one_untimed_run_per_switch(fp32_bundle, monkeypatch):
    """Two bundles, 7 repeats in blocks of 3: A A A A | B B B B | A A A A | B B B B | A A | B B after
    one warm-up each, where the first run of every block is untimed (the other session's spinning
    threads hold the cores then); each bundle is timed exactly 7 times."""
    from aerovis_slam import bundle as bundle_mod

    calls = []
    real_detect = bundle_mod.BundleDetector.detect

    def counting_detect(self, batch, **kw):
        calls.append(self.tag)
        return real_detect(self, batch, **kw)

    monkeypatch.setattr(bundle_mod.BundleDetector, "detect", counting_detect)
    real_init = bundle_mod.BundleDetector.__init__
    tags = iter("AB")

    def tagging_init(self, *a, **kw):
        real_init(self, *a, **kw)
        self.tag = next(tags)

    monkeypatch.setattr(bundle_mod.BundleDetector, "__init__", tagging_init)
    out = bundle_mod.benchmark_bundles([fp32_bundle, fp32_bundle], repeats=7, warmup=1, block=3)
    assert "".join(calls) == "A" + "B" + "AAAA" + "BBBB" + "AAAA" + "BBBB" + "AA" + "BB"
    assert [r["repeats"] for r in out] == [7, 7] and [r["block"] for r in out] == [3, 3]
    # one bundle alone never switches: no untimed runs besides the warm-up
    calls.clear()
    tags = iter("C")
    bundle_mod.benchmark_bundles([fp32_bundle], repeats=4, warmup=2, block=3)
    assert "".join(calls) == "C" * 6
    with pytest.raises(ValueError, match="block"):
        bundle_mod.benchmark_bundles([fp32_bundle], repeats=4, block=0)
    assert bundle_mod.benchmark_bundles([], repeats=4) == []


def test_bench_blas_times_inference_after_products_per_blas_setting(fp32_bundle):
    from aerovis_slam.benchmarks import bench_blas

    r = bench_blas(fp32_bundle, height=48, width=64, products_ms=2.0, repeats=3, warmup=1)
    assert r["resolution"] == [64, 48] and r["products_per_frame"] >= 1
    assert set(r["infer_ms_p50"]) == {"blas_own_threads", "blas_1_thread", "alone"}
    assert all(v > 0 for v in r["infer_ms_p50"].values()) and all(v > 0 for v in r["products_ms_p50"].values())
    for key, ratio in r["slowdown"].items():  # each against the floor measured in the same run (rounded to 0.01)
        assert ratio == pytest.approx(r["infer_ms_p50"][key] / r["infer_ms_p50"]["alone"], abs=0.01)
    assert r["meets_target"] == (r["slowdown"]["blas_1_thread"] <= 1.1)
    assert r["blas"] and all(b["library"] and b["num_threads"] >= 1 for b in r["blas"])  # numpy's BLAS, found


def test_eval_pose_takes_a_bundle(fp32_bundle, tiny, capsys):
    from aerovis_train.eval.cli import main as eval_main

    rc = eval_main(["pose", "--data", str(tiny), "--model", str(fp32_bundle), "superlite", "--max-angle-deg", "10",
                    "--max-dt-s", "1", "--max-pairs", "4", "--quiet"])
    assert rc == 0
    onnx_run, torch_run = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert (onnx_run["model"], torch_run["model"]) == ("superlite-fp32", "superlite")
    assert onnx_run["pairs"] == torch_run["pairs"] > 0
    assert abs(onnx_run["auc10"] - torch_run["auc10"]) <= 100.0 / onnx_run["pairs"]  # same keypoints (FP32), one pair's weight


def test_default_bundle_is_the_shipped_superlite():
    b = Bundle.load(default_bundle_path())
    assert (b.name, b.precision, b.dynamic_hw, b.height, b.width, b.batch) == ("superlite", "fp32", True, 240, 424, 2)
    # regenerate with `python -m aerovis_export.default_bundle` whenever superlite.pt changes
    assert b.meta["source"]["sha256"] == file_sha256(WEIGHTS_DIR / "superlite.pt")
    model, cfg, _ = load_model("superlite")
    ref, det = TorchDetector(model, cfg), BundleDetector(b)
    x = synthetic_mcts(b, 1)[0]
    for crop in (x, x[:, :176, :240]):  # the drone rig's 240x424 and a DAVIS240's 176x240 (after cropping)
        s_ref, g_ref = ref.dense(crop)
        s, g = det.dense(crop[None])
        np.testing.assert_allclose(s[0], s_ref, atol=1e-5)
        np.testing.assert_allclose(g[0], g_ref, atol=1e-5)
