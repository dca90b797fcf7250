// SGM step 2: cost aggregation along one direction (dx, dy), added to the sum S. One workgroup
// per path: the path starts at a pixel whose predecessor (x - dx, y - dy) is outside the image
// and walks to the opposite border; its 64 invocations share the disparities (d = t, t + 64, ..).
// CPU reference: misslam_depth_sgm::reference (one traversal per direction) and the SIMD passes
// of misslam_depth_sgm::sgm, which give the same integers:
//   L(p, d) = C(p, d) + min(L(p-r, d), L(p-r, d-1) + P1, L(p-r, d+1) + P1, min_k L(p-r, k) + P2)
//             - min_k L(p-r, k),     L = C at the path's first pixel,
// with C the Hamming distance of the census codes (or `unknown` when x - d - dmin leaves the
// right image) and P2 divided by the intensity step when `p2_adaptive` is set.

struct Params {
    width: u32,
    height: u32,
    disparities: u32,
    min_disparity: i32,
    p1: u32,
    p2: u32,
    p2_adaptive: u32,
    unknown: u32,
    dx: i32,
    dy: i32,
    paths: u32,
    groups_x: u32,
}

const GROUP: u32 = 64u;
const MAX_D: u32 = 1024u;
const PER: u32 = 16u; // MAX_D / GROUP
const BIG: u32 = 0x3fffffffu;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read> images: array<u32>;
@group(0) @binding(2) var<storage, read> codes: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read_write> sums: array<u32>;

// L of the previous pixel at index d + 1; entries 0 and D + 1 stay BIG.
var<workgroup> prev: array<u32, 1026>;
var<workgroup> partial: array<u32, 64>;

fn start(path: u32) -> vec2<i32> {
    let w = i32(params.width);
    let h = i32(params.height);
    let p = i32(path);
    if (params.dy == 0) {
        // Rows: one path per row, from the left (dx > 0) or the right border.
        return vec2<i32>(select(w - 1, 0, params.dx > 0), p);
    }
    let y0 = select(h - 1, 0, params.dy > 0);
    if (p < w) {
        return vec2<i32>(p, y0);
    }
    // Diagonals also start on the first column of their direction, below (or above) the corner.
    let k = p - w + 1;
    return vec2<i32>(select(w - 1, 0, params.dx > 0), select(y0 - k, y0 + k, params.dy > 0));
}

@compute @workgroup_size(64, 1, 1)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let path = wid.x + wid.y * params.groups_x;
    // Uniform for the whole workgroup: every invocation returns or none does.
    if (path >= params.paths) {
        return;
    }
    let w = i32(params.width);
    let h = i32(params.height);
    let nd = params.disparities;
    let t = lid.x;
    let wh = params.width * params.height;
    if (t == 0u) {
        prev[0] = BIG;
        prev[nd + 1u] = BIG;
    }
    var p = start(path);
    var first = true;
    var min_prev = 0u;
    var gray_prev = 0u;
    var fresh: array<u32, PER>;
    loop {
        if (p.x < 0 || p.y < 0 || p.x >= w || p.y >= h) {
            break;
        }
        let i = u32(p.y) * params.width + u32(p.x);
        let gray = images[i];
        var p2 = params.p2;
        if (params.p2_adaptive != 0u && !first) {
            let step = max(select(gray_prev - gray, gray - gray_prev, gray > gray_prev), 1u);
            p2 = max(params.p2 / step, params.p1 + 1u);
        }
        let jump = min_prev + p2;
        let code = codes[i];
        var local_min = BIG;
        for (var k = 0u; k < PER; k = k + 1u) {
            let d = t + k * GROUP;
            if (d >= nd) {
                break;
            }
            let xr = p.x - i32(d) - params.min_disparity;
            var c = params.unknown;
            if (xr >= 0 && xr < w) {
                let r = codes[wh + u32(p.y) * params.width + u32(xr)];
                c = countOneBits(code.x ^ r.x) + countOneBits(code.y ^ r.y);
            }
            var l = c;
            if (!first) {
                let best = min(min(prev[d + 1u], jump), min(prev[d] + params.p1, prev[d + 2u] + params.p1));
                l = c + best - min_prev;
            }
            fresh[k] = l;
            local_min = min(local_min, l);
            sums[i * nd + d] = sums[i * nd + d] + l;
        }
        partial[t] = local_min;
        // Everyone has read `prev` and written `partial`.
        workgroupBarrier();
        for (var k = 0u; k < PER; k = k + 1u) {
            let d = t + k * GROUP;
            if (d >= nd) {
                break;
            }
            prev[d + 1u] = fresh[k];
        }
        var m = BIG;
        for (var j = 0u; j < GROUP; j = j + 1u) {
            m = min(m, partial[j]);
        }
        // `prev` holds this pixel and everyone has read `partial`.
        workgroupBarrier();
        min_prev = m;
        gray_prev = gray;
        first = false;
        p = p + vec2<i32>(params.dx, params.dy);
    }
}
