"""The `boxjax` command line: `main` (the entry point) and one module per group of commands (`episodes`:
simulate, rotate, demo, evaluate; `box`: box, config; `train`: train-estimator, train-moments, estimator-eval,
calibrate, train-baseline, compare; `reproduce`). `args` holds the option rules (an option the chosen
mode does not use is refused) and `models` the checks that a model fits the given config.

The command modules import the library inside each command, not at the top, so that a command loads only
what it runs (the one place where boxjax imports inside functions: `tests/test_layers.py`)."""

from boxjax.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
