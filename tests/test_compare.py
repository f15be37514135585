"""``aerovis-eval compare``: learned models (on their own time surfaces) and classical baselines in
one run on the `tiny` preset, on exactly the same pairs."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import onnxruntime
import pytest

torch = pytest.importorskip("torch", reason="learned models need the train extra (torch)")

from aerovis_slam.errors import DataError  # noqa: E402
from aerovis_slam.io.sequence import Sequence  # noqa: E402
from aerovis_train.checkpoints import SHIPPED, WEIGHTS_DIR, save_slim  # noqa: E402
from aerovis_train.eval import cli  # noqa: E402
from aerovis_train.eval.compare import JSON_KEYS  # noqa: E402
from aerovis_train.eval.pose import evaluate_sequence, plan_frames  # noqa: E402
from aerovis_train.models import build_model  # noqa: E402

DT_CFG = {"name": "dt_net", "encoder": "vgg_lite", "encoder_conf": {"width_mult": 0.25}, "in_channels": 10, "descriptor_dim": 32,
          "head_width": 32, "mcts": {"kind": "dt", "params": [1, 3, 10, 30, 100]}}


@pytest.fixture(scope="module")
def tiny(tiny_cache):
    from aerovis_slam.sim.cache import ensure_preset

    return Path(ensure_preset("tiny", str(tiny_cache), progress=False))


@pytest.fixture(scope="module")
def dt_model(tmp_path_factory):
    """A small untrained network on MCTS_dt (SuperEvent's surface): its warm-up differs from MCTS_Ne's."""
    torch.manual_seed(0)
    return save_slim(DT_CFG, build_model(DT_CFG).state_dict(), tmp_path_factory.mktemp("w") / "dt_net.pt")


def test_compare_same_pairs_one_table(tiny, dt_model, tmp_path, capsys):
    out = tmp_path / "cmp"
    argv = ["compare", "--data", str(tiny), "--models", "superlite", "superevent_plus", f"dt={dt_model}", "--detectors", "orb", "sift",
            "--max-pairs", "4", "--out", str(out)]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    lines = [json.loads(x) for x in captured.out.strip().splitlines()]
    shipped_plus = (WEIGHTS_DIR / "superevent_plus.pt").exists()
    expected = ["superlite", *(["superevent_plus"] if shipped_plus else []), "dt", "orb", "sift"]
    assert [x["method"] for x in lines] == expected
    for x in lines:
        assert list(x)[: len(JSON_KEYS)] == list(JSON_KEYS)  # the issue's keys first, in its order
        assert 0 <= x["auc5"] <= x["auc10"] <= x["auc20"] <= 100 and 0 <= x["inlier_ratio"] <= 1 and x["latency_ms"] > 0
    assert {x["pairs"] for x in lines} == {lines[0]["pairs"]} and lines[0]["pairs"] > 0
    assert [x["mcts"] for x in lines if x["method"] in ("superlite", "dt", "orb")] == ["ne", "dt", "ne"]
    if not shipped_plus:  # a shipped name without installed weights is reported, not fatal
        assert "no weights installed for superevent_plus" in captured.err
    assert "| method | kind | MCTS | AUC@5 | AUC@10 |" in captured.err  # the table

    doc = json.loads((out / "compare.json").read_text())
    assert doc["missing"] == ([] if shipped_plus else ["superevent_plus"])
    assert [r["method"] for r in doc["rows"]] == expected and doc["command"].startswith("aerovis-eval compare --data")
    assert doc["host"]["environment"]["packages"]["onnxruntime"] == onnxruntime.__version__
    # every method saw the same (sequence, t0, t1) pairs
    keys = {m: [(r["sequence"], p["t0_us"], p["t1_us"]) for r in res for p in r["per_pair"]] for m, res in doc["results"].items()}
    assert all(k == keys["orb"] for k in keys.values()) and len(keys["orb"]) == lines[0]["pairs"]
    # the common start is the later of the two surfaces' warm-ups, so both are warm at every frame
    for seq_path, t_start in doc["t_start_us"].items():
        with Sequence(seq_path) as seq:
            first = {k: int(plan_frames(seq, mcts_kind=k, rate_hz=20.0).times_us[0]) for k in ("ne", "dt")}
            assert t_start == max(first.values())
            assert seq.time_range("cam0")[0] + 100_000 <= t_start  # MCTS_dt's longest window (100 ms) has elapsed
    assert [r["method"] for r in csv.DictReader((out / "compare.csv").open())] == expected
    assert "pairs on" in (out / "compare.md").read_text()

    # the figures are those of a plain evaluation started at the same frame (nothing compare-specific)
    seq_path, t_start = next(iter(doc["t_start_us"].items()))
    ref = evaluate_sequence(seq_path, "orb", mcts_kind="ne", rate_hz=20.0, max_pairs=4, t_start_us=t_start)
    orb_seq = next(r for r in doc["results"]["orb"] if r["sequence"] == seq_path)
    assert [p["rot_err_deg"] for p in orb_seq["per_pair"]] == [p["rot_err_deg"] for p in ref["per_pair"]]


def test_compare_bad_input(tmp_path, capsys):
    assert cli.main(["compare", "--data", str(tmp_path / "nope"), "--detectors", "orb", "--models"]) == 2
    assert f"{tmp_path / 'nope'}: no such file or folder" in capsys.readouterr().err
    assert cli.main(["compare", "--data", str(tmp_path), "--models", str(tmp_path / "missing.pt")]) == 2
    err = capsys.readouterr().err
    assert "missing.pt: no such checkpoint" in err and "Traceback" not in err
    only_missing = [n for n in SHIPPED if not (WEIGHTS_DIR / f"{n}.pt").exists()]
    if only_missing:  # nothing left to compare: said plainly
        assert cli.main(["compare", "--data", str(tmp_path), "--models", *only_missing, "--detectors"]) == 2
        assert "nothing to compare" in capsys.readouterr().err


def test_compare_bundle_model_with_onnx_latency(tiny, tmp_path, capsys):
    from aerovis_slam.bundle import Bundle, default_bundle_path

    try:
        bundle = default_bundle_path()
    except DataError as exc:  # the shipped bundle is written by aerovis-export; a checkout without it has none to run
        pytest.skip(f"no shipped default bundle: {exc}")
    argv = ["compare", "--data", str(tiny), "--models", f"lite_onnx={bundle}", "--detectors", "orb", "--max-pairs", "2",
            "--onnx-latency", "--quiet"]
    assert cli.main(argv) == 0
    rows = {x["method"]: x for x in map(json.loads, capsys.readouterr().out.strip().splitlines())}
    b = Bundle.load(bundle)
    lite = rows["lite_onnx"]
    # an exported bundle runs in ONNX Runtime on the model's own surface and is timed as exported
    assert lite["kind"] == "learned" and lite["mcts"] == b.mcts_kind and lite["runtime"] == f"onnxruntime {b.precision}"
    key = "onnx_fp32_ms" if b.precision == "fp32" else "onnx_ms"
    assert lite[key] > 0 and lite["onnx"]["resolution"] == [b.width, b.height] and lite["onnx"]["batch"] == b.batch
    assert "onnx_fp32_ms" not in rows["orb"]  # classical baselines have no network to time
    assert lite["pairs"] == rows["orb"]["pairs"] > 0


def test_onnx_latency_times_every_model_at_one_size(tiny, tmp_path):
    """A MaxViT model (sides multiples of 40) and a convolutional one (multiples of 8) are both timed at
    400x240, the largest size both accept, so that their latency ratio compares the same input."""
    from types import SimpleNamespace

    from aerovis_train.eval.compare import markdown_table, onnx_figures

    torch.manual_seed(0)
    conv = build_model(DT_CFG).eval()
    vit_cfg = {"name": "vit", "encoder": "maxvit", "encoder_conf": {"width_mult": 0.25, "out_channels": 32},
               "in_channels": 8, "descriptor_dim": 16, "head_width": 16, "mcts": {"kind": "ne", "params": [0.03, 0.1, 0.3, 1.0]}}
    vit = build_model(vit_cfg).eval()
    assert (conv.size_multiple, vit.size_multiple) == (8, 40)
    methods = [SimpleNamespace(label=name, detector=SimpleNamespace(model=m)) for name, m in (("conv", conv), ("vit", vit))]
    seq = sorted(tiny.glob("*.h5"))[0]
    figures = onnx_figures(methods, calibration=seq, repeats=2, warmup=1)
    for name in ("conv", "vit"):
        assert figures[name]["onnx_fp32_ms"] > 0
        assert figures[name]["onnx"]["resolution"] == [400, 240] and figures[name]["onnx"]["batch"] == 2
        assert figures[name]["onnx"]["requested"] == [424, 240] and "cropped to 400x240" in figures[name]["onnx"]["note"]
        assert figures[name]["onnx"]["block"] == 5  # timed in blocks between switches (benchmark_bundles' default)
    rows = [{"method": n, "kind": "learned", "mcts": "ne", "auc5": 1.0, "auc10": 2.0, "auc20": 3.0, "matches": 1.0,
             "inlier_ratio": 0.5, "latency_ms": 1.0, **figures[n]} for n in ("conv", "vit")]
    assert "ONNX FP32 (ms, 2x400x240)" in markdown_table(rows)
    # alone, the convolutional model keeps the full 424x240
    alone = onnx_figures(methods[:1], calibration=seq, repeats=2, warmup=1)
    assert alone["conv"]["onnx"]["resolution"] == [424, 240]


def test_compare_oracle_rows_and_table(tmp_path, capsys):
    """``compare --oracle-noise-px``: each row carries the ceiling and correct-match figures that a
    plain evaluation with the oracle gives at the same start, and the table gains a second part.
    (A 1 s spin of the drone rig at half size: ORB finds nothing at the tiny preset's 64x48.)"""
    from aerovis_slam.sim import SequenceSpec, write_sequence

    seq = tmp_path / "spin.h5"
    write_sequence(SequenceSpec("spin", rig="drone424", rig_scale=0.5, trajectory="spin", trajectory_seed=4, scene_seed=4,
                                duration_s=1.0, frame_rate_hz=20, gt_rate_hz=200), seq)
    out = tmp_path / "cmp"
    assert cli.main(["compare", "--data", str(seq), "--models", "--detectors", "orb", "--max-dt-s", "1", "--max-angle-deg", "10",
                     "--oracle-noise-px", "0", "1", "--quiet", "--out", str(out)]) == 0
    row = json.loads(capsys.readouterr().out.strip())
    doc = json.loads((out / "compare.json").read_text())
    t_start = doc["t_start_us"][str(seq)]
    ref = evaluate_sequence(seq, "orb", mcts_kind="ne", rate_hz=20.0, max_dt_s=1.0, max_angle_deg=10.0, t_start_us=t_start,
                            oracle_noise_px=(0.0, 1.0))
    assert row["oracle"] == ref["oracle"] and row["correct_matches_3px"] == ref["correct_matches_3px"]
    assert row["correct_error_px"] == ref["correct_error_px"] and [o["noise_px"] for o in row["oracle"]] == [0.0, 1.0]
    md = (out / "compare.md").read_text()
    assert "The protocol's ceiling" in md and "| orb |" in md.split("The protocol's ceiling")[1]
