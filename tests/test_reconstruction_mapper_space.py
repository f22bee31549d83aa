"""A reconstruction study searches only the options its mapper reads. Which options a mapper reads is asked of
pycolmap: a parameter is inert for a mapper when changing it leaves that mapper's pycolmap options unchanged."""
from __future__ import annotations

import dataclasses

import pytest

pytest.importorskip("pycolmap")

MAPPER_PARAMS = ("min_inliers", "min_model_size", "max_num_models", "init_min_num_inliers",
                 "abs_pose_min_num_inliers", "abs_pose_max_error", "filter_max_reproj_error",
                 "global_max_rotation_error", "global_max_angular_error")


def _plain(x):
    """pycolmap's ``todict()`` with its numpy arrays as lists (comparable with ==)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    return x.tolist() if hasattr(x, "tolist") else x


def _reads(mapper: str) -> set[str]:
    """The MapperConfig fields whose change (doubled, plus one) changes ``mapper``'s pycolmap options."""
    from pipeline.config import MapperConfig, PipelineConfig
    from pipeline.tasks.reconstruction import ReconstructionTask, _mapper_options
    rc = ReconstructionTask(mapper=mapper).rc
    base = _plain(_mapper_options(mapper, PipelineConfig(), rc, 1).todict())
    out = set()
    for p in MAPPER_PARAMS:
        v = getattr(MapperConfig(), p)
        changed = PipelineConfig(mapper=dataclasses.replace(MapperConfig(), **{p: type(v)(v * 2 + 1)}))
        if _plain(_mapper_options(mapper, changed, rc, 1).todict()) != base:
            out.add(p)
    return out


@pytest.mark.parametrize("mapper", ["incremental", "global"])
def test_a_study_searches_what_its_mapper_reads(mapper):
    from pipeline.config import PipelineConfig
    from pipeline.tasks.reconstruction import ReconstructionTask
    from tuner.protocol import searchable
    from tuner.space import SPACES_DIR, load_space
    task = ReconstructionTask(mapper=mapper)
    reads = _reads(mapper)
    assert reads and reads < set(MAPPER_PARAMS)  # each mapper ignores some of them
    used = set(searchable(task, PipelineConfig())) & set(MAPPER_PARAMS)
    assert used == reads, (mapper, sorted(used ^ reads))
    space = load_space(SPACES_DIR / task.space_file, feature="sift", estimator="degensac")
    searched = set(space.params) & set(MAPPER_PARAMS)
    assert searched and searched <= reads, (task.space_file, sorted(searched - reads))
