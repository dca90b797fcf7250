//! Ground-truth depth stored beside a stereo sequence.
//!
//! - `pfm`: `depth_gt/<n>.pfm`, depth in mm (what `misslam phantom export` writes).
//! - `colonsyn_rgb`: `depth_gt/depth_<n, 7 digits>.png`, the RGB encoding of the synthetic colon
//!   sets: `Z = 10 * ((b + 1)/256 + 100 (g + 1)/256 + (r + 1)/256 - 0.5)` mm (the source's units
//!   are cm, and its evaluation script subtracts 0.5). Checked against the stereo pairs: with this
//!   decoding, left pixels and their disparity-shifted partners differ by 4.69 gray levels on
//!   average over colonsyn30 frames 1, 3, 5, 7, 9, against 5.85 without the 0.5 offset (the best
//!   offset found, 0.55, gives 4.62).

use std::path::{Path, PathBuf};

use misslam_framework::FloatMap;

/// How ground-truth depth is stored.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum DepthGtFormat {
    /// No ground truth: the `depth_gt` port stays empty.
    #[default]
    None,
    /// `<dir>/<n>.pfm`, mm.
    Pfm,
    /// `<dir>/depth_<n:07>.png`, the ColonSyn RGB encoding.
    ColonsynRgb,
}

/// The file holding frame number `n`'s GT depth.
pub fn depth_gt_path(dir: &Path, format: DepthGtFormat, n: u64) -> Option<PathBuf> {
    match format {
        DepthGtFormat::None => None,
        DepthGtFormat::Pfm => Some(dir.join(format!("{n}.pfm"))),
        DepthGtFormat::ColonsynRgb => Some(dir.join(format!("depth_{n:07}.png"))),
    }
}

/// Decodes one ColonSyn RGB depth pixel to mm; NaN where the code is not a positive depth.
#[inline]
pub fn colonsyn_depth_mm(r: u8, g: u8, b: u8) -> f32 {
    let z = 10.0
        * ((b as f32 + 1.0) / 256.0 + 100.0 * (g as f32 + 1.0) / 256.0 + (r as f32 + 1.0) / 256.0
            - 0.5);
    if z > 0.0 {
        z
    } else {
        f32::NAN
    }
}

/// Reads GT depth of frame number `n`, checking its size. Errors name the file.
pub fn read_depth_gt(
    dir: &Path,
    format: DepthGtFormat,
    n: u64,
    size: (u32, u32),
) -> Result<Option<FloatMap>, String> {
    let Some(path) = depth_gt_path(dir, format, n) else {
        return Ok(None);
    };
    if !path.exists() {
        return Err(format!("{} is missing", path.display()));
    }
    let map = match format {
        DepthGtFormat::None => return Ok(None),
        DepthGtFormat::Pfm => misslam_framework::pfm::read_pfm(&path).map_err(|e| e.to_string())?,
        DepthGtFormat::ColonsynRgb => {
            let img = image::open(&path)
                .map_err(|e| format!("{}: cannot decode: {e}", path.display()))?
                .into_rgb8();
            let (width, height) = img.dimensions();
            let data = img
                .pixels()
                .map(|p| colonsyn_depth_mm(p[0], p[1], p[2]))
                .collect();
            FloatMap {
                width,
                height,
                data,
            }
        }
    };
    if (map.width, map.height) != size {
        return Err(format!(
            "{} is {}x{}, the images are {}x{}",
            path.display(),
            map.width,
            map.height,
            size.0,
            size.1
        ));
    }
    Ok(Some(map))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colonsyn_decoding() {
        // (145, 33, 0): 10 * (1/256 + 3400/256 + 146/256 - 0.5) = 133.71 mm.
        let z = colonsyn_depth_mm(145, 33, 0);
        assert!((z - 10.0 * (3547.0 / 256.0 - 0.5)).abs() < 1e-4, "{z}");
        assert!(colonsyn_depth_mm(0, 0, 0).is_nan());
        assert_eq!(
            depth_gt_path(Path::new("d"), DepthGtFormat::ColonsynRgb, 7),
            Some(PathBuf::from("d/depth_0000007.png"))
        );
    }
}
