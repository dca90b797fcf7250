// SGM step 2, the part both aggregation kernels share (`sgm_aggregate.wgsl`, which exchanges
// neighbouring disparities through workgroup memory, and `sgm_aggregate_subgroup.wgsl`, through
// subgroup shuffles): the paths, the matching cost, the recurrence and the store of L.
// A path starts at a pixel whose predecessor (x - dx, y - dy) lies outside the image and walks
// to the opposite border; THREADS invocations hold its disparities, four consecutive ones each
// (d = 4t + k) in the lanes of a vec4 (no arrays: the GPU keeps them in registers). Each
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
// The host places a kernel after this file and specialises THREADS, BYTES and SUMMED (and the
// kernel's own constants) by their lines `const NAME: u32 = ...;`.

struct Dir {
    dx: i32,
    dy: i32,
    // Paths of this direction.
    paths: u32,
    pad: u32,
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
    // Slots per row of each copy of the right codes in `pairs` (see `sgm_census.wgsl`).
    pair_stride: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
    dir: array<Dir, 8>,
}

const THREADS: u32 = 32u;
const BYTES: u32 = 1u;
const SUMMED: u32 = 0u;
const BIG: u32 = 0x3fffffffu;

@group(0) @binding(0) var<uniform> params: Params;
// Gray levels, four per word (little-endian), of the left image.
@group(0) @binding(1) var<storage, read> images: array<u32>;
// (hi, lo) census code per pixel of the left image.
@group(0) @binding(2) var<storage, read> codes: array<vec2<u32>>;
// The right image's codes, each row twice (`sgm_census.wgsl`), two codes per element.
@group(0) @binding(5) var<storage, read> pairs: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read_write> volumes: array<u32>;
// The workgroups' dispatch order (see `workgroup_paths`).
@group(0) @binding(6) var<storage, read> order: array<u32>;
// The volume of sums (SUMMED = 1; binding 4, a placeholder otherwise) and `add_sums` come from
// `sgm_sums.wgsl` (32-bit atomics) or `sgm_sums64.wgsl` (64-bit), as the host assembles the kernel.

// A workgroup's share of the paths: its direction `dir`, that direction's step (dx, dy) and number
// of paths, and its first path (it takes `per_group` consecutive ones).
struct Group {
    dir: u32,
    dx: i32,
    dy: i32,
    paths: u32,
    first: u32,
}

// The share of workgroup `wid`, from the host's dispatch order (`order`: the direction in the
// high 3 bits, the block of `per_group` paths in the low 29; the longest paths first). Uniform for
// the workgroup, so every invocation returns or none does when `first` is past the paths (the
// grid's padding past the order included).
fn workgroup_paths(wid: vec3<u32>, per_group: u32) -> Group {
    let group = wid.x + wid.y * params.groups_x;
    if (group >= arrayLength(&order)) {
        return Group(0u, 0, 0, 0u, 1u);
    }
    let e = order[group];
    let r = e >> 29u;
    let d = params.dir[r];
    return Group(r, d.dx, d.dy, d.paths, (e & 0x1fffffffu) * per_group);
}

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

// Steps of the `count` paths from `first`: the longest one's pixels.
fn longest(first: u32, count: u32, paths: u32, dx: i32, dy: i32) -> u32 {
    var steps = 0u;
    for (var k = 0u; k < count; k = k + 1u) {
        if (first + k < paths) {
            steps = max(steps, length(start(first + k, dx, dy), dx, dy));
        }
    }
    return steps;
}

struct Right {
    hi: vec4<u32>,
    lo: vec4<u32>,
}

// Census codes of the right image at x - d - dmin for d = d0 .. d0 + 3: the codes j0 ..= j0 + 3
// of row q.y (j0 = x - dmin - d0 - 3), four consecutive ones, read as two aligned pairs
// (`pairs`, written by the census kernel): from the even copy of the row where j0 is even, else
// from the odd one. Where some of the four lie outside the image (their cost is `unknown`), the
// row's margin of 4 codes keeps the others in place; where all do, the read is clamped into the
// row. Two 16-byte reads instead of four 8-byte ones: the invocations of a path read 32 bytes
// apart, so each read spans the same cache lines, half as many times.
fn right_codes(q: vec2<i32>, d0: u32) -> Right {
    let s = i32(params.pair_stride);
    let j0 = q.x - params.min_disparity - i32(d0) - 3;
    let odd = j0 & 1;
    let region = select(0, i32(params.height) * s, odd != 0);
    let slot = clamp(4 + j0 - odd, 0, s - 4);
    let at = u32(region + q.y * s + slot) / 2u;
    let a = pairs[at];
    let c = pairs[at + 1u];
    // a = (code j0, code j0 + 1), c = (code j0 + 2, code j0 + 3); d0 is code j0 + 3.
    return Right(vec4<u32>(c.z, c.x, a.z, a.x), vec4<u32>(c.w, c.y, a.w, a.y));
}

// C at pixel p for the disparities d: the Hamming distance of the codes, or `unknown` where
// x - d - dmin leaves the right image. Where every searched disparity stays inside (most pixels;
// the test is on the path's pixel, so the invocations of a path agree), no test per disparity.
fn cost(p: vec2<i32>, d: vec4<u32>, code: vec2<u32>, right: Right) -> vec4<u32> {
    let c = countOneBits(vec4<u32>(code.x) ^ right.hi) + countOneBits(vec4<u32>(code.y) ^ right.lo);
    let x = p.x - params.min_disparity;
    if (x + 1 >= i32(params.disparities) && x < i32(params.width)) {
        return c;
    }
    let xr = vec4<i32>(x) - vec4<i32>(d);
    let inside = (xr >= vec4<i32>(0)) & (xr < vec4<i32>(i32(params.width)));
    return select(vec4<u32>(params.unknown), c, inside);
}

// P2 between gray levels g_prev and g (divided by the step when `p2_adaptive` is set).
fn penalty2(g_prev: u32, g: u32) -> u32 {
    if (params.p2_adaptive == 0u) {
        return params.p2;
    }
    let jump_g = select(g_prev - g, g - g_prev, g > g_prev);
    return max(params.p2 / max(jump_g, 1u), params.p1 + 1u);
}

// The recurrence: L of this pixel from its cost `cur`, the previous pixel's L (`prev`, with
// `below` and `above` the neighbouring invocations' L at d0 - 1 and d0 + 4) and their minimum.
fn recur(cur: vec4<u32>, prev: vec4<u32>, below: u32, above: u32, min_prev: u32, p2: u32) -> vec4<u32> {
    let l_minus = vec4<u32>(below, prev.x, prev.y, prev.z);
    let l_plus = vec4<u32>(prev.y, prev.z, prev.w, above);
    let best = min(
        min(prev, vec4<u32>(min_prev + p2)),
        min(l_minus, l_plus) + vec4<u32>(params.p1),
    );
    return cur + best - vec4<u32>(min_prev);
}

// Stores L of pixel i, disparities d0 .. d0 + 3, into direction r's volume: BYTES per
// disparity, little-endian within a word; or adds it to the sums, `keep` (0xffff for a searched
// disparity, 0 for padding) masking out the padding.
fn store(r: u32, i: u32, d0: u32, cur: vec4<u32>, keep: vec4<u32>) {
    if (SUMMED == 1u) {
        let b = cur & keep;
        let s = (i * (4u * THREADS) + d0) / 2u;
        add_sums(s, b);
        return;
    }
    let at = r * params.volume_words + (i * (4u * THREADS) + d0) * BYTES / 4u;
    if (BYTES == 1u) {
        let b = cur & vec4<u32>(0xffu);
        volumes[at] = b.x | (b.y << 8u) | (b.z << 16u) | (b.w << 24u);
    } else {
        let b = cur & vec4<u32>(0xffffu);
        volumes[at] = b.x | (b.y << 16u);
        volumes[at + 1u] = b.z | (b.w << 16u);
    }
}
