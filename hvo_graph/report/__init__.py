"""Reporting: tables, progress and figures of the experiments. No domain logic.

- :mod:`~hvo_graph.report.tables`: number and CI formatting, Markdown tables, CSV text,
  seeds and software versions of the result pages;
- :mod:`~hvo_graph.report.progress`: a text progress bar;
- :mod:`~hvo_graph.report.plotting`: the shared figure style (one look per method).
"""
