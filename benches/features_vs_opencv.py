#!/usr/bin/env python3
"""ORB and Hamming matching against OpenCV, in the same run, single-threaded (misslam with
RAYON_NUM_THREADS=1; its ORB levels run in parallel otherwise, shown beside as "2 threads").

    python3 -m venv .venv-bench && .venv-bench/bin/pip install opencv-python-headless scikit-image
    .venv-bench/bin/python benches/features_vs_opencv.py [--misslam target/debug/misslam]

Images: scikit-image's astronaut and the Middlebury motorcycle (left view), gray, 640x480.
- ORB detect-and-describe, 1000 keypoints: median ms (misslam with its default quadtree spread
  and with `none`, which keeps the strongest corners as OpenCV does). OpenCV and misslam take
  turns over `--rounds` rounds (20 runs each a round): a shared machine's speed drifts by tens of
  per cent within a minute, so the ratio is taken within each round, and its median and range
  over the rounds are reported.
- Hamming 2-NN of 2000 x 2000 descriptors (misslam's brute force vs OpenCV's BFMatcher.knnMatch).
- Matching precision on pairs related by a known homography (rotation, scale, perspective): the
  second image is the first warped by H; a match (ratio 0.8, cross-check) is correct when H maps
  the first keypoint within 3 px of the second. Both run the same matching rule. misslam runs
  with its learned tests (rBRIEF, the default) and with steered BRIEF's Gaussian tests, and with
  OpenCV's detection rule (`none` and no low-threshold retry in empty cells: on weak texture the
  retry adds weaker corners, and matches, that OpenCV does not find).
"""
import argparse, json, os, subprocess, tempfile, time

import cv2
import numpy as np
import skimage.data


def homographies(w, h):
    c = np.array([[1, 0, -w / 2], [0, 1, -h / 2], [0, 0, 1]], float)
    ci = np.linalg.inv(c)
    out = []
    for name, deg, s, persp in [("rot30", 30, 1.0, 0), ("scale1.3", 0, 1.3, 0), ("rot20+scale1.2", 20, 1.2, 0),
                                ("perspective", 10, 1.1, 3e-4)]:
        a = np.radians(deg)
        r = np.array([[s * np.cos(a), -s * np.sin(a), 0], [s * np.sin(a), s * np.cos(a), 0], [persp, 0, 1]])
        out.append((name, ci @ r @ c))
    return out


def precision(pairs, H, tol=3.0):
    if len(pairs) == 0:
        return 0.0, 0
    p = np.asarray(pairs, float)
    a = np.c_[p[:, :2], np.ones(len(p))] @ H.T
    a = a[:, :2] / a[:, 2:]
    ok = np.hypot(*(a - p[:, 2:4]).T) <= tol
    return float(ok.mean()), len(p)


def cv_match(da, db):
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    fwd = bf.knnMatch(da, db, k=2)
    back = {m[0].queryIdx: m[0].trainIdx for m in bf.knnMatch(db, da, k=1) if m}
    return [m[0] for m in fwd if len(m) == 2 and m[0].distance < 0.8 * m[1].distance
            and m[0].distance <= 64 and back.get(m[0].trainIdx) == m[0].queryIdx]


def misslam(exe, a, b=None, n=1000, dist="quadtree", repeat=20, pattern="learned", retry=True, threads=1):
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "r.json")
        cmd = [exe, "bench", "features", "--image", a, "--n-features", str(n), "--distribution", dist,
               "--pattern", pattern, "--repeat", str(repeat), "--out", out]
        if not retry:
            cmd += ["--min-fast-threshold", "0"]
        if b:
            cmd += ["--image2", b]
        subprocess.run(cmd, check=True, capture_output=True,
                       env=dict(os.environ, RAYON_NUM_THREADS=str(threads)))
        return json.load(open(out))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--misslam", default="target/debug/misslam")
    ap.add_argument("--json", help="also write the rows here")
    ap.add_argument("--rounds", type=int, default=5,
                    help="ORB timing rounds, OpenCV and misslam in turns (the ratio is taken per round)")
    ap.add_argument("--image", action="append", default=[],
                    help="also run on this image (gray, resized to 640x480); repeatable")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    imgs = {
        "astronaut": cv2.cvtColor(skimage.data.astronaut(), cv2.COLOR_RGB2GRAY),
        "motorcycle": cv2.cvtColor(skimage.data.stereo_motorcycle()[0], cv2.COLOR_RGB2GRAY),
    }
    for path in args.image:
        img = cv2.imread(path, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SystemExit(f"{path}: not an image")
        imgs[os.path.basename(os.path.dirname(os.path.dirname(path))) + "/" + os.path.basename(path)] = img
    rows = []
    with tempfile.TemporaryDirectory() as d:
        for name, img in imgs.items():
            img = cv2.resize(img, (640, 480), interpolation=cv2.INTER_AREA)
            pa = os.path.join(d, f"{name.replace('/', '_')}.png")
            cv2.imwrite(pa, img)
            orb = cv2.ORB_create(1000)
            # OpenCV and misslam (its default) in turns: the ratio within each round.
            cv_rounds, our_rounds = [], []
            for _ in range(args.rounds):
                ts = []
                for _ in range(20):
                    t = time.perf_counter()
                    ka, da = orb.detectAndCompute(img, None)
                    ts.append(1e3 * (time.perf_counter() - t))
                cv_rounds.append(float(np.median(ts)))
                our_rounds.append(misslam(args.misslam, pa, dist="quadtree"))
            ratios = [c / o["orb_ms"] for c, o in zip(cv_rounds, our_rounds)]
            mid = int(np.argsort(ratios)[len(ratios) // 2])
            cv_ms = cv_rounds[mid]
            ours = {"quadtree": our_rounds[mid], "none": misslam(args.misslam, pa, dist="none")}
            ours["rule"] = misslam(args.misslam, pa, dist="none", retry=False)
            ours["2t"] = misslam(args.misslam, pa, threads=2)
            row = dict(image=name, opencv_orb_ms=cv_ms, opencv_keypoints=len(ka),
                       misslam_orb_ms=ours["quadtree"]["orb_ms"], misslam_keypoints=ours["quadtree"]["keypoints"],
                       misslam_orb_none_ms=ours["none"]["orb_ms"],
                       misslam_orb_opencv_rule_ms=ours["rule"]["orb_ms"],
                       misslam_opencv_rule_keypoints=ours["rule"]["keypoints"],
                       misslam_orb_2_threads_ms=ours["2t"]["orb_ms"],
                       ratio=float(np.median(ratios)), ratio_min=min(ratios), ratio_max=max(ratios),
                       rounds=args.rounds)
            rows.append(row)
            print(f"ORB 1000 kp {name}: OpenCV {cv_ms:.2f} ms ({len(ka)} kp), misslam {row['misslam_orb_ms']:.2f} ms "
                  f"({row['misslam_keypoints']} kp; none: {row['misslam_orb_none_ms']:.2f}; OpenCV's rule: "
                  f"{row['misslam_orb_opencv_rule_ms']:.2f} ms, {row['misslam_opencv_rule_keypoints']} kp) "
                  f"-> x{row['ratio']:.2f} (the median round of {args.rounds}; rounds x{row['ratio_min']:.2f} "
                  f"to x{row['ratio_max']:.2f}); misslam on 2 threads {row['misslam_orb_2_threads_ms']:.2f} ms")
            # 2000 x 2000 Hamming kNN: descriptors of this image against those of a warped copy.
            H = homographies(640, 480)[0][1]
            wb = cv2.warpPerspective(img, H, (640, 480))
            pb = os.path.join(d, f"{name.replace('/', '_')}_warp.png")
            cv2.imwrite(pb, wb)
            o2 = cv2.ORB_create(2000)
            _, d1 = o2.detectAndCompute(img, None)
            _, d2 = o2.detectAndCompute(wb, None)
            bf = cv2.BFMatcher(cv2.NORM_HAMMING)
            ts = []
            for _ in range(5):
                t = time.perf_counter()
                bf.knnMatch(d1, d2, k=2)
                ts.append(1e3 * (time.perf_counter() - t))
            cv_knn = float(np.median(ts))
            r = misslam(args.misslam, pa, pb, n=2000, dist="none", repeat=5)
            print(f"Hamming 2-NN {len(d1)}x{len(d2)}: OpenCV BFMatcher {cv_knn:.2f} ms; misslam "
                  f"{r['keypoints']}x{r['keypoints2']} {r['knn_ms']:.2f} ms -> x{cv_knn / r['knn_ms']:.2f}")
            rows.append(dict(image=name, opencv_knn_ms=cv_knn, misslam_knn_ms=r["knn_ms"],
                             n_cv=[len(d1), len(d2)], n_ours=[r["keypoints"], r["keypoints2"]]))
            for hname, H in homographies(640, 480):
                wb = cv2.warpPerspective(img, H, (640, 480))
                cv2.imwrite(pb, wb)
                kb, db = orb.detectAndCompute(wb, None)
                m = cv_match(da, db)
                cv_p, cv_n = precision([[*ka[x.queryIdx].pt, *kb[x.trainIdx].pt] for x in m], H)
                res = {}
                for key, dist, pattern, retry in [("none", "none", "learned", True),
                                                  ("quadtree", "quadtree", "learned", True),
                                                  ("none_gaussian", "none", "gaussian", True),
                                                  ("opencv_rule", "none", "learned", False)]:
                    r = misslam(args.misslam, pa, pb, n=1000, dist=dist, repeat=1, pattern=pattern, retry=retry)
                    res[key] = precision(r["matches"], H)
                fmt = lambda k: f"{res[k][0]:.3f} ({res[k][1]})"
                print(f"  {hname:<15} precision (matches): OpenCV {cv_p:.3f} ({cv_n}), misslam none "
                      f"{fmt('none')}, quadtree {fmt('quadtree')}; steered BRIEF, none {fmt('none_gaussian')}; "
                      f"OpenCV's rule (none, no retry) {fmt('opencv_rule')}")
                rows.append(dict(image=name, warp=hname, opencv_precision=cv_p, opencv_matches=cv_n,
                                 misslam_none_precision=res["none"][0], misslam_none_matches=res["none"][1],
                                 misslam_quadtree_precision=res["quadtree"][0],
                                 misslam_quadtree_matches=res["quadtree"][1],
                                 misslam_none_gaussian_precision=res["none_gaussian"][0],
                                 misslam_none_gaussian_matches=res["none_gaussian"][1],
                                 misslam_opencv_rule_precision=res["opencv_rule"][0],
                                 misslam_opencv_rule_matches=res["opencv_rule"][1]))
    if args.json:
        json.dump(rows, open(args.json, "w"), indent=1)


if __name__ == "__main__":
    main()
