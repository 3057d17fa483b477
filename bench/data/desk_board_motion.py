"""Where does handheld_desk's ground truth stop being the camera's pose in the static world?

The desk GT is checkerboard PnP: the camera relative to the board. A hand holds and moves the board in part of
the sequence, and there the GT follows the board while a SLAM system that leaves moved objects out follows the
desk. This script finds those frames from the images and the GT alone: for frame pairs (i, i + gap) it matches SIFT
features and counts the matches that the board plane's homography, predicted from the two GT poses and the true
intrinsics, explains within 2 px. While the board lies still on the desk, the desk and the board are one plane
and nearly every match fits; where the board moves, the desk's matches leave it and fit a second homography of
their own.

Usage: python bench/data/desk_board_motion.py [../shared/data/handheld_desk] [--step 15] [--gap 10]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
from services.runner.groundtruth import source_groundtruth  # noqa: E402

FIT_PX = 2.0  # reprojection tolerance of the board-plane homography (source pixels)


def board_homography(k: np.ndarray, world_from_cam_a: np.ndarray, world_from_cam_b: np.ndarray) -> np.ndarray:
    """Image a → image b homography of the world plane z = 0 (the board: corners at (0.04 i, 0.04 j, 0))."""
    def plane_to_image(world_from_cam: np.ndarray) -> np.ndarray:
        cam_from_world = np.linalg.inv(world_from_cam)
        return k @ cam_from_world[:3][:, [0, 1, 3]]
    return plane_to_image(world_from_cam_b) @ np.linalg.inv(plane_to_image(world_from_cam_a))


def matches(sift, grey_a: np.ndarray, grey_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ka, da = sift.detectAndCompute(grey_a, None)
    kb, db = sift.detectAndCompute(grey_b, None)
    pairs = cv2.BFMatcher().knnMatch(da, db, k=2)
    good = [m for m, n in (p for p in pairs if len(p) == 2) if m.distance < 0.75 * n.distance]
    return (np.float32([ka[m.queryIdx].pt for m in good]).reshape(-1, 2),
            np.float32([kb[m.trainIdx].pt for m in good]).reshape(-1, 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", nargs="?", type=Path, default=REPO.parent / "shared" / "data" / "handheld_desk")
    parser.add_argument("--step", type=int, default=15, help="frames between checked pairs")
    parser.add_argument("--gap", type=int, default=10, help="frames between the two images of a pair")
    args = parser.parse_args()
    if not (args.folder / "camera.txt").is_file():
        raise SystemExit(f"no camera.txt in {args.folder}: pass the handheld_desk folder")
    fx, fy, cx, cy = map(float, (args.folder / "camera.txt").read_text().split()[:4])
    k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    names = [line.split()[1] for line in (args.folder / "rgb.txt").read_text().splitlines()
             if line.strip() and not line.startswith("#")]
    gt = source_groundtruth(str(args.folder)).world_from_cam
    sift = cv2.SIFT_create(3000)
    print("frames      matches  fit board plane  second plane")
    for a in range(0, len(names) - args.gap, args.step):
        b = a + args.gap
        pa, pb = matches(sift, *(cv2.imread(str(args.folder / names[i]), cv2.IMREAD_GRAYSCALE) for i in (a, b)))
        if len(pa) < 8:
            print(f"{a:4d}-{b:4d}  {len(pa):7d}  too few matches")
            continue
        landed = cv2.perspectiveTransform(pa[:, None], board_homography(k, gt[a], gt[b]))[:, 0]
        fits = np.linalg.norm(landed - pb, axis=1) < FIT_PX
        second = 0
        if (~fits).sum() >= 12:
            _, mask = cv2.findHomography(pa[~fits], pb[~fits], cv2.RANSAC, FIT_PX)
            second = int(mask.sum()) if mask is not None else 0
        print(f"{a:4d}-{b:4d}  {len(pa):7d}  {fits.mean():15.2f}  {second:12d}")


if __name__ == "__main__":
    main()
