#!/usr/bin/env bash
# Issue 7's GPU-machine check in one call: the main graph's frame rate, binaries taken in turns.
#
# Each variant runs `graphs/mis_slam.toml` with its scoring at 640x480 (focal 700 px, 96
# disparities), GPU depth, the levels pipelined (3 frames in flight) and the frames rendered
# into memory first (as a camera delivers them), for ROUNDS rounds in turns (A B A B ...). Every
# run prints a line: frames a second (1000 / the median time between frames), the medians of
# fusion, its solve and factorisation, post-processing and the two scoring nodes, and
# recon.mean_mm. A table of each variant's medians over its rounds ends the output; with $OUT set
# (the device tool's folder that comes back) the lines and each run's metrics.json go there too.
#
#   benches/device_ab.sh ROUNDS NAME=BINARY[@KEY=VALUE,KEY=VALUE...] ...
#
# BINARY may be gzipped (`.gz`); `@...` adds `--set` overrides for that variant only, e.g.
#   benches/device_ab.sh 3 base=.dev/base.gz new=.dev/new.gz \
#       nice=.dev/new.gz@recon.nice=10,recon_world.nice=10,export.nice=10 \
#       gpupost=.dev/new.gz@post.device=gpu
# FRAMES (default 150) and EXTRA (more `--set` arguments for every variant) are read from the
# environment; with BENCH=1 the last variant's binary first runs `misslam bench sgm-gpu` and
# `misslam bench post-gpu` (the GPU stages alone against their CPU paths, with the adapter's
# name), into $OUT/bench-*.txt and .json too.
#
# The lent machines have no Rust toolchain and no network. Prepare on this machine:
#   cargo build && strip -o .dev/new "$CARGO_TARGET_DIR/debug/misslam" && gzip -9f .dev/new
#   (the baseline likewise, built in a `git worktree` at its commit; two stripped binaries do
#   not fit the device tool's 64 MiB unzipped), and the Vulkan loader's .deb files in .gl/ (the
#   device tool's README gives the recipe). Both folders stay out of git (.git/info/exclude).
# On the machine, with `carry` [".gl", ".dev"]:
#   for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig; benches/device_ab.sh 3 base=... new=...
set -euo pipefail
cd "$(dirname "$0")/.."

rounds="${1:?usage: benches/device_ab.sh ROUNDS NAME=BINARY[@KEY=VALUE,...] ...}"
shift
[ "$#" -ge 1 ] || { echo "name at least one variant: NAME=BINARY" >&2; exit 2; }
case "$rounds" in '' | *[!0-9]*) echo "ROUNDS must be a whole number, got '$rounds'" >&2; exit 2 ;; esac
frames="${FRAMES:-150}"
work="$(mktemp -d)"
out="${OUT:-$work/out}"
mkdir -p "$out"
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-$work}"

names=()
for spec in "$@"; do
    name="${spec%%=*}"
    rest="${spec#*=}"
    bin="${rest%%@*}"
    sets=""
    [ "$rest" != "$bin" ] && sets="${rest#*@}"
    case "$name" in '' | *[!A-Za-z0-9_-]*) echo "variant name '$name': letters, digits, _ and - only" >&2; exit 2 ;; esac
    [ -f "$bin" ] || { echo "variant $name: no binary at '$bin'" >&2; exit 2; }
    if [ "${bin%.gz}" != "$bin" ]; then
        gzip -dc "$bin" > "$work/$name.bin"
    else
        cp "$bin" "$work/$name.bin"
    fi
    chmod +x "$work/$name.bin"
    echo "$sets" > "$work/$name.sets"
    names+=("$name")
done

if [ "${BENCH:-0}" = 1 ]; then
    last="${names[${#names[@]} - 1]}"
    for b in sgm-gpu post-gpu; do
        echo "== $last: misslam bench $b" | tee "$out/bench-$b.txt"
        "$work/$last.bin" bench "$b" --repeat 20 --out "$out/bench-$b.json" 2>&1 \
            | grep -v ' INFO ' | tee -a "$out/bench-$b.txt"
    done
fi

for ((r = 1; r <= rounds; r++)); do
    for name in "${names[@]}"; do
        args=()
        IFS=',' read -r -a extra_sets <<< "$(cat "$work/$name.sets")"
        for s in "${extra_sets[@]}"; do [ -n "$s" ] && args+=(--set "$s"); done
        # shellcheck disable=SC2206
        [ -n "${EXTRA:-}" ] && args+=(${EXTRA})
        run="$work/$name-$r"
        if ! "$work/$name.bin" run graphs/mis_slam.toml --frames "$frames" \
            --set src.width=640 --set src.height=480 --set src.focal_px=700 \
            --set depth.max_disparity=96 --set depth.device=gpu --set graph.pipeline=3 \
            --set src.prerender_frames="$frames" "${args[@]}" --out "$run" > "$run.log" 2>&1; then
            echo "$name round $r failed; the end of its log:" >&2
            tail -n 20 "$run.log" >&2
            exit 1
        fi
        cp "$run/metrics.json" "$out/$name-$r.json"
        python3 - "$name" "$r" "$run/metrics.json" <<'EOF' | tee -a "$out/runs.txt"
import json, sys
name, r, path = sys.argv[1:]
m = json.load(open(path))
t = m["timing_ms"]
med = lambda k: t[k]["median_ms"] if k in t else float("nan")
print(f"{name:>10} round {r}: {1000 / med('_interval'):6.1f} fps  fusion {med('fusion'):6.2f}  "
      f"solve {med('fusion.solve'):5.2f}  factor {med('fusion.solve.factor'):5.2f}  "
      f"post {med('post'):5.2f}  recon {med('recon'):5.2f}  recon_world {med('recon_world'):5.2f} ms  "
      f"recon.mean_mm {m['eval'].get('recon.mean_mm', float('nan')):.6f}")
EOF
    done
done

python3 - "$out" "$rounds" "${names[@]}" <<'EOF' | tee "$out/summary.txt"
import json, statistics, sys
out, rounds, names = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
keys = ["_interval", "fusion", "fusion.solve", "fusion.solve.factor", "post", "recon", "recon_world"]
print("variant     rounds  fps (each round)               " + "  ".join(k for k in keys[1:]) + "  (medians over rounds, ms)")
for name in names:
    # This call's rounds only (an $OUT used before may hold other runs' files).
    runs = [json.load(open(f"{out}/{name}-{r}.json")) for r in range(1, rounds + 1)]
    fps = [1000 / r["timing_ms"]["_interval"]["median_ms"] for r in runs]
    cols = [statistics.median(r["timing_ms"][k]["median_ms"] for r in runs if k in r["timing_ms"]) for k in keys[1:]]
    print(f"{name:<10} {len(runs):>6}  {', '.join(f'{f:.1f}' for f in fps):<30} " + "  ".join(f"{c:.2f}" for c in cols))
EOF
