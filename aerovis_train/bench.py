"""``aerovis-bench``: performance benchmarks, one JSON line each (never timed tests).

    aerovis-bench mcts     # event ingest and MCTS_Ne against a memory-traffic floor (one core)
    aerovis-bench sim      # simulator speed for a 10 s stereo sequence at 240x320
    aerovis-bench train    # training samples/s and data-wait fraction (superlite, superevent_plus)

Each subcommand imports only what it needs, so ``aerovis-bench mcts`` runs without torch.
"""

from __future__ import annotations

import argparse
import json
import sys


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="aerovis-bench", description="Benchmarks; each prints one JSON line.")
    sub = ap.add_subparsers(dest="command", required=True)
    p_mcts = sub.add_parser("mcts", help="event ingest rate and MCTS_Ne time vs. memory floor, on one core")
    p_mcts.add_argument("--events", type=int, default=10_000_000)
    sub.add_parser("sim", help="simulate a 10 s stereo sequence at 240x320 with handheld motion")
    p_train = sub.add_parser("train", help="training samples/s of superlite and superevent_plus, and the data-wait fraction")
    p_train.add_argument("--steps", type=int, default=12)
    p_train.add_argument("overrides", nargs="*", help="extra train.py overrides, e.g. data.num_workers=2")
    args = ap.parse_args(argv)
    if args.command == "mcts":
        from aerovis_slam.benchmarks import bench_mcts

        result = bench_mcts(n_events=args.events)
    elif args.command == "sim":
        from aerovis_slam.sim.bench import run_sim_benchmark

        result = run_sim_benchmark()
    elif args.command == "train":
        from aerovis_train.benchmarks import bench_train

        result = bench_train(steps=args.steps, overrides=args.overrides)
    else:  # pragma: no cover - argparse rejects unknown commands
        return 2
    print(json.dumps(result))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
