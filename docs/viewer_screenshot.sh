#!/usr/bin/env bash
# Regenerates docs/viewer.jpg, the README's picture of a run in the Rerun viewer: 60 frames of
# graphs/mis_slam.toml on the built-in phantom, recorded, trimmed to the entities shown, opened with
# a fixed layout and captured by the viewer itself (`--screenshot-to`). Headless machines need
# Xvfb and a Vulkan driver (Debian: xvfb mesa-vulkan-drivers libvulkan1), and ImageMagick.
#
#   docs/viewer_screenshot.sh [VENV]   # VENV: a venv with rerun-sdk==0.36.3 (default .venv)
set -euo pipefail
cd "$(dirname "$0")/.."
venv=${1:-.venv}
work=$(mktemp -d)
trap 'kill ${warp:-} ${xvfb:-} 2>/dev/null; rm -rf "$work"' EXIT
cargo run --quiet -- run graphs/mis_slam.toml --quiet --frames 60 --out "$work/out" \
    --rerun "save:$work/full.rrd"
# Only what the layout shows: the viewer then loads every frame before it takes the picture.
drop=()
for e in /src/depth_gt /src/disparity_gt /src/mesh_gt /src/mesh_rest /src/rest_points_gt \
    /src/right /src/left /src/stereo/right /depth/disparity /depth/depth /post/depth \
    /post/normals /post/vertices /recon_world/colored /features/features \
    /features/features/points3d /features/stereo_matches /fusion/graph/edges /track/matches \
    /track/matches/train_points /src/pose_gt /src/pose_gt_trajectory /fusion/pose \
    /fusion/pose_trajectory; do
    drop+=(--drop-entity "$e")
done
"$venv/bin/rerun" rrd filter "${drop[@]}" "$work/full.rrd" -o "$work/shown.rrd"
"$venv/bin/python" - "$work/layout.rbl" <<'PY'
import sys
import rerun.blueprint as rrb

def eye(position, target):
    return rrb.EyeControls3D(position=position, look_target=target, eye_up=[0.0, -1.0, 0.0])

rrb.Blueprint(
    rrb.Horizontal(
        rrb.Vertical(
            rrb.Spatial3DView(
                name="surfel model and ED nodes (world frame)",
                contents=["/fusion/model", "/fusion/graph/nodes"],
                eye_controls=eye([45.0, -55.0, 20.0], [0.0, -12.0, 78.0]),
            ),
            rrb.Spatial3DView(
                name="distance to the true surface (scope frame)",
                contents=["/recon/colored"],
                eye_controls=eye([35.0, -40.0, -10.0], [0.0, 0.0, 70.0]),
            ),
            row_shares=[3, 2],
        ),
        rrb.Vertical(
            rrb.Spatial2DView(name="left image", origin="/src/stereo/left"),
            rrb.TimeSeriesView(name="reconstruction error (mm)", origin="/recon/metrics"),
            rrb.TimeSeriesView(name="ED solve (ms)", origin="/fusion/info",
                               contents=["/fusion/info/fusion.solve_ms"]),
        ),
        column_shares=[3, 2],
    ),
    rrb.TimePanel(timeline="frame", state="collapsed", play_state="following"),
    collapse_panels=True,
).save("misslam", sys.argv[1])
PY
warp=""
if [ -z "${DISPLAY:-}" ]; then
    Xvfb :93 -screen 0 1600x1000x24 >/dev/null 2>&1 &
    xvfb=$!
    export DISPLAY=:93
    mkdir -p "$work/xdg" && chmod 700 "$work/xdg"
    export XDG_RUNTIME_DIR="$work/xdg"
    sleep 2
    # On this private screen only: keep the pointer in the bottom-right corner, where it hovers
    # over nothing (the window takes the whole screen, and a hover tooltip would be captured).
    python3 -c "
import ctypes, time
x = ctypes.CDLL('libX11.so.6')
x.XOpenDisplay.restype = ctypes.c_void_p
d = ctypes.c_void_p(x.XOpenDisplay(None))
x.XDefaultRootWindow.restype = ctypes.c_ulong
r = ctypes.c_ulong(x.XDefaultRootWindow(d))
for _ in range(240):
    x.XWarpPointer(d, 0, r, 0, 0, 0, 0, 1599, 999)
    x.XFlush(d)
    time.sleep(0.25)
" &
    warp=$!
fi
# The viewer exits non-zero after `--screenshot-to`; the picture's presence is the check.
"$venv/bin/rerun" "$work/shown.rrd" "$work/layout.rbl" \
    --window-size 1600x1000 --screenshot-to "$work/shot.png" >"$work/viewer.log" 2>&1 || true
[ -z "$warp" ] || kill "$warp" 2>/dev/null || true
if ! [ -s "$work/shot.png" ]; then
    echo "the viewer wrote no picture; its log:" >&2
    cat "$work/viewer.log" >&2
    exit 1
fi
convert "$work/shot.png" -resize 1200x -quality 88 docs/viewer.jpg
echo "docs/viewer.jpg"
