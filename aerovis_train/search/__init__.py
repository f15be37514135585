"""Architecture search: per-job metrics, leaderboards with Pareto fronts, a guided (Optuna) search,
and the generated results page.

* :mod:`.metrics`: ``metrics.json`` of one training job (parameters, FLOPs, validation AUC,
  ONNX Runtime latency, overrides); written by ``train.py`` at the end of every job.
* :mod:`.leaderboard`: read every ``metrics.json`` under a sweep folder, rank, mark the Pareto
  front of AUC@10 against latency, write CSV, Markdown, PNG and a summary JSON.
* :mod:`.optuna_search`: a guided search driven by ``conf/search/<name>.yaml`` (Optuna >= 4),
  each trial one in-process training job.
* :mod:`.results`: ``docs/results.md`` from the outputs of ``aerovis-eval compare`` and searches.
* :mod:`.cli`: ``aerovis-search summarize | optuna | results``.

Grid sweeps need nothing of this package: ``python train.py -m model.encoder=vgg_lite,maxvit
model.descriptor_dim=64,128`` (Hydra's basic sweeper; ``train.py`` returns the validation AUC@10,
so any Hydra sweeper can drive it), then ``aerovis-search summarize multirun/<date>``.
"""

from .leaderboard import pareto_front, rank_jobs, read_jobs, summarize_dir
from .metrics import METRICS_FILE, job_metrics, load_metrics, onnx_latency, write_json

__all__ = [
    "METRICS_FILE",
    "job_metrics",
    "load_metrics",
    "onnx_latency",
    "pareto_front",
    "rank_jobs",
    "read_jobs",
    "summarize_dir",
    "write_json",
]
