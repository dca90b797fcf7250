//! `misslam eval depth`: scores a folder of estimated depth maps (`<frame>.pfm`, mm, named by
//! frame index as `sink.files` writes them) against the ground truth of a dataset folder, with
//! the same scoring as the `eval.depth` node.

use std::path::Path;

use misslam_eval_depth::{score, DepthScores, Params as EvalParams};
use misslam_framework::{pfm, DepthMap};
use misslam_source_stereo_folder::depth_gt::DepthGtFormat;
use misslam_source_stereo_folder::{Params as FolderParams, StereoFolder};
use serde::Serialize;

/// Scores of one frame.
#[derive(Debug, Serialize)]
pub struct FrameRow {
    /// Frame index (position in the dataset's sorted pairs).
    pub frame: u64,
    /// The dataset's file number of that frame.
    pub file_number: u64,
    /// % bad at 1 px.
    pub bad1_pct: f64,
    /// % bad at 2 px.
    pub bad2_pct: f64,
    /// % bad at 2 px over estimated pixels.
    pub bad2_valid_pct: f64,
    /// Mean absolute depth error, mm.
    pub mae_mm: f64,
    /// Mean signed depth error (estimate minus GT), mm.
    pub bias_mm: f64,
    /// % of GT pixels estimated.
    pub density_pct: f64,
}

/// Scores every `<k>.pfm` in `est_dir` against frame k of `dataset`.
pub fn eval_depth(
    est_dir: &Path,
    dataset: &Path,
    gt_format: DepthGtFormat,
    params: &EvalParams,
) -> Result<Vec<FrameRow>, String> {
    if gt_format == DepthGtFormat::None {
        return Err("--gt-format must be pfm or colonsyn_rgb".into());
    }
    let folder = StereoFolder::open(
        FolderParams {
            path: dataset.to_owned(),
            depth_gt: gt_format,
            ..FolderParams::default()
        },
        dataset.to_owned(),
    )?;
    let mut files: Vec<(u64, std::path::PathBuf)> = std::fs::read_dir(est_dir)
        .map_err(|e| format!("{}: {e}", est_dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "pfm"))
        .filter_map(|p| {
            p.file_stem()?
                .to_str()?
                .parse::<u64>()
                .ok()
                .map(|k| (k, p.clone()))
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(format!("{} holds no <frame>.pfm files", est_dir.display()));
    }
    let calib = *folder.calib();
    let mut rows = Vec::new();
    for (k, path) in files {
        let gt = folder.read_depth_gt(k as usize)?.ok_or_else(|| {
            format!(
                "{}: frame {k} is past the end of {}",
                path.display(),
                dataset.display()
            )
        })?;
        let map = pfm::read_pfm(&path).map_err(|e| e.to_string())?;
        let est = DepthMap { map, calib };
        let s: DepthScores =
            score(&est, &gt, params).map_err(|e| format!("{}: {e}", path.display()))?;
        rows.push(FrameRow {
            frame: k,
            file_number: folder.files(k as usize).map_or(k, |f| f.number),
            bad1_pct: s.bad1_pct,
            bad2_pct: s.bad2_pct,
            bad2_valid_pct: s.bad2_valid_pct,
            mae_mm: s.mae_mm,
            bias_mm: s.bias_mm,
            density_pct: s.density_pct,
        });
    }
    Ok(rows)
}

/// Means over frames under the `depth.*` keys (frames with nothing to score left out).
pub fn summary(rows: &[FrameRow]) -> std::collections::BTreeMap<String, f64> {
    let mut means = misslam_framework::metrics::FrameMeans::default();
    for r in rows {
        means.add([
            ("depth.bad1_pct".to_owned(), r.bad1_pct),
            ("depth.bad2_pct".to_owned(), r.bad2_pct),
            ("depth.bad2_valid_pct".to_owned(), r.bad2_valid_pct),
            ("depth.mae_mm".to_owned(), r.mae_mm),
            ("depth.bias_mm".to_owned(), r.bias_mm),
            ("depth.density_pct".to_owned(), r.density_pct),
        ]);
    }
    means.means().map(|(k, v)| (k.to_owned(), v)).collect()
}

/// A trajectory file in TUM layout (`key tx ty tz qx qy qz qw`, `#` comments): the first column
/// and the pose of every line, in file order.
pub fn read_tum(
    path: &Path,
) -> Result<Vec<(f64, misslam_framework::nalgebra::Isometry3<f64>)>, String> {
    use misslam_framework::nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|t| t.parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|e| format!("{}:{}: {e}", path.display(), n + 1))?;
        if v.len() != 8 || v.iter().any(|x| !x.is_finite()) {
            return Err(format!(
                "{}:{}: expected 8 finite numbers (key tx ty tz qx qy qz qw), got `{line}`",
                path.display(),
                n + 1
            ));
        }
        let q = Quaternion::new(v[7], v[4], v[5], v[6]);
        if (q.norm() - 1.0).abs() > 1e-3 {
            return Err(format!(
                "{}:{}: the quaternion has norm {}, not 1",
                path.display(),
                n + 1,
                q.norm()
            ));
        }
        out.push((
            v[0],
            Isometry3::from_parts(
                Translation3::new(v[1], v[2], v[3]),
                UnitQuaternion::from_quaternion(q),
            ),
        ));
    }
    Ok(out)
}

/// Scores an estimated trajectory (as `sink.files` writes it: the first column is the frame
/// index, lost frames are comments) against a GT trajectory whose line k is frame k (as
/// `misslam phantom export` writes `poses_gt.txt`).
pub fn eval_tracking(
    est: &Path,
    gt: &Path,
    align: misslam_eval_tracking::Align,
) -> Result<misslam_eval_tracking::TrackingScores, String> {
    let e = read_tum(est)?;
    let g: Vec<_> = read_tum(gt)?.into_iter().map(|(_, p)| p).collect();
    if g.is_empty() {
        return Err(format!("{}: no poses", gt.display()));
    }
    let mut per_frame = vec![None; g.len()];
    for (k, pose) in e {
        if k < 0.0 || k.fract() != 0.0 {
            return Err(format!(
                "{}: the first column must be a frame index, got {k}",
                est.display()
            ));
        }
        let k = k as usize;
        if k >= g.len() {
            return Err(format!(
                "{}: frame {k} is past the {} frames of {}",
                est.display(),
                g.len(),
                gt.display()
            ));
        }
        per_frame[k] = Some(pose);
    }
    Ok(misslam_eval_tracking::score(&per_frame, &g, align))
}

/// Scores a saved reconstruction (its vertices: a surfel model, point cloud or mesh as PLY, OBJ
/// or glTF) against a GT mesh file, as the `eval.recon` node does.
pub fn eval_recon(est: &Path, gt: &Path) -> Result<misslam_eval_recon::ReconScores, String> {
    use misslam_source_phantom::mesh_input::read_geometry;
    // The readers name the file in their messages.
    let e = read_geometry(est)?;
    let g = read_geometry(gt)?;
    if g.triangles.is_empty() {
        return Err(format!(
            "{}: the GT must be a mesh with triangles",
            gt.display()
        ));
    }
    let mesh = misslam_framework::Mesh {
        vertices: g.vertices,
        normals: None,
        colors: None,
        triangles: g.triangles,
    };
    misslam_eval_recon::score(&e.vertices, &mesh).map(|(s, _)| s)
}
