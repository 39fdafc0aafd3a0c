"""``hvo-graph simulate``: write the paper's scenario (camera, tracks, ground truth)."""

from __future__ import annotations

import argparse

from hvo_graph.arguments import finite_float, int_at_least
from hvo_graph.cli._common import PROG, progress


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``simulate`` on the subcommand parsers."""
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

    sim.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from hvo_graph.sim.scenario import paper_scenario, simulate, write_scenario

    overrides = {
        "seed": args.seed,
        "noise_var": args.noise_var,
        "duration": args.duration,
        "fps": args.fps,
        "num_points": args.num_points,
    }
    config = paper_scenario(noisy=True, **{k: v for k, v in overrides.items() if v is not None})
    progress(f"simulating {config.num_frames} frames of {config.num_points} points")
    scenario = simulate(config)
    write_scenario(args.out, scenario)
    print(
        f"{PROG} simulate: wrote {config.num_frames} frames, {config.num_points} points, "
        f"noise variance {config.noise_var:g} px^2 to {args.out}"
    )
    return 0
