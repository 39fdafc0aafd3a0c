"""The ``hvo-graph`` command: ``simulate``, ``estimate`` and ``evaluate`` (docs/conventions.md).

A thin layer over the library: it parses arguments, reads the contract's files,
calls :func:`hvo_graph.sim.scenario.simulate`, :func:`hvo_graph.pipeline.estimate`
or :mod:`hvo_graph.eval.metrics`, and writes the contract's files. Bad input
(an :class:`~hvo_graph.errors.InputError`, or a file that cannot be read or
written) prints one line ``hvo-graph: error: ...`` on stderr and exits with
status 2, like argparse's own usage errors; never a traceback.

Examples::

    hvo-graph simulate --out run/                       # the paper's noisy scenario
    hvo-graph estimate --camera run/camera.yaml --tracks run/tracks.csv \\
        --method smoother --out run/smoother
    hvo-graph evaluate --estimate run/smoother --groundtruth run/
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from hvo_graph.arguments import acceleration_sigma_value, finite_float, int_at_least
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import (
    COMMAND_METHODS,
    KALMAN_R_PRESETS,
    ROBUST_LOSSES,
    VELOCITY_FACTOR_POLICIES,
    check_applicable,
)

if TYPE_CHECKING:  # the CLI imports the heavy modules lazily, per subcommand
    from hvo_graph.geometry.camera import CameraModel
    from hvo_graph.types import FrameObservations

PROG = "hvo-graph"
#: ``--method`` choices, from the method registry (the first is the default).
METHODS: tuple[str, ...] = COMMAND_METHODS
#: ``--kalman-r`` choices.
KALMAN_R: tuple[str, ...] = KALMAN_R_PRESETS
#: ``--robust`` choices: "none" or a robust loss.
ROBUST: tuple[str, ...] = ("none", *ROBUST_LOSSES)
#: RANSAC threshold on H_d for tracks from images (KLT drifts off the plane at edges).
IMAGE_RANSAC_PX = 2.0


def _progress(message: str) -> None:
    """Progress notes go to stderr, and only when a person is watching it."""
    if sys.stderr.isatty():
        print(f"{PROG}: {message}", file=sys.stderr, flush=True)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (subcommands simulate, estimate, evaluate)."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        description="Homography-based visual odometry fused in a GTSAM factor graph.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sim = sub.add_parser(
        "simulate",
        help="simulate the paper's scenario (tracks, camera and ground truth)",
        description="Write DIR/camera.yaml, DIR/tracks.csv, DIR/groundtruth.txt (TUM, T_wc) and "
        "DIR/groundtruth_velocity.csv. Defaults reproduce the paper's noisy run "
        "(variance 0.05 px^2, 30 fps, 4 points, 10 s).",
    )
    sim.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    sim.add_argument("--scenario", choices=("paper",), default="paper", help="scenario (paper)")
    sim.add_argument("--seed", type=int_at_least(0), default=0, help="noise seed (default 0)")
    sim.add_argument(
        "--noise-var",
        type=finite_float(0.0, strict=False),
        default=None,
        metavar="PX2",
        help="pixel noise variance in px^2 (default 0.05; 0 for the noise-free run)",
    )
    sim.add_argument(
        "--duration", type=finite_float(0.0, strict=True), default=None, metavar="S", help="seconds"
    )
    sim.add_argument(
        "--fps", type=finite_float(0.0, strict=True), default=None, metavar="F", help="frame rate"
    )
    sim.add_argument(
        "--num-points", type=int_at_least(4), default=None, metavar="N", help="plane points"
    )

    est = sub.add_parser(
        "estimate",
        help="estimate the trajectory from tracks",
        description="Write DIR/trajectory.txt (TUM, T_wc), DIR/velocity.csv and, with "
        "--covariance, DIR/covariance.csv.",
    )
    est.set_defaults(options_parser=est)  # --config values are parsed by these actions
    est.add_argument("--camera", required=True, metavar="FILE", help="camera/scene YAML")
    source = est.add_mutually_exclusive_group(required=True)
    source.add_argument("--tracks", metavar="FILE", help="feature tracks CSV (frame,t,id,u,v)")
    source.add_argument(
        "--images",
        metavar="PATH",
        help="image folder (sorted by name; PATH/times.txt or --fps gives the times) or video",
    )
    est.add_argument("--method", choices=METHODS, default=METHODS[0], help="default: smoother")
    est.add_argument("--out", required=True, metavar="DIR", help="output folder (created)")
    # Options left out are not passed on, so the pipeline's own defaults apply.
    S = argparse.SUPPRESS
    est.add_argument("--seed", type=int_at_least(0), default=S, help="Kalman initial-state seed")
    est.add_argument("--kalman-r", choices=KALMAN_R, default=S, help="Kalman R_k preset")
    est.add_argument(
        "--kalman-world-velocity",
        action="store_true",
        default=S,
        help="rotate measured v into the world frame before the Kalman update (not the paper's)",
    )
    est.add_argument(
        "--online", action="store_true", default=S, help="write the causal (filtered) estimate"
    )
    est.add_argument(
        "--covariance", action="store_true", default=S, help="also write covariance.csv"
    )
    est.add_argument(
        "--lag",
        type=finite_float(0.0, strict=True),
        default=S,
        metavar="SECONDS",
        help="fixed-lag window",
    )
    est.add_argument("--robust", choices=ROBUST, default=S, help="robust loss of the smoother")
    est.add_argument(
        "--pixel-sigma",
        type=finite_float(0.0, strict=True),
        default=S,
        metavar="PX",
        help="pixel noise std (overrides the camera file's noise.pixel_sigma)",
    )
    est.add_argument(
        "--ransac-px",
        type=finite_float(0.0, strict=True),
        default=S,
        metavar="PX",
        help="RANSAC threshold on H_d in pixels (default: 5 pixel sigmas, at least "
        "0.5 px, for --tracks; 2 px for --images)",
    )
    est.add_argument(
        "--no-ransac", action="store_true", default=S, help="least squares on every point"
    )
    est.add_argument(
        "--gate-chi2",
        type=finite_float(0.0, strict=True),
        default=S,
        metavar="X2",
        help="per-point chi^2 gate on the transfer residuals (default 13.8, chi^2_2(0.999))",
    )
    est.add_argument("--no-gate", action="store_true", default=S, help="no per-point gate")
    est.add_argument(
        "--reject-after",
        type=int_at_least(1),
        default=S,
        metavar="N",
        help="exclude a track rejected in N frames (default 3)",
    )
    model = est.add_argument_group("factor-graph and filter options")
    model.add_argument(
        "--acceleration-sigma",
        type=acceleration_sigma_value,
        default=S,
        metavar="auto|S|SW,SV",
        help="white-noise acceleration of the motion model (rad s^-3/2, m s^-3/2); "
        "default auto: fitted to the sequence",
    )
    model.add_argument(
        "--robust-threshold",
        type=finite_float(0.0, strict=True),
        default=S,
        metavar="X",
        help="robust loss threshold on the whitened residual (default 3.55)",
    )
    model.add_argument(
        "--velocity-factors",
        choices=VELOCITY_FACTOR_POLICIES,
        default=S,
        help="H_c twist factors: only where poses leave a gap (default) or all",
    )
    model.add_argument(
        "--independent-poses",
        action="store_true",
        default=S,
        help="treat the H_d poses as independent (no shared reference-frame noise)",
    )
    model.add_argument(
        "--relinearize-threshold",
        type=finite_float(0.0, strict=True),
        default=S,
        metavar="X",
        help="ISAM2 pose relinearization threshold (rad, m; default 0.05)",
    )
    model.add_argument(
        "--relinearize-skip",
        type=int_at_least(1),
        default=S,
        metavar="N",
        help="ISAM2 checks relinearization every N updates (default 10)",
    )
    est.add_argument(
        "--config",
        metavar="FILE",
        default=None,
        help="YAML mapping of these options (names without --); the command line wins",
    )
    images = est.add_argument_group("image input (--images)")
    images.add_argument(
        "--fps",
        type=finite_float(0.0, strict=True),
        default=None,
        metavar="F",
        help="frame rate of an image folder without times.txt (default 30) or of a video",
    )
    images.add_argument(
        "--max-features", type=int_at_least(4), default=None, metavar="N", help="default 200"
    )
    images.add_argument(
        "--save-tracks", metavar="FILE", default=None, help="also write the tracks CSV here"
    )

    ev = sub.add_parser(
        "evaluate",
        help="errors of an estimate against ground truth",
        description="Position (m), orientation (deg), linear (m/s) and angular (rad/s) velocity "
        "errors, RMSE and max, matched by timestamp.",
    )
    ev.add_argument("--estimate", required=True, metavar="DIR", help="an estimate output folder")
    ev.add_argument("--groundtruth", required=True, metavar="DIR", help="a simulate-style folder")
    ev.add_argument("--json", action="store_true", help="print one JSON object instead of a table")
    ev.add_argument(
        "--skip",
        type=finite_float(0.0, strict=False),
        default=None,
        metavar="SECONDS",
        help="ignore frames in the first SECONDS after the ground truth's first timestamp",
    )
    return parser


def _simulate(args: argparse.Namespace) -> int:
    from hvo_graph.sim.scenario import paper_scenario, simulate, write_scenario

    overrides = {
        "seed": args.seed,
        "noise_var": args.noise_var,
        "duration": args.duration,
        "fps": args.fps,
        "num_points": args.num_points,
    }
    config = paper_scenario(noisy=True, **{k: v for k, v in overrides.items() if v is not None})
    _progress(f"simulating {config.num_frames} frames of {config.num_points} points")
    scenario = simulate(config)
    write_scenario(args.out, scenario)
    print(
        f"{PROG} simulate: wrote {config.num_frames} frames, {config.num_points} points, "
        f"noise variance {config.noise_var:g} px^2 to {args.out}"
    )
    return 0


def _estimate(args: argparse.Namespace) -> int:
    from hvo_graph.io.config import load_scene
    from hvo_graph.io.tracks import read_tracks, write_tracks
    from hvo_graph.io.trajectory import write_estimate_dir, write_run_record
    from hvo_graph.pipeline import FRONT_END_OPTIONS, run_estimate
    from hvo_graph.report.tables import software_versions

    scene = load_scene(args.camera)
    if args.images is not None:
        observations = _track_images(args, scene.camera)
        if args.save_tracks:
            write_tracks(args.save_tracks, observations)
    else:
        for flag in ("fps", "max_features", "save_tracks"):
            if getattr(args, flag) is not None:
                raise InputError(f"--{flag.replace('_', '-')}: only for --images input")
        observations = read_tracks(args.tracks)
    if args.config is not None:
        _apply_config(args, args.config)
    options = _estimate_options(args)
    check_applicable(
        args.method,
        [k for k in options if k not in FRONT_END_OPTIONS],
        spell=lambda name: _FLAGS.get(name, "--" + name.replace("_", "-")),
    )
    _progress(f"estimating {len(observations)} frames with --method {args.method}")
    start = time.perf_counter()
    run = run_estimate(observations, scene, method=args.method, **options)
    seconds = time.perf_counter() - start
    _progress(f"done in {seconds:.1f} s")
    write_estimate_dir(args.out, run.trajectory)
    record = {
        "command": "estimate",
        **run.summary(),
        "inputs": {
            "camera": str(args.camera),
            **({"images": str(args.images)} if args.images else {"tracks": str(args.tracks)}),
            **({"config": str(args.config)} if args.config else {}),
        },
        "wall_time_s": round(seconds, 3),
        "software": f"hvo-graph {_version()}, {software_versions()}",
    }
    write_run_record(args.out, record)
    counts = run.summary()["counts"]
    rejected = counts["rejected_points"]  # type: ignore[index]
    note = f"; {rejected} track points rejected as outliers" if rejected else ""
    print(
        f"{PROG} estimate: wrote {len(run.trajectory)} frames ({args.method}) to {args.out}{note}"
    )
    return 0


#: ``estimate`` options: argparse dest -> library option name.
_OPTION_OF_DEST = {
    "seed": "seed",
    "kalman_r": "kalman_r",
    "kalman_world_velocity": "kalman_world_velocity",
    "online": "online",
    "covariance": "covariance",
    "lag": "lag",
    "robust": "robust",
    "robust_threshold": "robust_threshold",
    "acceleration_sigma": "acceleration_sigma",
    "velocity_factors": "velocity_factors",
    "relinearize_threshold": "relinearize_threshold",
    "relinearize_skip": "relinearize_skip",
    "pixel_sigma": "pixel_sigma",
    "ransac_px": "ransac_threshold_px",
    "reject_after": "reject_after",
    "gate_chi2": "outlier_chi2",
}

#: Library option -> its flag, where the names differ.
_FLAGS = {
    "ransac_threshold_px": "--ransac-px",
    "outlier_chi2": "--gate-chi2",
    "shared_reference_noise": "--independent-poses",
}


def _estimate_options(args: argparse.Namespace) -> dict[str, object]:
    """The library options of the flags given (left-out flags keep the library defaults)."""
    options = {
        option: getattr(args, dest)
        for dest, option in _OPTION_OF_DEST.items()
        if hasattr(args, dest)
    }
    if getattr(args, "no_ransac", False):
        if "ransac_threshold_px" in options:
            raise InputError("--no-ransac: contradicts --ransac-px")
        options["ransac"] = False
    if getattr(args, "no_gate", False):
        if "outlier_chi2" in options:
            raise InputError("--no-gate: contradicts --gate-chi2")
        options["outlier_chi2"] = None
    if getattr(args, "independent_poses", False):
        options["shared_reference_noise"] = False
    if "ransac_threshold_px" not in options and args.images is not None:
        options["ransac_threshold_px"] = IMAGE_RANSAC_PX
    if options.get("robust") == "none":
        options["robust"] = None
    return options


def _apply_config(args: argparse.Namespace, path: str) -> None:
    """Set the options a YAML config file gives, unless the command line gave them.

    Keys are the option names without "--" (dashes or underscores); values are
    parsed by the same argument types as on the command line.
    """
    import yaml

    from hvo_graph.io._common import read_text

    try:
        data = yaml.safe_load(read_text(path))
    except yaml.YAMLError as exc:
        raise InputError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if data is None:
        return
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of option names to values")
    actions = {a.dest: a for a in args.options_parser._actions if a.option_strings}
    fixed = {"camera", "tracks", "images", "out", "config", "help", "method"}
    for key, value in data.items():
        dest = str(key).replace("-", "_")
        action = actions.get(dest)
        if action is None or dest in fixed:
            allowed = sorted(d.replace("_", "-") for d in actions if d not in fixed)
            raise InputError(f"{path}: {key}: unknown option, expected one of {', '.join(allowed)}")
        if getattr(args, dest, None) not in (None, False):
            continue  # given on the command line
        setattr(args, dest, _config_value(path, str(key), action, value))


def _config_value(path: str, key: str, action: argparse.Action, value: object) -> object:
    if action.nargs == 0:  # a store_true flag
        if not isinstance(value, bool):
            raise InputError(f"{path}: {key}: expected true or false, got {value!r}")
        return value
    text = ",".join(map(str, value)) if isinstance(value, list) else str(value)
    try:
        parsed = action.type(text) if action.type else text  # type: ignore[operator]
    except (argparse.ArgumentTypeError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: {key}: {exc}") from None
    if action.choices is not None and parsed not in action.choices:
        choices = ", ".join(map(str, action.choices))
        raise InputError(f"{path}: {key}: expected one of {choices}, got {value!r}")
    return parsed


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hvo-graph")
    except PackageNotFoundError:
        return "unknown"


def _track_images(args: argparse.Namespace, camera: CameraModel) -> list[FrameObservations]:
    from hvo_graph.frontend.tracking import TrackerConfig, tracks_from_images

    config = (
        TrackerConfig()
        if args.max_features is None
        else TrackerConfig(
            max_features=args.max_features, min_tracked=min(args.max_features // 2, 100)
        )
    )
    _progress(f"tracking features in {args.images}")
    return tracks_from_images(args.images, camera, fps=args.fps, config=config)


def _evaluate(args: argparse.Namespace) -> int:
    from hvo_graph.eval.metrics import error_series, format_table, summarize
    from hvo_graph.io.trajectory import read_estimate_dir, read_groundtruth_dir

    estimate = read_estimate_dir(args.estimate)
    groundtruth = read_groundtruth_dir(args.groundtruth)
    series = error_series(estimate, groundtruth)
    t_start = None if args.skip is None else float(groundtruth.t[0]) + args.skip
    summary = summarize(series, t_start=t_start)
    if args.json:
        print(json.dumps(summary.as_dict()))
    else:
        name = Path(args.estimate).resolve().name or str(args.estimate)
        print(format_table({name: summary}))
    return 0


def _os_error_message(exc: OSError) -> str:
    """'cannot read|write PATH: reason', naming the path the OS complained about."""
    reason = exc.strerror or str(exc)
    if exc.filename is None:
        return reason
    return f"{exc.filename}: {reason}"


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 usage or input error)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2)
        return int(exc.code or 0)
    handler = {"simulate": _simulate, "estimate": _estimate, "evaluate": _evaluate}[args.command]
    try:
        return handler(args)
    except InputError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
    except OSError as exc:
        print(f"{PROG}: error: {_os_error_message(exc)}", file=sys.stderr)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
