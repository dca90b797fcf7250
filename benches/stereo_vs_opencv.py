#!/usr/bin/env python3
"""SGM against OpenCV StereoSGBM on the Middlebury motorcycle pair that scikit-image ships,
in the same run, single-threaded.

    python3 -m venv .venv-bench && .venv-bench/bin/pip install opencv-python-headless scikit-image
    .venv-bench/bin/python benches/stereo_vs_opencv.py [--misslam target/debug/misslam]

Reports bad-2 over non-occluded GT pixels (invalid estimates counted as bad, and valid-only),
density, and milliseconds per pair (median of runs), for 741x500 and 640x432.
"""
import argparse, json, os, subprocess, tempfile, time

import cv2
import numpy as np
import skimage.data
from PIL import Image


def read_pfm(path):
    with open(path, "rb") as f:
        f.readline()
        w, h = map(int, f.readline().split())
        scale = float(f.readline())
        a = np.fromfile(f, "<f4" if scale < 0 else ">f4").reshape(h, w)
    return a[::-1]


def scores(est, gt):
    ok = np.isfinite(gt)
    e = est[ok]
    g = gt[ok]
    valid = np.isfinite(e) & (e > 0)
    bad = ~valid | (np.abs(np.where(valid, e, 0) - g) > 2.0)
    bad_valid = np.abs(e[valid] - g[valid]) > 2.0
    return dict(bad2_pct=100 * bad.mean(), bad2_valid_pct=100 * bad_valid.mean(), density_pct=100 * valid.mean())


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--misslam", default="target/debug/misslam")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", help="also write the rows here")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    left, right, gt = skimage.data.stereo_motorcycle()
    rows = []
    for size in [(741, 500), (640, 432)]:
        if size != (left.shape[1], left.shape[0]):
            s = size[0] / left.shape[1]
            l = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
            r = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
            g = cv2.resize(np.where(np.isfinite(gt), gt, 0), size, interpolation=cv2.INTER_NEAREST) * s
            g = np.where(g > 0, g, np.nan)
        else:
            l, r, g = left, right, gt
        nd = 64
        gl, gr = cv2.cvtColor(l, cv2.COLOR_RGB2GRAY), cv2.cvtColor(r, cv2.COLOR_RGB2GRAY)
        for name, mode in [("opencv SGBM_HH (8 dirs)", cv2.STEREO_SGBM_MODE_HH), ("opencv SGBM (5 dirs)", cv2.STEREO_SGBM_MODE_SGBM)]:
            sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd, blockSize=5, P1=8 * 25, P2=32 * 25,
                                         uniquenessRatio=5, speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1, mode=mode)
            times = []
            for _ in range(args.runs):
                t = time.perf_counter()
                d = sgbm.compute(gl, gr).astype(np.float32) / 16.0
                times.append(1e3 * (time.perf_counter() - t))
            d[d < 0] = np.nan
            rows.append(dict(method=name, size=f"{size[0]}x{size[1]}", ms=float(np.median(times)), **scores(d, g)))
        with tempfile.TemporaryDirectory() as tmp:
            for side, img in [("left", l), ("right", r)]:
                os.makedirs(f"{tmp}/{side}")
                Image.fromarray(img).save(f"{tmp}/{side}/0.png")
            with open(f"{tmp}/calib.toml", "w") as f:
                f.write(f"width = {size[0]}\nheight = {size[1]}\nfx = 1000.0\nfy = 1000.0\ncx = {size[0] / 2}\ncy = {size[1] / 2}\nbaseline_mm = 100.0\ndoffs = 0.0\n")
            times = []
            for _ in range(args.runs):
                out = f"{tmp}/out"
                subprocess.run([args.misslam, "run", "graphs/depth_sgm.toml", "--quiet", "--out", out,
                                "--set", f"src.path={tmp}", "--set", "src.mask_border=false",
                                "--set", f"depth.max_disparity={nd}"],
                               check=True, env=dict(os.environ, RAYON_NUM_THREADS="1"), stderr=subprocess.DEVNULL)
                m = json.load(open(f"{out}/metrics.json"))
                times.append(m["timing_ms"]["depth"]["median_ms"])
            d = read_pfm(f"{tmp}/out/files/disparity/000000.pfm")
            rows.append(dict(method="misslam depth.sgm (8 paths, census 9x7)", size=f"{size[0]}x{size[1]}", ms=float(np.median(times)), **scores(d, g)))
    print(f"{'method':42s} {'size':>8s} {'ms':>8s} {'bad2 %':>7s} {'bad2v %':>8s} {'dens %':>7s}")
    for r in rows:
        print(f"{r['method']:42s} {r['size']:>8s} {r['ms']:8.1f} {r['bad2_pct']:7.2f} {r['bad2_valid_pct']:8.2f} {r['density_pct']:7.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
