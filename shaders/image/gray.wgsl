// RGB (interleaved u8) to BT.601 luma in 8-bit fixed point: (77 R + 150 G + 29 B + 128) >> 8.
// CPU reference: misslam_framework::payload::luma_bt601. Each invocation makes 4 gray pixels
// from 12 RGB bytes (3 words) and writes them as one packed word, so no byte addressing is needed.

struct Params {
    pixels: u32,   // number of pixels
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> rgb: array<u32>;
@group(0) @binding(2) var<storage, read_write> gray: array<u32>;

fn byte_at(i: u32) -> u32 {
    return (rgb[i >> 2u] >> ((i & 3u) * 8u)) & 0xffu;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let quad = gid.x;
    let first = quad * 4u;
    if (first >= params.pixels) {
        return;
    }
    var packed = 0u;
    for (var k = 0u; k < 4u; k = k + 1u) {
        let p = first + k;
        if (p < params.pixels) {
            let r = byte_at(p * 3u);
            let g = byte_at(p * 3u + 1u);
            let b = byte_at(p * 3u + 2u);
            let y = (77u * r + 150u * g + 29u * b + 128u) >> 8u;
            packed = packed | (y << (k * 8u));
        }
    }
    gray[quad] = packed;
}
