"""``python -m services.ba`` / ``kmvipe service ba``: settings from KMVIPE_BA_* and KMVIPE_BUS_*."""
from __future__ import annotations

import sys

from services.ba.service import build_state, run
from services.ba.settings import BaSettings
from services.common.service_main import service_main


def _body(bus, stop) -> None:
    cfg = BaSettings()
    run(cfg, bus, stop, build_state(cfg))


def main(argv: list[str] | None = None) -> int:
    return service_main("ba", _body, handles_tensors=True)


if __name__ == "__main__":
    sys.exit(main())
