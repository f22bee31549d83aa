"""imtune's matching pipeline: pure, cacheable stages (data, features, matching, geometry, tasks, metrics).

Nothing in here imports Optuna or ``tuner``. A stage takes a plain, hashable config and returns arrays.

    from pipeline import load_scene, PipelineConfig, evaluate_stereo
"""
from pipeline.config import FeatureConfig, GeometryConfig, MatchConfig, PipelineConfig
from pipeline.errors import ImtuneError

__all__ = ["ImtuneError", "FeatureConfig", "MatchConfig", "GeometryConfig", "PipelineConfig",
           "load_scene", "evaluate_stereo"]


def __getattr__(name):  # lazy: keep `import pipeline` cheap (no cv2/torch at import time)
    if name == "load_scene":
        from pipeline.data import load_scene
        return load_scene
    if name == "evaluate_stereo":
        from pipeline.tasks.stereo import evaluate_stereo
        return evaluate_stereo
    raise AttributeError(name)
