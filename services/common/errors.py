"""One exception base for the whole project; specific subclasses say what went wrong."""


class KmVipeError(Exception):
    """Base of every error KM-ViPE raises on purpose."""


class ConfigError(KmVipeError):
    """A setting is missing or has a value that cannot work (the message says which and how to fix it)."""


class DecodeError(KmVipeError):
    """A payload is not a valid KM-ViPE message (bad msgpack, wrong kind, wrong version, bad field)."""


class SourceError(KmVipeError):
    """A video source cannot be opened or read (missing file, no camera, unreachable URL)."""


class ModelError(KmVipeError):
    """A model is missing, corrupt, or does not fit the map it is asked to serve."""


MODELS_EXTRA = "pip install 'kmvipe[models]' (from a checkout: EXTRAS=models ./scripts/install.sh)"
"""How to install the optional ``models`` extra (pyproject.toml), whose packages are only imported lazily."""


def missing_models_extra(package: str, needed_by: str) -> ModelError:
    """The error of a lazy import from the ``models`` extra that is not installed (tests/test_dependencies.py)."""
    return ModelError(f"{needed_by} needs the {package} package, which comes with the models extra: {MODELS_EXTRA}")


class BusError(KmVipeError):
    """The Zenoh session cannot be opened (no router at the endpoint, an endpoint already in use, bad config)."""


class ServiceTimeout(KmVipeError):
    """A service did not answer a request within its deadline."""

    def __init__(self, service: str, seconds: float):
        super().__init__(f"service '{service}' did not answer within {seconds:.1f} s")
        self.service = service
        self.seconds = seconds


class UnknownSession(KmVipeError):
    """A map verb asked for a session of which no map is kept. Its class name is the wire contract: a queryable's
    error reply reads ``UnknownSession: ...`` and the gateway answers 404 with it."""
