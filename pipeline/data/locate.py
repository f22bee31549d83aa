"""Where the data lives: one rule for every command, and what to do when there is none.

    from pipeline.data.locate import locate, resolve_data
    loc = locate()                 # Located(path=.../strecha, rule='download location', detail='$IMTUNE_DATA_HOME')
    root = resolve_data("--data value or None", download=True)   # the main job: fetch the default set if missing

The data folder (a data set: its scenes are sub-folders) is the first of:

1. ``--data DIR`` (the ``cli_value`` argument);
2. the environment variable ``IMTUNE_DATA``;
3. the ``data:`` key of ``imtune.yaml`` (current directory, then the project root; relative to that file);
4. the default set (``strecha``) in the download location: ``$IMTUNE_DATA_HOME``, else the platform's user data
   folder + ``imtune/data`` (platformdirs when installed; else ``$XDG_DATA_HOME/imtune/data``, default
   ``~/.local/share/imtune/data``) — where ``tune data download`` writes;
5. the default set in ``../shared/data`` beside the project (``$IMTUNE_SHARED/data`` when that is set): the copy
   used in development and CI.

Rules 1-3 name a folder explicitly: if it does not exist that is an error naming the rule, never a silent fall
through to another data set. Rules 4-5 are looked at only when 1-3 say nothing, and count only when the folder
holds something (an empty folder left by an old, interrupted download is skipped).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import NamedTuple

import yaml

from pipeline.data.download import ENV_DATA_HOME, download_home  # noqa: F401 (ENV_DATA_HOME: re-exported)
from pipeline.errors import ImtuneError

ENV_DATA = "IMTUNE_DATA"
ENV_SHARED = "IMTUNE_SHARED"
CONFIG_FILE = "imtune.yaml"
DEFAULT_SET = "strecha"
PROJECT_ROOT = Path(__file__).resolve().parents[2]

#: rule names, in precedence order (what `tune data scenes` prints after "found by").
RULES = ("--data", ENV_DATA, CONFIG_FILE, "download location", "../shared/data")


class Located(NamedTuple):
    """A data folder and why it was chosen: ``rule`` is one of RULES; ``detail`` says more (the imtune.yaml file,
    which variable set the download location, ...)."""
    path: Path
    rule: str
    detail: str = ""

    def describe(self) -> str:
        return f"{self.rule} ({self.detail})" if self.detail else self.rule


class DataNotFound(ImtuneError):
    """No data folder by any rule (the message names where it looked and the command that fixes it)."""


def shared_data_root() -> Path:
    """``../shared/data`` beside the project, or ``$IMTUNE_SHARED/data``."""
    shared = os.environ.get(ENV_SHARED)
    return (Path(shared).expanduser() if shared else PROJECT_ROOT.parent / "shared").resolve() / "data"


def project_config() -> tuple[dict, Path | None]:
    """The first ``imtune.yaml`` found (cwd, then project root), parsed (:func:`pipeline.fileio.load_yaml`), and its
    path."""
    for p in (Path.cwd() / CONFIG_FILE, PROJECT_ROOT / CONFIG_FILE):
        if os.path.lexists(p):  # a folder (or a broken link) there is named, not skipped for the next rule
            from pipeline.fileio import load_yaml, read_text
            text = read_text(p, "project configuration")
            try:
                d = load_yaml(text, str(p)) or {}  # a key given twice is one line, not the last one silently
            except yaml.YAMLError as e:
                raise ImtuneError(f"{p}: invalid YAML ({str(e).splitlines()[0]})") from None
            if not isinstance(d, dict):
                raise ImtuneError(f"{p}: expected a mapping at top level")
            # a misspelt key or an empty / non-text data: was skipped for the next rule (another data folder), unsaid
            unknown = [k for k in d if k != "data"]
            if unknown:
                raise ImtuneError(f"{p}: unknown key {unknown[0]!r} (expected data: the data folder)")
            if "data" in d and not (isinstance(d["data"], str) and d["data"].strip()):
                raise ImtuneError(f"{p}: data must be the path of the data folder, got {d['data']!r}")
            return d, p
    return {}, None


def _explicit(cli_value: str | os.PathLike | None) -> Located | None:
    """Rules 1-3: the folder the user named, or None when nobody named one."""
    if cli_value:
        return Located(Path(cli_value).expanduser().resolve(), "--data")
    if os.environ.get(ENV_DATA):
        return Located(Path(os.environ[ENV_DATA]).expanduser().resolve(), ENV_DATA)
    conf, where = project_config()
    if conf.get("data") and where is not None:  # where: the config file the value came from
        p = Path(str(conf["data"])).expanduser()
        if not p.is_absolute():
            p = where.parent / p
        return Located(p.resolve(), CONFIG_FILE, str(where))
    return None


def _usable(p: Path) -> bool:
    try:
        return p.is_dir() and any(p.iterdir())
    except OSError:
        return False


def fallback_roots() -> list[Located]:
    """Rules 4-5 as (root folder, rule, detail), whether or not they exist."""
    home, why = download_home()
    return [Located(home, "download location", why), Located(shared_data_root(), "../shared/data",
                                                              f"${ENV_SHARED}/data" if os.environ.get(ENV_SHARED)
                                                              else "beside the project")]


def locate(cli_value: str | os.PathLike | None = None, name: str = DEFAULT_SET) -> Located:
    """The data folder by the rules of this module, and the rule that chose it.

    ``name`` is the data set looked for in the download location and ../shared/data (default ``strecha``).
    Raises ImtuneError (one line) when a named folder does not exist, DataNotFound when no rule finds one."""
    exp = _explicit(cli_value)
    if exp is not None:
        if not exp.path.is_dir():
            where = f" in {exp.detail}" if exp.detail else ""
            what = "is a file, not a folder" if exp.path.exists() else "does not exist"
            raise ImtuneError(f"data folder {exp.path} (from {exp.rule}{where}) {what}")
        return exp
    roots = fallback_roots()
    for r in roots:
        if _usable(r.path / name):
            return Located(r.path / name, r.rule, r.detail)
    raise DataNotFound(f"no data: {not_found_text(name, roots)}, and no --data, ${ENV_DATA} or {CONFIG_FILE} "
                       f"names a folder; {fix_hint(name)}")


def not_found_text(name: str = DEFAULT_SET, roots: list[Located] | None = None) -> str:
    """'strecha is not in A (download location) or B (../shared/data)' — for messages."""
    roots = roots if roots is not None else fallback_roots()
    where = " or ".join(f"{r.path / name} ({r.rule})" for r in roots)
    return f"{name} is not in {where}"


def fix_hint(name: str = DEFAULT_SET) -> str:
    return f"run `tune data download {name}` (needs a network), or pass --data DIR"


def resolve_data(cli_value: str | os.PathLike | None = None, *, download: bool = False,
                 quiet: bool = False, name: str = DEFAULT_SET) -> Path:
    """The data folder (see :func:`locate`). With ``download`` (the main job), when no rule finds one, data set
    ``name`` is downloaded into the download location (once the first file arrives, a line on stderr says so)
    and that folder returned; if the download fails (no network), one ImtuneError line says what is missing and
    the command to run, and nothing is left behind."""
    try:
        return locate(cli_value, name).path
    except DataNotFound:
        if not download:
            raise
    from pipeline.data.download import describe_source
    from pipeline.data.download import download as fetch
    home, _ = download_home()

    def announce() -> None:
        print(f"tune: no data found; downloading the default data set {name} ({describe_source(name)}) into "
              f"{home / name}", file=sys.stderr, flush=True)
    try:
        return fetch(name, home, quiet=quiet, on_connected=announce)
    except ImtuneError as err:
        raise DataNotFound(f"no data: {not_found_text(name)}, and downloading it failed ({err}); "
                           f"{fix_hint(name)}") from None
