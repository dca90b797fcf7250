// SGM step 3, the part both selection kernels share (`sgm_select.wgsl`, one pixel per
// invocation, and `sgm_select_subgroup.wgsl`, one pixel per cluster of subgroup lanes): the
// parameters, the right image's winners in workgroup memory, the output of a pixel from its
// winner and the left-right check.
// The host places a kernel after this file and specialises BYTES (as the aggregation kernel's),
// DIRS and THREADS (invocations per workgroup).

struct Params {
    width: u32,
    height: u32,
    disparities: u32,
    min_disparity: i32,
    uniqueness_pct: u32,
    subpixel: u32,
    lr_check: u32,
    lr_max_diff: f32,
    dirs: u32,
    // Disparities per pixel in the volumes (the aggregation's THREADS * PER).
    dp: u32,
    volume_words: u32,
    // 1 when `mask` holds a mask (four bytes per word), 0 when every pixel may get a disparity.
    masked: u32,
}

// Marks an invalid pixel (NaN on the host).
const INVALID: f32 = -3.0e38;
const NONE: u32 = 0xffffffffu;
const BYTES: u32 = 1u;
const DIRS: u32 = 8u;
const THREADS: u32 = 128u;
// Widest row (the right winners live in workgroup memory).
const MAX_W: u32 = 4096u;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> volumes: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> mask: array<u32>;
@group(0) @binding(3) var<storage, read_write> disparity: array<f32>;

var<workgroup> right_key: array<atomic<u32>, MAX_W>;

// Word `at` of the volumes.
fn volumes_word(at: u32) -> u32 {
    return volumes[at >> 2u][at & 3u];
}

// The four bytes of a word, lowest first.
fn unpack_bytes(v: u32) -> vec4<u32> {
    return (vec4<u32>(v) >> vec4<u32>(0u, 8u, 16u, 24u)) & vec4<u32>(0xffu);
}

// S(x, d) is a candidate of right pixel xr = x - d - dmin: kept by an atomic minimum of
// (S << 11 | d), so that the smallest d with the least sum wins as on the CPU.
fn right_candidate(x: u32, v: u32, d: u32) {
    let xr = i32(x) - i32(d) - params.min_disparity;
    if (xr >= 0 && xr < i32(params.width)) {
        atomicMin(&right_key[u32(xr)], (v << 11u) | d);
    }
}

// The disparity of pixel i (x) from its winner bd with sum `best`, the least sum `second`
// outside bd - 1 ..= bd + 1 and the sums `before` and `after` at bd - 1 and bd + 1: the
// uniqueness test and the parabola, or INVALID (also where the mask forbids the pixel).
fn output(i: u32, best: u32, bd: u32, second: u32, before: u32, after: u32) -> f32 {
    var allowed = true;
    if (params.masked != 0u) {
        allowed = ((mask[i >> 2u] >> ((i & 3u) * 8u)) & 0xffu) != 0u;
    }
    if (!allowed || best * (100u + params.uniqueness_pct) > second * 100u) {
        return INVALID;
    }
    var disp = f32(bd);
    if (params.subpixel != 0u && bd > 0u && bd + 1u < params.disparities) {
        let a = f32(before);
        let b = f32(best);
        let c = f32(after);
        let den = a - 2.0 * b + c;
        if (den > 0.0) {
            disp = disp + 0.5 * (a - c) / den;
        }
    }
    return disp + f32(params.min_disparity);
}

// The left-right check of row y, by invocation t of THREADS, once every right winner is in.
fn lr_check(y: u32, t: u32) {
    let w = params.width;
    for (var x = t; x < w; x = x + THREADS) {
        let i = y * w + x;
        var out = disparity[i];
        if (out == INVALID) {
            continue;
        }
        // Rust's f32::round: half away from zero; -0.5 and below leave the image.
        let r = f32(x) - out;
        if (r <= -0.5) {
            out = INVALID;
        } else {
            let xr = i32(floor(r + 0.5));
            if (xr >= i32(w)) {
                out = INVALID;
            } else {
                let key = atomicLoad(&right_key[u32(xr)]);
                if (key == NONE
                    || abs(f32(key & 0x7ffu) + f32(params.min_disparity) - out) > params.lr_max_diff) {
                    out = INVALID;
                }
            }
        }
        disparity[i] = out;
    }
}

// Marks every right winner of the row as none yet.
fn clear_right(t: u32) {
    for (var x = t; x < params.width; x = x + THREADS) {
        atomicStore(&right_key[x], NONE);
    }
}
