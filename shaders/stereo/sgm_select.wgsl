// SGM step 3: winner-takes-all of the summed directions, one workgroup per image row. Each
// invocation takes the pixels x = t, t + THREADS, ... and walks their disparities once, summing
// the directions' volumes four (u8) or two (u16) disparities per word, and keeps:
// - the winner bd, the smallest d with the least S(x, d);
// - the least S outside bd - 1 ..= bd + 1 (the uniqueness margin), online: when d becomes the
//   winner, the least S of the disparities below d - 1 so far; afterwards every d > bd + 1;
// - S(bd - 1) and S(bd + 1) for the parabola;
// - the right image's winners: S(x, d) is a candidate of right pixel xr = x - d - dmin, kept by an
//   atomic minimum of (S << 11 | d) in workgroup memory, so that the smallest d with the least
//   sum wins as on the CPU.
// After a barrier each invocation applies the left-right check to its pixels.
// CPU reference: the selection of misslam_depth_sgm::reference and `finish`'s left-right check
// (same integers; the parabola's f32 division is the only operation WGSL may round differently).
// The host specialises BYTES (as the aggregation kernel's), DIRS and THREADS. The volumes are
// read 16 bytes at a time; the per-disparity work is a function on a struct (no arrays, so the
// GPU keeps the state in registers).

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

// Sums of the directions' volumes at 16-byte block `at` of every direction, the disparities
// of each word in 16-bit lanes: for bytes (a: lanes 0 and 2, b: lanes 1 and 3), for u16
// (a: lanes 0 and 1). No lane overflows: eight directions of at most 4063 each.
struct Block {
    a: vec4<u32>,
    b: vec4<u32>,
}

fn sum_block(at: u32) -> Block {
    var a = vec4<u32>(0u);
    var b = vec4<u32>(0u);
    for (var r = 0u; r < DIRS; r = r + 1u) {
        let v = volumes[r * (params.volume_words / 4u) + at];
        if (BYTES == 1u) {
            a = a + (v & vec4<u32>(0x00ff00ffu));
            b = b + ((v >> vec4<u32>(8u)) & vec4<u32>(0x00ff00ffu));
        } else {
            a = a + v;
        }
    }
    return Block(a, b);
}

// The online winner-takes-all of one pixel.
struct Wta {
    x: u32,
    best: u32,
    bd: u32,
    // Least S outside bd - 1 ..= bd + 1 so far.
    second: u32,
    // Least S over d' <= d - 2, and S(d - 1).
    below: u32,
    last: u32,
    before_best: u32,
    after_best: u32,
}

// Without branches on the sums (the invocations of a warp visit their pixels' disparities in
// step, and would otherwise take each other's branches); `below` needs no test at d = 0, where
// `last` still holds its initial 65535.
fn visit(s: ptr<function, Wta>, v: u32, d: u32) {
    if (d >= params.disparities) {
        return;
    }
    let better = v < (*s).best;
    (*s).second = select(
        select((*s).second, min((*s).second, v), d > (*s).bd + 1u),
        (*s).below,
        better,
    );
    (*s).before_best = select((*s).before_best, (*s).last, better);
    (*s).best = select((*s).best, v, better);
    (*s).bd = select((*s).bd, d, better);
    (*s).after_best = select((*s).after_best, v, d == (*s).bd + 1u);
    let xr = i32((*s).x) - i32(d) - params.min_disparity;
    if (xr >= 0 && xr < i32(params.width)) {
        atomicMin(&right_key[u32(xr)], (v << 11u) | d);
    }
    (*s).below = min((*s).below, (*s).last);
    (*s).last = v;
}

// The four disparities d .. d + 3 of one word of sums.
fn visit_word(s: ptr<function, Wta>, a: u32, b: u32, d: u32) {
    if (BYTES == 1u) {
        visit(s, a & 0xffffu, d);
        visit(s, b & 0xffffu, d + 1u);
        visit(s, a >> 16u, d + 2u);
        visit(s, b >> 16u, d + 3u);
    } else {
        visit(s, a & 0xffffu, d);
        visit(s, a >> 16u, d + 1u);
    }
}

@compute @workgroup_size(THREADS, 1, 1)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let y = wid.x;
    let w = params.width;
    let t = lid.x;
    let nd = params.disparities;
    // Disparities per word and per 16-byte block.
    let per_word = 4u / BYTES;
    let per_block = 4u * per_word;
    for (var x = t; x < w; x = x + THREADS) {
        atomicStore(&right_key[x], NONE);
    }
    workgroupBarrier();
    for (var x = t; x < w; x = x + THREADS) {
        let i = y * w + x;
        var s = Wta(x, NONE, 0u, 65535u, 65535u, 65535u, 0u, 0u);
        let blocks = (nd + per_block - 1u) / per_block;
        let row = i * params.dp / per_block;
        for (var k = 0u; k < blocks; k = k + 1u) {
            let sum = sum_block(row + k);
            let d = k * per_block;
            visit_word(&s, sum.a.x, sum.b.x, d);
            visit_word(&s, sum.a.y, sum.b.y, d + per_word);
            visit_word(&s, sum.a.z, sum.b.z, d + 2u * per_word);
            visit_word(&s, sum.a.w, sum.b.w, d + 3u * per_word);
        }
        var out = INVALID;
        var allowed = true;
        if (params.masked != 0u) {
            allowed = ((mask[i >> 2u] >> ((i & 3u) * 8u)) & 0xffu) != 0u;
        }
        if (allowed && s.best * (100u + params.uniqueness_pct) <= s.second * 100u) {
            var disp = f32(s.bd);
            if (params.subpixel != 0u && s.bd > 0u && s.bd + 1u < nd) {
                let a = f32(s.before_best);
                let b = f32(s.best);
                let c = f32(s.after_best);
                let den = a - 2.0 * b + c;
                if (den > 0.0) {
                    disp = disp + 0.5 * (a - c) / den;
                }
            }
            out = disp + f32(params.min_disparity);
        }
        disparity[i] = out;
    }
    workgroupBarrier();
    if (params.lr_check == 0u) {
        return;
    }
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
