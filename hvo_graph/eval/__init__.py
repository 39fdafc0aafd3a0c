"""Evaluation: errors against ground truth, statistics over seeds, consistency of covariances.

- :mod:`~hvo_graph.eval.metrics`: per-frame errors and their RMSE / max, matched by time;
- :mod:`~hvo_graph.eval.association`, :mod:`~hvo_graph.eval.alignment`,
  :mod:`~hvo_graph.eval.ape_rpe`, :mod:`~hvo_graph.eval.evaluation`: evo's
  association, Umeyama alignment, APE and RPE (what ``hvo-graph evaluate`` runs);
- :mod:`~hvo_graph.eval.stats`: RMSE and Student-t confidence intervals (no SciPy).

Functions of trajectories and records only; the public names are re-exported
here and imported on first use.
"""

from hvo_graph import _lazy_exports

__all__, __getattr__, __dir__ = _lazy_exports(
    __name__,
    {
        "hvo_graph.eval.metrics": (
            "QUANTITIES",
            "Quantity",
            "ErrorSeries",
            "ErrorSummary",
            "error_series",
            "summarize",
            "format_table",
        ),
        "hvo_graph.eval.association": ("associate", "associate_velocity"),
        "hvo_graph.eval.alignment": ("Alignment", "align", "umeyama"),
        "hvo_graph.eval.ape_rpe": ("ape_errors", "rpe_errors", "rpe_pairs", "statistics"),
        "hvo_graph.eval.evaluation": ("Evaluation", "EvaluationOptions", "evaluate_trajectory"),
        "hvo_graph.eval.stats": ("MeanCI", "mean_ci", "rmse", "t_quantile", "normal_quantile"),
    },
)
