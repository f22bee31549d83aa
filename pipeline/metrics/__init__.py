"""Metrics: pose errors and mAA (``pose``)."""
# one name a line: ruff's import sorter takes its indent from this file's first indented line, the 35-column one
from pipeline.metrics.pose import (
    accuracy_curve,
    mean_average_accuracy,
    pose_error_deg,
    rotation_error_deg,
    translation_error_deg,
)

__all__ = ["accuracy_curve", "mean_average_accuracy", "pose_error_deg", "rotation_error_deg",
           "translation_error_deg"]
