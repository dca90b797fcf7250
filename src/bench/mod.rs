//! The benchmarks behind `misslam bench`, one module per subject; the shared timing helpers.

mod ed;
mod features;
mod phantom;
mod post;
mod runtime;
mod stereo;

use std::path::Path;
use std::time::Instant;

pub use ed::{ed_scaling, EdScalingParams, EdScalingRow};
pub use features::{features, surf, FeaturesBench};
pub use phantom::{phantom, PhantomRow};
pub use post::{bilateral, post_gpu, post_scene, BilateralBench, PostGpuBench};
pub use runtime::{runtime_overhead, OverheadRow};
pub use stereo::{
    disparity_parity, elas, random_dot_pair, sgm_cpu, sgm_gpu, ElasBench, SgmCpuBench, SgmGpuBench,
};

/// A seeded stream of pseudo-random bytes (xorshift64) for the synthetic inputs of the benchmarks
/// and the tests: the same seed, the same bytes.
pub struct SeededBytes(u64);

impl SeededBytes {
    /// The stream of `seed` (any value, 0 included).
    pub fn new(seed: u64) -> Self {
        SeededBytes(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1)
    }

    /// The next `n` bytes.
    pub fn bytes(&mut self, n: usize) -> Vec<u8> {
        self.take(n).collect()
    }
}

impl Iterator for SeededBytes {
    type Item = u8;

    fn next(&mut self) -> Option<u8> {
        let s = &mut self.0;
        *s ^= *s << 13;
        *s ^= *s >> 7;
        *s ^= *s << 17;
        Some((*s >> 24) as u8)
    }
}

fn gray_image(path: &Path) -> Result<(u32, u32, Vec<u8>), String> {
    let img = image::open(path)
        .map_err(|e| format!("{}: {e}", path.display()))?
        .to_luma8();
    Ok((img.width(), img.height(), img.into_raw()))
}

/// Runs `f` `repeat` times (at least once) and returns the median wall time, ms.
fn median_ms<E>(repeat: usize, mut f: impl FnMut() -> Result<(), E>) -> Result<f64, E> {
    let mut v = Vec::with_capacity(repeat.max(1));
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        f()?;
        v.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median(v))
}

/// The median of `v` (the upper one of an even count; NaN when empty).
fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[cfg(test)]
mod seeded_bytes_tests {
    use super::SeededBytes;

    #[test]
    fn a_seed_gives_its_own_bytes_spread_over_the_range() {
        let a = SeededBytes::new(7).bytes(10_000);
        assert_eq!(
            a,
            SeededBytes::new(7).bytes(10_000),
            "the same seed, the same bytes"
        );
        assert_ne!(a, SeededBytes::new(8).bytes(10_000));
        for seed in [0, 7] {
            let v = SeededBytes::new(seed).bytes(10_000);
            let mean = v.iter().map(|&b| f64::from(b)).sum::<f64>() / v.len() as f64;
            let distinct = v.iter().collect::<std::collections::BTreeSet<_>>().len();
            assert!(
                (120.0..136.0).contains(&mean) && distinct == 256,
                "seed {seed}: mean {mean}, {distinct} values"
            );
        }
    }
}
