//! `depth.postprocess`: turns a stereo node's disparity (or depth) into the cleaned depth, vertex
//! map and normal map the deformation and fusion stages read (method.md 1.3): disparity to
//! depth, range limits, masks (the black rectification border, specular highlights), optional
//! edge-preserving smoothing, and vertex / normal maps. The operations are the plain functions
//! of [`maps`].
#![deny(missing_docs)]

pub mod gpu;
pub mod maps;

use misslam_framework::{
    BuildContext, BuildError, DepthMap, Device, DisparityMap, FloatMap, Flow, FrameInfo,
    GpuContext, Inputs, Metrics, Node, NodeContext, NodeError, NodeResult, NormalMap, Outputs,
    PortSpec, PortType, Registry, StereoCalib, StereoFrame, TypedPlugin, VertexMap,
};
use rayon::prelude::*;
use std::sync::Arc;

pub use maps::Pinhole;

/// Edge-preserving smoothing.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Smoothing {
    /// None.
    None,
    /// Bilateral filter on depth (`smooth_radius`, `smooth_sigma_px`, `smooth_sigma_mm`).
    Bilateral,
}

/// Parameters of `depth.postprocess`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Nearest valid depth, mm.
    pub min_depth_mm: f32,
    /// Farthest valid depth, mm.
    pub max_depth_mm: f32,
    /// Invalidate the black rectification border: the pair's left mask when it has one, else
    /// pixels whose brightest channel is below `black_level`.
    pub mask_border: bool,
    /// Brightest-channel level below which a pixel counts as border (without a left mask).
    pub black_level: u8,
    /// Invalidate specular highlights (stereo matching is wrong on them).
    pub mask_specular: bool,
    /// A highlight's brightest channel is at least this.
    pub specular_min_value: u8,
    /// A highlight's saturation, (max - min) / max, is at most this.
    pub specular_max_saturation: f32,
    /// Grow the highlight mask by this many pixels.
    pub specular_dilate_px: usize,
    /// Edge-preserving smoothing of depth.
    pub smoothing: Smoothing,
    /// Bilateral radius, pixels.
    pub smooth_radius: usize,
    /// Bilateral spatial sigma, pixels.
    pub smooth_sigma_px: f32,
    /// Bilateral depth sigma, mm (steps much larger than this are kept).
    pub smooth_sigma_mm: f32,
    /// No normal across a depth step larger than this, mm (an occlusion edge).
    pub max_normal_step_mm: f32,
    /// Where the masks, the filter and the maps run: "cpu", "gpu" (WGSL, `gpu.rs`; an error
    /// without an adapter) or "auto". The GPU gives the same invalid pixels and counts, and
    /// depth, points and normals within a few f32 roundings of the CPU's.
    pub device: Device,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            min_depth_mm: 10.0,
            max_depth_mm: 300.0,
            mask_border: true,
            black_level: 10,
            mask_specular: true,
            specular_min_value: 240,
            specular_max_saturation: 0.2,
            specular_dilate_px: 3,
            smoothing: Smoothing::Bilateral,
            smooth_radius: 3,
            smooth_sigma_px: 2.0,
            smooth_sigma_mm: 1.5,
            max_normal_step_mm: 3.0,
            device: Device::Cpu,
        }
    }
}

impl Params {
    /// Checks the ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.min_depth_mm >= 0.0 && self.max_depth_mm > self.min_depth_mm) {
            return Err(format!(
                "`min_depth_mm` ({}) must be >= 0 and below `max_depth_mm` ({})",
                self.min_depth_mm, self.max_depth_mm
            ));
        }
        if !(0.0..=1.0).contains(&self.specular_max_saturation) {
            return Err(format!(
                "`specular_max_saturation` must lie in [0, 1], got {}",
                self.specular_max_saturation
            ));
        }
        if self.specular_dilate_px > 32 || self.smooth_radius > 15 {
            return Err(format!(
                "`specular_dilate_px` ({}) must be <= 32 and `smooth_radius` ({}) <= 15",
                self.specular_dilate_px, self.smooth_radius
            ));
        }
        for (name, v, finite) in [
            ("smooth_sigma_px", self.smooth_sigma_px, true),
            ("smooth_sigma_mm", self.smooth_sigma_mm, true),
            // Infinite: no step is too large.
            ("max_normal_step_mm", self.max_normal_step_mm, false),
        ] {
            if v.is_nan() || v <= 0.0 || (finite && v.is_infinite()) {
                return Err(format!("`{name}` must be a positive number, got {v}"));
            }
        }
        Ok(())
    }
}

/// The cleaned maps of one frame.
#[derive(Clone, Debug)]
pub struct Cleaned {
    /// Depth, mm, NaN invalid.
    pub depth: Vec<f32>,
    /// Camera-frame points, mm.
    pub vertices: Vec<[f32; 3]>,
    /// Unit normals towards the camera.
    pub normals: Vec<[f32; 3]>,
    /// Pixels invalidated by the range limits.
    pub out_of_range: usize,
    /// Pixels invalidated by the border mask.
    pub border: usize,
    /// Pixels invalidated by the specular mask.
    pub specular: usize,
    /// Milliseconds of each step: on the CPU `masks` (range limits, border and specular masks),
    /// `smooth` (the bilateral filter) and `maps` (vertex and normal maps); on the GPU `upload`,
    /// `gpu` (the kernels, until the maps may be read) and `readback`.
    pub stages_ms: [(&'static str, f64); 3],
}

/// Runs the whole chain on depth (mm) with an optional pair for the masks.
pub fn clean(
    depth: Vec<f32>,
    calib: &StereoCalib,
    pair: Option<&StereoFrame>,
    p: &Params,
) -> Result<Cleaned, String> {
    clean_into(depth, calib, pair, p, (Vec::new(), Vec::new()))
}

/// [`clean`], writing the vertex and normal maps into `buffers` (reused when they have the
/// image's size, so a caller that gets them back saves the allocations).
pub fn clean_into(
    mut depth: Vec<f32>,
    calib: &StereoCalib,
    pair: Option<&StereoFrame>,
    p: &Params,
    buffers: (Vec<[f32; 3]>, Vec<[f32; 3]>),
) -> Result<Cleaned, String> {
    let (w, h) = (calib.width as usize, calib.height as usize);
    if depth.len() != w * h {
        return Err(format!(
            "the map has {} values, the calibration says {w}x{h}",
            depth.len()
        ));
    }
    let t = std::time::Instant::now();
    let mut lap = {
        let mut last = t;
        move || {
            let now = std::time::Instant::now();
            let ms = (now - last).as_secs_f64() * 1e3;
            last = now;
            ms
        }
    };
    let left = checked_left(pair, w, h)?;
    let out_of_range = maps::limit_range(&mut depth, p.min_depth_mm, p.max_depth_mm);
    let (mut border, mut specular) = (0, 0);
    if let Some((pair, img, c)) = left {
        if p.mask_border {
            border = match border_mask(pair, w, h) {
                Some(m) => invalidate::<1>(&mut depth, &m.data, |v| v[0] == 0),
                None => {
                    let dark = p.black_level;
                    match c {
                        1 => invalidate::<1>(&mut depth, &img.data, |v| v[0] < dark),
                        3 => invalidate::<3>(&mut depth, &img.data, |v| {
                            v[0].max(v[1]).max(v[2]) < dark
                        }),
                        // Other channel counts: the brightest channel of each pixel first.
                        _ => {
                            let hi: Vec<u8> = img
                                .data
                                .chunks_exact(c)
                                .map(|px| px.iter().copied().max().unwrap_or(0))
                                .collect();
                            invalidate::<1>(&mut depth, &hi, |v| v[0] < dark)
                        }
                    }
                }
            };
        }
        if p.mask_specular {
            let m = maps::specular_mask(
                &img.data,
                c,
                w,
                h,
                p.specular_min_value,
                p.specular_max_saturation,
                p.specular_dilate_px,
            );
            specular = invalidate::<1>(&mut depth, &m, |v| v[0] != 0);
        }
    }
    let masks_ms = lap();
    if p.smoothing == Smoothing::Bilateral {
        depth = maps::bilateral(
            &depth,
            w,
            h,
            p.smooth_radius,
            p.smooth_sigma_px,
            p.smooth_sigma_mm,
        );
    }
    let smooth_ms = lap();
    let k = Pinhole {
        width: w,
        height: h,
        fx: calib.fx,
        fy: calib.fy,
        cx: calib.cx,
        cy: calib.cy,
    };
    let (mut vertices, mut normals) = buffers;
    maps::vertex_normal_maps_into(
        &depth,
        &k,
        p.max_normal_step_mm,
        &mut vertices,
        &mut normals,
    );
    Ok(Cleaned {
        depth,
        vertices,
        normals,
        out_of_range,
        border,
        specular,
        stages_ms: [("masks", masks_ms), ("smooth", smooth_ms), ("maps", lap())],
    })
}

/// The pair's left image and its channel count, checked against the depth's size (`w` x `h`);
/// the message says what does not fit.
fn checked_left(
    pair: Option<&StereoFrame>,
    w: usize,
    h: usize,
) -> Result<Option<(&StereoFrame, &misslam_framework::Image, usize)>, String> {
    let Some(pair) = pair else { return Ok(None) };
    let img = &*pair.left;
    if (img.width as usize, img.height as usize) != (w, h) {
        return Err(format!(
            "the left image is {}x{} but the depth is {w}x{h}",
            img.width, img.height
        ));
    }
    let c = img.channels as usize;
    if c == 0 || img.data.len() != w * h * c {
        return Err(format!(
            "the left image has {} bytes for {w}x{h} pixels of {c} channels",
            img.data.len()
        ));
    }
    Ok(Some((pair, img, c)))
}

/// The border mask the pair brings: its left mask when it has one of the image's size (else the
/// black level decides).
fn border_mask(pair: &StereoFrame, w: usize, h: usize) -> Option<&misslam_framework::Mask> {
    pair.left_mask.as_ref().filter(|m| m.data.len() == w * h)
}

/// Sets to NaN each valid depth whose pixel (`C` bytes of `data`) is `bad`, in parallel, and
/// returns how many it set.
fn invalidate<const C: usize>(
    depth: &mut [f32],
    data: &[u8],
    bad: impl Fn(&[u8; C]) -> bool + Sync,
) -> usize {
    const CHUNK: usize = 4096;
    depth
        .par_chunks_mut(CHUNK)
        .zip(data.par_chunks(CHUNK * C))
        .map(|(zs, px)| {
            let mut n = 0;
            for (z, v) in zs.iter_mut().zip(px.as_chunks::<C>().0) {
                // Branch-free, so it vectorises.
                let kill = z.is_finite() & bad(v);
                n += usize::from(kill);
                *z = if kill { f32::NAN } else { *z };
            }
            n
        })
        .sum()
}

/// The node.
pub struct PostprocessNode {
    params: Params,
    /// The vertex and normal maps of the last frames (at most [`KEPT_MAPS`], the oldest first):
    /// once no other holder is left, their buffers are taken back for a new frame's maps.
    recent: std::collections::VecDeque<(Arc<VertexMap>, Arc<NormalMap>)>,
    /// The GPU kernels, with `device` = "gpu" (or "auto" with an adapter).
    gpu: Option<(Arc<GpuContext>, gpu::PostGpu)>,
}

/// How many frames' maps `depth.postprocess` keeps for their buffers: a consumer may hold a
/// frame's maps into the next frame (`fusion.surfel` anchors a frame's keypoints at the start
/// of the next), and pipelined, the later levels are a frame or two behind.
pub const KEPT_MAPS: usize = 3;

impl PostprocessNode {
    /// The buffers of the oldest kept maps nothing else holds, else empty ones.
    fn recycled(&mut self) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
        let free = self
            .recent
            .iter()
            .position(|(v, n)| Arc::strong_count(v) == 1 && Arc::strong_count(n) == 1);
        match free.and_then(|i| self.recent.remove(i)) {
            Some((v, n)) => (
                Arc::try_unwrap(v).map(|v| v.points).unwrap_or_default(),
                Arc::try_unwrap(n).map(|n| n.normals).unwrap_or_default(),
            ),
            None => (Vec::new(), Vec::new()),
        }
    }

    /// Keeps a frame's maps for their buffers (dropping the oldest past [`KEPT_MAPS`]).
    fn keep(&mut self, maps: (Arc<VertexMap>, Arc<NormalMap>)) {
        self.recent.push_back(maps);
        while self.recent.len() > KEPT_MAPS {
            self.recent.pop_front();
        }
    }
}

impl Node for PostprocessNode {
    fn process(
        &mut self,
        ctx: &mut NodeContext,
        _: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let pair = inputs.opt::<StereoFrame>("stereo")?;
        let (depth, calib) = if let Some(d) = inputs.opt::<DisparityMap>("disparity")? {
            let c = d.calib;
            (
                d.map
                    .data
                    .par_iter()
                    .map(|&v| c.depth_from_disparity(v))
                    .collect(),
                c,
            )
        } else if let Some(d) = inputs.opt::<DepthMap>("depth")? {
            (d.map.data.clone(), d.calib)
        } else {
            return Err(NodeError::msg(
                "neither `disparity` nor `depth` received anything on this frame",
            ));
        };
        let buffers = self.recycled();
        let pair = pair.map(|p| p.as_ref());
        let c = match &mut self.gpu {
            Some((gpu, kernels)) => kernels
                .clean_into(gpu, depth, &calib, pair, &self.params, buffers)
                .map(|(c, _)| c),
            None => clean_into(depth, &calib, pair, &self.params, buffers),
        }
        .map_err(NodeError::msg)?;
        for (stage, ms) in c.stages_ms {
            ctx.report_stage_ms(stage, ms);
        }
        let n = c.depth.len().max(1) as f64;
        let valid = c.depth.par_iter().filter(|v| v.is_finite()).count() as f64;
        let mut m = Metrics::default();
        m.values
            .insert("postprocess.valid_pct".into(), 100.0 * valid / n);
        m.values.insert(
            "postprocess.specular_pct".into(),
            100.0 * c.specular as f64 / n,
        );
        m.values
            .insert("postprocess.border_pct".into(), 100.0 * c.border as f64 / n);
        m.values.insert(
            "postprocess.out_of_range_pct".into(),
            100.0 * c.out_of_range as f64 / n,
        );
        let (w, h) = (calib.width, calib.height);
        outputs.put(
            "depth",
            DepthMap {
                map: FloatMap {
                    width: w,
                    height: h,
                    data: c.depth,
                },
                calib,
            },
        )?;
        let vertices = Arc::new(VertexMap {
            width: w,
            height: h,
            points: c.vertices,
        });
        let normals = Arc::new(NormalMap {
            width: w,
            height: h,
            normals: c.normals,
        });
        outputs.put_arc("vertices", Arc::clone(&vertices))?;
        outputs.put_arc("normals", Arc::clone(&normals))?;
        self.keep((vertices, normals));
        outputs.put("metrics", m)?;
        Ok(Flow::Continue)
    }
}

/// Builds the node.
pub fn build(params: Params, ctx: &BuildContext) -> Result<PostprocessNode, BuildError> {
    params.validate().map_err(|m| BuildError::Param {
        key: None,
        path: String::new(),
        message: m,
    })?;
    let gpu = ctx
        .gpu
        .for_device(params.device, ctx.node_id)
        .map_err(|e| BuildError::param("device", e.to_string()))?
        .map(|c| {
            let k = gpu::PostGpu::new(&c);
            (c, k)
        });
    Ok(PostprocessNode {
        params,
        recent: Default::default(),
        gpu,
    })
}

/// Registers `depth.postprocess`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "depth.postprocess",
        "disparity to depth, range limits, border and specular masks, bilateral smoothing, vertex and normal maps",
        vec![
            PortSpec::optional("disparity", PortType::Disparity, "a stereo node's disparity, px"),
            PortSpec::optional("depth", PortType::Depth, "or depth, mm"),
            PortSpec::optional(
                "stereo",
                PortType::Stereo,
                "the pair (its left image and mask drive the border and specular masks)",
            ),
        ],
        vec![
            PortSpec::new("depth", PortType::Depth, "cleaned depth, mm, NaN invalid"),
            PortSpec::new("vertices", PortType::VertexMap, "camera-frame points, mm"),
            PortSpec::new("normals", PortType::NormalMap, "unit normals towards the camera"),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "postprocess.valid_pct, specular_pct, border_pct, out_of_range_pct",
            ),
        ],
        build,
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use misslam_framework::Image;
    use std::sync::Arc;

    #[test]
    fn a_left_image_with_the_wrong_byte_count_is_an_error_naming_it() {
        let (w, h) = (8u32, 6u32);
        let calib = StereoCalib {
            width: w,
            height: h,
            fx: 100.0,
            fy: 100.0,
            cx: 4.0,
            cy: 3.0,
            cx_right: 4.0,
            baseline_mm: 5.0,
        };
        // Claims 8x6x3 but holds one row fewer (built field by field, as a plugin could).
        let short = Image {
            width: w,
            height: h,
            channels: 3,
            data: vec![128; (w * (h - 1) * 3) as usize],
        };
        let full = Image::new(w, h, 3, vec![128; (w * h * 3) as usize]).unwrap();
        let pair = |left: Image| StereoFrame {
            index: 0,
            timestamp: 0.0,
            left: Arc::new(left),
            right: Arc::new(full.clone()),
            calib,
            left_mask: None,
            right_mask: None,
        };
        let depth = vec![60.0f32; (w * h) as usize];
        let err = clean(
            depth.clone(),
            &calib,
            Some(&pair(short)),
            &Params::default(),
        )
        .err()
        .unwrap();
        assert!(err.contains("120 bytes") && err.contains("8x6"), "{err}");
        assert!(clean(depth, &calib, Some(&pair(full.clone())), &Params::default()).is_ok());
    }

    #[test]
    fn masks_invalidate_exactly_their_pixels_and_count_them() {
        // 70x70 (more pixels than one parallel chunk): a black band (the border), one white
        // pixel (specular, dilated by 1 px), a NaN depth inside the band (not counted).
        let (w, h) = (70usize, 70usize);
        let calib = StereoCalib {
            width: w as u32,
            height: h as u32,
            fx: 100.0,
            fy: 100.0,
            cx: 35.0,
            cy: 35.0,
            cx_right: 35.0,
            baseline_mm: 5.0,
        };
        let mut img = vec![100u8; w * h * 3];
        for y in 0..h {
            for x in 0..3 {
                img[3 * (y * w + x)..3 * (y * w + x) + 3].fill(0);
            }
        }
        let white = 40 * w + 40;
        img[3 * white..3 * white + 3].fill(255);
        let mut depth = vec![60.0f32; w * h];
        depth[10 * w + 1] = f32::NAN;
        let pair = |left_mask: Option<misslam_framework::Mask>| StereoFrame {
            index: 0,
            timestamp: 0.0,
            left: Arc::new(Image::new(w as u32, h as u32, 3, img.clone()).unwrap()),
            right: Arc::new(Image::new(w as u32, h as u32, 3, img.clone()).unwrap()),
            calib,
            left_mask,
            right_mask: None,
        };
        let p = Params {
            specular_dilate_px: 1,
            smoothing: Smoothing::None,
            ..Params::default()
        };
        let c = clean(depth.clone(), &calib, Some(&pair(None)), &p).unwrap();
        assert_eq!(c.border, 3 * h - 1, "the band, less the NaN pixel");
        assert_eq!(c.specular, 9, "the white pixel and its 8 neighbours");
        for (i, z) in c.depth.iter().enumerate() {
            let (x, y) = (i % w, i / w);
            let masked = x < 3 || (x.abs_diff(40) <= 1 && y.abs_diff(40) <= 1);
            assert_eq!(z.is_nan(), masked, "({x}, {y})");
        }
        // A left mask replaces the black level: only its zeros are border.
        let mut mask = vec![255u8; w * h];
        mask[5 * w..6 * w].fill(0);
        let m = misslam_framework::Mask {
            width: w as u32,
            height: h as u32,
            data: mask,
        };
        let c = clean(depth, &calib, Some(&pair(Some(m))), &p).unwrap();
        assert_eq!(c.border, w);
        assert!(c.depth[5 * w + 1].is_nan() && c.depth[20 * w + 1].is_finite());
    }

    #[test]
    fn map_buffers_come_back_only_when_nothing_else_holds_them() {
        let mut node = PostprocessNode {
            params: Params::default(),
            recent: Default::default(),
            gpu: None,
        };
        let maps = || {
            (
                Arc::new(VertexMap {
                    width: 2,
                    height: 1,
                    points: vec![[1.0; 3]; 2],
                }),
                Arc::new(NormalMap {
                    width: 2,
                    height: 1,
                    normals: vec![[0.0, 0.0, -1.0]; 2],
                }),
            )
        };
        // A consumer still holds the last maps: their buffers are not taken.
        let (v, n) = maps();
        node.keep((Arc::clone(&v), Arc::clone(&n)));
        let (bv, bn) = node.recycled();
        assert!(bv.is_empty() && bn.is_empty());
        assert_eq!(v.points, vec![[1.0; 3]; 2], "the held maps are untouched");
        // A later frame's maps nobody holds come back, while the held ones stay kept.
        let (v2, n2) = maps();
        let (pv, pn) = (v2.points.as_ptr(), n2.normals.as_ptr());
        node.keep((v2, n2));
        let (bv, bn) = node.recycled();
        assert_eq!((bv.as_ptr(), bn.as_ptr()), (pv, pn));
        assert_eq!(node.recent.len(), 1);
        // Once the first frame is done too, its buffers come back.
        let (pv, pn) = (v.points.as_ptr(), n.normals.as_ptr());
        drop((v, n));
        let (bv, bn) = node.recycled();
        assert_eq!((bv.as_ptr(), bn.as_ptr()), (pv, pn));
        assert!(node.recent.is_empty());
        // At most KEPT_MAPS frames are kept.
        for _ in 0..KEPT_MAPS + 2 {
            node.keep(maps());
        }
        assert_eq!(node.recent.len(), KEPT_MAPS);
    }
}
