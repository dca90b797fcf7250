// The distance field function (DFF) of a depth scan by projection, one invocation per voxel.
// CPU reference: misslam_deformation_ed::field::ProjectiveField::value (the same f32 arithmetic
// in the same order). Voxel (x, y, z) has centre c = origin + (x, y, z) * voxel in the camera
// frame; c projects to the nearest pixel (u, v); over the pixels i of the (2 window + 1)^2 block
// around it whose point q_i and normal n_i are valid, |n_i . (c - q_i)| <= truncation and
// |c - q_i| <= 2 truncation, the voxel holds the mean of n_i . (c - q_i), else UNKNOWN (NaN on
// the host). `main_normals` also writes the mean of those n_i (CPU reference:
// ProjectiveField::value_and_normal), three floats a voxel.

struct Params {
    origin_voxel: vec4<f32>,   // origin x, y, z; voxel side
    intrinsics: vec4<f32>,     // fx, fy, cx, cy
    dims: vec4<u32>,           // voxels along x, y, z; invocations per row of the dispatch grid
    size_trunc: vec4<f32>,     // map width, map height, truncation; w: the window (u32 bits)
}

const UNKNOWN: f32 = 3.0e38;

@group(0) @binding(0) var<uniform> params: Params;
// Per pixel: x, y, z and w = 1 where the point and its normal are valid (0 otherwise).
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> normals: array<vec4<f32>>;
@group(0) @binding(3) var<storage, read_write> field: array<f32>;
@group(0) @binding(4) var<storage, read_write> field_normals: array<f32>;

struct Voxel {
    value: f32,
    normal: vec3<f32>,
}

// Voxel i's value and mean normal (UNKNOWN and 0 where no pixel counts).
fn voxel_at(i: u32) -> Voxel {
    let nx = params.dims.x;
    let ny = params.dims.y;
    let x = i % nx;
    let y = (i / nx) % ny;
    let z = i / (nx * ny);
    let voxel = params.origin_voxel.w;
    let c = params.origin_voxel.xyz + vec3<f32>(f32(x), f32(y), f32(z)) * voxel;
    var out = Voxel(UNKNOWN, vec3<f32>(0.0, 0.0, 0.0));
    if (c.z > 0.0) {
        let k = params.intrinsics;
        let uf = floor(k.x * c.x / c.z + k.z + 0.5);
        let vf = floor(k.y * c.y / c.z + k.w + 0.5);
        let w = i32(params.size_trunc.x);
        let h = i32(params.size_trunc.y);
        if (uf >= 0.0 && vf >= 0.0 && uf < params.size_trunc.x && vf < params.size_trunc.y) {
            let u = i32(uf);
            let v = i32(vf);
            let r = i32(bitcast<u32>(params.size_trunc.w));
            let t = params.size_trunc.z;
            var sum = 0.0;
            var nsum = vec3<f32>(0.0, 0.0, 0.0);
            var count = 0u;
            for (var y = max(v - r, 0); y <= min(v + r, h - 1); y = y + 1) {
                for (var x = max(u - r, 0); x <= min(u + r, w - 1); x = x + 1) {
                    let p = u32(y * w + x);
                    let q = points[p];
                    if (q.w > 0.5) {
                        let d = c - q.xyz;
                        let n = normals[p].xyz;
                        let s = n.x * d.x + n.y * d.y + n.z * d.z;
                        let r2 = d.x * d.x + d.y * d.y + d.z * d.z;
                        if (abs(s) <= t && r2 <= 4.0 * t * t) {
                            sum = sum + s;
                            nsum = vec3<f32>(nsum.x + n.x, nsum.y + n.y, nsum.z + n.z);
                            count = count + 1u;
                        }
                    }
                }
            }
            if (count > 0u) {
                let kf = f32(count);
                out = Voxel(sum / kf, vec3<f32>(nsum.x / kf, nsum.y / kf, nsum.z / kf));
            }
        }
    }
    return out;
}

fn voxel_index(gid: vec3<u32>) -> u32 {
    return gid.x + gid.y * params.dims.w;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = voxel_index(gid);
    if (i >= params.dims.x * params.dims.y * params.dims.z) {
        return;
    }
    field[i] = voxel_at(i).value;
}

@compute @workgroup_size(64)
fn main_normals(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = voxel_index(gid);
    if (i >= params.dims.x * params.dims.y * params.dims.z) {
        return;
    }
    let v = voxel_at(i);
    field[i] = v.value;
    field_normals[3u * i] = v.normal.x;
    field_normals[3u * i + 1u] = v.normal.y;
    field_normals[3u * i + 2u] = v.normal.z;
}
