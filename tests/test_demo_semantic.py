"""``kmvipe demo --serve`` end to end, as a new user meets it: the synthetic world through every service with its
oracle features and oracle text vectors (labelled oracle everywhere), "chair" answered over HTTP, and typed into
the viewer's search box in headless Chromium; the highlighted points are checked against the world's
ground-truth labels of what stays put (precision and recall printed)."""
from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from services.evaluation import map_quality as mq
from services.evaluation.ate import absolute_trajectory_error
from services.evaluation.trajectory_io import Trajectory, read_tum
from services.synth import LABEL_NAMES, SynthWorld
from services.synth.spec import config_from_spec
from tests.helpers.processes import served_run
from tests.query_api_fixtures import wait_for

FRAMES = 60
SOURCE = f"synth:frames={FRAMES},seed=0"  # what `kmvipe demo --frames 60` streams
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """A user's `kmvipe demo --serve` (their environment, no test settings), from a scratch directory."""
    work = tmp_path_factory.mktemp("demo")
    env = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
    with served_run(["demo", "--frames", str(FRAMES)], work, env) as url:
        yield url, work / "out"


@pytest.mark.slow
def test_demo_answers_chair_with_regions_labelled_oracle(demo):
    url, out = demo
    summary = json.loads((out / "summary.json").read_text())
    assert summary["queries"]["text"] and summary["queries"]["oracle"]
    assert "oracle" in summary["queries"]["text_why"]
    r = httpx.post(f"{url}/v1/streams/cam0/query", json={"texts": ["chair"], "top_k": 5}, timeout=30)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["oracle"] is True and body["encoder"] == "oracle" and body["space"] == "oracle"
    assert body["results"][0]["regions"], "no region for 'chair'"
    streams = httpx.get(f"{url}/v1/streams", timeout=30).json()["streams"]
    assert streams[0]["queries"]["text"] and streams[0]["queries"]["oracle"]


def gt_labels(out: Path, xyz: np.ndarray, stride_frames: int = 3) -> np.ndarray:
    """Each map point's ground-truth label after the Sim(3) that aligns the run's trajectory to the world's:
    -1 where no GT surface lies within 10 cm, ``mq.AMBIGUOUS`` where two do (the floor round a chair's legs:
    such a voxel fuses both, and which label its nearest GT point has is chance), ``mq.MOVING`` near the chair
    that slides across the room or the person (the map leaves moved objects out: whether a few voxels of the
    moved chair's last place survive is not what the search box is judged by)."""
    world = SynthWorld(config_from_spec(SOURCE))
    truth = Trajectory(world.timestamps_ns() / 1e9, world.poses)
    ate = absolute_trajectory_error(truth, read_tum(out / "trajectory.txt"), align="sim3", max_diff=0.02)
    parts = []
    for seq in range(0, FRAMES, stride_frames):
        f = world.render(seq)
        parts.append(mq.gt_points_of_frame(f.depth, f.labels, f.dynamic, f.world_from_cam, f.intrinsics, 4))
    gt = mq.concat_gt(parts)
    return mq.unambiguous_labels(mq.apply_sim3(ate.alignment, xyz), gt, 0.10, moving=False)


@pytest.mark.slow
@pytest.mark.skipif(not (CHROMIUM and DRIVER), reason="chromium and chromedriver are not installed")
def test_viewer_search_box_highlights_the_chairs(demo):
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.common.by import By

    url, out = demo
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1280,800"):
        opts.add_argument(arg)
    browser = webdriver.Chrome(service=webdriver.ChromeService(DRIVER), options=opts)
    try:
        browser.get(f"{url}/?poll=1000")
        wait_for(lambda: int(browser.find_element(By.ID, "point-count").text) > 0, 60, what="points on the page")
        browser.find_element(By.ID, "query").send_keys("chair\n")
        items = wait_for(lambda: browser.find_elements(By.CSS_SELECTOR, "#results li.result"), 30,
                         what="the result list")
        assert items[0].text.startswith("chair")
        time.sleep(0.5)  # the highlight is drawn right after the list
        xyz = np.array(browser.execute_script("return Array.from(state.xyz)"), np.float32).reshape(-1, 3)
        lit = np.array(browser.execute_script("return Array.from(state.highlight)"), np.uint8)[: len(xyz)] == 1
    finally:
        browser.quit()
    labels = gt_labels(out, xyz)
    chair = LABEL_NAMES.index("chair")
    known = labels >= 0
    precision = float((labels[lit & known] == chair).mean())
    recall = float(lit[known & (labels == chair)].mean())
    print(f"\n'chair' in the viewer: {int(lit.sum())} of {len(xyz)} shown points highlighted; "
          f"precision {precision:.2f}, recall {recall:.2f} against the ground-truth labels "
          f"({int((known & (labels == chair)).sum())} chair points shown, "
          f"{int((labels == mq.AMBIGUOUS).sum())} between two surfaces and "
          f"{int((labels == mq.MOVING).sum())} by moving objects left out)")
    assert lit.sum() > 0
    assert precision >= 0.7 and recall >= 0.5
