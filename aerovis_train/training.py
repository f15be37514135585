"""The training job behind ``python train.py``: data, module, callbacks, trainer, summary.

Every job ends by writing ``metrics.json`` beside ``model.pt`` (parameters, FLOPs, validation
AUC@5/10/20 of the selected checkpoint, ONNX Runtime latency, the Hydra overrides that define it;
see :mod:`aerovis_train.search.metrics`), which ``aerovis-search summarize`` turns into a
leaderboard.

Resuming: a run directory that already holds ``checkpoints/last.ckpt`` continues from it (run the
same command with ``hydra.run.dir=<that directory>``); ``last.ckpt`` is refreshed every
``checkpoint_every_min`` minutes and at the end of each validation, so an interruption loses at most
that much work. ``best.ckpt`` (highest validation AUC@10) is written atomically. ``model.pt`` holds the best
checkpoint's weights, or with ``weights=last`` the final step's (fixed-budget runs to compare).
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import Callback, ModelCheckpoint, TQDMProgressBar
from lightning.pytorch.loggers import CSVLogger, TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from aerovis_slam.errors import DataError

from .checkpoints import AtomicCheckpointIO, lightning_model_state, save_slim
from .data import EventPairDataset, make_loader, mcts_spec_from_config
from .homographic import HomographyRange, RealViewDataset
from .labels import CornerLabeller
from .models import count_parameters
from .losses import descriptor_loss_terms, repeatability_weight
from .module import KeypointModule

#: what ``model.pt`` (and ``metrics.json``) hold: the highest validation AUC@10, or the final step
WEIGHT_SELECTIONS = ("best", "last")


class _EpochSetter(Callback):
    """Gives the dataset the epoch number so random pairs differ between epochs, reproducibly."""

    def __init__(self, *datasets):
        self.datasets = [d for d in datasets if d is not None]

    def on_train_epoch_start(self, trainer, pl_module):
        for d in self.datasets:
            d.set_epoch(trainer.current_epoch)


class LastCheckpoint(Callback):
    """Keeps ``path`` (``last.ckpt``, what a resumed run continues from) current: written after every
    validation, every ``every_min`` minutes of training in between, and when training ends.

    Written by hand because Lightning's ``save_last=True`` does not do this: on the callback that
    keeps the best checkpoint it refreshes ``last.ckpt`` only when the best improves, and a second,
    time-triggered callback with ``save_last`` writes ``last-v1.ckpt`` beside it, since the name is
    taken (a 4.5-minute GPU run of this trainer left ``last.ckpt`` at step 400 of 2472, its best).
    The file goes through the trainer's checkpoint IO (:class:`AtomicCheckpointIO`: never half-written).
    """

    def __init__(self, path: str | os.PathLike, every_min: float):
        self.path = Path(path)
        self.interval_s = float(every_min) * 60.0
        self._t_saved = time.monotonic()
        self._step_saved = -1

    def on_train_start(self, trainer, pl_module):
        self._t_saved = time.monotonic()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        due = time.monotonic() - self._t_saved >= self.interval_s
        # all ranks must agree (saving is collective under DDP), as Lightning's own time trigger does
        if trainer.strategy.broadcast(due):
            self._save(trainer)

    def on_validation_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self._save(trainer)  # also at a step saved by time: the checkpoint then holds this validation

    def on_train_end(self, trainer, pl_module):
        if trainer.global_step != self._step_saved:
            self._save(trainer)

    def _save(self, trainer) -> None:
        trainer.save_checkpoint(self.path)
        self._t_saved = time.monotonic()
        self._step_saved = trainer.global_step


def checkpoint_callbacks(ckpt_dir: str | os.PathLike, every_min: float) -> tuple[ModelCheckpoint, LastCheckpoint]:
    """(``best.ckpt`` by validation AUC@10, ``last.ckpt`` kept current by :class:`LastCheckpoint`)."""
    ckpt_dir = Path(ckpt_dir)
    best = ModelCheckpoint(dirpath=ckpt_dir, filename="best", monitor="val/auc10", mode="max", save_top_k=1, save_last=False)
    return best, LastCheckpoint(ckpt_dir / "last.ckpt", every_min)


def expand_sequences(items) -> list[Path]:
    """Config items (``.h5`` files or folders of them) as sequence paths: a folder gives its ``*.h5``, sorted."""
    out = []
    for item in items or []:
        p = Path(str(item)).expanduser()
        out.extend(sorted(p.glob("*.h5")) if p.is_dir() else [p])
    return out


def sequences_from_config(data_cfg) -> tuple[list[Path], list[Path]]:
    """(train paths, validation paths) from ``cfg.data``: a simulator preset (generated on first use
    into the cache) or explicit lists/folders of canonical sequences."""
    if data_cfg.get("preset"):
        from aerovis_slam.sim.cache import ensure_preset

        folder = ensure_preset(data_cfg.preset, data_cfg.get("cache_dir"), seed=int(data_cfg.get("seed", 0)),
                               workers=data_cfg.get("sim_workers"))
        paths = sorted(Path(folder).glob("*.h5"))
        n_val = int(data_cfg.get("val_sequences", 2))
        if len(paths) <= n_val:
            raise DataError(folder, f"preset {data_cfg.preset!r} has {len(paths)} sequences; need more than data.val_sequences={n_val}")
        return paths[:-n_val], paths[-n_val:]

    train, val = expand_sequences(data_cfg.get("train")), expand_sequences(data_cfg.get("val"))
    if not train:
        raise DataError(None, "data.train lists no sequences (give .h5 files or folders of them)")
    for p in train + val:
        if not p.exists():
            raise DataError(p, "training sequence not found")
    return train, val


def fit_crop(cfg: DictConfig, size_multiple: int) -> tuple[int, int] | None:
    """``cfg.data.crop`` (h, w) fitted to a model whose input sides must be multiples of ``size_multiple``.

    With ``data.crop_fit=shrink`` (the default) a crop that is no multiple is shrunk to the
    nearest multiples below, with a message on stderr: one sweep can then mix encoders of
    different multiples (``model.encoder=vgg_lite,maxvit``: 160x224 trains MaxViT on 160x200).
    ``data.crop_fit=error`` refuses such a crop instead.

    Raises:
        DataError: the crop is no multiple and ``crop_fit`` is ``error``, or a side is smaller
            than one multiple.
    """
    crop = tuple(int(v) for v in cfg.data.crop) if cfg.data.get("crop") else None
    if crop is None or not (crop[0] % size_multiple or crop[1] % size_multiple):
        return crop
    policy = str(cfg.data.get("crop_fit") or "shrink")
    if policy not in ("shrink", "error"):
        raise DataError(None, f"data.crop_fit must be 'shrink' or 'error', not {policy!r}")
    fitted = (crop[0] // size_multiple * size_multiple, crop[1] // size_multiple * size_multiple)
    if policy == "error" or min(fitted) == 0:
        why = "" if policy == "error" else f"; a side below {size_multiple} cannot be shrunk to one"
        raise DataError(None, f"data.crop={list(crop)} must be a multiple of {size_multiple} for encoder {cfg.model.encoder}{why}")
    print(f"train.py: note: data.crop={list(crop)} is not a multiple of {size_multiple} (encoder {cfg.model.encoder} needs "
          f"multiples of {size_multiple}): training on {list(fitted)} crops (data.crop_fit=error refuses instead)", file=sys.stderr)
    return fitted


def make_dataset(cfg: DictConfig, paths: list[Path], size_multiple: int, samples_per_epoch: int | None = None) -> EventPairDataset:
    """The training pairs that ``cfg.data`` describes, for a model whose input sides must be
    multiples of ``size_multiple`` (the crop fitted by :func:`fit_crop`)."""
    crop = fit_crop(cfg, size_multiple)
    # data.label_subpixel: corners refined to sub-pixel positions and trained as soft cell targets
    try:
        labeller = CornerLabeller(subpixel_window=int(cfg.data.get("label_subpixel", 0) or 0))
    except ValueError as exc:
        raise ValueError(f"data.label_subpixel (cornerSubPix half-window in px; 0: integer labels): {exc}") from None
    return EventPairDataset(
        paths, mcts_spec_from_config(cfg.model.mcts), crop=crop, max_gap_frames=int(cfg.data.max_gap_frames),
        stereo_fraction=float(cfg.data.stereo_fraction), supervision=str(cfg.data.supervision),
        samples_per_epoch=samples_per_epoch or int(cfg.data.samples_per_epoch), seed=int(cfg.seed),
        event_cache=event_cache_dir(cfg), roll_deg=float(cfg.data.get("roll_deg", 0.0)),
        labeller=labeller, soft_labels=labeller.subpixel_window > 0,
        pixel_warps=repeatability_weight(cfg.loss) > 0)


def real_recordings(cfg: DictConfig) -> tuple[list[Path], int, HomographyRange] | None:
    """``data.real`` checked, before any data is generated: (recordings, pairs per batch from them,
    homography range), or None without ``data.real``.

    ``data.real_fraction`` of every batch (at least one pair, at most all but one) comes from them.

    Raises:
        DataError: a setting that mixing cannot honour (pose-only supervision, the repeatability
            loss, a batch of one, a fraction outside (0, 1), a bad homography range) or a missing recording.
    """
    real = cfg.data.get("real")
    if not real:
        return None
    batch = int(cfg.data.batch_size)
    fraction = float(cfg.data.get("real_fraction", 0.25))
    if not 0.0 < fraction < 1.0:
        raise DataError(None, f"data.real_fraction={fraction}: the share of each batch from data.real must be in (0, 1)")
    if str(cfg.data.get("supervision", "depth")) != "depth":
        raise DataError(None, "data.real mixes homographic pairs, whose targets are warps, with the simulator's: "
                              "it needs data.supervision=depth")
    if repeatability_weight(cfg.loss) > 0:
        raise DataError(None, "data.real: the repeatability loss needs per-pixel warps of the simulator's depth; use loss.repeatability=0")
    if batch < 2:
        raise DataError(None, f"data.real needs data.batch_size >= 2 (one simulated and one real pair), got {batch}")
    try:
        hrange = HomographyRange(**{k: (tuple(v) if k == "scale" else float(v)) for k, v in dict(cfg.data.get("homography") or {}).items()})
    except (TypeError, ValueError) as exc:
        raise DataError(None, f"data.homography: {exc}") from None
    paths = expand_sequences([real] if isinstance(real, str) else real)
    for p in paths:
        if not p.is_file():
            raise DataError(p, "data.real: recording not found (canonical .h5 files or folders of them; aerovis-data convert)")
    if not paths:
        raise DataError(None, f"data.real={real}: no .h5 recordings there")
    return paths, min(batch - 1, max(1, int(round(batch * fraction)))), hrange


def make_real_dataset(cfg: DictConfig, size_multiple: int, sim: EventPairDataset) -> tuple[RealViewDataset | None, int]:
    """Self-supervised pairs from the recordings of ``data.real`` (:mod:`aerovis_train.homographic`, checked
    by :func:`real_recordings`) and the simulator's share of each batch: ``(None, data.batch_size)``
    without ``data.real``. The real dataset is sized so that both loaders end their epoch together."""
    checked = real_recordings(cfg)
    batch = int(cfg.data.batch_size)
    if checked is None:
        return None, batch
    paths, n_real, hrange = checked
    crop = sim.crop or fit_crop(cfg, size_multiple)
    if crop is None:
        raise DataError(None, "data.real needs a data.crop: the real recordings' sensors differ from the simulator's")
    n_sim = batch - n_real
    steps = max(1, len(sim) // n_sim)
    dataset = RealViewDataset(paths, sim.mcts, crop=crop, samples_per_epoch=steps * n_real,
                              seed=int(cfg.seed), homography=hrange, labeller=sim.labeller, soft_labels=sim.soft_labels)
    return dataset, n_sim


def gpu_processes(trainer_cfg) -> int:
    """Training processes the ``trainer`` config starts on GPUs of this machine (0: training on the CPU)."""
    accelerator = str(trainer_cfg.get("accelerator", "cpu"))
    if accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available()):
        return 0
    devices = trainer_cfg.get("devices", 1)
    if str(devices) in ("-1", "auto"):
        return max(1, torch.cuda.device_count())
    if OmegaConf.is_list(devices) or isinstance(devices, (list, tuple)):
        return len(devices)
    if isinstance(devices, str) and "," in devices:  # Lightning's "0,1"
        return len([d for d in devices.split(",") if d.strip()])
    return max(1, int(devices))


def loader_workers(cfg: DictConfig) -> int:
    """``data.num_workers``: a number, or ``auto``: 1 when training on the CPU (the training process
    uses every core, and one worker keeps its data wait under 1 % on the 2-core CI box); on GPUs, the
    cores left after one per GPU process, shared among the processes, at most 10 each (on an H200 with
    16 cores, 10 workers left SuperLitE 1.8 % of its step time waiting for data and 8 workers 23 %)."""
    setting = cfg.data.get("num_workers", "auto")
    if str(setting) != "auto":
        return int(setting)
    procs = gpu_processes(cfg.trainer)
    if procs == 0:
        return 1
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(10, cores // procs - 1))


def event_cache_dir(cfg: DictConfig) -> Path | None:
    """``data.event_cache``: false/null (off), true (``$AEROVIS_CACHE/decoded`` or
    ``~/.cache/aerovis/decoded``), a folder, or ``auto``: on when training on GPUs, where the loader
    limits the step rate (2.4x faster workers), off on the CPU, where the model does (the copies take
    about 3x the sequences' disk space)."""
    setting = cfg.data.get("event_cache", "auto")
    if str(setting) == "auto":
        setting = gpu_processes(cfg.trainer) > 0
    if setting is None or setting is False:
        return None
    if setting is True:
        from aerovis_slam.sim.cache import cache_root

        return cache_root().parent / "decoded"
    return Path(str(setting)).expanduser()


def init_from_weights(model: torch.nn.Module, name_or_path: str, model_cfg) -> dict:
    """Load the weights of a shipped model (``superlite``...), a ``model.pt`` or a ``train.py`` ``.ckpt``
    into ``model`` before training (``init_weights=...``: fine-tuning, e.g. on a user's recordings).

    Returns:
        ``{"path", "sha256"}`` of the weights loaded, recorded in the run's ``model.pt`` (its provenance).

    Raises:
        DataError: unreadable weights, or weights of another architecture (named with both models).
    """
    from .checkpoints import load_model

    src, src_cfg, meta = load_model(name_or_path)
    try:
        state = src.state_dict()
        if getattr(model, "detector_pixel", None) is not None and getattr(src, "detector_pixel", None) is None:
            # a pixel detector branch added to a network trained without one: it starts at zero
            # (its last conv), so the run starts as the loaded network
            state.update({f"detector_pixel.{k}": v for k, v in model.detector_pixel.state_dict().items()})
            print("train.py: note: init_weights has no detector_pixel branch; the new branch starts at zero",
                  file=sys.stderr)
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        lines = str(exc).splitlines()
        first = lines[1].strip() if len(lines) > 1 else str(exc)
        raise DataError(meta["path"], f"init_weights: these weights are a {src_cfg.get('name')} model "
                                      f"({src_cfg.get('encoder')}, D={src_cfg.get('descriptor_dim')}) and do not fit this run's "
                                      f"{model_cfg.name} ({model_cfg.encoder}, D={model_cfg.descriptor_dim}): {first}") from None
    run_mcts = OmegaConf.to_container(model_cfg.mcts, resolve=True)
    if dict(src_cfg.get("mcts", {})) != dict(run_mcts):
        print(f"train.py: note: init_weights {meta['path']} was trained on MCTS {src_cfg.get('mcts')}; this run uses "
              f"{run_mcts}", file=sys.stderr)
    print(f"initialised from {meta['path']} (sha256 {meta['sha256'][:12]})")
    return {"path": meta["path"], "sha256": meta["sha256"]}


def job_overrides() -> list[str] | None:
    """The Hydra overrides of the running job (``HydraConfig.get().overrides.task``); None outside Hydra."""
    from hydra.core.hydra_config import HydraConfig

    try:
        return list(HydraConfig.get().overrides.task)
    except ValueError:  # HydraConfig was not set: train() called from Python with a composed config
        return None


def log_lightning_once() -> None:
    """Print each Lightning log record once where the root logger already has handlers (Hydra's).

    The ``lightning`` package adds a console handler of its own to the ``lightning`` logger at import,
    and its records still propagate to the root, where Hydra's console handler printed every one a
    second time ("INFO: Seed set to 0", then "[...][lightning.fabric.utilities.seed][INFO] - Seed set
    to 0"). Without root handlers (a plain script) Lightning's own handler stays, the only output.
    """
    if not logging.getLogger().hasHandlers():
        return
    lightning_logger = logging.getLogger("lightning")
    for handler in list(lightning_logger.handlers):
        if type(handler) is logging.StreamHandler:  # its console handler; file handlers stay
            lightning_logger.removeHandler(handler)


def train(cfg: DictConfig, overrides: list[str] | None = None) -> float:
    """Run one training job; returns the validation AUC@10 of the weights it keeps in ``model.pt``
    (the best epoch's, or with ``weights=last`` the final step's): what a sweep optimises.

    Args:
        cfg: the composed run config (``conf/config.yaml``).
        overrides: the overrides that define the job, recorded in ``metrics.json``; None: the
            running Hydra job's (``python train.py ...``), if any.
    """
    t_start = time.time()
    log_lightning_once()
    selection = str(cfg.get("weights", "best"))
    if selection not in WEIGHT_SELECTIONS:
        raise DataError(None, f"weights={selection!r}: expected one of {', '.join(WEIGHT_SELECTIONS)} "
                              "(best: highest validation AUC@10; last: the final step)")
    try:
        descriptor_loss_terms(str(cfg.loss.get("descriptor", "hinge")), str(cfg.data.get("supervision", "depth")))
    except ValueError as exc:  # refused before any data is generated
        raise DataError(None, str(exc)) from None
    if repeatability_weight(cfg.loss) > 0 and str(cfg.data.get("supervision", "depth")) != "depth":
        raise DataError(None, f"loss.repeatability={cfg.loss.repeatability} needs data.supervision=depth (pixel warps need "
                              f"depth; this run has {cfg.data.supervision!r}); use loss.repeatability=0")
    real_recordings(cfg)  # data.real refused before any data is generated
    L.seed_everything(int(cfg.seed), workers=True)
    torch.set_num_threads(int(cfg.get("torch_threads") or torch.get_num_threads()))
    run_dir = Path(cfg.run_dir)
    ckpt_dir = run_dir / "checkpoints"
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))

    module = KeypointModule(OmegaConf.to_container(cfg, resolve=True))
    try:
        frozen = module.frozen_parts()
    except ValueError as exc:  # a part the network does not have: refused before any data is generated
        raise DataError(None, str(exc)) from None
    if frozen and not cfg.get("init_weights") and not (ckpt_dir / "last.ckpt").exists():
        print(f"train.py: note: optim.train_only without init_weights: {', '.join(frozen)} keep their "
              "random initialisation", file=sys.stderr)
    train_paths, val_paths = sequences_from_config(cfg.data)
    dataset = make_dataset(cfg, train_paths, module.model.size_multiple)
    real_dataset, sim_batch = make_real_dataset(cfg, module.model.size_multiple, dataset)
    workers = loader_workers(cfg)
    loader = make_loader(dataset, sim_batch, workers, shuffle=True)
    print(f"data: {len(train_paths)} training sequences, {workers} loader worker{'s' if workers != 1 else ''}"
          + (f", decoded copies in {dataset.event_cache}" if dataset.event_cache else ""))
    if real_dataset is not None:
        from lightning.pytorch.utilities import CombinedLoader

        n_real = int(cfg.data.batch_size) - sim_batch
        real_loader = make_loader(real_dataset, n_real, workers, shuffle=True)
        # every step: sim_batch simulated pairs and n_real homographic pairs of real recordings, one batch
        loader = CombinedLoader({"sim": loader, "real": real_loader}, mode="min_size")
        print(f"data: {n_real} of {cfg.data.batch_size} pairs a batch from {len(real_dataset.views)} real camera stream(s) "
              "through random homographies (data.real)")
    val_loader = torch.utils.data.DataLoader([str(p) for p in val_paths], batch_size=None)
    best_cb, last_cb = checkpoint_callbacks(ckpt_dir, float(cfg.checkpoint_every_min))
    loggers = [CSVLogger(run_dir, name="logs", version=""), TensorBoardLogger(run_dir, name="tensorboard", version="")]
    trainer = L.Trainer(
        **OmegaConf.to_container(cfg.trainer, resolve=True),
        default_root_dir=run_dir,
        logger=loggers,
        callbacks=[best_cb, last_cb, _EpochSetter(dataset, real_dataset), TQDMProgressBar(refresh_rate=1)],
        plugins=[AtomicCheckpointIO()],
        num_sanity_val_steps=0,
        deterministic=False,
    )
    last = ckpt_dir / "last.ckpt"
    resume = last if (cfg.get("resume", True) and last.exists()) else None
    init_meta = None  # where the weights started (model.pt's meta): None for a run from scratch
    if resume:
        print(f"resuming from {resume}")
        if cfg.get("init_weights"):
            # the first start loaded them; their file may have changed since, so only the name is recorded
            init_meta = {"path": str(cfg.init_weights), "sha256": None}
    elif cfg.get("init_weights"):
        init_meta = init_from_weights(module.model, cfg.init_weights, cfg.model)
    trainer.fit(module, loader, val_loader, ckpt_path=str(resume) if resume else None)

    best_auc = float(best_cb.best_model_score) if best_cb.best_model_score is not None else float("nan")
    if not trainer.is_global_zero:
        # under DDP the other processes stop here: model.pt, metrics.json and summary.json are written
        # once (a second writer without the metrics could replace summary.json after the first)
        return best_auc
    best_path = best_cb.best_model_path or str(last)
    # weights=last: the final step's weights instead of the validation's pick (fixed-budget runs to compare)
    selected_path = str(last) if selection == "last" else best_path
    selected = selected_path if selected_path and Path(selected_path).exists() else None
    slim_path = run_dir / "model.pt"
    extra = {"best_val_auc10": best_auc, "checkpoint": selected, "weights_selection": selection,
             "weights": str(slim_path) if selected else None, "steps": int(trainer.global_step),
             "train_wall_s": round(time.time() - t_start, 1), "seed": int(cfg.seed), "run_dir": str(run_dir),
             "crop": list(dataset.crop) if dataset.crop else None}
    metrics_path, metrics = _write_metrics(cfg, module, selected, val_loader, (val_paths or train_paths)[0],
                                           overrides if overrides is not None else job_overrides(), run_dir, extra)
    selected_auc = best_auc
    if selection == "last":
        # the final weights' own validation score (re-validated for metrics.json), not the best epoch's
        selected_auc = float(metrics["auc10"]) if metrics["auc10"] is not None else float("nan")
    slim = None
    if selected:
        ckpt = torch.load(selected, map_location="cpu", weights_only=False)
        slim = save_slim(module.cfg["model"], lightning_model_state(ckpt), slim_path,
                         meta={"val_auc10": selected_auc, "seed": int(cfg.seed), "data": OmegaConf.to_container(cfg.data, resolve=True),
                               "global_step": int(ckpt.get("global_step", 0)), "selection": selection,
                               "descriptor_loss": str(cfg.loss.descriptor), "init_weights": init_meta,
                               "train_only": module.model_trainable_parts()})
    summary = {
        "model": cfg.model.name,
        "best_val_auc10": best_auc,
        "best_checkpoint": best_path,
        "weights_selection": selection,
        "weights_val_auc10": selected_auc,
        "weights": str(slim) if slim else None,
        "steps": int(trainer.global_step),
        "epochs": int(trainer.current_epoch),
        "parameters": count_parameters(module.model),
        "skipped_nonfinite_steps": module.skipped_nonfinite,
        "train_sequences": len(train_paths),
        "val_sequences": len(val_paths),
        "wall_s": round(time.time() - t_start, 1),
        "run_dir": str(run_dir),
        "config": str(run_dir / "config.yaml"),
        "logs": str(run_dir / "logs"),
        "metrics": str(metrics_path) if metrics_path else None,
    }
    tmp = run_dir / "summary.json.partial"
    tmp.write_text(json.dumps(summary, indent=2))
    tmp.replace(run_dir / "summary.json")
    print(f"\n{cfg.model.name}: best val AUC@10 {best_auc:.2f} % after {summary['steps']} steps ({summary['wall_s']:.0f} s)")
    print(f"  weights     {summary['weights']} ({'final step' if selection == 'last' else 'best validation'}, "
          f"val AUC@10 {selected_auc:.2f} %)\n  checkpoint  {selected}\n  config      {summary['config']}\n"
          f"  logs        {summary['logs']} (tensorboard: {run_dir / 'tensorboard'})\n  summary     {run_dir / 'summary.json'}\n"
          f"  metrics     {summary['metrics']}")
    return selected_auc


def _write_metrics(cfg: DictConfig, module: KeypointModule, checkpoint: str | None, val_loader, calibration: Path,
                   overrides: list[str] | None, run_dir: Path, extra: dict) -> tuple[Path, dict]:
    """``run_dir/metrics.json`` of the job (:mod:`aerovis_train.search.metrics`): the selected
    checkpoint is re-validated with the module's own validation step (so AUC@5, AUC@10 and AUC@20
    belong to the weights that ``model.pt`` keeps), then parameters, FLOPs and ONNX latency.
    Returns the file's path and its contents."""
    from .search.metrics import METRICS_FILE, job_metrics, write_json

    val = None
    if checkpoint is not None:
        # a separate, silent trainer: the run's loggers and checkpoints are left as fit() left them
        checker = L.Trainer(accelerator=cfg.trainer.accelerator, devices=1, logger=False, enable_checkpointing=False,
                            enable_progress_bar=False, enable_model_summary=False)
        res = checker.validate(module, val_loader, ckpt_path=checkpoint, verbose=False, weights_only=False)
        if res and "val/auc10" in res[0]:
            val = {k.split("/", 1)[1]: float(v) for k, v in res[0].items() if k.startswith("val/")}
    mc = OmegaConf.to_container(cfg.metrics, resolve=True) if cfg.get("metrics") is not None else {}
    metrics = job_metrics(module.model.cpu(), module.cfg["model"], val=val, overrides=overrides, calibration=calibration, metrics_cfg=mc,
                          extra=extra, bundle_dir=run_dir / "bundle_fp32" if mc.get("keep_bundle", True) else None)
    path = write_json(run_dir / METRICS_FILE, metrics)
    lat = f"{metrics['latency_ms']:.1f} ms" if metrics["latency_ms"] is not None else f"not measured ({metrics['latency_error']})"
    auc = "n/a" if metrics["auc10"] is None else f"{metrics['auc5']:.1f} / {metrics['auc10']:.1f} / {metrics['auc20']:.1f} %"
    print(f"  val AUC@5/10/20 {auc}, {metrics['parameters'] / 1e6:.2f} M params, {metrics['flops'] / 1e9:.2f} GFLOP, latency {lat}",
          file=sys.stderr)
    return path, metrics
