//! The per-frame distance field on the GPU (`shaders/fusion/dff.wgsl`): one invocation per voxel,
//! the arithmetic of the CPU reference [`DistanceField::from_maps`], upload and readback included.

use misslam_deformation_ed::field::ProjectiveField;
use misslam_deformation_ed::{DistanceField, Intrinsics};
use misslam_framework::gpu::{GpuContext, GpuError};
use wgpu::util::DeviceExt;

/// WGSL of the kernel.
pub const DFF_WGSL: &str = include_str!("../../../../shaders/fusion/dff.wgsl");

/// Workgroup size of the kernel.
const GROUP: u32 = 64;

/// Marks an unknown voxel in the kernel's output.
const UNKNOWN: f32 = 3.0e38;

/// The compiled DFF kernel.
pub struct DffKernel {
    pipeline: wgpu::ComputePipeline,
    /// `main_normals`: the values and the mean normals.
    with_normals: wgpu::ComputePipeline,
}

/// Milliseconds of one GPU field build.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DffTiming {
    /// Packing the maps and the box on the CPU.
    pub prepare_ms: f64,
    /// Upload, kernel and readback (waits for the GPU).
    pub gpu_ms: f64,
}

impl DffKernel {
    /// Compiles the kernel.
    pub fn new(ctx: &GpuContext) -> Self {
        DffKernel {
            pipeline: ctx.compute_pipeline("dff", DFF_WGSL, "main"),
            with_normals: ctx.compute_pipeline("dff normals", DFF_WGSL, "main_normals"),
        }
    }

    /// The field of a scan's vertex and normal maps, as [`DistanceField::from_maps`] builds it on
    /// the CPU (same box, same arguments and errors), or with `with_normals` as
    /// [`DistanceField::from_maps_with_normals`] does.
    #[allow(clippy::too_many_arguments)]
    pub fn build(
        &self,
        ctx: &GpuContext,
        vertices: &[[f32; 3]],
        normals: &[[f32; 3]],
        k: &Intrinsics,
        voxel: f64,
        truncation: f64,
        window: u32,
        max_voxels: usize,
        with_normals: bool,
    ) -> Result<(DistanceField, DffTiming), String> {
        let t0 = std::time::Instant::now();
        DistanceField::check_maps(vertices, normals, k)?;
        let (w, h) = (k.width as usize, k.height as usize);
        let (origin, dims) =
            DistanceField::scan_box(vertices, normals, voxel, truncation, max_voxels)?;
        let total = dims[0] * dims[1] * dims[2];
        let limit = ctx.device.limits().max_storage_buffer_binding_size as usize;
        if total * if with_normals { 12 } else { 4 } > limit || w * h * 16 > limit {
            return Err(format!(
                "the field ({total} voxels) or the maps exceed the GPU's storage buffer limit of {limit} bytes: use field.device = \"cpu\" or a larger voxel"
            ));
        }
        let pf = ProjectiveField::new(origin, voxel, truncation, k, window);
        let mut pts = Vec::with_capacity(w * h * 4);
        let mut nrm = Vec::with_capacity(w * h * 4);
        for (p, n) in vertices.iter().zip(normals) {
            let valid = p.iter().chain(n.iter()).all(|c| c.is_finite());
            if valid {
                pts.extend_from_slice(&[p[0], p[1], p[2], 1.0]);
                nrm.extend_from_slice(&[n[0], n[1], n[2], 0.0]);
            } else {
                pts.extend_from_slice(&[0.0; 4]);
                nrm.extend_from_slice(&[0.0; 4]);
            }
        }
        let groups = (total as u32).div_ceil(GROUP);
        let max_x = ctx.device.limits().max_compute_workgroups_per_dimension;
        let gx = groups.min(max_x);
        let gy = groups.div_ceil(gx);
        let mut params = [0u32; 16];
        let fl = |v: f32| v.to_bits();
        params[..4].copy_from_slice(&[
            fl(pf.origin[0]),
            fl(pf.origin[1]),
            fl(pf.origin[2]),
            fl(pf.voxel),
        ]);
        params[4..8].copy_from_slice(&pf.k.map(fl));
        params[8..12].copy_from_slice(&[
            dims[0] as u32,
            dims[1] as u32,
            dims[2] as u32,
            gx * GROUP,
        ]);
        params[12..16].copy_from_slice(&[
            fl(pf.size[0] as f32),
            fl(pf.size[1] as f32),
            fl(pf.truncation),
            pf.window,
        ]);
        let prepare_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = std::time::Instant::now();
        let dev = &ctx.device;
        let storage = |label: &str, data: &[f32]| {
            dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytemuck::cast_slice(data),
                usage: wgpu::BufferUsages::STORAGE,
            })
        };
        let params_buf = dev.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("dff params"),
            contents: bytemuck::cast_slice(&params),
            usage: wgpu::BufferUsages::UNIFORM,
        });
        let pts_buf = storage("dff points", &pts);
        let nrm_buf = storage("dff normals", &nrm);
        let out_size = (total * 4) as u64;
        let out_buf = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some("dff field"),
            size: out_size,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        let normals_buf = with_normals.then(|| {
            dev.create_buffer(&wgpu::BufferDescriptor {
                label: Some("dff field normals"),
                size: out_size * 3,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            })
        });
        match &normals_buf {
            Some(nb) => ctx.dispatch(
                &self.with_normals,
                "dff normals",
                &[&params_buf, &pts_buf, &nrm_buf, &out_buf, nb],
                (gx, gy, 1),
            ),
            None => ctx.dispatch(
                &self.pipeline,
                "dff",
                &[&params_buf, &pts_buf, &nrm_buf, &out_buf],
                (gx, gy, 1),
            ),
        }
        let bytes = ctx
            .read_back(&out_buf, out_size)
            .map_err(|e: GpuError| e.to_string())?;
        let values: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|b| {
                let v = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                if v >= UNKNOWN {
                    f32::NAN
                } else {
                    v
                }
            })
            .collect();
        // The mean normals, NaN where the value is unknown (as on the CPU).
        let normals = match &normals_buf {
            Some(nb) => {
                let bytes = ctx
                    .read_back(nb, out_size * 3)
                    .map_err(|e: GpuError| e.to_string())?;
                bytes
                    .chunks_exact(12)
                    .zip(&values)
                    .map(|(b, v)| {
                        let c = |k: usize| {
                            f32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]])
                        };
                        if v.is_nan() {
                            [f32::NAN; 3]
                        } else {
                            [c(0), c(1), c(2)]
                        }
                    })
                    .collect()
            }
            None => Vec::new(),
        };
        let gpu_ms = t1.elapsed().as_secs_f64() * 1e3;
        Ok((
            DistanceField {
                origin,
                voxel,
                dims,
                values,
                truncation,
                normals,
            },
            DffTiming { prepare_ms, gpu_ms },
        ))
    }
}
