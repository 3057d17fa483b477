"""The web viewer in headless Chromium against a running gateway (uvicorn) with a real map behind it: the
page draws the map and trajectory, a typed query lists the answer and highlights the points of its regions, and a
box dragged over a keyframe thumbnail (query by keyframe region, a real mapstore behind the gateway) highlights
the object under the box. Skips when Chromium or selenium is missing (Debian: apt-get install chromium
chromium-driver)."""
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

from selenium.webdriver.common.action_chains import ActionChains  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402

from services.common import keys  # noqa: E402
from services.common.schema import Poses  # noqa: E402
from services.query_api.gateway import Gateway  # noqa: E402
from services.query_api.refmap import RefMap, RefMapParams  # noqa: E402
from services.query_api.service import start_background  # noqa: E402
from services.synth import LABEL_NAMES  # noqa: E402
from tests.query_api_fixtures import bus_pair, oracle_settings, wait_for  # noqa: E402
from tests.test_query_api_e2e import DIM, SEED, STREAM, mapstore_messages, nearest_labels, synth_points  # noqa: E402
from tests.test_query_keyframe import N_KF, keyframe_boxes  # noqa: E402

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


KF_STREAM = "kfview"


@pytest.fixture(scope="module")
def mapstore_url(tmp_path_factory):
    """The gateway (uvicorn) in front of a real mapstore fed the synthetic stream (6 keyframes) over loopback Zenoh."""
    import threading

    from services.common.schema import Eos
    from services.mapstore.config import MapstoreSettings
    from services.mapstore.service import run as run_mapstore

    map_bus, gw_bus = bus_pair("mapstore")
    stop = threading.Event()
    cfg_map = MapstoreSettings(stream=KF_STREAM, db_path=str(tmp_path_factory.mktemp("viewer") / "{stream}.db"),
                               device="cpu", voxel_mode="absolute", voxel_size=0.15, synchronous="NORMAL")
    mapstore = threading.Thread(target=run_mapstore, args=(cfg_map, map_bus, stop), daemon=True)
    mapstore.start()
    cfg = oracle_settings(oracle_synth_seed=SEED, oracle_synth_dim=DIM, port=0, viewer_points=40_000)
    gw = Gateway(cfg, gw_bus)
    wait_for(lambda: gw.maps.stats(KF_STREAM), what="the mapstore")
    done = threading.Event()
    gw_bus.subscribe(keys.topic(KF_STREAM, keys.EOS), lambda d: d.msg.stage == "mapstore" and done.set(), [Eos])
    for msg in mapstore_messages(KF_STREAM, N_KF):
        gw_bus.publish(keys.topic(KF_STREAM, msg.KIND), msg)
    gw_bus.publish(keys.topic(KF_STREAM, keys.EOS), Eos(KF_STREAM, N_KF, 0, stage=cfg_map.upstream))
    assert done.wait(30), "the mapstore did not forward the end of stream"
    server, thread, port = start_background(cfg, gw_bus, gw)
    gt_xyz, _, gt_label, *_ = synth_points(N_KF, step=4)
    yield f"http://127.0.0.1:{port}", gt_xyz, gt_label
    server.should_exit = True
    thread.join(10)
    stop.set()
    mapstore.join(5)
    map_bus.close()
    gw_bus.close()


def drag(browser, img, box: np.ndarray) -> None:
    """Press at the normalised box's top-left corner on the shown image, move to its bottom-right, release."""
    w, h = img.size["width"], img.size["height"]
    x0, y0, x1, y1 = (np.asarray(box) * [w, h, w, h]).round().astype(int).tolist()
    # Selenium 4 offsets are from the element's centre
    ActionChains(browser).move_to_element_with_offset(img, x0 - w // 2, y0 - h // 2).click_and_hold() \
        .move_by_offset(x1 - x0, y1 - y0).release().perform()


def highlighted_labels(browser, gt_xyz, gt_label) -> tuple[np.ndarray, np.ndarray]:
    """(GT label of every point on the page, whether the page highlights it)."""
    pts = np.array(browser.execute_script("return Array.from(state.xyz)"), np.float32).reshape(-1, 3)
    hl = np.array(browser.execute_script("return Array.from(state.highlight)"), np.uint8) == 1
    return nearest_labels(pts, gt_xyz, gt_label), hl


def test_viewer_drags_a_box_on_a_keyframe_and_highlights_that_object(mapstore_url, browser, tmp_path):
    url, gt_xyz, gt_label = mapstore_url
    seq, label, box = keyframe_boxes()[1]
    browser.get(f"{url}/?stream={KF_STREAM}&poll=1000")
    thumb = f'#strip img.thumb[data-seq="{seq}"]'
    wait_for(lambda: browser.execute_script(f"const t = document.querySelector('{thumb}'); return t && t.naturalWidth"),
             30, what="the keyframe's thumbnail in the strip")
    assert len(browser.find_elements(By.CSS_SELECTOR, "#strip img.thumb")) == N_KF
    browser.find_element(By.CSS_SELECTOR, thumb).click()
    img = browser.find_element(By.ID, "kf-image")
    wait_for(lambda: browser.execute_script("return arguments[0].complete && arguments[0].naturalWidth", img),
             what="the opened keyframe")
    assert browser.find_element(By.ID, "kf-title").text == f"keyframe {seq}"
    drag(browser, img, box)
    items = wait_for(lambda: browser.find_elements(By.CSS_SELECTOR, "#results li.result"), 30, what="the result list")
    assert items[0].text.startswith(f"keyframe {seq}: score")
    assert "box on keyframe" in browser.find_element(By.ID, "answer-note").text
    truth, hl = highlighted_labels(browser, gt_xyz, gt_label)
    assert int(browser.find_element(By.ID, "highlight-count").text) == int(hl.sum()) > 0
    precision = float(np.mean(truth[hl] == label))
    recall = float(np.sum(hl & (truth == label)) / max(1, np.sum(truth == label)))
    print(f"\nviewer box on keyframe {seq} over '{LABEL_NAMES[label]}': {hl.sum()} points highlighted, "
          f"precision {precision:.3f}, recall {recall:.3f}")
    assert precision > 0.8 and recall > 0.5
    shot = Path(os.environ.get("KMVIPE_VIEWER_KEYFRAME_SCREENSHOT", tmp_path / "viewer_keyframe.png"))
    shot.parent.mkdir(parents=True, exist_ok=True)
    browser.save_screenshot(str(shot))  # on demand only (the env variable), so a test run never dirties the tree
    # a click (no drag) queries the one 1/8-grid cell under it
    centre = np.repeat(box.reshape(2, 2).mean(0)[None], 2, 0).ravel()
    before = browser.execute_script("return state.regions.length ? state.regions[0].score : null")
    browser.execute_script("state.regions = []; document.getElementById('results').innerHTML = '';")
    drag(browser, img, centre)
    wait_for(lambda: browser.find_elements(By.CSS_SELECTOR, "#results li.result"), 30, what="the click's results")
    assert "a spot on keyframe" in browser.find_element(By.ID, "answer-note").text
    truth, hl = highlighted_labels(browser, gt_xyz, gt_label)
    print(f"viewer click: precision {np.mean(truth[hl] == label):.3f} (box's best region score {before:.3f})")
    assert np.mean(truth[hl] == label) > 0.8


def test_viewer_shows_whether_text_queries_are_available_and_marks_oracle_answers(mapstore_url, browser):
    url, *_ = mapstore_url
    browser.get(f"{url}/?stream={KF_STREAM}")
    wait_for(lambda: int(browser.find_element(By.ID, "point-count").text), what="points on the page")
    status = lambda entry: browser.execute_script(  # noqa: E731
        "showTextSupport(arguments[0]); return document.getElementById('text-status').textContent", entry)
    assert status({"queries": {"text": {"available": False, "why": "no CLIP weights"}}}) == \
        "text: unavailable — no CLIP weights"
    assert status({"queries": {"text": {"available": True, "why": "", "encoder": "oracle", "oracle": True}}}) == \
        "text: oracle (synthetic ground truth)"
    assert status({"queries": {"text": {"available": True, "encoder": "clip+talk2dino"}}}) == "text: clip+talk2dino"
    flat = {"queries": {"text": False, "text_why": "no model", "example": False}}  # the flat form of the field
    assert status(flat) == "text: unavailable — no model"
    assert status({"name": KF_STREAM}) == ""  # a gateway that does not say: nothing shown
    browser.find_element(By.ID, "query").send_keys("table\n")
    wait_for(lambda: browser.find_elements(By.CSS_SELECTOR, "#results li.result"), 30, what="the result list")
    note = browser.find_element(By.ID, "answer-note").text
    oracle = browser.execute_script("return fetch('/v1/streams/%s/query', {method: 'POST', headers: "
                                    "{'Content-Type': 'application/json'}, body: JSON.stringify({texts: ['table']})})"
                                    ".then(r => r.json()).then(a => !!a.oracle)" % KF_STREAM)
    assert ("oracle answer" in note) == oracle  # marked exactly when the gateway says its answer is the oracle's
