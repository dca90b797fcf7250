// uses: sgm_select_common.wgsl
// SGM step 3 as `sgm_select.wgsl` (one workgroup per image row, the same output), for adapters
// whose subgroups the aggregation uses: a pixel per cluster of LANES subgroup lanes, each lane
// holding four consecutive disparities (d = 4t + k) as in the aggregation, so a cluster reads a
// pixel's costs of one direction as one contiguous run. Per pixel, the cluster finds
// - the winner bd, the smallest d with the least S(x, d): the least (S << 11 | d) over the lanes;
// - the least S outside bd - 1 ..= bd + 1 (the uniqueness margin), a second minimum;
// - S(bd - 1) and S(bd + 1) for the parabola, shuffled from the lanes that hold them;
// and every S(x, d) is a candidate of the right image's winner at x - d - dmin.
// After a barrier each invocation applies the left-right check to its share of the pixels.
// The host specialises LANES (a power of two, at most the subgroup size; lanes past the
// disparities hold padding) and the shared constants (THREADS: the workgroup's invocations, a
// whole number of subgroups). Subgroups are wgpu's native feature `SUBGROUP`.

const LANES: u32 = 32u;
const NO_SUM: u32 = 0xffffu;

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

// Component k of v.
fn lane_of(v: vec4<u32>, k: u32) -> u32 {
    return select(select(v.w, v.z, k == 2u), select(v.y, v.x, k == 0u), k < 2u);
}

@compute @workgroup_size(THREADS, 1, 1)
fn main(
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
    @builtin(subgroup_id) subgroup: u32,
    @builtin(subgroup_size) subgroup_size: u32,
    @builtin(subgroup_invocation_id) lane: u32,
) {
    let y = wid.x;
    let w = params.width;
    let nd = params.disparities;
    let t = lane % LANES;
    // The cluster's first lane, and its index in the workgroup.
    let base = lane - t;
    let slot = subgroup * (subgroup_size / LANES) + lane / LANES;
    let pixels = THREADS / LANES;
    let d0 = 4u * t;
    let d = vec4<u32>(d0) + vec4<u32>(0u, 1u, 2u, 3u);
    let real = d < vec4<u32>(nd);
    clear_right(li);
    workgroupBarrier();
    // Every cluster runs every round (the reductions need all lanes); x may lie past the row.
    for (var x0 = 0u; x0 < w; x0 = x0 + pixels) {
        let x = x0 + slot;
        let inside = x < w;
        let i = y * w + min(x, w - 1u);
        // S for d0 .. d0 + 3: the directions' words of this lane summed.
        var s = vec4<u32>(0u);
        if (inside && d0 < params.dp) {
            for (var r = 0u; r < DIRS; r = r + 1u) {
                let at = r * params.volume_words + (i * params.dp + d0) * BYTES / 4u;
                if (BYTES == 1u) {
                    s = s + unpack_bytes(volumes_word(at));
                } else {
                    let a = volumes_word(at);
                    let b = volumes_word(at + 1u);
                    s = s + vec4<u32>(a & 0xffffu, a >> 16u, b & 0xffffu, b >> 16u);
                }
            }
        }
        s = select(vec4<u32>(NO_SUM), s, real);
        // The winner: the least (S << 11 | d), so the smallest d among equal sums.
        let keys = (s << vec4<u32>(11u)) | d;
        let key = cluster_min(min(min(keys.x, keys.y), min(keys.z, keys.w)), subgroup_size);
        let best = key >> 11u;
        let bd = key & 0x7ffu;
        // The least S outside bd - 1 ..= bd + 1.
        let near = (d + vec4<u32>(1u) >= vec4<u32>(bd)) & (d <= vec4<u32>(bd + 1u));
        let far = select(s, vec4<u32>(NO_SUM), near);
        let second = cluster_min(min(min(far.x, far.y), min(far.z, far.w)), subgroup_size);
        // S(bd - 1) and S(bd + 1) from the lanes holding them (bd - 1 wraps to a padding lane's
        // value when bd = 0; unused then).
        let below = (bd + 4u * LANES - 1u) % (4u * LANES);
        let above = min(bd + 1u, 4u * LANES - 1u);
        let before = subgroupShuffle(lane_of(s, below % 4u), base + below / 4u);
        let after = subgroupShuffle(lane_of(s, above % 4u), base + above / 4u);
        if (inside) {
            if (real.x) { right_candidate(x, s.x, d.x); }
            if (real.y) { right_candidate(x, s.y, d.y); }
            if (real.z) { right_candidate(x, s.z, d.z); }
            if (real.w) { right_candidate(x, s.w, d.w); }
            if (t == 0u) {
                disparity[i] = output(i, best, bd, second, before, after);
            }
        }
    }
    workgroupBarrier();
    if (params.lr_check != 0u) {
        lr_check(y, li);
    }
}
