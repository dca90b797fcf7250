//! `misslam phantom export`: the phantom as a dataset folder that `source.stereo_folder` (and
//! other tools) read, with its ground truth beside the images.

use std::io::Write;
use std::path::Path;

use misslam_framework::registry::parse_params;
use misslam_sink_files::{mesh_io, pfm};
use misslam_source_phantom::{Params, Phantom};

/// What the folder holds; also written into it as README.md.
pub const LAYOUT: &str = "# misslam phantom export

| path | content |
|---|---|
| `calib.toml` | rectified calibration (width, height, fx, fy, cx, cy, baseline_mm, doffs) |
| `left/<n>.png`, `right/<n>.png` | the rectified pair of frame n (8-bit sRGB) |
| `depth_gt/<n>.pfm` | exact depth of the left view, mm, NaN where no tissue (1-channel PFM, rows bottom-up) |
| `disparity_gt/<n>.pfm` | exact disparity of the left view, px: `d = fx * baseline_mm / Z - doffs` |
| `rest_points_gt/<n>.pfm` | per left pixel, the rest-shape point it sees, mm, world frame at t = 0 (3-channel PFM) |
| `mesh_gt/<n>.ply` | the tissue surface at frame n, world frame, mm (binary PLY with normals and colours) |
| `poses_gt.txt` | TUM format, one line per frame: `t tx ty tz qx qy qz qw`, world_from_camera of the left camera, mm |
| `params.toml` | the phantom parameters that made it |

World frame: the left camera at t = 0 (x right, y down, z forward).
";

/// Exports `frames` frames of the phantom made from `params` (TOML keys of `source.phantom`).
pub fn export(
    params: &misslam_framework::toml::Table,
    seed: u64,
    out: &Path,
) -> Result<u64, String> {
    let p: Params = parse_params(params).map_err(|e| format!("phantom parameters: {e}"))?;
    let frames = p.frames;
    let params_text = misslam_framework::toml::to_string(&p).map_err(|e| e.to_string())?;
    let mut phantom = Phantom::new(p, seed)?;
    let io = |path: &Path, e: std::io::Error| format!("{}: {e}", path.display());
    for dir in [
        "left",
        "right",
        "depth_gt",
        "disparity_gt",
        "rest_points_gt",
        "mesh_gt",
    ] {
        let d = out.join(dir);
        std::fs::create_dir_all(&d).map_err(|e| io(&d, e))?;
    }
    let c = *phantom.calib();
    let calib = format!(
        "# Rectified stereo calibration of a misslam phantom (pinhole, no distortion).\nwidth = {}\nheight = {}\nfx = {}\nfy = {}\ncx = {}\ncy = {}\nbaseline_mm = {}\ndoffs = {}\n",
        c.width,
        c.height,
        c.fx,
        c.fy,
        c.cx,
        c.cy,
        c.baseline_mm,
        c.doffs()
    );
    for (name, text) in [
        ("calib.toml", calib.as_str()),
        ("README.md", LAYOUT),
        ("params.toml", params_text.as_str()),
    ] {
        let path = out.join(name);
        std::fs::write(&path, text).map_err(|e| io(&path, e))?;
    }
    let poses_path = out.join("poses_gt.txt");
    let mut poses = std::fs::File::create(&poses_path).map_err(|e| io(&poses_path, e))?;
    let mut n = 0;
    while let Some(f) = phantom.render(n) {
        let png = |dir: &str, img: &misslam_framework::Image| {
            let path = out.join(dir).join(format!("{n}.png"));
            image::save_buffer(
                &path,
                &img.data,
                img.width,
                img.height,
                image::ExtendedColorType::Rgb8,
            )
            .map_err(|e| format!("{}: {e}", path.display()))
        };
        png("left", &f.stereo.left)?;
        png("right", &f.stereo.right)?;
        let path = out.join("depth_gt").join(format!("{n}.pfm"));
        pfm::write_pfm(&path, &f.depth.map).map_err(|e| io(&path, e))?;
        let path = out.join("disparity_gt").join(format!("{n}.pfm"));
        pfm::write_pfm(&path, &f.disparity.map).map_err(|e| io(&path, e))?;
        let path = out.join("rest_points_gt").join(format!("{n}.pfm"));
        pfm::write_pfm3(
            &path,
            f.rest_points.width,
            f.rest_points.height,
            &f.rest_points.points,
        )
        .map_err(|e| io(&path, e))?;
        let path = out.join("mesh_gt").join(format!("{n}.ply"));
        let g = mesh_io::Geometry {
            positions: &f.mesh.vertices,
            normals: f.mesh.normals.as_deref(),
            colors: f.mesh.colors.as_deref(),
            triangles: &f.mesh.triangles,
        };
        mesh_io::write_ply(&path, &g).map_err(|e| io(&path, e))?;
        let iso = f.pose.world_from_camera;
        let (t, q) = (iso.translation.vector, iso.rotation);
        writeln!(
            poses,
            "{:.6} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
            f.stereo.timestamp, t.x, t.y, t.z, q.i, q.j, q.k, q.w
        )
        .map_err(|e| io(&poses_path, e))?;
        n += 1;
    }
    debug_assert_eq!(n, frames);
    Ok(n)
}
