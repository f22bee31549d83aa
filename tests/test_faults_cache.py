"""Fault suite, cache half (issue 14): every corruption mode of a cache entry is detected, warned about in one
line naming the entry, and recomputed, so the run's numbers equal the clean run's; concurrent evaluations from
two real processes on one cache folder give identical records; a read-only or full cache folder is a one-line
error (exit 2) and a full disk leaves no partial temp file.

Real processes (`python -m tuner evaluate`), the real pipeline on 4 real Strecha images (6 pairs, 1024 SIFT
features, seeded DEGENSAC, so runs are reproducible), real files damaged the way disks and people damage them.
"""
from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.cache import FORMAT, H5Cache
from tests.conftest import ROOT, copy_strecha_subset

IMAGES = ["0003.jpg", "0004.jpg", "0005.jpg", "0006.jpg"]
ARGS = ["--feature", "sift", "--num-features", "1024", "--ratio", "0.85", "--ransac", "degensac",
        "--threshold", "0.75", "--max-iters", "5000", "--seed", "0", "--scenes", "fountain-P11"]


def tune_cmd(data: Path, cache: Path) -> list[str]:
    return [sys.executable, "-m", "tuner", "evaluate", *ARGS, "--data", str(data), "--cache", str(cache),
            "--json", "--pairs", "--quiet"]


def env_for(tmp: Path) -> dict:
    e = dict(os.environ)
    e["IMTUNE_GT"] = str(tmp / "no-gt")  # never read a ground truth built elsewhere
    e.pop("IMTUNE_CACHE", None)
    return e


def run(data: Path, cache: Path, tmp: Path) -> subprocess.CompletedProcess:
    return subprocess.run(tune_cmd(data, cache), capture_output=True, text=True, cwd=ROOT, env=env_for(tmp),
                          timeout=600)


def records(out: dict) -> list[dict]:
    """Pair records without the wall times (which differ run to run)."""
    return [{k: v for k, v in r.items() if not k.endswith("seconds")} for r in out["stereo"]["pair_records"]]


def entries(cache: Path, stage: str) -> list[Path]:
    return sorted((cache / stage).rglob("*.h5"))


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """The data subset, a clean cache and the clean run's output."""
    tmp = tmp_path_factory.mktemp("faults-cache")
    data = copy_strecha_subset(tmp / "data", IMAGES)
    cache = tmp / "clean-cache"
    r = run(data, cache, tmp)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["stereo"]["pairs"] == 6
    assert out["stereo"]["mAA10"] > 0.5  # the images are good: a damaged entry would show
    assert len(entries(cache, "features")) == 4 and len(entries(cache, "knn")) == 6
    return {"tmp": tmp, "data": data, "cache": cache, "out": out}


def _overwrite_middle(p: Path) -> None:
    b = bytearray(p.read_bytes())
    mid = len(b) // 2
    b[mid:mid + 256] = bytes(x ^ 0xFF for x in b[mid:mid + 256])  # every byte changed, length kept
    p.write_bytes(bytes(b))


def _truncate(p: Path) -> None:
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])


def _zero_length(p: Path) -> None:
    p.write_bytes(b"")


def _not_h5(p: Path) -> None:
    p.write_text("this is not an h5 file\n")


def _old_format(p: Path) -> None:
    """An entry as the previous format wrote it: valid arrays and checksum, but no key inside."""
    import h5py

    from pipeline.fileio import arrays_checksum
    with h5py.File(p, "r") as f:
        arrays = {k: f[k][()] for k in f.keys()}
    p.unlink()
    with h5py.File(p, "w") as f:
        for k, v in arrays.items():
            f.create_dataset(k, data=v)
        f.attrs["sha1"] = arrays_checksum(arrays)


MODES = {"truncated": _truncate, "overwritten": _overwrite_middle, "zero-length": _zero_length,
         "not-h5": _not_h5, "old-format": _old_format}


def _assert_repaired(cache: Path, clean_cache: Path, damaged: list[Path]) -> None:
    """Each damaged entry was rewritten: valid again (a fresh reader trusts it) and equal to the clean one."""
    fresh, ref = H5Cache(cache), H5Cache(clean_cache)
    for p in damaged:
        stage, key = p.relative_to(cache).parts[0], p.stem
        got, want = fresh.get(stage, key), ref.get(stage, key)
        assert got is not None and want is not None, p
        assert set(got) == set(want)
        for k in want:
            if k != "seconds":
                np.testing.assert_array_equal(got[k], want[k])
    assert fresh.stats["corrupt"] == 0


@pytest.mark.parametrize("mode", list(MODES))
def test_damaged_entry_is_detected_and_recomputed(clean, tmp_path, mode):
    cache = tmp_path / "cache"
    shutil.copytree(clean["cache"], cache)
    damaged = [entries(cache, "features")[1], entries(cache, "knn")[2]]
    before = [p.read_bytes() for p in damaged]
    for p in damaged:
        MODES[mode](p)
    assert [p.read_bytes() for p in damaged] != before
    r = run(clean["data"], cache, tmp_path)
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    if mode == "old-format":  # stale, not corrupt: one line for the folder, naming the first entry met
        assert sum("old-format cache entries" in ln for ln in r.stderr.splitlines()) == 1, r.stderr
    else:
        for p in damaged:
            lines = [ln for ln in r.stderr.splitlines() if str(p) in ln]
            assert len(lines) == 1 and "recomputing" in lines[0], r.stderr
    out = json.loads(r.stdout)
    assert out["stereo"]["mAA10"] == clean["out"]["stereo"]["mAA10"]
    assert out["stereo"]["mAA5"] == clean["out"]["stereo"]["mAA5"]
    assert records(out) == records(clean["out"])
    _assert_repaired(cache, clean["cache"], damaged)


@pytest.mark.parametrize("stage", ["features", "knn"])
def test_swapped_valid_entries_are_not_trusted(clean, tmp_path, stage):
    """Two valid entries swapped on disk (each file intact, checksum good): the key inside each disagrees
    with its name, so both are recomputed. Trusted, they would pair one image's keypoints with another's."""
    cache = tmp_path / "cache"
    shutil.copytree(clean["cache"], cache)
    a, b = entries(cache, stage)[0], entries(cache, stage)[1]
    da, db = a.read_bytes(), b.read_bytes()
    import h5py
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:  # really two valid, different entries
        assert fa.attrs["format"] == FORMAT and fa.attrs["key"] == a.stem and fb.attrs["key"] == b.stem
        assert fa["keypoints" if stage == "features" else "idx12"][()].tobytes() != \
            fb["keypoints" if stage == "features" else "idx12"][()].tobytes()
    a.write_bytes(db)
    b.write_bytes(da)
    r = run(clean["data"], cache, tmp_path)
    assert r.returncode == 0, r.stderr
    for p in (a, b):
        lines = [ln for ln in r.stderr.splitlines() if str(p) in ln]
        assert len(lines) == 1 and "not this key" in lines[0], r.stderr
    out = json.loads(r.stdout)
    assert out["stereo"]["mAA10"] == clean["out"]["stereo"]["mAA10"]
    assert records(out) == records(clean["out"])
    _assert_repaired(cache, clean["cache"], [a, b])


def test_concurrent_evaluations_on_one_cache(clean, tmp_path):
    """Two real processes start together on one empty cache folder: both compute and write the same entries
    (atomic renames), neither sees a partial entry, both give the clean run's records; so does a third run that
    reads what they left."""
    cache = tmp_path / "shared-cache"
    procs = [subprocess.Popen(tune_cmd(clean["data"], cache), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, cwd=ROOT, env=env_for(tmp_path)) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (_so, se) in zip(procs, outs):
        assert p.returncode == 0, se
        assert "recomputing" not in se and "Traceback" not in se, se
    recs = [records(json.loads(so)) for so, _ in outs]
    assert recs[0] == recs[1] == records(clean["out"])
    assert not list(cache.rglob("*.tmp"))  # no temp file left behind
    assert len(entries(cache, "features")) == 4 and len(entries(cache, "knn")) == 6
    r = run(clean["data"], cache, tmp_path)
    assert r.returncode == 0 and "recomputing" not in r.stderr, r.stderr
    assert records(json.loads(r.stdout)) == records(clean["out"])


# ----------------------------------------------------------------------------- cache folder faults

def _can_mount() -> str | None:
    if os.geteuid() != 0 or not shutil.which("unshare"):
        return "needs root and unshare(1) to mount a private tmpfs"
    r = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"], capture_output=True)
    return None if r.returncode == 0 else f"cannot mount a tmpfs in a private namespace: {r.stderr.decode().strip()}"


def _in_private_tmpfs(clean, mnt: Path, cache: Path, opts: str) -> subprocess.CompletedProcess:
    """Run `tune evaluate` with a tmpfs (mount options ``opts``) at ``mnt``, in a private mount namespace (the
    mount vanishes with the process); after it, list any file left on that filesystem on stdout."""
    cmd = " ".join(f"'{a}'" for a in tune_cmd(clean["data"], cache))
    script = (f"mount -t tmpfs -o {opts} tmpfs '{mnt}' || exit 99; {cmd} >/dev/null; rc=$?; "
              f"echo LEFT; find '{mnt}' -type f; exit $rc")
    return subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, cwd=ROOT,
                          env=env_for(clean["tmp"]), timeout=600)


def _one_line(r) -> str:
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr
    return lines[0]


def test_full_disk_is_one_line_and_leaves_no_temp_file(clean, tmp_path):
    why = _can_mount()
    if why:
        pytest.skip(why)
    mnt = tmp_path / "small"
    mnt.mkdir()
    # 200 KiB: the cache folder is created, then the first feature entry (~0.6 MB) fills the disk mid-write
    r = _in_private_tmpfs(clean, mnt, mnt / "cache", "size=200k")
    assert r.returncode == 2, r.stderr
    line = _one_line(r)
    assert str(mnt / "cache") in line and "full" in line and "--cache" in line and "IMTUNE_CACHE" in line
    left = r.stdout.split("LEFT", 1)[1].split()
    assert left == [], f"files left on the full disk: {left}"


def test_read_only_cache_folder_is_one_line(clean, tmp_path):
    if os.geteuid() == 0:  # root writes through permission bits: a read-only file system is the real thing
        why = _can_mount()
        if why:
            pytest.skip(why)
        mnt = tmp_path / "ro"
        mnt.mkdir()
        r = _in_private_tmpfs(clean, mnt, mnt, "ro,size=64k")
        folder = mnt
    else:
        folder = tmp_path / "ro"
        folder.mkdir()
        folder.chmod(0o555)
        r = run(clean["data"], folder, tmp_path)
    assert r.returncode == 2, r.stderr
    line = _one_line(r)
    assert str(folder) in line and "not writable" in line and "--cache" in line


@pytest.mark.parametrize("stage", ["features", "knn"])
def test_an_entry_that_is_a_folder(clean, tmp_path, stage):
    """A folder where an entry's file goes (a copy gone wrong, a hand-made folder) was warned "recomputing it", then
    the run failed with "cache folder ... cannot be written (...: Is a directory)", naming the whole cache. An empty
    folder is now removed and the entry recomputed (the clean run's numbers); one holding files is never deleted:
    one line naming the entry and what to do."""
    cache = tmp_path / "cache"
    shutil.copytree(clean["cache"], cache)
    p = entries(cache, stage)[1]
    p.unlink()
    p.mkdir()
    r = run(clean["data"], cache, tmp_path)
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if str(p) in ln]
    assert len(lines) == 1 and "a folder, not a file" in lines[0] and "recomputing" in lines[0], r.stderr
    out = json.loads(r.stdout)
    assert records(out) == records(clean["out"])
    _assert_repaired(cache, clean["cache"], [p])

    p.unlink()
    (p / "keep").mkdir(parents=True)
    (p / "keep" / "note.txt").write_text("mine")
    r = run(clean["data"], cache, tmp_path)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"tune: error: cache entry {p} ({stage}) is a folder with files"), \
        r.stderr
    assert "move it away" in lines[0]
    assert (p / "keep" / "note.txt").read_text() == "mine"


def test_a_fifo_at_an_entrys_name_is_named_not_waited_on(clean, tmp_path):
    """A FIFO where an entry's file goes: reading the entry blocked until a writer came, the run hung without a
    word. Now one line naming the entry and what to do; the FIFO is left alone."""
    cache = tmp_path / "cache"
    shutil.copytree(clean["cache"], cache)
    p = entries(cache, "features")[0]
    p.unlink()
    os.mkfifo(p)
    r = subprocess.run(tune_cmd(clean["data"], cache), capture_output=True, text=True, cwd=ROOT, env=env_for(tmp_path),
                       timeout=120)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"tune: error: cache entry {p} (features) is a FIFO, not a file"), \
        r.stderr
    assert "move it away" in lines[0] and stat.S_ISFIFO(os.lstat(p).st_mode)


@pytest.mark.parametrize("where", ["stage", "shard"])
def test_a_file_inside_the_cache_in_a_folders_place_is_named(clean, tmp_path, where):
    """A file where one of the cache's own folders goes (``knn`` or ``knn/d9``) said "cache folder CACHE is not a
    folder (a file is in the way: Not a directory)" of a cache that is a folder: the file in the way went unnamed.
    Now the line names it and what to do; it is left alone."""
    cache = tmp_path / "cache"
    shutil.copytree(clean["cache"], cache)
    blocker = cache / "knn" if where == "stage" else entries(cache, "knn")[0].parent
    shutil.rmtree(blocker)
    blocker.write_text("mine")
    r = run(clean["data"], cache, tmp_path)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"tune: error: cache folder {cache}: {blocker} is a file where a "
                                                   "folder of the cache should be: move it away"), r.stderr
    assert blocker.read_text() == "mine"
