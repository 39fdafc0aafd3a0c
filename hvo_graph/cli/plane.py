"""``hvo-graph plane``: the plane n*, d* of the first frame, written into a camera YAML.

From a target the first image shows (chessboard, ChArUco or ArUco board:
:mod:`hvo_graph.frontend.target`) or from the camera's height above a floor and
its tilt. The output is a complete camera YAML for ``estimate --camera``.
"""

from __future__ import annotations

import argparse

from hvo_graph.arguments import finite_float
from hvo_graph.cli._common import PROG
from hvo_graph.errors import InputError


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``plane`` on the subcommand parsers."""
    cmd = sub.add_parser(
        "plane",
        help="derive the plane (n*, d*) from a target or a camera height; write the camera YAML",
        description="Write FILE: the camera YAML of --camera with plane.distance (d*) and "
        "plane.normal (n*) of the first frame, from a target seen in --image "
        "(cv2.solvePnP on its corners) or from --height and --tilt.",
    )
    cmd.add_argument(
        "--camera",
        required=True,
        metavar="FILE",
        help="camera YAML (its plane section, if any, is replaced)",
    )
    cmd.add_argument("--out", required=True, metavar="FILE", help="camera YAML to write")
    cmd.add_argument(
        "--target",
        metavar="SPEC",
        help="chessboard:COLSxROWS:SQUARE (inner corners, metres), "
        "charuco:COLSxROWS:SQUARE:MARKER:DICT or aruco:COLSxROWS:MARKER:GAP:DICT",
    )
    cmd.add_argument(
        "--image",
        metavar="PATH",
        help="the first frame: an image, or an image folder or video (its first frame)",
    )
    cmd.add_argument(
        "--height",
        type=finite_float(0.0, strict=True),
        metavar="M",
        help="camera height above the floor, metres (instead of a target)",
    )
    cmd.add_argument(
        "--tilt",
        type=finite_float(-90.0, strict=True),
        metavar="DEG",
        help="with --height: optical axis below the horizon, degrees (90: straight down)",
    )
    cmd.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hvo_graph.frontend.target import (
        first_image,
        parse_target,
        plane_from_height,
        plane_from_target,
    )
    from hvo_graph.io.config import SceneConfig, load_camera, save_scene

    target = args.target is not None or args.image is not None
    floor = args.height is not None or args.tilt is not None
    if target == floor:
        raise InputError("plane: give either --target and --image, or --height and --tilt")
    pair = ("target", "image") if target else ("height", "tilt")
    for name in pair:
        if getattr(args, name) is None:
            other = next(n for n in pair if n != name)
            raise InputError(f"--{name}: required with --{other}")
    spec = parse_target(args.target) if target else None
    camera, _, pixel_sigma = load_camera(args.camera)
    if spec is not None:
        found = plane_from_target(first_image(args.image, camera), camera, spec)
        plane = found.plane
        how = (
            f"{spec.kind} {spec.columns}x{spec.rows}: {len(found.image_points)} corners, "
            f"reprojection {found.rms_px:.2f} px rms"
        )
    else:
        plane = plane_from_height(args.height, args.tilt)
        how = f"height {args.height:g} m, tilt {args.tilt:g} deg"
    save_scene(args.out, SceneConfig(camera, plane, pixel_sigma))
    normal = ", ".join(f"{x:.4f}" for x in plane.normal)
    print(f"{PROG} plane: {how}; d* = {plane.distance:.4f} m, n* = [{normal}]; wrote {args.out}")
    return 0
