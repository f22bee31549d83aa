"""imtune's Optuna layer and CLI. Everything the CLI does is a Python call first:

    from tuner import evaluate_config, resolve_data
"""
from tuner.options import resolve_data, build_config, evaluate_config  # noqa: F401
