"""``kmvipe map export``: write map.ply, depth maps and COLMAP cameras from a mapstore database."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..common.errors import KmVipeError
from ..common.keys import DEFAULT_STREAM


def register(subparsers) -> None:
    parser = subparsers.add_parser("map", help="work with a stored semantic map")
    sub = parser.add_subparsers(dest="map_command", required=True)
    export = sub.add_parser("export", help="export a map database to PLY + depth maps + COLMAP text")
    export.add_argument("--db", required=True, help="the mapstore's SQLite file (e.g. out/run/map.db)")
    export.add_argument("--out", required=True, help="output folder")
    export.add_argument("--stream", default=DEFAULT_STREAM)
    export.set_defaults(func=run_export)


def run_export(args: argparse.Namespace) -> int:
    from .config import MapstoreSettings
    from .service import export_state
    from .state import MapState

    db = Path(args.db)
    if not db.is_file():
        raise KmVipeError(f"no map database at {db}; `kmvipe run` writes one as <out>/map.db")
    state = MapState(MapstoreSettings(db_path=str(db), stream=args.stream))
    try:
        written = export_state(state, Path(args.out))
    finally:
        state.close()
    print(f"exported {args.db} to {args.out}: {written}")
    return 0
