//! `depth.postprocess` on the GPU (`shaders/stereo/postprocess.wgsl`, `device = "gpu"`): the
//! range limits, masks, bilateral filter and vertex and normal maps of [`crate::clean_into`], five
//! passes of one invocation a pixel in one submission, upload and readback included. The depth
//! comes from the disparity on the CPU as before (in f64, as the CPU path has it).
//!
//! Against the CPU path: the same invalid pixels and counts (the masks are comparisons of the
//! same values); the filtered depth within a few units in the last place (a driver may fuse the
//! filter's multiplies and adds); the points within an f32 rounding of the CPU's f64 product;
//! the normals from those points (`tests/gpu_postprocess.rs` states the tolerances and checks
//! them on the adapter it finds, lavapipe in CI).

use crate::maps::{self, BilateralTables, RANGE_LUT};
use crate::{border_mask, checked_left, Cleaned, Params, Smoothing};
use misslam_framework::gpu::{GpuContext, GpuError};
use misslam_framework::StereoCalib;

/// WGSL of the kernels.
pub const POSTPROCESS_WGSL: &str = include_str!("../../../../shaders/stereo/postprocess.wgsl");

/// The kernels' entry points, in the order they run.
const ENTRIES: [&str; 6] = [
    "masks",
    "dilate_rows",
    "apply_specular",
    "bilateral",
    "lift",
    "normal",
];

/// Each entry point's bindings (the numbers of the kernel's `@binding`s).
const BINDINGS: [&[u32]; 6] = [
    &[0, 1, 2, 3, 4, 5, 6, 13],
    &[0, 6, 7],
    &[0, 5, 7, 8, 9, 13],
    &[0, 4, 8, 9, 10],
    &[0, 4, 10, 11],
    &[0, 11, 12],
];

/// The kernels' flags (`FLAG_*` in the WGSL).
const FLAG_BORDER_LEVEL: u32 = 1;
const FLAG_BORDER_MASK: u32 = 2;
const FLAG_SPECULAR: u32 = 4;
const FLAG_BILATERAL: u32 = 8;
const FLAG_STEP_LIMIT: u32 = 16;

/// Workgroups are 8 x 8 pixels.
const TILE: u32 = 8;

/// Milliseconds of one frame on the GPU.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PostGpuTiming {
    /// The tables and the uploads (depth, image, mask) written to the queue.
    pub upload_ms: f64,
    /// The kernels and the copy into the readback buffer, until the host may read it.
    pub gpu_ms: f64,
    /// Copying the maps out of the mapped buffer.
    pub readback_ms: f64,
}

/// The buffers of one image size and channel count, kept from frame to frame.
struct Frame {
    key: (usize, usize, usize, usize),
    params: wgpu::Buffer,
    depth: wgpu::Buffer,
    image: wgpu::Buffer,
    mask: wgpu::Buffer,
    tables: wgpu::Buffer,
    counts: wgpu::Buffer,
    depth_out: wgpu::Buffer,
    vertices: wgpu::Buffer,
    normals: wgpu::Buffer,
    staging: wgpu::Buffer,
    groups: [wgpu::BindGroup; 6],
    /// The staging buffer's layout: depth, vertices, normals, counts (bytes).
    bytes: (u64, u64, u64),
    /// What the tables buffer holds (None: nothing yet).
    tables_key: Option<TablesKey>,
}

/// What the kernels' tables depend on: the filter's radius and sigmas, the specular saturation
/// and the calibration (as bits).
type TablesKey = [u64; 9];

/// The kernels' tables: the range weights (RANGE_LUT + 1), then at `offsets` the spatial
/// weights, the widest spreads per brightest value, (u - cx) / fx per column and (v - cy) / fy
/// per row.
struct Tables {
    key: TablesKey,
    data: Vec<f32>,
    offsets: [u32; 4],
    lut_scale: f32,
}

impl Tables {
    fn key(p: &Params, calib: &StereoCalib, radius: usize) -> TablesKey {
        [
            radius as u64,
            u64::from(p.smooth_sigma_px.to_bits()),
            u64::from(p.smooth_sigma_mm.to_bits()),
            u64::from(p.specular_max_saturation.to_bits()),
            u64::from(calib.width) << 32 | u64::from(calib.height),
            calib.fx.to_bits(),
            calib.fy.to_bits(),
            calib.cx.to_bits(),
            calib.cy.to_bits(),
        ]
    }

    fn new(p: &Params, calib: &StereoCalib, radius: usize, key: TablesKey) -> Self {
        let (w, h) = (calib.width as usize, calib.height as usize);
        let bt = BilateralTables::new(radius, p.smooth_sigma_px, p.smooth_sigma_mm);
        let widest = maps::widest_spreads(p.specular_max_saturation);
        let mut data: Vec<f32> = Vec::with_capacity(RANGE_LUT + 1 + bt.spatial.len() + 256 + w + h);
        data.extend_from_slice(&bt.range);
        let spatial_at = data.len() as u32;
        data.extend_from_slice(&bt.spatial);
        let widest_at = data.len() as u32;
        data.extend(widest.iter().map(|&v| f32::from(v)));
        let xs_at = data.len() as u32;
        data.extend((0..w).map(|u| ((u as f64 - calib.cx) / calib.fx) as f32));
        let ys_at = data.len() as u32;
        data.extend((0..h).map(|v| ((v as f64 - calib.cy) / calib.fy) as f32));
        Tables {
            key,
            data,
            offsets: [spatial_at, widest_at, xs_at, ys_at],
            lut_scale: bt.lut_scale,
        }
    }
}

/// The compiled kernels and the buffers of the last frame's size.
pub struct PostGpu {
    pipelines: Vec<wgpu::ComputePipeline>,
    frame: Option<Frame>,
    /// The tables of the last call's parameters and calibration.
    tables: Option<Tables>,
}

/// Bytes of `n` u8 values rounded up to whole 4-byte words (at least one word).
fn word_bytes(n: usize) -> u64 {
    (n.div_ceil(4).max(1) * 4) as u64
}

impl PostGpu {
    /// Compiles the kernels.
    pub fn new(ctx: &GpuContext) -> Self {
        PostGpu {
            pipelines: ENTRIES
                .iter()
                .map(|e| ctx.compute_pipeline(e, POSTPROCESS_WGSL, e))
                .collect(),
            frame: None,
            tables: None,
        }
    }

    /// The buffers for a `w` x `h` frame with `c` image channels and `tables` floats of tables:
    /// those in `slot` when they fit, else new ones.
    fn frame<'a>(
        slot: &'a mut Option<Frame>,
        pipelines: &[wgpu::ComputePipeline],
        ctx: &GpuContext,
        key: (usize, usize, usize, usize),
    ) -> &'a mut Frame {
        if let Some(f) = slot.take().filter(|f| f.key == key) {
            return slot.insert(f);
        }
        let (w, h, c, tables) = key;
        let n = (w * h) as u64;
        let storage = wgpu::BufferUsages::STORAGE;
        let input = storage | wgpu::BufferUsages::COPY_DST;
        let output = storage | wgpu::BufferUsages::COPY_SRC;
        let params = ctx.buffer(
            "post params",
            64,
            wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
        );
        let depth = ctx.buffer("post depth in", 4 * n, input);
        let image = ctx.buffer("post image", word_bytes(w * h * c), input);
        let mask = ctx.buffer("post mask", word_bytes(w * h), input);
        let tables_buf = ctx.buffer("post tables", 4 * tables as u64, input);
        let counts = ctx.buffer("post counts", 16, output | wgpu::BufferUsages::COPY_DST);
        let masked = ctx.buffer("post depth masked", 4 * n, storage);
        let specular = ctx.buffer("post specular", 4 * n, storage);
        let specular_rows = ctx.buffer("post specular rows", 4 * n, storage);
        let clean = ctx.buffer("post depth clean", 4 * n, storage);
        let far = ctx.buffer("post depth far", 4 * n, storage);
        let depth_out = ctx.buffer("post depth out", 4 * n, output);
        let vertices = ctx.buffer("post vertices", 12 * n, output);
        let normals = ctx.buffer("post normals", 12 * n, output);
        let bytes = (4 * n, 12 * n, 12 * n);
        let staging = ctx.buffer(
            "post readback",
            bytes.0 + bytes.1 + bytes.2 + 16,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let by_binding: [&wgpu::Buffer; 14] = [
            &params,
            &depth,
            &image,
            &mask,
            &tables_buf,
            &masked,
            &specular,
            &specular_rows,
            &clean,
            &far,
            &depth_out,
            &vertices,
            &normals,
            &counts,
        ];
        let groups = std::array::from_fn(|k| {
            let entries: Vec<wgpu::BindGroupEntry> = BINDINGS[k]
                .iter()
                .map(|&b| wgpu::BindGroupEntry {
                    binding: b,
                    resource: by_binding[b as usize].as_entire_binding(),
                })
                .collect();
            ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(ENTRIES[k]),
                layout: &pipelines[k].get_bind_group_layout(0),
                entries: &entries,
            })
        });
        slot.insert(Frame {
            key,
            params,
            depth,
            image,
            mask,
            tables: tables_buf,
            counts,
            depth_out,
            vertices,
            normals,
            staging,
            groups,
            bytes,
            tables_key: None,
        })
    }

    /// [`crate::clean_into`] on the GPU: the same arguments, checks and outputs (the maps
    /// written into `buffers`' allocations), the stages `upload`, `gpu` and `readback`.
    pub fn clean_into(
        &mut self,
        ctx: &GpuContext,
        mut depth: Vec<f32>,
        calib: &StereoCalib,
        pair: Option<&misslam_framework::StereoFrame>,
        p: &Params,
        buffers: (Vec<[f32; 3]>, Vec<[f32; 3]>),
    ) -> Result<(Cleaned, PostGpuTiming), String> {
        let (w, h) = (calib.width as usize, calib.height as usize);
        if depth.len() != w * h {
            return Err(format!(
                "the map has {} values, the calibration says {w}x{h}",
                depth.len()
            ));
        }
        let left = checked_left(pair, w, h)?;
        let limits = ctx.device.limits();
        let (binding, buffer) = (
            limits.max_storage_buffer_binding_size,
            limits.max_buffer_size,
        );
        // The points' and normals' maps are the largest bindings; the readback holds all maps.
        if 12 * (w * h) as u64 > binding || 28 * (w * h) as u64 + 16 > buffer {
            return Err(format!(
                "a {w}x{h} map exceeds the GPU's buffer limits ({binding} bytes a binding, {buffer} a buffer): use device = \"cpu\""
            ));
        }
        let t0 = std::time::Instant::now();
        let radius = if p.smoothing == Smoothing::Bilateral {
            p.smooth_radius
        } else {
            0
        };
        let key = Tables::key(p, calib, radius);
        if self.tables.as_ref().is_none_or(|t| t.key != key) {
            self.tables = Some(Tables::new(p, calib, radius, key));
        }
        let tables = self.tables.as_ref().expect("just set");
        let [spatial_at, widest_at, xs_at, ys_at] = tables.offsets;

        let mut flags = 0;
        let (mut c, mut image_bytes, mut mask_bytes): (usize, &[u8], &[u8]) = (0, &[], &[]);
        if let Some((pair, img, channels)) = left {
            (c, image_bytes) = (channels, &img.data);
            if p.mask_border {
                match border_mask(pair, w, h) {
                    Some(m) => {
                        flags |= FLAG_BORDER_MASK;
                        mask_bytes = &m.data;
                    }
                    None => flags |= FLAG_BORDER_LEVEL,
                }
            }
            if p.mask_specular {
                flags |= FLAG_SPECULAR;
            }
        }
        if p.smoothing == Smoothing::Bilateral {
            flags |= FLAG_BILATERAL;
        }
        if p.max_normal_step_mm.is_finite() {
            flags |= FLAG_STEP_LIMIT;
        }
        let dilate = if flags & FLAG_SPECULAR != 0 {
            p.specular_dilate_px as u32
        } else {
            0
        };
        let f32b = f32::to_bits;
        let uniform: [u32; 16] = [
            w as u32,
            h as u32,
            c as u32,
            flags,
            u32::from(p.black_level),
            u32::from(p.specular_min_value),
            dilate,
            radius as u32,
            f32b(p.min_depth_mm),
            f32b(p.max_depth_mm),
            f32b(tables.lut_scale),
            f32b(p.max_normal_step_mm),
            spatial_at,
            widest_at,
            xs_at,
            ys_at,
        ];
        let pipelines_groups = (
            (w as u32).div_ceil(TILE),
            (h as u32).div_ceil(TILE),
            ctx.device.limits().max_compute_workgroups_per_dimension,
        );
        if pipelines_groups.0 > pipelines_groups.2 || pipelines_groups.1 > pipelines_groups.2 {
            return Err(format!(
                "a {w}x{h} map needs more workgroups than the GPU dispatches: use device = \"cpu\""
            ));
        }
        let f = Self::frame(
            &mut self.frame,
            &self.pipelines,
            ctx,
            (w, h, c.max(1), tables.data.len()),
        );
        let q = &ctx.queue;
        q.write_buffer(&f.params, 0, bytemuck::cast_slice(&uniform));
        // The tables change with the parameters and the calibration only.
        if f.tables_key != Some(key) {
            q.write_buffer(&f.tables, 0, bytemuck::cast_slice(&tables.data));
            f.tables_key = Some(key);
        }
        q.write_buffer(&f.depth, 0, bytemuck::cast_slice(&depth));
        write_bytes(q, &f.image, image_bytes);
        write_bytes(q, &f.mask, mask_bytes);
        let upload_ms = t0.elapsed().as_secs_f64() * 1e3;

        let t1 = std::time::Instant::now();
        let mut enc = ctx.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&f.counts, 0, None);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("depth.postprocess"),
                timestamp_writes: None,
            });
            for (k, pipeline) in self.pipelines.iter().enumerate() {
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, &f.groups[k], &[]);
                pass.dispatch_workgroups(pipelines_groups.0, pipelines_groups.1, 1);
            }
        }
        let (bd, bv, bn) = f.bytes;
        enc.copy_buffer_to_buffer(&f.depth_out, 0, &f.staging, 0, bd);
        enc.copy_buffer_to_buffer(&f.vertices, 0, &f.staging, bd, bv);
        enc.copy_buffer_to_buffer(&f.normals, 0, &f.staging, bd + bv, bn);
        enc.copy_buffer_to_buffer(&f.counts, 0, &f.staging, bd + bv + bn, 16);
        let index = q.submit(Some(enc.finish()));
        let slice = f.staging.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        let gpu_err = |e: String| GpuError::Operation(e).to_string();
        // This submission only: pipelined, the depth node's next pair may be on the GPU too.
        ctx.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
            .map_err(|e| gpu_err(e.to_string()))?;
        rx.recv()
            .map_err(|e| gpu_err(e.to_string()))?
            .map_err(|e| gpu_err(e.to_string()))?;
        let gpu_ms = t1.elapsed().as_secs_f64() * 1e3;

        let t2 = std::time::Instant::now();
        let (mut vertices, mut normals) = buffers;
        // Unmapped whatever happens, so that the next frame can map the buffer again.
        let counts = slice.get_mapped_range().map(|mapped| {
            let (bd, bv, bn) = (bd as usize, bv as usize, bn as usize);
            copy_floats(&mapped[..bd], &mut depth);
            copy_points(&mapped[bd..bd + bv], &mut vertices);
            copy_points(&mapped[bd + bv..bd + bv + bn], &mut normals);
            let c = &mapped[bd + bv + bn..bd + bv + bn + 16];
            let word = |k: usize| {
                u32::from_le_bytes([c[4 * k], c[4 * k + 1], c[4 * k + 2], c[4 * k + 3]]) as usize
            };
            [word(0), word(1), word(2)]
        });
        f.staging.unmap();
        let counts = counts.map_err(|e| gpu_err(e.to_string()))?;
        let readback_ms = t2.elapsed().as_secs_f64() * 1e3;
        Ok((
            Cleaned {
                depth,
                vertices,
                normals,
                out_of_range: counts[0],
                border: counts[1],
                specular: counts[2],
                stages_ms: [
                    ("upload", upload_ms),
                    ("gpu", gpu_ms),
                    ("readback", readback_ms),
                ],
            },
            PostGpuTiming {
                upload_ms,
                gpu_ms,
                readback_ms,
            },
        ))
    }
}

/// Writes `data` into `buf` padded to whole words (nothing when empty: the kernel reads the
/// buffer only when a flag says it holds something).
fn write_bytes(q: &wgpu::Queue, buf: &wgpu::Buffer, data: &[u8]) {
    if data.is_empty() {
        return;
    }
    let whole = data.len() / 4 * 4;
    if whole > 0 {
        q.write_buffer(buf, 0, &data[..whole]);
    }
    if whole < data.len() {
        let mut tail = [0u8; 4];
        tail[..data.len() - whole].copy_from_slice(&data[whole..]);
        q.write_buffer(buf, whole as u64, &tail);
    }
}

/// The mapped bytes as f32 into `out` (its allocation reused).
fn copy_floats(bytes: &[u8], out: &mut Vec<f32>) {
    out.clear();
    match bytemuck::try_cast_slice::<u8, f32>(bytes) {
        Ok(v) => out.extend_from_slice(v),
        Err(_) => out.extend(
            bytes
                .chunks_exact(4)
                .map(|q| f32::from_le_bytes([q[0], q[1], q[2], q[3]])),
        ),
    }
}

/// The mapped bytes as points (three f32 each) into `out` (its allocation reused).
fn copy_points(bytes: &[u8], out: &mut Vec<[f32; 3]>) {
    out.clear();
    match bytemuck::try_cast_slice::<u8, [f32; 3]>(bytes) {
        Ok(v) => out.extend_from_slice(v),
        Err(_) => out.extend(bytes.chunks_exact(12).map(|b| {
            std::array::from_fn(|k| {
                f32::from_le_bytes([b[4 * k], b[4 * k + 1], b[4 * k + 2], b[4 * k + 3]])
            })
        })),
    }
}
