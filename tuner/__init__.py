"""imtune's Optuna layer and CLI. Everything the CLI does is a Python call first:

    from tuner import TuneSettings, tune, evaluate_config, resolve_data, build_config
    from tuner import freeze, run_test, load_space
"""
from tuner.evaluate import evaluate_config, load_scenes  # noqa: F401
from tuner.options import build_config, resolve_data  # noqa: F401

_LAZY = {"tune": "tuner.study", "TuneSettings": "tuner.study", "freeze": "tuner.freeze",
         "run_test": "tuner.freeze", "load_space": "tuner.space"}


def __getattr__(name):  # lazy: `tune list` / `tune evaluate` do not pay for importing Optuna
    if name in _LAZY:
        import importlib
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(name)
