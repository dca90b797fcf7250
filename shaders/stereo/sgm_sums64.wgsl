// replaces: sgm_sums.wgsl
// SGM step 2, the volume of sums with one 64-bit atomic add per four disparities (wgpu's
// `SHADER_INT64_ATOMIC_ALL_OPS`), half the atomics of `sgm_sums.wgsl`, whose place it takes
// where the adapter has them: the same words, little-endian (word s in the low half).

@group(0) @binding(4) var<storage, read_write> sums: array<atomic<u64>>;

// Adds the four sums `b` (each below 65536) at words s and s + 1 (s even).
fn add_sums(s: u32, b: vec4<u32>) {
    let lo = u64(b.x | (b.y << 16u));
    let hi = u64(b.z | (b.w << 16u));
    atomicAdd(&sums[s / 2u], lo | (hi << 32u));
}
