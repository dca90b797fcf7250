//! `misslam bench elas`, `sgm` and `sgm-gpu`: the stereo stages on a pair, step by step.

use std::path::Path;
use std::time::Instant;

use super::{gray_image, median, median_ms};

/// One ELAS run's figures ([`elas`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ElasBench {
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// Support points found.
    pub support_points: usize,
    /// Median total time, ms.
    pub ms: f64,
    /// Median time of each step, ms: descriptors, support, triangulation, dense, postprocess.
    pub steps_ms: [f64; 5],
    /// The adapter when the dense matching ran on the GPU.
    pub gpu: Option<String>,
    /// With the GPU: medians of the dense matching's parts, ms: the host's raster of the
    /// triangles, the uploads, and the kernel with the readback.
    pub dense_gpu_ms: Option<[f64; 3]>,
    /// With the GPU: pixels whose validity differs from the CPU's output on the same pair, and
    /// the largest |GPU - CPU| over pixels valid in both, px.
    pub parity: Option<(usize, f32)>,
    /// Left disparity of the last run (px, NaN invalid), row-major.
    #[serde(skip)]
    pub disparity: Vec<f32>,
}

/// ELAS on a pair (threads: as rayon is configured, e.g. `RAYON_NUM_THREADS=1`), with the time
/// of each step (median of `repeat`); with `gpu` the dense matching runs on the GPU and the
/// output is compared with the CPU's.
pub fn elas(
    left: &Path,
    right: &Path,
    p: &misslam_depth_elas::ElasParams,
    repeat: usize,
    gpu: bool,
) -> Result<ElasBench, String> {
    let (w, h, l) = gray_image(left)?;
    let (w2, h2, r) = gray_image(right)?;
    if (w, h) != (w2, h2) {
        return Err(format!(
            "{} is {w}x{h} but {} is {w2}x{h2}",
            left.display(),
            right.display()
        ));
    }
    let mut steps: Vec<[f64; 5]> = Vec::new();
    let mut parts: Vec<[f64; 3]> = Vec::new();
    let mut last = None;
    let mut scratch = misslam_depth_elas::Scratch::default();
    let ctx = if gpu {
        Some(
            misslam_framework::gpu::GpuProvider::new()
                .get()
                .map_err(|e| e.to_string())?,
        )
    } else {
        None
    };
    let mut kernel = ctx
        .as_ref()
        .map(|c| misslam_depth_elas::dense_gpu::DenseGpu::new(c));
    let (wu, hu) = (w as usize, h as usize);
    let ms = median_ms(repeat, || {
        let o = match (&ctx, &mut kernel) {
            (Some(c), Some(k)) => {
                misslam_depth_elas::elas_gpu(&l, &r, wu, hu, p, &mut scratch, (c, k))?
            }
            _ => misslam_depth_elas::elas_with(&l, &r, wu, hu, p, &mut scratch)?,
        };
        let t = o.timing;
        if let Some(g) = t.dense_gpu {
            parts.push([g.raster_ms, g.upload_ms, g.kernel_readback_ms]);
        }
        steps.push([
            t.descriptors,
            t.support,
            t.triangulation,
            t.dense,
            t.postprocess,
        ]);
        last = Some(o);
        Ok::<(), String>(())
    })?;
    let o = last.ok_or("no run")?;
    let steps_ms = std::array::from_fn(|k| median(steps.iter().map(|s| s[k]).collect()));
    let parity = if gpu {
        let cpu = misslam_depth_elas::elas_with(&l, &r, wu, hu, p, &mut Default::default())?;
        Some(disparity_parity(&o.left, &cpu.left))
    } else {
        None
    };
    Ok(ElasBench {
        width: w,
        height: h,
        support_points: o.support.len(),
        ms,
        steps_ms,
        gpu: ctx.as_ref().map(|c| {
            let i = &c.adapter_info;
            format!("{} ({:?}, {:?})", i.name, i.backend, i.device_type)
        }),
        dense_gpu_ms: (!parts.is_empty())
            .then(|| std::array::from_fn(|k| median(parts.iter().map(|s| s[k]).collect()))),
        parity,
        disparity: o.left,
    })
}

/// `misslam bench sgm`: the CPU SGM on one pair, the median of each stage ([`sgm_cpu`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SgmCpuBench {
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Disparities searched.
    pub disparities: u32,
    /// Paths (4 or 8).
    pub paths: u32,
    /// Rayon's threads.
    pub threads: usize,
    /// Timed runs (after one warm-up run).
    pub runs: usize,
    /// Median wall time of one pair, ms.
    pub ms: f64,
    /// Fastest of the same runs, ms.
    pub min_ms: f64,
    /// Median of each stage over the same runs, ms.
    pub stages_ms: misslam_depth_sgm::sgm::SgmTiming,
    /// Valid pixels of the output, % of all.
    pub density_pct: f64,
    /// The lane code the kernels ran at ("Avx512", "Avx2" or "Portable"): the widest the CPU
    /// has, at most the one asked for.
    pub lanes: String,
}

/// Loads a gray pair (or makes the random-dot pair of `size`), checking that the sizes agree.
fn sgm_pair(
    pair: Option<(&Path, &Path)>,
    size: (usize, usize),
    nd: u32,
) -> Result<(usize, usize, Vec<u8>, Vec<u8>), String> {
    match pair {
        Some((l, r)) => {
            let (w, h, left) = gray_image(l)?;
            let (w2, h2, right) = gray_image(r)?;
            if (w, h) != (w2, h2) {
                return Err(format!(
                    "{} is {w}x{h} but {} is {w2}x{h2}",
                    l.display(),
                    r.display()
                ));
            }
            Ok((w as usize, h as usize, left, right))
        }
        None => {
            let (l, r) = random_dot_pair(size.0, size.1, nd);
            Ok((size.0, size.1, l, r))
        }
    }
}

/// The CPU SGM ([`misslam_depth_sgm::sgm::sgm`]) on a pair, with the threads rayon has and
/// the lane code capped at `lanes` (`None`: as `MISSLAM_SIMD` says, else the widest the CPU
/// has): the median time per pair and of each stage over `repeat` runs after a warm-up run.
pub fn sgm_cpu(
    pair: Option<(&Path, &Path)>,
    size: (usize, usize),
    p: &misslam_depth_sgm::sgm::SgmParams,
    repeat: usize,
    lanes: Option<misslam_depth_sgm::simd::Level>,
) -> Result<SgmCpuBench, String> {
    use misslam_depth_sgm::simd::{cap, level, uncap};
    if let Some(l) = lanes {
        cap(l);
    }
    let r = sgm_cpu_at(pair, size, p, repeat, format!("{:?}", level()));
    uncap();
    r
}

fn sgm_cpu_at(
    pair: Option<(&Path, &Path)>,
    size: (usize, usize),
    p: &misslam_depth_sgm::sgm::SgmParams,
    repeat: usize,
    lanes: String,
) -> Result<SgmCpuBench, String> {
    use misslam_depth_sgm::sgm::{sgm, Scratch, SgmTiming};
    let (w, h, left, right) = sgm_pair(pair, size, p.max_disparity)?;
    let mut scratch = Scratch::default();
    let mut out = sgm(&left, &right, w, h, None, p, &mut scratch)?;
    let mut stages: Vec<SgmTiming> = Vec::new();
    let mut totals = Vec::new();
    let ms = median_ms(repeat, || {
        let t = Instant::now();
        out = sgm(&left, &right, w, h, None, p, &mut scratch)?;
        totals.push(t.elapsed().as_secs_f64() * 1e3);
        stages.push(scratch.last_timing());
        Ok::<(), String>(())
    })?;
    let med = |f: &dyn Fn(&SgmTiming) -> f64| median(stages.iter().map(f).collect());
    let stages_ms = SgmTiming {
        census_ms: med(&|t| t.census_ms),
        forward_ms: med(&|t| t.forward_ms),
        backward_select_ms: med(&|t| t.backward_select_ms),
        finish_ms: med(&|t| t.finish_ms),
        total_ms: med(&|t| t.total_ms),
    };
    let valid = out.iter().filter(|v| v.is_finite()).count();
    Ok(SgmCpuBench {
        width: w,
        height: h,
        disparities: p.max_disparity,
        paths: p.paths,
        threads: rayon::current_num_threads(),
        runs: repeat.max(1),
        ms,
        min_ms: totals.iter().copied().fold(f64::INFINITY, f64::min),
        stages_ms,
        density_pct: 100.0 * valid as f64 / (w * h) as f64,
        lanes,
    })
}

/// `misslam bench sgm-gpu`: the WGSL SGM against the CPU path on the same pair in the same run
/// ([`sgm_gpu`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SgmGpuBench {
    /// The adapter (name, backend, type).
    pub adapter: String,
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Disparities searched.
    pub disparities: u32,
    /// Paths (4 or 8).
    pub paths: u32,
    /// Timed runs (after one warm-up run).
    pub runs: usize,
    /// Median wall time of one pair on the GPU as the node runs it (every kernel in one pass,
    /// untimed), upload and readback included, ms.
    pub gpu_ms: f64,
    /// Fastest of the same runs, ms.
    pub gpu_min_ms: f64,
    /// Wall time per pair of a stream of `runs` pairs with two in flight
    /// ([`misslam_depth_sgm::gpu::SgmGpu::submit`]: the next pair uploaded and submitted before
    /// the one before is read back), upload and readback included, ms: the throughput of a
    /// video, where `gpu_ms` is the latency of one pair. Median of three streams.
    pub stream_ms: f64,
    /// Whether every streamed pair gave the bits of `gpu_ms`'s runs.
    pub stream_identical: bool,
    /// Median of each stage, ms, over runs of their own: from GPU timestamps where the adapter
    /// has them (a pass per stage, so their `total_ms` is a little above `gpu_ms`), else with
    /// every stage waited for (their sum well above `gpu_ms`).
    pub stages_ms: misslam_depth_sgm::gpu::SgmGpuTiming,
    /// Median wall time of the CPU path ([`misslam_depth_sgm::sgm::sgm`]) on the same pair, with
    /// the threads rayon has, ms.
    pub cpu_ms: f64,
    /// Rayon's threads for the CPU runs.
    pub cpu_threads: usize,
    /// `cpu_ms / gpu_ms`.
    pub speedup: f64,
    /// Pixels whose validity differs between the GPU and the CPU output.
    pub validity_differs: usize,
    /// Largest |GPU - CPU| over pixels valid in both, px.
    pub max_abs_diff_px: f32,
    /// Valid pixels of the CPU output, % of all.
    pub density_pct: f64,
}

/// How two disparity maps (NaN invalid) differ: the pixels valid in one and not the other, and
/// the largest |a - b| over pixels valid in both.
pub fn disparity_parity(a: &[f32], b: &[f32]) -> (usize, f32) {
    let validity = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.is_finite() != y.is_finite())
        .count();
    let max_diff = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    (validity, max_diff)
}

/// A rectified random-dot pair of `w` x `h` with a slanted background and a nearer block (so
/// there are occlusions), disparities within 0..`nd`.
pub fn random_dot_pair(w: usize, h: usize, nd: u32) -> (Vec<u8>, Vec<u8>) {
    let mut random = super::SeededBytes::new((w * 31 + h) as u64);
    let left = random.bytes(w * h);
    let fill = random.bytes(w * h);
    let top = (nd.max(4) - 2) as usize;
    let disp = |x: usize, y: usize| {
        if (w / 3..w / 2).contains(&x) && (h / 4..h / 2).contains(&y) {
            top
        } else {
            2 + (x + 2 * y) * (top / 2) / (w + 2 * h)
        }
    };
    let right = misslam_depth_sgm::synthetic::right_view(&left, w, h, disp, fill);
    (left, right)
}

/// SGM on the GPU and on the CPU on one pair (the files, or [`random_dot_pair`] at `size`):
/// median times, the GPU's stage breakdown and the parity of the two outputs. `int64_atomics`
/// false keeps the summed costs to 32-bit atomics ([`misslam_depth_sgm::gpu::SgmGpu::set_int64_atomics`]).
pub fn sgm_gpu(
    pair: Option<(&Path, &Path)>,
    size: (usize, usize),
    p: &misslam_depth_sgm::sgm::SgmParams,
    repeat: usize,
    int64_atomics: bool,
) -> Result<SgmGpuBench, String> {
    use misslam_depth_sgm::gpu::{Breakdown, SgmGpu, SgmGpuTiming};
    use misslam_depth_sgm::sgm::{sgm, Scratch};
    let (w, h, left, right) = sgm_pair(pair, size, p.max_disparity)?;
    let ctx = misslam_framework::gpu::GpuProvider::new()
        .get()
        .map_err(|e| e.to_string())?;
    let info = &ctx.adapter_info;
    let adapter = format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type);
    let mut kernels = SgmGpu::new(&ctx);
    kernels.set_int64_atomics(int64_atomics);
    let run = |k: &mut SgmGpu| k.run(&ctx, &left, &right, w, h, None, p);
    let (got, _) = run(&mut kernels)?;
    let mut totals = Vec::new();
    let mut gpu_out = got;
    // The node's way, untimed stages in one pass.
    let gpu_ms = median_ms(repeat, || {
        let t = Instant::now();
        let (d, _) = run(&mut kernels)?;
        totals.push(t.elapsed().as_secs_f64() * 1e3);
        gpu_out = d;
        Ok::<(), String>(())
    })?;
    let gpu_min_ms = totals.iter().copied().fold(f64::INFINITY, f64::min);
    // A stream: the next pair submitted before the one before is collected.
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let want = bits(&gpu_out);
    let mut stream_identical = true;
    let n = repeat.max(2);
    let mut streams = Vec::new();
    for _ in 0..3 {
        let t = Instant::now();
        kernels.submit(&ctx, &left, &right, w, h, None, p)?;
        for k in 0..n {
            if k + 1 < n {
                kernels.submit(&ctx, &left, &right, w, h, None, p)?;
            }
            let (d, _) = kernels.collect(&ctx)?;
            stream_identical &= bits(&d) == want;
        }
        streams.push(t.elapsed().as_secs_f64() * 1e3 / n as f64);
    }
    let stream_ms = median(streams);
    // The breakdown, in runs of their own: timestamps where the adapter has them, else each
    // stage waited for.
    kernels.set_breakdown(Breakdown::Timestamps);
    let mut stages: Vec<SgmGpuTiming> = Vec::new();
    for _ in 0..repeat.max(1) {
        stages.push(run(&mut kernels)?.1);
    }
    kernels.set_breakdown(Breakdown::Off);
    let med = |f: &dyn Fn(&SgmGpuTiming) -> f64| median(stages.iter().map(f).collect());
    let stages_ms = SgmGpuTiming {
        upload_ms: med(&|t| t.upload_ms),
        census_ms: med(&|t| t.census_ms),
        aggregate_ms: med(&|t| t.aggregate_ms),
        select_ms: med(&|t| t.select_ms),
        median_ms: med(&|t| t.median_ms),
        readback_ms: med(&|t| t.readback_ms),
        submit_ms: med(&|t| t.submit_ms),
        copy_ms: med(&|t| t.copy_ms),
        speckle_ms: med(&|t| t.speckle_ms),
        finish_ms: med(&|t| t.finish_ms),
        total_ms: med(&|t| t.total_ms),
        gpu_timestamps: stages.iter().all(|t| t.gpu_timestamps),
        summed_volumes: stages.iter().any(|t| t.summed_volumes),
        subgroups: stages.iter().any(|t| t.subgroups),
        atomics64: stages.iter().any(|t| t.atomics64),
    };
    let mut scratch = Scratch::default();
    let mut cpu_out = Vec::new();
    let cpu_ms = median_ms(repeat.clamp(1, 10), || {
        cpu_out = sgm(&left, &right, w, h, None, p, &mut scratch)?;
        Ok::<(), String>(())
    })?;
    let (validity_differs, max_abs_diff_px) = disparity_parity(&gpu_out, &cpu_out);
    let valid = cpu_out.iter().filter(|v| v.is_finite()).count();
    Ok(SgmGpuBench {
        adapter,
        width: w,
        height: h,
        disparities: p.max_disparity,
        paths: p.paths,
        runs: repeat.max(1),
        gpu_ms,
        gpu_min_ms,
        stream_ms,
        stream_identical,
        stages_ms,
        cpu_ms,
        cpu_threads: rayon::current_num_threads(),
        speedup: cpu_ms / gpu_ms,
        validity_differs,
        max_abs_diff_px,
        density_pct: 100.0 * valid as f64 / (w * h) as f64,
    })
}
