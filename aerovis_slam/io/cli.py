"""``aerovis-data``: inspect and convert event-camera recordings.

    aerovis-data info PATH                  # JSON summary of any supported recording
    aerovis-data convert PATH OUT.h5 [--calib FILE [FILE]] [--no-calib]
    aerovis-data formats                    # list the supported formats
"""

from __future__ import annotations

import argparse
import json
import sys

from ..errors import DataError


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="aerovis-data", description="Inspect and convert event-camera recordings to the canonical HDF5 sequence.")
    sub = ap.add_subparsers(dest="command", required=True)
    p_info = sub.add_parser("info", help="print a JSON summary (cameras, resolution, events, time range, IMU, GT)")
    p_info.add_argument("path")
    p_conv = sub.add_parser("convert", help="write the canonical sequence format")
    p_conv.add_argument("path")
    p_conv.add_argument("out", help="output .h5 (written atomically)")
    p_conv.add_argument("--calib", nargs="+", metavar="FILE",
                        help="calibration: Kalibr camchain(-imucam) yaml, ROS camera_info yaml(s) (left right), or ECD calib.txt")
    p_conv.add_argument("--no-calib", action="store_true", help="write without calibration (sensor sizes only)")
    p_conv.add_argument("--quiet", action="store_true", help="no progress bar")
    sub.add_parser("formats", help="list supported input formats")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from .source import convert, open_recording, supported_formats

    try:
        if args.command == "formats":
            print("\n".join(supported_formats()))
            return 0
        if args.command == "info":
            with open_recording(args.path) as rec:
                print(json.dumps(rec.info()))
            return 0
        if args.command == "convert":
            calib = None
            if args.calib:
                from .calib_yaml import load_calibration

                calib = load_calibration(args.calib if len(args.calib) > 1 else args.calib[0])
            with open_recording(args.path) as rec:
                summary = convert(rec, args.out, calib=calib, require_calib=not args.no_calib, progress=not args.quiet)
            cams = ", ".join(f"{k}: {v['events']:,} events {v['width']}x{v['height']}" for k, v in summary["cameras"].items())
            print(f"wrote {args.out} ({cams}; {summary['imu']} IMU, {summary['gt']} GT samples)", file=sys.stderr)
            print(json.dumps(summary))
            return 0
    except DataError as exc:
        print(f"aerovis-data: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("aerovis-data: interrupted; no output written", file=sys.stderr)
        return 130
    return 1


if __name__ == "__main__":
    sys.exit(main())
