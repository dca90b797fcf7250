//! `misslam bench features`: ORB (and SURF) timing and matching on real images.

use std::path::Path;

use serde::Serialize;

use super::{gray_image, median_ms};

/// Result of `misslam bench features`.
#[derive(Debug, Serialize)]
pub struct FeaturesBench {
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Keypoints found in the first image.
    pub keypoints: usize,
    /// Keypoints found in the second image.
    pub keypoints2: usize,
    /// Median ORB detect-and-describe time on the first image, ms.
    pub orb_ms: f64,
    /// Median brute-force Hamming 2-NN time, first against second, ms.
    pub knn_ms: Option<f64>,
    /// Matches (ratio 0.8, cross-check) as `[x1, y1, x2, y2]`.
    pub matches: Vec<[f32; 4]>,
}

/// ORB timing and matching on one image or a pair (see [`FeaturesBench`]).
pub fn features(
    image: &Path,
    image2: Option<&Path>,
    n_features: usize,
    distribution: &str,
    pattern: &str,
    min_fast_threshold: Option<u8>,
    repeat: usize,
) -> Result<FeaturesBench, String> {
    use misslam_features_matching::{knn2_hamming, match_descriptors, MatchParams, MatchScratch};
    use misslam_features_orb::extract::{
        extract, Distribution, OrbParams, OrbScratch, PatternKind,
    };
    use misslam_framework::Descriptors;
    let distribution = match distribution {
        "quadtree" => Distribution::Quadtree,
        "grid" => Distribution::Grid,
        "none" => Distribution::None,
        other => {
            return Err(format!(
                "--distribution `{other}`: expected quadtree, grid or none"
            ))
        }
    };
    let pattern = match pattern {
        "learned" => PatternKind::Learned,
        "gaussian" => PatternKind::Gaussian,
        other => return Err(format!("--pattern `{other}`: expected learned or gaussian")),
    };
    let defaults = OrbParams::default();
    let p = OrbParams {
        n_features,
        distribution,
        pattern,
        min_fast_threshold: min_fast_threshold.unwrap_or(defaults.min_fast_threshold),
        ..defaults
    };
    p.validate()?;
    let (w, h, gray) = gray_image(image)?;
    let mut scratch = OrbScratch::default();
    let (mut k1, mut d1) = (Vec::new(), Vec::new());
    let orb_ms = median_ms(repeat, || {
        extract(
            &gray,
            w as usize,
            h as usize,
            &p,
            &mut scratch,
            &mut k1,
            &mut d1,
        )
    })?;
    let mut out = FeaturesBench {
        width: w,
        height: h,
        keypoints: k1.len(),
        keypoints2: 0,
        orb_ms,
        knn_ms: None,
        matches: Vec::new(),
    };
    if let Some(path2) = image2 {
        let (w2, h2, gray2) = gray_image(path2)?;
        let (mut k2, mut d2) = (Vec::new(), Vec::new());
        extract(
            &gray2,
            w2 as usize,
            h2 as usize,
            &p,
            &mut scratch,
            &mut k2,
            &mut d2,
        )?;
        out.keypoints2 = k2.len();
        let mut nn = Vec::new();
        let knn_ms = median_ms(repeat, || {
            knn2_hamming(&d1, &d2, &mut nn);
            Ok::<(), String>(())
        })?;
        out.knn_ms = Some(knn_ms);
        let m = match_descriptors(
            &Descriptors::Binary256(d1),
            &Descriptors::Binary256(d2),
            &MatchParams {
                ratio: 0.8,
                max_distance: 64.0,
                max_distance_l2: 0.4,
                cross_check: true,
            },
            &mut MatchScratch::default(),
        )?;
        out.matches = m
            .iter()
            .map(|m| {
                let (a, b) = (&k1[m.query as usize], &k2[m.train as usize]);
                [a.x, a.y, b.x, b.y]
            })
            .collect();
    }
    Ok(out)
}

/// SURF detect-and-describe on one image, one thread: (keypoints, median ms).
pub fn surf(image: &Path, max_keypoints: usize, repeat: usize) -> Result<(usize, f64), String> {
    use misslam_features_surf::surf::{extract, SurfParams, SurfScratch};
    let p = SurfParams {
        n_features: max_keypoints,
        ..SurfParams::default()
    };
    let (w, h, gray) = gray_image(image)?;
    let mut scratch = SurfScratch::default();
    let (mut k, mut d) = (Vec::new(), Vec::new());
    let ms = median_ms(repeat, || {
        extract(
            &gray,
            w as usize,
            h as usize,
            &p,
            &mut scratch,
            &mut k,
            &mut d,
        )
    })?;
    Ok((k.len(), ms))
}
