"""The estimator registry: name -> Estimator subclass (``tune list`` reads its availability)."""
from __future__ import annotations

from pipeline.registry import Registry

ESTIMATORS = Registry("estimator")
