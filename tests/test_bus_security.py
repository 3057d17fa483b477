"""The secured bus: the router runs from deploy/zenoh/router.json5 itself (only its secret paths and port are
swapped) with TLS, user/password and access control; every client is a real ``Bus`` on loopback, configured
the way services are (``KMVIPE_BUS_USER``, ``_PASSWORD_FILE``, ``_TLS_ROOT_CA``). The edge rules of a new camera
come from ``kmvipe bus users`` (services/common/acl.py); a config it wrote runs in a router of its own here."""
from __future__ import annotations

import json
import shutil
import threading
from pathlib import Path

import pytest
import yaml
import zenoh
from cryptography import x509
from pydantic import ValidationError

from services.cli import main
from services.common import keys
from services.common.acl import render_router_config, write_router_config
from services.common.bus import Bus, bus_password, zenoh_config
from services.common.certs import (GATEWAY_USER, SERVICE_USER, USERS_FILE, cert_pem, edge_user, make_ca,
                                   write_bus_certs, write_bus_users)
from services.common.config import BusSettings
from services.common.errors import BusError, ConfigError, ServiceTimeout
from services.runner.children import free_tcp_endpoint
from tests.conftest import REPO, wait_until

ROUTER_CONFIG = REPO / "deploy" / "zenoh" / "router.json5"
EDGE = edge_user(keys.DEFAULT_STREAM)
OWN, OTHER = keys.DEFAULT_STREAM, "cam1"


def open_router(config: Path, secrets: Path) -> tuple[zenoh.Session, str]:
    """A router from ``config`` on a free loopback port with the secrets of ``secrets``; (session, tls endpoint)."""
    endpoint = "tls/" + free_tcp_endpoint().removeprefix("tcp/")
    conf = zenoh_config(BusSettings(mode="router", zenoh_config=config, listen=[endpoint]))
    for key, path in {"transport/link/tls/listen_certificate": secrets / "router.pem",
                      "transport/link/tls/listen_private_key": secrets / "router.key",
                      "transport/auth/usrpwd/dictionary_file": secrets / USERS_FILE}.items():
        conf.insert_json5(key, json.dumps(str(path)))
    return zenoh.open(conf), endpoint


@pytest.fixture(scope="module")
def router(tmp_path_factory):
    """A secured router on a free loopback port; yields (tls endpoint, secrets folder)."""
    secrets = tmp_path_factory.mktemp("bus-secrets")
    write_bus_certs(secrets)
    write_bus_users(secrets, (OWN,))
    session, endpoint = open_router(ROUTER_CONFIG, secrets)
    yield endpoint, secrets
    session.close()


def settings(router, as_user: str | None, **overrides) -> BusSettings:
    endpoint, secrets = router
    fields = dict(mode="client", connect=[endpoint], tls_root_ca=secrets / "ca.pem")
    if as_user:
        fields.update(user=as_user, password_file=secrets / f"{as_user}.password")
    return BusSettings(**(fields | overrides))


@pytest.fixture
def bus(router):
    opened: list[Bus] = []

    def open_as(user: str, service: str) -> Bus:
        opened.append(Bus(settings(router, user), service))
        return opened[-1]

    yield open_as
    for b in opened:
        b.close()


def received(b: Bus, key: str) -> list[str]:
    """Keys of the samples ``b`` gets on ``key`` (appended as they arrive)."""
    got: list[str] = []
    b._handles.append(b.session.declare_subscriber(key, lambda s: got.append(str(s.key_expr))))
    return got


def put_until(sender: Bus, key: str, got: list[str], what: str) -> None:
    """Put on ``key`` until it arrives: a new subscription takes a moment to reach the publisher."""
    wait_until(lambda: sender.put(key, b"x") or key in got, 5.0, what, poll=0.05)


class Sources:
    """The source tokens a session sees (``Bus.watch_sources``): {token key: present}."""

    def __init__(self, b: Bus):
        self.present: dict[str, bool] = {}
        self._lock = threading.Lock()
        b.watch_sources(self._on_change)

    def _on_change(self, stream: str, key: str, present: bool) -> None:
        with self._lock:
            self.present[key] = present

    def get(self, stream: str, by: Bus) -> bool | None:
        """Whether ``by`` announces ``stream`` (None: never heard of)."""
        with self._lock:
            return self.present.get(keys.source(stream, by.instance))


def announce_own_not_other(edge: Bus, watcher: Sources, own: str, other: str) -> list:
    """Announce both, the forbidden one first: once the allowed one is seen, the other had its chance to arrive.
    Returns the tokens (dropping one undeclares it)."""
    tokens = [edge.announce(other), edge.announce(own)]
    wait_until(lambda: watcher.get(own, edge), 5.0, f"the announcement of {own} at a service")
    assert watcher.get(other, edge) is None, f"{other} was announced by the credential of {own}"
    return tokens


def test_the_service_credential_opens_a_session(router, bus):
    with Bus(settings(router, SERVICE_USER), "features") as b:
        assert b.session.info.routers_zid()


@pytest.mark.parametrize("case", ["no credential", "wrong password", "unknown user", "no CA", "another CA",
                                  "plain tcp"])
def test_a_client_without_valid_credentials_or_trust_is_refused(router, tmp_path, case):
    endpoint, secrets = router
    other_ca = tmp_path / "other-ca.pem"
    other_ca.write_bytes(cert_pem(make_ca()[1]))
    cfg = {
        "no credential": settings(router, None),
        "wrong password": settings(router, SERVICE_USER, password_file=None, password="not-the-password"),
        "unknown user": settings(router, None, user="intruder", password="x"),
        "no CA": settings(router, SERVICE_USER, tls_root_ca=None),  # the public web CAs do not vouch for ours
        "another CA": settings(router, SERVICE_USER, tls_root_ca=other_ca),
        "plain tcp": settings(router, SERVICE_USER, connect=["tcp/" + endpoint.removeprefix("tls/")]),
    }[case]
    with pytest.raises(BusError, match="cannot open the Zenoh session"):
        Bus(cfg, "intruder")


def test_edge_publishes_its_own_stream_only(bus):
    features, edge = bus(SERVICE_USER, "features"), bus(EDGE, "ingest")
    frames = received(features, keys.topic("*", keys.FRAME))
    put_until(edge, keys.topic(OWN, keys.FRAME), frames, "the edge's frames on its own stream")
    for _ in range(5):
        edge.put(keys.topic(OTHER, keys.FRAME), b"forged")
        edge.put(keys.topic(OTHER, keys.EOS), b"forged")
    eos = received(features, keys.topic("*", keys.EOS))
    put_until(edge, keys.topic(OWN, keys.EOS), eos, "the edge's EOS, sent after the forged frames")
    assert keys.topic(OTHER, keys.FRAME) not in frames and keys.topic(OTHER, keys.EOS) not in eos


def test_edge_announces_its_own_stream_only_and_services_see_it(bus):
    live = Sources(bus(SERVICE_USER, "features"))
    edge = bus(EDGE, "ingest")
    tokens = announce_own_not_other(edge, live, OWN, OTHER)
    late = Sources(bus(SERVICE_USER, "ba"))  # a service started after the source still learns of it
    wait_until(lambda: late.get(OWN, edge), 5.0, "the announcement at a service that joined later")
    assert late.get(OTHER, edge) is None
    tokens[1].undeclare()  # the source stopped: services release the stream on this
    wait_until(lambda: live.get(OWN, edge) is False and late.get(OWN, edge) is False, 5.0,
               "the end of the announcement")


def test_only_services_learn_which_sources_there_are(bus):
    ingest = bus(SERVICE_USER, "ingest")
    token = ingest.announce(OWN)  # compose's local ingest announces with the service credential
    services = Sources(bus(SERVICE_USER, "mapstore"))
    wait_until(lambda: services.get(OWN, ingest), 5.0, "a service credential's announcement at a service")
    for user, service in [(EDGE, "ingest"), (GATEWAY_USER, "query_api")]:
        outsider = bus(user, service)
        watching = Sources(outsider)
        replies = list(outsider.session.liveliness().get(keys.source(), timeout=1.0))
        assert not [r for r in replies if r.ok is not None], f"{user} listed the sources"
        assert watching.get(OWN, ingest) is None, f"{user} learnt of a source"
    token.undeclare()


def test_edge_gets_its_credit_and_nothing_else(bus):
    features, edge = bus(SERVICE_USER, "features"), bus(EDGE, "ingest")
    own_credit = received(edge, keys.topic(OWN, keys.CREDIT))
    anything = received(edge, "kmvipe/**")  # refused at the router: only its own credit key is granted
    gateway_poses = received(bus(GATEWAY_USER, "query_api"), keys.topic("*", keys.POSE))
    features.put(keys.topic(OTHER, keys.CREDIT), b"other stream")
    put_until(features, keys.topic(OWN, keys.POSE), gateway_poses, "a pose at the gateway")
    put_until(features, keys.topic(OWN, keys.CREDIT), own_credit, "credit of the edge's stream")
    # each local subscriber's callback runs in turn: the wide one may get the sample just after the other
    wait_until(lambda: keys.topic(OWN, keys.CREDIT) in anything, 5.0, "the credit at the edge's wide subscriber")
    assert set(anything) == {keys.topic(OWN, keys.CREDIT)}  # delivered for the granted subscription only


def test_only_the_gateway_reads_the_map(bus):
    mapstore, gateway = bus(SERVICE_USER, "mapstore"), bus(GATEWAY_USER, "query_api")
    mapstore.serve(keys.map_key(OWN, "**"), lambda key, params, payload: b"the map")
    mapstore.ready()
    stats = keys.map_key(OWN, "stats")

    def answered() -> bool:
        try:
            return gateway.request(stats, timeout=0.5) == b"the map"
        except ServiceTimeout:
            return False

    wait_until(answered, 5.0, "the gateway's map query")
    for user, service in [(EDGE, "ingest"), (SERVICE_USER, "ba")]:
        other = bus(user, service)
        for selector in (stats, keys.map_key("*", "stats"), "kmvipe/**"):
            assert not list(other.session.get(selector, timeout=0.5)), f"{user} read {selector}"
    assert gateway.alive().get("mapstore"), "the gateway must see services alive (/v1/health)"


def test_services_run_the_pipeline_between_them(bus):
    features, ba = bus(SERVICE_USER, "features"), bus(SERVICE_USER, "ba")
    features.serve(keys.topic(OWN, keys.PCA), lambda key, params, payload: b"basis")
    keyframes = received(ba, keys.topic(OWN, keys.KEYFRAME))
    put_until(features, keys.topic(OWN, keys.KEYFRAME), keyframes, "a keyframe from features at ba")
    assert ba.request(keys.topic(OWN, keys.PCA), timeout=2.0) == b"basis"


def test_credentials_come_from_the_environment_or_a_file(tmp_path, monkeypatch):
    secret = tmp_path / "pw"
    secret.write_text("s3cret\n")  # `echo s3cret > file` adds the newline; it is not part of the password
    monkeypatch.setenv("KMVIPE_BUS_USER", "kmvipe-service")
    monkeypatch.setenv("KMVIPE_BUS_PASSWORD_FILE", str(secret))
    cfg = BusSettings()
    assert bus_password(cfg) == "s3cret"
    assert json.loads(zenoh_config(cfg).get_json("transport/auth/usrpwd/password")) == "s3cret"
    assert "s3cret" not in repr(BusSettings(password_file=None, password="s3cret"))
    with pytest.raises(ValidationError, match="not both"):
        BusSettings(password="a")
    monkeypatch.delenv("KMVIPE_BUS_PASSWORD_FILE")
    with pytest.raises(ValidationError, match="needs both"):
        BusSettings()
    monkeypatch.delenv("KMVIPE_BUS_USER")
    with pytest.raises(ConfigError, match="does not exist"):
        zenoh_config(BusSettings(tls_root_ca=tmp_path / "missing.pem"))


def test_adding_a_camera_keeps_the_other_passwords(tmp_path):
    first = {u: p.read_text() for u, p in write_bus_users(tmp_path, ("cam0",)).items()}
    second = {u: p.read_text() for u, p in write_bus_users(tmp_path, ("cam1",)).items()}
    assert second.items() >= first.items() and set(second) - set(first) == {"edge-cam1"}
    assert len(set(second.values())) == len(second)
    assert (tmp_path / USERS_FILE).stat().st_mode & 0o077 == 0


def test_renewing_the_router_certificate_keeps_the_ca(tmp_path):
    first = write_bus_certs(tmp_path, ("zenoh",))
    ca = first.ca_cert.read_bytes()
    renewed = write_bus_certs(tmp_path, ("zenoh", "10.0.0.2"))
    assert renewed.ca_cert.read_bytes() == ca  # clients keep their ca.pem
    leaf = x509.load_pem_x509_certificate(renewed.router_cert.read_bytes())
    leaf.verify_directly_issued_by(x509.load_pem_x509_certificate(ca))
    assert "10.0.0.2" in str(leaf.extensions.get_extension_for_class(x509.SubjectAlternativeName).value)
    assert write_bus_certs(tmp_path, ("zenoh",), new_ca=True).ca_cert.read_bytes() != ca


def test_the_bus_commands_write_what_compose_mounts(tmp_path, capsys):
    out, config = tmp_path / "secrets", tmp_path / "router.json5"
    shutil.copy(ROUTER_CONFIG, config)
    assert main(["bus", "certs", "--out", str(out), "--hosts", "zenoh", "192.0.2.7"]) == 0
    assert main(["bus", "users", "--out", str(out), "--streams", "cam0", "lobby", "--router-config", str(config)]) == 0
    compose = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    mounted = {Path(s["file"]).name for s in compose["secrets"].values()}
    assert mounted <= {p.name for p in out.iterdir()}, "a secret compose mounts is not made by the commands"
    assert "edge-lobby" in (out / USERS_FILE).read_text()
    assert main(["bus", "users", "--out", str(out), "--streams", "not/a/stream", "--router-config", str(config)]) == 2
    assert main(["bus", "users", "--out", str(tmp_path / "elsewhere"), "--router-config", str(tmp_path / "none")]) == 2
    assert not (tmp_path / "elsewhere").exists(), "secrets were written although the router config cannot be"


def test_the_committed_router_config_is_what_the_command_writes_for_cam0():
    """Compose and k8s run deploy/zenoh/router.json5 as committed: its edge entries must be the generated ones
    (a hand edit between the markers, or a rule changed in acl.py without regenerating, fails here)."""
    text = ROUTER_CONFIG.read_text()
    assert render_router_config(text, [keys.DEFAULT_STREAM]) == text


def test_adding_a_camera_writes_its_rules_and_keeps_the_others(tmp_path):
    secrets, config = tmp_path / "secrets", tmp_path / "router.json5"
    shutil.copy(ROUTER_CONFIG, config)
    assert main(["bus", "certs", "--out", str(secrets), "--hosts", "localhost", "127.0.0.1"]) == 0
    assert main(["bus", "users", "--out", str(secrets), "--streams", "cam0", "--router-config", str(config)]) == 0
    assert main(["bus", "users", "--out", str(secrets), "--streams", "lobby", "--router-config", str(config)]) == 0
    session, endpoint = open_router(config, secrets)
    opened: list[Bus] = []

    def as_user(user: str, service: str) -> Bus:
        opened.append(Bus(BusSettings(mode="client", connect=[endpoint], tls_root_ca=secrets / "ca.pem", user=user,
                                      password_file=secrets / f"{user}.password"), service))
        return opened[-1]

    try:
        features = as_user(SERVICE_USER, "features")
        sources, frames = Sources(features), received(features, keys.topic("*", keys.FRAME))
        lobby, cam0 = as_user(edge_user("lobby"), "ingest"), as_user(edge_user("cam0"), "ingest")
        tokens = announce_own_not_other(lobby, sources, "lobby", "cam0")
        tokens += announce_own_not_other(cam0, sources, "cam0", "lobby")  # the first camera works beside the new one
        for _ in range(5):
            lobby.put(keys.topic("cam0", keys.FRAME), b"forged")
        put_until(lobby, keys.topic("lobby", keys.FRAME), frames, "the new camera's frames on its own stream")
        assert keys.topic("cam0", keys.FRAME) not in frames
    finally:
        for b in opened:
            b.close()
        session.close()


def test_revoking_a_camera_removes_its_rules(tmp_path):
    """docs/SECURITY.md: delete the user's line, run `kmvipe bus users --streams`, restart the router."""
    secrets, config = tmp_path / "secrets", tmp_path / "router.json5"
    shutil.copy(ROUTER_CONFIG, config)
    users_cmd = ["bus", "users", "--out", str(secrets), "--router-config", str(config), "--streams"]
    assert main([*users_cmd, "cam0", "lobby"]) == 0
    users = secrets / USERS_FILE
    kept = [line for line in users.read_text().splitlines(True) if not line.startswith("edge-lobby:")]
    users.write_text("".join(kept))
    assert main(users_cmd) == 0  # no stream: the rules of the users left
    text = config.read_text()
    assert "edge-lobby" not in text and "kmvipe/lobby/" not in text
    assert render_router_config(text, ["cam0"]) == text


def test_a_router_config_the_command_cannot_update_is_left_as_it_was(tmp_path):
    config = tmp_path / "router.json5"
    unmarked = ROUTER_CONFIG.read_text().replace("// kmvipe-bus-users: begin policies", "// policies")
    config.write_text(unmarked)
    with pytest.raises(ConfigError, match="comment pair"):
        write_router_config(config, ["lobby"])
    assert config.read_text() == unmarked
    dangling = ROUTER_CONFIG.read_text().replace('"services-alive"],', '"services-alive", "no-such-rule"],')
    config.write_text(dangling)
    with pytest.raises(ConfigError, match="no-such-rule"):
        write_router_config(config, ["lobby"])
    assert config.read_text() == dangling
