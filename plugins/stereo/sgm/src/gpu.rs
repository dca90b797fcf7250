//! SGM on the GPU (`shaders/stereo/sgm_*.wgsl`), one submission per pair:
//!
//! 1. census of both images (one invocation per pixel);
//! 2. aggregation along all 4 or 8 directions in one dispatch: a path per THREADS invocations, each
//!    invocation holding four consecutive disparities in a vec4; they exchange their neighbouring
//!    costs and their minimum at each pixel by subgroup shuffles where the adapter's subgroups
//!    have one size that holds a path (`gpu_exchange`), else through workgroup memory with one
//!    barrier per pixel; the workgroups take their paths in the host's order, the longest first
//!    (`gpu_layout::workgroup_order`);
//!    each direction writes its own volume of L, as bytes when the largest cost plus P2 fits
//!    one (the default parameters) and as u16 otherwise; or (`gpu_volumes`: on a discrete GPU,
//!    and where the adapter's storage buffers cannot hold a volume per direction) every
//!    direction adds its L into one volume of u16 sums by atomic adds (one 64-bit add per four
//!    disparities where the adapter has them), which the selection reads as one u16 volume;
//! 3. selection, one workgroup per row: the sums of the volumes, the winner with the uniqueness
//!    margin and the parabola, the right image's winners (atomic minima in workgroup memory) and
//!    the left-right check;
//! 4. the 3x3 median;
//! 5. speckle removal by a parallel union-find, each 16x16 tile in workgroup memory first;
//! 6. the final map's bits, NaN where invalid, so the readback is a plain copy (written by the
//!    speckles' last kernel, or by `finish` when they are off).
//!
//! [`SgmGpu::run`] does one pair; [`SgmGpu::submit`] and [`SgmGpu::collect`] keep two in flight,
//! so that a stream of pairs runs at the pace of the GPU instead of the GPU's time plus the
//! host's (upload, submission, the wait and the copy of the map). On a discrete GPU the host
//! polls for the map before it blocks on the fence (`gpu_wait`).
//! The buffers live across calls (reallocated when the size or the disparity layout changes);
//! every kernel runs in one compute pass, or a pass per stage timed by GPU timestamps
//! ([`SgmGpu::set_breakdown`]). The layout for a configuration and an adapter is
//! `gpu_layout.rs`'s. The kernels compute the
//! same integers as [`crate::sgm::sgm`]; the parity test runs both on Mesa's lavapipe in CI.

use std::collections::HashMap;

mod frame;

use crate::gpu_layout::{paths_of, specialise, workgroup_order, Adapter, Layout};
use crate::reference::{DIRS, DIRS4};
use crate::sgm::{check_pair, GpuWait, SgmParams};
use frame::{dispatch, encode_pair, pair_stride, EncodeKey, Frame};
use misslam_framework::gpu::{wgsl_with_uses, GpuContext, GpuError};

/// WGSL of the kernels.
pub const CENSUS_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_census.wgsl");
/// What both aggregation kernels share: paths, cost, recurrence, store (`// uses:` line).
pub const PATHS_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_paths.wgsl");
/// The volume of sums with 32-bit atomics (`// uses: sgm_sums.wgsl`).
pub const SUMS_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_sums.wgsl");
/// The same with 64-bit atomics, in its place where the adapter has them.
pub const SUMS64_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_sums64.wgsl");
/// Aggregation along all directions, exchanging through workgroup memory.
pub const AGGREGATE_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_aggregate.wgsl");
/// Aggregation along all directions, exchanging by subgroup shuffles.
pub const AGGREGATE_SUBGROUP_WGSL: &str =
    include_str!("../../../../shaders/stereo/sgm_aggregate_subgroup.wgsl");
/// Winner-takes-all and left-right check.
pub const SELECT_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_select.wgsl");
/// 3x3 median.
pub const MEDIAN_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_median.wgsl");
/// Speckle removal (union-find).
pub const SPECKLE_WGSL: &str = include_str!("../../../../shaders/stereo/sgm_speckle.wgsl");

/// The largest disparity count (the right winners' keys keep d in 11 bits).
const MAX_D: u32 = 1024;
/// The widest image (the selection keeps a row's right winners in workgroup memory).
const MAX_W: usize = 4096;

/// Milliseconds of one GPU pair.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SgmGpuTiming {
    /// Images and parameters packed and queued for upload (host time; the first call's
    /// compilation and allocation are only in `total_ms`).
    pub upload_ms: f64,
    /// Census of both images.
    pub census_ms: f64,
    /// All directions.
    pub aggregate_ms: f64,
    /// Winner-takes-all, uniqueness, sub-pixel and left-right check.
    pub select_ms: f64,
    /// The 3x3 median.
    pub median_ms: f64,
    /// Speckle removal.
    pub speckle_ms: f64,
    /// The final map's bits for the host (NaN where invalid), when the speckles are off (else
    /// their last kernel writes them, within `speckle_ms`).
    pub finish_ms: f64,
    /// After the kernels: the copy to the host and the mapping (with GPU timestamps: the wall
    /// time from submission to the host's copy less the kernels' times, so it also holds the
    /// submission and the gaps between the kernels).
    pub readback_ms: f64,
    /// Of `readback_ms`: the host's submission call (wall time).
    pub submit_ms: f64,
    /// Of `readback_ms`: the host's work once the GPU is done, the mapped results copied
    /// (wall time).
    pub copy_ms: f64,
    /// Everything, from the gray images to the disparity map (wall time).
    pub total_ms: f64,
    /// True when the kernels' times come from GPU timestamps; false when each stage was
    /// submitted and waited for on its own, which adds each submission's latency, or when the
    /// stages were not timed (the stage fields are then 0; see [`SgmGpu::set_breakdown`]).
    pub gpu_timestamps: bool,
    /// True when the directions' costs were summed into one volume (`gpu_volumes`).
    pub summed_volumes: bool,
    /// True when the aggregation exchanged by subgroup shuffles (`gpu_exchange`).
    pub subgroups: bool,
    /// True when the sums were added by 64-bit atomics.
    pub atomics64: bool,
}

struct Timestamps {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    read: wgpu::Buffer,
}

/// Query slots: a begin and an end per stage.
const STAGES: u32 = 6;

/// Whether and how [`SgmGpu::run`] times its stages.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Breakdown {
    /// Not at all: every kernel in one compute pass (the fastest; the node's setting).
    #[default]
    Off,
    /// A compute pass per stage with GPU timestamps, where the adapter has them (else as
    /// `Staged`).
    Timestamps,
    /// Each stage submitted and waited for on its own, timed by the wall clock (at the cost of
    /// the overlap).
    Staged,
}

/// The compiled SGM kernels and their buffers.
pub struct SgmGpu {
    census: wgpu::ComputePipeline,
    median: wgpu::ComputePipeline,
    finish: wgpu::ComputePipeline,
    speckle: Vec<wgpu::ComputePipeline>,
    specialised: HashMap<(Layout, u32), (wgpu::ComputePipeline, wgpu::ComputePipeline)>,
    frame: Option<Frame>,
    timestamps: Option<Timestamps>,
    breakdown: Breakdown,
    /// 64-bit atomics for the sums where the adapter has them.
    int64_atomics: bool,
    /// The mask as 0 / 1 bytes, reused.
    host: Vec<u8>,
    /// What each uniform buffer of the frame last received (written again only when it
    /// changes: on the H100 the upload went from 0.09 to 0.12 ms to 0.06).
    uniforms: [Vec<u32>; 5],
    /// Pairs submitted and not yet collected, oldest first (at most [`IN_FLIGHT`]).
    in_flight: std::collections::VecDeque<Pending>,
    /// The readback buffer of the next submission.
    next_slot: usize,
}

/// How long [`SgmGpu::collect`] polls before it blocks ([`SgmParams::gpu_wait`]; a pair
/// takes about a millisecond on an H100).
const SPIN: std::time::Duration = std::time::Duration::from_millis(5);

/// The most pairs [`SgmGpu::submit`] keeps in flight (one per readback buffer).
pub const IN_FLIGHT: usize = 2;

type MapResult = Result<(), wgpu::BufferAsyncError>;

/// A submitted pair: its readback buffer, its submission, the mappings requested (the map,
/// then the timestamps where they were taken) and its timing so far.
struct Pending {
    slot: usize,
    index: wgpu::SubmissionIndex,
    mapped: Vec<std::sync::mpsc::Receiver<MapResult>>,
    bytes: usize,
    timing: SgmGpuTiming,
    stage_ms: [f64; STAGES as usize],
    /// Stages that ran (the others keep 0).
    ran: [bool; STAGES as usize],
    t_all: std::time::Instant,
    t_submit: std::time::Instant,
    /// Poll for the map before blocking ([`SgmParams::gpu_wait`]).
    spin: bool,
}

/// Writes `data` into uniform buffer `buf` unless `last` says it already holds it.
fn write_uniform(q: &wgpu::Queue, buf: &wgpu::Buffer, last: &mut Vec<u32>, data: &[u32]) {
    if last[..] != *data {
        q.write_buffer(buf, 0, words(data));
        last.clear();
        last.extend_from_slice(data);
    }
}

fn words(v: &[u32]) -> &[u8] {
    bytemuck::cast_slice(v)
}

const SPECKLE_ENTRIES: [&str; 4] = ["local", "merge", "count", "apply"];

/// Whether this adapter can run `p`'s `gpu_exchange` (a forced "subgroup" needs subgroups
/// of one size that hold a path); the message names the parameter. The node checks it when it
/// is built, before any frame.
pub fn check_exchange(p: &SgmParams, ctx: &GpuContext) -> Result<(), String> {
    Layout::of(p)
        .exchanged(p.gpu_exchange, ctx.subgroup_size())
        .map(|_| ())
}

impl SgmGpu {
    /// Compiles the kernels that do not depend on the disparity count.
    pub fn new(ctx: &GpuContext) -> Self {
        let timestamps = ctx
            .device
            .features()
            .contains(wgpu::Features::TIMESTAMP_QUERY)
            .then(|| {
                let n = 2 * STAGES;
                let size = u64::from(n) * 8;
                Timestamps {
                    set: ctx.device.create_query_set(&wgpu::QuerySetDescriptor {
                        label: Some("sgm timestamps"),
                        ty: wgpu::QueryType::Timestamp,
                        count: n,
                    }),
                    resolve: ctx.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("sgm timestamps resolve"),
                        size,
                        usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                        mapped_at_creation: false,
                    }),
                    read: ctx.device.create_buffer(&wgpu::BufferDescriptor {
                        label: Some("sgm timestamps read"),
                        size,
                        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                        mapped_at_creation: false,
                    }),
                }
            });
        SgmGpu {
            census: ctx.compute_pipeline("sgm census", CENSUS_WGSL, "main"),
            median: ctx.compute_pipeline("sgm median", MEDIAN_WGSL, "main"),
            finish: ctx.compute_pipeline("sgm finish", MEDIAN_WGSL, "finish"),
            speckle: SPECKLE_ENTRIES
                .iter()
                .map(|e| ctx.compute_pipeline(&format!("sgm speckle {e}"), SPECKLE_WGSL, e))
                .collect(),
            specialised: HashMap::new(),
            frame: None,
            timestamps,
            breakdown: Breakdown::Off,
            int64_atomics: true,
            host: Vec::new(),
            uniforms: Default::default(),
            in_flight: Default::default(),
            next_slot: 0,
        }
    }

    /// Whether the volume of sums may use 64-bit atomics where the adapter has them (the
    /// default; off: two 32-bit atomics per four disparities). The output is the same.
    pub fn set_int64_atomics(&mut self, on: bool) {
        self.int64_atomics = on;
    }

    /// Whether and how the following runs time their stages (the timing's stage fields).
    pub fn set_breakdown(&mut self, breakdown: Breakdown) {
        self.breakdown = breakdown;
    }

    /// The kernels' layout for these parameters on this adapter: the aggregated costs per
    /// direction or summed, as `gpu_volumes` asks and the adapter's buffer limits allow, and
    /// the exchange, as `gpu_exchange` asks and its subgroups allow.
    fn layout(
        &self,
        ctx: &GpuContext,
        p: &SgmParams,
        w: usize,
        h: usize,
        dirs: usize,
    ) -> Result<Layout, String> {
        let limits = ctx.device.limits();
        let max = limits
            .max_storage_buffer_binding_size
            .min(limits.max_buffer_size);
        let a = Adapter {
            max_buffer: max,
            subgroup: ctx.subgroup_size(),
            discrete: ctx.is_discrete(),
            int64_atomics: self.int64_atomics && ctx.has_int64_atomics(),
            max_workgroup: limits
                .max_compute_workgroup_size_x
                .min(limits.max_compute_invocations_per_workgroup),
        };
        Layout::choose(p, (w, h, dirs), a)
    }

    /// Disparity of the left image (px, NaN invalid): the contract of [`crate::sgm::sgm`].
    /// One pair at a time: [`SgmGpu::submit`] then [`SgmGpu::collect`] (an error while pairs
    /// submitted on their own are in flight).
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
        if !self.in_flight.is_empty() {
            return Err(format!(
                "{} GPU SGM pair(s) submitted and not collected: collect them before `run`",
                self.in_flight.len()
            ));
        }
        self.submit(ctx, left, right, w, h, valid, p)?;
        self.collect(ctx)
    }

    /// Pairs submitted and not yet collected.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    /// Uploads a pair and submits its kernels without waiting for them, so that the host can
    /// upload and submit the next pair, or read the one before, while the GPU works: a stream
    /// of pairs runs at the pace of the slower of the two instead of their sum. At most
    /// [`IN_FLIGHT`] pairs, of one size and parameters' layout, and with the breakdown off
    /// when more than one; [`SgmGpu::collect`] returns them in order.
    #[allow(clippy::too_many_arguments)]
    pub fn submit(
        &mut self,
        ctx: &GpuContext,
        left: &[u8],
        right: &[u8],
        w: usize,
        h: usize,
        valid: Option<&[u8]>,
        p: &SgmParams,
    ) -> Result<(), String> {
        let t_all = std::time::Instant::now();
        if self.in_flight.len() >= IN_FLIGHT {
            return Err(format!(
                "{IN_FLIGHT} GPU SGM pairs are in flight already: collect one first"
            ));
        }
        if !self.in_flight.is_empty() && self.breakdown != Breakdown::Off {
            return Err(
                "a timed GPU SGM pair (breakdown on) runs alone: collect the pair in flight first"
                    .into(),
            );
        }
        check_pair(left, right, w, h, valid, p)?;
        if p.max_disparity > MAX_D {
            return Err(format!(
                "`max_disparity` {} exceeds the GPU kernels' {MAX_D}",
                p.max_disparity
            ));
        }
        let max_groups = ctx.device.limits().max_compute_workgroups_per_dimension as usize;
        if h > max_groups {
            return Err(format!(
                "the GPU kernels take images up to {max_groups} px high (one workgroup per row), not {h}: use device = \"cpu\""
            ));
        }
        if w > MAX_W {
            return Err(format!(
                "the GPU kernels take images up to {MAX_W} px wide, not {w}: use device = \"cpu\""
            ));
        }
        let dirs: &[(isize, isize)] = if p.paths == 8 { &DIRS } else { &DIRS4 };
        let layout = self.layout(ctx, p, w, h, dirs.len())?;
        let same_frame = self
            .frame
            .as_ref()
            .is_some_and(|f| (f.w, f.h, f.dirs, f.layout) == (w, h, dirs.len(), layout));
        if !self.in_flight.is_empty() && !same_frame {
            return Err(format!(
                "a {w}x{h} GPU SGM pair needs other buffers than the pair in flight: collect it first"
            ));
        }
        self.pipelines(ctx, layout, dirs.len() as u32)?;
        self.frame(ctx, w, h, dirs.len(), layout);
        let (agg, sel) = &self.specialised[&(layout, dirs.len() as u32)];
        let f = self.frame.as_ref().ok_or("no GPU buffers")?;
        let gpu = |e: GpuError| e.to_string();
        let q = &ctx.queue;
        let t_upload = std::time::Instant::now();
        let (wu, hu) = (w as u32, h as u32);
        let image_words = (w * h).div_ceil(4);
        // The images (and the mask) are written straight into the queue's staging memory,
        // copied at the submission (no wait for a mapping): left and right, each padded to whole
        // words (the kernels read four gray levels per word), and the mask as 0 / 1 bytes.
        let plane = 4 * image_words;
        let size = |bytes: usize| {
            wgpu::BufferSize::new(bytes as u64).ok_or_else(|| "an empty image".to_owned())
        };
        {
            let mut m = q
                .write_buffer_with(&f.images, 0, size(2 * plane)?)
                .ok_or("the GPU could not stage the images")?;
            m.slice(..w * h).copy_from_slice(left);
            m.slice(plane..plane + w * h).copy_from_slice(right);
            m.slice(w * h..plane).fill(0);
            m.slice(plane + w * h..).fill(0);
        }
        if let Some(mask) = valid {
            self.host.clear();
            self.host.extend(mask.iter().map(|&v| u8::from(v != 0)));
            self.host.resize(plane, 0);
            q.write_buffer(&f.mask, 0, &self.host);
        }
        let right_words = image_words as u32;
        // Words of one direction's volume (the aggregation's per-direction layout).
        let volume_words = ((w * h) as u64 * u64::from(layout.dp() * layout.bytes) / 4) as u32;
        write_uniform(
            q,
            &f.census_u,
            &mut self.uniforms[0],
            &[
                wu,
                hu,
                p.census_width / 2,
                p.census_height / 2,
                right_words,
                pair_stride(w) as u32,
                0,
                0,
            ],
        );
        let max_x = ctx.device.limits().max_compute_workgroups_per_dimension;
        let mut agg_params = vec![
            wu,
            hu,
            p.max_disparity,
            p.min_disparity as u32,
            u32::from(p.p1),
            u32::from(p.p2),
            u32::from(p.p2_adaptive),
            u32::from(p.unknown_cost()),
            dirs.len() as u32,
            0, // groups_x, below
            volume_words,
            right_words,
            pair_stride(w) as u32,
            0,
            0,
            0,
        ];
        let mut total_groups = 0u32;
        for &(dx, dy) in dirs {
            let paths = paths_of(wu, hu, (dx, dy));
            agg_params.extend([dx as u32, dy as u32, paths, 0]);
            total_groups += paths.div_ceil(layout.paths);
        }
        agg_params.resize(16 + 8 * 4, 0);
        let groups_x = total_groups.min(max_x);
        agg_params[9] = groups_x;
        write_uniform(q, &f.aggregate_u, &mut self.uniforms[1], &agg_params);
        let (sel_bytes, sel_dirs) = layout.selected(dirs.len() as u32);
        let sel_words = ((w * h) as u64 * u64::from(layout.dp() * sel_bytes) / 4) as u32;
        write_uniform(
            q,
            &f.select_u,
            &mut self.uniforms[2],
            &[
                wu,
                hu,
                p.max_disparity,
                p.min_disparity as u32,
                p.uniqueness_pct,
                u32::from(p.subpixel),
                u32::from(p.lr_check),
                p.lr_max_diff.to_bits(),
                sel_dirs,
                layout.dp(),
                sel_words,
                u32::from(valid.is_some()),
            ],
        );
        write_uniform(q, &f.median_u, &mut self.uniforms[3], &[wu, hu, 0, 0]);
        write_uniform(
            q,
            &f.speckle_u,
            &mut self.uniforms[4],
            &[wu, hu, p.speckle_window, p.speckle_range.to_bits()],
        );
        let mut timing = SgmGpuTiming {
            upload_ms: t_upload.elapsed().as_secs_f64() * 1e3,
            ..Default::default()
        };

        let key = EncodeKey {
            median: p.median,
            speckle: p.speckle_window > 0,
            slot: self.next_slot,
            groups: (groups_x, total_groups.div_ceil(groups_x)),
        };
        let mut stages = self.stages(f, agg, sel, key);
        let bytes = (w * h * 4) as u64;
        let ts = match self.breakdown {
            Breakdown::Timestamps => self.timestamps.as_ref(),
            Breakdown::Off | Breakdown::Staged => None,
        };
        let staged = self.breakdown == Breakdown::Staged
            || (self.breakdown == Breakdown::Timestamps && ts.is_none());
        // The sums are cleared after each pair (below), so a pair clears them itself only when it
        // is the first on these buffers.
        let clear = (layout.summed && !f.sums_clean.get()).then_some(&f.volumes);
        let mut stage_ms = [0.0f64; STAGES as usize];
        let slot = key.slot;
        let staging = &f.staging[slot];
        let commands = if self.breakdown == Breakdown::Off {
            // Untimed: every kernel in one pass (wgpu orders the dispatches by their buffers),
            // recorded while the pair before was on the GPU where it could be.
            let prepared = f
                .prepared
                .take()
                .filter(|(k, _)| *k == key && clear.is_none());
            match prepared {
                Some((_, commands)) => commands,
                None => encode_pair(&ctx.device, &stages, clear, &f.bits, staging, bytes),
            }
        } else {
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            if let Some(v) = clear {
                enc.clear_buffer(v, 0, None);
            }
            for (k, jobs) in stages.iter().enumerate() {
                if jobs.is_empty() {
                    continue;
                }
                let lap = std::time::Instant::now();
                {
                    let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("sgm"),
                        timestamp_writes: ts.map(|t| wgpu::ComputePassTimestampWrites {
                            query_set: &t.set,
                            beginning_of_pass_write_index: Some(2 * k as u32),
                            end_of_pass_write_index: Some(2 * k as u32 + 1),
                        }),
                    });
                    dispatch(&mut pass, jobs);
                }
                if staged {
                    q.submit(Some(enc.finish()));
                    ctx.wait().map_err(gpu)?;
                    stage_ms[k] = lap.elapsed().as_secs_f64() * 1e3;
                    enc = ctx.device.create_command_encoder(&Default::default());
                }
            }
            enc.copy_buffer_to_buffer(&f.bits, 0, staging, 0, bytes);
            if let Some(t) = ts {
                enc.resolve_query_set(&t.set, 0..2 * STAGES, &t.resolve, 0);
                enc.copy_buffer_to_buffer(&t.resolve, 0, &t.read, 0, u64::from(2 * STAGES) * 8);
            }
            enc.finish()
        };
        let t_submit = std::time::Instant::now();
        let index = q.submit(Some(commands));
        timing.submit_ms = t_submit.elapsed().as_secs_f64() * 1e3;
        if layout.summed {
            // The next pair's sums cleared now, in a submission of their own: the GPU clears them
            // while the host waits for this pair's map and copies it (the map waits only for
            // the submission that wrote it), not before the next pair's census.
            let mut enc = ctx.device.create_command_encoder(&Default::default());
            enc.clear_buffer(&f.volumes, 0, None);
            q.submit(Some(enc.finish()));
            f.sums_clean.set(true);
        }
        // Both mappings are requested now; `collect` waits for them.
        let mut buffers = vec![staging];
        buffers.extend(ts.map(|t| &t.read));
        let mapped = buffers
            .iter()
            .map(|buf| {
                let (tx, rx) = std::sync::mpsc::channel();
                buf.slice(..).map_async(wgpu::MapMode::Read, move |r| {
                    let _ = tx.send(r);
                });
                rx
            })
            .collect();
        let ran = std::array::from_fn(|k| stages.get(k).is_some_and(|j| !j.is_empty()));
        if self.breakdown == Breakdown::Off {
            // The next pair's commands (the other readback buffer), recorded while the GPU works
            // on this one: a pair with the same buffers and kernels submits them as they are.
            let next = EncodeKey {
                slot: (slot + 1) % IN_FLIGHT,
                ..key
            };
            stages = self.stages(f, agg, sel, next);
            let commands = encode_pair(
                &ctx.device,
                &stages,
                None,
                &f.bits,
                &f.staging[next.slot],
                bytes,
            );
            f.prepared.set(Some((next, commands)));
        }
        timing.summed_volumes = layout.summed;
        timing.subgroups = layout.lanes > 0;
        timing.atomics64 = layout.atomics64;
        self.next_slot = (slot + 1) % IN_FLIGHT;
        self.in_flight.push_back(Pending {
            slot,
            index,
            mapped,
            bytes: bytes as usize,
            timing,
            stage_ms,
            ran,
            t_all,
            t_submit,
            spin: match p.gpu_wait {
                GpuWait::Auto => ctx.is_discrete(),
                GpuWait::Spin => true,
                GpuWait::Block => false,
            },
        });
        Ok(())
    }

    /// Waits for the oldest pair in flight ([`SgmGpu::submit`]) and returns its disparity
    /// (px, NaN invalid) and timing; `total_ms` runs from its submission call to here, so in a
    /// stream it also holds the time spent on the pairs around it.
    pub fn collect(&mut self, ctx: &GpuContext) -> Result<(Vec<f32>, SgmGpuTiming), String> {
        let Pending {
            slot,
            index,
            mapped,
            bytes,
            mut timing,
            mut stage_ms,
            ran,
            t_all,
            t_submit,
            spin,
        } = self
            .in_flight
            .pop_front()
            .ok_or("no GPU SGM pair in flight to collect")?;
        let f = self.frame.as_ref().ok_or("no GPU buffers")?;
        let q = &ctx.queue;
        let ts = mapped.len() > 1;
        let mut results: Vec<Option<Result<(), String>>> = vec![None; mapped.len()];
        let take = |results: &mut Vec<Option<Result<(), String>>>| {
            for (r, rx) in results.iter_mut().zip(&mapped) {
                if r.is_none() {
                    match rx.try_recv() {
                        Ok(v) => *r = Some(v.map_err(|e| e.to_string())),
                        Err(std::sync::mpsc::TryRecvError::Empty) => {}
                        Err(e) => *r = Some(Err(e.to_string())),
                    }
                }
            }
            results.iter().all(Option::is_some)
        };
        // With `gpu_wait` spinning (a discrete GPU by default) the host polls without blocking
        // for up to `SPIN` first, as CUDA's default schedule does where a core is free: a
        // thread blocked on the fence wakes later than the GPU finishes. Else, and after
        // `SPIN`, it blocks.
        let mut ready = false;
        if spin {
            let until = std::time::Instant::now() + SPIN;
            loop {
                ctx.device
                    .poll(wgpu::PollType::Poll)
                    .map_err(|e| e.to_string())?;
                ready = take(&mut results);
                if ready || std::time::Instant::now() >= until {
                    break;
                }
                std::hint::spin_loop();
            }
        }
        if !ready {
            ctx.device
                .poll(wgpu::PollType::Wait {
                    submission_index: Some(index),
                    timeout: None,
                })
                .map_err(|e| e.to_string())?;
        }
        let t_copy = std::time::Instant::now();
        let mut d = Vec::new();
        let mut stamps = Vec::new();
        let mut buffers = vec![&f.staging[slot]];
        buffers.extend(self.timestamps.as_ref().filter(|_| ts).map(|t| &t.read));
        // Every mapping is waited for and undone, even after an error, so that the readback
        // buffers can be used again.
        let mut failure = None;
        for (k, ((buf, rx), r)) in buffers.iter().zip(&mapped).zip(results).enumerate() {
            let r = r.unwrap_or_else(|| match rx.recv() {
                Ok(v) => v.map_err(|e| e.to_string()),
                Err(e) => Err(e.to_string()),
            });
            if let Err(e) = r {
                failure.get_or_insert(e);
                continue;
            }
            match buf.slice(..).get_mapped_range() {
                Ok(view) if k == 0 => {
                    // NaN where invalid already (`finish`): a plain copy. (Split over rayon's
                    // threads it took 0.31 ms on the H100 machine instead of 0.19.)
                    // Into fresh memory, not zeroed first (on the H100 machine the copy took 0.15
                    // ms of the pair's 1.2).
                    d = match bytemuck::try_cast_slice::<u8, f32>(&view[..bytes]) {
                        Ok(v) => v.to_vec(),
                        Err(_) => bytemuck::pod_collect_to_vec(&view[..bytes]),
                    };
                }
                Ok(view) => {
                    stamps = view
                        .chunks_exact(8)
                        .map(|b| u64::from_le_bytes(b.try_into().unwrap_or_default()))
                        .collect();
                }
                Err(e) => {
                    failure.get_or_insert(e.to_string());
                }
            }
            buf.unmap();
        }
        if let Some(e) = failure {
            return Err(format!("the GPU SGM readback failed: {e}"));
        }
        let after_submit = t_submit.elapsed().as_secs_f64() * 1e3;
        timing.copy_ms = t_copy.elapsed().as_secs_f64() * 1e3;
        let mut kernels = 0.0;
        if ts {
            let period = f64::from(q.get_timestamp_period()) * 1e-6;
            for (k, ms) in stage_ms.iter_mut().enumerate() {
                if ran[k] {
                    *ms = stamps[2 * k + 1].saturating_sub(stamps[2 * k]) as f64 * period;
                    kernels += *ms;
                }
            }
            timing.gpu_timestamps = true;
        }
        [
            timing.census_ms,
            timing.aggregate_ms,
            timing.select_ms,
            timing.median_ms,
            timing.speckle_ms,
            timing.finish_ms,
        ] = stage_ms;
        timing.readback_ms = (after_submit - kernels).max(0.0);
        timing.total_ms = t_all.elapsed().as_secs_f64() * 1e3;
        Ok((d, timing))
    }
}
