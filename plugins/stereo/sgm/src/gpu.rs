//! SGM on the GPU (`shaders/stereo/sgm_*.wgsl`): census of both images, aggregation along each
//! of the 4 or 8 directions (one workgroup per path, the disparities shared by its invocations),
//! winner-takes-all with the uniqueness margin, the parabola and the left-right check, and the
//! 3x3 median. Speckle removal (a sequential flood fill) runs on the CPU after readback. The
//! kernels compute the same integers as [`crate::sgm::sgm`]; the parity test runs both on
//! Mesa's lavapipe in CI.

use crate::reference::{DIRS, DIRS4};
use crate::sgm::{check_pair, remove_speckles_with, SgmParams, SpeckleScratch};
use misslam_framework::gpu::{GpuContext, GpuError};
use wgpu::util::DeviceExt;

/// WGSL of the four kernels.
pub const CENSUS_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_census.wgsl");
/// Aggregation along one direction.
pub const AGGREGATE_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_aggregate.wgsl");
/// Winner-takes-all and left-right check.
pub const SELECT_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_select.wgsl");
/// 3x3 median.
pub const MEDIAN_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_median.wgsl");

/// Marks an invalid pixel in the kernels' output.
const INVALID: f32 = -3.0e38;
/// The aggregation kernel's largest disparity count (its per-invocation arrays).
const MAX_D: u32 = 1024;

/// Milliseconds of one GPU pair, each stage waited for (the stages' sum is a little above an
/// unsynchronised run).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SgmGpuTiming {
    /// Buffers created and the images uploaded.
    pub upload_ms: f64,
    /// Census of both images.
    pub census_ms: f64,
    /// All directions.
    pub aggregate_ms: f64,
    /// Winner-takes-all, uniqueness, sub-pixel and left-right check.
    pub select_ms: f64,
    /// The 3x3 median.
    pub median_ms: f64,
    /// Disparities copied back to the host.
    pub readback_ms: f64,
    /// Speckle removal on the CPU.
    pub speckle_ms: f64,
    /// Everything, from the gray images to the disparity map.
    pub total_ms: f64,
}

/// The compiled SGM kernels.
pub struct SgmGpu {
    census: wgpu::ComputePipeline,
    aggregate: wgpu::ComputePipeline,
    select: wgpu::ComputePipeline,
    median: wgpu::ComputePipeline,
    speckle: SpeckleScratch,
}

fn words(v: &[u32]) -> &[u8] {
    bytemuck::cast_slice(v)
}

impl SgmGpu {
    /// Compiles the kernels.
    pub fn new(ctx: &GpuContext) -> Self {
        SgmGpu {
            census: ctx.compute_pipeline("sgm census", CENSUS_WGSL, "main"),
            aggregate: ctx.compute_pipeline("sgm aggregate", AGGREGATE_WGSL, "main"),
            select: ctx.compute_pipeline("sgm select", SELECT_WGSL, "main"),
            median: ctx.compute_pipeline("sgm median", MEDIAN_WGSL, "main"),
            speckle: SpeckleScratch::default(),
        }
    }

    /// Disparity of the left image (px, NaN invalid): the contract of [`crate::sgm::sgm`].
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &mut self,
        ctx: &GpuContext,
        left: &[u8],
        right: &[u8],
        w: usize,
        h: usize,
        valid: Option<&[u8]>,
        p: &SgmParams,
    ) -> Result<(Vec<f32>, SgmGpuTiming), String> {
        let t_all = std::time::Instant::now();
        check_pair(left, right, w, h, valid, p)?;
        if p.max_disparity > MAX_D {
            return Err(format!(
                "`max_disparity` {} exceeds the GPU kernel's {MAX_D}",
                p.max_disparity
            ));
        }
        let nd = p.max_disparity as usize;
        let sums_size = (w * h * nd * 4) as u64;
        let limit = ctx.device.limits().max_storage_buffer_binding_size;
        if sums_size > limit {
            return Err(format!(
                "the cost sums of {w}x{h}x{nd} ({sums_size} bytes) exceed the GPU's storage buffer limit of {limit} bytes: use device = \"cpu\" or fewer disparities"
            ));
        }
        let gpu = |e: GpuError| e.to_string();
        let mut timing = SgmGpuTiming::default();
        let mut lap = std::time::Instant::now();
        let mut stage = |ctx: &GpuContext, slot: &mut f64| -> Result<(), String> {
            ctx.wait().map_err(gpu)?;
            *slot = lap.elapsed().as_secs_f64() * 1e3;
            lap = std::time::Instant::now();
            Ok(())
        };
        let dev = &ctx.device;
        let init = |label: &str, bytes: &[u8], usage: wgpu::BufferUsages| {
            dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage,
            })
        };
        let empty = |label: &str, size: u64, usage: wgpu::BufferUsages| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage,
                mapped_at_creation: false,
            })
        };
        let storage = wgpu::BufferUsages::STORAGE;
        let uniform = wgpu::BufferUsages::UNIFORM;
        let images: Vec<u32> = left.iter().chain(right).map(|&v| u32::from(v)).collect();
        let images = init("sgm images", words(&images), storage);
        let mask: Vec<u32> = match valid {
            Some(m) => m.iter().map(|&v| u32::from(v != 0)).collect(),
            None => vec![1; w * h],
        };
        let mask = init("sgm mask", words(&mask), storage);
        let codes = empty("sgm census", (2 * w * h * 8) as u64, storage);
        // wgpu zero-initialises new buffers: the directions add into zeros.
        let sums = empty("sgm sums", sums_size, storage);
        let disp = empty(
            "sgm disparity",
            (w * h * 4) as u64,
            storage | wgpu::BufferUsages::COPY_SRC,
        );
        let out = empty(
            "sgm median",
            (w * h * 4) as u64,
            storage | wgpu::BufferUsages::COPY_SRC,
        );
        let (wu, hu) = (w as u32, h as u32);
        let census_params = init(
            "sgm census params",
            words(&[wu, hu, p.census_width / 2, p.census_height / 2]),
            uniform,
        );
        let tiles = (wu.div_ceil(8), hu.div_ceil(8));
        stage(ctx, &mut timing.upload_ms)?;
        ctx.dispatch(
            &self.census,
            "sgm census",
            &[&census_params, &images, &codes],
            (tiles.0, tiles.1, 2),
        );
        stage(ctx, &mut timing.census_ms)?;
        let dirs: &[(isize, isize)] = if p.paths == 8 { &DIRS } else { &DIRS4 };
        let max_x = dev.limits().max_compute_workgroups_per_dimension;
        for &(dx, dy) in dirs {
            let paths = if dy == 0 {
                hu
            } else if dx == 0 {
                wu
            } else {
                wu + hu - 1
            };
            let gx = paths.min(max_x);
            let params = [
                wu,
                hu,
                p.max_disparity,
                p.min_disparity as u32,
                u32::from(p.p1),
                u32::from(p.p2),
                u32::from(p.p2_adaptive),
                u32::from(p.unknown_cost()),
                dx as u32,
                dy as u32,
                paths,
                gx,
            ];
            let params = init("sgm aggregate params", words(&params), uniform);
            ctx.dispatch(
                &self.aggregate,
                "sgm aggregate",
                &[&params, &images, &codes, &sums],
                (gx, paths.div_ceil(gx), 1),
            );
        }
        stage(ctx, &mut timing.aggregate_ms)?;
        let select_params = [
            wu,
            hu,
            p.max_disparity,
            p.min_disparity as u32,
            p.uniqueness_pct,
            u32::from(p.subpixel),
            u32::from(p.lr_check),
            p.lr_max_diff.to_bits(),
        ];
        let select_params = init("sgm select params", words(&select_params), uniform);
        ctx.dispatch(
            &self.select,
            "sgm select",
            &[&select_params, &sums, &mask, &disp],
            (tiles.0, tiles.1, 1),
        );
        stage(ctx, &mut timing.select_ms)?;
        let result = if p.median {
            let median_params = init("sgm median params", words(&[wu, hu, 0, 0]), uniform);
            ctx.dispatch(
                &self.median,
                "sgm median",
                &[&median_params, &disp, &out],
                (tiles.0, tiles.1, 1),
            );
            &out
        } else {
            &disp
        };
        stage(ctx, &mut timing.median_ms)?;
        let bytes = ctx.read_back(result, (w * h * 4) as u64).map_err(gpu)?;
        let mut d: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| {
                let v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                if v <= INVALID {
                    f32::NAN
                } else {
                    v
                }
            })
            .collect();
        stage(ctx, &mut timing.readback_ms)?;
        if p.speckle_window > 0 {
            remove_speckles_with(
                &mut d,
                w,
                h,
                p.speckle_window as usize,
                p.speckle_range,
                &mut self.speckle,
            );
        }
        timing.speckle_ms = lap.elapsed().as_secs_f64() * 1e3;
        timing.total_ms = t_all.elapsed().as_secs_f64() * 1e3;
        Ok((d, timing))
    }
}
