// uses: sgm_paths.wgsl
// uses: sgm_sums.wgsl
// SGM step 2 as `sgm_aggregate.wgsl` (paths, cost, recurrence and store in `sgm_paths.wgsl`),
// for adapters with subgroups of a known size: a path's invocations are LANES consecutive lanes
// of one subgroup (LANES, a power of two, at least THREADS and at most the subgroup size; lanes
// past THREADS hold only padding), and they exchange their neighbouring L and their minimum by
// subgroup shuffles instead of workgroup memory, so no barrier is needed: each subgroup walks
// its paths at its own pace. The exchange reads the previous pixel's L, so it runs before this
// pixel's cost and in uniform control flow, every step of the workgroup's longest path.
// The host specialises LANES and PATHS (and the shared constants) and picks this kernel only
// where the adapter's subgroups all have one size and the workgroup is a whole number of them.
// Subgroups are wgpu's native feature `SUBGROUP` (naga 30 rejects `enable subgroups;`, the
// standard's directive, and needs none).

const LANES: u32 = 32u;
const PATHS: u32 = 2u;

// The minimum over the LANES lanes of this invocation's cluster.
fn cluster_min(v: u32, subgroup_size: u32) -> u32 {
    if (LANES == subgroup_size) {
        return subgroupMin(v);
    }
    var m = v;
    for (var o = LANES / 2u; o > 0u; o = o / 2u) {
        m = min(m, subgroupShuffleXor(m, o));
    }
    return m;
}

@compute @workgroup_size(LANES * PATHS, 1, 1)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(subgroup_id) subgroup: u32,
    @builtin(subgroup_size) subgroup_size: u32,
    @builtin(subgroup_invocation_id) lane: u32,
) {
    let wg = workgroup_paths(wid, PATHS);
    if (wg.first >= wg.paths) {
        return;
    }
    // Steps of the workgroup: its longest path (uniform, so the shuffles meet every lane).
    let steps = longest(wg.first, PATHS, wg.paths, wg.dx, wg.dy);
    let sp = subgroup * (subgroup_size / LANES) + lane / LANES;
    let t = lane % LANES;
    let path = wg.first + sp;
    let d0 = 4u * t;
    let d = vec4<u32>(d0) + vec4<u32>(0u, 1u, 2u, 3u);
    let padding = d >= vec4<u32>(params.disparities);
    let keep = select(vec4<u32>(0xffffu), vec4<u32>(0u), padding);
    let holds = t < THREADS;
    var p = start(path, wg.dx, wg.dy);
    var len = 0u;
    if (path < wg.paths && sp < PATHS) {
        len = length(p, wg.dx, wg.dy);
    }
    var gray_prev = 0u;
    var prev = vec4<u32>(BIG);
    // Census codes of the pixel about to be aggregated.
    var code = vec2<u32>(0u);
    var right = Right(vec4<u32>(0u), vec4<u32>(0u));
    if (len > 0u && holds) {
        code = codes[u32(p.y) * params.width + u32(p.x)];
        right = right_codes(p, d0);
    }
    for (var step = 0u; step < steps; step = step + 1u) {
        // The previous pixel's exchange: the cluster's minimum and the neighbours' L at d0 - 1
        // and d0 + 4 (lanes past THREADS hold BIG).
        let min_prev = cluster_min(min(min(prev.x, prev.y), min(prev.z, prev.w)), subgroup_size);
        let from_below = subgroupShuffleUp(prev.w, 1u);
        let from_above = subgroupShuffleDown(prev.x, 1u);
        if (step < len) {
            let i = u32(p.y) * params.width + u32(p.x);
            var cur = cost(p, d, code, right);
            // The next pixel's codes, loaded a step ahead.
            let q = p + vec2<i32>(wg.dx, wg.dy);
            if (step + 1u < len && holds) {
                code = codes[u32(q.y) * params.width + u32(q.x)];
                right = right_codes(q, d0);
            }
            var g = 0u;
            if (params.p2_adaptive != 0u) {
                g = gray(i);
            }
            if (step > 0u) {
                let below = select(from_below, BIG, t == 0u);
                let above = select(from_above, BIG, t + 1u >= THREADS);
                cur = recur(cur, prev, below, above, min_prev, penalty2(gray_prev, g));
            }
            cur = select(cur, vec4<u32>(BIG), padding);
            prev = cur;
            if (holds) {
                store(wg.dir, i, d0, cur, keep);
            }
            gray_prev = g;
            p = q;
        }
    }
}
