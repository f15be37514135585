"""``aerovis-search``: leaderboards of architecture searches, a guided search, the results page.

    aerovis-search summarize MULTIRUN_DIR [--out DIR] [--top N]
        leaderboard.csv, leaderboard.md, pareto.png and search_summary.json of every job's
        metrics.json under MULTIRUN_DIR (a `python train.py -m ...` sweep or an Optuna study folder)
    aerovis-search retime MULTIRUN_DIR [--repeats 20] [--threads N]
        time every job's kept bundle again on this machine, all in one run (latencies measured by
        jobs on different machines or under different load become comparable), then summarize again
    aerovis-search optuna [--search optuna] [search.n_trials=20] [TRAIN OVERRIDES ...]
        guided search configured by conf/search/<name>.yaml (see aerovis_train/search/optuna_search.py)
    aerovis-search results [--compare DIR] [--ablation DIR [--ablation-methods REGEX] [--ablation-title TEXT] ...]
                           [--classical DIR ...] [--ceiling DIR] [--recipes DIR --recipe A=REGEX --recipe B=REGEX]
                           [--keep HEADING ...] [--search DIR ...] [--out docs/results.md]
        the results page from the outputs of `aerovis-eval compare` and of searches

A grid search is Hydra's own: ``python train.py -m model.encoder=vgg_lite,vgg,mobilenetv3,maxvit
model.descriptor_dim=64,128,256`` (each job writes its metrics.json), then ``summarize``.

Each command prints one JSON line on stdout (human text on stderr). Bad input (a folder without
metrics.json, a file that is not one) prints one message naming the file and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import sys

from hydra.errors import HydraException

from aerovis_slam.errors import DataError

PROG = "aerovis-search"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description="Architecture search: leaderboards, guided search, results page.")
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("summarize", help="leaderboard (CSV, Markdown), Pareto plot (PNG) and summary JSON of a sweep folder")
    p.add_argument("multirun_dir", help="folder with one metrics.json per job (searched recursively)")
    p.add_argument("--out", help="where to write (default: MULTIRUN_DIR)")
    p.add_argument("--top", type=int, default=None, help="rows of the Markdown table (default all)")
    p = sub.add_parser("retime", help="time every job's kept bundle again, round-robin in one run, and update its metrics.json")
    p.add_argument("multirun_dir", help="folder with one metrics.json per job (searched recursively)")
    p.add_argument("--repeats", type=int, default=20, help="timed runs per bundle (default 20)")
    p.add_argument("--threads", type=int, default=None, help="ONNX Runtime intra-op threads (default: its own)")
    p = sub.add_parser("optuna", help="guided search with Optuna, configured by conf/search/<name>.yaml")
    p.add_argument("--search", default="optuna", help="search config in conf/search/ (default optuna; optuna_pareto: AUC and latency)")
    p.add_argument("overrides", nargs="*", help="search.* overrides and train.py overrides applied to every trial")
    p = sub.add_parser("results", help="write docs/results.md from `aerovis-eval compare --out` and search folders")
    p.add_argument("--compare", help="folder (or compare.json) written by `aerovis-eval compare --out`")
    p.add_argument("--ablation", action="append", default=[], metavar="DIR",
                   help="an `aerovis-eval compare --out` folder with several training runs (seeds) of MCTS_Ne and MCTS_dt "
                        "models: their mean AUC@10 compared (repeatable: one section each)")
    p.add_argument("--ablation-methods", action="append", default=[], metavar="REGEX",
                   help="regular expression: only the methods of the --ablation (the n-th for the n-th) whose label matches it")
    p.add_argument("--ablation-title", action="append", default=[], metavar="TEXT",
                   help="what the runs of the --ablation (the n-th for the n-th) are (e.g. the network), added to its "
                        "section's heading")
    p.add_argument("--classical", action="append", default=[], metavar="DIR",
                   help="an `aerovis-eval compare --classical-mcts KIND --out` folder: the classical detectors on another time "
                        "surface (repeatable)")
    p.add_argument("--ceiling", metavar="DIR", help="an `aerovis-eval compare --oracle-noise-px ... --out` folder: what perfect "
                                                    "matches of each method's keypoints reach")
    p.add_argument("--recipes", metavar="DIR", help="an `aerovis-eval compare --out` folder with several training runs of two "
                                                    "recipes (e.g. losses): their mean AUC@10 compared")
    p.add_argument("--recipe", action="append", default=[], metavar="NAME=REGEX",
                   help="a recipe of --recipes and the regular expression of its runs' labels (give two; the first is compared "
                        "with the second)")
    p.add_argument("--recipes-title", help="what the --recipes runs are, added to its section's heading")
    p.add_argument("--keep", action="append", default=[], metavar="HEADING",
                   help="carry the section of the existing --out page whose heading starts with HEADING over verbatim "
                        "(its inputs are gone; repeatable)")
    p.add_argument("--search", action="append", default=[], help="a search folder (repeatable)")
    p.add_argument("--out", default="docs/results.md", help="output Markdown (default docs/results.md)")
    p.add_argument("--top", type=int, default=20, help="leaderboard rows per search (default 20)")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.command == "summarize":
            from .leaderboard import markdown_table, summarize_dir

            s = summarize_dir(args.multirun_dir, args.out, args.top)
            print(markdown_table(s["leaderboard"], args.top), file=sys.stderr)
            print(f"{s['jobs']} jobs; best {s['best']}; Pareto front (by latency): {', '.join(s['pareto']) or 'none (no latencies)'}",
                  file=sys.stderr)
            print(json.dumps({k: s[k] for k in ("root", "command", "jobs", "with_latency", "best", "pareto", "outputs")}))
        elif args.command == "retime":
            from .metrics import retime_jobs

            jobs = retime_jobs(args.multirun_dir, repeats=args.repeats, threads=args.threads)
            for j in jobs:
                print(f"{j['job']}: {j['latency_ms']:.1f} ms (in the job: {j['latency_in_job_ms']:.1f} ms)", file=sys.stderr)
            print(json.dumps({"root": args.multirun_dir, "retimed": jobs}))
        elif args.command == "optuna":
            from .optuna_search import run_study

            s = run_study(args.search, args.overrides)
            print(f"{s['complete']} trials complete, {s['failed']} failed; study.json in {s['out_dir']}", file=sys.stderr)
            print(json.dumps({k: s[k] for k in ("study_name", "storage", "out_dir", "complete", "failed", "best")}))
        elif args.command == "results":
            from .results import write_results

            r = write_results(args.out, args.compare, args.search, args.top, args.ablation, args.ablation_methods,
                              args.ablation_title, classical=args.classical, ceiling=args.ceiling, keep=args.keep,
                              recipes=args.recipes, recipe=args.recipe, recipes_title=args.recipes_title)
            print(f"wrote {r['out']}", file=sys.stderr)
            print(json.dumps(r))
        sys.stdout.flush()
        return 0
    except (DataError, HydraException) as exc:  # bad input or a config that does not compose: one line, no traceback
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
