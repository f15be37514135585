"""Guided architecture search with Optuna (>= 4), configured by ``conf/search/<name>.yaml``.

    aerovis-search optuna [--search optuna] [search.n_trials=40] [TRAIN OVERRIDES ...]

e.g. ``aerovis-search optuna search.n_trials=30 trainer.max_time=00:00:20:00``. Each trial
samples the parameters of ``search.params`` (Hydra overrides such as ``model.encoder`` or
``+model.encoder_conf.width_mult``), composes the training config exactly as
``python train.py OVERRIDES SAMPLED`` would, and runs one training job in this process
(:func:`aerovis_train.training.train`) in ``search.out_dir/trial_NNNN``; that job writes its
``metrics.json``, whose fields ``search.objectives`` name (``auc10`` to maximise; add
``latency_ms`` to minimise for a two-objective search with a Pareto front).

Why a driver of our own rather than hydra-optuna-sweeper: that plugin's last release pins
optuna < 3 and breaks with SQL storage under SQLAlchemy 2 (REFERENCE.md section 7). Driving
``train()`` directly needs no plugin and keeps Hydra's config composition.

The study lives in ``search.storage`` (default ``sqlite:///<out_dir>/optuna.db``): an interrupted
search continues where it stopped when run again with the same config (``load_if_exists``), and
several machines can work on one study by pointing ``search.storage`` at a shared database
server (PostgreSQL/MySQL URL; SQLite is for one machine). The driver writes ``study.json`` (the
command, the best trial(s), every trial) and ``trials.csv`` in ``out_dir``; ``aerovis-search
summarize <out_dir>`` turns the trials' ``metrics.json`` into a leaderboard and Pareto plot.
"""

from __future__ import annotations

import csv
import io
import math
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from aerovis_slam.errors import DataError

from .metrics import METRICS_FILE, load_metrics, write_json, write_text

SAMPLERS = ("tpe", "random", "nsga2", "qmc", "gp", "grid")


def compose_train_config(overrides: Sequence[str], conf_dir: str | Path | None = None) -> DictConfig:
    """The config ``python train.py OVERRIDES`` composes (``run_dir`` must be among the overrides:
    outside a Hydra run there is no output directory to default to). ``conf_dir`` defaults to the
    repository's ``conf/`` (:data:`aerovis_train.models.CONF_DIR`)."""
    from hydra import compose, initialize_config_dir

    if conf_dir is None:
        from aerovis_train.models import CONF_DIR as conf_dir
    with initialize_config_dir(config_dir=str(Path(conf_dir).resolve()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def _sampler(spec: dict, params: list[dict]):
    import optuna

    name = str(spec.get("name", "tpe")).lower()
    seed = spec.get("seed")
    kwargs = dict(spec.get("kwargs") or {})
    if name == "tpe":
        return optuna.samplers.TPESampler(seed=seed, **kwargs)
    if name == "random":
        return optuna.samplers.RandomSampler(seed=seed, **kwargs)
    if name == "nsga2":
        return optuna.samplers.NSGAIISampler(seed=seed, **kwargs)
    if name == "qmc":
        return optuna.samplers.QMCSampler(seed=seed, **kwargs)
    if name == "gp":
        return optuna.samplers.GPSampler(seed=seed, **kwargs)
    if name == "grid":
        space = {}
        for p in params:
            if p["type"] != "categorical":
                raise DataError(None, f"search.sampler.name=grid needs categorical params only; {p['name']!r} is {p['type']}")
            space[p["name"]] = list(p["choices"])
        return optuna.samplers.GridSampler(space, seed=seed, **kwargs)
    raise DataError(None, f"search.sampler.name must be one of {SAMPLERS}, not {name!r}")


def _suggest(trial, p: dict):
    """One sampled value of parameter spec ``p`` (``{name, type, choices | low, high[, step, log]}``)."""
    kind = p.get("type")
    name = p["name"]
    if kind == "categorical":
        return trial.suggest_categorical(name, list(p["choices"]))
    if kind == "int":
        return trial.suggest_int(name, int(p["low"]), int(p["high"]), step=int(p.get("step") or 1), log=bool(p.get("log", False)))
    if kind == "float":
        step = p.get("step")
        return trial.suggest_float(name, float(p["low"]), float(p["high"]), step=None if step is None else float(step),
                                   log=bool(p.get("log", False)))
    raise DataError(None, f"search.params entry {name!r}: type must be categorical, int or float, not {kind!r}")


def _override_value(v) -> str:
    if isinstance(v, float):
        return repr(round(v, 10))
    return str(v)


def _check_search(scfg: dict, where: str) -> None:
    """DataError naming the search config (``where``) and the field unless ``scfg`` is usable."""
    for key in ("study_name", "n_trials", "objectives", "params"):
        if scfg.get(key) is None:
            raise DataError(where, f"field {key!r} is missing (see conf/search/optuna.yaml)")
    for o in scfg["objectives"]:
        if not isinstance(o, dict) or not o.get("metric") or o.get("direction") not in ("maximize", "minimize"):
            raise DataError(where, f"objectives entry {o!r}: expected {{metric: <metrics.json field>, direction: maximize|minimize}}")
    for p in scfg["params"]:
        if not isinstance(p, dict) or not p.get("name") or p.get("type") not in ("categorical", "int", "float"):
            raise DataError(where, f"params entry {p!r}: expected {{name: <override key>, type: categorical|int|float, ...}}")
        need = ("choices",) if p["type"] == "categorical" else ("low", "high")
        if any(p.get(k) is None for k in need):
            raise DataError(where, f"params entry {p['name']!r} of type {p['type']} needs {' and '.join(need)}")
    names = [p["name"] for p in scfg["params"]]
    if len(set(names)) != len(names):
        raise DataError(where, f"params need unique names (Hydra override keys), got {names}")


def run_study(search: str = "optuna", overrides: Sequence[str] = (), *, conf_dir: str | Path | None = None,
              train_fn: Callable[[DictConfig, list[str]], float] | None = None, progress: bool = True) -> dict:
    """Run (or continue) the Optuna study that ``conf/search/<search>.yaml`` describes.

    Args:
        search: name of the search config in ``conf/search/``.
        overrides: ``search.*`` overrides of the search config and training overrides applied
            to every trial (e.g. ``trainer.max_time=00:00:20:00``).
        conf_dir: the Hydra config folder (default: the repository's ``conf/``).
        train_fn: ``(cfg, overrides) -> value`` run per trial; default
            :func:`aerovis_train.training.train`. It must leave ``metrics.json`` in ``cfg.run_dir``.
        progress: one line per finished trial on stderr.
    Returns:
        The content of ``study.json``: ``command``, ``study_name``, ``storage``, ``objectives``,
        ``best`` (best trial, or the Pareto-optimal trials of a multi-objective study), ``trials``.
    """
    import optuna

    search_ov = [o for o in overrides if o.split("=", 1)[0].lstrip("+~").startswith("search.")]
    train_ov = [o for o in overrides if o not in search_ov]
    base = compose_train_config([f"+search={search}", *overrides, "run_dir=."], conf_dir)
    scfg = OmegaConf.to_container(base.search, resolve=True)
    _check_search(scfg, f"conf/search/{search}.yaml (with overrides {search_ov})" if search_ov else f"conf/search/{search}.yaml")
    out_dir = Path(scfg.get("out_dir") or f"multirun/optuna/{scfg['study_name']}").resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    storage = scfg.get("storage") or f"sqlite:///{out_dir / 'optuna.db'}"
    objectives = [dict(o) for o in scfg["objectives"]]
    params = [dict(p) for p in scfg["params"]]
    if not progress:
        optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(study_name=scfg["study_name"], storage=storage, sampler=_sampler(scfg.get("sampler") or {}, params),
                                directions=[o["direction"] for o in objectives], load_if_exists=True)
    if train_fn is None:
        from aerovis_train.training import train as train_fn  # noqa: N813 - the default per-trial job
    command = "aerovis-search optuna " + " ".join(shlex.quote(a) for a in [f"--search={search}", *overrides])

    def objective(trial) -> float | list[float]:
        sampled = [f"{p['name']}={_override_value(_suggest(trial, p))}" for p in params]
        run_dir = out_dir / f"trial_{trial.number:04d}"
        job_ov = [*train_ov, *sampled]
        cfg = compose_train_config([*job_ov, f"run_dir={run_dir}"], conf_dir)
        trial.set_user_attr("run_dir", str(run_dir))
        trial.set_user_attr("overrides", job_ov)
        t0 = time.time()
        returned = float(train_fn(cfg, job_ov))
        mpath = run_dir / METRICS_FILE
        metrics = load_metrics(mpath) if mpath.is_file() else {}
        values = []
        for o in objectives:
            v = returned if o["metric"] == "returned" else metrics.get(o["metric"])
            if v is None or not math.isfinite(float(v)):
                raise DataError(mpath, f"objective {o['metric']!r} is missing or not finite ({v!r}); the trial counts as failed")
            values.append(float(v))
        if progress:
            print(f"aerovis-search: trial {trial.number}: {' '.join(sampled)} -> "
                  + ", ".join(f"{o['metric']} {v:.3f}" for o, v in zip(objectives, values)) + f" ({time.time() - t0:.0f} s)", file=sys.stderr)
        return values[0] if len(values) == 1 else values

    # a trial whose config is invalid (unknown encoder option, crop too small) or whose training
    # diverges is recorded as failed and the search goes on
    try:
        study.optimize(objective, n_trials=int(scfg["n_trials"]), timeout=scfg.get("timeout_s"),
                       catch=(DataError, ValueError, FloatingPointError), gc_after_trial=True)
    finally:  # an interrupted search still leaves its record (the storage has every finished trial anyway)
        summary = _study_summary(study, command, storage, objectives, out_dir)
        write_json(out_dir / "study.json", summary)
        write_text(out_dir / "trials.csv", _trials_csv(summary["trials"], params, objectives))
    return summary


def _trial_dict(t, objectives: list[dict]) -> dict:
    vals = t.values or []
    return {"number": t.number, "state": t.state.name, "params": t.params,
            **{o["metric"]: (vals[i] if i < len(vals) else None) for i, o in enumerate(objectives)},
            "run_dir": t.user_attrs.get("run_dir"), "overrides": t.user_attrs.get("overrides"),
            "duration_s": t.duration.total_seconds() if t.duration else None}


def _study_summary(study, command: str, storage: str, objectives: list[dict], out_dir: Path) -> dict:
    from optuna.trial import TrialState

    trials = [_trial_dict(t, objectives) for t in study.trials]
    done = [t for t in study.trials if t.state == TrialState.COMPLETE]
    if not done:
        best = None
    elif len(objectives) == 1:
        best = _trial_dict(study.best_trial, objectives)
    else:
        best = [_trial_dict(t, objectives) for t in study.best_trials]
    return {"command": command, "study_name": study.study_name, "storage": storage, "out_dir": str(out_dir),
            "objectives": objectives, "complete": len(done), "failed": sum(t.state == TrialState.FAIL for t in study.trials),
            "best": best, "trials": trials}


def _trials_csv(trials: list[dict], params: list[dict], objectives: list[dict]) -> str:
    buf = io.StringIO()
    fields = ["number", "state", *[o["metric"] for o in objectives], *[p["name"] for p in params], "duration_s", "run_dir"]
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for t in trials:
        w.writerow({**{k: t.get(k) for k in fields if k in t}, **{p["name"]: t["params"].get(p["name"]) for p in params}})
    return buf.getvalue()
