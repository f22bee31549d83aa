"""Configurations named on the command line: a study (its frozen settings), a frozen.yaml, a configuration
file or an IMC benchmark method JSON (``pipeline.config_files``) — what `tune compare`, `tune viz --compare` and
`tune evaluate --config` take.

    from tuner.sources import resolve_source
    src = resolve_source("sift-8000-degensac-stereo", studies_dir)   # Source(conf, label, study, frozen, path)
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from pipeline.config import PipelineConfig
from pipeline.errors import ImtuneError


@dataclass
class Source:
    """A configuration to evaluate or draw: the config, its label, and the study it comes from (if any)."""
    conf: PipelineConfig
    label: str
    study: str | None = None
    frozen: dict | None = None
    path: Path | None = None


def studies_dir(value: str | None = None) -> Path:
    from tuner.storage import default_studies_dir
    return Path(value).expanduser().resolve() if value else default_studies_dir()


def load_config_source(path: str | Path, base: PipelineConfig | None = None) -> Source:
    """A configuration file (``pipeline.config_files.load_config_file``) as a Source."""
    from pipeline.config_files import load_config_file
    cf = load_config_file(path, base)
    if cf.frozen is not None:  # a frozen.yaml: its numbers are checked as when a study's is loaded
        from tuner.freeze import check_frozen
        check_frozen(cf.frozen, cf.path)
    check_prefilter(cf.conf, str(cf.path))
    return Source(cf.conf, cf.label, frozen=cf.frozen, path=cf.path)


def check_prefilter(conf: PipelineConfig, where: str) -> None:
    """The configuration's pre-filter accepts its options: built once here (cheap), so that a wrong option name in
    a file is one line naming the file now, not a line without it at the first pair."""
    m = conf.matching
    if not m.prefilter or m.prefilter == "none":
        return
    from pipeline.matching.prefilters import get_prefilter
    try:
        get_prefilter(m.prefilter, m.prefilter_options)
    except ImtuneError as e:
        raise ImtuneError(f"{where}: {e}") from None


def load_study_source(name: str, sdir: Path) -> Source:
    """The frozen settings of a study (``<sdir>/<study>/frozen.yaml``); one-line ImtuneError without them."""
    from pipeline.config_files import config_label, pipeline_from_dict
    from tuner.freeze import load_frozen
    frozen = load_frozen(sdir, name)
    conf = pipeline_from_dict(frozen["config"], where=f"study {name} frozen.yaml")
    trial = frozen.get("trial")
    return Source(conf, f"{name}" + (f" (trial #{trial})" if trial is not None else "") +
                  f": {config_label(conf, frozen.get('task'))}",
                  study=name, frozen=frozen)


def resolve_source(spec: str, sdir: Path) -> Source:
    """A config file path, else a study name (with frozen settings in ``sdir``)."""
    p = Path(spec).expanduser()
    if p.is_file():
        return load_config_source(p)
    if p.suffix.lower() in (".yaml", ".yml", ".json") or "/" in spec:
        if p.exists():  # a folder, a device, a FIFO: the reader says which, and never reads it
            return load_config_source(p)
        raise ImtuneError(f"config file {p} does not exist")
    from tuner.freeze import study_dir
    if not (study_dir(sdir, spec) / "frozen.yaml").exists():  # a folder there: load_frozen says so
        raise ImtuneError(f"{spec!r} is neither a config file nor a study with frozen settings "
                          f"({study_dir(sdir, spec) / 'frozen.yaml'} does not exist)")
    return load_study_source(spec, sdir)
