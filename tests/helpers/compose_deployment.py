"""docker-compose.yml's services as processes on this host, for tests/test_deployment.py: compose's file and the
Dockerfile read as docker would (variables, anchors, volumes, secrets, the image's environment), the operator's
bus commands run, the compose router started from the config compose mounts, and each service's environment with
only the host-specific parts swapped."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path, PurePosixPath

import pytest
import yaml
import zenoh

from services.common.acl import edge_user
from services.common.bus_cli import DEFAULT_OUT
from services.runner.children import free_tcp_endpoint
from tests.conftest import REPO, wait_until

SECRET_DIR = "/run/secrets/"
ROUTER_SECRETS = {  # the router config's keys that name a secret file (compose mounts them under /run/secrets)
    "transport/link/tls/listen_certificate", "transport/link/tls/listen_private_key",
    "transport/auth/usrpwd/dictionary_file"}

# The compose router is the eclipse/zenoh image on the same JSON5; the Python package of the same release runs it
# here. It applies the given changes, reports which config paths differ from the file, then serves until SIGTERM.
ROUTER = r"""
import json, signal, sys, threading, zenoh

def flat(node, path=""):
    if not isinstance(node, dict):
        return {path: node}
    return {k: v for key, sub in node.items() for k, v in flat(sub, f"{path}/{key}".lstrip("/")).items()}

config, changes = sys.argv[1], json.loads(sys.argv[2])
conf = zenoh.Config.from_file(config)
for key, value in changes.items():
    conf.insert_json5(key, json.dumps(value))
written, running = flat(json.loads(str(zenoh.Config.from_file(config)))), flat(json.loads(str(conf)))
print("changed " + json.dumps(sorted(k for k in written.keys() | running.keys() if written.get(k) != running.get(k))))
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *_: stop.set())
session = zenoh.open(conf)
print("ready", flush=True)
stop.wait()
session.close()
"""


def venv_bin() -> Path:
    value = os.environ.get("KMVIPE_PROD_VENV", "")
    if not value:
        if os.environ.get("KMVIPE_REQUIRE_PROD_VENV") == "1":
            pytest.fail("KMVIPE_PROD_VENV is not set (tests/test_production_install.py says how to make it)")
        return Path(sys.executable).parent
    path = Path(value).resolve() / "bin"
    assert (path / "kmvipe").is_file(), f"{path} has no kmvipe: is it a KM-ViPE install?"
    return path


# --- docker-compose.yml, as compose reads it ------------------------------------------------------------------
_VARIABLE = re.compile(r"\$\{(?P<name>\w+)(?P<op>:?-)?(?P<default>[^}]*)\}")


def interpolate(value: str, host_env: dict[str, str]) -> str:
    """Compose's ``${VAR}``, ``${VAR:-default}`` and ``${VAR-default}``; any other use of ``$`` fails the test
    (a form this reader does not know would be passed on wrong)."""

    def one(m: re.Match) -> str:
        if m["op"] is None and m["default"]:
            pytest.fail(f"compose interpolation {m[0]!r} is not understood by this test")
        if m["op"] == ":-" and not host_env.get(m["name"]):
            return m["default"]
        return host_env.get(m["name"], m["default"] if m["op"] else "")

    if re.search(r"\$(?!\{)", value):
        pytest.fail(f"compose interpolation in {value!r} is not understood by this test")
    return _VARIABLE.sub(one, value)


def dockerfile_image() -> tuple[list[str], dict[str, str]]:
    """The image's ENTRYPOINT and ENV (what every service container starts with)."""
    text = (REPO / "Dockerfile").read_text().replace("\\\n", " ")
    entrypoint = json.loads(re.search(r"^ENTRYPOINT\s+(\[.*\])\s*$", text, re.MULTILINE)[1])
    env: dict[str, str] = {}
    for line in re.findall(r"^ENV\s+(.*)$", text, re.MULTILINE):
        env.update(pair.split("=", 1) for pair in line.split())
    return entrypoint, env


class Compose:
    """docker-compose.yml with anchors, merge keys and ``${...}`` resolved; container paths mapped to this host."""

    def __init__(self, tmp: Path, host_env: dict[str, str]):
        spec = yaml.safe_load((REPO / "docker-compose.yml").read_text())  # PyYAML resolves anchors and `<<`
        self.services, self.host_env = spec["services"], host_env
        self.secret_dir = tmp / "secrets"
        self.secret_files = {name: self._secret_file(entry["file"]) for name, entry in spec["secrets"].items()}
        self.volumes = {name: tmp / "volumes" / name for name in spec.get("volumes", {})}
        self.rootfs = tmp / "rootfs"

    def _secret_file(self, file: str) -> Path:
        relative = PurePosixPath(file).relative_to(PurePosixPath("./" + DEFAULT_OUT))  # where the bus commands write
        return self.secret_dir / relative

    def container_paths(self, service: str) -> dict[str, Path]:
        """Container path -> host path, for what compose mounts into ``service`` (secrets and named volumes)."""
        spec = self.services[service]
        paths = {SECRET_DIR + name: self.secret_files[name] for name in spec.get("secrets", [])}
        for volume in spec.get("volumes", []):
            source, target = volume.split(":")[:2]
            if source in self.volumes:
                paths[target] = self.volumes[source]
        return paths

    def host_path(self, service: str, value: str) -> str:
        """``value`` with a container path replaced by its host path: a mount's, else a folder standing for the
        container's own file system (so no host path is used by mistake). A secret not mounted fails the test."""
        if not value.startswith("/"):
            return value
        for target, host in self.container_paths(service).items():
            if value == target or value.startswith(target + "/"):
                return str(host) + value[len(target):]
        assert not value.startswith(SECRET_DIR), f"{service} reads {value}, but compose does not mount that secret"
        return str(self.rootfs / service) + value

    def environment(self, service: str) -> dict[str, str]:
        return {k: interpolate(str(v), self.host_env) for k, v in self.services[service]["environment"].items()}


# --- processes ----------------------------------------------------------------------------------------------
class Processes:
    """Every process the test starts, each logging to its own file; stopped with SIGTERM, then SIGKILL."""

    def __init__(self, logs: Path):
        self.logs, self.procs = logs, {}
        logs.mkdir()

    def start(self, name: str, argv: list[str], env: dict[str, str], cwd: Path) -> subprocess.Popen:
        log = (self.logs / f"{name}.log").open("wb")
        self.procs[name] = subprocess.Popen(argv, env=env, cwd=cwd, stdout=log, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL)
        log.close()  # the child holds its own descriptor
        return self.procs[name]

    def log(self, name: str) -> str:
        path = self.logs / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def check_running(self, *names: str) -> None:
        for name in names or self.procs:
            code = self.procs[name].poll()
            assert code is None, f"{name} exited with {code}:\n{self.log(name)[-3000:]}"

    def stop(self, grace_s: float = 15.0) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + grace_s
        for proc in self.procs.values():
            try:
                proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def dump(self) -> None:
        for name in self.procs:
            print(f"===== {name} (exit {self.procs[name].poll()}) =====\n{self.log(name)[-4000:]}")


def base_env(bin_dir: Path, home: Path) -> dict[str, str]:
    """A clean shell: none of this session's KMVIPE_* settings or Python paths; the chosen venv first on PATH."""
    keep = {k: v for k, v in os.environ.items()
            if not k.startswith("KMVIPE_") and k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSAFEPATH")}
    return {**keep, "PATH": f"{bin_dir}{os.pathsep}{keep.get('PATH', '')}", "VIRTUAL_ENV": str(bin_dir.parent),
            "HOME": str(home)}


def make_secrets(bin_dir: Path, env: dict[str, str], compose: Compose, tmp: Path, streams: tuple[str, ...]) -> Path:
    """The operator's two commands, into the test's folder, for edge cameras on ``streams``; returns the router
    config they wrote the edge rules into (a copy of the file compose mounts into the router)."""
    command = compose.services["zenoh"]["command"]
    mounted = dict(v.split(":")[1::-1] for v in compose.services["zenoh"]["volumes"])  # target -> source
    source = mounted[command[command.index("--config") + 1]]  # the router runs the config compose mounts
    config = tmp / "router.json5"
    config.write_bytes((REPO / source).read_bytes())
    out = str(compose.secret_dir)
    for argv in (["bus", "certs", "--out", out, "--hosts", "localhost", "127.0.0.1"],
                 ["bus", "users", "--out", out, "--streams", *streams, "--router-config", str(config)]):
        result = subprocess.run([str(bin_dir / "kmvipe"), *argv], env=env, cwd=tmp, capture_output=True, text=True,
                                timeout=120)
        assert result.returncode == 0, f"kmvipe {' '.join(argv)}: {result.stdout}{result.stderr}"
    return config


def router_changes(compose: Compose, config: Path, port: int) -> dict[str, object]:
    """What differs between compose's router and this one: its secrets' paths and the listen endpoint."""
    written = zenoh.Config.from_file(str(config))
    listen = json.loads(written.get_json("listen/endpoints"))
    published = {int(p.split(":")[-1]) for p in compose.services["zenoh"]["ports"]}
    assert [e.rsplit(":", 1)[1] for e in listen] == ["7447"] and published == {7447}, (listen, published)
    changes: dict[str, object] = {"listen/endpoints": [f"tls/127.0.0.1:{port}"]}
    for key in ROUTER_SECRETS:
        changes[key] = compose.host_path("zenoh", json.loads(written.get_json(key)))
        assert changes[key] != json.loads(written.get_json(key)), f"{key}: not a secret compose mounts"
    return changes


def start_router(procs: Processes, bin_dir: Path, env: dict[str, str], config: Path, changes: dict, cwd: Path):
    procs.start("zenoh", [str(bin_dir / "python"), "-c", ROUTER, str(config), json.dumps(changes)], env, cwd)
    wait_until(lambda: procs.check_running("zenoh") or "ready" in procs.log("zenoh"), 30, "the router")
    changed = json.loads(procs.log("zenoh").split("changed ", 1)[1].splitlines()[0])
    assert set(changed) == set(changes), f"the router runs a config that differs from the file in {changed}"


def service_env(compose: Compose, name: str, base: dict[str, str], image_env: dict[str, str], router: str,
                gateway_port: int, oracle_source: str) -> dict[str, str]:
    """``name``'s environment as compose gives it, with the host-specific parts swapped (see the module docstring);
    features runs the synthetic world's oracle backbone for ``oracle_source``."""
    env = {k: compose.host_path(name, v) for k, v in {**image_env, **compose.environment(name)}.items()
           if k != "PATH"}  # the image's PATH names its venv; base has ours
    assert env["KMVIPE_BUS_CONNECT"] == '["tls/zenoh:7447"]', env["KMVIPE_BUS_CONNECT"]
    env["KMVIPE_BUS_CONNECT"] = json.dumps([router])
    if name == "features":
        # the synthetic world's exact label features in place of DINO: the backbone would take most of the CPU
        # time on 2 cores and is not what this test is about (test_multi_stream.py does the same)
        env.update(KMVIPE_FEATURES_BACKBONE="synth-oracle", KMVIPE_FEATURES_ORACLE_SOURCE=oracle_source)
    if name == "query_api":
        published = {p.rsplit(":", 1)[1] for p in compose.services[name]["ports"]}
        assert published == {env["KMVIPE_QUERY_PORT"]}, (published, env["KMVIPE_QUERY_PORT"])
        env["KMVIPE_QUERY_PORT"] = str(gateway_port)
    if "KMVIPE_METRICS_PORT" in env:  # each container has its own network namespace; processes on one host do not
        env["KMVIPE_METRICS_PORT"] = free_tcp_endpoint().rsplit(":", 1)[1]
    # a container's 0.0.0.0 is its own network; here it would be every interface of the host: loopback instead
    return {**base, **{k: "127.0.0.1" if v == "0.0.0.0" else v for k, v in env.items()}}


def edge_env(base: dict[str, str], secret_dir: Path, stream: str) -> dict[str, str]:
    """The device's credential as docs/SECURITY.md gives it (section 3)."""
    user = edge_user(stream)
    return {**base, "KMVIPE_BUS_USER": user, "KMVIPE_BUS_PASSWORD_FILE": str(secret_dir / f"{user}.password"),
            "KMVIPE_BUS_TLS_ROOT_CA": str(secret_dir / "ca.pem")}
