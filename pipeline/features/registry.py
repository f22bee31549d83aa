"""The feature-extractor registry. Family modules register into it on import of ``pipeline.features``.

    from pipeline.features import EXTRACTORS
    EXTRACTORS.names()          # ['sift', 'rootsift', 'orb', ...]
    EXTRACTORS.availability()   # {name: (available, reason)}
"""
from pipeline.registry import Registry

EXTRACTORS = Registry("feature")
