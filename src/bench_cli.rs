//! The `misslam bench` subcommands: their arguments and the tables they print.

use crate::{count, count_usize, write_json};
use anyhow::Context;
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Subcommand)]
pub(crate) enum BenchCommand {
    /// ELAS on a rectified pair: the time of each step (median of runs; threads as
    /// RAYON_NUM_THREADS says) and, with `--out`, the left disparity as PFM.
    Elas {
        /// Left image (PNG, PGM; converted to gray).
        #[arg(long)]
        left: PathBuf,
        /// Right image.
        #[arg(long)]
        right: PathBuf,
        /// robotics or middlebury.
        #[arg(long, default_value = "robotics")]
        preset: String,
        /// Largest disparity searched.
        #[arg(long, default_value_t = 255)]
        disp_max: u32,
        /// Sub-pixel refinement (off in libelas's presets).
        #[arg(long)]
        subpixel: bool,
        /// The dense matching on the GPU (`device = "gpu"`), compared with the CPU's output.
        #[arg(long)]
        gpu: bool,
        /// Runs.
        #[arg(long, default_value_t = 5, value_parser = count_usize)]
        repeat: usize,
        /// Write the left disparity here (PFM, NaN invalid).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// `depth.postprocess`'s bilateral filter on a depth map: the median time per map (threads
    /// as RAYON_NUM_THREADS says) and, with `--out`, the filtered map (benches/
    /// postprocess_vs_opencv.py compares it with OpenCV's `bilateralFilter` in the same run).
    Bilateral {
        /// Depth map (PFM, mm, NaN invalid).
        #[arg(long)]
        depth: PathBuf,
        /// Window radius, pixels (`smooth_radius`).
        #[arg(long, default_value_t = 3)]
        radius: usize,
        /// Spatial sigma, pixels (`smooth_sigma_px`).
        #[arg(long, default_value_t = 2.0)]
        sigma_px: f32,
        /// Depth sigma, mm (`smooth_sigma_mm`).
        #[arg(long, default_value_t = 1.5)]
        sigma_mm: f32,
        /// Timed runs (the median is reported).
        #[arg(long, default_value_t = 20, value_parser = count_usize)]
        repeat: usize,
        /// Write the filtered map here (PFM).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Write the figures as JSON here.
        #[arg(long)]
        json: Option<PathBuf>,
    },
    /// `depth.postprocess` on the GPU (`device = "gpu"`) against its CPU path on the same
    /// synthetic depth map and image, in turns: wall time and the process's CPU time per map
    /// (the CPU path's threads as RAYON_NUM_THREADS says), the GPU's stages, and how the outputs
    /// compare.
    PostGpu {
        /// Map width.
        #[arg(long, default_value_t = 640)]
        width: usize,
        /// Map height.
        #[arg(long, default_value_t = 480)]
        height: usize,
        /// Timed runs of each path (medians are reported).
        #[arg(long, default_value_t = 50, value_parser = count_usize)]
        repeat: usize,
        /// Write the figures as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// SGM on the CPU: the median time per pair and of each stage (census, forward pass,
    /// backward pass with the selection, left-right check with median and speckles); threads as
    /// RAYON_NUM_THREADS says.
    Sgm {
        /// Left image (PNG, PGM; converted to gray); without it a random-dot pair is made.
        #[arg(long, requires = "right")]
        left: Option<PathBuf>,
        /// Right image.
        #[arg(long, requires = "left")]
        right: Option<PathBuf>,
        /// Width of the random-dot pair.
        #[arg(long, default_value_t = 640)]
        width: usize,
        /// Height of the random-dot pair.
        #[arg(long, default_value_t = 480)]
        height: usize,
        /// Disparities searched.
        #[arg(long, default_value_t = 64)]
        disparities: u32,
        /// Aggregation paths, 4 or 8.
        #[arg(long, default_value_t = 8)]
        paths: u32,
        /// Timed runs (medians are reported).
        #[arg(long, default_value_t = 20, value_parser = count_usize)]
        repeat: usize,
        /// The widest lane code the kernels may use: avx512, avx2 or portable (default: as
        /// MISSLAM_SIMD says, else the widest the CPU has; the output says which ran).
        #[arg(long, value_parser = misslam_depth_sgm::simd::parse_level)]
        lanes: Option<misslam_depth_sgm::simd::Level>,
        /// Write the figures as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// SGM on the GPU (WGSL kernels) against the CPU path on the same pair in the same run:
    /// median ms per pair (upload and readback included), the stage breakdown, the parity.
    SgmGpu {
        /// Left image (PNG, PGM; converted to gray); without it a random-dot pair is made.
        #[arg(long, requires = "right")]
        left: Option<PathBuf>,
        /// Right image.
        #[arg(long, requires = "left")]
        right: Option<PathBuf>,
        /// Width of the random-dot pair.
        #[arg(long, default_value_t = 640)]
        width: usize,
        /// Height of the random-dot pair.
        #[arg(long, default_value_t = 480)]
        height: usize,
        /// Disparities searched.
        #[arg(long, default_value_t = 128)]
        disparities: u32,
        /// Aggregation paths, 4 or 8.
        #[arg(long, default_value_t = 8)]
        paths: u32,
        /// Layout of the path costs: auto, per_direction or summed (`depth.sgm`'s `gpu_volumes`).
        #[arg(long, default_value = "auto", value_parser = parse_volumes)]
        volumes: misslam_depth_sgm::sgm::GpuVolumes,
        /// How a path's invocations exchange their costs: auto, subgroup or workgroup
        /// (`depth.sgm`'s `gpu_exchange`).
        #[arg(long, default_value = "auto", value_parser = parse_exchange)]
        exchange: misslam_depth_sgm::sgm::GpuExchange,
        /// Summed costs by 32-bit atomics even where the adapter has 64-bit ones.
        #[arg(long)]
        atomics32: bool,
        /// Block on each pair's fence at once, without polling for it first (`depth.sgm`'s
        /// `gpu_wait = "block"`; by default it polls on a discrete GPU).
        #[arg(long)]
        block: bool,
        /// Timed runs (medians are reported).
        #[arg(long, default_value_t = 50, value_parser = count_usize)]
        repeat: usize,
        /// Write the figures as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Render speed of the phantom (both views and all GT) per scene at 640x480 and 360x288.
    Phantom {
        /// Frames per configuration.
        #[arg(long, default_value_t = 20, value_parser = count)]
        frames: u64,
        /// Also write the rows as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The thesis's Fig. 5.9: a map that grows every frame while the camera sees a bounded region;
    /// per frame, batch and decoupled ED: nodes, nodes solved, ms, mean error against GT (mm).
    EdScaling {
        /// Frames (the map grows from about 1,000 nodes by about 300 per frame at the defaults).
        #[arg(long, default_value_t = 30, value_parser = count_usize)]
        frames: usize,
        /// Camera advance per frame, mm.
        #[arg(long, default_value_t = 110.0)]
        advance_mm: f64,
        /// Node spacing, mm.
        #[arg(long, default_value_t = 5.0)]
        spacing_mm: f64,
        /// Solver iterations per frame.
        #[arg(long, default_value_t = 3)]
        iterations: usize,
        /// Batch: factorise all 12 unknowns of every node instead of first eliminating the
        /// affine parts of the nodes without data (same solution; times what that saves).
        #[arg(long)]
        full_factorisation: bool,
        /// Write the rows as JSON here (fields documented in ARCHITECTURE.md, "Benchmarks").
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// ORB on an image (single thread): detect-and-describe time, Hamming kNN time of the
    /// image's descriptors against a second image's, and the matches as JSON for scoring
    /// (benches/features_vs_opencv.py compares with OpenCV in the same run).
    Features {
        /// The image (PNG, PGM; converted to gray).
        #[arg(long)]
        image: PathBuf,
        /// A second image to match against (e.g. the first warped by a known homography).
        #[arg(long)]
        image2: Option<PathBuf>,
        /// Keypoints wanted.
        #[arg(long, default_value_t = 1000)]
        n_features: usize,
        /// quadtree, grid or none (none keeps the strongest corners, as OpenCV's ORB).
        #[arg(long, default_value = "quadtree")]
        distribution: String,
        /// The ORB tests: learned (rBRIEF) or gaussian (steered BRIEF).
        #[arg(long, default_value = "learned")]
        pattern: String,
        /// FAST threshold of the retry in empty cells (default: the plugin's, 7); 0 disables the
        /// retry, which with `--distribution none` is OpenCV's ORB detection rule.
        #[arg(long)]
        min_fast_threshold: Option<u8>,
        /// orb, or surf (SURF: `--n-features` caps the keypoints; timing only, no pair).
        #[arg(long, default_value = "orb")]
        detector: String,
        /// Timed repetitions (the median is reported).
        #[arg(long, default_value_t = 20, value_parser = count_usize)]
        repeat: usize,
        /// Write timings, keypoints and matches as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The scheduler's own cost per node per frame (budget: 50 us), on trivial nodes.
    RuntimeOverhead {
        /// Pass-through nodes per graph.
        #[arg(long, default_value_t = 32)]
        nodes: usize,
        /// Frames per configuration.
        #[arg(long, default_value_t = 5000, value_parser = count)]
        frames: u64,
        /// Also write the rows as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

/// Runs one benchmark and prints its table (and writes its JSON with `--out`).
pub(crate) fn run(which: BenchCommand) -> anyhow::Result<()> {
    match which {
        BenchCommand::Phantom { frames, out } => {
            let rows = misslam::bench::phantom(frames).map_err(anyhow::Error::msg)?;
            out!(
                "{:<8} {:>9} {:>7} {:>10} {:>8}",
                "scene",
                "size",
                "frames",
                "ms/frame",
                "fps"
            );
            for r in &rows {
                out!(
                    "{:<8} {:>9} {:>7} {:>10.1} {:>8.1}",
                    r.scene,
                    format!("{}x{}", r.width, r.height),
                    r.frames,
                    r.ms_per_frame,
                    r.fps
                );
            }
            if let Some(path) = out {
                write_json(&path, &rows)?;
            }
            Ok(())
        }
        BenchCommand::EdScaling {
            frames,
            advance_mm,
            spacing_mm,
            iterations,
            full_factorisation,
            out,
        } => {
            let p = misslam::bench::EdScalingParams {
                frames,
                advance_mm,
                spacing_mm,
                iterations,
                full_factorisation,
                ..Default::default()
            };
            let rows = misslam::bench::ed_scaling(&p).map_err(anyhow::Error::msg)?;
            out!(
                "{:>5} {:>7} {:>7} {:>8} {:>9} {:>4} {:>9} {:>9} {:>9} {:>8} {:>9} {:>9} {:>9}",
                "frame",
                "nodes",
                "visible",
                "batch n",
                "batch ms",
                "it",
                "ms/it",
                "batch mm",
                "seen mm",
                "dec n",
                "dec ms",
                "dec mm",
                "seen mm"
            );
            for r in &rows {
                out!(
                    "{:>5} {:>7} {:>7} {:>8} {:>9.1} {:>4} {:>9.1} {:>9.3} {:>9.3} {:>8} {:>9.1} {:>9.3} {:>9.3}",
                    r.frame,
                    r.total_nodes,
                    r.visible_points,
                    r.batch_solved,
                    r.batch_ms,
                    r.batch_iterations,
                    (r.batch_assemble_ms + r.batch_factor_ms) / r.batch_iterations.max(1) as f64,
                    r.batch_err_mm,
                    r.batch_seen_err_mm,
                    r.decoupled_solved,
                    r.decoupled_ms,
                    r.decoupled_err_mm,
                    r.decoupled_seen_err_mm
                );
            }
            if let Some(path) = out {
                write_json(&path, &rows)?;
            }
            Ok(())
        }
        BenchCommand::Bilateral {
            depth,
            radius,
            sigma_px,
            sigma_mm,
            repeat,
            out,
            json,
        } => {
            let r = misslam::bench::bilateral(&depth, radius, sigma_px, sigma_mm, repeat)
                .map_err(anyhow::Error::msg)?;
            out!(
                "bilateral {}x{}, radius {radius}, sigma {sigma_px} px / {sigma_mm} mm, {} threads: {:.2} ms per map (median of {}, fastest {:.2}); {:.1} % valid",
                r.width, r.height, r.threads, r.ms, r.runs, r.min_ms, r.valid_pct
            );
            if let Some(path) = out {
                let map = misslam::framework::FloatMap {
                    width: r.width,
                    height: r.height,
                    data: r.filtered.clone(),
                };
                misslam::framework::pfm::write_pfm(&path, &map)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            if let Some(path) = json {
                write_json(&path, &r)?;
            }
            Ok(())
        }
        BenchCommand::Sgm {
            left,
            right,
            width,
            height,
            disparities,
            paths,
            repeat,
            lanes,
            out,
        } => {
            let p = misslam_depth_sgm::sgm::SgmParams {
                max_disparity: disparities,
                paths,
                ..Default::default()
            };
            let pair = left.as_deref().zip(right.as_deref());
            let r = misslam::bench::sgm_cpu(pair, (width, height), &p, repeat, lanes)
                .map_err(anyhow::Error::msg)?;
            let s = &r.stages_ms;
            out!(
                "SGM {}x{}, {} disparities, {} paths, {} threads, {} lanes: {:.1} ms per pair (median of {}, fastest {:.1}); density {:.1} %",
                r.width, r.height, r.disparities, r.paths, r.threads, r.lanes, r.ms, r.runs, r.min_ms, r.density_pct
            );
            out!(
                "stages: census {:.2}, forward {:.2}, backward + select {:.2}, finish {:.2}, total {:.2} ms",
                s.census_ms, s.forward_ms, s.backward_select_ms, s.finish_ms, s.total_ms
            );
            if let Some(path) = out {
                write_json(&path, &r)?;
            }
            Ok(())
        }
        BenchCommand::PostGpu {
            width,
            height,
            repeat,
            out,
        } => {
            let r = misslam::bench::post_gpu(width, height, repeat).map_err(anyhow::Error::msg)?;
            out!(
                "depth.postprocess {}x{} on {} (medians of {} runs each, in turns)",
                r.width,
                r.height,
                r.adapter,
                r.runs
            );
            out!(
                "CPU ({} threads): {:.3} ms a map, {:.2} ms of CPU; GPU: {:.3} ms a map (upload {:.3}, kernels and copy back {:.3}, readback {:.3}), {:.2} ms of CPU",
                r.cpu_threads,
                r.cpu_ms,
                r.cpu_cpu_ms,
                r.gpu_ms,
                r.gpu_upload_ms,
                r.gpu_kernels_ms,
                r.gpu_readback_ms,
                r.gpu_cpu_ms
            );
            out!(
                "parity: masks and counts {}; largest differences: depth {:.2e} mm, points {:.2e} mm, normals {:.2e}",
                if r.masks_equal { "equal" } else { "DIFFER" },
                r.max_depth_diff_mm,
                r.max_point_diff_mm,
                r.max_normal_diff
            );
            if let Some(path) = out {
                write_json(&path, &r)?;
            }
            Ok(())
        }
        BenchCommand::SgmGpu {
            left,
            right,
            width,
            height,
            disparities,
            paths,
            volumes,
            exchange,
            atomics32,
            block,
            repeat,
            out,
        } => {
            let p = misslam_depth_sgm::sgm::SgmParams {
                max_disparity: disparities,
                paths,
                gpu_volumes: volumes,
                gpu_exchange: exchange,
                gpu_wait: if block {
                    misslam_depth_sgm::sgm::GpuWait::Block
                } else {
                    misslam_depth_sgm::sgm::GpuWait::Auto
                },
                ..Default::default()
            };
            let pair = left.as_deref().zip(right.as_deref());
            let r = misslam::bench::sgm_gpu(pair, (width, height), &p, repeat, !atomics32)
                .map_err(anyhow::Error::msg)?;
            let s = &r.stages_ms;
            out!(
                "SGM {}x{}, {} disparities, {} paths on {}",
                r.width,
                r.height,
                r.disparities,
                r.paths,
                r.adapter
            );
            out!(
                "GPU {:.3} ms per pair (median of {}, fastest {:.3}); CPU ({} threads) {:.1} ms: {:.1}x",
                r.gpu_ms, r.runs, r.gpu_min_ms, r.cpu_threads, r.cpu_ms, r.speedup
            );
            out!(
                "GPU stream, two pairs in flight: {:.3} ms per pair (median of 3 streams of {}), {}",
                r.stream_ms,
                r.runs.max(2),
                if r.stream_identical {
                    "every pair identical to the pair alone"
                } else {
                    "SOME PAIRS DIFFER from the pair alone"
                }
            );
            out!(
                "stages ({}; {}; {}): upload {:.3}, census {:.3}, aggregate {:.3}, select {:.3}, median {:.3}, readback {:.3} (submission {:.3}, host copy {:.3}), speckles {:.3}, finish {:.3}, total {:.3} ms",
                if s.gpu_timestamps { "GPU timestamps" } else { "each waited for" },
                match (s.summed_volumes, s.atomics64) {
                    (true, true) => "costs summed into one volume, 64-bit atomics",
                    (true, false) => "costs summed into one volume, 32-bit atomics",
                    _ => "a volume per direction",
                },
                if s.subgroups { "subgroup exchange" } else { "workgroup exchange" },
                s.upload_ms, s.census_ms, s.aggregate_ms, s.select_ms, s.median_ms, s.readback_ms, s.submit_ms, s.copy_ms, s.speckle_ms, s.finish_ms, s.total_ms
            );
            out!(
                "parity with the CPU: {} pixels differ in validity, max |diff| {:.2e} px; density {:.1} %",
                r.validity_differs, r.max_abs_diff_px, r.density_pct
            );
            if let Some(path) = out {
                write_json(&path, &r)?;
            }
            Ok(())
        }
        BenchCommand::Elas {
            left,
            right,
            preset,
            disp_max,
            subpixel,
            gpu,
            repeat,
            out,
        } => {
            let mut p = match preset.as_str() {
                "robotics" => misslam_depth_elas::ElasParams::robotics(),
                "middlebury" => misslam_depth_elas::ElasParams::middlebury(),
                other => anyhow::bail!("--preset `{other}`: expected robotics or middlebury"),
            };
            p.disp_max = disp_max;
            p.subpixel = subpixel;
            let r =
                misslam::bench::elas(&left, &right, &p, repeat, gpu).map_err(anyhow::Error::msg)?;
            let s = r.steps_ms;
            out!(
                "ELAS {preset} {}x{}, disp_max {disp_max}: {:.1} ms (median of {repeat}); descriptors {:.1}, support {:.1} ({} points), triangulation {:.1}, dense {:.1}, postprocess {:.1}",
                r.width, r.height, r.ms, s[0], s[1], r.support_points, s[2], s[3], s[4]
            );
            if let (Some(a), Some(g), Some((validity, diff))) = (&r.gpu, r.dense_gpu_ms, r.parity) {
                out!(
                    "dense matching on {a}: raster {:.2}, upload {:.2}, kernel and readback {:.2} ms; against the CPU: {validity} pixels differ in validity, max |diff| {diff:.2e} px",
                    g[0], g[1], g[2]
                );
            }
            if let Some(path) = out {
                let map = misslam::framework::FloatMap {
                    width: r.width,
                    height: r.height,
                    data: r.disparity,
                };
                misslam::framework::pfm::write_pfm(&path, &map)
                    .with_context(|| format!("writing {}", path.display()))?;
            }
            Ok(())
        }
        BenchCommand::Features {
            image,
            image2,
            n_features,
            distribution,
            pattern,
            min_fast_threshold,
            detector,
            repeat,
            out,
        } => {
            if detector == "surf" {
                let (n, ms) =
                    misslam::bench::surf(&image, n_features, repeat).map_err(anyhow::Error::msg)?;
                out!("SURF: {n} keypoints, detect+describe {ms:.2} ms (median of {repeat}, 1 thread)");
                if let Some(path) = out {
                    let v = serde_json::json!({ "keypoints": n, "surf_ms": ms });
                    write_json(&path, &v)?;
                }
                return Ok(());
            }
            anyhow::ensure!(
                detector == "orb",
                "--detector `{detector}`: expected orb or surf"
            );
            let r = misslam::bench::features(
                &image,
                image2.as_deref(),
                n_features,
                &distribution,
                &pattern,
                min_fast_threshold,
                repeat,
            )
            .map_err(anyhow::Error::msg)?;
            out!(
                "ORB {}x{}: {} keypoints, detect+describe {:.2} ms (median of {repeat}, 1 thread)",
                r.width,
                r.height,
                r.keypoints,
                r.orb_ms
            );
            if let Some(ms) = r.knn_ms {
                out!(
                    "Hamming 2-NN {} x {}: {:.2} ms; {} matches (ratio 0.8, cross-check)",
                    r.keypoints,
                    r.keypoints2,
                    ms,
                    r.matches.len()
                );
            }
            if let Some(path) = out {
                write_json(&path, &r)?;
            }
            Ok(())
        }
        BenchCommand::RuntimeOverhead { nodes, frames, out } => {
            let dir = std::env::temp_dir().join(format!("misslam-bench-{}", std::process::id()));
            let rows = misslam::bench::runtime_overhead(nodes, frames, &dir)
                .map_err(anyhow::Error::msg)?;
            let _ = std::fs::remove_dir_all(&dir);
            out!(
                "{:<6} {:>6} {:>8} {:>9} {:>9} {:>11} {:>13} {:>10}",
                "shape",
                "nodes",
                "frames",
                "parallel",
                "pipeline",
                "frame us",
                "us/node/frame",
                "x budget"
            );
            for r in &rows {
                out!(
                    "{:<6} {:>6} {:>8} {:>9} {:>9} {:>11.2} {:>13.3} {:>10.4}",
                    r.shape,
                    r.nodes,
                    r.frames,
                    r.parallel,
                    r.pipeline,
                    r.frame_us,
                    r.per_node_us,
                    r.budget_ratio
                );
            }
            if let Some(path) = out {
                write_json(&path, &rows)?;
            }
            Ok(())
        }
    }
}

/// `--volumes` of `bench sgm-gpu`: the names `depth.sgm`'s `gpu_volumes` takes.
fn parse_volumes(s: &str) -> Result<misslam_depth_sgm::sgm::GpuVolumes, String> {
    serde_json::from_value(serde_json::Value::String(s.to_owned()))
        .map_err(|_| format!("`{s}`: expected auto, per_direction or summed"))
}

/// `--exchange` of `bench sgm-gpu`: the names `depth.sgm`'s `gpu_exchange` takes.
fn parse_exchange(s: &str) -> Result<misslam_depth_sgm::sgm::GpuExchange, String> {
    serde_json::from_value(serde_json::Value::String(s.to_owned()))
        .map_err(|_| format!("`{s}`: expected auto, subgroup or workgroup"))
}

#[cfg(test)]
mod tests {
    use super::{parse_exchange, parse_volumes};
    use misslam_depth_sgm::sgm::{GpuExchange, GpuVolumes};

    #[test]
    fn volumes_take_the_parameter_names() {
        assert_eq!(parse_volumes("summed"), Ok(GpuVolumes::Summed));
        assert_eq!(parse_volumes("per_direction"), Ok(GpuVolumes::PerDirection));
        assert_eq!(parse_volumes("auto"), Ok(GpuVolumes::Auto));
        assert!(parse_volumes("both").unwrap_err().contains("`both`"));
        assert_eq!(parse_exchange("subgroup"), Ok(GpuExchange::Subgroup));
        assert_eq!(parse_exchange("workgroup"), Ok(GpuExchange::Workgroup));
        assert_eq!(parse_exchange("auto"), Ok(GpuExchange::Auto));
        assert!(parse_exchange("warp").unwrap_err().contains("`warp`"));
    }
}
