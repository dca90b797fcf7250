#!/usr/bin/env python3
"""SGM and ELAS against OpenCV StereoSGBM on the Middlebury motorcycle pair that scikit-image
ships, and SGM on the ColonSyn sequences of ../shared/data (GT depth), in the same run, on 1 and
2 threads.

    python3 -m venv .venv-bench && .venv-bench/bin/pip install opencv-python-headless scikit-image
    .venv-bench/bin/python benches/stereo_vs_opencv.py [--misslam target/debug/misslam]

Reports bad-1 and bad-2 over non-occluded GT pixels (invalid estimates counted as bad, and
valid-only), density, and milliseconds per pair (median of runs), for 741x500 and 640x432.
Occluded pixels are derived from the GT: a left pixel is occluded when another pixel of its row
with a disparity larger by more than 1 px lands on the same right-image column.
"""
import argparse, json, os, subprocess, tempfile, time, tomllib

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


def non_occluded(gt):
    """GT pixels visible in the right image (z-buffer along each row)."""
    h, w = gt.shape
    ok = np.isfinite(gt)
    d = np.where(ok, gt, -1.0)
    xr = np.round(np.arange(w)[None, :] - d).astype(int)
    inside = ok & (xr >= 0) & (xr < w)
    best = np.full((h, w), -1.0)
    rows = np.repeat(np.arange(h)[:, None], w, axis=1)
    np.maximum.at(best, (rows[inside], xr[inside]), d[inside])
    front = np.zeros((h, w), bool)
    front[inside] = d[inside] >= best[rows[inside], xr[inside]] - 1.0
    return front


def scores(est, gt, mask=None):
    ok = np.isfinite(gt) if mask is None else mask
    e = est[ok]
    g = gt[ok]
    valid = np.isfinite(e) & (e > 0)
    out = dict()
    for t in (1, 2):
        bad = ~valid | (np.abs(np.where(valid, e, 0) - g) > t)
        out[f"bad{t}_pct"] = 100 * bad.mean()
        out[f"bad{t}_valid_pct"] = 100 * (np.abs(e[valid] - g[valid]) > t).mean()
    out["density_pct"] = 100 * valid.mean()
    return out


def colonsyn_rows(args):
    """ColonSyn (synthetic colon, 640x480, GT depth): every pair of each sequence, GT disparity
    fx * B / Z from the depth the project decodes (`graphs/colonsyn_gt.toml`, `sink.files`), 256
    disparities (the GT reaches about 300 px at the closest wall; beyond 255 a pixel counts as
    bad for every method). Scores pooled over all pairs; ms is the median over pairs."""
    rows = []
    for seq in ["colonsyn30", "colonsyn31"]:
        data = os.path.join(args.data, seq)
        if not os.path.isdir(data):
            print(f"skipping {seq}: {data} is absent")
            continue
        with open(f"{data}/calib.toml", "rb") as f:
            calib = tomllib.load(f)
        fx, base = calib["fx"], calib["baseline_mm"]
        nd = 256
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run([args.misslam, "run", "graphs/colonsyn_gt.toml", "--quiet", "--out", f"{tmp}/gt",
                            "--set", f"src.path={data}"], check=True, stderr=subprocess.DEVNULL)
            names = sorted(os.listdir(f"{data}/left"), key=lambda n: int(os.path.splitext(n)[0]))
            gts = []
            for k in range(len(names)):
                z = read_pfm(f"{tmp}/gt/files/depth/{k:06d}.pfm")
                g = np.where(np.isfinite(z) & (z > 0), fx * base / np.where(z > 0, z, 1), np.nan)
                gts.append(g)
            masks = [non_occluded(g) for g in gts]
            gray = [(cv2.imread(f"{data}/left/{n}", cv2.IMREAD_GRAYSCALE), cv2.imread(f"{data}/right/{n}", cv2.IMREAD_GRAYSCALE)) for n in names]
            for threads in [int(t) for t in args.threads.split(",")]:
                cv2.setNumThreads(threads)
                for name, mode in [("opencv SGBM_HH (8 dirs)", cv2.STEREO_SGBM_MODE_HH), ("opencv SGBM (5 dirs)", cv2.STEREO_SGBM_MODE_SGBM)]:
                    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd, blockSize=5, P1=8 * 25, P2=32 * 25,
                                                 uniquenessRatio=5, speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1, mode=mode)
                    times, ests = [], []
                    for gl, gr in gray:
                        t = time.perf_counter()
                        d = sgbm.compute(gl, gr).astype(np.float32) / 16.0
                        times.append(1e3 * (time.perf_counter() - t))
                        d[d < 0] = np.nan
                        ests.append(d)
                    rows.append(dict(method=name, size=seq, threads=threads, ms=float(np.median(times)),
                                     **scores(np.stack(ests), np.stack(gts), np.stack(masks))))
                # The widest lane code this CPU has, then capped at AVX2 (the same output).
                for name, env in [("misslam depth.sgm (8 paths, census 9x7)", {}),
                                  ("misslam depth.sgm, AVX2 lanes", {"MISSLAM_SIMD": "avx2"})]:
                    out = f"{tmp}/sgm{threads}"
                    subprocess.run([args.misslam, "run", "graphs/depth_sgm.toml", "--quiet", "--out", out,
                                    "--set", f"src.path={data}", "--set", "src.mask_border=false",
                                    "--set", "graph.parallel=false", "--set", f"depth.max_disparity={nd}"],
                                   check=True, env=dict(os.environ, RAYON_NUM_THREADS=str(threads), **env),
                                   stderr=subprocess.DEVNULL)
                    m = json.load(open(f"{out}/metrics.json"))
                    ests = [read_pfm(f"{out}/files/disparity/{k:06d}.pfm") for k in range(len(names))]
                    rows.append(dict(method=name, size=seq, threads=threads,
                                     ms=m["timing_ms"]["depth"]["median_ms"],
                                     **scores(np.stack(ests), np.stack(gts), np.stack(masks))))
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--misslam", default="target/debug/misslam")
    ap.add_argument("--runs", type=int, default=9)
    ap.add_argument("--json", help="also write the rows here")
    ap.add_argument("--threads", default="1,2", help="thread counts to run, e.g. 1 or 1,2")
    ap.add_argument("--sgm-only", action="store_true", help="skip the ELAS rows")
    ap.add_argument("--data", default="../shared/data", help="folder holding colonsyn30 and colonsyn31")
    ap.add_argument("--no-colonsyn", action="store_true", help="skip the ColonSyn rows")
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
        mask = non_occluded(g)
        label = f"{size[0]}x{size[1]}"
        gl, gr = cv2.cvtColor(l, cv2.COLOR_RGB2GRAY), cv2.cvtColor(r, cv2.COLOR_RGB2GRAY)
        with tempfile.TemporaryDirectory() as tmp:
            # The same pair `runs` times: the node's median over frames is a warm timing.
            for side, img in [("left", l), ("right", r)]:
                os.makedirs(f"{tmp}/{side}")
                for k in range(args.runs):
                    Image.fromarray(img).save(f"{tmp}/{side}/{k}.png")
            with open(f"{tmp}/calib.toml", "w") as f:
                f.write(f"width = {size[0]}\nheight = {size[1]}\nfx = 1000.0\nfy = 1000.0\ncx = {size[0] / 2}\ncy = {size[1] / 2}\nbaseline_mm = 100.0\ndoffs = 0.0\n")
            for threads in [int(t) for t in args.threads.split(",")]:
                cv2.setNumThreads(threads)
                for name, mode in [("opencv SGBM_HH (8 dirs)", cv2.STEREO_SGBM_MODE_HH), ("opencv SGBM (5 dirs)", cv2.STEREO_SGBM_MODE_SGBM)]:
                    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=nd, blockSize=5, P1=8 * 25, P2=32 * 25,
                                                 uniquenessRatio=5, speckleWindowSize=100, speckleRange=2, disp12MaxDiff=1, mode=mode)
                    times = []
                    for _ in range(args.runs):
                        t = time.perf_counter()
                        d = sgbm.compute(gl, gr).astype(np.float32) / 16.0
                        times.append(1e3 * (time.perf_counter() - t))
                    d[d < 0] = np.nan
                    rows.append(dict(method=name, size=label, threads=threads, ms=float(np.median(times)), **scores(d, g, mask)))
                # The SGM kernels at the widest lane code this CPU has, then capped at AVX2
                # (MISSLAM_SIMD; the same output, so the same scores).
                misslam_runs = [
                    ("misslam depth.sgm (8 paths, census 9x7)", "graphs/depth_sgm.toml", [f"depth.max_disparity={nd}"], {}),
                    ("misslam depth.sgm, AVX2 lanes", "graphs/depth_sgm.toml", [f"depth.max_disparity={nd}"], {"MISSLAM_SIMD": "avx2"}),
                    ("misslam depth.elas robotics", "graphs/depth_elas.toml", ["depth.preset=robotics", "depth.disp_max=255", "depth.subpixel=false"], {}),
                    ("misslam depth.elas robotics + subpixel", "graphs/depth_elas.toml", ["depth.preset=robotics", "depth.disp_max=255", "depth.subpixel=true"], {}),
                    ("misslam depth.elas middlebury", "graphs/depth_elas.toml", ["depth.preset=middlebury", "depth.disp_max=255", "depth.subpixel=false"], {}),
                ]
                if args.sgm_only:
                    misslam_runs = misslam_runs[:2]
                for name, graph, sets, env in misslam_runs:
                    out = f"{tmp}/out"
                    # graph.parallel=false: the depth node runs alone, as OpenCV's call does
                    # (not beside the source decoding and the sink encoding the next frame).
                    cmd = [args.misslam, "run", graph, "--quiet", "--out", out,
                           "--set", f"src.path={tmp}", "--set", "src.mask_border=false",
                           "--set", "graph.parallel=false"]
                    for kv in sets:
                        cmd += ["--set", kv]
                    subprocess.run(cmd, check=True, env=dict(os.environ, RAYON_NUM_THREADS=str(threads), **env), stderr=subprocess.DEVNULL)
                    m = json.load(open(f"{out}/metrics.json"))
                    d = read_pfm(f"{out}/files/disparity/000000.pfm")
                    rows.append(dict(method=name, size=label, threads=threads, ms=m["timing_ms"]["depth"]["median_ms"], **scores(d, g, mask)))
    if not args.no_colonsyn:
        rows += colonsyn_rows(args)
    print("non-occluded GT pixels; bad-N: error > N px with invalid pixels counted bad; 'v': over valid pixels only")
    print(f"{'method':42s} {'size':>10s} {'thr':>3s} {'ms':>8s} {'bad1 %':>7s} {'bad2 %':>7s} {'bad1v %':>8s} {'bad2v %':>8s} {'dens %':>7s}")
    for r in rows:
        print(f"{r['method']:42s} {r['size']:>10s} {r['threads']:3d} {r['ms']:8.1f} {r['bad1_pct']:7.2f} {r['bad2_pct']:7.2f} {r['bad1_valid_pct']:8.2f} {r['bad2_valid_pct']:8.2f} {r['density_pct']:7.1f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=2)


if __name__ == "__main__":
    main()
