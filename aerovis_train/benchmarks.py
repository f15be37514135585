"""Training-side benchmarks for ``aerovis-bench`` (one JSON-ready dict each)."""

from __future__ import annotations

import time
from pathlib import Path

import torch


def compose_config(overrides: list[str]):
    """The run config exactly as ``python train.py OVERRIDES`` would compose it (no run directory)."""
    from hydra import compose, initialize_config_dir

    conf_dir = Path(__file__).resolve().parents[1] / "conf"
    with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
        return compose("config", overrides=overrides + ["run_dir=."])


def bench_train(models=("superlite", "superevent_plus"), steps_min: int = 12, warmup: int = 3, overrides: list[str] | None = None,
                device: str = "cpu") -> dict:
    """Training throughput with the default data pipeline and the fraction of step time spent waiting
    for data, per model, measured in one run on the default config (``data=sim``: the `train` preset,
    generated on first use).

    ``data_wait_fraction`` is the time blocked in ``next(loader)`` over the whole step time: below 20 %
    means the loader (with ``data.num_workers`` workers) keeps up with the model. ``device``
    (``cpu``, ``cuda``) is where the model trains; on a GPU each step ends with a synchronisation, so
    the step time is the GPU's, and batches are copied to it as a training run copies them.
    """
    from lightning.fabric.utilities.apply_func import move_data_to_device
    from omegaconf import OmegaConf

    from .data import make_loader
    from .module import KeypointModule
    from .training import loader_workers, make_dataset, sequences_from_config

    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("aerovis-bench train --device cuda: no CUDA device is available to torch")
    result: dict = {"device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else "cpu"}
    for name in models:
        overrides_m = ([f"model={name}"] + (["data.crop=[160,200]"] if name.startswith("superevent") else [])
                       + (["trainer=gpu"] if dev.type == "cuda" else []) + list(overrides or []))
        cfg = compose_config(overrides_m)
        module = KeypointModule(OmegaConf.to_container(cfg, resolve=True)).to(dev)
        train_paths, _ = sequences_from_config(cfg.data)
        # The workers fill a queue of num_workers * prefetch_factor (2) batches while the first steps run:
        # timing those would measure the queue, not the loader's steady state (a 20-step run with 12
        # workers on a GPU showed 1.5 % waiting, where 4 workers showed 89 %).
        workers = loader_workers(cfg)
        skip = max(warmup, 2 * workers + 1)
        # A loader slightly slower than the model still finds that queue full after the skipped steps
        # (it drains only by the difference of the two rates), so time at least 10 queues' worth of
        # steps: batches queued before timing can then hide at most about a tenth of the wait.
        steps = max(steps_min, 10 * 2 * workers)
        ds = make_dataset(cfg, train_paths, module.model.size_multiple, samples_per_epoch=(steps + skip) * int(cfg.data.batch_size))
        loader = make_loader(ds, int(cfg.data.batch_size), workers, shuffle=True)
        opt = module.configure_optimizers()
        it = iter(loader)
        wait = busy = 0.0
        for i in range(steps + skip):
            t0 = time.perf_counter()
            batch = move_data_to_device(next(it), dev)
            t1 = time.perf_counter()
            loss = module._losses(batch)["loss"]
            opt.zero_grad()
            loss.backward()
            opt.step()
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            t2 = time.perf_counter()
            if i >= skip:
                wait += t1 - t0
                busy += t2 - t1
        bs = int(cfg.data.batch_size)
        result[name] = {
            "steps": steps,
            "samples_per_s": round(steps * bs / (wait + busy), 3),
            "step_s": round((wait + busy) / steps, 3),
            "data_wait_fraction": round(wait / (wait + busy), 3),
            "batch_size": bs,
            "crop": list(cfg.data.crop),
            "num_workers": workers,
            "event_cache": ds.event_cache is not None,
            "torch_threads": torch.get_num_threads(),
            "warmup_steps": skip,
        }
        del it, loader
    return result
