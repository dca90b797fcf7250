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
    var v: array<f32, 9>;
    var n = 0u;
    for (var dy = -1; dy <= 1; dy = dy + 1) {
        for (var dx = -1; dx <= 1; dx = dx + 1) {
            let xx = i32(gid.x) + dx;
            let yy = i32(gid.y) + dy;
            if (xx >= 0 && yy >= 0 && xx < w && yy < h) {
                let q = src[u32(yy * w + xx)];
                if (q != INVALID) {
                    // Insertion into the sorted prefix.
                    var j = n;
                    while (j > 0u && v[j - 1u] > q) {
                        v[j] = v[j - 1u];
                        j = j - 1u;
                    }
                    v[j] = q;
                    n = n + 1u;
                }
            }
        }
    }
    dst[i] = v[n / 2u];
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
