"""The documented Python hook: a new extractor registered in a few lines works from Python and, through
IMTUNE_PLUGINS, from the CLI (`tune list`, `tune evaluate`)."""
from __future__ import annotations

import json
import shutil
import textwrap

import pytest

from pipeline.errors import ImtuneError
from tests.conftest import DATA
from tests.test_cli_evaluate import tune

PLUGIN = textwrap.dedent('''
    import cv2
    import numpy as np
    from pipeline.features import EXTRACTORS, Extractor, Features

    @EXTRACTORS.register("plugin-sift", "SIFT from a plug-in (docs/extending.md example)")
    class PluginSIFT(Extractor):
        version = "1"

        def extract(self, image):
            kps, desc = cv2.SIFT_create(self.conf.num_features).detectAndCompute(image, None)
            kps, desc = kps[: self.conf.num_features], desc[: self.conf.num_features]
            score = np.array([k.response for k in kps], np.float32)
            order = np.argsort(-score, kind="stable")
            xy = np.array([k.pt for k in kps], np.float32)
            return Features(keypoints=xy[order], descriptors=desc[order].astype(np.float32), scores=score[order])
''')


def test_plugin_file_registers_and_runs(tmp_path):
    src = DATA / "strecha" / "fountain-P11"
    if not src.exists():
        pytest.skip(f"real data not found at {src}")
    plugin = tmp_path / "my_plugin.py"
    plugin.write_text(PLUGIN)
    env = {"IMTUNE_PLUGINS": str(plugin), "IMTUNE_CACHE": str(tmp_path / "cache")}
    r = tune("list", "--json", env=env)
    assert r.returncode == 0, r.stderr
    assert any(row["name"] == "plugin-sift" and row["available"] == "yes" for row in json.loads(r.stdout))
    data = tmp_path / "data" / "fountain-P11"
    for sub, suffix in (("images", ""), ("gt_dense_cameras", ".camera")):
        (data / sub).mkdir(parents=True)
        for n in ("0004.jpg", "0005.jpg", "0006.jpg"):
            shutil.copy(src / sub / (n + suffix), data / sub / (n + suffix))
    r = tune("evaluate", "--feature", "plugin-sift", "--num-features", "2048", "--ratio", "0.85",
             "--max-iters", "5000", "--data", str(tmp_path / "data"), "--json", "--quiet", env=env)
    assert r.returncode == 0, r.stderr
    st = json.loads(r.stdout)["stereo"]
    assert st["pairs"] == 3 and st["mAA10"] > 0.6


def test_plugin_errors_are_one_line(tmp_path):
    from pipeline.features import load_plugins
    with pytest.raises(ImtuneError, match="not found"):
        load_plugins(str(tmp_path / "missing.py"))
    bad = tmp_path / "bad.py"
    bad.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(ImtuneError, match="boom") as e:
        load_plugins(str(bad))
    assert "\n" not in str(e.value)
    with pytest.raises(ImtuneError, match="no_such_module"):
        load_plugins("no_such_module_xyz")
    r = tune("list", env={"IMTUNE_PLUGINS": "no_such_module_xyz"})
    assert r.returncode != 0 and len(r.stderr.strip().splitlines()) == 1 and "no_such_module_xyz" in r.stderr


@pytest.mark.parametrize("code", [0, 3])
def test_plugin_calling_sys_exit_is_one_line_not_a_silent_end(code, tmp_path):
    """A plug-in that exits while importing ended `tune list` with its exit code and no word (0: a success)."""
    p = tmp_path / "exits.py"
    p.write_text(f"import sys\nsys.exit({code})\n")
    r = tune("list", env={"IMTUNE_PLUGINS": str(p)})
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1, (r.returncode, r.stderr)
    assert str(p) in lines[0] and f"sys.exit({code})" in lines[0] and "Traceback" not in r.stderr


def test_plugin_module_named_from_its_folder_with_the_tune_command(tmp_path):
    """docs/extending.md: `IMTUNE_PLUGINS=mylab.features tune ...` with mylab/features.py in the current folder.
    The `tune` console script (unlike `python -m tuner`) does not have the current folder on sys.path, so it
    failed: "plug-in 'mylab.features' failed to import: ModuleNotFoundError: No module named 'mylab'"."""
    import re
    import subprocess
    import sys
    from pathlib import Path
    doc = (Path(__file__).resolve().parents[1] / "docs" / "extending.md").read_text()
    code = re.search(r"```python\n(# mylab/features.py\n.*?)```", doc, re.S)
    assert code, "docs/extending.md lost its 'Register a new extractor' example"
    (tmp_path / "mylab").mkdir()
    (tmp_path / "mylab" / "features.py").write_text(code.group(1))
    script = Path(sys.executable).parent / "tune"
    if not script.is_file():
        pytest.skip(f"no `tune` console script beside {sys.executable}")
    env = {k: v for k, v in __import__("os").environ.items() if k != "PYTHONPATH"}
    env["IMTUNE_PLUGINS"] = "mylab.features"
    r = subprocess.run([str(script), "list", "--json"], capture_output=True, text=True, cwd=tmp_path, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert any(row["name"] == "my-feature" for row in json.loads(r.stdout))
    # a research folder may hold a `pipeline/` of its own: the current folder is on sys.path for the plug-in's import
    # only, so the spawned pair workers still import imtune's pipeline (not a namespace package of that folder)
    (tmp_path / "pipeline" / "geometry").mkdir(parents=True)
    (tmp_path / "pipeline" / "geometry" / "mylib_backend.py").write_text("raise ImportError('not this one')\n")
    src = DATA / "strecha" / "fountain-P11"
    if not src.exists():
        pytest.skip(f"real data not found at {src}")
    data = tmp_path / "data" / "fountain-P11"
    for sub, suffix in (("images", ""), ("gt_dense_cameras", ".camera")):
        (data / sub).mkdir(parents=True)
        for n in ("0004.jpg", "0005.jpg", "0006.jpg"):
            shutil.copy(src / sub / (n + suffix), data / sub / (n + suffix))
    env["IMTUNE_CACHE"] = str(tmp_path / "cache")
    r = subprocess.run([str(script), "evaluate", "--num-features", "1024", "--max-iters", "2000", "--jobs", "2",
                        "--data", str(tmp_path / "data"), "--json", "--quiet"], capture_output=True, text=True,
                       cwd=tmp_path, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["stereo"]["pairs"] == 3
