"""KM-ViPE's services (ingest, features, ba, mapstore, query_api) and what they share (common, runner, synth)."""
import os

# torch's CPU thread pool (OpenMP) lets idle threads spin for a while after every parallel operator. The services
# share few cores, so that spinning is CPU taken from tracking and mapping: features on KITTI 07's keyframes next to
# one busy process used 27-31 CPU-s with spinning threads, 22-23 with sleeping ones, and the same on an idle
# machine (docs/BENCHMARKS.md, "Threads that sleep"). OpenMP reads it once, when torch loads it: this package is
# imported before torch in every service process. A value the user set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
