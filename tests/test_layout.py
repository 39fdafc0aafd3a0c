"""The package's layout: old import paths that the docs promised still resolve."""

from __future__ import annotations

import importlib

import pytest

import hvo_graph

#: Old path -> {name: new module}, one or more names per moved module.
MOVED = {
    "hvo_graph.tracking": {
        "TrackerConfig": "hvo_graph.frontend.tracking",
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
