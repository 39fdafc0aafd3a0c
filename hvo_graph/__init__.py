"""hvo_graph: homography-based visual odometry fused in a GTSAM factor graph.

The main names of every layer are available from the package itself
(``hvo_graph.simulate``, ``hvo_graph.FactorGraphSmoother``, ...). They are
imported on first use (PEP 562 module ``__getattr__``), so ``import hvo_graph``
stays light: GTSAM, OpenCV and matplotlib load only when something that needs
them is used. The full API, layer by layer, is in docs/api.md.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable
from typing import Any

__version__ = "0.1.0"

#: Defining module -> the names re-exported from it, in the order of the layers.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "hvo_graph.errors": ("InputError",),
    "hvo_graph.types": (
        "Plane",
        "FrameObservations",
        "PoseMeasurement",
        "VelocityMeasurement",
        "FrameMeasurement",
        "Trajectory",
        "StateEstimate",
    ),
    "hvo_graph.geometry.camera": ("CameraModel",),
    "hvo_graph.render": ("render_plane_images",),
    "hvo_graph.tracking": ("TrackerConfig", "FeatureTracker", "track_images", "tracks_from_images"),
    "hvo_graph.frontend": ("FrontEndConfig", "MeasurementFrontEnd", "measure_sequence"),
    "hvo_graph.estimators.base": ("Estimator",),
    "hvo_graph.estimators.measurements": ("RawMeasurements",),
    "hvo_graph.estimators.kalman": ("KalmanBaseline",),
    "hvo_graph.estimators.smoother": ("FactorGraphSmoother", "BatchSmoother", "FixedLagSmoother"),
    "hvo_graph.io.config": ("SceneConfig", "load_scene", "save_scene"),
    "hvo_graph.io.tracks": ("read_tracks", "write_tracks"),
    "hvo_graph.io.trajectory": (
        "read_tum",
        "write_tum",
        "read_estimate_dir",
        "write_estimate_dir",
        "read_groundtruth_dir",
        "write_groundtruth_dir",
    ),
    "hvo_graph.simulation": (
        "ScenarioConfig",
        "Scenario",
        "paper_scenario",
        "simulate",
        "write_scenario",
    ),
    "hvo_graph.evaluation": (
        "ErrorSeries",
        "ErrorSummary",
        "error_series",
        "summarize",
        "format_table",
    ),
    "hvo_graph.pipeline": ("make_estimator", "estimate"),
}


def _lazy_exports(
    package: str, exports: dict[str, tuple[str, ...]]
) -> tuple[list[str], Callable[[str], Any], Callable[[], list[str]]]:
    """``__all__``, ``__getattr__`` and ``__dir__`` of a package re-exporting ``exports``.

    Each name is imported from its defining module on first access (PEP 562) and
    then stored on the package, so that later lookups are plain attribute reads.
    (Also used by the subpackages ``geometry``, ``estimators`` and ``io``.)
    """
    lazy = {name: module for module, names in exports.items() for name in names}

    def __getattr__(name: str) -> Any:
        module = lazy.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *lazy})

    return list(lazy), __getattr__, __dir__


_names, __getattr__, __dir__ = _lazy_exports(__name__, _EXPORTS)
__all__ = ["__version__", *_names]
