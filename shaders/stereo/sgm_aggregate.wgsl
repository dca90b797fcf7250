// uses: sgm_paths.wgsl
// uses: sgm_sums.wgsl
// SGM step 2, aggregation along every direction in one dispatch (paths, cost, recurrence and
// store in `sgm_paths.wgsl`), for any adapter: a workgroup walks PATHS neighbouring paths of one
// direction side by side, THREADS invocations per path. Per pixel, the invocations of a path
// exchange their lowest and highest L and their minimum through double-buffered workgroup
// memory: one barrier per pixel. The census codes of the next pixel are loaded before the
// barrier, so their latency hides behind it. `sgm_aggregate_subgroup.wgsl` does the same
// exchange by subgroup shuffles, without barriers, where the adapter has subgroups.
// The host specialises PATHS (and the shared constants).

const PATHS: u32 = 2u;

// Per buffer and path: each invocation's L at its lowest and highest disparity, and its minimum.
var<workgroup> lo: array<array<array<u32, THREADS>, PATHS>, 2>;
var<workgroup> hi: array<array<array<u32, THREADS>, PATHS>, 2>;
// The minima are read four at a time (a vec4 load): with scalar loads the kernel is about a third
// slower on an H100. Each invocation writes one component; naga lowers that to a store through
// an access chain to the component, so neighbours' components are not rewritten.
var<workgroup> mins: array<array<array<vec4<u32>, THREADS / 4u>, PATHS>, 2>;

@compute @workgroup_size(THREADS * PATHS, 1, 1)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    let wg = workgroup_paths(wid, PATHS);
    if (wg.first >= wg.paths) {
        return;
    }
    // Steps of the workgroup: its longest path (uniform, so every invocation meets every barrier).
    let steps = longest(wg.first, PATHS, wg.paths, wg.dx, wg.dy);
    let sp = lid.x / THREADS;
    let t = lid.x % THREADS;
    let path = wg.first + sp;
    let d0 = 4u * t;
    let d = vec4<u32>(d0) + vec4<u32>(0u, 1u, 2u, 3u);
    let padding = d >= vec4<u32>(params.disparities);
    let keep = select(vec4<u32>(0xffffu), vec4<u32>(0u), padding);
    var p = start(path, wg.dx, wg.dy);
    var len = 0u;
    if (path < wg.paths) {
        len = length(p, wg.dx, wg.dy);
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
            var cur = cost(p, d, code, right);
            // The next pixel's codes, used after the barrier.
            let q = p + vec2<i32>(wg.dx, wg.dy);
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
                cur = recur(cur, prev, below, above, min_prev, penalty2(gray_prev, g));
            }
            cur = select(cur, vec4<u32>(BIG), padding);
            prev = cur;
            store(wg.dir, i, d0, cur, keep);
            gray_prev = g;
            p = q;
            lo[buf ^ 1u][sp][t] = cur.x;
            hi[buf ^ 1u][sp][t] = cur.w;
            mins[buf ^ 1u][sp][t / 4u][t % 4u] = min(min(cur.x, cur.y), min(cur.z, cur.w));
        }
        buf = buf ^ 1u;
        // Everyone's exchange for this pixel is written; the other buffer, read for this pixel,
        // is written again only after the next barrier.
        workgroupBarrier();
    }
}
