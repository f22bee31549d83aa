"""`tune dashboard` serves optuna-dashboard on 127.0.0.1; a real headless Chromium shows the study and its
trials (Selenium + Debian's chromium-driver)."""
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request

import pytest

from tests.conftest import DATA, ROOT

STRECHA = DATA / "strecha"
CHROMIUM = next((p for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser") if os.path.exists(p)),
                shutil.which("chromium"))
CHROMEDRIVER = "/usr/bin/chromedriver" if os.path.exists("/usr/bin/chromedriver") else shutil.which("chromedriver")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def tuner_cache(tmp_path_factory):
    d = tmp_path_factory.getbasetemp() / "tuner-cache"
    d.mkdir(exist_ok=True)
    return str(d)


@pytest.fixture(scope="module")
def served(tmp_path_factory, tuner_cache):
    """A real 3-trial study, and `tune dashboard` on its storage (a free port)."""
    if not STRECHA.is_dir():
        pytest.skip(f"real data not found at {STRECHA}")
    d = tmp_path_factory.mktemp("dash-studies")
    env = dict(os.environ, IMTUNE_CACHE=tuner_cache)
    r = subprocess.run([sys.executable, "-m", "tuner", "--data", str(STRECHA), "--feature", "sift", "--num-features",
                        "2048", "--ransac", "degensac", "--scenes", "fountain-P11", "--max-pairs", "6", "--budget",
                        "0.1", "--calibration-pairs", "4", "--n-trials", "3", "--no-test", "--json",
                        "--studies-dir", str(d), "--study", "dash-sift-study"],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    port = _free_port()
    p = subprocess.Popen([sys.executable, "-m", "tuner", "dashboard", "--studies-dir", str(d), "--port", str(port)],
                         cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.time() + 60
        while True:
            try:
                with urllib.request.urlopen(url + "/api/studies", timeout=2) as resp:
                    studies = json.loads(resp.read())
                break
            except OSError:
                if p.poll() is not None or time.time() > deadline:
                    raise AssertionError(f"dashboard did not start: {p.stderr.read()[-2000:]}") from None
                time.sleep(0.3)
        yield {"url": url, "port": port, "studies": studies, "proc": p, "trials": json.loads(r.stdout)}
    finally:
        p.terminate()
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()


def test_dashboard_binds_loopback_only(served):
    # listening on 127.0.0.1 only: the machine's other addresses refuse
    names = served["studies"]["study_summaries"]
    assert [s["study_name"] for s in names] == ["dash-sift-study"]
    others = set()
    try:
        others = {a[4][0] for a in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)} - {"127.0.0.1"}
    except OSError:
        pass
    for addr in list(others)[:2]:
        if addr.startswith("127."):
            continue
        with socket.socket() as s:
            s.settimeout(2)
            assert s.connect_ex((addr, served["port"])) != 0


@pytest.mark.skipif(not (CHROMIUM and CHROMEDRIVER), reason="chromium and chromedriver not installed "
                    "(Debian packages chromium, chromium-driver; .ci/install.sh installs them)")
def test_dashboard_in_headless_chromium(served):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait
    opts = webdriver.ChromeOptions()
    profile = tempfile.mkdtemp(prefix="imtune-chromium-")
    for a in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
              "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage",
              f"--user-data-dir={profile}"):
        opts.add_argument(a)
    opts.binary_location = CHROMIUM
    drv = webdriver.Chrome(service=Service(CHROMEDRIVER), options=opts)
    try:
        drv.set_page_load_timeout(60)
        drv.get(served["url"] + "/dashboard")
        WebDriverWait(drv, 60).until(lambda d: "dash-sift-study" in d.find_element(By.TAG_NAME, "body").text)
        sid = served["studies"]["study_summaries"][0]["study_id"]
        drv.get(f"{served['url']}/dashboard/studies/{sid}/trials")
        WebDriverWait(drv, 60).until(lambda d: "Trial 2" in d.find_element(By.TAG_NAME, "body").text)
        body = drv.find_element(By.TAG_NAME, "body").text
        assert "dash-sift-study" in body
        for n in range(3):
            assert f"Trial {n}" in body
        # the objective's user attributes are shown with the trial
        assert "mAA5" in body and "ransac_seconds_median" in body
    finally:
        drv.quit()
        shutil.rmtree(profile, ignore_errors=True)


def test_dashboard_port_in_use(served, tmp_path):
    r = subprocess.run([sys.executable, "-m", "tuner", "dashboard", "--studies-dir", str(tmp_path), "--port",
                        str(served["port"])], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "cannot serve the dashboard" in r.stderr
