"""hvo_graph: homography-based visual odometry fused in a GTSAM factor graph.

The main names of every layer are available from the package itself
(``hvo_graph.simulate``, ``hvo_graph.FactorGraphSmoother``, ...). They are
imported on first use (PEP 562 module ``__getattr__``), so ``import hvo_graph``
stays light: GTSAM, OpenCV and matplotlib load only when something that needs
them is used. The full API, layer by layer, is in docs/api.md.

Modules that moved keep their old import path for one release
(``hvo_graph.simulation`` and others, :data:`_MOVED`): a name read from an old
path comes from its new module, with a DeprecationWarning naming that module.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from collections.abc import Callable, Sequence
from types import ModuleType
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
    "hvo_graph.sim.render": ("render_plane_images",),
    "hvo_graph.frontend.tracking": (
        "TrackerConfig",
        "FeatureTracker",
        "track_images",
        "tracks_from_images",
    ),
    "hvo_graph.frontend.measure": ("FrontEndConfig", "MeasurementFrontEnd", "measure_sequence"),
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
    "hvo_graph.sim.scenario": (
        "ScenarioConfig",
        "Scenario",
        "paper_scenario",
        "simulate",
        "write_scenario",
    ),
    "hvo_graph.eval.metrics": (
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
            if f"{package}.{name}" in _MOVED:  # e.g. hvo_graph.simulation without an import
                return importlib.import_module(f"{package}.{name}")
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *lazy})

    return list(lazy), __getattr__, __dir__


#: Old module path -> the modules its names moved to (searched in order). Kept for one
#: release; docs/api.md lists the moves.
_MOVED: dict[str, tuple[str, ...]] = {
    "hvo_graph.tracking": (
        "hvo_graph.frontend.tracking",
        "hvo_graph.frontend.tracker_config",
        "hvo_graph.io.images",
    ),
    "hvo_graph.simulation": ("hvo_graph.sim.scenario",),
    "hvo_graph.render": ("hvo_graph.sim.render",),
    "hvo_graph.evaluation": ("hvo_graph.eval.metrics",),
    "hvo_graph.stats": ("hvo_graph.eval.stats",),
    "hvo_graph.experiment": (  # constants resolve from the first module that has them
        "hvo_graph.estimators.registry",
        "hvo_graph.eval.metrics",
        "hvo_graph.report.tables",
        "hvo_graph.report.progress",
        "hvo_graph.montecarlo",
    ),
    "hvo_graph.plotting": ("hvo_graph.report.plotting",),
}


def _defined_names(module: ModuleType) -> set[str]:
    """Public names a module defines itself (not the ones it imports)."""
    return {
        name
        for name, value in vars(module).items()
        if not name.startswith("_")
        and not isinstance(value, ModuleType)
        and getattr(value, "__module__", module.__name__) == module.__name__
    }


class _MovedModule(ModuleType):
    """An old module path: each public name resolves from the module it moved to."""

    def __init__(self, name: str, targets: Sequence[str]) -> None:
        super().__init__(name, f"Moved: import from {', '.join(targets)}.")
        self.__targets = tuple(targets)

    def __getattr__(self, name: str) -> Any:
        modules = [importlib.import_module(target) for target in self.__targets]
        # The module that defines the name first, else one that imports it.
        home = next((m for m in modules if name in _defined_names(m)), None)
        home = home or next(
            (m for m in modules if not name.startswith("_") and name in vars(m)), None
        )
        if home is None:
            raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")
        warnings.warn(
            f"{self.__name__}.{name} moved to {home.__name__}.{name}; the old path "
            "will be removed in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(home, name)

    def __dir__(self) -> list[str]:
        modules = [importlib.import_module(target) for target in self.__targets]
        return sorted(set().union(*(_defined_names(m) for m in modules)))


class _MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Makes ``import hvo_graph.<old path>`` give a :class:`_MovedModule`."""

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        return importlib.util.spec_from_loader(fullname, self) if fullname in _MOVED else None

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        return _MovedModule(spec.name, _MOVED[spec.name])

    def exec_module(self, module: ModuleType) -> None:
        """Nothing to run: the names resolve on first access."""


if not any(isinstance(finder, _MovedFinder) for finder in sys.meta_path):
    sys.meta_path.append(_MovedFinder())

_names, __getattr__, __dir__ = _lazy_exports(__name__, _EXPORTS)
__all__ = ["__version__", *_names]
