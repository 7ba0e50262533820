"""The ``constrained`` command: ``main`` (parser, exit statuses) and one module per verb family."""
