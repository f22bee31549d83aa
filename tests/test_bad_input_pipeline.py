"""Bad input of the pipeline side (issue 14 items 2, 4, 6-cache, 8-covisibility), table-driven through the real CLI:
each case is `python -m tuner ...` in a real process -> exit 2, exactly one line on stderr naming the culprit,
no traceback, no "internal error".

Covered: non-finite or out-of-range numbers in every float option (evaluate, run, calibrate), in search-space
bounds and --fix values, in configuration files (YAML and JSON, nested and flat); integer configuration values
out of range; JPEGs that libjpeg reports as corrupt (middle overwritten with the end marker intact, zeros or
random bytes; truncated with an end marker appended) or truncated, built from a real Strecha image; a cache folder that is a file (--cache or
IMTUNE_CACHE) or lies under one.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT, copy_strecha_subset

IMAGES = ["0004.jpg", "0005.jpg"]
FAST = ["--num-features", "1024", "--max-iters", "2000", "--quiet"]


def _tiny_data(tmp: Path) -> Path:
    return copy_strecha_subset(tmp / "data", IMAGES)


def _damage(kind: str):
    """A setup that copies 2 real images and damages the second one; the culprit is that file."""
    def setup(tmp: Path):
        from pipeline.data.imagefile import jpeg_end
        data = _tiny_data(tmp)
        p = data / "fountain-P11" / "images" / IMAGES[1]
        b = bytearray(p.read_bytes())
        n = len(b)
        if kind == "truncated":
            b = b[: n // 2]
        elif kind == "truncated-eoi":  # cut, then an end marker appended: the marker walk is satisfied
            b = b[: n // 2] + b"\xff\xd9"
            assert jpeg_end(bytes(b)) is not None
        else:
            fill = bytes(8192) if kind == "zeros" else \
                np.random.default_rng(0).integers(0, 0xFF, 8192, dtype=np.uint8).tobytes()  # no 0xFF: no marker
            b[n // 2: n // 2 + 8192] = fill
            # the end marker is intact and the marker walk passes: only libjpeg's decode can tell
            assert jpeg_end(bytes(b)) is not None
            import cv2
            assert cv2.imdecode(np.frombuffer(bytes(b), np.uint8), cv2.IMREAD_GRAYSCALE) is not None
        p.write_bytes(bytes(b))
        return ["evaluate", "--data", str(data), *FAST, "--cache", str(tmp / "cache")], {}, str(p)
    return setup


def _float_tiff(tmp: Path):
    """The second image saved as a 32-bit float TIFF (a valid file libjpeg / libpng never see): it was "unreadable or
    corrupt image" after OpenCV's own WARN line, two lines blaming the file."""
    import cv2
    data = _tiny_data(tmp)
    scene = data / "fountain-P11"
    p = scene / "images" / IMAGES[1]
    tif = p.with_suffix(".tiff")
    assert cv2.imwrite(str(tif), cv2.imread(str(p)).astype(np.float32) / 255)
    p.unlink()
    (scene / "gt_dense_cameras" / f"{IMAGES[1]}.camera").rename(scene / "gt_dense_cameras" / f"{tif.name}.camera")
    return ["evaluate", "--data", str(data), *FAST, "--cache", str(tmp / "cache")], {}, f"image {tif} holds float32 samples"


def _keep_models_file(tmp: Path):
    """--keep-models naming a file: every bag failed ("NotADirectoryError" in its record), mAA 0, exit 0."""
    (tmp / "a-file").write_text("x")
    return (["evaluate", "--data", str(_tiny_data(tmp)), *FAST, "--cache", str(tmp / "cache"), "--task", "multiview",
             "--keep-models", str(tmp / "a-file")], {}, f"--keep-models folder {tmp / 'a-file'} is not a folder")


def _zero_baseline(kind: str):
    """A ground-truth pair whose cameras share one centre (a camera file copied to another image; a pairs-list line
    with zero translation): its pair error was the angle of rounding noise (80 deg) or inf, counted in mAA, exit 0."""
    def setup(tmp: Path):
        data = _tiny_data(tmp)
        scene = data / "fountain-P11"
        if kind == "strecha":
            import shutil
            shutil.copy(scene / "images" / IMAGES[0], scene / "images" / "0009.jpg")
            shutil.copy(scene / "gt_dense_cameras" / f"{IMAGES[1]}.camera", scene / "gt_dense_cameras" / "0009.jpg.camera")
            needle = f"pair {IMAGES[1]}|0009.jpg has no baseline"
        else:
            K = "1000 0 768 0 1000 512 0 0 1"
            (scene / "pairs_with_gt.txt").write_text(f"{IMAGES[0]} {IMAGES[1]} 0 0 {K} {K} 1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1\n")
            import shutil
            shutil.rmtree(scene / "gt_dense_cameras")
            needle = f"pair {IMAGES[0]}|{IMAGES[1]} has no baseline"
        return ["evaluate", "--data", str(data), *FAST, "--cache", str(tmp / "cache")], {}, needle
    return setup


def _evaluate(*args, needle):
    def setup(tmp: Path):
        return ["evaluate", "--data", str(_tiny_data(tmp)), *FAST, "--cache", str(tmp / "cache"), *args], {}, needle
    return setup


def _parse(*args, needle):  # rejected while parsing the command line: no data needed
    def setup(tmp: Path):
        return list(args), {}, needle
    return setup


def _study(cmd: str, *args, needle):
    def setup(tmp: Path):
        return [cmd, "--data", str(_tiny_data(tmp)), "--storage", f"sqlite:///{tmp / 'optuna.db'}",
                "--studies-dir", str(tmp / "studies"), "--cache", str(tmp / "cache"), "--num-features", "1024",
                "--n-trials", "1", "--quiet", *args], {}, needle
    return setup


def _space(text: str, needle: str):
    def setup(tmp: Path):
        f = tmp / "space.yaml"
        f.write_text(text)
        argv, env, _ = _study("run", "--space", str(f), needle=needle)(tmp)
        return argv, env, needle
    return setup


def _strategy_beside_a_searching_space(tmp: Path):
    """--strategy uni with a --space that searches the strategy: the study searched it, uni ignored, unsaid."""
    f = tmp / "space.yaml"
    f.write_text("params:\n  ratio: {low: 0.6, high: 1.0}\n  strategy: {type: categorical, choices: [both, either]}\n")
    needle = f"--strategy uni does not apply: the search space {f} searches the strategy (both, either)"
    return _study("run", "--space", str(f), "--strategy", "uni", needle=needle)(tmp)


def _config(name: str, text: str, needle: str):
    def setup(tmp: Path):
        f = tmp / name
        f.write_text(text)
        return ["viz", "--config", str(f), "--data", str(_tiny_data(tmp)), "--cache", str(tmp / "cache"),
                "--out", str(tmp / "viz"), "--quiet"], {}, needle
    return setup


def _cache_file(how: str):
    def setup(tmp: Path):
        f = tmp / "not-a-folder"
        f.write_text("a file where the cache folder should be\n")
        data = _tiny_data(tmp)
        base = ["evaluate", "--data", str(data), *FAST]
        if how == "env":
            return base, {"IMTUNE_CACHE": str(f)}, str(f)
        target = f if how == "file" else f / "sub"
        return [*base, "--cache", str(target)], {}, str(target)
    return setup


CASES = {
    # item 2: every float option rejects nan / inf (and its own invalid range)
    "threshold-nan": _parse("evaluate", "--threshold", "nan", needle="--threshold"),
    "threshold-inf": _parse("evaluate", "--threshold", "inf", needle="--threshold"),
    "threshold-minus-inf": _parse("evaluate", "--threshold=-inf", needle="--threshold"),
    "threshold-zero": _parse("evaluate", "--threshold", "0", needle="--threshold"),
    "threshold-word": _parse("evaluate", "--threshold", "abc", needle="--threshold"),
    "ratio-nan": _parse("evaluate", "--ratio", "nan", needle="--ratio"),
    "ratio-zero": _parse("evaluate", "--ratio", "0", needle="--ratio"),
    "ratio-above-one": _parse("evaluate", "--ratio", "1.5", needle="--ratio"),
    "confidence-nan": _parse("evaluate", "--confidence", "nan", needle="--confidence"),
    "confidence-one": _parse("evaluate", "--confidence", "1", needle="--confidence"),
    "distance-threshold-inf": _parse("evaluate", "--distance-threshold", "inf", needle="--distance-threshold"),
    "distance-threshold-negative": _parse("evaluate", "--distance-threshold=-1", needle="--distance-threshold"),
    "mr-size-nan": _parse("evaluate", "--mr-size", "nan", needle="--mr-size"),
    # item 8: co-visibility is a fraction
    "covisibility-negative": _parse("evaluate", "--covisibility=-1", needle="--covisibility"),
    "covisibility-two": _parse("evaluate", "--covisibility", "2", needle="--covisibility"),
    "covisibility-nan": _parse("evaluate", "--covisibility", "nan", needle="--covisibility"),
    "covisibility-inf": _parse("evaluate", "--covisibility", "inf", needle="--covisibility"),
    "run-budget-inf": _parse("run", "--budget", "inf", needle="--budget"),
    "run-budget-nan": _parse("run", "--budget", "nan", needle="--budget"),
    "run-test-budget-inf": _parse("run", "--test-budget", "inf", needle="--test-budget"),
    "run-timeout-nan": _parse("run", "--timeout", "nan", needle="--timeout"),
    "run-covisibility-two": _parse("run", "--covisibility", "2", needle="--covisibility"),
    "calibrate-threshold-nan": _parse("calibrate", "--calibration-threshold", "nan", needle="--calibration-threshold"),
    "calibrate-ratio-inf": _parse("calibrate", "--calibration-ratio", "inf", needle="--calibration-ratio"),
    "calibrate-budget-nan": _parse("calibrate", "--budget", "nan", needle="--budget"),
    # seeds feed numpy's generators, which take no negative seed ("internal error" before); counts are >= 0
    "evaluate-seed-negative": _parse("evaluate", "--seed=-1", needle="--seed"),
    "run-seed-negative": _parse("run", "--seed=-3", needle="--seed"),
    "bag-seed-negative": _parse("evaluate", "--bag-seed=-1", needle="--bag-seed"),
    "viz-sample-seed-negative": _parse("viz", "--sample-seed=-1", needle="--sample-seed"),
    "viz-max-lines-negative": _parse("viz", "--max-lines=-1", needle="--max-lines"),
    "viz-worst-negative": _parse("viz", "--worst=-2", needle="--worst"),
    "max-side-negative": _parse("evaluate", "--max-side=-3", needle="--max-side"),
    "bag-min-points-negative": _parse("evaluate", "--bag-min-points=-1", needle="--bag-min-points"),
    # item 2: integer values out of range reach the config dataclasses
    "max-iters-zero": _evaluate("--max-iters", "0", needle="max-iters"),
    "num-features-zero": _evaluate("--num-features", "0", needle="num_features"),
    # item 2: search-space bounds and pinned values
    "space-low-nan": _space("params:\n  threshold: {low: .nan, high: 1.0}\n", "threshold"),
    "space-high-inf": _space("params:\n  threshold: {low: 0.1, high: .inf}\n", "threshold"),
    "space-ratio-high-nan": _space("params:\n  ratio: {low: 0.7, high: .nan}\n", "ratio"),
    "fix-threshold-nan": _study("run", "--fix", "threshold=nan", needle="threshold"),
    "fix-ratio-inf": _study("run", "--fix", "ratio=inf", needle="ratio"),
    # item 2: configuration files
    "config-yaml-threshold-nan": _config("c.yaml", "feature: {name: sift, num_features: 1024}\nmatching: {ratio: 0.8}\n"
                                                   "geometry: {ransac: degensac, threshold: .nan}\n", "threshold"),
    "config-json-threshold-infinity": _config("c.json", '{"feature": {"name": "sift"}, '
                                                        '"geometry": {"threshold": Infinity}}', "threshold"),
    "config-flat-ratio-nan": _config("flat.yaml", "ratio: .nan\nthreshold: 1.0\n", "ratio"),
    "config-confidence-inf": _config("conf.yaml", "geometry: {ransac: degensac, confidence: .inf}\n", "confidence"),
    # item 4: JPEGs that libjpeg reports as corrupt
    "jpeg-middle-zeros": _damage("zeros"),
    "jpeg-middle-random": _damage("random"),
    "jpeg-truncated": _damage("truncated"),
    "jpeg-truncated-end-marker-appended": _damage("truncated-eoi"),
    "float-tiff": _float_tiff,
    # a pre-filter option given twice: the last one was used, unsaid
    "prefilter-option-twice": _evaluate("--prefilter", "gms:threshold=1,threshold=2",
                                        needle="option threshold is given twice"),
    # pre-filter options out of range: an internal error inside kornia, or every match kept / dropped unsaid
    "prefilter-adalam-ransac-iters-0": _evaluate("--prefilter", "adalam:ransac_iters=0",
                                                 needle="prefilter 'adalam': option ransac_iters must be > 0"),
    "prefilter-adalam-scale-rate-0": _evaluate("--prefilter", "adalam:scale_rate_threshold=0",
                                               needle="option scale_rate_threshold must be > 0"),
    "prefilter-adalam-threads-negative": _evaluate("--prefilter", "adalam:threads=-3",
                                                   needle="option threads must be >= 0"),
    # records for the JSON without --json: ignored, unsaid
    "evaluate-pairs-without-json": _evaluate("--pairs", needle="--pairs adds records to the JSON output only: add --json"),
    "evaluate-bag-records-without-json": _evaluate("--bag-records", needle="--bag-records adds records to the JSON"),
    "keep-models-is-a-file": _keep_models_file,
    "ci-resamples-with-ci-none": _evaluate("--ci", "none", "--ci-resamples", "5000",
                                           needle="--ci-resamples 5000 does not apply with --ci none"),
    # a bag size given twice: the last count was used, unsaid
    "bags-size-twice": _evaluate("--task", "multiview", "--bags", "3:2,3:1", needle="size 3 is given twice"),
    # bags of 2 images: COLMAP's mapper keeps no model of two, every bag a recorded failure (SR 0, mAA 0), unsaid
    "bags-of-two-images": _evaluate("--task", "multiview", "--bags", "2:1", needle="bag size must be >= 3, got 2"),
    # an extractor option given twice: the last one was used, unsaid
    "feature-option-twice": _evaluate("--feature-option", "edge_threshold=10", "--feature-option", "edge_threshold=12",
                                      needle="--feature-option edge_threshold is given twice (edge_threshold=10 and "
                                             "edge_threshold=12)"),
    # random trials before a model, for a sampler that has no model: ignored, unsaid
    "startup-trials-with-random-sampler": _study("run", "--sampler", "random", "--startup-trials", "5",
                                                 needle="--startup-trials 5 applies to the tpe and cmaes samplers"),
    # --strategy where the study searches or pins the strategy: ignored, unsaid
    "strategy-beside-a-searching-space": _strategy_beside_a_searching_space,
    "strategy-beside-fix-strategy": _study("run", "--fix", "strategy=either", "--strategy", "uni",
                                           needle="--strategy uni does not apply: the strategy is pinned to either"),
    # a multiview option without the multiview task: ignored, the stereo task run, unsaid
    "evaluate-bags-on-stereo": _evaluate("--bags", "5:10", needle="--bags is an option of the multiview task, and only "
                                         "the stereo task runs here (--task stereo): add --task multiview"),
    "evaluate-mv-intrinsics-on-stereo": _evaluate("--task", "stereo", "--mv-intrinsics", "fixed",
                                                  needle="--mv-intrinsics is an option of the multiview task"),
    "run-workers-on-stereo": _study("run", "--workers", "2", needle="--workers is an option of the multiview task"),
    "prefilter-gms-threshold-0": _evaluate("--prefilter", "gms:threshold=0",
                                           needle="prefilter 'gms': option threshold must be > 0"),
    # a ground-truth pair without baseline: its error was rounding noise or inf, counted in mAA, unsaid
    "strecha-cameras-share-a-centre": _zero_baseline("strecha"),
    "pairs-list-zero-translation": _zero_baseline("pairs"),
    # item 6 (cache half): the cache folder is a file, or lies under one
    "cache-is-a-file": _cache_file("file"),
    "cache-under-a-file": _cache_file("under"),
    "imtune-cache-is-a-file": _cache_file("env"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_exit_2(case, tmp_path):
    argv, env, needle = CASES[case](tmp_path)
    e = dict(os.environ)
    e["IMTUNE_GT"] = str(tmp_path / "no-gt")
    e.pop("IMTUNE_CACHE", None)
    e.update(env)
    r = subprocess.run([sys.executable, "-m", "tuner", *argv], capture_output=True, text=True, cwd=ROOT, env=e,
                       timeout=300)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.stderr and "internal error" not in r.stderr, r.stderr
    assert needle in lines[0], lines[0]
    assert lines[0].startswith("tune: error: "), lines[0]

