"""``aerovis-bench``: performance benchmarks, one JSON line each (never timed tests).

    aerovis-bench mcts     # event ingest and MCTS_Ne against a memory-traffic floor (one core)
    aerovis-bench read     # event reading of a canonical sequence, per compression (what a replay keeps up with)
    aerovis-bench sim      # simulator speed for a 10 s stereo sequence at 240x320
    aerovis-bench train    # training samples/s and data-wait fraction (superlite, superevent_plus)
    aerovis-bench detector BUNDLE [BUNDLE...]   # ONNX Runtime latency of model bundles, one line per bundle
    aerovis-bench blas     # detector inference after the runtime's descriptor products: BLAS threads' cost

Each subcommand imports only what it needs, so ``aerovis-bench mcts``, ``detector`` and ``blas`` run without torch.
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
    p_read = sub.add_parser("read", help="stereo event reading rate of a canonical sequence, Blosc-LZ4 against gzip, in one run")
    p_read.add_argument("--events", type=int, default=6_000_000, help="events per camera")
    sub.add_parser("sim", help="simulate a 10 s stereo sequence at 240x320 with handheld motion")
    p_train = sub.add_parser("train", help="training samples/s of superlite and superevent_plus, and the data-wait fraction")
    p_train.add_argument("--steps", type=int, default=12,
                         help="timed steps per model (at least 10 x the loader's prefetch queue of 2 x num_workers batches)")
    p_train.add_argument("--device", default="cpu", help="where the model trains: cpu (default) or cuda")
    p_train.add_argument("overrides", nargs="*", help="extra train.py overrides, e.g. data.num_workers=2")
    p_det = sub.add_parser("detector", help="inference and inference + post-processing latency of model bundles (one line each, "
                                            "measured round-robin in blocks in one run)")
    p_det.add_argument("bundles", nargs="+", help="bundle directories written by aerovis-export")
    p_det.add_argument("--repeats", type=int, default=50)
    p_det.add_argument("--warmup", type=int, default=5)
    p_det.add_argument("--block", type=int, default=5,
                       help="timed runs of one bundle before switching to the next, each block after one untimed run (default 5)")
    p_det.add_argument("--threads", type=int, default=None, help="ONNX Runtime intra-op threads (default: its own, one per core)")
    p_det.add_argument("--height", type=int, default=None, help="measure at this height instead of each bundle's own")
    p_det.add_argument("--width", type=int, default=None, help="measure at this width instead of each bundle's own")
    p_blas = sub.add_parser("blas", help="detector inference after the runtime's descriptor products, numpy's BLAS at its own "
                                         "threads against one thread (SlamConfig.blas_threads), in one run")
    p_blas.add_argument("--bundle", default=None, help="model bundle (default: the shipped SuperLitE)")
    p_blas.add_argument("--repeats", type=int, default=30)
    p_blas.add_argument("--products-ms", type=float, default=30.0, help="descriptor products between inferences (ms)")
    args = ap.parse_args(argv)
    if args.command == "mcts":
        from aerovis_slam.benchmarks import bench_mcts

        result = bench_mcts(n_events=args.events)
    elif args.command == "read":
        from aerovis_slam.benchmarks import bench_read

        result = bench_read(n_events=args.events)
    elif args.command == "blas":
        from aerovis_slam.benchmarks import bench_blas

        result = bench_blas(args.bundle, repeats=args.repeats, products_ms=args.products_ms)
    elif args.command == "sim":
        from aerovis_slam.sim.bench import run_sim_benchmark

        result = run_sim_benchmark()
    elif args.command == "train":
        from aerovis_train.benchmarks import bench_train

        result = bench_train(steps_min=args.steps, overrides=args.overrides, device=args.device)
    elif args.command == "detector":
        from aerovis_slam.bundle import benchmark_bundles
        from aerovis_slam.errors import DataError

        try:
            results = benchmark_bundles(args.bundles, repeats=args.repeats, warmup=args.warmup, threads=args.threads,
                                        height=args.height, width=args.width, block=args.block)
        except (DataError, ValueError) as exc:
            print(f"aerovis-bench: error: {exc}", file=sys.stderr)
            return 2
        for r in results:
            print(json.dumps(r))
        sys.stdout.flush()
        return 0
    else:  # pragma: no cover - argparse rejects unknown commands
        return 2
    print(json.dumps(result))
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
