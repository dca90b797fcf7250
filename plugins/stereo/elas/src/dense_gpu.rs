//! ELAS's dense matching on the GPU (`shaders/stereo/elas_dense.wgsl`): the per-pixel search of
//! [`crate::dense::Matcher`] for both images in one dispatch. The host rasterises the triangles
//! into a per-pixel plan (column-major, as the raster walks) (the plane's rounded disparity and whether it is a prior), packs the
//! candidate grids, uploads the descriptors and reads the two maps back; the kernels give the
//! CPU's integers (the sub-pixel fit, one division, within a few 1e-7 px).

use misslam_framework::gpu::GpuContext;

use crate::dense::{raster_columns, round_i32, DisparityGrid, TrianglePlanes};
use crate::descriptor::Desc;
use crate::support::SupportPoint;
use crate::ElasParams;

/// WGSL of the kernel.
pub const DENSE_WGSL: &str = include_str!("../../../../shaders/stereo/elas_dense.wgsl");

const OUTSIDE: u32 = u32::MAX;

/// A triangle's corners (u, v) in the raster's image.
type Corners = [(f32, f32); 3];

/// What the host hands the kernel for one image: its triangles with their planes, its grid.
pub struct Image<'a> {
    /// Triangles (indices into the support points).
    pub tris: &'a [[u32; 3]],
    /// Their planes.
    pub planes: &'a [TrianglePlanes],
    /// The candidate grid.
    pub grid: &'a DisparityGrid,
}

/// Milliseconds of one GPU dense matching.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DenseGpuTiming {
    /// The host's raster of the triangles into the per-pixel plan.
    pub raster_ms: f64,
    /// Packing and queueing the uploads.
    pub upload_ms: f64,
    /// Submission, the kernel, the readback and its copy.
    pub kernel_readback_ms: f64,
}

struct Buffers {
    n: usize,
    cells: usize,
    cands: usize,
    params: wgpu::Buffer,
    desc: wgpu::Buffer,
    plan: wgpu::Buffer,
    offsets: wgpu::Buffer,
    cands_buf: wgpu::Buffer,
    prior: wgpu::Buffer,
    out: wgpu::Buffer,
    staging: wgpu::Buffer,
    bind: wgpu::BindGroup,
}

/// The compiled kernel and its buffers (kept across frames, grown when needed).
pub struct DenseGpu {
    pipeline: wgpu::ComputePipeline,
    buffers: Option<Buffers>,
    plan: Vec<u32>,
    words: Vec<u32>,
}

impl DenseGpu {
    /// Compiles the kernel.
    pub fn new(ctx: &GpuContext) -> Self {
        DenseGpu {
            pipeline: ctx.compute_pipeline("elas dense", DENSE_WGSL, "main"),
            buffers: None,
            plan: Vec::new(),
            words: Vec::new(),
        }
    }

    fn buffers(&mut self, ctx: &GpuContext, n: usize, cells: usize, cands: usize, radius: usize) {
        if self
            .buffers
            .as_ref()
            .is_some_and(|b| b.n == n && b.cells == cells && b.cands >= cands)
        {
            return;
        }
        let buffer = |label: &str, size: u64, usage| ctx.buffer(label, size, usage);
        use wgpu::BufferUsages as U;
        let cands = cands.next_power_of_two().max(1024);
        let params = buffer("elas dense params", 48, U::UNIFORM | U::COPY_DST);
        let desc = buffer(
            "elas descriptors",
            2 * n as u64 * 16,
            U::STORAGE | U::COPY_DST,
        );
        let plan = buffer("elas plan", 2 * n as u64 * 4, U::STORAGE | U::COPY_DST);
        let offsets = buffer(
            "elas grid offsets",
            2 * (cells as u64 + 1) * 4,
            U::STORAGE | U::COPY_DST,
        );
        let cands_buf = buffer(
            "elas grid candidates",
            cands as u64 * 4,
            U::STORAGE | U::COPY_DST,
        );
        let prior = buffer(
            "elas prior",
            (radius as u64 + 1) * 4 + 256,
            U::STORAGE | U::COPY_DST,
        );
        let out = buffer("elas dense out", 2 * n as u64 * 4, U::STORAGE | U::COPY_SRC);
        let staging = buffer(
            "elas dense readback",
            2 * n as u64 * 4,
            U::MAP_READ | U::COPY_DST,
        );
        let bind = ctx.bind_buffers(
            &self.pipeline,
            "elas dense",
            &[&params, &desc, &plan, &offsets, &cands_buf, &prior, &out],
        );
        self.buffers = Some(Buffers {
            n,
            cells,
            cands,
            params,
            desc,
            plan,
            offsets,
            cands_buf,
            prior,
            out,
            staging,
            bind,
        });
    }

    /// Dense matching of both images into `out_l` and `out_r` (w x h, NaN where none): the
    /// result of [`crate::dense::Matcher::run`] on each.
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &mut self,
        ctx: &GpuContext,
        (desc_l, desc_r): (&[Desc], &[Desc]),
        (w, h): (usize, usize),
        p: &ElasParams,
        support: &[SupportPoint],
        (left, right): (Image, Image),
        (table, radius): (&[i32], usize),
        (out_l, out_r): (&mut [f32], &mut [f32]),
    ) -> Result<DenseGpuTiming, String> {
        let n = w * h;
        if desc_l.len() != n || desc_r.len() != n || out_l.len() != n || out_r.len() != n {
            return Err(format!(
                "the GPU dense matching needs {w}x{h} descriptors and maps"
            ));
        }
        let (dmin, dmax, r) = (p.disp_min as i32, p.disp_max as i32, radius as i32);
        if dmax + r + 1 > 32767 || table.len() != radius + 1 {
            return Err(format!(
                "the GPU dense matching takes disparities up to {}, not {dmax}",
                32767 - r - 1
            ));
        }
        let grids = [left.grid, right.grid];
        if grids[0].gw != grids[1].gw || grids[0].gh != grids[1].gh {
            return Err("the two images' grids differ in size".into());
        }
        let t0 = std::time::Instant::now();
        // The plan: libelas's raster, the last triangle drawn wins (as on the CPU); the two
        // images side by side, each column-major.
        self.plan.clear();
        self.plan.resize(2 * n, OUTSIDE);
        // Column-major, in the raster's order (the raster walks columns), so that blocks of
        // columns are rasterised on rayon's threads into disjoint slices, each visiting the
        // triangles in order.
        const BLOCK: usize = 32;
        let code = |plane: Option<crate::dense::Plane>, valid: bool, u: usize, v: usize| match plane
        {
            None => 0,
            Some(pl) => {
                let dp = round_i32(pl.at(u as f32, v as f32)).clamp(dmin - r - 1, dmax + r + 1);
                (dp + 32768) as u32 | 1 << 16 | u32::from(valid) << 17
            }
        };
        let corners = |im: &Image, right: bool| -> Vec<(Corners, (f32, f32))> {
            im.tris
                .iter()
                .map(|t| {
                    let c = t.map(|i| {
                        let s = support[i as usize];
                        let u = if right { s.u - s.d } else { s.u };
                        (u as f32, s.v as f32)
                    });
                    let lo = c.iter().map(|p| p.0).fold(f32::INFINITY, f32::min);
                    let hi = c.iter().map(|p| p.0).fold(f32::NEG_INFINITY, f32::max);
                    (c, (lo, hi))
                })
                .collect()
        };
        let tris = [corners(&left, false), corners(&right, true)];
        let ims = [&left, &right];
        use rayon::prelude::*;
        let (plan_l, plan_r) = self.plan.split_at_mut(n);
        let chunk = BLOCK * h;
        plan_l
            .par_chunks_mut(chunk)
            .enumerate()
            .map(|(b, c)| (0, b, c))
            .chain(
                plan_r
                    .par_chunks_mut(chunk)
                    .enumerate()
                    .map(|(b, c)| (1, b, c)),
            )
            .for_each(|(img, b, chunk)| {
                let cols = b * BLOCK..((b + 1) * BLOCK).min(w);
                let u0 = cols.start;
                for ((c, (lo, hi)), tp) in tris[img].iter().zip(ims[img].planes) {
                    // The raster's columns lie in [trunc(lo), trunc(hi)).
                    if (*hi as i64) <= u0 as i64 || (*lo as i64) >= cols.end as i64 {
                        continue;
                    }
                    let (plane, valid) = tp.for_image(img == 1);
                    raster_columns(*c, w, h, cols.clone(), |u, v| {
                        chunk[(u - u0) * h + v] = code(plane, valid, u, v);
                    });
                }
            });
        let raster_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = std::time::Instant::now();
        let cells = grids[0].gw * grids[0].gh;
        let (gl, gr) = (grids[0].raw(), grids[1].raw());
        let total_cands = gl.1.len() + gr.1.len();
        self.buffers(ctx, n, cells, total_cands, radius);
        let b = self.buffers.as_ref().ok_or("no GPU buffers")?;
        let q = &ctx.queue;
        let params = [
            w as u32,
            h as u32,
            grids[0].size as u32,
            grids[0].gw as u32,
            grids[0].gh as u32,
            dmin as u32,
            dmax as u32,
            radius as u32,
            p.match_texture,
            u32::from(p.subpixel),
            cells as u32,
            0,
        ];
        q.write_buffer(&b.params, 0, bytemuck::cast_slice(&params));
        q.write_buffer(&b.desc, 0, bytemuck::cast_slice(desc_l));
        q.write_buffer(&b.desc, n as u64 * 16, bytemuck::cast_slice(desc_r));
        q.write_buffer(&b.plan, 0, bytemuck::cast_slice(&self.plan));
        // Offsets of both grids (the right's after the left's candidates), then the candidates.
        self.words.clear();
        self.words.extend_from_slice(gl.0);
        let shift = gl.1.len() as u32;
        self.words.extend(gr.0.iter().map(|o| o + shift));
        q.write_buffer(&b.offsets, 0, bytemuck::cast_slice(&self.words));
        self.words.clear();
        self.words
            .extend(gl.1.iter().chain(gr.1).map(|&d| u32::from(d)));
        if self.words.is_empty() {
            self.words.push(0);
        }
        q.write_buffer(&b.cands_buf, 0, bytemuck::cast_slice(&self.words));
        q.write_buffer(&b.prior, 0, bytemuck::cast_slice(table));
        let upload_ms = t1.elapsed().as_secs_f64() * 1e3;
        let t2 = std::time::Instant::now();
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &b.bind, &[]);
            pass.dispatch_workgroups((w as u32).div_ceil(64), h as u32, 2);
        }
        let bytes = 2 * n as u64 * 4;
        enc.copy_buffer_to_buffer(&b.out, 0, &b.staging, 0, bytes);
        let index = q.submit(Some(enc.finish()));
        let (tx, rx) = std::sync::mpsc::channel();
        b.staging
            .slice(..bytes)
            .map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send(r);
            });
        ctx.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
            .map_err(|e| e.to_string())?;
        rx.recv()
            .map_err(|e| e.to_string())?
            .map_err(|e| format!("the GPU dense matching's readback failed: {e}"))?;
        // Mapped from here: unmapped whatever happens, so that the buffer can be used again.
        let copied = b
            .staging
            .slice(..bytes)
            .get_mapped_range()
            .map_err(|e| e.to_string())
            .and_then(|view| {
                let maps: &[f32] = bytemuck::try_cast_slice(&view).map_err(|e| e.to_string())?;
                out_l.copy_from_slice(&maps[..n]);
                out_r.copy_from_slice(&maps[n..]);
                Ok(())
            });
        b.staging.unmap();
        copied.map_err(|e| format!("the GPU dense matching's readback failed: {e}"))?;
        Ok(DenseGpuTiming {
            raster_ms,
            upload_ms,
            kernel_readback_ms: t2.elapsed().as_secs_f64() * 1e3,
        })
    }
}
