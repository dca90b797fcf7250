#!/usr/bin/env python3
"""Which prior suits the part of an organ the camera never sees: its seen side's rigid motion
carried to it (the ED graph's as-rigid-as-possible extrapolation, `weights.unseen_motion = 0`), or
no motion (the limit of the fading prior, `weights.unseen_motion > 0`)? An oracle from ground
truth, and a statistic of the seen side alone that might choose between them.

For each sequence, every `--step`-th frame against frame 0:
- seen: the vertices on the true depth of some frame so far (phantoms: the exported GT depth and
  poses; `../shared/data/heart`: a z-buffer seen from -z, as `plugins/deformation/ed/tests/heart.rs`
  places its camera, on the frame of largest motion);
- the seen side's mean motion, and what of it no rigid motion explains (the mean residual of the
  least-squares rigid fit, Kabsch): the "not rigid" share;
- the unseen side's mean error when held still (its true motion) and when carried by the seen
  side's rigid fit.

    python3 benches/unseen_motion_oracle.py --misslam "$CARGO_TARGET_DIR/debug/misslam" \\
        [--scenes heart,liver,kidney,stomach] [--frames 120] [--heart ../shared/data/heart]

Needs numpy. The phantoms are exported as `graphs/template_dff.toml` renders them (sweep, 320x240,
f = 350 px, 2 mm mesh) into a temporary folder.
"""
import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np


def read_ply_points(path):
    data = open(path, "rb").read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode().splitlines()
    n = int(next(line for line in header if line.startswith("element vertex")).split()[2])
    dt = np.dtype([("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)])
    return np.frombuffer(data[end : end + n * dt.itemsize], dtype=dt)["p"].astype(np.float64)


def read_pfm(path):
    data = open(path, "rb").read()
    _, size, scale, rest = data.split(b"\n", 3)
    w, h = map(int, size.split())
    a = np.frombuffer(rest[: w * h * 4], dtype="<f4" if float(scale) < 0 else ">f4")
    return np.flipud(a.reshape(h, w)).astype(np.float64)


def rotation(qx, qy, qz, qw):
    x, y, z, w = qx, qy, qz, qw
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rigid_fit(a, b):
    """R, t minimising sum |R a_i + t - b_i|^2 (Kabsch)."""
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def row(p0, p, seen):
    r, t = rigid_fit(p0[seen], p[seen])
    carried = p0 @ r.T + t
    norm = lambda v: np.linalg.norm(v, axis=1).mean()
    un = ~seen
    return (
        norm(p[seen] - p0[seen]),
        norm(p[seen] - carried[seen]),
        norm(p[un] - p0[un]),
        norm(p[un] - carried[un]),
    )


def report(name, seen_share, rows):
    a = np.array(rows).mean(0)
    verdict = "carried rigidly" if a[3] < a[2] else "held still"
    print(
        f"{name:<12} seen {100 * seen_share:5.1f} %  seen motion {a[0]:.3f} mm, not rigid {a[1]:.3f}"
        f" ({100 * a[1] / a[0]:4.1f} %)  unseen: held still {a[2]:.3f} mm, carried rigidly"
        f" {a[3]:.3f} mm -> {verdict}"
    )


def phantom(binary, scene, frames, step, out):
    subprocess.run(
        [binary, "phantom", "export", "--scene", scene, "--frames", str(frames), "--out", out,
         "--set", "trajectory=sweep", "--set", "width=320", "--set", "height=240",
         "--set", "focal_px=350", "--set", "mesh_step_mm=2.0"],
        check=True, capture_output=True,
    )
    cal = {}
    for line in open(f"{out}/calib.toml"):
        if "=" in line and not line.startswith("#"):
            k, v = line.split("=", 1)
            cal[k.strip()] = float(v)
    fx, fy, cx, cy = cal["fx"], cal["fy"], cal["cx"], cal["cy"]
    w, h = int(cal["width"]), int(cal["height"])
    poses = [list(map(float, line.split())) for line in open(f"{out}/poses_gt.txt")]
    p0 = read_ply_points(f"{out}/mesh_gt/0.ply")
    seen = np.zeros(len(p0), bool)
    rows = []
    for f in range(0, frames, step):
        p = read_ply_points(f"{out}/mesh_gt/{f}.ply")
        t = poses[f]
        pc = (p - np.array(t[1:4])) @ rotation(*t[4:8])
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.round(fx * pc[:, 0] / pc[:, 2] + cx)
            v = np.round(fy * pc[:, 1] / pc[:, 2] + cy)
        ok = (pc[:, 2] > 0) & (u >= 0) & (v >= 0) & (u < w) & (v < h)
        depth = read_pfm(f"{out}/depth_gt/{f}.pfm")
        z = np.full(len(p), np.nan)
        z[ok] = depth[v[ok].astype(int), u[ok].astype(int)]
        seen |= ok & (np.abs(z - pc[:, 2]) < 0.5)
        if f > 0 and (~seen).sum() >= 10:
            rows.append(row(p0, p, seen))
    report(scene, seen.mean(), rows)


def heart_data(folder, cell=6.0, tol=3.0):
    traj = np.load(f"{folder}/heart_trajectory.npy").astype(np.float64)
    p0 = traj[0]
    last = int(np.argmax(np.linalg.norm(traj[1:] - p0, axis=2).sum(1)) + 1)
    # Seen from -z (far away, so near-orthographic): the front-most vertices of each cell.
    p = traj[last]
    key = np.floor(p[:, :2] / cell).astype(np.int64)
    key = key[:, 0] * 1_000_003 + key[:, 1]
    front = {}
    for k, z in zip(key, p[:, 2]):
        front[k] = min(front.get(k, np.inf), z)
    seen = np.array([z <= front[k] + tol for k, z in zip(key, p[:, 2])])
    rows = [row(p0, traj[f], seen) for f in range(1, len(traj))]
    report("heart data", seen.mean(), rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--misslam", required=True, help="the misslam binary")
    ap.add_argument("--scenes", default="heart,liver,kidney,stomach")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--step", type=int, default=4)
    ap.add_argument("--heart", default=os.path.join(os.path.dirname(__file__), "../../shared/data/heart"))
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for scene in filter(None, a.scenes.split(",")):
            phantom(a.misslam, scene, a.frames, a.step, os.path.join(tmp, scene))
    if os.path.exists(f"{a.heart}/heart_trajectory.npy"):
        heart_data(a.heart)
    else:
        print(f"skipped the heart data: no {a.heart}/heart_trajectory.npy", file=sys.stderr)


if __name__ == "__main__":
    main()
