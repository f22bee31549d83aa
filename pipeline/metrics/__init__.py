"""Metrics: pose errors and mAA (``pose``)."""
from pipeline.metrics.pose import (accuracy_curve, mean_average_accuracy, pose_error_deg,
                                   rotation_error_deg, translation_error_deg)

__all__ = ["accuracy_curve", "mean_average_accuracy", "pose_error_deg", "rotation_error_deg",
           "translation_error_deg"]
