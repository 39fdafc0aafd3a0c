"""``hvo-graph estimate``: tracks or images in, the contract's trajectory files out."""

from __future__ import annotations

import argparse
import time
from typing import TYPE_CHECKING

from hvo_graph.arguments import acceleration_sigma_value, finite_float, int_at_least
from hvo_graph.cli._common import PROG, package_version, progress
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import (
    COMMAND_METHODS,
    KALMAN_R_PRESETS,
    ROBUST_LOSSES,
    VELOCITY_FACTOR_POLICIES,
    check_applicable,
)

if TYPE_CHECKING:  # the heavy modules are imported when the command runs
    from hvo_graph.geometry.camera import CameraModel
    from hvo_graph.types import FrameObservations

#: ``--method`` choices, from the method registry (the first is the default).
METHODS: tuple[str, ...] = COMMAND_METHODS
#: ``--kalman-r`` choices.
KALMAN_R: tuple[str, ...] = KALMAN_R_PRESETS
#: ``--robust`` choices: "none" or a robust loss.
ROBUST: tuple[str, ...] = ("none", *ROBUST_LOSSES)
#: RANSAC threshold on H_d for tracks from images (KLT drifts off the plane at edges).
IMAGE_RANSAC_PX = 2.0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``estimate`` on the subcommand parsers."""
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
    images.add_argument(
        "--plane",
        choices=("auto",),
        default=None,
        help="auto: n*, d* from the --target seen in the first image, in place of the "
        "camera file's plane section (which may be left out); default: the camera file's",
    )
    images.add_argument(
        "--target",
        metavar="SPEC",
        default=None,
        help="with --plane auto: chessboard:COLSxROWS:SQUARE, "
        "charuco:COLSxROWS:SQUARE:MARKER:DICT or aruco:COLSxROWS:MARKER:GAP:DICT",
    )

    est.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hvo_graph.io.config import load_scene
    from hvo_graph.io.tracks import read_tracks, write_tracks
    from hvo_graph.io.trajectory import write_estimate_dir, write_run_record
    from hvo_graph.pipeline import FRONT_END_OPTIONS, run_estimate
    from hvo_graph.report.tables import software_versions

    scene = _auto_scene(args) if args.plane == "auto" else load_scene(args.camera)
    if args.target is not None and args.plane != "auto":
        raise InputError("--target: only with --plane auto")
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
    progress(f"estimating {len(observations)} frames with --method {args.method}")
    start = time.perf_counter()
    run = run_estimate(observations, scene, method=args.method, **options)
    seconds = time.perf_counter() - start
    progress(f"done in {seconds:.1f} s")
    write_estimate_dir(args.out, run.trajectory)
    record = {
        "command": "estimate",
        **run.summary(),
        "inputs": {
            "camera": str(args.camera),
            **({"images": str(args.images)} if args.images else {"tracks": str(args.tracks)}),
            **({"config": str(args.config)} if args.config else {}),
            **({"target": str(args.target)} if args.plane == "auto" else {}),
        },
        "plane": {"distance": scene.plane.distance, "normal": _listed(scene.plane.normal)},
        "wall_time_s": round(seconds, 3),
        "software": f"hvo-graph {package_version()}, {software_versions()}",
    }
    write_run_record(args.out, record)
    _report_health(run.frames)
    counts = run.summary()["counts"]
    rejected = counts["rejected_points"]  # type: ignore[index]
    note = f"; {rejected} track points rejected as outliers" if rejected else ""
    print(
        f"{PROG} estimate: wrote {len(run.trajectory)} frames ({args.method}) to {args.out}{note}"
    )
    return 0


def _report_health(frames: list) -> None:
    """The front end's health on stderr, always (a lost pose must never go unnoticed)."""
    import sys

    from hvo_graph.frontend.health import front_end_health

    health = front_end_health(frames)
    print(f"{PROG} estimate: front end: {health.summary()}", file=sys.stderr)
    for warning in health.warnings():
        print(f"{PROG} estimate: warning: {warning}", file=sys.stderr)


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
    fixed = {"camera", "tracks", "images", "out", "config", "help", "method", "plane", "target"}
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


def _auto_scene(args: argparse.Namespace) -> object:
    """The scene of ``--plane auto``: the camera file's camera, the plane of the target
    in the first image (:mod:`hvo_graph.frontend.target`)."""
    from hvo_graph.frontend.target import first_image, parse_target, plane_from_target
    from hvo_graph.io.config import SceneConfig, load_camera

    if args.target is None:
        raise InputError("--plane auto: needs --target (the board seen in the first image)")
    if args.images is None:
        raise InputError("--plane auto: needs --images (the first image shows the target)")
    spec = parse_target(args.target)
    camera, _, pixel_sigma = load_camera(args.camera)
    found = plane_from_target(first_image(args.images, camera), camera, spec)
    progress(f"plane from the {spec.kind}: d* = {found.plane.distance:.4f} m")
    return SceneConfig(camera, found.plane, pixel_sigma)


def _listed(normal: object) -> list[float] | None:
    return None if normal is None else [float(x) for x in normal]  # type: ignore[union-attr]


def _track_images(args: argparse.Namespace, camera: CameraModel) -> list[FrameObservations]:
    from hvo_graph.frontend.tracking import TrackerConfig, tracks_from_images

    config = (
        TrackerConfig()
        if args.max_features is None
        else TrackerConfig(
            max_features=args.max_features, min_tracked=min(args.max_features // 2, 100)
        )
    )
    progress(f"tracking features in {args.images}")
    return tracks_from_images(args.images, camera, fps=args.fps, config=config)
