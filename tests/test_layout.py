"""The package's layout: floors that import only downwards, module sizes, and the old
import paths that the docs promised still resolving."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import hvo_graph

#: Old path -> {name: new module}, one or more names per moved module.
MOVED = {
    "hvo_graph.tracking": {
        "TrackerConfig": "hvo_graph.frontend.tracker_config",
        "track_images": "hvo_graph.frontend.tracking",
        "tracks_from_images": "hvo_graph.frontend.tracking",
        "load_image_sequence": "hvo_graph.io.images",
        "IMAGE_EXTENSIONS": "hvo_graph.io.images",
    },
    "hvo_graph.simulation": {
        "paper_scenario": "hvo_graph.sim.scenario",
        "simulate": "hvo_graph.sim.scenario",
        "ScenarioConfig": "hvo_graph.sim.scenario",
        "PAPER_NOISE_VAR": "hvo_graph.sim.scenario",
    },
    "hvo_graph.render": {
        "render_plane_images": "hvo_graph.sim.render",
        "make_texture": "hvo_graph.sim.render",
    },
    "hvo_graph.evaluation": {
        "error_series": "hvo_graph.eval.metrics",
        "summarize": "hvo_graph.eval.metrics",
        "format_table": "hvo_graph.eval.metrics",
        "ErrorSummary": "hvo_graph.eval.metrics",
    },
    "hvo_graph.stats": {
        "mean_ci": "hvo_graph.eval.stats",
        "t_quantile": "hvo_graph.eval.stats",
        "MeanCI": "hvo_graph.eval.stats",
    },
    "hvo_graph.experiment": {
        "METHOD_LABELS": "hvo_graph.estimators.registry",
        "METHOD_TITLES": "hvo_graph.estimators.registry",
        "check_methods": "hvo_graph.estimators.registry",
        "QUANTITIES": "hvo_graph.eval.metrics",
        "run_seed": "hvo_graph.montecarlo",
        "run_seeds": "hvo_graph.montecarlo",
        "make_method": "hvo_graph.montecarlo",
        "SeedResult": "hvo_graph.montecarlo",
        "method_statistics": "hvo_graph.montecarlo",
        "ProgressBar": "hvo_graph.report.progress",
        "markdown_table": "hvo_graph.report.tables",
        "format_ci": "hvo_graph.report.tables",
        "write_text_atomic": "hvo_graph.report.tables",
    },
    "hvo_graph.plotting": {
        "METHOD_STYLE": "hvo_graph.report.plotting",
        "method_style": "hvo_graph.report.plotting",
        "save_figure": "hvo_graph.report.plotting",
        "FIGURE_DPI": "hvo_graph.report.plotting",
    },
}


@pytest.mark.parametrize("old", sorted(MOVED))
def test_old_import_paths_resolve_with_a_deprecation_warning(old: str) -> None:
    assert set(hvo_graph._MOVED) == set(MOVED)
    module = importlib.import_module(old)
    for name, new in MOVED[old].items():
        with pytest.warns(DeprecationWarning, match=rf"{old}\.{name} moved to {new}\.{name}"):
            value = getattr(module, name)
        assert value is getattr(importlib.import_module(new), name)
        assert name in dir(module)
    with pytest.raises(AttributeError, match="has no attribute 'not_a_name'"):
        module.not_a_name  # noqa: B018
    # also reachable as an attribute of the package, without an import statement
    assert getattr(hvo_graph, old.rsplit(".", 1)[1]) is module


# -- floors ------------------------------------------------------------------------------------

PACKAGE = Path(hvo_graph.__file__).resolve().parent
ROOT = PACKAGE.parent

#: Floors, lowest first: a module imports only from its own floor or lower ones.
FLOORS: tuple[tuple[str, ...], ...] = (
    ("hvo_graph", "hvo_graph.errors", "hvo_graph.types"),
    ("hvo_graph.geometry",),
    ("hvo_graph.io",),
    ("hvo_graph.frontend", "hvo_graph.sim"),
    ("hvo_graph.estimators", "hvo_graph.eval"),
    ("hvo_graph.report",),
    (
        "hvo_graph.montecarlo",
        "hvo_graph.image_runs",
        "hvo_graph.pipeline",
        "hvo_graph.parallel",
        "hvo_graph.batch",
    ),
    ("hvo_graph.arguments", "hvo_graph.cli", "hvo_graph.__main__"),
)

MAX_MODULE_LINES = 500
MAX_IMAGES_SCRIPT_LINES = 450


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def floor(module: str) -> int:
    """The floor of a module of the package: its longest matching prefix in FLOORS."""
    best, depth = None, -1
    for level, prefixes in enumerate(FLOORS):
        for prefix in prefixes:
            matches = module == prefix or module.startswith(prefix + ".")
            if matches and prefix.count(".") > depth:
                best, depth = level, prefix.count(".")
    assert best is not None, f"{module}: on no floor of tests/test_layout.py FLOORS"
    return best


def package_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import of the package in a file, at any depth (functions,
    TYPE_CHECKING blocks) and both forms (``import a.b``, ``from a.b import c``)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            # ``from hvo_graph.eval import stats`` names a submodule: take the deepest path.
            names = [
                f"{node.module}.{alias.name}"
                if (ROOT / f"{node.module}.{alias.name}".replace(".", "/"))
                .with_suffix(".py")
                .exists()
                or (ROOT / f"{node.module}.{alias.name}".replace(".", "/")).is_dir()
                else node.module
                for alias in node.names
            ]
        else:
            continue
        found += [(node.lineno, n) for n in names if n == "hvo_graph" or n.startswith("hvo_graph.")]
    return found


MODULES = sorted(PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=[module_name(p) for p in MODULES])
def test_lower_floors_never_import_higher_ones(path: Path) -> None:
    here = module_name(path)
    wrong = [
        f"{path.relative_to(ROOT)}:{line}: imports {target} (floor {floor(target)} > {floor(here)})"
        for line, target in package_imports(path)
        if floor(target) > floor(here)
    ]
    assert not wrong, "\n".join(wrong)


def test_geometry_imports_only_errors_and_types() -> None:
    for path in (PACKAGE / "geometry").rglob("*.py"):
        for line, target in package_imports(path):
            assert target in ("hvo_graph", "hvo_graph.errors", "hvo_graph.types") or (
                target.startswith("hvo_graph.geometry")
            ), f"{path.relative_to(ROOT)}:{line}: imports {target}"


def test_the_floor_test_sees_imports_inside_functions(tmp_path: Path) -> None:
    source = tmp_path / "probe.py"
    source.write_text("def f():\n    from hvo_graph.cli import main\n    import hvo_graph.io\n")
    assert package_imports(source) == [(2, "hvo_graph.cli"), (3, "hvo_graph.io")]


@pytest.mark.parametrize("path", MODULES, ids=[module_name(p) for p in MODULES])
def test_no_module_is_over_500_lines(path: Path) -> None:
    lines = len(path.read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_MODULE_LINES, f"{path.relative_to(ROOT)}: {lines} lines"


def test_the_images_script_holds_no_library_code() -> None:
    script = ROOT / "experiments" / "images.py"
    lines = len(script.read_text(encoding="utf-8").splitlines())
    assert lines < MAX_IMAGES_SCRIPT_LINES, f"experiments/images.py: {lines} lines"


@pytest.mark.parametrize("name", ["decompose_homography", "select_solution", "HomographySolution"])
def test_decomposition_names_still_resolve_from_discrete(name: str) -> None:
    from hvo_graph.geometry import decomposition, discrete

    with pytest.warns(DeprecationWarning, match=rf"discrete\.{name} moved to .*decomposition"):
        value = getattr(discrete, name)
    assert value is getattr(decomposition, name)
