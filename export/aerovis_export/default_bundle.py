"""Regenerate the runtime's shipped default bundle: SuperLitE, FP32, dynamic resolution.

    python -m aerovis_export.default_bundle [--data bench] [--calib-data train]

Exports the shipped ``superlite`` checkpoint into ``aerovis_slam/bundles/superlite-fp32/``
(:func:`aerovis_slam.bundle.default_bundle_path`) at a nominal 240x424 with batch 2 (a stereo pair)
and a graph that takes any multiple of 8, with its parity check on the ``bench`` preset and the
descriptor scale from the ``train`` preset. Run it again whenever ``superlite.pt`` changes: the
test suite checks that the bundle's source hash matches the shipped weights.
"""

from __future__ import annotations

import argparse
import json
import sys

from aerovis_slam.bundle import DEFAULT_BUNDLE_DIR
from aerovis_slam.errors import DataError


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m aerovis_export.default_bundle", description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="bench", help="held-out data of the parity check (default bench)")
    ap.add_argument("--calib-data", default="train", help="data of the descriptor scale (default train)")
    args = ap.parse_args(argv)
    from .exporter import export_bundle

    try:
        out = export_bundle("superlite", DEFAULT_BUNDLE_DIR, precision="fp32", height=240, width=424, batch=2,
                            calibration=args.calib_data, parity_data=args.data, force=True)
    except DataError as exc:
        print(f"default_bundle: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({"bundle": str(out), "parity": json.loads((out / "parity.json").read_text())}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
