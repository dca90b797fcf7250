// SGM step 4: 3x3 median over the valid neighbours of each valid pixel (the middle element,
// index n / 2, of the sorted valid values). CPU reference: misslam_depth_sgm::sgm::median3.

struct Params {
    width: u32,
    height: u32,
    pad0: u32,
    pad1: u32,
}

const INVALID: f32 = -3.0e38;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;

// Above every disparity: where a neighbour is invalid or outside the image.
const ABSENT: f32 = 3.0e38;

// Sorts (a, b) in place.
fn exchange(a: ptr<function, f32>, b: ptr<function, f32>) {
    let lo = min(*a, *b);
    *b = max(*a, *b);
    *a = lo;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = i32(params.width);
    let h = i32(params.height);
    if (gid.x >= params.width || gid.y >= params.height) {
        return;
    }
    let i = gid.y * params.width + gid.x;
    if (src[i] == INVALID) {
        dst[i] = INVALID;
        return;
    }
    // The window in registers, ABSENT where no valid value: sorted by a network of 25
    // exchanges, the valid values come first, in order, and the median is the n / 2-th.
    var v0 = ABSENT;
    var v1 = ABSENT;
    var v2 = ABSENT;
    var v3 = ABSENT;
    var v4 = ABSENT;
    var v5 = ABSENT;
    var v6 = ABSENT;
    var v7 = ABSENT;
    var v8 = ABSENT;
    var n = 0u;
    for (var k = 0; k < 9; k = k + 1) {
        let xx = i32(gid.x) + k % 3 - 1;
        let yy = i32(gid.y) + k / 3 - 1;
        var q = ABSENT;
        if (xx >= 0 && yy >= 0 && xx < w && yy < h) {
            q = src[u32(yy * w + xx)];
            if (q == INVALID) {
                q = ABSENT;
            }
        }
        n = n + u32(q != ABSENT);
        switch k {
            case 0: { v0 = q; }
            case 1: { v1 = q; }
            case 2: { v2 = q; }
            case 3: { v3 = q; }
            case 4: { v4 = q; }
            case 5: { v5 = q; }
            case 6: { v6 = q; }
            case 7: { v7 = q; }
            default: { v8 = q; }
        }
    }
    exchange(&v0, &v3); exchange(&v1, &v7); exchange(&v2, &v5); exchange(&v4, &v8);
    exchange(&v0, &v7); exchange(&v2, &v4); exchange(&v3, &v8); exchange(&v5, &v6);
    exchange(&v0, &v2); exchange(&v1, &v3); exchange(&v4, &v5); exchange(&v7, &v8);
    exchange(&v1, &v4); exchange(&v3, &v6); exchange(&v5, &v7);
    exchange(&v0, &v1); exchange(&v2, &v4); exchange(&v3, &v5); exchange(&v6, &v8);
    exchange(&v2, &v3); exchange(&v4, &v5); exchange(&v6, &v7);
    exchange(&v1, &v2); exchange(&v3, &v4); exchange(&v5, &v6);
    var m = v0;
    switch n / 2u {
        case 0u: { m = v0; }
        case 1u: { m = v1; }
        case 2u: { m = v2; }
        case 3u: { m = v3; }
        default: { m = v4; }
    }
    dst[i] = m;
}

// The final map for the host (entry point `finish`, after the median and the speckles, over
// 8x8 tiles): the disparity's bits, or a quiet NaN's where it is invalid, so the host's
// readback is a plain copy.
@group(0) @binding(3) var<storage, read_write> bits: array<u32>;

@compute @workgroup_size(8, 8, 1)
fn finish(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= params.width || gid.y >= params.height) {
        return;
    }
    let i = gid.y * params.width + gid.x;
    let v = src[i];
    bits[i] = select(bitcast<u32>(v), 0x7fc00000u, v == INVALID);
}
