"""optuna-dashboard tells the same story as imtune (tuner.annotate): the metric is named "mAA(10°)", an
over-budget trial carries a note saying so, the frozen trial and the study carry notes. Checked on the
storage, then in a real headless Chromium (Debian chromium + chromedriver via Selenium) against `tune
dashboard` on a free loopback port, with a screenshot; and once on a real tiny `tune` study (2 trials,
4 Strecha images), where `freeze` writes the notes."""
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
import zlib

import pytest

from tests.conftest import ROOT, copy_strecha_subset

CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser") if os.path.exists(p)),
                shutil.which("chromium"))
CHROMEDRIVER = "/usr/bin/chromedriver" if os.path.exists("/usr/bin/chromedriver") else shutil.which("chromedriver")
NEEDS_BROWSER = pytest.mark.skipif(not (CHROMIUM and CHROMEDRIVER), reason=(
    "chromium and chromedriver not installed (Debian packages chromium, chromium-driver; the README's test "
    "command installs them)"))

B = 0.5
# (value = mAA(10), median estimator seconds per pair): trial 1 has the best raw value but is over B
TRIALS = [(0.40, 0.21), (0.71, 0.93), (0.55, 0.44), (0.31, 0.12)]
FROZEN = 2


def _study(storage, name="dash-annotated"):
    """A study shaped like imtune's (the study and trial attributes the objective writes), made with
    Optuna directly: cheap, and with known feasibility."""
    import optuna
    from optuna.distributions import FloatDistribution, IntDistribution
    from optuna.trial import create_trial
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    st = optuna.create_study(study_name=name, storage=storage, direction="maximize")
    for k, v in {"task": "stereo", "feature": "sift", "num_features": 2048, "ransac": "degensac",
                 "budget": {"seconds_per_pair": B, "test_seconds_per_pair": 1.0, "gamma_max": 20000,
                            "statistic": "median estimator seconds per pair"},
                 "data": {"val_scenes": ["fountain-P11"], "pairs": 55}, "imtune": 1}.items():
        st.set_user_attr(k, v)
    dist = {"ratio": FloatDistribution(0.6, 1.0), "threshold": FloatDistribution(0.1, 2.0, log=True),
            "max_iters": IntDistribution(100, 20000, log=True)}
    for i, (value, med) in enumerate(TRIALS):
        st.add_trial(create_trial(
            value=value, params={"ratio": 0.7 + 0.05 * i, "threshold": 0.3 + 0.2 * i, "max_iters": 1000 * (i + 1)},
            distributions=dist, constraints={"budget": med - B},
            user_attrs={"mAA10": value, "mAA5": value / 2, "ransac_seconds_median": med, "feasible": med <= B}))
    return st


def _notes(study):
    import optuna
    from optuna_dashboard import get_note
    return get_note(study), {t.number: get_note(optuna.Trial(study, t._trial_id)) for t in study.trials}


def test_annotate_notes_and_idempotence(tmp_path):
    from tuner.annotate import annotate_study, over_budget_text
    st = _study(f"sqlite:///{tmp_path / 'a.db'}")
    out = annotate_study(st, {"trial": FROZEN})
    assert out["over_budget"] == [1] and out["frozen"] == FROZEN and out["dashboard_best"] == 1
    assert out["best_feasible"] == FROZEN
    assert st.metric_names == ["mAA(10°)"]
    study_note, notes = _notes(st)
    assert notes[1] == "**imtune** · " + over_budget_text(0.93, B)
    assert "over budget: median estimator CPU time 0.93 s > 0.5 s per pair; never frozen" in notes[1]
    assert "**frozen**" in notes[FROZEN] and "0.550" in notes[FROZEN] and "0.44 s <= 0.5 s" in notes[FROZEN]
    assert notes[0] == "" and notes[3] == ""
    assert f"frozen: trial {FROZEN}, mAA(10°) = 0.550" in study_note
    assert "Best Trial ranks by value only and ignores the budget: its trial 1" in study_note
    assert "over budget: 1 of 4 completed trials (trial 1)" in study_note
    # idempotent: the same call writes nothing (no new note versions either)
    before = dict(st._storage.get_study_system_attrs(st._study_id))
    assert annotate_study(st, {"trial": FROZEN})["notes_written"] == 0
    assert dict(st._storage.get_study_system_attrs(st._study_id)) == before
    # a user's own text below imtune's paragraph survives a re-annotation
    import optuna
    from optuna_dashboard import get_note, save_note
    t0 = optuna.Trial(st, st.trials[FROZEN]._trial_id)
    save_note(t0, get_note(t0) + "\n\nmy remark: looks good")
    # another frozen trial (e.g. more trials were run): the old frozen trial's imtune text goes, its user text stays
    annotate_study(st, {"trial": 0})
    study_note, notes = _notes(st)
    assert notes[FROZEN] == "my remark: looks good"
    assert "**frozen**" in notes[0] and "frozen: trial 0," in study_note
    # frozen=None: the best feasible trial is imtune's pick, not called frozen
    annotate_study(st, None)
    study_note, notes = _notes(st)
    assert "not frozen yet" in notes[FROZEN] and notes[FROZEN].endswith("my remark: looks good")
    assert notes[0] == "" and "best feasible (not frozen yet): trial 2" in study_note


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve(storage, studies_dir):
    port = _free_port()
    p = subprocess.Popen([sys.executable, "-m", "tuner", "dashboard", "--storage", storage, "--studies-dir",
                          str(studies_dir), "--port", str(port)], cwd=ROOT, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    deadline = time.time() + 60
    while True:
        try:
            with urllib.request.urlopen(url + "/api/studies", timeout=2) as resp:
                return p, url, json.loads(resp.read())
        except OSError:
            if p.poll() is not None or time.time() > deadline:
                p.kill()
                raise AssertionError(f"dashboard did not start: {p.communicate()[1][-2000:]}") from None
            time.sleep(0.3)


def _png_pixels(path):
    """(width, height, rows of RGB(A) bytes) of a non-interlaced 8-bit PNG, read with zlib (no image
    library in the test extras); raises AssertionError on anything that is not a valid PNG."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", "not a PNG signature"
    pos, idat, ihdr = 8, b"", None
    while pos < len(data):
        n = int.from_bytes(data[pos:pos + 4], "big")
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        crc = int.from_bytes(data[pos + 8 + n:pos + 12 + n], "big")
        assert zlib.crc32(kind + body) == crc, f"bad CRC in chunk {kind!r}"
        if kind == b"IHDR":
            ihdr = body
        elif kind == b"IDAT":
            idat += body
        elif kind == b"IEND":
            break
        pos += 12 + n
    assert ihdr is not None and idat, "PNG without IHDR / IDAT"
    w, h = int.from_bytes(ihdr[0:4], "big"), int.from_bytes(ihdr[4:8], "big")
    depth, ctype, interlace = ihdr[8], ihdr[9], ihdr[12]
    assert depth == 8 and ctype in (2, 6) and interlace == 0, (depth, ctype, interlace)
    bpp = 3 if ctype == 2 else 4
    raw = zlib.decompress(idat)
    stride = w * bpp
    assert len(raw) == h * (stride + 1), "truncated image data"
    rows, prev = [], bytearray(stride)
    for y in range(h):  # undo the PNG row filters (spec section 9)
        f, line = raw[y * (stride + 1)], bytearray(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)])
        for x in range(stride):
            a = line[x - bpp] if x >= bpp else 0
            b, c = prev[x], prev[x - bpp] if x >= bpp else 0
            if f == 1:
                line[x] = (line[x] + a) & 255
            elif f == 2:
                line[x] = (line[x] + b) & 255
            elif f == 3:
                line[x] = (line[x] + (a + b) // 2) & 255
            elif f == 4:
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                line[x] = (line[x] + (a if pa <= pb and pa <= pc else b if pb <= pc else c)) & 255
        rows.append(bytes(line))
        prev = line
    return w, h, bpp, rows


@NEEDS_BROWSER
def test_dashboard_shows_metric_budget_and_frozen(tmp_path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    from tuner.annotate import annotate_study
    storage = f"sqlite:///{tmp_path / 'optuna.db'}"
    st = _study(storage)
    annotate_study(st, {"trial": FROZEN})
    p, url, studies = _serve(storage, tmp_path)
    sid = studies["study_summaries"][0]["study_id"]
    opts = webdriver.ChromeOptions()
    profile = tempfile.mkdtemp(prefix="imtune-chromium-")
    for a in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
              "--disable-background-networking", "--disable-component-update", "--disable-sync",
              "--disable-dev-shm-usage", "--window-size=1400,1000", f"--user-data-dir={profile}"):
        opts.add_argument(a)
    opts.binary_location = CHROMIUM
    drv = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)

    def page(path, *until):
        """The page's text once every string of ``until`` is shown (the SPA renders its frame before the
        study's data arrive: wait for the data, not the frame; a string that never comes fails the test)."""
        drv.get(url + path)
        WebDriverWait(drv, 60).until(lambda d: all(u in d.find_element(By.TAG_NAME, "body").text for u in until))
        return drv.find_element(By.TAG_NAME, "body").text

    try:
        drv.set_page_load_timeout(60)
        # the study page: the history axis and the Best Trial card say mAA(10°), not "Objective 0"
        body = page(f"/dashboard/studies/{sid}", "Best Trial (number=", "mAA(10°)")
        assert "mAA(10°)" in body and "Objective 0" not in body
        assert "Best Trial (number=1)" in body  # the dashboard's own pick ignores the budget ...
        # ... so the over-budget best trial is visibly labelled on its own page
        body = page(f"/dashboard/studies/{sid}/trials?numbers=1", "Trial 1 (trial_id=")
        assert "Best Trial" in body
        assert "over budget: median estimator CPU time 0.93 s > 0.5 s per pair; never frozen" in body
        shot = tmp_path / "dashboard-over-budget-trial.png"
        assert drv.save_screenshot(str(shot))
        assert "feasible False" in body  # the objective's user attribute, shown with the trial
        body = page(f"/dashboard/studies/{sid}/trials?numbers={FROZEN}", f"Trial {FROZEN} (trial_id=")
        assert "frozen: the best feasible trial, mAA(10°) = 0.550" in body
        # the study note tells the whole story
        body = page(f"/dashboard/studies/{sid}/note", "metric: mAA(10°)")
        assert f"frozen: trial {FROZEN}, mAA(10°) = 0.550" in body
        assert "its trial 1 (mAA(10°) = 0.710) is over budget" in body
        assert "budget B = 0.5 s median estimator CPU time per pair" in body
    finally:
        drv.quit()
        shutil.rmtree(profile, ignore_errors=True)
        p.terminate()
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
    w, h, bpp, rows = _png_pixels(shot)
    assert w >= 800 and h >= 600, (w, h)
    colours = {row[x:x + 3] for row in rows[::10] for x in range(0, w * bpp, 10 * bpp)}
    assert len(colours) > 20, f"screenshot looks blank ({len(colours)} distinct colours sampled)"


def test_real_tiny_study_is_annotated_by_freeze(tmp_path_factory):
    """`tune` (2 trials on 4 Strecha images, no test run) freezes, and freezing annotates the study."""
    import optuna
    from optuna_dashboard import get_note
    root = copy_strecha_subset(tmp_path_factory.mktemp("data"), ["0002.jpg", "0003.jpg", "0004.jpg", "0005.jpg"])
    sdir = tmp_path_factory.mktemp("studies")
    env = dict(os.environ, IMTUNE_CACHE=str(tmp_path_factory.mktemp("cache")))
    r = subprocess.run([sys.executable, "-m", "tuner", "--data", str(root), "--feature", "sift", "--num-features",
                        "1024", "--ransac", "degensac", "--scenes", "fountain-P11", "--budget", "1.0",
                        "--calibration-pairs", "4", "--n-trials", "3", "--no-test", "--json", "--studies-dir",
                        str(sdir), "--study", "tiny"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout)
    st = optuna.load_study(study_name="tiny", storage=f"sqlite:///{sdir / 'optuna.db'}")
    assert st.metric_names == ["mAA(10°)"]
    frozen_no = out["frozen"]["trial"]
    study_note = get_note(st)
    assert f"frozen: trial {frozen_no}, mAA(10°) = {out['frozen']['value']:.3f}" in study_note
    assert "budget B = 1 s median estimator CPU time per pair" in study_note
    for t in st.trials:
        note = get_note(optuna.Trial(st, t._trial_id))
        if t.number == frozen_no:
            assert note.startswith("**imtune** · **frozen**")
        elif t.user_attrs.get("feasible") is False:
            assert "over budget: median estimator CPU time" in note and "never frozen" in note
        else:
            assert note == ""
    from tuner.annotate import annotate_study
    assert annotate_study(st, out["frozen"])["notes_written"] == 0  # freeze already wrote them
