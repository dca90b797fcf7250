// SGM step 3: winner-takes-all per left pixel with the uniqueness margin and the sub-pixel
// parabola, then the left-right check against the right image's winner
// argmin_d S(y, xr + d + dmin, d) at xr = round(x - disparity). One invocation per pixel.
// CPU reference: the selection of misslam_depth_sgm::reference and `finish`'s left-right check
// (same integers; the parabola's f32 division is the only operation WGSL may round differently).

struct Params {
    width: u32,
    height: u32,
    disparities: u32,
    min_disparity: i32,
    uniqueness_pct: u32,
    subpixel: u32,
    lr_check: u32,
    lr_max_diff: f32,
}

// Marks an invalid pixel (NaN on the host).
const INVALID: f32 = -3.0e38;
const NONE: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> sums: array<u32>;
// 1 where the pixel may get a disparity.
@group(0) @binding(2) var<storage, read> mask: array<u32>;
@group(0) @binding(3) var<storage, read_write> disparity: array<f32>;

// Winner of right pixel (xr, y): the smallest d with the least S(y, xr + d + dmin, d), or NONE.
fn right_winner(xr: i32, y: u32) -> u32 {
    let w = i32(params.width);
    let nd = params.disparities;
    var best = NONE;
    var bd = NONE;
    for (var d = 0u; d < nd; d = d + 1u) {
        let x = xr + i32(d) + params.min_disparity;
        if (x < 0 || x >= w) {
            continue;
        }
        let v = sums[(y * params.width + u32(x)) * nd + d];
        if (v < best) {
            best = v;
            bd = d;
        }
    }
    return bd;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    if (gid.x >= w || gid.y >= params.height) {
        return;
    }
    let i = gid.y * w + gid.x;
    let nd = params.disparities;
    var out = INVALID;
    if (mask[i] != 0u) {
        var best = NONE;
        var bd = 0u;
        for (var d = 0u; d < nd; d = d + 1u) {
            let v = sums[i * nd + d];
            if (v < best) {
                best = v;
                bd = d;
            }
        }
        var second = 65535u;
        for (var d = 0u; d < nd; d = d + 1u) {
            if (d + 1u < bd || d > bd + 1u) {
                second = min(second, sums[i * nd + d]);
            }
        }
        if (best * (100u + params.uniqueness_pct) <= second * 100u) {
            var disp = f32(bd);
            if (params.subpixel != 0u && bd > 0u && bd + 1u < nd) {
                let a = f32(sums[i * nd + bd - 1u]);
                let b = f32(sums[i * nd + bd]);
                let c = f32(sums[i * nd + bd + 1u]);
                let den = a - 2.0 * b + c;
                if (den > 0.0) {
                    disp = disp + 0.5 * (a - c) / den;
                }
            }
            out = disp + f32(params.min_disparity);
        }
    }
    if (out != INVALID && params.lr_check != 0u) {
        // Rust's f32::round: half away from zero; -0.5 and below leave the image.
        let r = f32(gid.x) - out;
        if (r <= -0.5) {
            out = INVALID;
        } else {
            let xr = i32(floor(r + 0.5));
            if (xr >= i32(w)) {
                out = INVALID;
            } else {
                let dr = right_winner(xr, gid.y);
                if (dr == NONE || abs(f32(dr) + f32(params.min_disparity) - out) > params.lr_max_diff) {
                    out = INVALID;
                }
            }
        }
    }
    disparity[i] = out;
}
