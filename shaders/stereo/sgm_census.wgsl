// SGM step 1: census transform of the left and the right image (gid.z = 0, 1), one invocation
// per pixel, a 16x16 tile per workgroup. CPU reference: misslam_depth_sgm::sgm::census. Bit k
// of the window (row by row, the centre skipped) lands at bit n - 1 - k of the 64-bit code, kept
// as (hi, lo) u32 halves; a neighbour outside the image counts as equal to the centre (bit 0).

struct Params {
    width: u32,
    height: u32,
    radius_x: u32,
    radius_y: u32,
    // Word offset of the right image in `images`.
    right_words: u32,
    // Slots per row of each copy of the right codes (the host's `pair_stride`: the row and a
    // margin of 4 either side, even).
    pair_stride: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> params: Params;
// Gray levels, four per word (little-endian): the left image, then the right one from word
// `right_words`.
@group(0) @binding(1) var<storage, read> images: array<u32>;
// (hi, lo) per pixel of the left image.
@group(0) @binding(2) var<storage, read_write> codes: array<vec2<u32>>;
// The right image's codes, each row twice so that the aggregation reads any four consecutive
// codes as two aligned pairs (vec4): code x of row y at slot y * S + 4 + x of the even copy and
// at slot (h + y) * S + 3 + x of the odd copy (S = `params.pair_stride`; the margins are never
// written).
@group(0) @binding(3) var<storage, read_write> pairs: array<vec2<u32>>;


fn gray(image: u32, i: u32) -> u32 {
    let j = image * params.right_words * 4u + i;
    return (images[j >> 2u] >> ((j & 3u) * 8u)) & 0xffu;
}

// A 16x16 tile of pixels per workgroup; its gray levels and the window's margin are loaded once
// into workgroup memory (each pixel's window reads 62 of them). The widest window the 64-bit
// code holds reaches 10 px each way (21x3 or 3x21).
const TILE: u32 = 16u;
const MAX_RADIUS: u32 = 10u;
const SPAN: u32 = TILE + 2u * MAX_RADIUS;
// Outside the image: never below the centre (bit 0).
const OUTSIDE: u32 = 256u;
var<workgroup> tile: array<u32, SPAN * SPAN>;

@compute @workgroup_size(16, 16, 1)
fn main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
) {
    let w = params.width;
    let h = params.height;
    let rx = params.radius_x;
    let ry = params.radius_y;
    // The tile with its margin: (TILE + 2 rx) x (TILE + 2 ry) gray levels from (x0, y0).
    let tw = TILE + 2u * rx;
    let th = TILE + 2u * ry;
    let x0 = i32(wid.x * TILE) - i32(rx);
    let y0 = i32(wid.y * TILE) - i32(ry);
    for (var k = li; k < tw * th; k = k + TILE * TILE) {
        let xx = x0 + i32(k % tw);
        let yy = y0 + i32(k / tw);
        var g = OUTSIDE;
        if (xx >= 0 && yy >= 0 && xx < i32(w) && yy < i32(h)) {
            g = gray(gid.z, u32(yy) * w + u32(xx));
        }
        tile[k] = g;
    }
    workgroupBarrier();
    if (gid.x >= w || gid.y >= h) {
        return;
    }
    // The pixel's window in the tile: rows ly .. ly + 2 ry, columns lx .. lx + 2 rx.
    let lx = gid.x % TILE;
    let ly = gid.y % TILE;
    let c = tile[(ly + ry) * tw + lx + rx];
    var hi = 0u;
    var lo = 0u;
    for (var dy = 0u; dy <= 2u * ry; dy = dy + 1u) {
        let row = (ly + dy) * tw + lx;
        for (var dx = 0u; dx <= 2u * rx; dx = dx + 1u) {
            if (dx == rx && dy == ry) {
                continue;
            }
            let bit = select(0u, 1u, tile[row + dx] < c);
            hi = (hi << 1u) | (lo >> 31u);
            lo = (lo << 1u) | bit;
        }
    }
    let code = vec2<u32>(hi, lo);
    if (gid.z == 0u) {
        codes[gid.y * w + gid.x] = code;
    } else {
        let s = params.pair_stride;
        pairs[gid.y * s + 4u + gid.x] = code;
        pairs[(h + gid.y) * s + 3u + gid.x] = code;
    }
}
