"""docker-compose.yml names only services that exist as `kmvipe service NAME`, pins the router to the Python
package's Zenoh release, and passes `docker-compose config -q` where docker-compose is installed (CI)."""
from __future__ import annotations

import importlib.metadata
import shutil
import subprocess

import pytest
import yaml

from services.cli import build_parser
from services.runner.children import PIPELINE, is_built
from tests.conftest import REPO


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load((REPO / "docker-compose.yml").read_text())


def test_every_service_exists_as_kmvipe_service(compose):
    named = {name: spec["command"] for name, spec in compose["services"].items() if name != "zenoh"}
    assert set(named) == set(PIPELINE)
    for name, command in named.items():
        assert command == ["service", name]
        assert is_built(name), f"docker-compose runs `kmvipe service {name}` but that service is not built"
        args = build_parser().parse_args(command)
        assert args.name == name


def test_router_image_matches_python_zenoh(compose):
    image = compose["services"]["zenoh"]["image"]
    assert image == f"eclipse/zenoh:{importlib.metadata.version('eclipse-zenoh')}"


def test_clients_connect_to_the_router(compose):
    for name in PIPELINE:
        env = compose["services"][name]["environment"]
        assert env["KMVIPE_BUS_MODE"] == "client"
        assert env["KMVIPE_BUS_CONNECT"] == '["tcp/zenoh:7447"]'


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="docker-compose not installed (CI installs it)")
def test_docker_compose_config_is_valid():
    result = subprocess.run(["docker-compose", "config", "-q"], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
