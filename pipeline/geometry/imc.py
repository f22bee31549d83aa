"""The official IMC benchmark's ``geom`` section (ubc-vision/image-matching-benchmark JSON method
configs) mapped onto imtune estimator names.

    imc_geom_to_config({"method": "cmp-degensac-f", "threshold": 0.5, "confidence": 0.999999,
                        "max_iter": 100000, "error_type": "sampson", "degeneracy_check": True})
    -> {"ransac": "degensac", "threshold": 0.5, "confidence": 0.999999, "max_iters": 100000}

Keys the section does not give are left out (the caller's defaults apply). Methods imtune has no
backend for (cv2-7pt, cv2-usacfast-f, skimage-ransac-f, intel-dfe-f, the LAF-consistency and
essential-matrix variants) give a one-line ``ImtuneError``.
"""
from __future__ import annotations

from pipeline.errors import ImtuneError

IMC_METHODS: dict[str, str] = {
    "cmp-degensac-f": "degensac",  # "pyransac" when "degeneracy_check" is false
    "cmp-magsac-f": "magsac",
    "cmp-gc-ransac-f": "gcransac",
    "cv2-ransac-f": "cv-ransac",
    "cv2-patched-ransac-f": "cv-ransac",
    "cv2-usacdef-f": "cv-usac",
    "cv2-usacmagsac-f": "cv-magsac",
    "cv2-usacaccurate-f": "cv-accurate",
    "cv2-lmeds-f": "cv-lmeds",
    "cv2-8pt": "cv-8pt",
}


def imc_geom_to_config(geom: dict) -> dict:
    """``geom`` section of an IMC method config -> GeometryConfig keyword arguments."""
    if not isinstance(geom, dict) or "method" not in geom:
        raise ImtuneError("IMC geom section must be an object with a 'method' key")
    method = str(geom["method"]).lower()
    if method not in IMC_METHODS:
        raise ImtuneError(f"IMC geom method {method!r} is not supported "
                          f"(supported: {', '.join(sorted(IMC_METHODS))})")
    name = IMC_METHODS[method]
    if method == "cmp-degensac-f":
        if not geom.get("degeneracy_check", True):
            name = "pyransac"
        if str(geom.get("error_type", "sampson")).lower() != "sampson":
            raise ImtuneError(f"IMC geom error_type {geom['error_type']!r} is not supported (only 'sampson')")
    out: dict = {"ransac": name}
    # the values as written: GeometryConfig checks them (a string or nan is one line there; int() / float() here
    # raised a bare ValueError or cut 1000.5 iterations to 1000 silently)
    for key, field in (("threshold", "threshold"), ("confidence", "confidence"), ("max_iter", "max_iters")):
        if key in geom:
            v = geom[key]
            out[field] = float(v) if field != "max_iters" and isinstance(v, int) and not isinstance(v, bool) else v
    return out
