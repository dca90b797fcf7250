#!/usr/bin/env python3
"""`depth.postprocess`'s bilateral filter (`misslam bench bilateral`) against OpenCV's
`bilateralFilter` on the same depth map in the same run, on 1 and 2 threads.

    python3 -m venv .venv-bench && .venv-bench/bin/pip install opencv-python-headless
    .venv-bench/bin/python benches/postprocess_vs_opencv.py [--misslam target/release/misslam]

The map is 640x480 (or --width/--height) of a smooth tissue-like surface with a 6 mm step (a
fold), with Gaussian depth noise (--noise-mm, 0.5): milliseconds per map (median of runs) and the
mean distance to the noise-free surface, over the pixels at least 4 from the image's and the
step's edges, of the noisy map, misslam's filtered map and OpenCV's. Both filters take the node's
defaults: radius 3 (OpenCV: d = 7, a round window of 37 taps where misslam's is the 7x7 square),
spatial sigma 2 px, depth sigma 1.5 mm. OpenCV spreads NaN, so the compared map has no holes;
misslam's time on the map with a hole (its invalid pixels never used) is reported too.
"""
import argparse, json, os, subprocess, tempfile, time

import cv2
import numpy as np


def write_pfm(path, a):
    with open(path, "wb") as f:
        f.write(b"Pf\n%d %d\n-1.0\n" % (a.shape[1], a.shape[0]))
        f.write(np.ascontiguousarray(a[::-1]).astype("<f4").tobytes())


def read_pfm(path):
    with open(path, "rb") as f:
        f.readline()
        w, h = map(int, f.readline().split())
        scale = float(f.readline())
        a = np.fromfile(f, "<f4" if scale < 0 else ">f4").reshape(h, w)
    return a[::-1]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--misslam", default="target/release/misslam")
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--noise-mm", type=float, default=0.5)
    ap.add_argument("--repeat", type=int, default=30)
    args = ap.parse_args()
    h, w = args.height, args.width
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    truth = 80 + 0.02 * x + 0.01 * y + 3 * np.sin(x / 40) + 2 * np.cos(y / 55)
    step = w * 5 // 8
    truth[:, step:] += 6
    rng = np.random.default_rng(1)
    noisy = (truth + rng.normal(0, args.noise_mm, truth.shape)).astype(np.float32)
    holed = noisy.copy()
    holed[h // 5 : h // 5 + 30, w // 3 : w // 3 + 60] = np.nan
    inner = np.zeros((h, w), bool)
    inner[4:-4, 4:-4] = True
    inner[:, step - 4 : step + 4] = False
    err = lambda a: float(np.abs(a[inner] - truth[inner]).mean())
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        src, held = os.path.join(tmp, "d.pfm"), os.path.join(tmp, "holes.pfm")
        write_pfm(src, noisy)
        write_pfm(held, holed)
        for threads in (1, 2):
            env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
            figures = {}
            for name, path in (("ours", src), ("holes", held)):
                out, js = os.path.join(tmp, name + ".pfm"), os.path.join(tmp, name + ".json")
                subprocess.run(
                    [args.misslam, "bench", "bilateral", "--depth", path, "--repeat",
                     str(args.repeat), "--out", out, "--json", js],
                    env=env, check=True, capture_output=True,
                )
                figures[name] = (json.load(open(js)), read_pfm(out))
            cv2.setNumThreads(threads)
            times, cv = [], None
            for _ in range(args.repeat):
                t = time.perf_counter()
                cv = cv2.bilateralFilter(noisy, 7, 1.5, 2.0)
                times.append((time.perf_counter() - t) * 1e3)
            ours, ours_map = figures["ours"]
            rows.append(dict(
                threads=threads, misslam_ms=ours["ms"], opencv_ms=float(np.median(times)),
                misslam_holes_ms=figures["holes"][0]["ms"], noisy_err_mm=err(noisy),
                misslam_err_mm=err(ours_map), opencv_err_mm=err(cv),
                misslam_vs_opencv_mm=float(np.abs(ours_map[inner] - cv[inner]).mean()),
            ))
    print(f"bilateral, {w}x{h}, noise {args.noise_mm} mm; mean distance to the true surface, "
          f"ms per map (median of {args.repeat})")
    for r in rows:
        print(f"{r['threads']} thread(s): misslam {r['misslam_ms']:.2f} ms "
              f"({r['misslam_holes_ms']:.2f} with a hole), OpenCV {r['opencv_ms']:.2f} ms "
              f"(misslam {r['opencv_ms'] / r['misslam_ms']:.2f}x OpenCV's speed); "
              f"error noisy {r['noisy_err_mm']:.4f}, misslam {r['misslam_err_mm']:.4f}, "
              f"OpenCV {r['opencv_err_mm']:.4f} mm; misslam to OpenCV {r['misslam_vs_opencv_mm']:.4f} mm")
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
