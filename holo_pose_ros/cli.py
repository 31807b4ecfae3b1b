"""`holo-pose` command line: one sub-command per job of the ROS-free core."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _cmd_generate(args: argparse.Namespace) -> int:
    from holo_pose_ros.data.generator import generate

    summary = generate(args.robot, args.n, args.out, seed=args.seed, workers=args.workers, width=args.width,
                       height=args.height, config=args.config, progress=not args.quiet)
    print(f"wrote {summary.n_frames} frames of {args.robot} to {args.out} in {summary.seconds:.1f} s "
          f"({summary.fps:.1f} frames/s)")
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from holo_pose_ros.data.preview import dataset_preview

    out = Path(args.out) if args.out else Path(args.data) / "preview.png"
    stats = dataset_preview(args.data, args.robot, out, n=args.n, units=args.units)
    print(stats.report())
    print(f"preview: {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="holo-pose", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    g = sub.add_parser("generate", help="render a synthetic DREAM folder with masks (domain randomization)")
    g.add_argument("--robot", required=True, help="robot name (panda, kuka, baxter) or robot YAML path")
    g.add_argument("--n", type=int, required=True, help="number of frames")
    g.add_argument("--out", required=True, help="output folder")
    g.add_argument("--seed", type=int, default=0, help="random seed: same seed, same frames")
    g.add_argument("--workers", type=int, default=None, help="parallel processes (default: all cores)")
    g.add_argument("--width", type=int, default=640, help="image width, pixels")
    g.add_argument("--height", type=int, default=480, help="image height, pixels")
    g.add_argument("--config", default="randomized", help="generator YAML: name in config/generate or a path")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.set_defaults(func=_cmd_generate)

    s = sub.add_parser("show", help="statistics of a DREAM folder and a grid of frames with keypoints (PNG)")
    s.add_argument("data", help="DREAM folder")
    s.add_argument("--robot", required=True, help="robot name or robot YAML path")
    s.add_argument("--out", default=None, help="PNG path (default: DATA/preview.png)")
    s.add_argument("--n", type=int, default=12, help="frames in the grid")
    s.add_argument("--units", default="auto", choices=["auto", "m", "cm"], help="3D units of the files")
    s.set_defaults(func=_cmd_show)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"holo-pose {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
