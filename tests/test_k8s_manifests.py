"""deploy/k8s validates offline against the Kubernetes schemas (PyPI kubernetes-validate, which bundles them), runs
only `kmvipe service NAME`s that exist with settings that exist, gives each StatefulSet a KMVIPE_SHARD_COUNT equal
to its replicas, names only files that exist in its kustomization, and fits the secured router of
deploy/zenoh/router.json5 (its port, its secrets, clients that dial it with TLS credentials)."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import PurePosixPath

import pytest
import yaml

from services.cli import build_parser
from services.common.sharding import ShardSettings
from services.runner.children import PIPELINE, is_built
from tests.conftest import REPO
from tests.test_compose import _settings_classes

K8S = REPO / "deploy" / "k8s"
KUSTOMIZATION = K8S / "kustomization.yaml"
STATEFUL = {"features", "ba", "mapstore"}
OLDEST_K8S = "1.28"  # the oldest release the manifests promise to work on (docs/DEPLOY.md)
NOT_A_SETTING = {"KMVIPE_MODELS_DIR"}  # read by the models registry itself (services/common/models/cli.py)


def _validator():
    return pytest.importorskip(
        "kubernetes_validate", reason="kubernetes-validate is not installed (dev extra: pip install -e '.[dev]')")


@pytest.fixture(scope="module")
def kustomization() -> dict:
    return yaml.safe_load(KUSTOMIZATION.read_text())


@pytest.fixture(scope="module")
def resources() -> list[dict]:
    files = sorted(p for p in K8S.glob("*.yaml") if p != KUSTOMIZATION)
    assert files, f"no manifests in {K8S}"
    return [doc for p in files for doc in yaml.safe_load_all(p.read_text()) if doc]


def _of_kind(resources: list[dict], kind: str) -> dict[str, dict]:
    return {r["metadata"]["name"]: r for r in resources if r["kind"] == kind}


def _containers(resources: list[dict]) -> list[tuple[dict, dict]]:
    """(workload, container) of every Deployment and StatefulSet."""
    return [(r, c) for r in resources if r["kind"] in ("Deployment", "StatefulSet")
            for c in r["spec"]["template"]["spec"]["containers"]]


def _env(container: dict) -> dict[str, dict]:
    return {e["name"]: e for e in container.get("env", [])}


def _validate_all(docs: list[dict]) -> list[str]:
    kv = _validator()
    errors = []
    for doc in docs:
        for version in (OLDEST_K8S, kv.latest_version()):
            try:
                kv.validate(doc, version, strict=True)  # strict: unknown fields (typos) are errors too
            except (kv.ValidationError, kv.SchemaNotFoundError) as exc:
                where = ".".join(str(p) for p in getattr(exc, "path", ()))
                errors.append(f"{doc['kind']}/{doc['metadata']['name']} on {version}: {where}: {exc.message}")
    return errors


def test_every_manifest_validates_against_the_kubernetes_schemas(resources):
    assert _validate_all(resources) == []


def test_kustomization_lists_every_manifest(kustomization):
    listed = set(kustomization["resources"])
    on_disk = {p.name for p in K8S.glob("*.yaml") if p != KUSTOMIZATION}
    assert listed == on_disk, "deploy/k8s/kustomization.yaml `resources` must name exactly the manifests beside it"


def test_generated_config_files_exist(kustomization):
    generators = kustomization.get("configMapGenerator", []) + kustomization.get("secretGenerator", [])
    paths = [f.split("=", 1)[-1] for g in generators for f in g.get("files", []) + g.get("envs", [])]
    assert paths, "the router's config should come from a configMapGenerator"
    for path in paths:
        assert (K8S / path).is_file(), f"kustomization.yaml generates from {path}, which does not exist under {K8S}"


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl (its built-in kustomize) not installed")
def test_rendered_kustomization_validates():
    """What `kubectl apply` receives: generated ConfigMaps, the namespace and labels applied, names rewritten."""
    result = subprocess.run(["kubectl", "kustomize", "--load-restrictor", "LoadRestrictionsNone", str(K8S)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    rendered = [d for d in yaml.safe_load_all(result.stdout) if d]
    assert _validate_all(rendered) == []
    config = next(d for d in rendered if d["kind"] == "ConfigMap" and d["metadata"]["name"].startswith("zenoh-router"))
    volumes = _of_kind(rendered, "Deployment")["zenoh-router"]["spec"]["template"]["spec"]["volumes"]
    assert {"configMap": {"name": config["metadata"]["name"]}, "name": "config"} in volumes


def test_services_are_kmvipe_services_that_exist(resources):
    assert set(_of_kind(resources, "StatefulSet")) == STATEFUL
    run = {}
    for workload, container in _containers(resources):
        if container["image"].startswith("kmvipe:"):
            run[workload["metadata"]["name"]] = container["args"]
    assert {args[1] for args in run.values()} == STATEFUL | {"query_api"}
    for args in run.values():
        assert args[0] == "service" and is_built(args[1]) and args[1] in PIPELINE
        assert build_parser().parse_args(args).name == args[1]


def test_images_match_docker_compose(resources):
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())["services"]
    images = {c["image"] for _, c in _containers(resources)}
    assert images == {compose["zenoh"]["image"], compose["features"]["image"]}


def test_every_variable_set_is_a_setting(resources):
    """A KMVIPE_* variable no settings class reads is silently not applied (tests/test_compose.py does the same)."""
    classes = {**_settings_classes(), ShardSettings.model_config["env_prefix"]: ShardSettings}
    for workload, container in _containers(resources):
        for var in _env(container):
            if not var.startswith("KMVIPE_") or var in NOT_A_SETTING:
                continue
            prefix = max((p for p in classes if var.startswith(p)), key=len, default=None)
            assert prefix is not None, f"{workload['metadata']['name']}: {var} has no settings class"
            field = var[len(prefix):].lower()
            assert field in classes[prefix].model_fields, f"{workload['metadata']['name']}: {var} is not a setting"


def test_each_replica_is_its_own_shard(resources, monkeypatch):
    """KMVIPE_SHARD_COUNT equals replicas, and pod <name>-i resolves to shard i (the ordinal from the pod name)."""
    monkeypatch.chdir(REPO / "tests")  # no .env file there
    for name, sts in _of_kind(resources, "StatefulSet").items():
        env = _env(sts["spec"]["template"]["spec"]["containers"][0])
        replicas = sts["spec"]["replicas"]
        assert env["KMVIPE_SHARD_COUNT"]["value"] == str(replicas), f"{name}: KMVIPE_SHARD_COUNT != replicas"
        assert env["KMVIPE_SHARD_POD_NAME"]["valueFrom"] == {"fieldRef": {"fieldPath": "metadata.name"}}
        for ordinal in range(replicas):
            shard = ShardSettings(count=int(env["KMVIPE_SHARD_COUNT"]["value"]), pod_name=f"{name}-{ordinal}")
            assert shard.index == ordinal


def _secret_mounts(workload: dict, container: dict) -> dict[str, str]:
    """mountPath → Secret name of the container's Secret volumes."""
    secrets = {v["name"]: v["secret"]["secretName"] for v in workload["spec"]["template"]["spec"].get("volumes", [])
               if "secret" in v}
    return {m["mountPath"]: secrets[m["name"]] for m in container.get("volumeMounts", []) if m["name"] in secrets}


def _on_a_secret(path: str, mounts: dict[str, str]) -> bool:
    return any(PurePosixPath(path).is_relative_to(m) for m in mounts)


def test_clients_reach_the_router_service_with_their_credentials(resources):
    router = _of_kind(resources, "Deployment")["zenoh-router"]
    router_labels = router["spec"]["template"]["metadata"]["labels"]
    for workload, container in _containers(resources):
        if workload is router:
            continue
        name, env = workload["metadata"]["name"], _env(container)
        assert env["KMVIPE_BUS_MODE"]["value"] == "client"
        for endpoint in json.loads(env["KMVIPE_BUS_CONNECT"]["value"]):
            host, port = endpoint.split("/", 1)[1].split(":")
            service = _of_kind(resources, "Service")[host]["spec"]
            assert service["selector"].items() <= router_labels.items(), f"{name}: {host} does not select the router"
            assert int(port) in {p["port"] for p in service["ports"]}
        assert _on_a_secret(env["KMVIPE_BUS_ZENOH_CONFIG"]["value"], _secret_mounts(workload, container)), name


def test_router_config_fits_the_router_pod(resources):
    """deploy/zenoh/router.json5 listens on the port the Services forward and reads its secrets where they are."""
    config = (REPO / "deploy" / "zenoh" / "router.json5").read_text()
    router = _of_kind(resources, "Deployment")["zenoh-router"]
    container = router["spec"]["template"]["spec"]["containers"][0]
    listen = re.findall(r'"(?:tcp|tls|quic)/[^"]*:(\d+)"', config.split("listen", 1)[1].split("]", 1)[0])
    assert listen and {int(p) for p in listen} <= {p["containerPort"] for p in container["ports"]}
    secrets = re.findall(r'"(/run/secrets/[^"]+)"', config)
    assert all(_on_a_secret(path, _secret_mounts(router, container)) for path in secrets), secrets


def test_client_config_example_is_a_valid_zenoh_config(resources):
    import zenoh

    example = K8S / "bus-client.example.json5"
    conf = zenoh.Config.from_file(str(example))  # refuses unknown or misspelt keys
    ca = json.loads(conf.get_json("transport/link/tls/root_ca_certificate"))
    for workload, container in _containers(resources):
        if "KMVIPE_BUS_ZENOH_CONFIG" in _env(container):
            config_dir = PurePosixPath(_env(container)["KMVIPE_BUS_ZENOH_CONFIG"]["value"]).parent
            assert PurePosixPath(ca).parent == config_dir, "the CA must lie in the Secret beside the client config"


def test_gateway_key_comes_from_a_secret_and_its_port_is_served(resources):
    gateway = _of_kind(resources, "Deployment")["query-api"]["spec"]["template"]["spec"]["containers"][0]
    env = _env(gateway)
    assert "secretKeyRef" in env["KMVIPE_QUERY_API_KEY"]["valueFrom"]
    assert int(env["KMVIPE_QUERY_PORT"]["value"]) in {p["containerPort"] for p in gateway["ports"]}
    assert "/v1/health" in " ".join(gateway["readinessProbe"]["exec"]["command"])


def test_containers_have_requests_and_limits(resources):
    for workload, container in _containers(resources):
        for bound in ("requests", "limits"):
            assert set(container["resources"][bound]) == {"cpu", "memory"}, f"{workload['metadata']['name']} {bound}"


def test_the_durable_map_lies_on_the_shard_volume(resources):
    sts = _of_kind(resources, "StatefulSet")["mapstore"]["spec"]
    container = sts["template"]["spec"]["containers"][0]
    claims = {t["metadata"]["name"] for t in sts["volumeClaimTemplates"]}
    mounts = {m["mountPath"]: m["name"] for m in container["volumeMounts"]}
    for var in ("KMVIPE_MAPSTORE_DB_PATH", "KMVIPE_MAPSTORE_EXPORT_DIR"):
        path = PurePosixPath(_env(container)[var]["value"])
        assert any(path.is_relative_to(m) and name in claims for m, name in mounts.items()), f"{var} not on a claim"


def test_stateful_services_serve_every_stream_and_are_probed_on_their_metrics_port(resources):
    """No stream setting (the default serves every stream a source announces); readiness asks /readyz and liveness
    /livez on the port KMVIPE_METRICS_PORT opens to the kubelet (services/common/metrics.py)."""
    for name, sts in _of_kind(resources, "StatefulSet").items():
        container = sts["spec"]["template"]["spec"]["containers"][0]
        env = _env(container)
        assert not [var for var in env if var.endswith("_STREAM")], f"{name} is pinned to one stream"
        assert env["KMVIPE_METRICS_HOST"]["value"] == "0.0.0.0"
        ports = {p["name"]: p["containerPort"] for p in container["ports"]}
        assert ports["metrics"] == int(env["KMVIPE_METRICS_PORT"]["value"])
        for probe, path in (("readinessProbe", "/readyz"), ("livenessProbe", "/livez")):
            assert container[probe]["httpGet"] == {"path": path, "port": "metrics"}, f"{name} {probe}"
        annotations = sts["spec"]["template"]["metadata"]["annotations"]
        assert annotations["prometheus.io/port"] == env["KMVIPE_METRICS_PORT"]["value"]
