"""Structured logging: one logger per module; fields such as stream, seq and t_ns go in ``extra``.

``log.warning("dropped corrupt frame", extra={"stream": s, "seq": 12})`` prints
``… WARNING services.ingest.service dropped corrupt frame stream=cam0 seq=12``, or with ``KMVIPE_LOG_FORMAT=json``
``{"time": "…", "level": "WARNING", "logger": "services.ingest.service", "message": "dropped corrupt frame",
"stream": "cam0", "seq": 12}`` (python-json-logger).
"""
from __future__ import annotations

import logging
import sys

from pythonjsonlogger.json import JsonFormatter

from .config import LogSettings

_STANDARD = set(logging.LogRecord("", 0, "", 0, "", None, None).__dict__) | {"message", "asctime"}


def _fields(record: logging.LogRecord) -> dict:
    return {k: v for k, v in record.__dict__.items() if k not in _STANDARD}


class TextFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        line = super().format(record)
        extra = " ".join(f"{k}={v}" for k, v in _fields(record).items())
        return f"{line} {extra}" if extra else line


def json_formatter() -> JsonFormatter:
    """One JSON object per line: time, level, logger, message, the record's ``extra`` fields, ``exc`` when an
    exception is logged; values JSON cannot hold are written as their ``str``."""
    return JsonFormatter("{asctime}{levelname}{name}{message}", style="{",
                         rename_fields={"asctime": "time", "levelname": "level", "name": "logger", "exc_info": "exc"})


def setup_logging(service: str, settings: LogSettings | None = None) -> None:
    """Configure the root logger of a service process (stderr)."""
    settings = settings or LogSettings()
    handler = logging.StreamHandler(sys.stderr)
    if settings.format == "json":
        handler.setFormatter(json_formatter())
    else:
        handler.setFormatter(TextFormatter(f"%(asctime)s %(levelname)s [{service}] %(name)s %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(settings.level)
