// SGM step 2, the volume of sums (`gpu_volumes = "summed"`) with 32-bit atomics: every direction
// adds its L of four disparities to word s (d0, d0 + 1) and s + 1 (d0 + 2, d0 + 3), u16 lanes
// that never carry (eight paths of at most 4063 each). `sgm_sums64.wgsl` does the same with one
// 64-bit atomic where the adapter has them; the words are the same.

@group(0) @binding(4) var<storage, read_write> sums: array<atomic<u32>>;

// Adds the four sums `b` (each below 65536) at words s and s + 1 (s even).
fn add_sums(s: u32, b: vec4<u32>) {
    atomicAdd(&sums[s], b.x | (b.y << 16u));
    atomicAdd(&sums[s + 1u], b.z | (b.w << 16u));
}
