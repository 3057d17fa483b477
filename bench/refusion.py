"""The mapstore's re-fusion CPU on a real run's map: a stored map.db restarted, then rebuilt from its live keyframes.

    .venv/bin/python bench/refusion.py /tmp/kmvipe-live/kitti07-lossless/map.db            # 3 rounds
    .venv/bin/python bench/refusion.py MAP_DB --rounds 5

Re-fusion (consistency, free-space carving, the voxel sums) is most of the mapstore's CPU on a stream: ba moves its
window's keyframes after every BA and each is re-fused; a rebuild does the same work per keyframe (points,
consistency, carving, sums), less subtracting the old sums. The map.db is copied first (it is never written to); the
printed checksum of the fused map shows whether a change kept the map as it was.
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.mapstore.config import MapstoreSettings  # noqa: E402
from services.mapstore.core.fusion import FusedVoxels  # noqa: E402
from services.mapstore.state import MapState  # noqa: E402


def checksum(fused: FusedVoxels) -> str:
    """A short hash of the fused map's keys, positions and codes (rounded below float noise)."""
    parts = (fused.keys.tobytes(), np.round(fused.xyz, 9).tobytes(), np.nan_to_num(fused.codes).round(5).tobytes())
    return hashlib.sha1(b"".join(parts)).hexdigest()[:12]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map_db", type=Path, help="a run's map.db (kmvipe run --out DIR writes DIR/map.db)")
    ap.add_argument("--rounds", type=int, default=3, help="times the map is rebuilt")
    args = ap.parse_args()
    if not args.map_db.is_file():
        sys.exit(f"no map database at {args.map_db}; run e.g. `python bench/live.py --kitti --lossless` first")
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copy(args.map_db, Path(tmp) / "map.db")
        began = time.process_time()
        state = MapState(MapstoreSettings(db_path=str(Path(tmp) / "map.db")))
        load_s = time.process_time() - began
        loaded = checksum(state.map.fused())
        began = time.process_time()
        live = [len(state.map.rebuild().refreshed) for _ in range(args.rounds)][-1]
        refuse_s = time.process_time() - began
        fused = state.map.fused()
        state.close()
    per = 1000 * refuse_s / max(1, args.rounds * live)
    print(f"restart: {load_s:.2f} CPU-s, checksum {loaded}; {len(fused.keys)} voxels")
    print(f"re-fusion: {args.rounds} x {live} keyframes in {refuse_s:.2f} CPU-s ({per:.1f} ms each), "
          f"checksum {checksum(fused)}")


if __name__ == "__main__":
    main()
