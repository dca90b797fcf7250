// SGM step 1: census transform of the left and the right image (gid.z = 0, 1), one invocation
// per pixel. CPU reference: misslam_depth_sgm::sgm::census. Bit k of the window (row by row, the
// centre skipped) lands at bit n - 1 - k of the 64-bit code, kept as (hi, lo) u32 halves; a
// neighbour outside the image counts as equal to the centre (bit 0).

struct Params {
    width: u32,
    height: u32,
    radius_x: u32,
    radius_y: u32,
    // Word offset of the right image in `images`.
    right_words: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Gray levels, four per word (little-endian): the left image, then the right one from word
// `right_words`.
@group(0) @binding(1) var<storage, read> images: array<u32>;
// (hi, lo) per pixel, left then right.
@group(0) @binding(2) var<storage, read_write> codes: array<vec2<u32>>;

fn gray(image: u32, i: u32) -> u32 {
    let j = image * params.right_words * 4u + i;
    return (images[j >> 2u] >> ((j & 3u) * 8u)) & 0xffu;
}

@compute @workgroup_size(8, 8, 1)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let w = params.width;
    let h = params.height;
    if (gid.x >= w || gid.y >= h) {
        return;
    }
    let c = gray(gid.z, gid.y * w + gid.x);
    let rx = i32(params.radius_x);
    let ry = i32(params.radius_y);
    var hi = 0u;
    var lo = 0u;
    for (var dy = -ry; dy <= ry; dy = dy + 1) {
        for (var dx = -rx; dx <= rx; dx = dx + 1) {
            if (dx == 0 && dy == 0) {
                continue;
            }
            let xx = i32(gid.x) + dx;
            let yy = i32(gid.y) + dy;
            var bit = 0u;
            if (xx >= 0 && yy >= 0 && xx < i32(w) && yy < i32(h)) {
                bit = select(0u, 1u, gray(gid.z, u32(yy) * w + u32(xx)) < c);
            }
            hi = (hi << 1u) | (lo >> 31u);
            lo = (lo << 1u) | bit;
        }
    }
    codes[gid.z * w * h + gid.y * w + gid.x] = vec2<u32>(hi, lo);
}
