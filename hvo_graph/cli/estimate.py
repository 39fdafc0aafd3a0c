"""``hvo-graph estimate``: tracks or images in, the contract's trajectory files out."""

from __future__ import annotations

import argparse
import sys
import time
from typing import TYPE_CHECKING

from hvo_graph.arguments import acceleration_sigma_value, finite_float, int_at_least
from hvo_graph.cli._common import PROG, package_version, progress
from hvo_graph.cli._inputs import normal_argument, scene_from_arguments, track_recording
from hvo_graph.errors import InputError
from hvo_graph.estimators.registry import (
    COMMAND_METHODS,
    KALMAN_R_PRESETS,
    MOTION_MODEL_CHOICES,
    ROBUST_LOSSES,
    VELOCITY_FACTOR_POLICIES,
    check_applicable,
)

if TYPE_CHECKING:  # the heavy modules are imported when the command runs
    from hvo_graph.io.config import SceneConfig
    from hvo_graph.io.sequences import Recording

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
    est.add_argument(
        "--camera",
        metavar="FILE",
        default=None,
        help="camera/scene YAML, or a calibration file (OpenCV FileStorage YAML/XML, ROS "
        "camera_info, Kalibr camchain, EuRoC sensor.yaml) with --plane-distance; may be left "
        "out when --images holds a calibration (EuRoC sensor.yaml, a bag's CameraInfo)",
    )
    source = est.add_mutually_exclusive_group(required=True)
    source.add_argument("--tracks", metavar="FILE", help="feature tracks CSV (frame,t,id,u,v)")
    source.add_argument(
        "--images",
        metavar="PATH",
        help="recorded images, layout recognised from PATH: image folder (PATH/times.txt or "
        "--fps gives the times), video file, TUM RGB-D (folder with rgb.txt, or rgb.txt), "
        "EuRoC/ASL (root, mav0/ or cam0/), ROS 1 .bag or ROS 2 bag folder",
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
        help="robust loss threshold on the whitened residual (default 3.55; tight methods: "
        "Huber on the pixel residual, default 2.45)",
    )
    model.add_argument(
        "--velocity-factors",
        choices=VELOCITY_FACTOR_POLICIES,
        default=S,
        help="H_c twist factors: only where poses leave a gap (default) or all",
    )
    model.add_argument(
        "--motion-model",
        choices=MOTION_MODEL_CHOICES,
        default=S,
        help="smoother motion model: white-noise acceleration (wna, default), white-noise "
        "jerk (wnj), or auto: the one the sequence's poses make more likely",
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
    plane = est.add_argument_group(
        "plane (when --camera is a calibration file without one, or is left out)"
    )
    plane.add_argument(
        "--plane-distance",
        type=finite_float(0.0, strict=True),
        default=None,
        metavar="D",
        help="d*: metres from the first frame's optical centre to the plane",
    )
    plane.add_argument(
        "--plane-normal",
        type=normal_argument,
        default=None,
        metavar="NX,NY,NZ",
        help="n*: unit normal in the first camera frame, away from the camera "
        "(default: estimated from the images)",
    )
    images = est.add_argument_group("image input (--images)")
    images.add_argument(
        "--fps",
        type=finite_float(0.0, strict=True),
        default=None,
        metavar="F",
        help="frame rate of an image folder without times.txt (required there), or replacing "
        "a video's own timestamps",
    )
    images.add_argument(
        "--topic", default=None, metavar="TOPIC", help="image topic of a bag with several"
    )
    images.add_argument(
        "--max-features", type=int_at_least(4), default=None, metavar="N", help="default 200"
    )
    images.add_argument(
        "--save-tracks", metavar="FILE", default=None, help="also write the tracks CSV here"
    )
    images.add_argument(
        "--compensate-exposure", action="store_true", default=None,
        help="divide each image by its gain relative to the first (auto exposure)",
    )  # fmt: skip
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
        "charuco:COLSxROWS:SQUARE:MARKER:DICT or aruco:COLSxROWS:MARKER:GAP:DICT; "
        "features are then tracked on the board only",
    )

    est.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hvo_graph.io._common import staged_output
    from hvo_graph.io.sequences import open_recording
    from hvo_graph.io.tracks import read_track_table, write_tracks
    from hvo_graph.io.trajectory import ESTIMATE_FILES, write_estimate_dir, write_run_record
    from hvo_graph.pipeline import FRONT_END_OPTIONS, run_estimate
    from hvo_graph.report.tables import software_versions

    if args.config is not None:  # first: it may set input options such as fps
        _apply_config(args, args.config)
    if args.target is not None and args.plane != "auto":
        raise InputError("--target: only with --plane auto")
    if args.plane == "auto" and args.target is None:
        raise InputError("--plane auto: needs --target (the board seen in the first image)")
    recording = None
    if args.images is not None:
        recording = open_recording(args.images, fps=args.fps, topic=args.topic)
        scene = (
            _auto_scene(args, recording)
            if args.plane == "auto"
            else scene_from_arguments(args, recording)
        )
        observations = track_recording(args, scene, recording)
        if args.save_tracks:
            write_tracks(args.save_tracks, observations)
    else:
        for flag in ("fps", "topic", "max_features", "save_tracks", "compensate_exposure"):
            if getattr(args, flag) is not None:
                raise InputError(f"--{flag.replace('_', '-')}: only for --images input")
        if args.plane == "auto":
            raise InputError("--plane auto: needs --images (the first image shows the target)")
        scene = scene_from_arguments(args, None)
        observations = read_track_table(args.tracks)  # frames made one at a time
    options = _estimate_options(args)
    check_applicable(
        args.method,
        [k for k in options if k not in FRONT_END_OPTIONS],
        spell=lambda name: _FLAGS.get(name, "--" + name.replace("_", "-")),
    )
    progress(f"estimating {len(observations)} frames with --method {args.method}")
    start = time.perf_counter()
    try:
        run = run_estimate(observations, scene, method=args.method, **options)
    except InputError as exc:  # say where the normal came from
        if not str(exc).startswith("plane.normal:") or args.plane == "auto":
            raise
        given = (
            "--plane-normal" if args.plane_normal is not None else f"{args.camera}: plane.normal"
        )
        raise InputError(given + str(exc).removeprefix("plane.normal")) from None
    seconds = time.perf_counter() - start
    progress(f"done in {seconds:.1f} s")
    record = {
        "command": "estimate",
        **run.summary(),
        "inputs": {
            **({"camera": str(args.camera)} if args.camera else {}),
            **(
                {"images": str(args.images), "layout": recording.layout}
                if recording is not None
                else {"tracks": str(args.tracks)}
            ),
            **({"topic": args.topic} if args.topic else {}),
            **({"plane_distance": args.plane_distance} if args.plane_distance else {}),
            **({"plane_normal": args.plane_normal} if args.plane_normal else {}),
            **({"config": str(args.config)} if args.config else {}),
            **({"target": str(args.target)} if args.plane == "auto" else {}),
        },
        "plane": {"distance": scene.plane.distance, "normal": _listed(scene.plane.normal)},
        "wall_time_s": round(seconds, 3),
        "software": f"hvo-graph {package_version()}, {software_versions()}",
    }
    # All files or none: a failure or Ctrl-C while writing leaves --out as it was.
    with staged_output(args.out, owned=(*ESTIMATE_FILES, "run.json")) as stage:
        write_estimate_dir(stage, run.trajectory)
        write_run_record(stage, record)
    _report_health(run.frames)
    if run.normal_fit is not None:
        from hvo_graph.frontend.normal_search import UNOBSERVED_SIGMA_DEG

        fit = run.normal_fit
        normal = ", ".join(f"{x:.4f}" for x in fit.normal)
        print(
            f"{PROG} estimate: plane normal n* = ({normal}) fitted to {len(fit.motions)} "
            f"frames, standard deviation {fit.sigma_deg:.2f} deg",
            file=sys.stderr,
        )
        if fit.sigma_deg >= UNOBSERVED_SIGMA_DEG:
            print(
                f"{PROG} estimate: warning: no frame translates measurably against the first "
                "(the camera turns or stands still): these tracks cannot tell n*, and the "
                "poses will be tilted once it moves; give the normal (plane.normal) if known",
                file=sys.stderr,
            )
    if run.pixel_noise is not None:
        sigma = f"{run.pixel_noise.sigma:.3g} px"
        print(
            f"{PROG} estimate: pixel noise sigma = {sigma}, read from the tracks "
            f"({run.pixel_noise.differences} differences; the camera file's "
            "noise.pixel_sigma or --pixel-sigma sets it)"
            if run.pixel_noise_used
            else f"{PROG} estimate: the tracks' frame-to-frame noise is {sigma}; the "
            f"pixel sigma stays {run.front_end.pixel_sigma:.4g} px, since errors that "
            "neighbouring tracks share do not show in it (the camera file's "
            "noise.pixel_sigma or --pixel-sigma sets it)",
            file=sys.stderr,
        )
    counts = run.summary()["counts"]
    rejected = counts["rejected_points"]  # type: ignore[index]
    note = f"; {rejected} track points rejected as outliers" if rejected else ""
    print(
        f"{PROG} estimate: wrote {len(run.trajectory)} frames ({args.method}) to {args.out}{note}"
    )
    return 0


def _report_health(frames: list) -> None:
    """The front end's health on stderr, always (a lost pose must never go unnoticed)."""

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
    "motion_model": "motion_model",
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


def _auto_scene(args: argparse.Namespace, recording: Recording) -> SceneConfig:
    """The scene of ``--plane auto``: the camera (``--camera``, else the recording's), the
    plane of the target in the first image (:mod:`hvo_graph.frontend.target`)."""
    from hvo_graph.frontend.target import parse_target, plane_from_target
    from hvo_graph.io.calibration import load_calibration
    from hvo_graph.io.config import SceneConfig, load_camera
    from hvo_graph.io.images import as_gray_image

    if args.target is None:
        raise InputError("--plane auto: needs --target (the board seen in the first image)")
    for flag in ("plane_distance", "plane_normal"):
        if getattr(args, flag) is not None:
            raise InputError(f"--{flag.replace('_', '-')}: contradicts --plane auto")
    spec = parse_target(args.target)
    pixel_sigma = None
    if args.camera is None and recording.camera is None:
        raise InputError(f"--camera: required, {args.images} carries no calibration")
    if args.camera is None:
        camera = recording.camera
    else:
        try:  # the project's camera YAML, whose plane section may be left out here
            camera, _, pixel_sigma = load_camera(args.camera)
        except InputError:  # another tool's calibration (or the YAML's own error, again)
            camera = load_calibration(args.camera).camera
    first = next(iter(recording.frames), None)
    if first is None:
        raise InputError(f"{args.images}: no frames")
    image = as_gray_image(first, recording.frames.names[0], camera)
    found = plane_from_target(image, camera, spec)
    progress(f"plane from the {spec.kind}: d* = {found.plane.distance:.4f} m")
    return SceneConfig(camera, found.plane, pixel_sigma)


def _listed(normal: object) -> list[float] | None:
    return None if normal is None else [float(x) for x in normal]  # type: ignore[union-attr]
