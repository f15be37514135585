"""``aerovis-export``: export a trained keypoint network to a model bundle.

    aerovis-export CKPT_OR_NAME --precision fp32|fp16|int8 [--target cpu|tensorrt] [--ptq]
                   --height H --width W [--batch 2] --out DIR [--force] [--engine]
                   [--data PRESET_OR_DIR] [--calib-data PRESET_OR_DIR] [--qat-steps N] ...

``CKPT_OR_NAME`` is a shipped model name (``superlite``), a slim ``model.pt`` or a ``train.py``
``.ckpt``. The bundle (``model.onnx``, ``metadata.json``, ``parity.json``) is built in
``DIR.partial`` and renamed to ``DIR`` when complete. ``--data`` is the held-out data of the parity
check (default ``bench``), ``--calib-data`` the data of QAT fine-tuning, INT8 calibration and the
descriptor scale (default ``train``); both take a simulator preset name, a folder of ``.h5`` sequences
or one ``.h5``.

Progress and a short summary go to stderr, one JSON line to stdout. Bad input (not a checkpoint,
a resolution the network cannot take, an existing ``--out`` without ``--force``) prints one message
and exits with status 2; ``--engine`` without TensorRT or a GPU prints one sentence and exits with
status 3, leaving the finished ONNX bundle in place.

Examples::

    aerovis-export superlite --precision fp32 --height 240 --width 424 --out bundles/superlite-fp32
    aerovis-export superlite --precision int8 --target cpu --qat-steps 200 --height 240 --width 424 --out bundles/superlite-int8
    aerovis-export superlite --precision int8 --ptq --height 240 --width 424 --out bundles/superlite-int8-ptq
"""

from __future__ import annotations

import argparse
import json
import sys

from aerovis_slam.errors import DataError

PROG = "aerovis-export"


def _parser() -> argparse.ArgumentParser:
    from .exporter import DEFAULT_QAT_STEPS

    ap = argparse.ArgumentParser(prog=PROG, description="Export a keypoint network to a model bundle (ONNX + metadata + parity).")
    ap.add_argument("model", help="shipped name (superlite, superevent_plus, superevent), model.pt or train.py .ckpt")
    ap.add_argument("--precision", choices=("fp32", "fp16", "int8"), required=True)
    ap.add_argument("--target", choices=("cpu", "tensorrt"), default="cpu",
                    help="INT8 flavour: cpu = uint8 activations/int8 weights (fast in ONNX Runtime), tensorrt = symmetric int8")
    ap.add_argument("--ptq", action="store_true", help="INT8 by post-training static quantisation (ONNX Runtime) instead of QAT")
    ap.add_argument("--height", type=int, required=True, help="input height in pixels (a multiple of the model's size multiple)")
    ap.add_argument("--width", type=int, required=True, help="input width in pixels")
    ap.add_argument("--batch", type=int, default=2, help="nominal batch (2: a stereo pair); the ONNX batch axis is dynamic")
    ap.add_argument("--out", required=True, help="bundle directory to create")
    ap.add_argument("--force", action="store_true", help="replace an existing --out")
    ap.add_argument("--engine", action="store_true", help="also build a TensorRT engine (needs TensorRT and a CUDA GPU)")
    ap.add_argument("--timing-cache", help="TensorRT timing cache file (default ~/.cache/aerovis/tensorrt/timing-<version>.cache)")
    ap.add_argument("--data", default="bench", help="held-out data for parity.json: preset, folder or .h5 (default bench)")
    ap.add_argument("--no-parity", action="store_true", help="skip the parity check (parity.json records that)")
    ap.add_argument("--parity-pairs", type=int, default=40, help="pairs per sequence in the parity check (default 40; 0: all)")
    ap.add_argument("--parity-max-angle-deg", type=float, default=45.0, help="largest pair rotation of the protocol (default 45)")
    ap.add_argument("--parity-max-dt-s", type=float, default=2.0, help="pair window of the protocol (default 2 s)")
    ap.add_argument("--calib-data", default="train",
                    help="data for QAT fine-tuning, INT8 calibration and the descriptor scale (default train)")
    ap.add_argument("--calib-frames", type=int, default=64, help="calibration MCTS (default 64)")
    ap.add_argument("--qat-steps", type=int, default=DEFAULT_QAT_STEPS, help=f"QAT fine-tuning steps (default {DEFAULT_QAT_STEPS})")
    ap.add_argument("--qat-lr", type=float, default=1e-5, help="QAT learning rate (default 1e-5)")
    ap.add_argument("--qat-batch", type=int, default=None, help="QAT batch size (default: the training config's)")
    ap.add_argument("--qat-override", action="append", default=[], metavar="KEY=VALUE",
                    help="training-config override for QAT data, e.g. data.supervision=epipolar (repeatable)")
    ap.add_argument("--reduce-range", action="store_true", help="7-bit INT8 (CPUs without VNNI may saturate in U8S8)")
    ap.add_argument("--fixed-hw", action="store_true", help="export for --height x --width only (no dynamic resolution)")
    ap.add_argument("--threshold", type=float, default=0.01, help="runtime detection threshold (default 0.01)")
    ap.add_argument("--nms-radius", type=int, default=2, help="runtime NMS radius (default 2: 5x5)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quiet", action="store_true", help="no progress bars or human summary")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from .exporter import export_bundle
    from .tensorrt import EngineBuildError, EngineUnavailable

    try:
        out = export_bundle(
            args.model, args.out, precision=args.precision, height=args.height, width=args.width, batch=args.batch, target=args.target,
            ptq=args.ptq, qat_steps=args.qat_steps, qat_lr=args.qat_lr, qat_batch=args.qat_batch, qat_overrides=args.qat_override,
            calibration=args.calib_data, calibration_frames=args.calib_frames, parity_data=None if args.no_parity else args.data,
            parity_pairs=args.parity_pairs or None, parity_max_angle_deg=args.parity_max_angle_deg, parity_max_dt_s=args.parity_max_dt_s,
            dynamic_hw=not args.fixed_hw, reduce_range=args.reduce_range, threshold=args.threshold, nms_radius=args.nms_radius,
            engine=args.engine, timing_cache=args.timing_cache, force=args.force, seed=args.seed, progress=not args.quiet)
    except DataError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except EngineUnavailable as exc:
        print(f"{PROG}: cannot build a TensorRT engine: {exc}; the ONNX bundle at {args.out} is complete.", file=sys.stderr)
        return 3
    except EngineBuildError as exc:
        print(f"{PROG}: error: {exc}; the ONNX bundle at {args.out} is complete.", file=sys.stderr)
        return 3
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted (nothing written to {args.out})", file=sys.stderr)
        return 130
    summary = _summary(out)
    if not args.quiet:
        p = summary.get("parity") or {}
        figures = (f"keypoints {p['keypoint_repeatability']:.3f}, descriptor cosine {p['descriptor_cosine']:.4f}, AUC@10 torch "
                   f"{p['auc10_torch']:.1f} / onnx {p['auc10_onnx']:.1f} on {p['pairs']} pairs"
                   + ("" if p.get("meets_targets") else " (below the issue's targets)")) if "auc10_onnx" in p else "parity not computed"
        print(f"{summary['model']} {summary['precision']} ({summary['target']}) -> {out}: {summary['onnx_mib']:.2f} MiB, "
              f"{'any HxW (multiples of %d)' % summary['size_multiple'] if summary['dynamic_hw'] else '%dx%d only' % (summary['height'], summary['width'])}; "
              f"{figures}", file=sys.stderr)
    print(json.dumps(summary))
    return 0


def _summary(out) -> dict:
    from aerovis_slam.bundle import Bundle

    b = Bundle.load(out)
    par = b.parity or {}
    keep = ("keypoint_repeatability", "descriptor_cosine", "auc10_torch", "auc10_onnx", "pairs", "meets_targets")
    return {"bundle": str(b.path), "model": b.name, "precision": b.precision, "target": b.target, "height": b.height, "width": b.width,
            "dynamic_hw": b.dynamic_hw, "size_multiple": b.size_multiple, "descriptor_scale": round(b.descriptor_scale, 3),
            "onnx_mib": b.onnx_path.stat().st_size / 2**20,
            "quantization": (b.meta.get("quantization") or {}).get("method"),
            "parity": {k: par[k] for k in keep if k in par} or None}


if __name__ == "__main__":
    sys.exit(main())
