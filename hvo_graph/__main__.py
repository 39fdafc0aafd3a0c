"""``python -m hvo_graph``: the same as the ``hvo-graph`` command."""

from hvo_graph.cli import main

if __name__ == "__main__":
    raise SystemExit(main())
