"""``tune export``: a study's frozen settings in the form another tool takes.

Formats: ``json`` (always); ``opencv`` (cv2.findFundamentalMat / findEssentialMat call, cv-* estimators);
``poselib`` (RansacOptions dict, poselib / poselib-e); ``colmap`` (COLMAP .ini options) and ``pycolmap``
(pycolmap.RANSACOptions) for colmap / colmap-e; ``hloc`` (a match_features 'NN-ratio' conf: the ratio test).
Thresholds are in pixels of the images as imtune fed them to the estimator (``config.feature.max_side``: the
longer side resized to it); each output carries the study's validation and test figures as comments.
A format the study's estimator cannot be expressed in: ImtuneError (one line).
"""
from __future__ import annotations

import json
from pathlib import Path

from pipeline.errors import ImtuneError

FORMATS = ("colmap", "pycolmap", "opencv", "poselib", "hloc", "json")
# estimator -> (cv2 function, method flag); E estimators (model "E") take the calibration K
OPENCV = {"cv-ransac": ("findFundamentalMat", "FM_RANSAC"), "cv-usac": ("findFundamentalMat", "USAC_DEFAULT"),
          "cv-magsac": ("findFundamentalMat", "USAC_MAGSAC"), "cv-accurate": ("findFundamentalMat", "USAC_ACCURATE"),
          "cv-lmeds": ("findFundamentalMat", "FM_LMEDS"), "cv-8pt": ("findFundamentalMat", "FM_8POINT"),
          "cv-e-ransac": ("findEssentialMat", "RANSAC"), "cv-e-magsac": ("findEssentialMat", "USAC_MAGSAC")}
POSELIB = {"poselib": "estimate_fundamental", "poselib-e": "estimate_relative_pose"}
COLMAP = ("colmap", "colmap-e")
FIGURES = ("mAA5", "mAA10", "auc5", "auc10", "auc20", "NI")


def settings(frozen: dict) -> dict:
    """The exported values of a frozen study: estimator, ratio, strategy, threshold (px), confidence, max_iters."""
    conf = frozen.get("config") or {}
    g, m = conf.get("geometry") or {}, conf.get("matching") or {}
    out = {"estimator": g.get("ransac", frozen.get("ransac")), "ratio": m.get("ratio"), "strategy": m.get("strategy"),
           "threshold": g.get("threshold"), "confidence": g.get("confidence"), "max_iters": g.get("max_iters"),
           "max_side": (conf.get("feature") or {}).get("max_side")}
    if "min_confidence" in m:  # a learned matcher (to_dict keeps its fields only then): no ratio test
        out.update(matcher=m.get("method"), min_confidence=m.get("min_confidence"),
                   matcher_options=dict(m.get("matcher_options") or ()), ratio=None, strategy=None,
                   feature=(conf.get("feature") or {}).get("name"))
    return out


def figures_line(frozen: dict, test: dict | None) -> str:
    """'validation mAA10 0.725, ...; test mAA10 ... (3 runs)': the study's figures, for a comment."""
    def part(d: dict) -> str:
        return ", ".join(f"{k} {float(d[k]):.4f}" for k in FIGURES if isinstance(d.get(k), (int, float)))
    obj = (frozen.get("objective") or {}).get("name", "mAA10")
    out = f"study {frozen.get('study')} (maximised {obj}), trial #{frozen.get('trial')}: validation " \
          f"{part(frozen.get('validation') or {}) or 'n/a'}"
    mean = (test or {}).get("mean")
    return out + (f"; test {part(mean)}" if mean else "; not tested")


def export(frozen: dict, fmt: str, test: dict | None = None) -> str:
    """The text of ``fmt`` for a frozen study (``tuner.freeze.load_frozen``) and its test.json (or None)."""
    if fmt not in FORMATS:
        raise ImtuneError(f"unknown export format {fmt!r} (choose from {', '.join(FORMATS)})")
    s = settings(frozen)
    est, note = s["estimator"], figures_line(frozen, test)
    px = f"threshold in px of images resized to max side {s['max_side']}" if s["max_side"] else "threshold in px"
    if fmt == "json":
        return json.dumps({"study": frozen.get("study"), "objective": (frozen.get("objective") or {}).get("name", "mAA10"),
                           "settings": s, "validation": frozen.get("validation"),
                           "test": (test or {}).get("mean")}, indent=2)
    if fmt == "hloc" and s.get("matcher") == "lightglue":  # hloc's match_features conf of LightGlue
        model = {"name": "lightglue", "features": s["feature"], "filter_threshold": s["min_confidence"],
                 **s["matcher_options"]}
        return (f"# {note}\n# hloc.match_features conf: LightGlue at the tuned confidence threshold\n"
                f"conf = {{'output': 'matches-{s['feature']}-lightglue', 'model': {model!r}}}\n")
    if fmt == "hloc":
        if s["ratio"] is None:
            raise ImtuneError(f"study {frozen.get('study')}: no ratio test in its frozen settings; --format hloc "
                              "exports the ratio test only")
        mutual = s["strategy"] == "both"
        return (f"# {note}\n# hloc.match_features conf ('NN-ratio'): ratio test at the tuned ratio, mutual check for "
                f"strategy both (this study: {s['strategy']})\n"
                f"conf = {{'output': 'matches-NN-{'mutual-' if mutual else ''}ratio{s['ratio']:.3f}', "
                f"'model': {{'name': 'nearest_neighbor', 'do_mutual_check': {mutual}, "
                f"'ratio_threshold': {s['ratio']!r}}}}}\n")
    if fmt == "opencv":
        if est not in OPENCV:
            raise ImtuneError(f"--format opencv: the study's estimator {est} is not OpenCV's (cv-*); "
                              f"choose {_formats_for(est)}")
        fn, flag = OPENCV[est]
        if fn == "findEssentialMat":  # as pipeline/geometry/opencv_backend.py calls it: two cameras K1, K2
            call = ("import numpy as np\n"
                    "n1 = cv2.undistortPoints(pts1.reshape(-1, 1, 2).astype(np.float64), K1, None).reshape(-1, 2)\n"
                    "n2 = cv2.undistortPoints(pts2.reshape(-1, 1, 2).astype(np.float64), K2, None).reshape(-1, 2)\n"
                    "f = (K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1]) / 4  # the px threshold / mean focal length\n"
                    f"E, mask = cv2.findEssentialMat(n1, n2, np.eye(3), method=cv2.{flag}, prob={s['confidence']!r}, "
                    f"threshold={s['threshold']!r} / f, maxIters={int(s['max_iters'])})\n"
                    "_, R, t, _ = cv2.recoverPose(E[:3], n1, n2, np.eye(3), mask=mask)")
        else:
            call = (f"F, mask = cv2.findFundamentalMat(pts1, pts2, cv2.{flag}, {s['threshold']!r}, "
                    f"{s['confidence']!r}, {int(s['max_iters'])})")
        return f"# {note}\n# {est}: {px}\nimport cv2\n{call}\n"
    if fmt == "poselib":
        if est not in POSELIB:
            raise ImtuneError(f"--format poselib: the study's estimator {est} is not PoseLib's (poselib, poselib-e); "
                              f"choose {_formats_for(est)}")
        opt = {"max_epipolar_error": s["threshold"], "success_prob": s["confidence"],
               "max_iterations": int(s["max_iters"]), "min_iterations": min(1000, int(s["max_iters"]))}
        call = ("F, info = poselib.estimate_fundamental(pts1, pts2, ransac_opt, {})" if est == "poselib" else
                "# camera1, camera2: {'model': 'PINHOLE', 'width': w, 'height': h, 'params': [fx, fy, cx, cy]}\n"
                "pose, info = poselib.estimate_relative_pose(pts1, pts2, camera1, camera2, ransac_opt, {})")
        return f"# {note}\n# {est}: {px}\nimport poselib\nransac_opt = {opt!r}\n{call}\n"
    if est not in COLMAP:
        raise ImtuneError(f"--format {fmt}: the study's estimator {est} is not COLMAP's (colmap, colmap-e); "
                          f"choose {_formats_for(est)}")
    iters = int(s["max_iters"])
    if fmt == "colmap":
        lines = [f"# {note}", f"# {est}: {px}; COLMAP >= 3.10 option names (older: [SiftMatching] max_error, ...)",
                 "[TwoViewGeometry]", f"max_error={s['threshold']!r}", f"confidence={s['confidence']!r}",
                 f"max_num_trials={iters}"]
        # COLMAP's option manager has no TwoViewGeometry.min_num_trials (checked against its source): the .ini keeps
        # the library's 1000, which imtune also used unless Gamma was below it
        if iters < 1000:
            lines.insert(2, f"# min_num_trials (1000 in COLMAP, not an .ini option) was {iters} in the study")
        if s["ratio"] is not None:
            lines += ["[SiftMatching]", f"max_ratio={s['ratio']!r}", f"cross_check={int(s['strategy'] == 'both')}"]
        return "\n".join(lines) + "\n"
    return (f"# {note}\n# {est}: {px}\nimport pycolmap\nopts = pycolmap.RANSACOptions()\n"
            f"opts.max_error = {s['threshold']!r}\nopts.confidence = {s['confidence']!r}\n"
            f"opts.max_num_trials = {iters}\nopts.min_num_trials = {min(1000, iters)}\n"
            + ("res = pycolmap.estimate_fundamental_matrix(pts1, pts2, opts)\n" if est == "colmap" else
               "# camera1, camera2: pycolmap.Camera(model='PINHOLE', width=w, height=h, params=[fx, fy, cx, cy])\n"
               "res = pycolmap.estimate_essential_matrix(pts1, pts2, camera1, camera2, opts)\n"))


def _formats_for(est: str) -> str:
    ok = ["json", "hloc"] + (["opencv"] if est in OPENCV else []) + (["poselib"] if est in POSELIB else []) \
        + (["colmap", "pycolmap"] if est in COLMAP else [])
    return " or ".join(ok)


def export_study(studies_dir: Path | str, name: str, fmt: str) -> str:
    """:func:`export` of study ``name``'s frozen.yaml (and test.json, when there) in ``studies_dir``."""
    from tuner.freeze import load_frozen, load_test_file, study_dir
    frozen = load_frozen(studies_dir, name)
    test, why = load_test_file(study_dir(studies_dir, name) / "test.json", name)
    out = export(frozen, fmt, test)
    return out if why is None else f"# test.json not read: {why}\n" + out
