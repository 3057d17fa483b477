"""Log lines (services/common/logs.py): the text format carries the ``extra`` fields as key=value, the JSON format
(python-json-logger) one object per line with the same fields, types kept, and the exception."""
from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from services.common.config import LogSettings
from services.common.logs import setup_logging


@pytest.fixture
def captured(capsys):
    """Reads what the root logger writes to stderr after ``setup_logging``; its handlers and level are put back
    afterwards."""
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    yield lambda: capsys.readouterr().err
    root.handlers[:] = handlers
    root.setLevel(level)


def test_json_lines_carry_level_logger_message_and_the_extra_fields(captured):
    setup_logging("test", LogSettings(format="json", level="INFO"))
    log = logging.getLogger("services.ingest.service")
    log.warning("dropped corrupt frame", extra={"stream": "cam0", "seq": 12, "ratio": 0.5, "shape": np.int64(3)})
    log.debug("below the level")
    try:
        raise RuntimeError("boom")
    except RuntimeError:
        log.exception("handler failed", extra={"seq": 13})
    first, second = [json.loads(line) for line in captured().splitlines()]
    assert {k: first[k] for k in ("level", "logger", "message", "stream", "seq", "ratio", "shape")} == {
        "level": "WARNING", "logger": "services.ingest.service", "message": "dropped corrupt frame",
        "stream": "cam0", "seq": 12, "ratio": 0.5, "shape": "3"}  # a value JSON cannot hold: its str
    assert first["time"][:2] == "20" and "exc" not in first
    assert second["level"] == "ERROR" and second["seq"] == 13
    assert "RuntimeError: boom" in second["exc"] and "Traceback" in second["exc"]


def test_text_lines_end_with_the_extra_fields(captured):
    setup_logging("svc", LogSettings(format="text", level="INFO"))
    logging.getLogger("services.ba.service").info("keyframe", extra={"stream": "cam0", "seq": 7})
    (line,) = captured().splitlines()
    assert line.endswith("INFO [svc] services.ba.service keyframe stream=cam0 seq=7")
