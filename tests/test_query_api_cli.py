"""``kmvipe query`` against a running gateway (uvicorn on a free port, a real map queryable behind it)."""
from __future__ import annotations

import argparse
import re

import numpy as np
import pytest

from services.query_api import cli
from services.query_api.gateway import Gateway
from services.query_api.service import start_background
from tests.query_api_fixtures import LABELS, STREAM, bus_pair, make_scene, oracle_settings, scene_map, wait_for


@pytest.fixture(scope="module")
def url():
    map_bus, gw_bus = bus_pair()
    scene_map(make_scene()).serve(map_bus, STREAM)
    cfg = oracle_settings(port=0)
    gw = Gateway(cfg, gw_bus)
    wait_for(lambda: gw.maps.stats(STREAM), what="the map queryable")
    server, thread, port = start_background(cfg, gw_bus, gw)
    yield f"http://127.0.0.1:{port}"
    server.should_exit = True
    thread.join(10)
    map_bus.close()
    gw_bus.close()


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="kmvipe")
    cli.register(parser.add_subparsers(dest="command", required=True))
    return parser.parse_args(list(argv))


def test_query_prints_a_table_of_regions(url, capsys):
    scene = make_scene()
    args = parse("query", "chair", "fire extinguisher", "--stream", STREAM, "--url", url)
    assert args.func(args) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert lines[0].startswith(f"stream {STREAM}: 2400 points")
    chair = next(line for line in lines if line.startswith("chair"))
    centre = np.array([float(v) for v in re.search(r"\(([-\d.]+), ([-\d.]+), ([-\d.]+)", chair).groups()])
    box = scene.boxes[LABELS.index("chair")]
    assert np.all((centre >= box[0] - 0.01) & (centre <= box[1] + 0.01))
    assert any(line.startswith("fire extinguisher") for line in lines)


def test_query_reports_gateway_errors(url, capsys):
    args = parse("query", "chair", "--stream", "nowhere", "--url", url)
    assert args.func(args) == 1
    assert "404: unknown stream 'nowhere'" in capsys.readouterr().err
    args = parse("query", "chair", "--url", "http://127.0.0.1:9")
    assert args.func(args) == 2
    assert "cannot reach the gateway" in capsys.readouterr().err
