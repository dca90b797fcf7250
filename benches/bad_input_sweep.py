#!/usr/bin/env python3
"""Bad-input sweep: runs graphs with every numeric parameter set to a bad or extreme value, and
with corrupted meshes and trajectories, and reports each run that panicked, hung or crashed.

A run may refuse the value (exit 1, a message naming the field) or run with it (exit 0: `inf` is
how a distance says "no limit"); anything else is reported. The tests hold the cases this found;
the sweep is for looking again after a change (standard library only; 2 jobs take about 25
minutes for the three fusion graphs on 2 cores).

    python3 benches/bad_input_sweep.py --binary "$CARGO_TARGET_DIR/debug/misslam" \\
        --graphs mis_slam,robocentric_surf,template_dff
    python3 benches/bad_input_sweep.py --binary ... --files ../shared/data/heart --mutations 100

Parameters: each numeric leaf of the graph's resolved parameters (`metrics.json`'s `params`) is
set by `--set` to 0, -1 and 2^32 + 1 (integers) or 0, -1, nan, inf and 1e12 (reals), and the graph
runs a few frames at 160x120. Files (`--files DIR` holding `heart.obj` and
`heart_trajectory.npy`): each is truncated or has bytes or tokens replaced, and given to
`graphs/template_dff.toml` as the phantom's mesh or trajectory; a template mesh in PLY and glb
is taken from a short run's export and given as `fusion.template_path`.
"""
import argparse
import concurrent.futures as cf
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile

SMALL = ["--set", "src.width=160", "--set", "src.height=120", "--set", "src.focal_px=175"]
INT_VALUES = ["0", "-1", "4294967297"]
REAL_VALUES = ["0.0", "-1.0", "nan", "inf", "1e12"]


def run(binary, repo, graph, sets, out, frames, timeout, small=True):
    cmd = [binary, "run", graph, "--frames", str(frames), *(SMALL if small else [])]
    for s in sets:
        cmd += ["--set", s]
    cmd += ["--out", out]
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=repo)
        rc, text = r.returncode, r.stdout + r.stderr
    except subprocess.TimeoutExpired:
        rc, text = "timeout", ""
    shutil.rmtree(out, ignore_errors=True)
    errors = [line for line in text.splitlines() if "error" in line.lower()]
    panicked = "panicked" in text
    bad = rc == "timeout" or rc not in (0, 1) or panicked
    return {"rc": rc, "bad": bad, "panicked": panicked, "last_error": errors[-1][-300:] if errors else ""}


def leaves(params):
    out = []

    def walk(path, v):
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{path}.{k}" if path else k, x)
        elif isinstance(v, bool) or v is None or isinstance(v, str):
            return
        elif isinstance(v, int):
            out.extend((path, x) for x in INT_VALUES)
        elif isinstance(v, float):
            out.extend((path, x) for x in REAL_VALUES)

    walk("", params)
    return out


def mutate(data, text, rng):
    if rng.random() < 0.3:
        return data[: rng.randrange(max(len(data), 1))]
    if text and rng.random() < 0.6:
        lines = data.decode(errors="replace").split("\n")
        i = rng.randrange(len(lines))
        tokens = lines[i].split()
        if len(tokens) > 1:
            tokens[rng.randrange(1, len(tokens))] = rng.choice(
                ["nan", "-1", "0", "999999", "1e400", "inf", "x", "1/2/3/4", "-99999"]
            )
            lines[i] = " ".join(tokens)
        return "\n".join(lines).encode()
    b = bytearray(data)
    for _ in range(rng.randint(1, 10)):
        head = rng.random() < 0.7
        b[rng.randrange(min(len(b), 4000) if head else len(b))] = rng.randrange(256)
    return bytes(b)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--binary", required=True, help="the misslam binary")
    ap.add_argument("--graphs", default="", help="comma-separated graph names in graphs/")
    ap.add_argument("--files", help="a folder with heart.obj and heart_trajectory.npy")
    ap.add_argument("--mutations", type=int, default=60, help="corrupted copies per file")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds a run may take")
    args = ap.parse_args()
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    binary = os.path.abspath(args.binary)
    work = tempfile.mkdtemp(prefix="misslam-sweep-")
    jobs = []
    for g in filter(None, args.graphs.split(",")):
        base = os.path.join(work, f"base-{g}")
        graph = f"graphs/{g}.toml"
        # Phantom graphs run small; a stereo folder's at its own size.
        for small in (True, False):
            cmd = [binary, "run", graph, "--frames", "2", *(SMALL if small else []), "--out", base]
            if subprocess.run(cmd, capture_output=True, cwd=repo).returncode == 0:
                break
        else:
            sys.exit(f"{graph} does not run as it is")
        params = json.load(open(os.path.join(base, "metrics.json")))["params"]
        shutil.rmtree(base, ignore_errors=True)
        jobs += [(graph, [f"{p}={v}"], f"{g} {p}={v}", small) for p, v in leaves(params)]
    if args.files:
        rng = random.Random(43)
        files = os.path.abspath(args.files)
        obj, npy = os.path.join(files, "heart.obj"), os.path.join(files, "heart_trajectory.npy")
        export = os.path.join(work, "export-run")
        subprocess.run(
            [binary, "run", "graphs/template_dff.toml", "--frames", "2", *SMALL, "--out", export],
            capture_output=True, cwd=repo, check=True,
        )
        sources = {
            "obj": (obj, lambda p: [f'src.mesh="{p}"', "src.distance_mm=120"]),
            "npy": (npy, lambda p: [f'src.mesh="{obj}"', f'src.vertex_trajectory="{p}"',
                                    "src.distance_mm=120", "src.sweep_mm=6"]),
            "ply": (os.path.join(export, "export/mesh/final.ply"), lambda p: [f'fusion.template_path="{p}"']),
            "glb": (os.path.join(export, "export/mesh/final.glb"), lambda p: [f'fusion.template_path="{p}"']),
        }
        for ext, (src, sets) in sources.items():
            good = open(src, "rb").read()
            for n in range(args.mutations):
                path = os.path.join(work, f"bad-{n}.{ext}")
                with open(path, "wb") as f:
                    f.write(mutate(good, ext == "obj", rng))
                jobs.append(("graphs/template_dff.toml", sets(path), f"{ext} #{n}: {path}", True))
    counts = {"refused": 0, "ran": 0, "reported": 0}

    def one(i_job):
        i, (graph, sets, label, small) = i_job
        out = os.path.join(work, f"out-{i}")
        return label, run(binary, repo, graph, sets, out, args.frames, args.timeout, small)

    with cf.ThreadPoolExecutor(args.jobs) as ex:
        for label, r in ex.map(one, enumerate(jobs)):
            if r["bad"]:
                counts["reported"] += 1
                print(f"REPORT {label}: rc {r['rc']}{', panicked' if r['panicked'] else ''} {r['last_error']}", flush=True)
            else:
                counts["refused" if r["rc"] == 1 else "ran"] += 1
    print(f"{len(jobs)} runs: {counts['refused']} refused, {counts['ran']} ran, "
          f"{counts['reported']} reported (kept for a look: {work})")


if __name__ == "__main__":
    main()
