"""docker-compose.yml names only services that exist as `kmvipe service NAME`, pins the router to the Python
package's Zenoh release, sets only settings that exist, and passes `docker-compose config -q` where docker-compose
is installed (CI)."""
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
        assert env["KMVIPE_BUS_CONNECT"] == '["tls/zenoh:7447"]'  # the secured router (docs/SECURITY.md)


@pytest.mark.skipif(shutil.which("docker-compose") is None, reason="docker-compose not installed (CI installs it)")
def test_docker_compose_config_is_valid():
    result = subprocess.run(["docker-compose", "config", "-q"], cwd=REPO, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


def _settings_classes() -> dict[str, type]:
    from services.ba.settings import BaSettings
    from services.common.config import BusSettings, LogSettings
    from services.features.config import FeaturesSettings
    from services.ingest.config import IngestSettings
    from services.mapstore.config import MapstoreSettings
    from services.query_api.config import QuerySettings

    classes = (BusSettings, LogSettings, IngestSettings, FeaturesSettings, BaSettings, MapstoreSettings, QuerySettings)
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

