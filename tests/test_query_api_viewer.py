"""The web viewer in headless Chromium against a running gateway (uvicorn) with a real map behind it: the
page draws the map and trajectory, a typed query lists the answer and highlights the points of its regions.
Skips when Chromium or selenium is missing (Debian: apt-get install chromium chromium-driver)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

webdriver = pytest.importorskip("selenium.webdriver")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
if not (CHROMIUM and DRIVER):
    pytest.skip("chromium and chromedriver are not installed", allow_module_level=True)

from selenium.webdriver.common.by import By  # noqa: E402

from services.common import keys  # noqa: E402
from services.common.schema import Poses  # noqa: E402
from services.query_api.gateway import Gateway  # noqa: E402
from services.query_api.refmap import RefMap, RefMapParams  # noqa: E402
from services.query_api.service import start_background  # noqa: E402
from tests.query_api_fixtures import bus_pair, oracle_settings, wait_for  # noqa: E402
from tests.test_query_api_e2e import DIM, SEED, STREAM, synth_points  # noqa: E402

# refresh the README picture with: KMVIPE_VIEWER_SCREENSHOT=docs/img/viewer.png pytest tests/test_query_api_viewer.py


@pytest.fixture(scope="module")
def gateway_url():
    xyz, rgb, _, feats, poses, stamps = synth_points(n_keyframes=8, step=2)
    map_bus, gw_bus = bus_pair()
    RefMap(xyz, rgb, feats, np.zeros(DIM, np.float32), np.eye(DIM, dtype=np.float32), "oracle",
           RefMapParams(voxel_size=0.1)).serve(map_bus, STREAM)
    cfg = oracle_settings(oracle_synth_seed=SEED, oracle_synth_dim=DIM, port=0, viewer_points=40_000)
    gw = Gateway(cfg, gw_bus)
    wait_for(lambda: gw.maps.stats(STREAM), what="the synthetic map")
    map_bus.publish(keys.topic(STREAM, keys.POSE), Poses(STREAM, 0, 0, frame_seqs=np.arange(len(poses)),
                                                         stamps_ns=stamps, poses=poses))
    wait_for(lambda: gw.trajectory(STREAM) is not None, what="poses")
    server, thread, port = start_background(cfg, gw_bus, gw)
    yield f"http://127.0.0.1:{port}", xyz
    server.should_exit = True
    thread.join(10)
    map_bus.close()
    gw_bus.close()


@pytest.fixture(scope="module")
def browser():
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1280,800"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=webdriver.ChromeService(DRIVER), options=opts)
    yield driver
    driver.quit()


def test_viewer_draws_the_map_and_highlights_a_query(gateway_url, browser, tmp_path):
    url, xyz = gateway_url
    browser.get(f"{url}/?poll=1000")
    expected = min(len(xyz), 40_000)
    wait_for(lambda: int(browser.find_element(By.ID, "point-count").text) == expected, 30, what="every point on the page")
    wait_for(lambda: int(browser.find_element(By.ID, "pose-count").text) == 8, 30, what="the 8 poses on the page")
    browser.find_element(By.ID, "query").send_keys("table\n")
    items = wait_for(lambda: browser.find_elements(By.CSS_SELECTOR, "#results li.result"), 30, what="the result list")
    assert items[0].text.startswith("table: score")
    highlighted = int(browser.find_element(By.ID, "highlight-count").text)
    # the page highlights the shown points inside the answer's region boxes: recount them here
    regions = browser.execute_script("return state.regions")
    pts = np.array(browser.execute_script("return Array.from(state.xyz)"), np.float32).reshape(-1, 3)
    inside = np.zeros(len(pts), bool)
    for r in regions:
        inside |= np.all((pts >= np.float32(r["box_min"])) & (pts <= np.float32(r["box_max"])), axis=1)
    assert highlighted == int(inside.sum()) > 0
    # the README's picture is refreshed on demand only, so a test run never dirties the work tree
    shot = Path(os.environ.get("KMVIPE_VIEWER_SCREENSHOT", tmp_path / "viewer.png"))
    shot.parent.mkdir(parents=True, exist_ok=True)
    browser.save_screenshot(str(shot))
    assert shot.stat().st_size > 10_000


def test_viewer_shows_the_error_of_an_unknown_label(gateway_url, browser):
    url, _ = gateway_url
    browser.get(url)
    wait_for(lambda: int(browser.find_element(By.ID, "point-count").text), what="points on the page")
    browser.find_element(By.ID, "query").send_keys("unicorn\n")
    error = wait_for(lambda: browser.find_element(By.ID, "error").text, what="the error message")
    assert "unicorn" in error and browser.find_element(By.ID, "highlight-count").text == "0"
