"""Chaos (issue 15): kill -9 one service at a random point of a lossless synthetic stream, restart it as compose's
``restart: unless-stopped`` does, and measure what the stream kept.

The deployment as compose runs it, without docker: a router (in this process, on loopback), features (the
synthetic oracle backbone unless --dino), ba (checkpointing into a folder, as compose's volume), mapstore,
query_api, each as ``kmvipe service NAME``, and an edge publisher (``kmvipe publish``). One undisturbed run first
(its duration sets the kill window, its ATE the reference); then, per service and kill, a fresh deployment whose
victim is killed at a uniformly random time in 15-75 % of the undisturbed duration and started again after
``--restart-delay`` seconds. A killed publisher restarts its stream, which is a new session by design: its
figures are the new session's.

Per run: whether the (last) session's stream completed (the mapstore's end of stream), frames posed (the gateway's
trajectory over HTTP, so a gateway that lost poses shows it), the Sim(3) ATE against the ground truth and its
ratio to the undisturbed run, keyframes features published that are missing from the map database, and world
frames per session: the Sim(3) that aligns the frames posed before the kill to the ground truth must also align
those posed after it (within 3x their own best alignment's error, or 2 % of the path); if not, the stream's poses
live in two frames.

Usage:
  python bench/chaos.py --kills 3                     # every service, 3 kills each
  python bench/chaos.py --services ba mapstore --kills 20 --json /tmp/chaos.json
"""
from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from services.common import keys  # noqa: E402
from services.common.bus import Bus  # noqa: E402
from services.common.config import BusSettings  # noqa: E402
from services.common.schema import Eos, Keyframe, Poses  # noqa: E402
from services.evaluation.ate import absolute_trajectory_error  # noqa: E402
from services.evaluation.trajectory_io import Trajectory  # noqa: E402
from services.ingest.sources import open_source  # noqa: E402
from services.runner.children import free_tcp_endpoint  # noqa: E402

KMVIPE = Path(sys.executable).parent / "kmvipe"
SERVICES = ("features", "ba", "mapstore", "query_api")
VICTIMS = ("publisher", *SERVICES)
STREAM = "cam1"


@dataclass
class Seen:
    """What a consumer on the bus saw of the stream, per session."""
    lock: threading.Lock = field(default_factory=threading.Lock)
    keyframes: dict[str, set[int]] = field(default_factory=dict)
    ended: set[str] = field(default_factory=set)
    posed_at: dict[int, float] = field(default_factory=dict)  # frame seq -> when a mapped pose first came

    def on_keyframe(self, d) -> None:
        with self.lock:
            self.keyframes.setdefault(d.msg.session, set()).add(int(d.msg.seq))

    def on_eos(self, d) -> None:
        if d.msg.stage == "mapstore":
            with self.lock:
                self.ended.add(d.msg.session)

    def on_pose(self, d) -> None:
        now = time.monotonic()
        with self.lock:
            for seq in d.msg.frame_seqs:
                self.posed_at.setdefault(int(seq), now)


class Deployment:
    def __init__(self, out: Path, spec: str, dino: bool):
        shutil.rmtree(out, ignore_errors=True)
        (out / "logs").mkdir(parents=True)
        self.out, self.spec = out, spec
        self.endpoint = free_tcp_endpoint()
        self.port = int(free_tcp_endpoint().rsplit(":", 1)[1])
        base = {k: v for k, v in os.environ.items() if not k.startswith("KMVIPE_")}
        self.env = {**base, "KMVIPE_BUS_MODE": "client", "KMVIPE_BUS_CONNECT": json.dumps([self.endpoint]),
                    "KMVIPE_BUS_LISTEN": "[]", "KMVIPE_MAPSTORE_DB_PATH": str(out / "maps" / "{stream}.db"),
                    "KMVIPE_BA_CHECKPOINT_DIR": str(out / "ba"), "KMVIPE_QUERY_PORT": str(self.port),
                    "KMVIPE_QUERY_HOST": "127.0.0.1"}
        if not dino:
            self.env |= {"KMVIPE_FEATURES_BACKBONE": "synth-oracle", "KMVIPE_FEATURES_ORACLE_SOURCE": spec}
        self.procs: dict[str, subprocess.Popen] = {}
        self.retired: list[subprocess.Popen] = []

    def start(self, name: str) -> None:
        args = ["service", name] if name != "publisher" else [
            "publish", self.spec, "--stream", STREAM, "--pacing", "lossless", "--connect", self.endpoint]
        log = (self.out / "logs" / f"{name}.log").open("ab")
        self.procs[name] = subprocess.Popen([str(KMVIPE), *args], env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                            stdin=subprocess.DEVNULL, cwd=REPO)

    def kill(self, name: str) -> None:
        proc = self.procs.pop(name)
        proc.kill()  # SIGKILL: no cleanup, as an OOM kill or a lost node
        proc.wait()
        self.retired.append(proc)

    def stop(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs.values():
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def trajectory(self, wait_s: float = 60.0) -> dict[int, np.ndarray]:
        """The gateway's trajectory of the stream (waiting up to ``wait_s`` for a restarted gateway to answer)."""
        import httpx

        deadline = time.monotonic() + wait_s
        while True:
            try:
                answer = httpx.get(f"http://127.0.0.1:{self.port}/v1/streams/{STREAM}/trajectory", timeout=15)
                break
            except httpx.HTTPError:
                if time.monotonic() > deadline:
                    return {}
                time.sleep(0.5)
        if answer.status_code != 200:
            return {}
        return {f["seq"]: np.array(f["world_from_cam"]) for f in answer.json()["frames"]}

    def map_keyframes(self) -> set[int]:
        path = self.out / "maps" / f"{STREAM}.db"
        if not path.is_file():
            return set()
        with sqlite3.connect(path) as db:
            return {row[0] for row in db.execute("SELECT kf_id FROM keyframes")}


def run_once(out: Path, spec: str, dino: bool, victim: str | None, kill_at: float, delay: float,
             timeout_s: float) -> dict:
    """One deployment, one stream; ``victim`` killed ``kill_at`` seconds after the publisher started."""
    dep, seen = Deployment(out, spec, dino), Seen()
    killed_at = None
    with Bus(BusSettings(mode="router", listen=[dep.endpoint]), "chaos") as bus:
        bus.subscribe(keys.topic(STREAM, keys.KEYFRAME), seen.on_keyframe, [Keyframe])
        bus.subscribe(keys.topic(STREAM, keys.EOS), seen.on_eos, [Eos])
        bus.subscribe(keys.topic(STREAM, keys.POSE), seen.on_pose, [Poses])
        try:
            for name in SERVICES:
                dep.start(name)
            deadline = time.monotonic() + 180
            while not set(SERVICES) <= set(bus.alive(timeout=0.5)):
                if time.monotonic() > deadline:
                    raise SystemExit(f"services did not start; see {out}/logs")
            began = time.monotonic()
            dep.start("publisher")
            while time.monotonic() - began < timeout_s:
                if victim and killed_at is None and time.monotonic() - began >= kill_at:
                    dep.kill(victim)
                    killed_at = time.monotonic()
                    time.sleep(delay)
                    dep.start(victim)
                with seen.lock:  # a killed publisher's stream is done when the session it restarted ends
                    done = (killed_at is not None or not victim) and _last(seen) in seen.ended and \
                        (victim != "publisher" or len(seen.keyframes) >= 2)
                if done:
                    break
                time.sleep(0.2)
            wall = time.monotonic() - began
            time.sleep(1.0)  # the gateway has the last poses
            trajectory = dep.trajectory()
        finally:
            dep.stop()
    session = _last(seen)
    features_kf = seen.keyframes.get(session, set())
    # a restarted publisher is a new session with its own world frame: its poses are all "after"
    posed_before = set() if victim == "publisher" else {s for s, t in seen.posed_at.items()
                                                        if killed_at is None or t < killed_at}
    return {"victim": victim, "kill_at_s": round(kill_at, 1) if victim else None, "wall_s": round(wall, 1),
            "completed": session in seen.ended, "trajectory": trajectory, "posed_before_kill": posed_before,
            "keyframes_missing": len(features_kf - dep.map_keyframes()) if session in seen.ended else None,
            "sessions": len(seen.keyframes)}


def _last(seen: Seen) -> str | None:
    return max(seen.keyframes) if seen.keyframes else None  # session ids sort by start time


def score(result: dict, world, n_frames: int, reference_ate: float | None) -> dict:
    traj = result.pop("trajectory")
    before = result.pop("posed_before_kill")
    seqs = sorted(s for s in traj if 0 <= s < n_frames)
    result["posed"] = len(seqs)
    result["ate_m"] = result["ate_ratio"] = None
    result["world_frames"] = None
    if len(seqs) >= 3:
        ate = _ate(world, seqs, traj)
        result["ate_m"] = round(ate.rmse, 4)
        if reference_ate:
            result["ate_ratio"] = round(ate.rmse / reference_ate, 2)
        result["world_frames"] = _world_frames(world, traj, [s for s in seqs if s in before],
                                               [s for s in seqs if s not in before])
    return result


def _ate(world, seqs, traj):
    seqs = np.asarray(seqs)
    return absolute_trajectory_error(Trajectory(seqs.astype(float), world.poses[seqs]),
                                     Trajectory(seqs.astype(float), np.stack([traj[s] for s in seqs])), align="sim3")


def _world_frames(world, traj, before: list[int], after: list[int]) -> int:
    """1 when the Sim(3) that aligns the frames posed before the kill to the ground truth also aligns the frames
    posed after it (error within 3x their own best alignment's, or 2 % of the path), else 2."""
    if len(before) < 5 or len(after) < 5:
        return 1
    fit = _ate(world, before, traj).alignment
    own = _ate(world, after, traj).rmse
    est = np.stack([traj[s][:3, 3] for s in after])
    moved = fit.scale * est @ fit.rotation.T + fit.translation
    err = float(np.sqrt(np.mean(np.sum((moved - world.poses[after][:, :3, 3]) ** 2, axis=1))))
    path = float(np.linalg.norm(np.diff(world.poses[:, :3, 3], axis=0), axis=1).sum())
    return 1 if err <= max(3 * own, 0.02 * path) else 2


def table(rows: list[dict]) -> str:
    lines = ["| service killed | kills | streams completed | frames posed (min / mean) | ATE ratio (max / mean) | "
             "acknowledged keyframes missing | world frames per session (max) |", "|---|---|---|---|---|---|---|"]
    for victim in VICTIMS:
        runs = [r for r in rows if r["victim"] == victim]
        if not runs:
            continue
        posed = [r["posed"] for r in runs]
        ratios = [r["ate_ratio"] for r in runs if r["ate_ratio"] is not None]
        missing = [r["keyframes_missing"] for r in runs if r["keyframes_missing"] is not None]
        frames = [r["world_frames"] for r in runs if r["world_frames"] is not None]
        lines.append(f"| {victim} | {len(runs)} | {sum(r['completed'] for r in runs)} / {len(runs)} | "
                     f"{min(posed)} / {np.mean(posed):.1f} | "
                     + (f"{max(ratios):.2f} / {np.mean(ratios):.2f}" if ratios else "–") + " | "
                     + (f"{sum(missing)}" + (f" (of {len(missing)} completed)" if len(missing) < len(runs) else "")
                        if missing else "–") + " | " + (f"{max(frames)}" if frames else "–") + " |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--services", nargs="+", choices=VICTIMS, default=list(VICTIMS))
    parser.add_argument("--kills", type=int, default=20, help="kills per service (one deployment each)")
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--dino", action="store_true", help="the real DINO backbone instead of the oracle")
    parser.add_argument("--restart-delay", type=float, default=1.0, help="seconds between the kill and the restart")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("/tmp/kmvipe-chaos"))
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # a stopped bench stops its deployment (finally)
    if not KMVIPE.is_file():
        raise SystemExit(f"the kmvipe command is not installed beside {sys.executable} (make install)")
    spec = f"synth:frames={args.frames},width=256,height=192"
    world = open_source(spec).world
    rng = random.Random(args.seed)
    print(f"undisturbed run of {spec} ...", flush=True)
    ref = score(run_once(args.out / "undisturbed", spec, args.dino, None, 0.0, 0.0, 600.0), world, args.frames, None)
    if not ref["completed"]:
        raise SystemExit(f"the undisturbed run did not complete; see {args.out / 'undisturbed' / 'logs'}")
    print(f"  {ref['wall_s']} s, {ref['posed']} posed, ATE {ref['ate_m']} m", flush=True)
    rows = []
    total = len(args.services) * args.kills
    for i, (victim, k) in enumerate((v, k) for v in args.services for k in range(args.kills)):
        kill_at = rng.uniform(0.15, 0.75) * ref["wall_s"]
        result = run_once(args.out / f"{victim}-{k}", spec, args.dino, victim, kill_at, args.restart_delay,
                          timeout_s=3 * ref["wall_s"] + 60)
        rows.append(score(result, world, args.frames, ref["ate_m"]))
        r = rows[-1]
        print(f"[{i + 1}/{total}] {victim} killed at {r['kill_at_s']} s: completed={r['completed']} "
              f"posed={r['posed']} ATE={r['ate_m']} ratio={r['ate_ratio']} missing={r['keyframes_missing']} "
              f"world_frames={r['world_frames']} ({r['wall_s']} s)", flush=True)
    cmd = "python bench/chaos.py " + " ".join(sys.argv[1:])
    print(f"\n`{cmd}` ({os.cpu_count()} CPUs; undisturbed: {ref['posed']}/{args.frames} posed, ATE "
          f"{ref['ate_m']} m, {ref['wall_s']} s)\n\n{table(rows)}")
    if args.json:
        args.json.write_text(json.dumps({"undisturbed": ref, "runs": rows}, indent=2, default=list))
    return 0


if __name__ == "__main__":
    sys.exit(main())
