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

/// A depth map and a left image like those `depth.postprocess` meets (the GPU parity test and
/// `misslam bench post-gpu` use them): a smooth surface at 45 to 75 mm with a fold (an 8 mm
/// step), noise of about 0.25 mm, invalid and out-of-range values on about 2.7 % of the pixels;
/// an image of `c` channels with a black border band, texture, near-white highlights (some
/// slightly tinted) and bright red patches (not highlights). Seeded, so a test's inputs never change.
pub fn post_scene(w: usize, h: usize, c: usize, seed: u64) -> (Vec<f32>, Vec<u8>) {
    let mut random = super::SeededBytes::new(seed);
    let noise = random.bytes(w * h);
    let depth = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            let fold = if x > 0.55 * w as f32 && y > 0.3 * h as f32 {
                8.0
            } else {
                0.0
            };
            let z = 60.0 + 10.0 * (x / 13.0).sin() + 5.0 * (y / 7.0).cos() + fold;
            match noise[i] {
                0..=2 => f32::NAN,
                3 => 5.0,
                4 => 400.0,
                5 => -3.0,
                6 => f32::INFINITY,
                n => z + (f32::from(n) - 128.0) * 0.004,
            }
        })
        .collect();
    let tex = random.bytes(w * h * c);
    let mut img = vec![0u8; w * h * c];
    for y in 0..h {
        for x in 0..w {
            let px = &mut img[(y * w + x) * c..(y * w + x + 1) * c];
            let t = &tex[(y * w + x) * c..(y * w + x + 1) * c];
            if x < 3 {
                px.fill(t[0] % 12); // the border band, some of it above the black level
            } else if (x + 3 * y) % 97 == 5 {
                px.fill(250 - t[0] % 8); // a highlight
            } else if (x + 5 * y) % 101 == 7 {
                // A tinted highlight: saturation 0.056, a highlight at the default 0.2 only.
                px.fill(236);
                px[0] = 250;
            } else if (x * 7 + y) % 89 == 1 {
                px[0] = 252; // bright but coloured: not a highlight
                px[1..].fill(90);
            } else {
                for (p, &v) in px.iter_mut().zip(t) {
                    *p = 40 + v % 150;
                }
            }
        }
    }
    (depth, img)
}

/// What `misslam bench post-gpu` measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PostGpuBench {
    /// Map size, pixels.
    pub width: usize,
    /// Map height, pixels.
    pub height: usize,
    /// The adapter (name, backend, type).
    pub adapter: String,
    /// Threads of the CPU path's pool.
    pub cpu_threads: usize,
    /// Timed runs of each path (taken in turns).
    pub runs: usize,
    /// The CPU path: median ms per map, and the process's CPU time per map, ms (every thread).
    pub cpu_ms: f64,
    /// See `cpu_ms`.
    pub cpu_cpu_ms: f64,
    /// The GPU path, upload and readback included: median ms per map, and the process's CPU
    /// time per map, ms.
    pub gpu_ms: f64,
    /// See `gpu_ms`.
    pub gpu_cpu_ms: f64,
    /// The GPU path's medians: handing the tables and maps to the queue, the kernels until the
    /// maps may be read, copying them out, ms.
    pub gpu_upload_ms: f64,
    /// See `gpu_upload_ms`.
    pub gpu_kernels_ms: f64,
    /// See `gpu_upload_ms`.
    pub gpu_readback_ms: f64,
    /// The masks' counts (out of range, border, specular) and every pixel's validity agree.
    pub masks_equal: bool,
    /// Largest differences to the CPU path: depth (mm), points (mm), normals.
    pub max_depth_diff_mm: f64,
    /// See `max_depth_diff_mm`.
    pub max_point_diff_mm: f64,
    /// See `max_depth_diff_mm`.
    pub max_normal_diff: f64,
}

/// `depth.postprocess`'s whole chain (the node's defaults) on [`post_scene`] at `width` x
/// `height`, on the CPU (threads as RAYON_NUM_THREADS says) and on the GPU in turns, `repeat`
/// times each: wall time and the process's CPU time per map, the GPU's stages, and how the
/// outputs compare.
pub fn post_gpu(width: usize, height: usize, repeat: usize) -> Result<PostGpuBench, String> {
    use misslam_depth_postprocess::{clean_into, gpu::PostGpu, Params};
    use misslam_framework::{metrics::process_cpu_ms, Image, StereoCalib, StereoFrame};
    use std::sync::Arc;
    if width < 3 || height < 3 {
        return Err(format!(
            "--width and --height must be at least 3, got {width}x{height}"
        ));
    }
    let ctx = misslam_framework::gpu::GpuProvider::new()
        .get()
        .map_err(|e| e.to_string())?;
    let info = &ctx.adapter_info;
    let adapter = format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type);
    let (depth, img) = post_scene(width, height, 3, 44);
    let calib = StereoCalib {
        width: width as u32,
        height: height as u32,
        fx: 700.0,
        fy: 700.0,
        cx: width as f64 / 2.0,
        cy: height as f64 / 2.0,
        cx_right: width as f64 / 2.0,
        baseline_mm: 5.0,
    };
    let image =
        Arc::new(Image::new(width as u32, height as u32, 3, img).map_err(|e| e.to_string())?);
    let pair = StereoFrame {
        index: 0,
        timestamp: 0.0,
        left: Arc::clone(&image),
        right: image,
        calib,
        left_mask: None,
        right_mask: None,
    };
    let p = Params::default();
    let mut kernels = PostGpu::new(&ctx);
    let cpu_clock = || process_cpu_ms().unwrap_or(f64::NAN);
    let mut cpu = clean_into(depth.clone(), &calib, Some(&pair), &p, Default::default())?;
    let (mut gpu, _) = kernels.clean_into(
        &ctx,
        depth.clone(),
        &calib,
        Some(&pair),
        &p,
        Default::default(),
    )?;
    let runs = repeat.max(1);
    let (mut cpu_wall, mut gpu_wall, mut stages) =
        (Vec::new(), Vec::new(), [(); 3].map(|_| Vec::new()));
    let (mut cpu_cpu, mut gpu_cpu) = (0.0, 0.0);
    for _ in 0..runs {
        // The maps' buffers go back in, as the node recycles them.
        let (c0, t) = (cpu_clock(), Instant::now());
        cpu = clean_into(
            depth.clone(),
            &calib,
            Some(&pair),
            &p,
            (
                std::mem::take(&mut cpu.vertices),
                std::mem::take(&mut cpu.normals),
            ),
        )?;
        cpu_wall.push(t.elapsed().as_secs_f64() * 1e3);
        cpu_cpu += cpu_clock() - c0;
        let (c0, t) = (cpu_clock(), Instant::now());
        let (g, timing) = kernels.clean_into(
            &ctx,
            depth.clone(),
            &calib,
            Some(&pair),
            &p,
            (
                std::mem::take(&mut gpu.vertices),
                std::mem::take(&mut gpu.normals),
            ),
        )?;
        gpu_wall.push(t.elapsed().as_secs_f64() * 1e3);
        gpu_cpu += cpu_clock() - c0;
        for (v, ms) in stages
            .iter_mut()
            .zip([timing.upload_ms, timing.gpu_ms, timing.readback_ms])
        {
            v.push(ms);
        }
        gpu = g;
    }
    let nan_eq = |a: f32, b: f32| a.is_nan() == b.is_nan();
    let masks_equal = (cpu.out_of_range, cpu.border, cpu.specular)
        == (gpu.out_of_range, gpu.border, gpu.specular)
        && cpu
            .depth
            .iter()
            .zip(&gpu.depth)
            .all(|(&a, &b)| nan_eq(a, b));
    let max_diff = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .filter(|(x, y)| x.is_finite() && y.is_finite())
            .map(|(x, y)| f64::from((x - y).abs()))
            .fold(0.0, f64::max)
    };
    let flat = |v: &[[f32; 3]]| v.iter().flatten().copied().collect::<Vec<f32>>();
    let [upload, kernels_ms, readback] = stages.map(super::median);
    Ok(PostGpuBench {
        width,
        height,
        adapter,
        cpu_threads: rayon::current_num_threads(),
        runs,
        cpu_ms: super::median(cpu_wall),
        cpu_cpu_ms: cpu_cpu / runs as f64,
        gpu_ms: super::median(gpu_wall),
        gpu_cpu_ms: gpu_cpu / runs as f64,
        gpu_upload_ms: upload,
        gpu_kernels_ms: kernels_ms,
        gpu_readback_ms: readback,
        masks_equal,
        max_depth_diff_mm: max_diff(&cpu.depth, &gpu.depth),
        max_point_diff_mm: max_diff(&flat(&cpu.vertices), &flat(&gpu.vertices)),
        max_normal_diff: max_diff(&flat(&cpu.normals), &flat(&gpu.normals)),
    })
}
