"""The settings a run used, for ``summary.json``: per service, the environment the runner gave it and the effective
value of every settings class it builds (the class defaults, then the user's environment and ``.env``, then the
runner's overrides — what the service itself computes), with secrets redacted.

Building the services' settings classes imports their packages (torch for features, ba and the gateway: about
1.4 s and 200 MB), which the runner itself never needs; so they are built in one short-lived child process
(``python -P -m services.runner.settings_used``, niced) started with the services, whose answer the runner reads
when it writes the summary. That process has one thread, so it may set each service's environment in
``os.environ`` in turn and let every class read it exactly as the service does."""
from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from dataclasses import asdict, is_dataclass

from pydantic import ValidationError

from . import children as kids

COMMON = ("services.common.config:BusSettings", "services.common.config:LogSettings",
          "services.common.config:MetricsSettings")
"""Built by every service process (services/common/service_main.py)."""
HOSTED = ("services.common.streams:HostSettings", "services.common.sharding:ShardSettings")
"""Built by the services that serve every stream (services/common/streams.py ``serve``)."""
SERVICE_SETTINGS: dict[str, tuple[str, ...]] = {
    "ingest": ("services.ingest.config:IngestSettings",),
    "features": ("services.features.config:FeaturesSettings", *HOSTED),
    "ba": ("services.ba.settings:BaSettings", *HOSTED),
    "mapstore": ("services.mapstore.config:MapstoreSettings", *HOSTED),
    "query_api": ("services.query_api.config:QuerySettings",),
}

SECRET = re.compile(r"password|secret|token|api_?key|credential", re.IGNORECASE)
REDACTED = "<redacted>"
PROBE_TIMEOUT_S = 60.0  # the probe ends within seconds; a summary never waits longer than this for it


def is_secret(name: str) -> bool:
    """A setting or variable whose value is a secret. A ``*_file`` names where a secret lies, not the secret."""
    return bool(SECRET.search(name)) and not name.lower().endswith("_file")


def redact(value, name: str = ""):
    """``value`` (JSON-like) with every non-empty value under a secret name replaced by ``<redacted>``."""
    if isinstance(value, dict):
        return {k: redact(v, str(k)) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [redact(v, name) for v in value]
    if is_secret(name) and value not in (None, "", []):
        return REDACTED
    return value


def child_env(endpoint: str, service_env: dict[str, str]) -> dict[str, str]:
    """What a service's environment adds to the runner's: the bus overrides of ``children.start`` (kept in step
    with it), then the service's own settings (``pipeline._service_env``)."""
    return {"KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": json.dumps([endpoint]), "KMVIPE_BUS_LISTEN": "[]",
            "KMVIPE_METRICS_PORT": "0", **service_env}


def run_settings(cfg) -> dict:
    """The runner's own settings (a dataclass) as JSON-ready values."""
    return redact(json.loads(json.dumps(asdict(cfg) if is_dataclass(cfg) else dict(cfg), default=str)))


def _settings_class(path: str):
    module, name = path.split(":")
    return getattr(importlib.import_module(module), name)


def collect(overrides: dict[str, dict[str, str]]) -> dict[str, dict]:
    """Per service: ``env`` (its overrides, redacted) and ``settings`` (class name → effective values, redacted;
    ``{"error": ...}`` for a class that refuses them). Sets ``os.environ`` in turn: one thread only."""
    base = dict(os.environ)
    found: dict[str, dict] = {}
    try:
        for service, env in overrides.items():
            os.environ.clear()
            os.environ.update({**base, **env})
            values = {}
            for path in COMMON + SERVICE_SETTINGS.get(service, ()):
                cls = _settings_class(path)
                try:
                    values[cls.__name__] = redact(cls().model_dump(mode="json"))
                except Exception as exc:  # noqa: BLE001 - a bad setting is reported, the others still collected
                    values[cls.__name__] = {"error": _error(exc)}
            found[service] = {"env": redact(env), "settings": values}
    finally:
        os.environ.clear()
        os.environ.update(base)
    return found


def _error(exc: Exception) -> str:
    """What is wrong, without the input values (pydantic's message quotes them: a password among them)."""
    if isinstance(exc, ValidationError):
        return "; ".join(f"{'.'.join(map(str, e['loc'])) or 'settings'}: {e['msg']}"
                         for e in exc.errors(include_url=False, include_context=False, include_input=False))
    return type(exc).__name__


class SettingsProbe:
    """The child process that collects the services' settings; a context manager that never leaves it behind."""

    def __init__(self, overrides: dict[str, dict[str, str]]):
        env = dict(os.environ)
        pythonpath = kids.child_pythonpath(env)  # import the runner's own package, from any working directory
        if pythonpath is not None:
            env["PYTHONPATH"] = pythonpath
        read, write = os.pipe()  # the overrides are small: they fit the pipe, so this write never blocks
        os.write(write, json.dumps(overrides).encode())
        os.close(write)
        try:
            self._process = subprocess.Popen([sys.executable, "-P", "-m", __name__], env=env, stdin=read,
                                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        finally:
            os.close(read)
        self._result: dict | None = None

    def result(self, timeout_s: float = PROBE_TIMEOUT_S) -> dict:
        """Service → ``{"env", "settings"}``; ``{"error": ...}`` when the probe failed or took too long."""
        if self._result is None:
            try:
                out, err = self._process.communicate(timeout=timeout_s)
                self._result = json.loads(out) if self._process.returncode == 0 else {
                    "error": f"the settings probe exited {self._process.returncode}: {err.strip()[-500:]}"}
            except subprocess.TimeoutExpired:
                self.close()
                self._result = {"error": f"the settings probe did not answer within {timeout_s:.0f} s"}
        return self._result

    def close(self) -> None:
        if self._process.poll() is None:
            self._process.kill()
            self._process.communicate()

    def __enter__(self) -> "SettingsProbe":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def main() -> int:
    if hasattr(os, "nice"):
        os.nice(10)  # it runs while the services load their models: theirs is the CPU that matters
    overrides, answer = json.load(sys.stdin), sys.stdout
    sys.stdout = sys.stderr  # whatever an import prints must not corrupt the answer
    json.dump(collect(overrides), answer)
    return 0


if __name__ == "__main__":
    sys.exit(main())
