"""Architecture search: per-job metrics.json from a real Hydra sweep, the leaderboard and Pareto front
on hand-made jobs with known answers, the Optuna driver, the SLURM launcher config, the results page."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

torch = pytest.importorskip("torch", reason="the search trains networks (train extra)")

from aerovis_slam.errors import DataError  # noqa: E402
from aerovis_train.search import cli as search_cli  # noqa: E402
from aerovis_train.search.leaderboard import pareto_front, summarize_dir  # noqa: E402
from aerovis_train.search.metrics import METRICS_FORMAT, latency_resolution, write_json  # noqa: E402

from conftest import REPO_ROOT  # noqa: E402


# ---------------------------------------------------------------------------------------------
# Pareto front and leaderboard on hand-made jobs
# ---------------------------------------------------------------------------------------------
def test_pareto_front_known_answer():
    # (latency ms, AUC@10): A fast/good, B slower/better, C dominated by A (slower and worse),
    # D dominated by B (same AUC, slower), E fastest/worst, F has no latency, G equals A exactly
    lat = [10, 20, 15, 30, 5, float("nan"), 10]
    auc = [30, 40, 25, 40, 10, 50, 30]
    assert pareto_front(auc, lat).tolist() == [True, True, False, False, True, False, True]
    # one point alone is its own front; all-NaN has none
    assert pareto_front([1.0], [1.0]).tolist() == [True]
    assert pareto_front([float("nan")], [1.0]).tolist() == [False]
    # brute force on random points: on the front <=> no other point at least as good in both and better in one
    rng = np.random.default_rng(0)
    a, t = rng.integers(0, 6, 40).astype(float), rng.integers(0, 6, 40).astype(float)  # many ties on purpose
    front = pareto_front(a, t)
    for i in range(40):
        dominated = any(a[j] >= a[i] and t[j] <= t[i] and (a[j] > a[i] or t[j] < t[i]) for j in range(40))
        assert front[i] == (not dominated)


def fake_job(root: Path, name: str, auc10, latency, encoder="vgg_lite", dim=64, params=887_425, extra_ov=()):
    """A metrics.json as train.py writes it, with hand-picked numbers."""
    m = {"format": METRICS_FORMAT, "overrides": ["model=superlite", f"model.encoder={encoder}", f"model.descriptor_dim={dim}",
                                                 "trainer.max_time=00:00:03:00", *extra_ov],
         "model": "superlite", "encoder": encoder, "encoder_conf": {}, "descriptor_dim": dim, "parameters": params, "flops": 6.2e9,
         "auc5": None if auc10 is None else auc10 / 2, "auc10": auc10, "auc20": None if auc10 is None else auc10 * 1.5,
         "latency_ms": latency, "latency": None if latency is None else {"resolution": [424, 240]},
         "latency_error": None if latency is not None else "not measured", "steps": 100, "train_wall_s": 180.0}
    write_json(root / name / "metrics.json", m)


def test_leaderboard_order_pareto_and_outputs(tmp_path, capsys):
    root = tmp_path / "multirun"
    fake_job(root, "0", 30.0, 60.0)                                  # front (fastest with AUC 30)
    fake_job(root, "1", 40.0, 250.0, encoder="maxvit", dim=256)      # front (best AUC)
    fake_job(root, "2", 40.0, 300.0, encoder="maxvit", dim=128)      # same AUC as 1 but slower: rank 3, dominated
    fake_job(root, "10", 25.0, 80.0, encoder="vgg", dim=64)          # dominated by 0
    fake_job(root, "3", None, 50.0, encoder="mobilenetv3", dim=64)   # never validated: last, never on the front
    # Hydra's record of the sweep command
    (root / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {"overrides": {"task": [
        "model=superlite", "model.encoder=vgg_lite,vgg,mobilenetv3,maxvit", "model.descriptor_dim=64,128,256"]}}}))
    assert search_cli.main(["summarize", str(root)]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["jobs"] == 5 and line["best"] == "1" and line["pareto"] == ["0", "1"]  # front ordered by latency
    assert line["command"] == "python train.py -m model=superlite model.encoder=vgg_lite,vgg,mobilenetv3,maxvit model.descriptor_dim=64,128,256"
    rows = list(csv.DictReader((root / "leaderboard.csv").open()))
    assert [r["job"] for r in rows] == ["1", "2", "0", "10", "3"]  # AUC@10 desc, tie 40/40 by latency, missing AUC last
    assert [r["pareto"] for r in rows] == ["True", "False", "True", "False", "False"]
    # only the overrides that vary between jobs describe them; the common max_time does not
    assert rows[0]["config"] == "model.encoder=maxvit model.descriptor_dim=256"
    md = (root / "leaderboard.md").read_text().splitlines()
    assert len(md) == 2 + 5 and md[2].startswith("| 1 | 1 | model.encoder=maxvit model.descriptor_dim=256 | 0.89 | 6.20 | 20.0 | 40.0 | 60.0 | 250.0 | yes |")
    assert (root / "pareto.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((root / "search_summary.json").read_text())
    assert summary["leaderboard"][0]["rank"] == 1 and summary["with_latency"] == 5


def test_summarize_bad_input(tmp_path, capsys):
    assert search_cli.main(["summarize", str(tmp_path)]) == 2
    assert f"{tmp_path}: holds no metrics.json" in capsys.readouterr().err
    (tmp_path / "0").mkdir()
    (tmp_path / "0" / "metrics.json").write_text(json.dumps({"format": "something else"}))
    assert search_cli.main(["summarize", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "0/metrics.json: field 'format' should be 'aerovis-metrics/1'" in err and "Traceback" not in err


def test_latency_resolution_crops_to_the_size_multiple():
    assert latency_resolution(8) == (240, 424)
    assert latency_resolution(40) == (240, 400)  # MaxViT: sides must be multiples of 8 x partition 5
    with pytest.raises(ValueError, match="smaller than"):
        latency_resolution(40, 32, 424)


def test_crop_fits_the_model(capsys):
    from omegaconf import OmegaConf

    from aerovis_train.training import fit_crop

    cfg = OmegaConf.create({"data": {"crop": [160, 224], "crop_fit": "shrink"}, "model": {"encoder": "maxvit"}})
    assert fit_crop(cfg, 8) == (160, 224) and capsys.readouterr().err == ""
    assert fit_crop(cfg, 40) == (160, 200)
    assert "data.crop=[160, 224] is not a multiple of 40" in capsys.readouterr().err
    cfg.data.crop_fit = "error"
    with pytest.raises(DataError, match="must be a multiple of 40"):
        fit_crop(cfg, 40)
    cfg.data.crop_fit, cfg.data.crop = "shrink", [32, 224]
    with pytest.raises(DataError, match="a side below 40"):
        fit_crop(cfg, 40)


# ---------------------------------------------------------------------------------------------
# A real sweep: two tiny jobs through Hydra's multirun, each writing metrics.json
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sim_cache(tiny_cache):
    return tiny_cache  # the session's `tiny` preset (conftest.py)


def test_sweep_jobs_write_metrics(tmp_path, sim_cache, capsys):
    from aerovis_train.models import build_model, count_flops, count_parameters

    sweep = tmp_path / "multirun"
    cmd = [sys.executable, str(REPO_ROOT / "train.py"), "-m", "data.preset=tiny", f"data.cache_dir={sim_cache}", "data.val_sequences=1",
           "data.samples_per_epoch=4", "data.batch_size=2", "data.num_workers=0", "val.max_pairs=3", "val.rate_hz=20",
           "trainer.max_steps=2", "data.crop=[40,56]", "torch_threads=1", "metrics.repeats=2",
           "model.descriptor_dim=32,64", f"hydra.sweep.dir={sweep}"]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    jobs = {m["descriptor_dim"]: m for m in (json.loads(p.read_text()) for p in sorted(sweep.glob("*/metrics.json")))}
    assert sorted(jobs) == [32, 64]
    for dim, m in jobs.items():
        assert f"model.descriptor_dim={dim}" in m["overrides"] and "trainer.max_steps=2" in m["overrides"]
        run = Path(m["run_dir"])
        summary = json.loads((run / "summary.json").read_text())
        # AUC@10 of the re-validated selected checkpoint equals the score that selected it: the same
        # deterministic validation code (seeded RANSAC) on the same weights, so equal up to float32 logging
        assert m["auc10"] == pytest.approx(summary["best_val_auc10"], abs=1e-4)
        assert 0 <= m["auc5"] <= m["auc10"] <= m["auc20"] <= 100  # AUC grows with the threshold
        net = build_model({"name": "superlite", "encoder": "vgg_lite", "in_channels": 8, "descriptor_dim": dim,
                           "detector_pixel": {"width": 16, "depth": 3}})  # model=superlite's default
        assert m["parameters"] == count_parameters(net) and m["flops_input"] == [1, 8, 240, 424]
        assert m["flops"] == count_flops(net, (1, 8, 240, 424))
        assert m["latency_error"] is None and m["latency_ms"] > 0, m["latency_error"]
        lat = m["latency"]
        assert lat["resolution"] == [424, 240] and lat["batch"] == 2 and lat["precision"] == "fp32" and lat["note"] is None
        assert m["crop"] == [40, 56] and Path(m["checkpoint"]).exists() and Path(m["weights"]).exists()
        assert m["environment"]["packages"]["torch"] == torch.__version__  # what the job was measured with
        # the latency was measured on the bundle kept beside the job, which holds this job's network
        meta = json.loads((run / "bundle_fp32" / "metadata.json").read_text())
        assert meta["descriptor_dim"] == dim and (meta["width"], meta["height"], meta["batch"]) == (424, 240, 2)
    # and the summariser reads the sweep
    assert search_cli.main(["summarize", str(sweep)]) == 0
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line["jobs"] == 2 and line["with_latency"] == 2 and "model.descriptor_dim=32,64" in line["command"]
    assert 1 <= len(line["pareto"]) <= 2 and (sweep / "pareto.png").exists()
    # timing the kept bundles again, together, replaces each job's figure and keeps the job's own
    assert search_cli.main(["retime", str(sweep), "--repeats", "2"]) == 0
    retimed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["retimed"]
    assert sorted(j["job"] for j in retimed) == ["0", "1"]
    for j in retimed:
        m = json.loads((sweep / j["job"] / "metrics.json").read_text())
        assert m["latency_ms"] == j["latency_ms"] == m["latency"]["latency_ms"] > 0 and m["latency"]["retimed"]
        assert m["latency_in_job"]["latency_ms"] == jobs[m["descriptor_dim"]]["latency_ms"]
        assert m["latency"]["resolution"] == [424, 240] and m["latency"]["repeats"] == 2


# ---------------------------------------------------------------------------------------------
# Optuna driver
# ---------------------------------------------------------------------------------------------
def test_optuna_driver_runs_and_resumes(tmp_path):
    from aerovis_train.search.optuna_search import run_study

    seen = []

    def cheap_train(cfg, overrides):
        # stands in for a training job: a known function of the sampled architecture, written as a job would
        auc = cfg.model.descriptor_dim / 8 + 10 * cfg.model.encoder_conf.width_mult
        seen.append((cfg.model.encoder, cfg.model.descriptor_dim, cfg.model.encoder_conf.width_mult, list(overrides), cfg.run_dir))
        fake_job(Path(cfg.run_dir).parent, Path(cfg.run_dir).name, auc, 100.0, encoder=cfg.model.encoder, dim=cfg.model.descriptor_dim)
        return auc

    out = tmp_path / "study"
    ov = [f"search.out_dir={out}", "search.n_trials=2", "search.sampler.name=random", "trainer.max_time=00:00:01:00"]
    s = run_study("optuna", ov, train_fn=cheap_train, progress=False)
    assert s["complete"] == 2 and len(seen) == 2
    for enc, dim, wm, overrides, run_dir in seen:
        assert enc in ("vgg_lite", "vgg", "mobilenetv3", "maxvit") and dim in (64, 128, 256) and wm in (0.5, 0.75, 1.0)
        # the job sees exactly the sampled overrides plus the common ones, not the search's own
        assert f"model.encoder={enc}" in overrides and "trainer.max_time=00:00:01:00" in overrides
        assert not any(o.startswith("search.") for o in overrides)
        assert (Path(run_dir) / "metrics.json").exists()
    best = max(s["trials"], key=lambda t: t["auc10"])
    assert s["best"]["number"] == best["number"]
    assert best["auc10"] == pytest.approx(best["params"]["model.descriptor_dim"] / 8 + 10 * best["params"]["+model.encoder_conf.width_mult"])
    # a second run continues the same study from its SQLite storage
    s2 = run_study("optuna", [*ov[:1], "search.n_trials=1", *ov[2:]], train_fn=cheap_train, progress=False)
    assert s2["complete"] == 3 and (out / "optuna.db").exists()
    assert len(list(csv.DictReader((out / "trials.csv").open()))) == 3
    # the study folder summarises like a sweep, with the driver's command
    summary = summarize_dir(out)
    assert summary["jobs"] == 3 and summary["command"].startswith("aerovis-search optuna --search=optuna")


def test_search_configs_compose_into_buildable_models():
    from omegaconf import OmegaConf

    from aerovis_train.models import build_model
    from aerovis_train.search.optuna_search import compose_train_config

    for name, n_obj in (("optuna", 1), ("optuna_pareto", 2)):
        cfg = compose_train_config([f"+search={name}", "run_dir=."])
        s = OmegaConf.to_container(cfg.search, resolve=True)
        assert len(s["objectives"]) == n_obj and s["out_dir"].endswith(s["study_name"])
    # every encoder choice with the extremes of the other parameters is a valid training config
    params = {p["name"]: p for p in s["params"]}
    for enc in params["model.encoder"]["choices"]:
        ov = [f"model.encoder={enc}", f"model.descriptor_dim={params['model.descriptor_dim']['choices'][-1]}",
              f"model.head_width={params['model.head_width']['choices'][0]}",
              f"+model.encoder_conf.width_mult={params['+model.encoder_conf.width_mult']['low']}", "run_dir=."]
        net = build_model(compose_train_config(ov).model)
        assert net.encoder_name == enc
    # the detector branch's choices are override strings (Optuna's categories cannot be dicts)
    from aerovis_train.search.optuna_search import _override_value

    built = [build_model(compose_train_config([f"model.detector_pixel={_override_value(v)}", "run_dir=."]).model)
             for v in params["model.detector_pixel"]["choices"]]
    assert [n.metadata()["detector_pixel"] for n in built] == [None, {"width": 16, "depth": 3, "within_cell": False}]


def test_optuna_bad_search_config(tmp_path, capsys):
    code = search_cli.main(["optuna", f"search.out_dir={tmp_path}", "search.params=[{name: model.encoder, type: choice}]"])
    err = capsys.readouterr().err
    assert code == 2 and "conf/search/optuna.yaml" in err and "type: categorical|int|float" in err


def test_slurm_launcher_config():
    conf = yaml.safe_load((REPO_ROOT / "conf" / "hydra" / "launcher" / "slurm.yaml").read_text())
    assert conf["defaults"] == ["submitit_slurm", "_self_"]
    # every key must be a field of hydra-submitit-launcher's SlurmQueueConf (1.2), or Hydra rejects the
    # config on the cluster: a misspelt key would only show up there
    fields = {"submitit_folder", "timeout_min", "cpus_per_task", "gpus_per_node", "tasks_per_node", "mem_gb", "nodes", "name",
              "stderr_to_stdout", "partition", "qos", "comment", "constraint", "exclude", "gres", "cpus_per_gpu", "gpus_per_task",
              "mem_per_gpu", "mem_per_cpu", "account", "signal_delay_s", "max_num_timeout", "additional_parameters",
              "array_parallelism", "setup", "_target_"}
    assert set(conf) - {"defaults"} <= fields
    assert conf["timeout_min"] > 0 and conf["max_num_timeout"] >= 0


# ---------------------------------------------------------------------------------------------
# results page
# ---------------------------------------------------------------------------------------------
def test_results_page_verdicts(tmp_path):
    from aerovis_train.search.results import write_results

    def row(method, kind, mcts, auc10, onnx=None, lat=10.0):
        return {"method": method, "kind": kind, "mcts": mcts, "auc5": auc10 / 2, "auc10": auc10, "auc20": auc10 * 1.4, "matches": 50.0,
                "inlier_ratio": 0.5, "latency_ms": lat, "onnx_fp32_ms": onnx, "parameters": 900_000, "source": f"/w/{method}.pt",
                **({"onnx": {"latency_ms": onnx, "batch": 2, "resolution": [400, 240], "block": 5}} if onnx else {})}

    cmp = {"command": "aerovis-eval compare --data bench --onnx-latency --out X", "pairs": 303, "sequences": ["/c/a.h5", "/c/b.h5"],
           "skipped": ["/c/slider.h5"], "missing": [],
           "rows": [row("superlite", "learned", "ne", 34.0, 60.0), row("superevent_plus", "learned", "ne", 40.0, 240.0),
                    row("superevent", "learned", "dt", 32.0, 250.0), row("orb", "classical", "ne", 33.0), row("sift", "classical", "ne", 20.0)]}
    # per-pair errors of the two MaxViT models: a constant 2 deg vs 4 deg on every pair, 3 start frames of 2 pairs
    # (every resample has N = 6 pairs). pose_auc's recall curve for N equal errors e rises from (0, 0) to (e, 1/N),
    # then steps to 1: AUC@10 = (e / (2 N) + 10 - e) / 10, i.e. 49/60 and 38/60, a gain of 11/38 = 28.9 % on every
    # resample, so the interval collapses to that value (the summary rows above are independent inputs)
    pairs = [{"t0_us": t0, "t1_us": t0 + 1} for t0 in (0, 0, 5, 5, 9, 9)]
    cmp["results"] = {m: [{"sequence": "/c/a.h5", "auc10": a, "pairs": 6, "per_pair": [{**p, "rot_err_deg": e} for p in pairs]}]
                      for m, e, a in (("superevent_plus", 2.0, 49 / 0.6), ("superevent", 4.0, 38 / 0.6))}
    write_json(tmp_path / "cmp" / "compare.json", cmp)
    sweep = tmp_path / "sweep"
    fake_job(sweep, "0", 30.0, 60.0)
    fake_job(sweep, "1", 35.0, 90.0, dim=128)
    r = write_results(tmp_path / "docs" / "results.md", tmp_path / "cmp", [str(sweep)])
    v = r["verdicts"]
    assert v["ablation"]["gain_pct"] == pytest.approx(100 * (40 - 32) / 32) and v["ablation"]["ne_beats_dt"]
    assert v["ablation"]["gain_ci95"] == pytest.approx([100 * 11 / 38] * 2)
    assert v["lite"]["auc_ratio_pct"] == pytest.approx(85.0) and v["lite"]["auc_ok"]  # 34/40 is exactly the 85 % target
    assert v["lite"]["speedup"] == pytest.approx(4.0) and v["lite"]["speed_ok"]
    # superevent (32.0) is below orb (33.0): the "every learned model beats every baseline" target fails
    assert v["classical"] == {"learned_beat_classical": False, "worst_learned": "superevent", "best_classical": "orb"}
    text = (tmp_path / "docs" / "results.md").read_text()
    assert "25.0 % (95 % interval +28.9 to +28.9 %, paired bootstrap over 3 start frames) (paper: +18.7 %)" in text
    assert "**not met** (weakest learned: superevent 32.0 %, strongest classical: orb 33.0 %)" in text
    assert "The interval resamples the pairs of one training run per model, not the training" in text
    # the per-sequence table lists the methods with per-sequence results, in the summary's order
    assert "| method | a (6 pairs) |\n|---|---:|\n| superevent_plus | 81.7 |\n| superevent | 63.3 |" in text
    assert "Best on each sequence: a: superevent_plus." in text
    assert "round-robin in blocks of 5 runs, each block after one untimed run" in text  # how the bundles were timed
    assert "aerovis-eval compare --data bench --onnx-latency --out X" in text and "| 1 | 1 | model.descriptor_dim=128 |" in text
    assert (tmp_path / "docs" / "results_search1_pareto.png").exists() and "(results_search1_pareto.png)" in text


def test_results_seed_ablation(tmp_path):
    """The ablation over several runs per time surface: the runs grouped by their MCTS, their means
    compared, and an interval that resamples the runs too (a known answer on constant errors)."""
    from aerovis_train.search.results import write_results

    # 6 pairs of 3 start frames; every model has one error on all of them. pose_auc gives AUC@10 =
    # (e / 12 + 10 - e) / 10 for N = 6 equal errors e: 49/60 at 2 deg, 38/60 at 4 deg (see the test above)
    pairs = [{"t0_us": t0, "t1_us": t0 + 1} for t0 in (0, 0, 5, 5, 9, 9)]
    err = {"ne0": 2.0, "ne1": 4.0, "dt0": 4.0, "dt1": 4.0, "orb": 1.0, "superlite": 1.0}
    rows = [{"method": m, "kind": "classical" if m == "orb" else "learned", "mcts": m[:2] if m[:2] in ("ne", "dt") else "ne",
             "auc5": 0.0, "auc10": 100 * (e / 12 + 10 - e) / 10, "auc20": 0.0, "matches": 40.0, "inlier_ratio": 0.5,
             "latency_ms": 5.0, "source": f"/w/{m}.pt"} for m, e in err.items()]
    cmp = {"command": "aerovis-eval compare --data bench --models ne0=A ne1=B dt0=C dt1=D --out Y", "pairs": 6,
           "sequences": ["/c/a.h5"], "rows": rows,
           "results": {m: [{"sequence": "/c/a.h5", "auc10": 0.0, "pairs": 6, "per_pair": [{**p, "rot_err_deg": e} for p in pairs]}]
                       for m, e in err.items()}}
    write_json(tmp_path / "seeds" / "compare.json", cmp)
    # the shipped superlite (MCTS_Ne, 1 deg) is not one of the runs: the label filter leaves it out
    r = write_results(tmp_path / "results.md", ablation=tmp_path / "seeds", ablation_methods=r"^(ne|dt)\d+$",
                      ablation_title="SuperLitE, two seeds")
    v = r["verdicts"]["seed_ablation"]
    assert v["runs"] == {"ne": 2, "dt": 2} and v["ne_beats_dt"]
    # means 43.5/60 vs 38/60: +14.47 %. A resample draws ne0 twice (+28.9 %), once (+14.5 %) or never (0 %) with
    # probabilities 1/4, 1/2, 1/4 (the pairs cancel: every model is constant), so the 2.5 and 97.5 percentiles are
    # exactly 0 and 11/38
    assert v["gain_pct"] == pytest.approx(100 * 5.5 / 38)
    assert v["gain_ci95"] == pytest.approx([0.0, 100 * 11 / 38])
    assert v["ne_wins"] == 2  # ne0 beats both dt runs; ne1 ties them
    text = (tmp_path / "results.md").read_text()
    assert "MCTS_Ne 72.5 ± 13.0 % over 2 runs (63.3-81.7), MCTS_dt 63.3 ± 0.0 % over 2 runs (63.3-63.3)" in text
    assert "(means): +14.5 % (95 % interval +0.0 to +28.9 %, bootstrap over 3 start frames and the runs of each side)" in text
    assert "| superlite |" not in text and "| orb |" not in text
    assert "## MCTS_Ne vs MCTS_dt over several training runs: SuperLitE, two seeds\n" in text
    assert "--ablation-methods '^(ne|dt)\\d+$' --ablation-title 'SuperLitE, two seeds'" in text
    # without the filter the shipped MCTS_Ne model joins its side; a side without models is reported, not divided by
    r = write_results(tmp_path / "r2.md", ablation=tmp_path / "seeds", ablation_methods="^ne")
    assert r["verdicts"]["seed_ablation"]["ne_beats_dt"] is None and "Not measured: no learned MCTS_dt model" in (tmp_path / "r2.md").read_text()
    with pytest.raises(DataError, match="--ablation-methods"):
        write_results(tmp_path / "r3.md", ablation=tmp_path / "seeds", ablation_methods="(ne")
    assert not (tmp_path / "r3.md").exists()
    # repeated --ablation: one section each, its methods and title paired by position (the same folder twice
    # here: the second section keeps the first seed of each side, ne0 at 2 deg against dt0 at 4 deg: 49/38 - 1)
    r = write_results(tmp_path / "r4.md", ablation=[tmp_path / "seeds", tmp_path / "seeds"],
                      ablation_methods=[r"^(ne|dt)\d+$", r"^(ne|dt)0$"], ablation_title=["two seeds", "seed 0"])
    v1, v2 = r["verdicts"]["seed_ablation1"], r["verdicts"]["seed_ablation2"]
    assert v1["gain_pct"] == pytest.approx(100 * 5.5 / 38) and v2["runs"] == {"ne": 1, "dt": 1}
    assert v2["gain_pct"] == pytest.approx(100 * 11 / 38)
    text = (tmp_path / "r4.md").read_text()
    assert text.index("training runs: two seeds\n") < text.index("training runs: seed 0\n")
    assert "--ablation-methods '^(ne|dt)0$' --ablation-title 'seed 0'" in text
    with pytest.raises(DataError, match="at most one of each per --ablation"):
        write_results(tmp_path / "r5.md", ablation=tmp_path / "seeds", ablation_title=["a", "b"])
    assert not (tmp_path / "r5.md").exists()


def test_results_other_surface_ceiling_and_kept_sections(tmp_path, capsys):
    """The classical detectors on another time surface, the protocol's ceiling (perfect matches of each
    method's keypoints) and sections carried over from the page as it stood, on hand-made comparisons."""
    def row(method, kind, mcts, auc10, **extra):
        return {"method": method, "kind": kind, "mcts": mcts, "auc5": auc10 / 2, "auc10": auc10, "auc20": auc10 * 1.4,
                "matches": 40.0, "inlier_ratio": 0.5, "latency_ms": 5.0, "source": f"/w/{method}.pt", **extra}

    same = {"pairs": 6, "sequences": ["/c/bench-seed0/a.h5"], "t_start_us": {"/c/bench-seed0/a.h5": 100}}
    main = {"command": "aerovis-eval compare --data bench --out M", **same,
            "rows": [row("superlite", "learned", "ne", 34.0), row("superevent", "learned", "dt", 24.0),
                     row("orb", "classical", "ne", 30.0), row("sift", "classical", "ne", 20.0)]}
    dt = {"command": "aerovis-eval compare --data bench --classical-mcts dt --out D", **same,
          "rows": [row("superevent", "learned", "dt", 24.0), row("orb", "classical", "dt", 33.0), row("sift", "classical", "dt", 22.0)]}

    def oracle(c0, c1, i1):  # levels 0 / 0.5 / 1 / 2 px; the statements quote 1 px, the level nearest CEILING_REFERENCE_PX
        return [{"noise_px": n, "auc10": c, "auc10_at_inliers": a, "matches": 100.0}
                for n, c, a in ((0.0, c0, c0), (0.5, c1 + 5, i1 + 5), (1.0, c1, i1), (2.0, c1 - 5, i1 - 5))]

    truth = {"superlite": (90.0, 75.0, 60.0, 12.0, 1.6), "orb": (88.0, 70.0, 50.0, 8.0, 1.3)}
    ceil = {"command": "aerovis-eval compare --data bench --oracle-noise-px 0 0.5 1 2 --out C", **same,
            "rows": [row(m, "learned" if m == "superlite" else "classical", "ne", {"superlite": 34.0, "orb": 30.0}[m],
                         oracle=oracle(c0, c1, i1), correct_matches_1px=3.0, correct_matches_3px=n3, correct_error_px=err)
                     for m, (c0, c1, i1, n3, err) in truth.items()],
            "results": {m: [{"sequence": "/c/bench-seed0/a.h5", "pairs": 6, "auc10": 34.0, "matches": 40.0, "correct_matches_3px": n3,
                             "correct_error_px": err, "oracle": oracle(c0, c1, i1),
                             "per_pair": [{"inliers": k} for k in (10, 20, 10, 20, 10, 20)]}]
                        for m, (c0, c1, i1, n3, err) in truth.items()}}
    for name, c in (("main", main), ("dt", dt), ("ceil", ceil)):
        write_json(tmp_path / name / "compare.json", c)
    page = tmp_path / "results.md"
    page.write_text("# Results\n\nold header\n\n## Search: old grid\n\nkept text | 1 |\n\n![plot](results_search1_pareto.png)\n\n"
                    "## Another\n\nnot kept\n")
    rc = search_cli.main(["results", "--compare", str(tmp_path / "main"), "--classical", str(tmp_path / "dt"),
                          "--ceiling", str(tmp_path / "ceil"), "--keep", "Search: old", "--out", str(page)])
    assert rc == 0
    v = json.loads(capsys.readouterr().out)["verdicts"]
    text = page.read_text()
    # another surface: ORB and SIFT against their MCTS_Ne rows of the same pairs; superevent (24) < orb (33) there
    assert v["classical_surface"]["against_main"]["orb"] == {"auc10": 33.0, "auc10_main": 30.0, "mcts_main": "ne"}
    assert v["classical_surface"]["learned_beat_classical"] is False
    assert "## Classical baselines on MCTS_dt\n" in text and "6 pairs, the same as in the tables above" in text
    assert "orb 33.0 % on MCTS_dt against 30.0 % on MCTS_Ne; sift 22.0 % on MCTS_dt against 20.0 % on MCTS_Ne." in text
    assert "**not met** (weakest learned: superevent 24.0 % on MCTS_dt, strongest classical: orb 33.0 % on MCTS_dt)" in text
    # the ceiling: twice ORB's 30 % is 60 %, 80 % of SuperLitE's 75 % at 1 px; its own 34 % is 45 % of the ceiling
    c = v["ceiling"]
    assert c["noise_px"] == 1.0 and c["ceiling_auc10"] == {"superlite": 75.0, "orb": 70.0}
    assert c["target_auc10"] == pytest.approx(60.0) and c["target_pct_of_ceiling"] == pytest.approx(80.0)
    assert "Twice ORB's AUC@10 (60.0 %, #4's target) is 80 % of SuperLitE's ceiling at 1 px (75.0 %); with as many " \
           "perfect matches as SuperLitE's RANSAC keeps, the ceiling is 60.0 %." in text
    assert "AUC@10 is 70.0-75.0 % at 1 px of noise whichever method's keypoints are matched (all in view; 88.0-90.0 % at 0 px, " \
           "75.0-80.0 % at 0.5 px, 65.0-70.0 % at 2 px)" in text
    assert "superlite 45 %, orb 43 %" in text  # 34 / 75, 30 / 70
    assert "superlite 12.0 of 40.0 (30 %), orb 8.0 of 40.0 (20 %)" in text
    # per sequence: own / ceiling / at own inliers; matches, mean inliers (15), correct within 3 px, their error
    assert "| superlite | 34.0 / 75.0 / 60.0; 40, 15, 12.0, 1.60 px |" in text
    # the kept section verbatim, after the generated ones, named in the header; the rest of the old page is gone
    assert text.index("## The protocol's ceiling") < text.index("## Search: old grid\n\nkept text | 1 |\n\n![plot](results_search1_pareto.png)\n")
    assert "Carried over verbatim" in text and '"Search: old"' in text and "not kept" not in text and "old header" not in text
    assert "--keep 'Search: old'" in text
    # bad input: a heading the page lacks, a ceiling run without --oracle-noise-px; the page is left as it was
    before = page.read_text()
    assert search_cli.main(["results", "--compare", str(tmp_path / "main"), "--keep", "Nowhere", "--out", str(page)]) == 2
    assert "no section headed '## Nowhere...' to keep" in capsys.readouterr().err
    assert search_cli.main(["results", "--ceiling", str(tmp_path / "main"), "--out", str(page)]) == 2
    assert "no row has field 'oracle'" in capsys.readouterr().err
    assert page.read_text() == before


def test_results_two_recipes(tmp_path):
    """Two training recipes over several runs each, picked by label: the same known answer as the
    seed ablation above (constant errors per model), the other methods listed as references."""
    from aerovis_train.search.results import write_results

    pairs = [{"t0_us": t0, "t1_us": t0 + 1} for t0 in (0, 0, 5, 5, 9, 9)]
    err = {"d0": 2.0, "d1": 4.0, "h0": 4.0, "h1": 4.0, "orb": 1.0}
    rows = [{"method": m, "kind": "classical" if m == "orb" else "learned", "mcts": "ne", "auc5": 0.0,
             "auc10": 100 * (e / 12 + 10 - e) / 10, "auc20": 0.0, "matches": 40.0, "inlier_ratio": 0.5, "latency_ms": 5.0,
             "source": f"/w/{m}.pt"} for m, e in err.items()]
    cmp = {"command": "aerovis-eval compare --data bench --models d0=A d1=B h0=C h1=D --detectors orb --out R", "pairs": 6,
           "sequences": ["/c/a.h5"], "rows": rows,
           "results": {m: [{"sequence": "/c/a.h5", "auc10": 100 * (e / 12 + 10 - e) / 10, "pairs": 6,
                            "per_pair": [{**p, "rot_err_deg": e} for p in pairs]}] for m, e in err.items()}}
    write_json(tmp_path / "runs" / "compare.json", cmp)
    r = write_results(tmp_path / "results.md", recipes=tmp_path / "runs", recipe=[r"dual=^d\d$", r"hinge=^h\d$"],
                      recipes_title="SuperLitE, two seeds")
    v = r["verdicts"]["recipes"]
    # means 43.5/60 against 38/60 (+14.5 %; ORB at 1 deg: (1/12 + 9)/10 = 90.8 %); the interval's ends as in test_results_seed_ablation: 0 and 11/38
    assert v["runs"] == {"dual": 2, "hinge": 2} and v["a_beats_b"] and v["wins"] == 2
    assert v["gain_pct"] == pytest.approx(100 * 5.5 / 38) and v["gain_ci95"] == pytest.approx([0.0, 100 * 11 / 38])
    text = (tmp_path / "results.md").read_text()
    assert "## dual vs hinge over several training runs: SuperLitE, two seeds\n" in text
    assert "| orb | reference | 0.0 | 90.8 | 0.0 |" in text and "| d0 | dual |" in text
    assert "| run | a |\n|---|---:|\n| d0 | 81.7 |\n| d1 | 63.3 |\n| h0 | 63.3 |\n| h1 | 63.3 |\n| orb | 90.8 |" in text
    assert "Relative AUC@10 gain of dual over hinge (means): +14.5 % (95 % interval +0.0 to +28.9 %" in text
    assert "--recipe 'dual=^d\\d$' --recipe 'hinge=^h\\d$' --recipes-title 'SuperLitE, two seeds'" in text
    with pytest.raises(DataError, match="exactly two NAME=REGEX"):
        write_results(tmp_path / "r2.md", recipes=tmp_path / "runs", recipe=["dual=^d"])
    r = write_results(tmp_path / "r3.md", recipes=tmp_path / "runs", recipe=["dual=^d", "hinge=^x"])
    assert r["verdicts"]["recipes"]["a_beats_b"] is None and "Not measured: no run of hinge" in (tmp_path / "r3.md").read_text()
