"""The code version recorded by studies, frozen files and test results (a leaf module)."""
from __future__ import annotations

from pathlib import Path


def code_version() -> str:
    """``imtune <version>`` plus the git commit of the checkout when there is one (read from .git)."""
    try:
        from importlib.metadata import version
        v = version("imtune")
    except Exception:  # noqa: BLE001
        v = "0+unknown"
    root = Path(__file__).resolve().parents[1] / ".git"
    try:
        if root.is_file():  # a worktree or submodule: ".git" names the real git folder
            line = root.read_text().strip()
            if line.startswith("gitdir:"):
                root = (root.parent / line.split(":", 1)[1].strip()).resolve()
        head = (root / "HEAD").read_text().strip()
        common = root  # a worktree keeps its HEAD here and the refs in the main git folder ("commondir")
        if (root / "commondir").is_file():
            common = (root / (root / "commondir").read_text().strip()).resolve()
        root = common
        if head.startswith("ref:"):
            ref = head.split(None, 1)[1]
            p = root / ref
            if p.is_file():
                sha = p.read_text().strip()
            else:
                sha = ""
                packed = root / "packed-refs"
                if packed.is_file():
                    for line in packed.read_text().splitlines():
                        if line.endswith(" " + ref):
                            sha = line.split()[0]
        else:
            sha = head
        if sha:
            v += f"+g{sha[:10]}"
    except OSError:
        pass
    return v
