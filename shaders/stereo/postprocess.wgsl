// depth.postprocess on the GPU: range limits, the border and specular masks, the bilateral
// filter, and the vertex and normal maps, one invocation per pixel in five passes.
// CPU reference: misslam_depth_postprocess::clean_into and the functions of its `maps` module,
// step for step: the masks and the range limits give the same pixels and counts; the filter takes
// its taps in the same order with the same tables (a driver may fuse a multiply and an add, so
// its sums can differ in the last bit); the vertex map multiplies by the column's and row's
// (u - cx) / fx and (v - cy) / fy rounded to f32 (the CPU multiplies in f64).
//
// Invalid depth is NaN in and out; WGSL lets a compiler assume that no NaN or infinity occurs,
// so validity is read and written as bits, never by comparing floats with NaN.

struct Params {
    size: vec4<u32>,     // width, height, channels of the left image, FLAG_* bits
    levels: vec4<u32>,   // black level, specular minimum value, dilation px, bilateral radius
    ranges: vec4<f32>,   // min depth, max depth (mm), the range table's scale, max normal step
    offsets: vec4<u32>,  // in `tables`: spatial weights, widest spreads, (u - cx) / fx, (v - cy) / fy
}

const FLAG_BORDER_LEVEL: u32 = 1u;    // border: brightest channel below the black level
const FLAG_BORDER_MASK: u32 = 2u;     // border: the pair's left mask is 0
const FLAG_SPECULAR: u32 = 4u;        // specular highlights
const FLAG_BILATERAL: u32 = 8u;       // bilateral smoothing
const FLAG_STEP_LIMIT: u32 = 16u;     // normals stop at depth steps over max normal step

const NAN_BITS: u32 = 0x7fc00000u;
const RANGE_LUT: u32 = 1024u;
// Stand-in for an invalid pixel in the bilateral filter (misslam_depth_postprocess::maps::FAR).
const FAR: f32 = 1e30;

const OUT_OF_RANGE: u32 = 0u;
const BORDER: u32 = 1u;
const SPECULAR: u32 = 2u;

@group(0) @binding(0) var<uniform> params: Params;
// The depth before the masks, mm.
@group(0) @binding(1) var<storage, read> depth_in: array<f32>;
// The left image's bytes (channels per pixel), four to a word, little-endian.
@group(0) @binding(2) var<storage, read> image: array<u32>;
// The left mask's bytes (one per pixel), four to a word.
@group(0) @binding(3) var<storage, read> mask: array<u32>;
// The range weights (RANGE_LUT + 1, the last 0), then at the offsets the spatial weights, the
// widest spread per brightest value (256, -1: none passes) and the two coordinate tables.
@group(0) @binding(4) var<storage, read> tables: array<f32>;
// After the range limits and the border mask.
@group(0) @binding(5) var<storage, read_write> depth_masked: array<f32>;
// Specular highlights (0 or 1 a pixel) before the dilation, then dilated along rows.
@group(0) @binding(6) var<storage, read_write> specular: array<u32>;
@group(0) @binding(7) var<storage, read_write> specular_rows: array<u32>;
// After the specular mask: the depth, and the same with FAR for invalid pixels.
@group(0) @binding(8) var<storage, read_write> depth_clean: array<f32>;
@group(0) @binding(9) var<storage, read_write> depth_far: array<f32>;
// The outputs: depth, then three floats a pixel of points and of normals.
@group(0) @binding(10) var<storage, read_write> depth_out: array<f32>;
@group(0) @binding(11) var<storage, read_write> vertices: array<f32>;
@group(0) @binding(12) var<storage, read_write> normals: array<f32>;
// Pixels invalidated by the range limits, the border and the specular mask.
@group(0) @binding(13) var<storage, read_write> counts: array<atomic<u32>, 4>;

fn is_finite(v: f32) -> bool {
    return (bitcast<u32>(v) & 0x7f800000u) != 0x7f800000u;
}

fn is_nan(v: f32) -> bool {
    let b = bitcast<u32>(v);
    return (b & 0x7f800000u) == 0x7f800000u && (b & 0x007fffffu) != 0u;
}

fn nan() -> f32 {
    return bitcast<f32>(NAN_BITS);
}

fn byte_of(words_index: u32, which: u32) -> u32 {
    return (image[words_index] >> (8u * which)) & 0xffu;
}

fn image_byte(j: u32) -> u32 {
    return byte_of(j >> 2u, j & 3u);
}

fn mask_byte(j: u32) -> u32 {
    return (mask[j >> 2u] >> (8u * (j & 3u))) & 0xffu;
}

// The pixel of this invocation, or false outside the image.
fn pixel(id: vec3<u32>) -> bool {
    return id.x < params.size.x && id.y < params.size.y;
}

// Range limits, the border mask and the specular test (misslam_depth_postprocess::maps::
// limit_range, clean_into's border, maps::specular_mask before its dilation).
@compute @workgroup_size(8, 8, 1)
fn masks(@builtin(global_invocation_id) id: vec3<u32>) {
    if (!pixel(id)) {
        return;
    }
    let w = params.size.x;
    let c = params.size.z;
    let flags = params.size.w;
    let i = id.y * w + id.x;
    var z = depth_in[i];
    let in_range = is_finite(z) && z > 0.0 && z >= params.ranges.x && z <= params.ranges.y;
    if (!in_range) {
        if (!is_nan(z)) {
            atomicAdd(&counts[OUT_OF_RANGE], 1u);
        }
        z = nan();
    }
    var hi = 0u;
    var lo = 255u;
    for (var k = 0u; k < c; k = k + 1u) {
        let b = image_byte(i * c + k);
        hi = max(hi, b);
        lo = min(lo, b);
    }
    var bad = false;
    if ((flags & FLAG_BORDER_MASK) != 0u) {
        bad = mask_byte(i) == 0u;
    } else if ((flags & FLAG_BORDER_LEVEL) != 0u) {
        bad = hi < params.levels.x;
    }
    if (bad && is_finite(z)) {
        atomicAdd(&counts[BORDER], 1u);
        z = nan();
    }
    depth_masked[i] = z;
    var s = 0u;
    if ((flags & FLAG_SPECULAR) != 0u && c > 0u) {
        let widest = i32(tables[params.offsets.y + hi]);
        if (hi >= params.levels.y && i32(hi - lo) <= widest) {
            s = 1u;
        }
    }
    specular[i] = s;
}

// The specular mask's dilation along rows (maps::dilate's row pass).
@compute @workgroup_size(8, 8, 1)
fn dilate_rows(@builtin(global_invocation_id) id: vec3<u32>) {
    if (!pixel(id)) {
        return;
    }
    let w = params.size.x;
    let r = params.levels.z;
    let row = id.y * w;
    var m = 0u;
    let last = min(id.x + r, w - 1u);
    for (var x = id.x - min(id.x, r); x <= last; x = x + 1u) {
        m = max(m, specular[row + x]);
    }
    specular_rows[row + id.x] = m;
}

// The dilation along columns, the specular mask applied, and the map the filter reads.
@compute @workgroup_size(8, 8, 1)
fn apply_specular(@builtin(global_invocation_id) id: vec3<u32>) {
    if (!pixel(id)) {
        return;
    }
    let w = params.size.x;
    let h = params.size.y;
    let r = params.levels.z;
    let i = id.y * w + id.x;
    var z = depth_masked[i];
    if ((params.size.w & FLAG_SPECULAR) != 0u) {
        var m = 0u;
        let last = min(id.y + r, h - 1u);
        for (var y = id.y - min(id.y, r); y <= last; y = y + 1u) {
            m = max(m, specular_rows[y * w + id.x]);
        }
        if (m != 0u && is_finite(z)) {
            atomicAdd(&counts[SPECULAR], 1u);
            z = nan();
        }
    }
    depth_clean[i] = z;
    depth_far[i] = select(FAR, z, is_finite(z));
}

// The bilateral filter (maps::bilateral, maps::pixel_sums): the taps inside the image in window
// order, rows then columns; without smoothing the depth passes through.
@compute @workgroup_size(8, 8, 1)
fn bilateral(@builtin(global_invocation_id) id: vec3<u32>) {
    if (!pixel(id)) {
        return;
    }
    let w = params.size.x;
    let h = params.size.y;
    let i = id.y * w + id.x;
    let z = depth_clean[i];
    if ((params.size.w & FLAG_BILATERAL) == 0u || !is_finite(z)) {
        depth_out[i] = z;
        return;
    }
    let r = params.levels.w;
    let side = 2u * r + 1u;
    let scale = params.ranges.z;
    var num = 0.0;
    var den = 0.0;
    let y_last = min(id.y + r, h - 1u);
    let x_first = id.x - min(id.x, r);
    let x_last = min(id.x + r, w - 1u);
    for (var y = id.y - min(id.y, r); y <= y_last; y = y + 1u) {
        let spatial_row = params.offsets.x + (y + r - id.y) * side;
        for (var x = x_first; x <= x_last; x = x + 1u) {
            let v = depth_far[y * w + x];
            let k = min(abs(v - z) * scale, f32(RANGE_LUT));
            let index = min(u32(k), RANGE_LUT);
            let wgt = tables[spatial_row + x + r - id.x] * tables[index];
            num = num + wgt * v;
            den = den + wgt;
        }
    }
    depth_out[i] = num / den;
}

// Camera-frame points, Z K^-1 [u v 1]^T (maps::vertex_normal_maps_into).
@compute @workgroup_size(8, 8, 1)
fn lift(@builtin(global_invocation_id) id: vec3<u32>) {
    if (!pixel(id)) {
        return;
    }
    let i = id.y * params.size.x + id.x;
    let z = depth_out[i];
    var p = vec3<f32>(nan(), nan(), nan());
    if (is_finite(z) && z > 0.0) {
        p = vec3<f32>(
            tables[params.offsets.z + id.x] * z,
            tables[params.offsets.w + id.y] * z,
            z
        );
    }
    vertices[3u * i] = p.x;
    vertices[3u * i + 1u] = p.y;
    vertices[3u * i + 2u] = p.z;
}

fn vertex(i: u32) -> vec3<f32> {
    return vec3<f32>(vertices[3u * i], vertices[3u * i + 1u], vertices[3u * i + 2u]);
}

// A neighbour that stops the normal: invalid, or across a depth step.
fn breaks(q: vec3<f32>, z: f32) -> bool {
    if (!is_finite(q.z)) {
        return true;
    }
    return (params.size.w & FLAG_STEP_LIMIT) != 0u && abs(q.z - z) > params.ranges.w;
}

// Normals: the cross product of central differences, towards the camera (as the CPU's
// vertex_normal_maps_into).
@compute @workgroup_size(8, 8, 1)
fn normal(@builtin(global_invocation_id) id: vec3<u32>) {
    if (!pixel(id)) {
        return;
    }
    let w = params.size.x;
    let h = params.size.y;
    let x = id.x;
    let y = id.y;
    let i = y * w + x;
    var out = vec3<f32>(nan(), nan(), nan());
    if (y > 0u && y + 1u < h && w >= 3u && x > 0u && x + 1u < w) {
        let p = vertex(i);
        if (is_finite(p.z)) {
            let l = vertex(i - 1u);
            let r = vertex(i + 1u);
            let u = vertex(i - w);
            let d = vertex(i + w);
            if (!(breaks(l, p.z) || breaks(r, p.z) || breaks(u, p.z) || breaks(d, p.z))) {
                let a = r - l;
                let b = d - u;
                let n = vec3<f32>(
                    a.y * b.z - a.z * b.y,
                    a.z * b.x - a.x * b.z,
                    a.x * b.y - a.y * b.x
                );
                let len = sqrt(n.x * n.x + n.y * n.y + n.z * n.z);
                if (!is_nan(len) && len > 0.0) {
                    var s = 1.0 / len;
                    if (n.x * p.x + n.y * p.y + n.z * p.z > 0.0) {
                        s = -1.0 / len;
                    }
                    out = n * s;
                }
            }
        }
    }
    normals[3u * i] = out.x;
    normals[3u * i + 1u] = out.y;
    normals[3u * i + 2u] = out.z;
}
