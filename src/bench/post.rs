//! `misslam bench bilateral`: `depth.postprocess`'s edge-preserving filter on a depth map
//! (benches/postprocess_vs_opencv.py runs OpenCV's `bilateralFilter` on the same map in the same
//! run).

use super::median_ms;
use std::path::Path;
use std::time::Instant;

/// What `misslam bench bilateral` measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct BilateralBench {
    /// Map size, pixels.
    pub width: u32,
    /// Map height, pixels.
    pub height: u32,
    /// Window radius, pixels (a square of 2 radius + 1 a side).
    pub radius: usize,
    /// Spatial sigma, pixels.
    pub sigma_px: f32,
    /// Depth sigma, mm.
    pub sigma_mm: f32,
    /// Threads of the pool it ran on.
    pub threads: usize,
    /// Timed runs.
    pub runs: usize,
    /// Median ms per map.
    pub ms: f64,
    /// Fastest run, ms.
    pub min_ms: f64,
    /// Valid (finite) pixels of the input, percent.
    pub valid_pct: f64,
    /// The filtered map (not in the JSON).
    #[serde(skip)]
    pub filtered: Vec<f32>,
}

/// Filters the depth map at `path` (PFM, mm, NaN invalid) `repeat` times with the parameters of
/// `depth.postprocess` (checked as the node checks them; the message names the field).
pub fn bilateral(
    path: &Path,
    radius: usize,
    sigma_px: f32,
    sigma_mm: f32,
    repeat: usize,
) -> Result<BilateralBench, String> {
    let p = misslam_depth_postprocess::Params {
        smooth_radius: radius,
        smooth_sigma_px: sigma_px,
        smooth_sigma_mm: sigma_mm,
        ..Default::default()
    };
    p.validate().map_err(|e| {
        format!("{e} (`--radius`, `--sigma-px` and `--sigma-mm` set the node's `smooth_radius`, `smooth_sigma_px` and `smooth_sigma_mm`)")
    })?;
    let map =
        misslam_framework::pfm::read_pfm(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let (w, h) = (map.width as usize, map.height as usize);
    let run =
        || misslam_depth_postprocess::maps::bilateral(&map.data, w, h, radius, sigma_px, sigma_mm);
    let mut filtered = run();
    let mut min_ms = f64::INFINITY;
    let ms = median_ms(repeat, || {
        let t = Instant::now();
        filtered = run();
        min_ms = min_ms.min(t.elapsed().as_secs_f64() * 1e3);
        Ok::<(), String>(())
    })?;
    let valid = map.data.iter().filter(|v| v.is_finite()).count();
    Ok(BilateralBench {
        width: map.width,
        height: map.height,
        radius,
        sigma_px,
        sigma_mm,
        threads: rayon::current_num_threads(),
        runs: repeat.max(1),
        ms,
        min_ms,
        valid_pct: 100.0 * valid as f64 / (w * h).max(1) as f64,
        filtered,
    })
}
