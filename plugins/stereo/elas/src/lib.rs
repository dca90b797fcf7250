//! `depth.elas`: Efficient LArge-scale Stereo (Geiger, Roser and Urtasun, ACCV 2010) on
//! rectified pairs, on the CPU, with the dense matching on the GPU on request
//! ([`dense_gpu`], `device = "gpu"`).
//!
//! The pipeline, one module per step:
//! 1. [`descriptor`]: 16-byte Sobel descriptors, SAD cost;
//! 2. [`support`]: support points on a grid with ratio, texture and left-right tests, removal of
//!    inconsistent and redundant points, optional corner points;
//! 3. [`delaunay`]: triangulation of the support points in the left and in the right image;
//! 4. [`dense`]: a disparity plane per triangle (a prior only when |a| < 0.7), candidate
//!    disparities on a grid, and the MAP disparity of every pixel for both images;
//! 5. [`filters`]: left-right check, small segments, gap interpolation, adaptive mean or median.
//!
//! The presets are libelas's: `robotics` leaves unreliable pixels invalid, `middlebury` fills
//! everything. Every parameter can be overridden on top of the preset. One addition, off in both
//! presets: `subpixel` refines the integer MAP disparity by an equiangular fit of the costs at
//! d - 1, d, d + 1 (a surgical scene at 100 mm loses about 4 mm per pixel of disparity).
#![deny(missing_docs)]

pub mod delaunay;
pub mod dense;
pub mod dense_gpu;
pub mod descriptor;
pub mod filters;
pub mod support;

use misslam_framework::{
    BuildContext, BuildError, DisparityMap, DisparityRangeWatch, FloatMap, Flow, FrameInfo, Inputs,
    Metrics, Node, NodeContext, NodeError, NodeResult, Outputs, PointCloud, PortSpec, PortType,
    Registry, StereoFrame, TypedPlugin,
};
use support::SupportPoint;

/// The two parameter sets of libelas.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// Leaves unreliable pixels invalid: stricter support (0.85), small gaps only, adaptive mean.
    #[default]
    Robotics,
    /// Fills everything: looser support (0.95), corners added, all gaps, median.
    Middlebury,
}

impl Preset {
    /// The preset's parameters.
    pub fn params(self) -> ElasParams {
        match self {
            Preset::Robotics => ElasParams::robotics(),
            Preset::Middlebury => ElasParams::middlebury(),
        }
    }
}

/// Declares [`ElasParams`] (resolved, for the library) and [`Params`] (the node's: a preset and
/// optional overrides) from one list: name, type, doc, (robotics, middlebury).
macro_rules! elas_params {
    ($( $(#[doc = $doc:literal])* $name:ident : $ty:ty = ($rob:expr, $mid:expr); )*) => {
        /// Parameters of ELAS (the names are libelas's).
        #[derive(Clone, Copy, Debug, PartialEq)]
        pub struct ElasParams {
            $( $(#[doc = $doc])* pub $name: $ty, )*
        }

        impl ElasParams {
            /// libelas's ROBOTICS setting.
            pub fn robotics() -> Self {
                ElasParams { $( $name: $rob, )* }
            }
            /// libelas's MIDDLEBURY setting.
            pub fn middlebury() -> Self {
                ElasParams { $( $name: $mid, )* }
            }
        }

        /// Parameters of the `depth.elas` node: a `preset`, then any parameter overridden.
        #[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
        #[serde(deny_unknown_fields, default)]
        pub struct Params {
            /// Starting values: `robotics` (unreliable pixels stay invalid) or `middlebury`
            /// (everything filled).
            pub preset: Preset,
            /// Where the dense matching (step 5) runs: "cpu", "gpu" (WGSL, the CPU's integers;
            /// an error without an adapter) or "auto"; every other step runs on the CPU.
            pub device: misslam_framework::gpu::Device,
            $(
                $(#[doc = $doc])*
                #[doc = concat!(" Preset values: robotics ", stringify!($rob), ", middlebury ", stringify!($mid), ".")]
                #[serde(skip_serializing_if = "Option::is_none")]
                pub $name: Option<$ty>,
            )*
        }

        impl Params {
            /// The preset with the overrides applied.
            pub fn resolve(&self) -> ElasParams {
                let mut p = self.preset.params();
                $( if let Some(v) = self.$name { p.$name = v; } )*
                p
            }
        }
    };
}

elas_params! {
    /// Smallest disparity searched, px.
    disp_min: u32 = (0, 0);
    /// Largest disparity searched, px.
    disp_max: u32 = (255, 255);
    /// Support points: the best cost must be below this fraction of the second best.
    support_threshold: f32 = (0.85, 0.95);
    /// Support points: least texture (sum of |descriptor - 128|) of the candidate's patch.
    support_texture: u32 = (10, 10);
    /// Spacing of the support-point candidates, px.
    candidate_stepsize: u32 = (5, 5);
    /// Half-size of the consistency window, in candidates.
    incon_window_size: u32 = (5, 5);
    /// Neighbours within this disparity support a point, px.
    incon_threshold: u32 = (5, 5);
    /// A support point needs this many supporters (itself included).
    incon_min_support: u32 = (5, 5);
    /// Add the image corners as support points (with their nearest point's disparity).
    add_corners: bool = (false, true);
    /// Size of the cells of the candidate-disparity grid, px.
    grid_size: u32 = (20, 20);
    /// Scale of the prior against the SAD cost (the prior is divided by it).
    beta: f32 = (0.02, 0.02);
    /// Uniform part of the prior's mixture (larger: weaker plane prior).
    gamma: f32 = (3.0, 5.0);
    /// Standard deviation of the plane prior, px.
    sigma: f32 = (1.0, 1.0);
    /// Radius of the disparities searched around the plane, in sigmas (at least 2 px).
    sradius: f32 = (2.0, 3.0);
    /// Dense matching: least texture of a pixel's descriptor (0: match every pixel).
    match_texture: u32 = (1, 0);
    /// Left-right check tolerance (support points and dense maps), px.
    lr_threshold: u32 = (2, 2);
    /// Neighbours within this disparity belong to one segment, px.
    speckle_sim_threshold: f32 = (1.0, 1.0);
    /// Segments smaller than this many pixels are removed (0: off).
    speckle_size: u32 = (200, 200);
    /// Longest gap filled by interpolation, px.
    ipol_gap_width: u32 = (3, 5000);
    /// Separable 7-tap median at the end.
    filter_median: bool = (false, true);
    /// Adaptive mean (discontinuity-preserving 8-tap filter) at the end.
    filter_adaptive_mean: bool = (true, false);
    /// Post-process only the left map (the right one is used for the left-right check only).
    postprocess_only_left: bool = (true, false);
    /// Sub-pixel refinement of the MAP disparity (not in libelas; off in both presets).
    subpixel: bool = (false, false);
}

impl Default for ElasParams {
    fn default() -> Self {
        ElasParams::robotics()
    }
}

impl ElasParams {
    /// Checks the parameters; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        let bad = |f: &str, m: String| Err(format!("`{f}` {m}"));
        if self.disp_max > 4096 {
            return bad(
                "disp_max",
                format!("must be at most 4096, got {}", self.disp_max),
            );
        }
        if self.disp_max < self.disp_min + 10 {
            return bad(
                "disp_max",
                format!(
                    "must exceed disp_min ({}) by at least 10 (support points need 10 disparities), got {}",
                    self.disp_min, self.disp_max
                ),
            );
        }
        if !(self.support_threshold > 0.0 && self.support_threshold <= 1.0) {
            return bad(
                "support_threshold",
                format!("must be in (0, 1], got {}", self.support_threshold),
            );
        }
        for (f, v) in [
            ("candidate_stepsize", self.candidate_stepsize),
            ("grid_size", self.grid_size),
        ] {
            if v == 0 {
                return bad(f, "must be at least 1".into());
            }
        }
        for (f, v) in [
            ("beta", self.beta),
            ("gamma", self.gamma),
            ("sigma", self.sigma),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return bad(f, format!("must be positive, got {v}"));
            }
        }
        for (f, v) in [
            ("sradius", self.sradius),
            ("speckle_sim_threshold", self.speckle_sim_threshold),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(f, format!("must be finite and not negative, got {v}"));
            }
        }
        if self.sigma * self.sradius > 64.0 {
            return bad(
                "sradius",
                format!(
                    "sigma x sradius must be at most 64 px, got {}",
                    self.sigma * self.sradius
                ),
            );
        }
        Ok(())
    }
}

/// The result of [`elas`].
#[derive(Clone, Debug)]
pub struct ElasOutput {
    /// Left disparity, px, NaN invalid (row-major).
    pub left: Vec<f32>,
    /// The support points.
    pub support: Vec<SupportPoint>,
    /// Triangles of the left triangulation (indices into `support`).
    pub triangles: Vec<[u32; 3]>,
    /// Wall time of each step, ms.
    pub timing: Timing,
}

/// Wall time of each step of [`elas`], ms.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Timing {
    /// Descriptors of both images.
    pub descriptors: f64,
    /// Support points (matching and removals).
    pub support: f64,
    /// Both triangulations and their planes.
    pub triangulation: f64,
    /// Grids and dense matching of both images.
    pub dense: f64,
    /// Left-right check, segments, gaps, mean or median.
    pub postprocess: f64,
    /// The dense matching's parts when it ran on the GPU.
    pub dense_gpu: Option<dense_gpu::DenseGpuTiming>,
}

/// Buffers reused across frames (a fresh allocation of a few MB per frame costs more in page
/// faults than some of the steps).
#[derive(Default)]
pub struct Scratch {
    desc_l: Vec<descriptor::Desc>,
    desc_r: Vec<descriptor::Desc>,
    sobel_l: (Vec<u8>, Vec<u8>),
    sobel_r: (Vec<u8>, Vec<u8>),
    right: Vec<f32>,
    tmp_l: Vec<f32>,
    tmp_r: Vec<f32>,
    speckle_l: misslam_depth_sgm::sgm::SpeckleScratch,
    speckle_r: misslam_depth_sgm::sgm::SpeckleScratch,
}

impl Scratch {
    /// The right image's disparities of the last run (post-processed only without
    /// `postprocess_only_left`).
    pub fn right_disparity(&self) -> &[f32] {
        &self.right
    }
}

/// Disparities of a rectified gray pair (see [`elas_with`] to reuse buffers across frames).
pub fn elas(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    p: &ElasParams,
) -> Result<ElasOutput, String> {
    elas_with(left, right, w, h, p, &mut Scratch::default())
}

/// Disparities of a rectified gray pair, with buffers kept by the caller.
pub fn elas_with(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    p: &ElasParams,
    s: &mut Scratch,
) -> Result<ElasOutput, String> {
    elas_on(left, right, w, h, p, s, None)
}

/// [`elas_with`] with the dense matching on the GPU ([`dense_gpu::DenseGpu`]): the same output
/// (the sub-pixel fit within a few 1e-7 px).
pub fn elas_gpu(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    p: &ElasParams,
    s: &mut Scratch,
    gpu: (
        &misslam_framework::gpu::GpuContext,
        &mut dense_gpu::DenseGpu,
    ),
) -> Result<ElasOutput, String> {
    elas_on(left, right, w, h, p, s, Some(gpu))
}

fn elas_on(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    p: &ElasParams,
    s: &mut Scratch,
    gpu: Option<(
        &misslam_framework::gpu::GpuContext,
        &mut dense_gpu::DenseGpu,
    )>,
) -> Result<ElasOutput, String> {
    p.validate()?;
    if w == 0 || h == 0 {
        return Err(format!("the images are {w}x{h}: nothing to match"));
    }
    if left.len() != w * h || right.len() != w * h {
        return Err(format!("images must be {w}x{h} gray"));
    }
    if w > 1 << 20 || h > 1 << 20 {
        return Err(format!("images of {w}x{h} are too large"));
    }
    let mut timing = Timing::default();
    let mut clock = std::time::Instant::now();
    let mut lap = |slot: &mut f64| {
        let now = std::time::Instant::now();
        *slot = (now - clock).as_secs_f64() * 1e3;
        clock = now;
    };
    let Scratch {
        desc_l,
        desc_r,
        sobel_l,
        sobel_r,
        right: disp_r,
        tmp_l,
        tmp_r,
        speckle_l,
        speckle_r,
    } = s;
    rayon::join(
        || descriptor::descriptors(left, w, h, desc_l, sobel_l),
        || descriptor::descriptors(right, w, h, desc_r, sobel_r),
    );
    let (dl, dr) = (&*desc_l, &*desc_r);
    lap(&mut timing.descriptors);
    let support = support::support_points(dl, dr, w, h, p);
    lap(&mut timing.support);
    let in_left: Vec<(i32, i32)> = support.iter().map(|s| (s.u, s.v)).collect();
    let in_right: Vec<(i32, i32)> = support.iter().map(|s| (s.u - s.d, s.v)).collect();
    let (tri_l, tri_r) = rayon::join(
        || delaunay::triangulate(&in_left),
        || delaunay::triangulate(&in_right),
    );
    let planes = |tris: &[[u32; 3]]| -> Vec<dense::TrianglePlanes> {
        tris.iter()
            .map(|t| dense::TrianglePlanes::of(t.map(|i| support[i as usize])))
            .collect()
    };
    let (planes_l, planes_r) = (planes(&tri_l), planes(&tri_r));
    lap(&mut timing.triangulation);
    let (table, radius) = dense::prior(p);
    let mut disp_l = vec![f32::NAN; w * h];
    disp_r.clear();
    disp_r.resize(w * h, f32::NAN);
    if let Some((ctx, kernel)) = gpu {
        let (grid_l, grid_r) = rayon::join(
            || dense::DisparityGrid::new(&support, w, h, false, p),
            || dense::DisparityGrid::new(&support, w, h, true, p),
        );
        let image = |tris, planes, grid| dense_gpu::Image { tris, planes, grid };
        timing.dense_gpu = Some(kernel.run(
            ctx,
            (dl, dr),
            (w, h),
            p,
            &support,
            (
                image(&tri_l, &planes_l, &grid_l),
                image(&tri_r, &planes_r, &grid_r),
            ),
            (&table, radius),
            (&mut disp_l, disp_r),
        )?);
    } else {
        rayon::join(
            || {
                let grid = dense::DisparityGrid::new(&support, w, h, false, p);
                let m = dense::Matcher {
                    own: dl,
                    other: dr,
                    w,
                    h,
                    right: false,
                    prior: (&table, radius),
                    p,
                };
                m.run(&support, &tri_l, &planes_l, &grid, &mut disp_l);
            },
            || {
                let grid = dense::DisparityGrid::new(&support, w, h, true, p);
                let m = dense::Matcher {
                    own: dr,
                    other: dl,
                    w,
                    h,
                    right: true,
                    prior: (&table, radius),
                    p,
                };
                m.run(&support, &tri_r, &planes_r, &grid, disp_r);
            },
        );
    }
    lap(&mut timing.dense);
    let both = !p.postprocess_only_left;
    filters::lr_check(&mut disp_l, disp_r, w, p.lr_threshold as f32, both, tmp_l);
    let post =
        |d: &mut [f32], tmp: &mut Vec<f32>, sp: &mut misslam_depth_sgm::sgm::SpeckleScratch| {
            if p.speckle_size > 0 {
                misslam_depth_sgm::sgm::remove_speckles_with(
                    d,
                    w,
                    h,
                    p.speckle_size as usize,
                    p.speckle_sim_threshold,
                    sp,
                );
            }
            filters::gap_interpolation(d, w, h, p.ipol_gap_width as usize, p.add_corners);
            if p.filter_adaptive_mean {
                filters::adaptive_mean(d, w, h, tmp);
            }
            if p.filter_median {
                filters::median(d, w, h, tmp);
            }
        };
    if both {
        rayon::join(
            || post(&mut disp_l, tmp_l, speckle_l),
            || post(disp_r, tmp_r, speckle_r),
        );
    } else {
        post(&mut disp_l, tmp_l, speckle_l);
    }
    lap(&mut timing.postprocess);
    Ok(ElasOutput {
        timing,
        left: disp_l,
        support,
        triangles: tri_l,
    })
}

/// The node.
pub struct ElasNode {
    params: ElasParams,
    /// The dense matching's kernel with `device` = "gpu" (or "auto" with an adapter).
    gpu: Option<(
        std::sync::Arc<misslam_framework::gpu::GpuContext>,
        dense_gpu::DenseGpu,
    )>,
    scratch: Scratch,
    gray_l: Vec<u8>,
    gray_r: Vec<u8>,
    /// Frames whose scene outgrew the disparity range.
    range: DisparityRangeWatch,
}

impl ElasNode {
    /// ELAS on a pair; the left mask (black border) invalidates its pixels.
    pub fn disparity(&mut self, pair: &StereoFrame) -> Result<(FloatMap, ElasOutput), String> {
        let (w, h) = (pair.left.width as usize, pair.left.height as usize);
        if (pair.right.width, pair.right.height) != (pair.left.width, pair.left.height) {
            return Err(format!(
                "left ({}x{}) and right ({}x{}) images differ in size",
                pair.left.width, pair.left.height, pair.right.width, pair.right.height
            ));
        }
        pair.left.gray_into(&mut self.gray_l);
        pair.right.gray_into(&mut self.gray_r);
        let mut out = match &mut self.gpu {
            Some((ctx, kernel)) => elas_gpu(
                &self.gray_l,
                &self.gray_r,
                w,
                h,
                &self.params,
                &mut self.scratch,
                (ctx, kernel),
            )?,
            None => elas_with(
                &self.gray_l,
                &self.gray_r,
                w,
                h,
                &self.params,
                &mut self.scratch,
            )?,
        };
        let mut data = std::mem::take(&mut out.left);
        if let Some(m) = &pair.left_mask {
            for (d, &k) in data.iter_mut().zip(&m.data) {
                if k == 0 {
                    *d = f32::NAN;
                }
            }
        }
        Ok((
            FloatMap {
                width: w as u32,
                height: h as u32,
                data,
            },
            out,
        ))
    }
}

impl Node for ElasNode {
    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        ctx.report_eval("depth.range_saturated_frames", self.range.frames as f64);
        Ok(())
    }

    fn process(
        &mut self,
        ctx: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let pair = inputs.get::<StereoFrame>("stereo")?;
        let (map, out) = self
            .disparity(pair)
            .map_err(|e| NodeError::msg(format!("frame {}: {e}", frame.index)))?;
        let top = self.params.disp_max as f32;
        let range = self.range.check(frame.index, &map, top, ctx.id, "disp_max");
        let calib = pair.calib;
        if out.support.len() < 3 {
            tracing::warn!(
                "frame {}: only {} support points (no texture, or the scene nearer than the \
                 disparity range reaches, `{}.disp_max` = {}?): no disparity",
                frame.index,
                out.support.len(),
                ctx.id,
                self.params.disp_max
            );
        }
        let density = 100.0 * range.valid as f64 / map.data.len().max(1) as f64;
        let support = PointCloud {
            positions: out
                .support
                .iter()
                .filter(|s| {
                    s.u >= 0 && (s.u as u32) < map.width && s.v >= 0 && (s.v as u32) < map.height
                })
                .filter_map(|s| {
                    let z = calib.depth_from_disparity(s.d as f32);
                    z.is_finite().then(|| {
                        [
                            ((s.u as f64 - calib.cx) * z as f64 / calib.fx) as f32,
                            ((s.v as f64 - calib.cy) * z as f64 / calib.fy) as f32,
                            z,
                        ]
                    })
                })
                .collect(),
            colors: None,
        };
        let mut metrics = Metrics::default();
        metrics
            .values
            .insert("elas.support_points".into(), out.support.len() as f64);
        metrics
            .values
            .insert("elas.triangles".into(), out.triangles.len() as f64);
        metrics.values.insert("elas.density_pct".into(), density);
        metrics
            .values
            .insert("elas.range_top_pct".into(), 100.0 * range.share);
        let t = out.timing;
        for (k, v) in [
            ("descriptors", t.descriptors),
            ("support", t.support),
            ("triangulation", t.triangulation),
            ("dense", t.dense),
            ("postprocess", t.postprocess),
        ] {
            metrics.values.insert(format!("elas.ms.{k}"), v);
        }
        let disparity = DisparityMap { map, calib };
        outputs.put("depth", disparity.to_depth())?;
        outputs.put("disparity", disparity)?;
        outputs.put("support", support)?;
        outputs.put("metrics", metrics)?;
        Ok(Flow::Continue)
    }
}

/// Builds the node.
pub fn build(params: Params, ctx: &BuildContext) -> Result<ElasNode, BuildError> {
    let device = params.device;
    let params = params.resolve();
    params.validate().map_err(|m| BuildError::param("", m))?;
    let gpu = ctx
        .gpu
        .for_device(device, ctx.node_id)
        .map_err(|e| BuildError::param("device", e.to_string()))?
        .map(|c| {
            let k = dense_gpu::DenseGpu::new(&c);
            (c, k)
        });
    Ok(ElasNode {
        params,
        gpu,
        scratch: Scratch::default(),
        gray_l: Vec::new(),
        gray_r: Vec::new(),
        range: DisparityRangeWatch::default(),
    })
}

/// Registers `depth.elas`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "depth.elas",
        "ELAS (Geiger 2010): support points, Delaunay plane priors, dense MAP matching, LR check, gap interpolation, adaptive mean or median; presets robotics and middlebury",
        vec![PortSpec::new("stereo", PortType::Stereo, "rectified pair; its left mask is honoured")],
        vec![
            PortSpec::new("disparity", PortType::Disparity, "left disparity, px, NaN invalid"),
            PortSpec::new("depth", PortType::Depth, "left depth, mm, NaN invalid"),
            PortSpec::new("support", PortType::PointCloud, "the support points in 3D, camera frame, mm"),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "elas.support_points, elas.triangles, elas.density_pct (of the left image), elas.range_top_pct (of its valid pixels, at the largest disparity), elas.ms.<step>",
            ),
        ],
        build,
    ))
}
