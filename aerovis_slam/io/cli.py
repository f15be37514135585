"""``aerovis-data``: inspect and convert event-camera recordings.

    aerovis-data info PATH                  # JSON summary of any supported recording
    aerovis-data convert PATH OUT.h5 [--calib FILE [FILE]] [--no-calib]
    aerovis-data formats                    # list the supported formats
    aerovis-data stats PATH... [--cam CAM] [--max-events N]   # one JSON line of event statistics per recording
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
    p_stats = sub.add_parser("stats", help="event statistics per recording (rate, ON share, isolated events, per-pixel rates, "
                                           "inter-event intervals, hot pixels): one JSON line each; see aerovis_slam.io.stats")
    p_stats.add_argument("paths", nargs="+", metavar="PATH", help="recordings of any supported format")
    p_stats.add_argument("--cam", default=None, help="one camera (default: every camera of each recording)")
    p_stats.add_argument("--max-events", type=int, default=20_000_000,
                         help="use at most the first N events of each camera (default 20,000,000; the statistics are exact over them)")
    return ap


def _stats(path: str, cam: str | None, max_events: int) -> dict:
    from .source import open_recording
    from .stats import event_stats
    from ..events import EventArray

    cameras = {}
    with open_recording(path) as rec:
        cams = rec.cameras()
        if cam is not None and cam not in cams:
            raise DataError(path, f"no camera {cam!r} (has {cams})")
        for c in [cam] if cam is not None else cams:
            width, height = rec.sensor_size(c)
            chunks, n, truncated = [], 0, False
            for chunk in rec.iter_events(c):
                if n + len(chunk) > max_events:
                    chunk = chunk[: max_events - n]
                    truncated = True
                chunks.append(chunk)
                n += len(chunk)
                if truncated:
                    break
            events = EventArray.concatenate(chunks) if chunks else EventArray.empty()
            try:
                cameras[c] = {**event_stats(events, width, height), "truncated": truncated}
            except ValueError as exc:
                raise DataError(path, f"{c}: {exc}") from None
    return {"recording": str(path), "cameras": cameras}


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
        if args.command == "stats":
            if args.max_events < 1:
                raise DataError(None, f"--max-events {args.max_events}: must be at least 1")
            for path in args.paths:
                print(json.dumps(_stats(path, args.cam, args.max_events)))
                sys.stdout.flush()
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
