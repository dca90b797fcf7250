// ELAS step 5, dense matching (Geiger, Roser and Urtasun, ACCV 2010): the maximum a-posteriori
// disparity of every pixel inside the triangulation, for the left image (z = 0) and the right
// image (z = 1) in one dispatch, one invocation per pixel.
// CPU reference: misslam_depth_elas::dense::Matcher::pixel, which this reproduces to the integer:
// the energy of d is the SAD of the two 16-byte descriptors, plus the prior table at |d - dp| for
// the plane's window when the triangle gives a valid prior; the candidates are the grid cell's
// disparities (ascending, those inside the plane's window skipped), then the window ascending;
// the first strictly smaller energy wins. Optional sub-pixel refinement by the equiangular fit of
// the energies at d - 1, d, d + 1 (the only floating-point step: one division).
// The host rasterises the triangles (libelas's scan, the last triangle drawn wins) into `plan`:
// per pixel 0xffffffff outside every triangle, else bits 0-15 the plane's rounded disparity dp
// plus 32768 (clamped just outside the disparity range, which changes nothing), bit 16 a plane,
// bit 17 a valid prior.

struct Params {
    width: u32,
    height: u32,
    grid_size: u32,
    grid_w: u32,
    grid_h: u32,
    disp_min: i32,
    disp_max: i32,
    radius: i32,
    match_texture: u32,
    subpixel: u32,
    // Cells of one image's grid.
    cells: u32,
    pad: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// 16-byte descriptors, four bytes per word: the left image's pixels, then the right's.
@group(0) @binding(1) var<storage, read> desc: array<vec4<u32>>;
// Per pixel of the left, then of the right image, column-major (u * height + v): the host's
// raster (see above), which walks columns.
@group(0) @binding(2) var<storage, read> plan: array<u32>;
// Candidate ranges per cell: `cells + 1` offsets into `cands` for the left grid, then the right.
@group(0) @binding(3) var<storage, read> offsets: array<u32>;
@group(0) @binding(4) var<storage, read> cands: array<u32>;
// The prior P[|d - dp|], SAD units, for |d - dp| <= radius.
@group(0) @binding(5) var<storage, read> prior: array<i32>;
// Disparity bits (f32, NaN where none) of the left, then of the right image.
@group(0) @binding(6) var<storage, read_write> out: array<u32>;

const WINDOW: i32 = 2;
const OUTSIDE: u32 = 0xffffffffu;
const NAN_BITS: u32 = 0x7fc00000u;
const NONE: i32 = 0x7fffffff;

fn sad4(a: u32, b: u32) -> u32 {
    let x = unpack4xU8(a);
    let y = unpack4xU8(b);
    let d = select(y - x, x - y, x > y);
    return d.x + d.y + d.z + d.w;
}

fn sad(a: vec4<u32>, b: vec4<u32>) -> i32 {
    return i32(sad4(a.x, b.x) + sad4(a.y, b.y) + sad4(a.z, b.z) + sad4(a.w, b.w));
}

// Column of disparity d in the other image, or -1 where the descriptor window leaves it.
fn warp(u: i32, d: i32, right: bool) -> i32 {
    let uw = select(u - d, u + d, right);
    if (uw < WINDOW || uw + WINDOW >= i32(params.width)) {
        return -1;
    }
    return uw;
}

@compute @workgroup_size(64, 1, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.width || gid.y >= params.height) {
        return;
    }
    let u = i32(gid.x);
    let v = gid.y;
    let right = gid.z == 1u;
    let n = params.width * params.height;
    let i = gid.z * n + v * params.width + gid.x;
    out[i] = NAN_BITS;
    let code = plan[gid.z * n + gid.x * params.height + v];
    if (code == OUTSIDE || u < WINDOW || u + WINDOW >= i32(params.width)) {
        return;
    }
    let a = desc[i];
    if (u32(sad(a, vec4<u32>(0x80808080u))) < params.match_texture) {
        return;
    }
    let row = (1u - gid.z) * n + v * params.width;
    let has_plane = (code & 0x10000u) != 0u;
    let valid = (code & 0x20000u) != 0u;
    let dp = i32(code & 0xffffu) - 32768;
    var lo = 1;
    var hi = 0;
    if (has_plane) {
        lo = max(dp - params.radius, params.disp_min);
        hi = min(dp + params.radius, params.disp_max);
    }
    var best_e = NONE;
    var best_d = -1;
    let cell = min(v / params.grid_size, params.grid_h - 1u) * params.grid_w
        + min(gid.x / params.grid_size, params.grid_w - 1u);
    let base = gid.z * (params.cells + 1u) + cell;
    let k1 = offsets[base + 1u];
    for (var k = offsets[base]; k < k1; k = k + 1u) {
        let d = i32(cands[k]);
        if (d >= lo && d <= hi) {
            continue;
        }
        let uw = warp(u, d, right);
        if (uw < 0) {
            continue;
        }
        let e = sad(a, desc[row + u32(uw)]);
        if (e < best_e) {
            best_e = e;
            best_d = d;
        }
    }
    for (var d = lo; d <= hi; d = d + 1) {
        let uw = warp(u, d, right);
        if (uw < 0) {
            continue;
        }
        var e = sad(a, desc[row + u32(uw)]);
        if (valid) {
            e = e + prior[abs(d - dp)];
        }
        if (e < best_e) {
            best_e = e;
            best_d = d;
        }
    }
    if (best_d < 0) {
        return;
    }
    var result = f32(best_d);
    if (params.subpixel != 0u) {
        // The energies at d - 1 and d + 1 (NONE where out of range or off the image).
        var side = array<i32, 2>(NONE, NONE);
        for (var s = 0; s < 2; s = s + 1) {
            let d = best_d - 1 + 2 * s;
            if (d < params.disp_min || d > params.disp_max) {
                continue;
            }
            let uw = warp(u, d, right);
            if (uw < 0) {
                continue;
            }
            var e = sad(a, desc[row + u32(uw)]);
            if (valid && abs(d - dp) <= params.radius) {
                e = e + prior[abs(d - dp)];
            }
            side[s] = e;
        }
        if (side[0] != NONE && side[1] != NONE) {
            let slope = max(side[0] - best_e, side[1] - best_e);
            if (slope > 0) {
                result = f32(best_d) + f32(side[0] - side[1]) / f32(2 * slope);
            }
        }
    }
    out[i] = bitcast<u32>(result);
}
