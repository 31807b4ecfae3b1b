"""`holo-pose` command line: one sub-command per job of the ROS-free core."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path


def _cmd_generate(args: argparse.Namespace) -> int:
    from holo_pose_ros.data.generator import generate

    summary = generate(args.robot, args.n, args.out, seed=args.seed, workers=args.workers, width=args.width,
                       height=args.height, config=args.config, progress=not args.quiet, second_robot=args.second_robot)
    robots = f"{args.robot} and {args.second_robot}" if args.second_robot else args.robot
    print(f"wrote {summary.n_frames} frames of {robots} to {args.out} in {summary.seconds:.1f} s "
          f"({summary.fps:.1f} frames/s)")
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    from holo_pose_ros.data.preview import dataset_preview

    out = Path(args.out) if args.out else Path(args.data) / "preview.png"
    stats = dataset_preview(args.data, args.robot, out, n=args.n, units=args.units)
    print(stats.report())
    print(f"preview: {out}")
    return 0


def _cmd_train(args: argparse.Namespace) -> int:
    # before torch loads OpenMP: its threads otherwise spin after every parallel region, stealing the cores from
    # ONNX Runtime's frozen blocks and the render worker (on 2 cores: 23.3 instead of 21.7 views/s)
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from holo_pose_ros.train.trainer import Trainer, load_train_config

    cfg = load_train_config(args.config)
    if args.out:
        cfg["out"] = args.out
    trainer = Trainer(cfg, device=args.device, progress=not args.quiet)
    kept = trainer.run(resume=args.resume)
    if trainer.rank == 0:  # under torchrun, rank 0 alone validates and keeps
        print(f"kept model: {kept}" if kept else "no model kept (no validation ran)")
    return 0


def _cmd_train_lifter(args: argparse.Namespace) -> int:
    import torch

    from holo_pose_ros.train.lifter_trainer import train_lifter

    torch.set_num_threads(args.threads)
    command = f"holo-pose train-lifter --robot {args.robot} " + (f"--steps {args.steps}" if args.steps is not None
                                                                 else f"--minutes {args.minutes:g}")
    command += "".join(f" --{k} {v}" for k, v in (("config", args.config), ("out", args.out)) if v is not None)
    command += f" --threads {args.threads}"
    card = train_lifter(args.robot, args.config, minutes=args.minutes if args.steps is None else None,
                        steps=args.steps, out=args.out, progress=not args.quiet, command=command)
    print(f"lifter: {card}")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from holo_pose_ros.data.dream import DreamReader
    from holo_pose_ros.estimator import Estimator
    from holo_pose_ros.evaluation.plots import plot_add_curve, plot_frames_grid
    from holo_pose_ros.evaluation.report import format_report, per_frame_add, write_report
    from holo_pose_ros.evaluation.run import evaluate_folder, evaluate_methods, format_ablation

    estimator = Estimator.from_model(args.model, device=args.device, backend=args.backend, tracking=args.tracking,
                                     fit=args.fit, parts=args.parts, localize_size=args.localize_size,
                                     close_ups=args.close_ups, static_camera=args.static_camera or False)
    reader = DreamReader(args.data, estimator.robot, units=args.units)
    if args.ablation:
        reports = evaluate_methods(estimator, reader, limit=args.limit, progress=not args.quiet,
                                   depth_diagnostics=args.depth_diagnostics is not False)
        print(format_ablation(reports))
        if args.out:
            write_report(reports, args.out)
            print(f"report: {args.out}")
        return 0
    report, results, images = evaluate_folder(estimator, reader, known_joints=args.known_joints, limit=args.limit,
                                              progress=not args.quiet, keep_images=12 if args.plots else 0,
                                              depth_diagnostics=args.depth_diagnostics)
    print(format_report(report))
    if args.out:
        write_report(report, args.out)
        print(f"report: {args.out}")
    if args.plots:
        plots = Path(args.plots)
        add_m, found = per_frame_add(results)
        plot_add_curve(add_m, found, plots / "add_curve.png", label=str(args.model))
        kept = results[:len(images)]
        plot_frames_grid(images, [r.pred_uv for r in kept], [r.gt_uv for r in kept], estimator.robot.keypoint_parents,
                         plots / "frames.png", titles=[r.name for r in kept])
        print(f"plots: {plots}")
    return 0


def _cmd_dream_to_bag(args: argparse.Namespace) -> int:
    from holo_pose_ros.bags import dream_to_bag

    n = dream_to_bag(args.data, args.out, storage=args.storage, robot=args.robot, units=args.units, rate_hz=args.rate,
                     start_time_s=args.start_time, frame_id=args.frame_id, limit=args.limit, progress=not args.quiet)
    print(f"wrote {n} frames (image, camera_info, ground truth) to the {args.storage} bag {args.out}")
    return 0


def _bag_inputs(parser: argparse.ArgumentParser, bag_help: str) -> None:
    """The arguments every bag command shares: the bag, the model, the image and CameraInfo topics."""
    parser.add_argument("--bag", required=True, help=bag_help)
    parser.add_argument("--model", required=True, help="shipped model name (panda) or model card / weights path")
    parser.add_argument("--image-topic", default=None, help="sensor_msgs/Image topic (default: the bag's only one)")
    parser.add_argument("--info-topic", default=None, help="sensor_msgs/CameraInfo topic (default: the bag's only one)")


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from holo_pose_ros.bag_calibration import calibrate_bag, calibration_document, format_calibration

    result = calibrate_bag(args.bag, args.model, args.joint_states_topic, image_topic=args.image_topic,
                           camera_info_topic=args.info_topic, window=args.window, tolerance_s=args.tolerance,
                           compare=not args.no_compare, backend=args.backend, limit=args.limit,
                           progress=not args.quiet)
    print(format_calibration(result))
    if result.calibration is None:
        return 1
    from holo_pose_ros.model.cards import read_card

    import yaml

    child = args.child_frame_id or f"{read_card(args.model)[1]['robot']}_base_link"
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(calibration_document(result, args.bag, args.model, child), sort_keys=False))
    print(f"calibration: {out}")
    return 0


def _cmd_bag_eval(args: argparse.Namespace) -> int:
    from holo_pose_ros.bags import bag_eval
    from holo_pose_ros.evaluation.report import format_report

    summary = bag_eval(args.bag, args.model, args.out, image_topic=args.image_topic,
                       camera_info_topic=args.info_topic, device=args.device, min_confidence=args.min_confidence,
                       tracking=args.tracking, storage=args.storage, use_rectified_p=args.use_rectified_p,
                       backend=args.backend, fit=args.fit,
                       limit=args.limit, progress=not args.quiet)
    print(f"{summary.n_images} images: {summary.n_found} found, {summary.n_not_found} not found, "
          f"{summary.n_skipped} skipped; estimates: {summary.out}")
    if summary.n_other_type:
        print(f"{summary.n_other_type} message(s) of other types on the image topic ignored")
    for problem in summary.problems:
        print(problem)
    if summary.report is not None:
        print(format_report(summary.report))
        print(f"report: {summary.report_path}")
    else:
        print("no ground truth in the bag: no report")
    return 0


def _cmd_adapt(args: argparse.Namespace) -> int:
    from holo_pose_ros.adaptation.adapt import adapt, format_adaptation
    from holo_pose_ros.adaptation.sources import AdaptationInputError

    command = "holo-pose " + " ".join(sys.argv[1:]) if sys.argv[0].endswith("holo-pose") else None
    try:
        result = adapt(args.model, args.images, args.out, joint_states_topic=args.joint_states_topic,
                       camera_info=args.camera_info, image_topic=args.image_topic, camera_info_topic=args.info_topic,
                       minutes=args.minutes, limit=args.limit, config=args.config, progress=not args.quiet,
                       seed=args.seed, command=command, plots=args.plots, score=False if args.no_score else None)
    except AdaptationInputError as e:
        print(f"holo-pose adapt: error: {e}", file=sys.stderr)
        return 1
    print(format_adaptation(result))
    return 0


def _cmd_benchmark(args: argparse.Namespace) -> int:
    import json

    from holo_pose_ros.benchmark import benchmark, format_benchmark

    result = benchmark(args.model, args.data, frames=args.frames, device=args.device, tracking=args.tracking,
                       threads=args.threads, backend=args.backend, fit=args.fit, parts=args.parts,
                       localize_size=args.localize_size, close_ups=args.close_ups, static_camera=args.static_camera)
    print(format_benchmark(result))
    if args.node:  # the only sub-command that starts a ROS 2 graph: rclpy is imported here, not in the core
        from holo_pose_ros.nodes.node_benchmark import format_node_latency, node_latency

        result["node"] = node_latency(args.model, args.data, frames=args.frames, rate_hz=args.node_rate,
                                      backend=args.backend, tracking=args.tracking, threads=args.threads or 0,
                                      pipeline=not args.no_pipeline)
        print(format_node_latency(result["node"]))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
        print(f"json: {args.json}")
    return 0


def _cmd_export(args: argparse.Namespace) -> int:
    from holo_pose_ros.estimator import localize_pass_size
    from holo_pose_ros.model.onnx_runtime import cached_export, export_localizer, export_onnx
    from holo_pose_ros.model.weights import load_model

    net, _, card = load_model(args.model)
    if args.localizer is None:
        path = export_onnx(net, args.out) if args.out else cached_export(net, args.model)
        print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB, opset 18, dynamic batch; inputs image (B, 3, "
              f"{net.cfg.input_size}, {net.cfg.input_size}) in [0, 1] and K_crop (B, 3, 3))")
        return 0
    chosen = (card.get("estimator") or {}).get("localize_size") if args.localizer == -1 else args.localizer
    size = localize_pass_size(net, chosen)
    if size is None:
        raise ValueError(f"{args.model}: its whole-image pass is the full network (export it without --localizer)")
    path = export_localizer(net, size, args.out) if args.out else cached_export(net, args.model, size)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB, opset 18, dynamic batch; input image (B, 3, {size}, "
          f"{size}) in [0, 1]; outputs presence_logit (B,), DREAM's keypoints uv (B, N, 2) px and confidence (B, N))")
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
    g.add_argument("--workers", type=int, default=None,
                   help="parallel processes (default: all cores, at most one per 16 frames)")
    g.add_argument("--width", type=int, default=640, help="image width, pixels")
    g.add_argument("--height", type=int, default=480, help="image height, pixels")
    g.add_argument("--config", default="randomized", help="generator YAML: name in config/generate or a path")
    g.add_argument("--second-robot", default=None, help="another robot type standing beside the first in every "
                   "frame (each robot's ground truth its own DREAM object; config/generate/scene/second_robot.yaml)")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.set_defaults(func=_cmd_generate)

    s = sub.add_parser("show", help="statistics of a DREAM folder and a grid of frames with keypoints (PNG)")
    s.add_argument("data", help="DREAM folder")
    s.add_argument("--robot", required=True, help="robot name or robot YAML path")
    s.add_argument("--out", default=None, help="PNG path (default: DATA/preview.png)")
    s.add_argument("--n", type=int, default=12, help="frames in the grid")
    s.add_argument("--units", default="auto", choices=["auto", "m", "cm"], help="3D units of the files")
    s.set_defaults(func=_cmd_show)

    t = sub.add_parser("train", help="train a model on rendered views (config/train/*.yaml)")
    t.add_argument("--config", required=True, help="training YAML")
    t.add_argument("--out", default=None, help="run folder (overrides the YAML's `out`)")
    t.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    t.add_argument("--device", default=None, help="cpu, cuda, cuda:N (default: cuda when available)")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=_cmd_train)

    lf = sub.add_parser("train-lifter", help="train the 2D keypoints -> (q, T_cam<-base) lifter on synthetic samples "
                                             "from forward kinematics (no rendering; CPU minutes)")
    lf.add_argument("--robot", required=True, help="robot name (panda, kuka, baxter) or robot YAML path")
    lf.add_argument("--minutes", type=float, default=12.0, help="wall-clock training time, minutes")
    lf.add_argument("--steps", type=int, default=None, help="train this many steps instead of --minutes")
    lf.add_argument("--config", default=None, help="lifter YAML merged over config/lifter.yaml (the defaults)")
    lf.add_argument("--out", default=None, help="weights path without suffix (default: "
                                                "holo_pose_ros/weights/<robot>_lifter)")
    lf.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1: the MLP is small, and "
                                                            "threads that wait on a busy CPU's cores cost 10x)")
    lf.add_argument("--quiet", action="store_true", help="no progress bar")
    lf.set_defaults(func=_cmd_train_lifter)

    e = sub.add_parser("evaluate", help="score a model on a DREAM folder exactly as deployed (no ground truth)")
    e.add_argument("--model", required=True, help="shipped model name (panda) or model card / weights path")
    e.add_argument("--data", required=True, help="DREAM folder")
    e.add_argument("--known-joints", action="store_true", help="use the true joints (camera-to-robot calibration)")
    e.add_argument("--tracking", action="store_true", help="crop from the previous frame (for video sequences)")
    e.add_argument("--fit", action=argparse.BooleanOptionalAction, default=None,
                   help="kinematic fit to the detected keypoints; --no-fit: the paper's feed-forward estimate "
                        "(default: the model card's validated choice)")
    e.add_argument("--parts", action=argparse.BooleanOptionalAction, default=None,
                   help="search the fit by parts, each chain swept two joints at a time (fitting/parts.py; "
                        "default: the model card's validated choice)")
    e.add_argument("--close-ups", action=argparse.BooleanOptionalAction, default=None,
                   help="a second pass on a close-up of each of the robot YAML's close_ups (an arm, a hand), whose "
                        "detections of that part replace the crop's (default: the model card's validated choice)")
    e.add_argument("--localize-size", type=int, default=None, metavar="PX",
                   help="input size (px, a multiple of 32) of the whole-image pass, run 2D-only (presence and DREAM's "
                        "keypoints); 0: the full network pass (default: the model card's choice, else the crop's size)")
    e.add_argument("--static-camera", nargs="?", const=True, default=None, metavar="YAML",
                   help="the camera and the robot's base do not move (a video): earlier frames' base poses become a "
                        "prior on each frame's fit (config/static_camera.yaml, or a YAML of its keys to override)")
    e.add_argument("--ablation", action="store_true", help="on the same frames and detections: feed-forward, "
                                                         "lifter, fitted, and fitted with the true joints")
    e.add_argument("--depth-diagnostics", action=argparse.BooleanOptionalAction, default=None,
                   help="also fit each detection without the depth prior (untimed) and report signed root-depth "
                        "errors of DepthNet, that fit and the shipped estimate, and the 2D keypoint scale about the "
                        "true centroid (report key depth_diagnostics; default: on unless --tracking)")
    e.add_argument("--out", default=None, help="report.json path")
    e.add_argument("--plots", default=None, help="folder for the ADD curve and a grid of frames")
    e.add_argument("--limit", type=int, default=None, help="only the first N frames")
    e.add_argument("--units", default="auto", choices=["auto", "m", "cm"], help="3D units of the files")
    e.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N")
    e.add_argument("--backend", default="torch", choices=["torch", "onnxruntime"], help="what runs the network")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    e.set_defaults(func=_cmd_evaluate)

    d = sub.add_parser("dream-to-bag", help="convert a DREAM folder into a ROS 2 bag (images, camera_info, ground "
                                            "truth), without ROS")
    d.add_argument("data", help="DREAM folder")
    d.add_argument("out", help="output bag folder (must not exist)")
    d.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"], help="rosbag2 storage plugin")
    d.add_argument("--robot", default=None, help="robot name or YAML (default: from _object_settings.json)")
    d.add_argument("--units", default="auto", choices=["auto", "m", "cm"], help="3D units of the files")
    d.add_argument("--rate", type=float, default=10.0, help="frames per second of the synthetic stamps")
    d.add_argument("--start-time", type=float, default=1.0, help="stamp of the first frame, seconds")
    d.add_argument("--frame-id", default="camera_color_optical_frame", help="header frame_id of every message")
    d.add_argument("--limit", type=int, default=None, help="only the first N frames")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=_cmd_dream_to_bag)

    b = sub.add_parser("bag-eval", help="estimate every image of a ROS 2 bag (mcap or sqlite3) without DDS; write "
                                        "the estimates as a bag, and OUT/report.json when it has ground truth")
    _bag_inputs(b, "input bag folder")
    b.add_argument("--out", required=True, help="output bag folder (must not exist); report.json goes inside")
    b.add_argument("--use-rectified-p", action="store_true", help="K from CameraInfo.p instead of CameraInfo.k")
    b.add_argument("--min-confidence", type=float, default=None,
                   help="robot-presence probability below which a frame is not found (default: the estimator's)")
    b.add_argument("--tracking", action="store_true", help="crop from the previous frame (for video sequences)")
    b.add_argument("--storage", default="mcap", choices=["mcap", "sqlite3"], help="storage of the output bag")
    b.add_argument("--limit", type=int, default=None, help="only the first N images")
    b.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N")
    b.add_argument("--backend", default="torch", choices=["torch", "onnxruntime"], help="what runs the network")
    b.add_argument("--fit", action=argparse.BooleanOptionalAction, default=None,
                   help="kinematic fit to the detected keypoints; --no-fit: the paper's feed-forward estimate "
                        "(default: the model card's validated choice)")
    b.add_argument("--quiet", action="store_true", help="no progress bar")
    b.set_defaults(func=_cmd_bag_eval)

    c = sub.add_parser("calibrate", help="camera-to-robot calibration from a ROS 2 bag with the robot's trusted "
                                         "joint states, without DDS; writes calibration.yaml")
    _bag_inputs(c, "input bag folder (images, camera_info, the robot's joint states)")
    c.add_argument("--joint-states-topic", required=True, help="the robot's sensor_msgs/JointState topic")
    c.add_argument("--out", required=True, help="calibration YAML to write")
    c.add_argument("--child-frame-id", default=None, help="the robot base frame (default: <robot>_base_link)")
    c.add_argument("--window", type=int, default=None, help="average only the last N usable frames (default: all)")
    c.add_argument("--tolerance", type=float, default=None,
                   help="seconds between an image and its joint state (default: the node's, config/estimator.yaml)")
    c.add_argument("--no-compare", action="store_true",
                   help="skip the comparison with the same frames estimated without the joints")
    c.add_argument("--limit", type=int, default=None, help="only the first N images")
    c.add_argument("--backend", default="torch", choices=["torch", "onnxruntime"], help="what runs the network")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=_cmd_calibrate)

    a = sub.add_parser("adapt", help="adapt a model to your own camera from its images alone, or with the robot's "
                                     "joint states (a bag); writes OUT/model.yaml for every command and the node")
    a.add_argument("--model", required=True, help="parent model: shipped name (panda) or model card path")
    a.add_argument("--images", required=True, help="a DREAM folder (only its images and camera file are read), a "
                   "folder of images with a camera_info YAML, or a bag (mcap or sqlite3) with Image + CameraInfo")
    a.add_argument("--out", required=True, help="folder of the adapted model (must not exist)")
    a.add_argument("--joint-states-topic", default=None, help="the robot's sensor_msgs/JointState topic in the bag: "
                   "the fits use the reported joints, far better pseudo-labels")
    a.add_argument("--minutes", type=float, default=30.0, help="wall-clock budget, minutes (the fine-tuning stops "
                                                               "when it is spent)")
    a.add_argument("--camera-info", default=None, help="camera_info YAML of an image folder (default: the folder's "
                                                       "only YAML file)")
    a.add_argument("--image-topic", default=None, help="bag Image topic (default: the bag's only one)")
    a.add_argument("--info-topic", default=None, help="bag CameraInfo topic (default: the bag's only one)")
    a.add_argument("--limit", type=int, default=None, help="only the first N images")
    a.add_argument("--config", default=None, help="YAML merged over config/adapt.yaml")
    a.add_argument("--plots", default=None, help="folder for before/after frames and the fine-tuning's loss curves")
    a.add_argument("--seed", type=int, default=0, help="random seed of crops and batches")
    a.add_argument("--no-score", action="store_true", help="do not score the parent and the adapted model on a "
                   "labelled DREAM source's frames afterwards (about half the wall time of a 300-frame run)")
    a.add_argument("--quiet", action="store_true", help="no progress bar")
    a.set_defaults(func=_cmd_adapt)

    m = sub.add_parser("benchmark", help="per-stage latency, frames/s, GFLOPs and memory of the deployed pipeline")
    m.add_argument("--model", required=True, help="shipped model name (panda) or model card / weights path")
    m.add_argument("--data", required=True, help="DREAM folder of frames to estimate (e.g. holo-pose generate)")
    m.add_argument("--frames", type=int, default=100, help="timed frames (after 5 untimed warm-up frames)")
    m.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N")
    m.add_argument("--backend", default="torch", choices=["torch", "onnxruntime"], help="what runs the network")
    m.add_argument("--fit", action=argparse.BooleanOptionalAction, default=None,
                   help="kinematic fit to the detected keypoints; --no-fit: the paper's feed-forward estimate "
                        "(default: the model card's validated choice)")
    m.add_argument("--parts", action=argparse.BooleanOptionalAction, default=None,
                   help="search the fit by parts, each chain swept two joints at a time (fitting/parts.py; "
                        "default: the model card's validated choice)")
    m.add_argument("--static-camera", action="store_true",
                   help="the static camera's prior on the base pose (play a generated video: one camera per clip)")
    m.add_argument("--close-ups", action=argparse.BooleanOptionalAction, default=None,
                   help="a second pass on a close-up of each of the robot YAML's close_ups (an arm, a hand), whose "
                        "detections of that part replace the crop's (default: the model card's validated choice)")
    m.add_argument("--localize-size", type=int, default=None, metavar="PX",
                   help="input size (px, a multiple of 32) of the whole-image pass, run 2D-only (presence and DREAM's "
                        "keypoints); 0: the full network pass (default: the model card's choice, else the crop's size)")
    m.add_argument("--tracking", action="store_true", help="crop from the previous frame: one network pass a frame")
    m.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    m.add_argument("--json", default=None, help="write the figures to this JSON file")
    m.add_argument("--node", action="store_true", help="also time the estimator node in a real ROS 2 graph (image "
                                                      "published -> JointState received)")
    m.add_argument("--no-pipeline", action="store_true", help="the node figure with pipeline:=false (network and fit "
                   "on one thread)")
    m.add_argument("--node-rate", type=float, default=30.0, help="camera rate of the node figure, frames/s")
    m.set_defaults(func=_cmd_benchmark)

    x = sub.add_parser("export", help="export a model's network to ONNX (the onnxruntime backend's graph)")
    x.add_argument("--model", required=True, help="shipped model name (panda) or model card / weights path")
    x.add_argument("--format", default="onnx", choices=["onnx"], help="export format")
    x.add_argument("--out", default=None, help="ONNX path (default: the cache the onnxruntime backend reads)")
    x.add_argument("--localizer", type=int, nargs="?", const=-1, default=None, metavar="PX",
                   help="export the 2D-only whole-image pass instead, at PX (default: the card's choice, else the "
                        "crop's size)")
    x.set_defaults(func=_cmd_export)
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
