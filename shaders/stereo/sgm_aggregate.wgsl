// SGM step 2: cost aggregation along every direction in one dispatch. A path starts at a pixel
// whose predecessor (x - dx, y - dy) lies outside the image and walks to the opposite border;
// THREADS invocations hold its disparities, four consecutive ones each (d = 4t + k) in the lanes
// of a vec4 (no arrays: the GPU keeps them in registers), and a workgroup walks PATHS
// neighbouring paths of one direction side by side. Per
// pixel, the invocations of a path exchange their lowest and highest L and their minimum
// through double-buffered workgroup memory: one barrier per pixel. The census codes of the
// next pixel are loaded before the barrier, so their latency hides behind it. Each
// direction writes its own volume of L (u8 or u16 per disparity, BYTES), row-major by pixel
// with DP = 4 * THREADS disparities per pixel; the selection kernel sums them. With SUMMED = 1
// (for adapters whose storage buffers cannot hold a volume per direction) every direction adds
// its L instead into one volume of sums, u16 per disparity, two to a word, by atomic adds: the
// sums are integers, so their order does not matter, and no lane carries into the next (eight
// paths of at most 64 + 4000 each; padding disparities add 0).
// CPU reference: misslam_depth_sgm::reference (one traversal per direction) and the SIMD passes
// of misslam_depth_sgm::sgm, which give the same integers:
//   L(p, d) = C(p, d) + min(L(p-r, d), L(p-r, d-1) + P1, L(p-r, d+1) + P1, min_k L(p-r, k) + P2)
//             - min_k L(p-r, k),     L = C at the path's first pixel,
// with C the Hamming distance of the census codes (or `unknown` when x - d - dmin leaves the
// right image) and P2 divided by the intensity step when `p2_adaptive` is set. L <= C + P2, so
// the host picks BYTES = 1 when the largest C plus P2 fits a byte.
// The host specialises THREADS, PATHS, BYTES and SUMMED (lines `const NAME: u32 = ...;`).

struct Dir {
    dx: i32,
    dy: i32,
    // Paths of this direction.
    paths: u32,
    // Index of its first workgroup (each takes PATHS paths).
    first: u32,
}

struct Params {
    width: u32,
    height: u32,
    disparities: u32,
    min_disparity: i32,
    p1: u32,
    p2: u32,
    p2_adaptive: u32,
    unknown: u32,
    dirs: u32,
    groups_x: u32,
    // Words of one direction's volume.
    volume_words: u32,
    // Word offset of the right image in `images`.
    right_words: u32,
    dir: array<Dir, 8>,
}

const THREADS: u32 = 32u;
const PATHS: u32 = 2u;
const BYTES: u32 = 1u;
const SUMMED: u32 = 0u;
const BIG: u32 = 0x3fffffffu;

@group(0) @binding(0) var<uniform> params: Params;
// Gray levels, four per word (little-endian), of the left image.
@group(0) @binding(1) var<storage, read> images: array<u32>;
// (hi, lo) census code per pixel, the left image then the right one.
@group(0) @binding(2) var<storage, read> codes: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read_write> volumes: array<u32>;
// The volume of sums (SUMMED = 1); a placeholder otherwise.
@group(0) @binding(4) var<storage, read_write> sums: array<atomic<u32>>;

// Per buffer and path: each invocation's L at its lowest and highest disparity, and its minimum.
var<workgroup> lo: array<array<array<u32, THREADS>, PATHS>, 2>;
var<workgroup> hi: array<array<array<u32, THREADS>, PATHS>, 2>;
// The minima are read four at a time (a vec4 load): with scalar loads the kernel is about a third
// slower on an H100. Each invocation writes one component; naga lowers that to a store through
// an access chain to the component, so neighbours' components are not rewritten.
var<workgroup> mins: array<array<array<vec4<u32>, THREADS / 4u>, PATHS>, 2>;

fn start(path: u32, dx: i32, dy: i32) -> vec2<i32> {
    let w = i32(params.width);
    let h = i32(params.height);
    let p = i32(path);
    if (dy == 0) {
        // Rows: one path per row, from the left (dx > 0) or the right border.
        return vec2<i32>(select(w - 1, 0, dx > 0), p);
    }
    let y0 = select(h - 1, 0, dy > 0);
    if (p < w) {
        return vec2<i32>(p, y0);
    }
    // Diagonals also start on the first column of their direction, below (or above) the corner.
    let k = p - w + 1;
    return vec2<i32>(select(w - 1, 0, dx > 0), select(y0 - k, y0 + k, dy > 0));
}

fn gray(i: u32) -> u32 {
    return (images[i >> 2u] >> ((i & 3u) * 8u)) & 0xffu;
}

// Pixels on a path of direction (dx, dy) from `p` to the border.
fn length(p: vec2<i32>, dx: i32, dy: i32) -> u32 {
    let w = i32(params.width);
    let h = i32(params.height);
    var n = 0x7fffffff;
    if (dx > 0) {
        n = min(n, w - p.x);
    } else if (dx < 0) {
        n = min(n, p.x + 1);
    }
    if (dy > 0) {
        n = min(n, h - p.y);
    } else if (dy < 0) {
        n = min(n, p.y + 1);
    }
    return u32(max(n, 0));
}

struct Right {
    hi: vec4<u32>,
    lo: vec4<u32>,
}

// Census codes of the right image at x - d - dmin for d = d0 .. d0 + 3 (clamped into the image;
// the range is checked where they are used).
fn right_codes(q: vec2<i32>, d0: u32) -> Right {
    let row = params.width * params.height + u32(q.y) * params.width;
    let xr = clamp(
        vec4<i32>(q.x - params.min_disparity) - vec4<i32>(vec4<u32>(d0) + vec4<u32>(0u, 1u, 2u, 3u)),
        vec4<i32>(0),
        vec4<i32>(i32(params.width) - 1),
    );
    let c0 = codes[row + u32(xr.x)];
    let c1 = codes[row + u32(xr.y)];
    let c2 = codes[row + u32(xr.z)];
    let c3 = codes[row + u32(xr.w)];
    return Right(vec4<u32>(c0.x, c1.x, c2.x, c3.x), vec4<u32>(c0.y, c1.y, c2.y, c3.y));
}

@compute @workgroup_size(THREADS * PATHS, 1, 1)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let group = wid.x + wid.y * params.groups_x;
    // Which direction: uniform for the whole workgroup, so every invocation returns or none does.
    var r = 0u;
    loop {
        if (r + 1u >= params.dirs || group < params.dir[r + 1u].first) {
            break;
        }
        r = r + 1u;
    }
    let dx = params.dir[r].dx;
    let dy = params.dir[r].dy;
    let paths = params.dir[r].paths;
    let first_path = (group - params.dir[r].first) * PATHS;
    if (first_path >= paths) {
        return;
    }
    // Steps of the workgroup: its longest path (uniform, so every invocation meets every barrier).
    var steps = 0u;
    for (var k = 0u; k < PATHS; k = k + 1u) {
        if (first_path + k < paths) {
            steps = max(steps, length(start(first_path + k, dx, dy), dx, dy));
        }
    }
    let sp = lid.x / THREADS;
    let t = lid.x % THREADS;
    let path = first_path + sp;
    let w = i32(params.width);
    let d0 = 4u * t;
    let d = vec4<u32>(d0) + vec4<u32>(0u, 1u, 2u, 3u);
    let padding = d >= vec4<u32>(params.disparities);
    let base = r * params.volume_words;
    var p = start(path, dx, dy);
    var len = 0u;
    if (path < paths) {
        len = length(p, dx, dy);
    }
    var gray_prev = 0u;
    var prev = vec4<u32>(BIG);
    // Census codes of the pixel about to be aggregated.
    var code = vec2<u32>(0u);
    var right = Right(vec4<u32>(0u), vec4<u32>(0u));
    if (len > 0u) {
        code = codes[u32(p.y) * params.width + u32(p.x)];
        right = right_codes(p, d0);
    }
    var buf = 0u;
    for (var step = 0u; step < steps; step = step + 1u) {
        if (step < len) {
            let i = u32(p.y) * params.width + u32(p.x);
            let xr = vec4<i32>(p.x - params.min_disparity) - vec4<i32>(d);
            let inside = (xr >= vec4<i32>(0)) & (xr < vec4<i32>(w));
            var cur = select(
                vec4<u32>(params.unknown),
                countOneBits(vec4<u32>(code.x) ^ right.hi) + countOneBits(vec4<u32>(code.y) ^ right.lo),
                inside,
            );
            // The next pixel's codes, used after the barrier.
            let q = p + vec2<i32>(dx, dy);
            if (step + 1u < len) {
                code = codes[u32(q.y) * params.width + u32(q.x)];
                right = right_codes(q, d0);
            }
            var g = 0u;
            if (params.p2_adaptive != 0u) {
                g = gray(i);
            }
            if (step > 0u) {
                // The previous pixel's exchange (written into `buf` before the last barrier).
                var m4 = mins[buf][sp][0];
                for (var j = 1u; j < THREADS / 4u; j = j + 1u) {
                    m4 = min(m4, mins[buf][sp][j]);
                }
                let min_prev = min(min(m4.x, m4.y), min(m4.z, m4.w));
                var below = BIG;
                if (t > 0u) {
                    below = hi[buf][sp][t - 1u];
                }
                var above = BIG;
                if (t + 1u < THREADS) {
                    above = lo[buf][sp][t + 1u];
                }
                var p2 = params.p2;
                if (params.p2_adaptive != 0u) {
                    let jump_g = select(gray_prev - g, g - gray_prev, g > gray_prev);
                    p2 = max(params.p2 / max(jump_g, 1u), params.p1 + 1u);
                }
                let l_minus = vec4<u32>(below, prev.x, prev.y, prev.z);
                let l_plus = vec4<u32>(prev.y, prev.z, prev.w, above);
                let best = min(
                    min(prev, vec4<u32>(min_prev + p2)),
                    min(l_minus, l_plus) + vec4<u32>(params.p1),
                );
                cur = cur + best - vec4<u32>(min_prev);
            }
            cur = select(cur, vec4<u32>(BIG), padding);
            prev = cur;
            let local_min = min(min(cur.x, cur.y), min(cur.z, cur.w));
            // Store L: BYTES per disparity, little-endian within a word, or add it to the sums.
            let at = base + (i * (4u * THREADS) + d0) * BYTES / 4u;
            if (SUMMED == 1u) {
                let b = select(cur & vec4<u32>(0xffffu), vec4<u32>(0u), padding);
                let s = (i * (4u * THREADS) + d0) / 2u;
                atomicAdd(&sums[s], b.x | (b.y << 16u));
                atomicAdd(&sums[s + 1u], b.z | (b.w << 16u));
            } else if (BYTES == 1u) {
                let b = cur & vec4<u32>(0xffu);
                volumes[at] = b.x | (b.y << 8u) | (b.z << 16u) | (b.w << 24u);
            } else {
                let b = cur & vec4<u32>(0xffffu);
                volumes[at] = b.x | (b.y << 16u);
                volumes[at + 1u] = b.z | (b.w << 16u);
            }
            gray_prev = g;
            p = q;
            lo[buf ^ 1u][sp][t] = cur.x;
            hi[buf ^ 1u][sp][t] = cur.w;
            mins[buf ^ 1u][sp][t / 4u][t % 4u] = local_min;
        }
        buf = buf ^ 1u;
        // Everyone's exchange for this pixel is written; the other buffer, read for this pixel,
        // is written again only after the next barrier.
        workgroupBarrier();
    }
}
