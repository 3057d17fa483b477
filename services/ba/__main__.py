"""``python -m services.ba`` / ``kmvipe service ba``: settings from KMVIPE_BA_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from services.ba.service import build_state, run
from services.ba.settings import BaSettings
from services.common.bus import Bus
from services.common.config import BusSettings
from services.common.errors import KmVipeError
from services.common.lifecycle import stop_on_signals
from services.common.logs import setup_logging


def main(argv: list[str] | None = None) -> int:
    setup_logging("ba")
    stop = stop_on_signals()
    cfg = BaSettings()
    try:
        state = build_state(cfg)
        with Bus(BusSettings(), "ba") as bus:
            run(cfg, bus, stop, state)
    except KmVipeError as exc:
        print(f"ba: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
