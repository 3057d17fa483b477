"""Live operation (issue 12): `kmvipe run` as a user runs it, on a source streamed at its real rate, measured from
the run's summary.json.

For every source frame the runner records when it saw the frame on the bus and when the frame's first pose came
(tracked or mapped); the summary has the posed fraction (frames with any pose / frames ingest read: frames ingest
dropped count as not posed), the frame → first pose latency, the Sim(3) ATE of those first poses (what a live
consumer saw) and of the final ones, drops per stage (from each stage's EOS), the keyframes whose codes the
backbone skipped, and each service's CPU time while the stream ran and peak RSS (psutil, every 0.5 s). This
script runs `kmvipe run` in a subprocess (so it measures the real processes, the bus and the model loading),
relays its progress bar, and prints one markdown table per run with the command it ran, the load average and the
machine's speed measured just before the run (bench/machine_reference.py: the same code's CPU seconds differ by up
to ~1.7x between days here).

Modes (several may be given; each is one run):
  --kitti          ../shared/data/kitti07_160 (KITTI 07, 160 frames at 10 Hz), realtime pacing
  --synth N        the synthetic world (N frames at 30 Hz, 512x384) rendered once into an image folder under /tmp
                   (the renderer is slower than 30 Hz) without depth.txt, so no sensor depth and no calibration
                   reach the pipeline; streamed at 30 Hz realtime
  --lossless       the same sources in lossless mode instead (end-to-end fps, every frame posed, ATE)
  --frames N       memory check: a lossless run of synth:frames=N,width=256,height=192,span=N*100/120 (the
                   demo's motion per frame, circling the room) that records every
                   service's RSS each 500 frames (summary rss_mb_at_frames) and reports ba's and the mapstore's
                   growth after the first 1,000 frames (those samples, and each one's high-water RSS over the first
                   1,000 frames against any later 1,000, from resources.csv; and each later 1,000 frames' median,
                   the level between bursts) and the end-of-stream time (ingest's EOS → the last stage's)

Usage:
  python bench/live.py --kitti
  python bench/live.py --synth 360
  python bench/live.py --kitti --lossless
  python bench/live.py --frames 10000                    # long: the memory check of issue 12
  python bench/live.py --frames 1500 --timeout 60        # stop after a minute (SIGTERM), report what was measured
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine_reference  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DATA_DIR = Path(os.environ.get("KMVIPE_DATA_DIR", REPO.parent / "shared" / "data"))
KMVIPE = Path(sys.executable).parent / "kmvipe"
STAGES = ("ingest", "features", "ba", "mapstore")
SYNTH_FPS = 30.0


@dataclass
class Run:
    label: str
    source: str
    pacing: str
    env: dict[str, str] = field(default_factory=dict)
    memory: bool = False  # report RSS growth and the end-of-stream time
    note: str = ""


def synth_folder(n_frames: int, cache: Path) -> Path:
    """The synthetic world (n_frames at 30 Hz) as a TUM-style image folder with ground truth and no depth.txt,
    rendered once into ``cache``."""
    folder = cache / f"kmvipe-live-synth-{n_frames}-30hz"
    done = folder / ".complete"
    if not done.is_file():
        from services.synth import SynthConfig, SynthWorld
        from services.synth.io import write_image_folder

        print(f"rendering {n_frames} synthetic frames into {folder} (once) ...", flush=True)
        began = time.monotonic()
        write_image_folder(SynthWorld(SynthConfig(n_frames=n_frames, fps=SYNTH_FPS)), folder)
        (folder / "depth.txt").unlink()  # no sensor depth: a calibration-free, depth-free run
        done.write_text("")
        print(f"rendered in {time.monotonic() - began:.0f} s", flush=True)
    assert not (folder / "depth.txt").exists()
    return folder


def run_kmvipe(run: Run, out_root: Path, timeout_s: float | None) -> tuple[dict, dict]:
    """``kmvipe run`` on ``run``; its summary and what this script measured around it (command, load, wall)."""
    out = out_root / run.label
    cmd = [str(KMVIPE), "run", run.source, "--skip", "query_api", "--pacing", run.pacing, "--out", str(out)]
    shown = " ".join([*(f"{k}={shlex.quote(v)}" for k, v in run.env.items()),
                      "kmvipe", *map(shlex.quote, cmd[1:])])
    print(f"\n[{run.label}] $ {shown}", flush=True)
    # a fresh folder: a previous run's map.db there would be loaded, then kept aside by the new session (a
    # 10,000-frame map: 26 s and ~500 MB of the mapstore counted in this run's first 1,000 frames)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    machine = machine_reference.reference()  # before the run: its speed, not the run's load
    load_before = os.getloadavg()
    loads: list[float] = []
    began = time.monotonic()
    with open(out / "kmvipe.stdout", "w") as stdout:
        proc = subprocess.Popen(cmd, env={**os.environ, **run.env}, stdout=stdout, stderr=subprocess.PIPE,
                                text=True, errors="replace", cwd=REPO)
        relay = threading.Thread(target=_relay, args=(proc.stderr, run.label), daemon=True)
        relay.start()
        stopped = False
        while proc.poll() is None:
            time.sleep(1.0)
            loads.append(os.getloadavg()[0])
            if timeout_s and not stopped and time.monotonic() - began > timeout_s:
                # SIGTERM, not SIGINT: a shell starts background jobs with SIGINT ignored, the ignore is inherited,
                # and kmvipe keeps an ignored signal ignored (as nohup expects), so SIGINT would not stop it
                print(f"[{run.label}] --timeout {timeout_s:.0f} s: stopping the run (SIGTERM)", flush=True)
                proc.send_signal(signal.SIGTERM)
                stopped = True
        relay.join(timeout=5)
    wall = time.monotonic() - began
    summary_path = out / "summary.json"
    if not summary_path.is_file():
        raise SystemExit(f"[{run.label}] kmvipe run exited {proc.returncode} without a summary; "
                         f"see {out / 'kmvipe.stdout'} and {out / 'logs'}")
    meta = {"command": shown, "returncode": proc.returncode, "wall_s": round(wall, 1),
            "load_before": [round(x, 2) for x in load_before], "load_after": [round(x, 2) for x in os.getloadavg()],
            "load_mean_1min": round(sum(loads) / len(loads), 2) if loads else None, "cpus": os.cpu_count(),
            "note": run.note, "machine_reference": machine}
    return json.loads(summary_path.read_text()), meta


def _relay(stream, label: str, every_s: float = 10.0) -> None:
    """The run's stderr (the progress bar, warnings) as progress lines, at most one bar update per ``every_s``
    (and the bar's last state at the end)."""
    last, pending = float("-inf"), None
    for line in stream:  # text mode: tqdm's carriage returns end lines too
        line = line.strip()
        if not line:
            continue
        if line.startswith("kmvipe "):  # the bar
            if time.monotonic() - last < every_s:
                pending = line
                continue
            last, pending = time.monotonic(), None
        print(f"[{label}] {line}", flush=True)
    if pending:
        print(f"[{label}] {pending}", flush=True)


def _fmt(value, spec: str = "", none: str = "–") -> str:
    return none if value is None else format(value, spec)


def table(run: Run, summary: dict, meta: dict, out_dir: Path | None = None) -> str:
    """One markdown table of a run (``out_dir``: its outputs, for the resources.csv of the memory rows)."""
    rows: list[tuple[str, str]] = []
    read = summary.get("frames_read") or 0
    posed = summary.get("posed_fraction")
    lat = summary.get("pose_latency_ms") or {}
    duration = summary.get("duration_s") or 0.0
    rows.append(("source", f"`{summary['source']}`"))
    rows.append(("pacing", run.pacing))
    rows.append(("end", summary.get("end_reason", "")))
    rows.append(("frames read / seen on the bus / keyframes", f"{read} / {summary['frames']} / {summary['keyframes']}"))
    rows.append(("posed (any pose) / frames read",
                 f"{round((posed or 0) * read)} / {read} ({100 * posed:.1f} %)" if posed is not None else "–"))
    rows.append(("frame → first pose p50 / p99 / max",
                 f"{lat['p50']:.0f} / {lat['p99']:.0f} / {lat['max']:.0f} ms" if lat else "–"))
    rows.append(("ATE first poses (Sim3)", _ate(summary.get("ate_first_poses"), summary.get("ate_first_poses_pairs"))))
    rows.append(("first poses provisional (rotation only, before the map)", str(summary.get("provisional_poses", 0))))
    rows.append(("ATE first poses after the map (Sim3)",
                 _ate(summary.get("ate_first_poses_mapped"), summary.get("ate_first_poses_mapped_pairs"))))
    rows.append(("ATE final poses (Sim3)", _ate(summary.get("ate_rmse_sim3"), summary.get("ate_pairs"))))
    fx, error = (summary.get("intrinsics") or [None])[0], summary.get("focal_error_pct")
    rows.append(("refined fx, source px (error against the true fx)",
                 "–" if fx is None else f"{fx:.1f}" + ("" if error is None else f" ({error:+.2f} %)")))
    rows.append(("end-to-end fps (frames read / ingest start → last EOS)",
                 f"{read / duration:.2f} ({read} in {duration:.1f} s)" if duration else "–"))
    rows.append(("end of stream (ingest EOS → last EOS)", _fmt(summary.get("end_of_stream_s"), ".1f") + " s"))
    stages = summary.get("end_of_stream_stages") or {}
    rows.append(("end of stream per stage: EOS after ingest's / own end-of-stream work",
                 ", ".join(f"{stage} {use['after_ingest_s']:.1f} / {use['work_s']:.1f} s" for stage, use in stages.items())
                 or "–"))
    drops = summary.get("drops") or {}
    rows.append(("dropped: " + " / ".join(STAGES), " / ".join(_fmt(drops.get(s)) for s in STAGES)))
    rows.append(("codes skipped (backbone, stale keyframes)", _fmt(summary.get("codes_skipped"))))
    for name, use in (summary.get("services") or {}).items():
        share = f"{100 * use['cpu_stream_s'] / duration:.0f} %" if duration else "–"
        rows.append((f"{name}: CPU share / CPU s / peak RSS",
                     f"{share} / {use['cpu_stream_s']:.1f} s / {use['rss_peak_mb']:.0f} MB"))
    rows.append(("all services: peak RSS (sum at one sample)", f"{summary.get('rss_total_peak_mb', 0):.0f} MB"))
    pss = summary.get("pss_total_peak_mb")
    rows.append(("all services: peak PSS (shared pages counted once)", f"{pss:.0f} MB" if pss else "–"))
    if run.memory:
        rows += memory_rows(summary)
        rows += high_water_rows(summary, out_dir)
    rows.append(("load average before / mean during (1 min) / after",
                 f"{meta['load_before'][0]:.2f} / {_fmt(meta['load_mean_1min'], '.2f')} / "
                 f"{meta['load_after'][0]:.2f} on {meta['cpus']} CPUs"))
    rows.append(("this machine's speed before the run (bench/machine_reference.py)",
                 machine_reference.describe(meta.get("machine_reference"))))
    lines = [f"**{run.label}**: `{meta['command']}`" + (f" ({meta['note']})" if meta["note"] else ""), "",
             "| metric | value |", "|---|---|", *(f"| {k} | {v} |" for k, v in rows)]
    return "\n".join(lines)


def _ate(rmse, pairs) -> str:
    return f"{rmse:.4f} m over {pairs}" if rmse is not None else "–"


def memory_rows(summary: dict) -> list[tuple[str, str]]:
    """ba's and the mapstore's RSS after the first 1,000 frames against later samples (streaming and at the
    end), and the RSS series itself."""
    series = summary.get("rss_mb_at_frames") or []
    rows = []
    if not series:
        return [("RSS series", "none recorded")]
    streaming = series[:-1] or series  # the last record is taken at the end of the stream
    base = next((s for s in streaming if s["frames"] >= 1000), None)
    for name in ("ba", "mapstore"):
        if base is None or name not in base["rss_mb"]:
            rows.append((f"{name}: RSS growth after 1,000 frames", "– (fewer than 1,000 frames)"))
            continue
        b = base["rss_mb"][name]
        last = streaming[-1]["rss_mb"].get(name, b)
        peak = max(s["rss_mb"].get(name, 0.0) for s in series if s["frames"] >= base["frames"])
        rows.append((f"{name}: RSS at {base['frames']} → {streaming[-1]['frames']} frames (peak after)",
                     f"{b:.0f} → {last:.0f} MB ({100 * (last - b) / b:+.1f} %; peak {peak:.0f} MB, "
                     f"{100 * (peak - b) / b:+.1f} %)"))
    rows.append(("RSS every 500 frames (ba / mapstore MB)",
                 ", ".join(f"{s['frames']}: {s['rss_mb'].get('ba', 0):.0f}/{s['rss_mb'].get('mapstore', 0):.0f}"
                           for s in series)))
    return rows


def high_water_rows(summary: dict, out_dir: Path | None) -> list[tuple[str, str]]:
    """ba's and the mapstore's highest RSS over the first 1,000 frames against their highest over any later
    1,000 frames, streaming (before ingest's EOS) and with the end of stream: like against like. The samples every
    500 frames above are single instants of processes whose BAs and re-fusions come and go in bursts of a few
    hundred MB, so they say more about where a burst fell than about growth. From the run's resources.csv (every
    0.5 s), mapped to frames through the series' timestamps (the last record is taken at the end of the stream).
    Also each later 1,000 frames' median sample against frames 900–1,000's: the level the bursts rise from."""
    series = summary.get("rss_mb_at_frames") or []
    path = None if out_dir is None else out_dir / "resources.csv"
    if path is None or not path.is_file() or len(series) < 3 or series[-2]["frames"] < 2000:
        return [("high-water RSS per 1,000 frames", "– (needs resources.csv and 2,000 frames)")]
    with open(path) as f:
        samples = list(csv.DictReader(f))
    streaming = series[:-1]
    end_t = streaming[-1]["t_s"]
    rows = []
    for name in ("ba", "mapstore"):
        t = np.array([float(r["t_s"]) for r in samples if r["service"] == name])
        rss = np.array([float(r["rss_mb"]) for r in samples if r["service"] == name])
        frame = np.interp(t, [s["t_s"] for s in streaming], [s["frames"] for s in streaming])
        first, later = rss[frame <= 1000], (frame > 1000) & (t <= end_t)
        if not first.size or not later.any():
            continue
        base = first.max()
        block = (np.ceil(frame[later]) - 1) // 1000  # k: frames 1000k+1 .. 1000(k+1)
        per_k = {int(k): float(rss[later][block == k].max()) for k in np.unique(block)}
        top, with_end = max(per_k.values()), float(rss[frame > 1000].max())
        rows.append((f"{name}: high-water RSS, first 1,000 frames → any later 1,000 (streaming / with the end)",
                     f"{base:.0f} → {top:.0f} MB ({100 * (top - base) / base:+.1f} %) / "
                     f"{with_end:.0f} MB ({100 * (with_end - base) / base:+.1f} %)"))
        rows.append((f"{name}: high-water RSS per 1,000 frames after the first (MB)",
                     ", ".join(f"{1000 * k}–{1000 * (k + 1)}: {v:.0f}" for k, v in sorted(per_k.items()))))
        # the level between bursts: a block's median sample, against the last 100 frames of the first 1,000 (the
        # first 1,000 frames fill the window, so their median is no level)
        settled = rss[(frame > 900) & (frame <= 1000)]
        if settled.size:
            later_rss, ref = rss[later], float(np.median(settled))
            level = {int(k): float(np.median(later_rss[block == k])) for k in np.unique(block)}
            rows.append((f"{name}: median RSS, frames 900–1,000 → each later 1,000 (the level between bursts, MB)",
                         f"{ref:.0f} → " + ", ".join(f"{v:.0f}" for _, v in sorted(level.items()))
                         + f" ({100 * (max(level.values()) - ref) / ref:+.1f} % at most)"))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--kitti", action="store_true", help="KITTI 07 (160 frames, 10 Hz)")
    parser.add_argument("--synth", type=int, metavar="N", help="the synthetic world, N frames at 30 Hz, no depth")
    parser.add_argument("--lossless", action="store_true", help="run --kitti / --synth in lossless mode")
    parser.add_argument("--frames", type=int, metavar="N", help="memory check: lossless synth:frames=N,256x192")
    parser.add_argument("--oracle", action="store_true",
                        help="synthetic sources: the synth-oracle backbone instead of DINO (no model, a test double)")
    parser.add_argument("--timeout", type=float, metavar="S", help="stop each run after S seconds (SIGTERM)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/kmvipe-live"), help="run outputs (one folder per run)")
    parser.add_argument("--cache", type=Path, default=Path("/tmp"), help="where the rendered synthetic folder goes")
    parser.add_argument("--json", type=Path, help="also write every run's summary and measurements here")
    args = parser.parse_args()
    if not (args.kitti or args.synth or args.frames):
        parser.error("give at least one of --kitti, --synth N, --frames N")
    if not KMVIPE.is_file():
        raise SystemExit(f"the kmvipe command is not installed beside {sys.executable} (make install)")
    pacing = "lossless" if args.lossless else "realtime"

    runs: list[Run] = []
    if args.kitti:
        kitti = DATA_DIR / "kitti07_160"
        if not kitti.is_dir():
            raise SystemExit(f"KITTI 07 not found at {kitti} (set KMVIPE_DATA_DIR)")
        runs.append(Run(f"kitti07-{pacing}", str(kitti), pacing))
    if args.synth:
        folder = synth_folder(args.synth, args.cache)
        env = {"KMVIPE_INGEST_FPS": f"{SYNTH_FPS:g}"}  # the folder's stamps say 30 Hz too; this makes it explicit
        if args.oracle:
            env |= {"KMVIPE_FEATURES_BACKBONE": "synth-oracle", "KMVIPE_FEATURES_ORACLE_SOURCE": f"synth:frames={args.synth}"}
        runs.append(Run(f"synth{args.synth}-30hz-{pacing}", str(folder), pacing, env,
                        note="512x384, no depth, no intrinsics"))
    if args.frames:
        # the demo's per-frame motion (100 degrees of orbit per 120 frames), circling the room for as long as it runs
        spec = f"synth:frames={args.frames},width=256,height=192,span={round(args.frames * 100 / 120)}"
        env = {"KMVIPE_FEATURES_BACKBONE": "synth-oracle", "KMVIPE_FEATURES_ORACLE_SOURCE": spec} if args.oracle else {}
        runs.append(Run(f"synth{args.frames}-memory-lossless", spec, "lossless", env, memory=True,
                        note="memory check"))

    results = []
    tables = []
    for run in runs:
        summary, meta = run_kmvipe(run, args.out, args.timeout)
        tables.append(table(run, summary, meta, args.out / run.label))
        print("\n" + tables[-1] + "\n", flush=True)
        results.append({"label": run.label, "summary": summary, "measured": meta})
    if len(tables) > 1:
        print("\n" + "\n\n".join(tables))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
