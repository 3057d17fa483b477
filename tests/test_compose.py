"""docker-compose.yml names only services that exist as `kmvipe service NAME`, pins the router to the Python
package's Zenoh release, sets only settings that exist, checks each service's health with a command that works,
and passes `docker-compose config -q` where docker-compose is installed (CI)."""
from __future__ import annotations

import importlib.metadata
import shutil
import subprocess
import sys
from types import SimpleNamespace

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
        assert env["KMVIPE_BUS_CONNECT"] == '["tls/zenoh:7447"]'  # the secured router (docs/SECURITY.md)


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="docker-compose not installed (CI installs it)")
def test_docker_compose_config_is_valid():
    result = subprocess.run(["docker-compose", "config", "-q"], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def _settings_classes() -> dict[str, type]:
    from services.ba.settings import BaSettings
    from services.common.config import BusSettings, LogSettings, MetricsSettings
    from services.features.config import FeaturesSettings
    from services.ingest.config import IngestSettings
    from services.mapstore.config import MapstoreSettings
    from services.query_api.config import QuerySettings

    classes = (BusSettings, LogSettings, MetricsSettings, IngestSettings, FeaturesSettings, BaSettings,
               MapstoreSettings, QuerySettings)
    return {cls.model_config["env_prefix"]: cls for cls in classes}


def test_every_variable_set_in_a_container_is_a_setting(compose):
    """A KMVIPE_* variable that no settings class reads is a setting silently not applied (a misspelt or removed
    one): each must name a field of the settings class of its prefix."""
    classes = _settings_classes()
    read_directly = {"KMVIPE_MODELS_DIR"}  # the models registry's folder (services/common/models/cli.py)
    for name, spec in compose["services"].items():
        for var in spec.get("environment", {}):
            if not var.startswith("KMVIPE_") or var in read_directly:
                continue
            prefix = next((p for p in classes if var.startswith(p)), None)
            assert prefix is not None, f"{name}: {var} has no settings class"
            field = var[len(prefix):].lower()
            assert field in classes[prefix].model_fields, f"{name}: {var} is not a setting of {classes[prefix].__name__}"


@pytest.mark.parametrize("ready", [False, True])
def test_healthchecks_ask_readyz_and_fail_until_ready(compose, ready):
    """Every pipeline service but the gateway (its /v1/health) serves its endpoints and is healthy only once ready:
    the compose command itself, run against a real metrics server on the port the container's environment names."""
    from services.common.metrics import HealthServer

    probe = SimpleNamespace(service="ba", instance="test", is_open=True, is_ready=ready)
    server = HealthServer(probe, "127.0.0.1", 0).start()
    try:
        for name in PIPELINE:
            spec = compose["services"][name]
            command = spec["healthcheck"]["test"]
            assert command[0] == "CMD"
            if name == "query_api":
                assert "/v1/health" in command[-1]
                continue
            assert "/readyz" in command[-1] and spec["environment"]["KMVIPE_METRICS_HOST"] == "0.0.0.0"
            env = {"KMVIPE_METRICS_PORT": str(server.port), "PATH": ""}  # the container's port, here a free one
            assert command[1] == "python"
            result = subprocess.run([sys.executable, *command[2:]], env=env, capture_output=True, timeout=30)
            assert (result.returncode == 0) == ready, (name, result.stderr)
    finally:
        server.close()
