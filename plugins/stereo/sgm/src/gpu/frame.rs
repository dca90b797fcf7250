//! The buffers of one image size and kernel layout, their bind groups, and a pair's commands
//! ([`SgmGpu`]'s kernels specialised, the frame built, the dispatches of each stage).

use super::*;

/// Codes per row in each copy (even, odd) of the right image's census codes: the row and a margin
/// of 4 on either side, even, so that any four consecutive codes are two aligned pairs
/// (`sgm_census.wgsl`, `sgm_paths.wgsl`'s `right_codes`).
pub(super) fn pair_stride(w: usize) -> usize {
    (w + 9) & !1
}

/// The buffers of one size and layout, with their bind groups.
pub(super) struct Frame {
    pub(super) w: usize,
    pub(super) h: usize,
    pub(super) dirs: usize,
    pub(super) layout: Layout,
    pub(super) images: wgpu::Buffer,
    pub(super) mask: wgpu::Buffer,
    /// Two readback buffers, so that a pair can be submitted while the one before is still
    /// being read ([`SgmGpu::submit`]).
    pub(super) staging: [wgpu::Buffer; 2],
    pub(super) census_u: wgpu::Buffer,
    pub(super) aggregate_u: wgpu::Buffer,
    pub(super) select_u: wgpu::Buffer,
    pub(super) median_u: wgpu::Buffer,
    pub(super) speckle_u: wgpu::Buffer,
    /// The aggregated costs: a volume per direction, or the sums.
    pub(super) volumes: wgpu::Buffer,
    pub(super) census_bg: wgpu::BindGroup,
    pub(super) aggregate_bg: wgpu::BindGroup,
    pub(super) select_bg: wgpu::BindGroup,
    pub(super) median_bg: wgpu::BindGroup,
    /// Speckle bind groups of the four entry points, on the median's output and on the
    /// selection's (median off).
    pub(super) speckle_bg: [Vec<wgpu::BindGroup>; 2],
    /// The final map's bits (NaN where invalid), copied to a `staging` buffer.
    pub(super) bits: wgpu::Buffer,
    /// `finish` on the median's output and on the selection's.
    pub(super) finish_bg: [wgpu::BindGroup; 2],
    /// The next pair's commands, recorded while the GPU ran the pair before, and what they
    /// were recorded for.
    pub(super) prepared: std::cell::Cell<Option<(EncodeKey, wgpu::CommandBuffer)>>,
    /// Whether the sums hold zeros (cleared after each pair; false on new buffers).
    pub(super) sums_clean: std::cell::Cell<bool>,
    pub(super) _keep: Vec<wgpu::Buffer>,
}

/// What a pair's commands depend on besides the frame's buffers and kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) struct EncodeKey {
    pub(super) median: bool,
    pub(super) speckle: bool,
    /// The readback buffer.
    pub(super) slot: usize,
    /// The aggregation's workgroups (x, y).
    pub(super) groups: (u32, u32),
}

/// (pipeline, bind group, workgroups) of one dispatch.
pub(super) type Job<'a> = (
    &'a wgpu::ComputePipeline,
    &'a wgpu::BindGroup,
    (u32, u32, u32),
);

pub(super) fn dispatch(pass: &mut wgpu::ComputePass, jobs: &[Job]) {
    for (pl, bg, (x, y, z)) in jobs {
        pass.set_pipeline(pl);
        pass.set_bind_group(0, *bg, &[]);
        pass.dispatch_workgroups(*x, *y, *z);
    }
}

/// A pair's commands with every kernel in one compute pass: the sums cleared first where
/// `clear` names them, the final map copied into `staging` last.
pub(super) fn encode_pair(
    dev: &wgpu::Device,
    stages: &[Vec<Job>],
    clear: Option<&wgpu::Buffer>,
    bits: &wgpu::Buffer,
    staging: &wgpu::Buffer,
    bytes: u64,
) -> wgpu::CommandBuffer {
    let mut enc = dev.create_command_encoder(&Default::default());
    if let Some(v) = clear {
        enc.clear_buffer(v, 0, None);
    }
    {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("sgm"),
            timestamp_writes: None,
        });
        dispatch(&mut pass, &stages.concat());
    }
    enc.copy_buffer_to_buffer(bits, 0, staging, 0, bytes);
    enc.finish()
}

/// A bind group of `entries` (binding, buffer) of group 0 of `pipeline`, for entry points whose
/// automatic layout holds only some of their module's bindings.
pub(super) fn bind_some(
    dev: &wgpu::Device,
    pipeline: &wgpu::ComputePipeline,
    entries: &[(u32, &wgpu::Buffer)],
) -> wgpu::BindGroup {
    let entries: Vec<wgpu::BindGroupEntry> = entries
        .iter()
        .map(|&(binding, b)| wgpu::BindGroupEntry {
            binding,
            resource: b.as_entire_binding(),
        })
        .collect();
    dev.create_bind_group(&wgpu::BindGroupDescriptor {
        label: Some("sgm"),
        layout: &pipeline.get_bind_group_layout(0),
        entries: &entries,
    })
}

impl SgmGpu {
    pub(super) fn pipelines(
        &mut self,
        ctx: &GpuContext,
        l: Layout,
        dirs: u32,
    ) -> Result<(), String> {
        if self.specialised.contains_key(&(l, dirs)) {
            return Ok(());
        }
        let mut constants = vec![
            ("THREADS", l.threads),
            ("PATHS", l.paths),
            ("BYTES", l.bytes),
            ("SUMMED", u32::from(l.summed)),
        ];
        let kernel = if l.lanes > 0 {
            constants.push(("LANES", l.lanes));
            AGGREGATE_SUBGROUP_WGSL
        } else {
            AGGREGATE_WGSL
        };
        let agg = specialise(
            &wgsl_with_uses(
                kernel,
                &[
                    ("sgm_paths.wgsl", PATHS_WGSL),
                    (
                        "sgm_sums.wgsl",
                        if l.atomics64 { SUMS64_WGSL } else { SUMS_WGSL },
                    ),
                ],
            )?,
            &constants,
        )?;
        let (sel_bytes, sel_dirs) = l.selected(dirs);
        let sel = specialise(
            SELECT_WGSL,
            &[
                ("BYTES", sel_bytes),
                ("DIRS", sel_dirs),
                ("THREADS", l.select_threads),
            ],
        )?;
        let pipelines = (
            ctx.compute_pipeline("sgm aggregate", &agg, "main"),
            ctx.compute_pipeline("sgm select", &sel, "main"),
        );
        self.specialised.insert((l, dirs), pipelines);
        Ok(())
    }

    pub(super) fn frame(&mut self, ctx: &GpuContext, w: usize, h: usize, dirs: usize, l: Layout) {
        if self
            .frame
            .as_ref()
            .is_some_and(|f| (f.w, f.h, f.dirs, f.layout) == (w, h, dirs, l))
        {
            return;
        }
        self.frame = None;
        self.uniforms = Default::default();
        let dev = &ctx.device;
        let buffer = |label: &str, size: u64, usage| ctx.buffer(label, size, usage);
        use wgpu::BufferUsages as U;
        let px = (w * h) as u64;
        let image_words = (w * h).div_ceil(4) as u64;
        let images = buffer("sgm images", 8 * image_words, U::STORAGE | U::COPY_DST);
        let mask = buffer("sgm mask", 4 * image_words, U::STORAGE | U::COPY_DST);
        let codes = buffer("sgm census", px * 8, U::STORAGE);
        // The right image's codes, each row twice with margins (`sgm_census.wgsl`).
        let pair_stride = pair_stride(w) as u64;
        let pairs = buffer(
            "sgm census pairs",
            2 * h as u64 * pair_stride * 8,
            U::STORAGE,
        );
        // The aggregated costs (the sums cleared after each pair, and by the first pair on them),
        // and a placeholder for the aggregation's binding the layout does not use.
        let volumes = buffer(
            "sgm volumes",
            l.volumes_bytes(w, h, dirs),
            U::STORAGE | U::COPY_DST,
        );
        let placeholder = buffer("sgm volumes placeholder", 16, U::STORAGE);
        // The aggregation's workgroups, longest paths first.
        let directions: &[(isize, isize)] = if dirs == 8 { &DIRS } else { &DIRS4 };
        let order = workgroup_order(w as u32, h as u32, directions, l.paths);
        let order_buf = buffer(
            "sgm aggregate order",
            4 * order.len() as u64,
            U::STORAGE | U::COPY_DST,
        );
        ctx.queue
            .write_buffer(&order_buf, 0, bytemuck::cast_slice(&order));
        let (per_direction, sums) = if l.summed {
            (&placeholder, &volumes)
        } else {
            (&volumes, &placeholder)
        };
        let disp = buffer("sgm disparity", px * 4, U::STORAGE | U::COPY_SRC);
        let out = buffer("sgm median", px * 4, U::STORAGE | U::COPY_SRC);
        let parent = buffer("sgm speckle parent", px * 4, U::STORAGE);
        let size = buffer("sgm speckle size", px * 4, U::STORAGE);
        let bits = buffer("sgm bits", px * 4, U::STORAGE | U::COPY_SRC);
        let staging = [0, 1].map(|_| buffer("sgm readback", px * 4, U::MAP_READ | U::COPY_DST));
        let uniform = |label: &str, bytes: u64| buffer(label, bytes, U::UNIFORM | U::COPY_DST);
        let census_u = uniform("sgm census params", 32);
        let aggregate_u = uniform("sgm aggregate params", 64 + 8 * 16);
        let select_u = uniform("sgm select params", 48);
        let median_u = uniform("sgm median params", 16);
        let speckle_u = uniform("sgm speckle params", 16);
        let bind = |label: &str, pipeline: &wgpu::ComputePipeline, bufs: &[&wgpu::Buffer]| {
            ctx.bind_buffers(pipeline, label, bufs)
        };
        let (agg, sel) = &self.specialised[&(l, dirs as u32)];
        let census_bg = bind(
            "sgm census",
            &self.census,
            &[&census_u, &images, &codes, &pairs],
        );
        let aggregate_bg = bind(
            "sgm aggregate",
            agg,
            &[
                &aggregate_u,
                &images,
                &codes,
                per_direction,
                sums,
                &pairs,
                &order_buf,
            ],
        );
        let select_bg = bind("sgm select", sel, &[&select_u, &volumes, &mask, &disp]);
        let median_bg = bind("sgm median", &self.median, &[&median_u, &disp, &out]);
        // Each entry point's automatic layout holds only the bindings it uses.
        let speckle_bg = [&out, &disp].map(|target| {
            self.speckle
                .iter()
                .zip(SPECKLE_ENTRIES)
                .map(|(pl, e)| {
                    let all = [&speckle_u, target, &parent, &size, &bits];
                    let used: &[u32] = match e {
                        "merge" => &[0, 1, 2],
                        "apply" => &[0, 1, 2, 3, 4],
                        _ => &[0, 1, 2, 3],
                    };
                    let entries: Vec<_> = used.iter().map(|&b| (b, all[b as usize])).collect();
                    bind_some(dev, pl, &entries)
                })
                .collect()
        });
        let finish_bg = [&out, &disp].map(|result| {
            bind_some(
                dev,
                &self.finish,
                &[(0, &median_u), (1, result), (3, &bits)],
            )
        });
        self.frame = Some(Frame {
            w,
            h,
            dirs,
            layout: l,
            images,
            mask,
            staging,
            census_u,
            aggregate_u,
            select_u,
            median_u,
            speckle_u,
            census_bg,
            aggregate_bg,
            select_bg,
            median_bg,
            speckle_bg,
            bits,
            finish_bg,
            volumes,
            prepared: Default::default(),
            sums_clean: Default::default(),
            _keep: vec![
                codes,
                pairs,
                placeholder,
                order_buf,
                parent,
                size,
                disp,
                out,
            ],
        });
    }

    /// The dispatches of a pair on frame `f`, stage by stage (the timestamps' [`STAGES`]; a
    /// stage switched off holds none).
    pub(super) fn stages<'a>(
        &'a self,
        f: &'a Frame,
        agg: &'a wgpu::ComputePipeline,
        sel: &'a wgpu::ComputePipeline,
        key: EncodeKey,
    ) -> Vec<Vec<Job<'a>>> {
        let (wu, hu) = (f.w as u32, f.h as u32);
        let tiles8 = (wu.div_ceil(8), hu.div_ceil(8));
        let tiles16 = (wu.div_ceil(16), hu.div_ceil(16));
        let on = usize::from(!key.median);
        let mut stages: Vec<Vec<Job>> = vec![
            vec![(&self.census, &f.census_bg, (tiles16.0, tiles16.1, 2))],
            vec![(agg, &f.aggregate_bg, (key.groups.0, key.groups.1, 1))],
            vec![(sel, &f.select_bg, (hu, 1, 1))],
            Vec::new(),
            Vec::new(),
            Vec::new(),
        ];
        if key.median {
            stages[3].push((&self.median, &f.median_bg, (tiles8.0, tiles8.1, 1)));
        }
        if key.speckle {
            // The last speckle kernel writes the final map.
            for (pl, bg) in self.speckle.iter().zip(&f.speckle_bg[on]) {
                stages[4].push((pl, bg, (tiles16.0, tiles16.1, 1)));
            }
        } else {
            stages[5].push((&self.finish, &f.finish_bg[on], (tiles8.0, tiles8.1, 1)));
        }
        stages
    }
}
