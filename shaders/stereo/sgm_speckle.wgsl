// SGM step 5: speckle removal, as connected-component labelling by a lock-free union-find
// (Playne and Hawick, "A new algorithm for parallel connected-component labelling on GPUs",
// IEEE TPDS 2018). Two valid 4-neighbours are joined when their disparities differ by at most
// `range`; every valid pixel of a component smaller than `window` pixels becomes invalid.
// Four entry points, dispatched in order over 16x16 tiles (one workgroup each):
//   local    the components within each tile, by the same union-find in workgroup memory;
//            parent(i) = the pixel of its tile component's root, size(i) = 0;
//   merge    joins the pixels on a tile's right and lower edge with their neighbour in the next
//            tile (atomicMin hooks the larger root under the smaller: a tile's local order is
//            the image's, so parent(i) <= i holds throughout and every find terminates);
//   count    parent(i) = root of i (the unions are done, so this path compression is safe while
//            other invocations walk the same trees), and size(root) += 1 per valid pixel
//            (summed per tile for the tile's smallest root);
//   apply    invalidates the pixels of small components.
// CPU reference: misslam_depth_sgm::sgm::remove_speckles (a flood fill); the components are
// the same partition, so the output is the same.

struct Params {
    width: u32,
    height: u32,
    window: u32,
    range: f32,
}

const INVALID: f32 = -3.0e38;

@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read_write> disparity: array<f32>;
@group(0) @binding(2) var<storage, read_write> parent: array<atomic<u32>>;
@group(0) @binding(3) var<storage, read_write> size: array<atomic<u32>>;

fn find(start: u32) -> u32 {
    var x = start;
    loop {
        let p = atomicLoad(&parent[x]);
        if (p == x) {
            return x;
        }
        x = p;
    }
    return x;
}

fn unite(a0: u32, b0: u32) {
    var a = a0;
    var b = b0;
    loop {
        a = find(a);
        b = find(b);
        if (a == b) {
            return;
        }
        if (a < b) {
            let old = atomicMin(&parent[b], a);
            if (old == b) {
                return;
            }
            b = old;
        } else {
            let old = atomicMin(&parent[a], b);
            if (old == a) {
                return;
            }
            a = old;
        }
    }
}

fn joined(a: f32, b: f32) -> bool {
    return a != INVALID && b != INVALID && abs(b - a) <= params.range;
}

fn pixel(gid: vec3<u32>) -> u32 {
    if (gid.x >= params.width || gid.y >= params.height) {
        return 0xffffffffu;
    }
    return gid.y * params.width + gid.x;
}

// Parents within a tile, by local index (row by row).
var<workgroup> local_parent: array<atomic<u32>, 256>;

fn find_local(start: u32) -> u32 {
    var x = start;
    loop {
        let p = atomicLoad(&local_parent[x]);
        if (p == x) {
            return x;
        }
        x = p;
    }
    return x;
}

fn unite_local(a0: u32, b0: u32) {
    var a = a0;
    var b = b0;
    loop {
        a = find_local(a);
        b = find_local(b);
        if (a == b) {
            return;
        }
        if (a < b) {
            let old = atomicMin(&local_parent[b], a);
            if (old == b) {
                return;
            }
            b = old;
        } else {
            let old = atomicMin(&local_parent[a], b);
            if (old == a) {
                return;
            }
            a = old;
        }
    }
}

@compute @workgroup_size(16, 16, 1)
fn local(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    atomicStore(&local_parent[li], li);
    let i = pixel(gid);
    var v = INVALID;
    if (i != 0xffffffffu) {
        v = disparity[i];
    }
    workgroupBarrier();
    if (v != INVALID) {
        if (lid.x < 15u && gid.x + 1u < params.width && joined(v, disparity[i + 1u])) {
            unite_local(li, li + 1u);
        }
        if (lid.y < 15u && gid.y + 1u < params.height && joined(v, disparity[i + params.width])) {
            unite_local(li, li + 16u);
        }
    }
    workgroupBarrier();
    if (i != 0xffffffffu) {
        let r = find_local(li);
        let x0 = gid.x - lid.x;
        let y0 = gid.y - lid.y;
        atomicStore(&parent[i], (y0 + r / 16u) * params.width + x0 + r % 16u);
        atomicStore(&size[i], 0u);
    }
}

@compute @workgroup_size(16, 16, 1)
fn merge(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_id) lid: vec3<u32>,
) {
    let i = pixel(gid);
    if (i == 0xffffffffu || (lid.x < 15u && lid.y < 15u)) {
        return;
    }
    let v = disparity[i];
    if (v == INVALID) {
        return;
    }
    if (lid.x == 15u && gid.x + 1u < params.width && joined(v, disparity[i + 1u])) {
        unite(i, i + 1u);
    }
    if (lid.y == 15u && gid.y + 1u < params.height && joined(v, disparity[i + params.width])) {
        unite(i, i + params.width);
    }
}

// The tile's smallest root and how many of its pixels have it: most tiles lie inside one
// large component, whose pixels would otherwise all add to one counter in global memory.
var<workgroup> leader: atomic<u32>;
var<workgroup> leader_count: atomic<u32>;

@compute @workgroup_size(16, 16, 1)
fn count(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) li: u32,
) {
    if (li == 0u) {
        atomicStore(&leader, 0xffffffffu);
        atomicStore(&leader_count, 0u);
    }
    workgroupBarrier();
    let i = pixel(gid);
    var root = 0xffffffffu;
    if (i != 0xffffffffu && disparity[i] != INVALID) {
        root = find(i);
        atomicStore(&parent[i], root);
        atomicMin(&leader, root);
    }
    workgroupBarrier();
    let l = atomicLoad(&leader);
    if (root != 0xffffffffu) {
        if (root == l) {
            atomicAdd(&leader_count, 1u);
        } else {
            atomicAdd(&size[root], 1u);
        }
    }
    workgroupBarrier();
    if (li == 0u && l != 0xffffffffu) {
        atomicAdd(&size[l], atomicLoad(&leader_count));
    }
}

// The final map for the host (as `finish` in `sgm_median.wgsl`, whose dispatch this one replaces
// when the speckles are removed): the disparity's bits, or a quiet NaN's where it is invalid or
// in a speckle.
@group(0) @binding(4) var<storage, read_write> bits: array<u32>;

@compute @workgroup_size(16, 16, 1)
fn apply(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = pixel(gid);
    if (i == 0xffffffffu) {
        return;
    }
    let v = disparity[i];
    var keep = v != INVALID;
    if (keep && atomicLoad(&size[atomicLoad(&parent[i])]) < params.window) {
        keep = false;
    }
    bits[i] = select(0x7fc00000u, bitcast<u32>(v), keep);
}
