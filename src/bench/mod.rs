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
