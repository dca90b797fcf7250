//! Payloads: the data that flows between nodes (method.md section 0).
//!
//! Every payload travels as an `Arc`, so handing one output to several consumers never copies it.
//! Units: millimetres for geometry, pixels for images, seconds for time. Maps use NaN for invalid.

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;

use nalgebra::Isometry3;

/// Rectified pinhole stereo calibration of the left camera plus the right principal point.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StereoCalib {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x (left camera), pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Principal point x of the right camera, pixels (`doffs = cx_right - cx`).
    pub cx_right: f64,
    /// Baseline, mm.
    pub baseline_mm: f64,
}

impl StereoCalib {
    /// `cx_right - cx`, pixels.
    pub fn doffs(&self) -> f64 {
        self.cx_right - self.cx
    }

    /// Depth in mm of a disparity in pixels: `Z = fx * b / (d + doffs)`; NaN where not positive.
    pub fn depth_from_disparity(&self, d: f32) -> f32 {
        let denom = d as f64 + self.doffs();
        if d.is_finite() && denom > 0.0 {
            (self.fx * self.baseline_mm / denom) as f32
        } else {
            f32::NAN
        }
    }

    /// Disparity in pixels of a depth in mm (inverse of [`Self::depth_from_disparity`]).
    pub fn disparity_from_depth(&self, z: f32) -> f32 {
        if z.is_finite() && z > 0.0 {
            (self.fx * self.baseline_mm / z as f64 - self.doffs()) as f32
        } else {
            f32::NAN
        }
    }

    /// Checks that every value is finite and physically meaningful; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        let finite = [
            ("fx", self.fx),
            ("fy", self.fy),
            ("cx", self.cx),
            ("cy", self.cy),
            ("cx_right", self.cx_right),
            ("baseline_mm", self.baseline_mm),
        ];
        for (name, v) in finite {
            if !v.is_finite() {
                return Err(format!("`{name}` is {v}, not a finite number"));
            }
        }
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(format!(
                "focal lengths must be positive (fx = {}, fy = {})",
                self.fx, self.fy
            ));
        }
        if self.baseline_mm <= 0.0 {
            return Err(format!(
                "`baseline_mm` must be positive, got {}",
                self.baseline_mm
            ));
        }
        Ok(())
    }
}

/// An interleaved 8-bit image with 1 (gray) or 3 (RGB) channels, rows tightly packed.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// 1 or 3.
    pub channels: u8,
    /// `width * height * channels` bytes.
    pub data: Vec<u8>,
}

impl Image {
    /// A new image; fails when the buffer does not match the shape.
    pub fn new(width: u32, height: u32, channels: u8, data: Vec<u8>) -> Result<Self, String> {
        let expected = width as usize * height as usize * channels as usize;
        if channels != 1 && channels != 3 {
            return Err(format!("images have 1 or 3 channels, not {channels}"));
        }
        if data.len() != expected {
            return Err(format!(
                "{width}x{height}x{channels} image needs {expected} bytes, got {}",
                data.len()
            ));
        }
        Ok(Image {
            width,
            height,
            channels,
            data,
        })
    }

    /// Pixel count.
    pub fn len(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// True when the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Writes the luma (BT.601, rounded) of this image into `out` (resized to the pixel count).
    pub fn gray_into(&self, out: &mut Vec<u8>) {
        out.clear();
        if self.channels == 1 {
            out.extend_from_slice(&self.data);
            return;
        }
        // Sized first, so the loop is plain stores (it vectorises; `push` would not).
        out.resize(self.len(), 0);
        for (o, px) in out.iter_mut().zip(self.data.chunks_exact(3)) {
            *o = luma_bt601(px[0], px[1], px[2]);
        }
    }
}

/// BT.601 luma of an sRGB pixel in 8-bit fixed point: `(77 R + 150 G + 29 B + 128) >> 8`.
/// The GPU kernel `shaders/image/gray.wgsl` computes exactly this.
#[inline]
pub fn luma_bt601(r: u8, g: u8, b: u8) -> u8 {
    ((77 * r as u32 + 150 * g as u32 + 29 * b as u32 + 128) >> 8) as u8
}

/// Per-pixel validity (1 valid, 0 invalid), e.g. the rectification border of an endoscope image.
#[derive(Clone, Debug, PartialEq)]
pub struct Mask {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// One byte per pixel.
    pub data: Vec<u8>,
}

impl Mask {
    /// Fraction of valid pixels.
    pub fn valid_fraction(&self) -> f64 {
        if self.data.is_empty() {
            return 0.0;
        }
        self.data.iter().filter(|&&v| v != 0).count() as f64 / self.data.len() as f64
    }
}

/// A rectified stereo pair with its calibration.
#[derive(Clone, Debug)]
pub struct StereoFrame {
    /// Index of the frame in its sequence (not the file number).
    pub index: u64,
    /// Capture time, seconds from the start of the sequence.
    pub timestamp: f64,
    /// Left image (shared with any `left` output port, never copied).
    pub left: Arc<Image>,
    /// Right image.
    pub right: Arc<Image>,
    /// Calibration.
    pub calib: StereoCalib,
    /// Valid region of the left image (black rectification border masked out), if known.
    pub left_mask: Option<Mask>,
    /// Valid region of the right image, if known.
    pub right_mask: Option<Mask>,
}

/// A dense `f32` map, NaN where invalid.
#[derive(Clone, Debug, PartialEq)]
pub struct FloatMap {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Row-major values.
    pub data: Vec<f32>,
}

impl FloatMap {
    /// A map filled with NaN.
    pub fn invalid(width: u32, height: u32) -> Self {
        FloatMap {
            width,
            height,
            data: vec![f32::NAN; width as usize * height as usize],
        }
    }

    /// Number of finite values.
    pub fn valid_count(&self) -> usize {
        self.data.iter().filter(|v| v.is_finite()).count()
    }

    /// Value at (x, y).
    #[inline]
    pub fn at(&self, x: u32, y: u32) -> f32 {
        self.data[y as usize * self.width as usize + x as usize]
    }
}

/// Disparity of the left image in pixels.
#[derive(Clone, Debug)]
pub struct DisparityMap {
    /// Values, NaN where invalid.
    pub map: FloatMap,
    /// Calibration of the pair it came from.
    pub calib: StereoCalib,
}

/// Watches a stereo node's disparity maps for a search range the scene has outgrown. A pixel
/// whose true disparity lies beyond the largest one searched matches best at that largest one,
/// so such a scene leaves a crowd of valid pixels at the top of the range, each with a wrong
/// depth (the phantom at 640x480, f = 700 px, with 48 of its 55 disparities searched: 29 to
/// 31 % of the valid pixels, against none with 64 or 96). A frame with more than
/// [`Self::MAX_SHARE`] of its valid pixels there is warned about (once per run of such frames)
/// and counted.
#[derive(Clone, Debug, Default)]
pub struct DisparityRangeWatch {
    /// Frames whose map had more than [`Self::MAX_SHARE`] of its valid pixels at the top.
    pub frames: u64,
    warned: bool,
}

/// What [`DisparityRangeWatch::check`] counted in one map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RangeCheck {
    /// The share (0 to 1) of the valid pixels at the top of the range; 0 when none is valid.
    pub share: f64,
    /// The valid (finite) pixels of the map, for the node's density figure.
    pub valid: usize,
}

impl DisparityRangeWatch {
    /// The share of valid pixels at the top of the range above which a frame is flagged.
    pub const MAX_SHARE: f64 = 0.05;

    /// Counts `map`'s valid pixels and the share of them within half a pixel of `top`, the
    /// largest disparity searched, or above it; flags the frame above [`Self::MAX_SHARE`],
    /// telling the user to raise the parameter `param` of node `node`.
    pub fn check(
        &mut self,
        frame: u64,
        map: &FloatMap,
        top: f32,
        node: &str,
        param: &str,
    ) -> RangeCheck {
        let (mut valid, mut high) = (0usize, 0usize);
        for &d in &map.data {
            valid += d.is_finite() as usize;
            high += (d >= top - 0.5 && d.is_finite()) as usize;
        }
        let share = if valid == 0 {
            0.0
        } else {
            high as f64 / valid as f64
        };
        let flagged = share > Self::MAX_SHARE;
        if flagged {
            self.frames += 1;
            if !self.warned {
                tracing::warn!(
                    "frame {frame}: {:.0} % of the matched pixels lie at the largest disparity \
                     searched ({top} px): the scene comes nearer than the range reaches and their \
                     depths are wrong; raise `{node}.{param}`. Counted in \
                     depth.range_saturated_frames",
                    100.0 * share
                );
            }
        }
        self.warned = flagged;
        RangeCheck { share, valid }
    }
}

impl DisparityMap {
    /// The depth of every pixel (`StereoCalib::depth_from_disparity`; NaN where invalid).
    pub fn to_depth(&self) -> DepthMap {
        DepthMap {
            map: FloatMap {
                width: self.map.width,
                height: self.map.height,
                data: self
                    .map
                    .data
                    .iter()
                    .map(|&d| self.calib.depth_from_disparity(d))
                    .collect(),
            },
            calib: self.calib,
        }
    }
}

/// Depth (z along the optical axis) of the left camera in mm.
#[derive(Clone, Debug)]
pub struct DepthMap {
    /// Values, NaN where invalid.
    pub map: FloatMap,
    /// Calibration of the camera.
    pub calib: StereoCalib,
}

/// The depth lifted to 3D points in the camera frame, `Gamma(u,v) = Z K^-1 [u v 1]^T`.
#[derive(Clone, Debug)]
pub struct VertexMap {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Row-major points in mm, NaN where invalid.
    pub points: Vec<[f32; 3]>,
}

/// Unit normals per pixel in the camera frame, NaN where invalid.
#[derive(Clone, Debug)]
pub struct NormalMap {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// Row-major unit vectors.
    pub normals: Vec<[f32; 3]>,
}

/// A detected feature.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Keypoint {
    /// Position x, pixels (level 0).
    pub x: f32,
    /// Position y, pixels (level 0).
    pub y: f32,
    /// Diameter of the meaningful neighbourhood, pixels.
    pub size: f32,
    /// Orientation, radians; NaN when not computed (upright).
    pub angle: f32,
    /// Detector response.
    pub response: f32,
    /// Pyramid level or octave.
    pub octave: i32,
}

/// Descriptors of a keypoint set.
#[derive(Clone, Debug, PartialEq)]
pub enum Descriptors {
    /// 256-bit binary descriptors (ORB).
    Binary256(Vec<[u64; 4]>),
    /// 64-float descriptors (SURF).
    Float64(Vec<[f32; 64]>),
}

impl Descriptors {
    /// Number of descriptors.
    pub fn len(&self) -> usize {
        match self {
            Descriptors::Binary256(d) => d.len(),
            Descriptors::Float64(d) => d.len(),
        }
    }

    /// True when there are none.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Keypoints with descriptors, optionally lifted to 3D by stereo matching.
#[derive(Clone, Debug, PartialEq)]
pub struct Features {
    /// Keypoints of the left image.
    pub keypoints: Vec<Keypoint>,
    /// One descriptor per keypoint.
    pub descriptors: Descriptors,
    /// 3D position in the camera frame (mm) per keypoint, NaN without a stereo match.
    pub points: Option<Vec<[f32; 3]>>,
    /// Descriptors of the same kind at any pixel of the left image, where the detector can give
    /// them (upright dense SURF): a match to a grid keypoint can then be moved to the pixel whose
    /// descriptor fits best, so that it follows the tissue instead of the grid.
    pub sampler: Option<Sampler>,
}

/// Float descriptors at any pixel of the image that a [`Features`] came from.
pub trait DescriptorSampler: Send + Sync {
    /// Width and height of the image, pixels.
    fn size(&self) -> (u32, u32);
    /// The descriptor centred on pixel (x, y); None where its window leaves the image.
    fn float64_at(&self, x: i32, y: i32) -> Option<[f32; 64]>;
}

/// A shared [`DescriptorSampler`]; two are equal when they are the same sampler.
#[derive(Clone)]
pub struct Sampler(pub Arc<dyn DescriptorSampler>);

impl PartialEq for Sampler {
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl fmt::Debug for Sampler {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (w, h) = self.0.size();
        write!(f, "Sampler({w}x{h})")
    }
}

/// One correspondence between two keypoint sets.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Match {
    /// Index into the query set.
    pub query: u32,
    /// Index into the train set.
    pub train: u32,
    /// Descriptor distance.
    pub distance: f32,
}

/// Matches with the 2D positions of both ends, so they can be drawn on their own.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Matches {
    /// The pairs.
    pub pairs: Vec<Match>,
    /// Query keypoint position per pair, pixels.
    pub query_xy: Vec<[f32; 2]>,
    /// Train keypoint position per pair, pixels.
    pub train_xy: Vec<[f32; 2]>,
    /// 3D position of the query end per pair (empty when the matches are 2D only), mm; its frame
    /// is documented by the node that produces the matches.
    pub query_points: Vec<[f32; 3]>,
    /// 3D position of the train end per pair (empty when 2D only), mm.
    pub train_points: Vec<[f32; 3]>,
}

/// State of a tracker on one frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackingState {
    /// Tracking normally.
    Tracking,
    /// Lost: the pose is the last good one and must not be trusted.
    Lost,
    /// Recovered against a stored keyframe on this frame.
    Relocalised,
}

/// A rigid camera pose.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// `world_from_camera`, translation in mm.
    pub world_from_camera: Isometry3<f64>,
    /// Tracker state that produced this pose.
    pub state: TrackingState,
}

/// An embedded deformation graph (Sumner et al. 2007).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DeformationGraph {
    /// Node positions g_j, mm.
    pub nodes: Vec<[f32; 3]>,
    /// Affine parts A_j, row-major 3x3.
    pub affines: Vec<[f32; 9]>,
    /// Translations t_j, mm.
    pub translations: Vec<[f32; 3]>,
    /// Node-to-node edges.
    pub edges: Vec<[u32; 2]>,
}

/// A surfel model (template-free fusion).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SurfelModel {
    /// Positions v_i, mm.
    pub positions: Vec<[f32; 3]>,
    /// Unit normals n_i.
    pub normals: Vec<[f32; 3]>,
    /// Colours C_i.
    pub colors: Vec<[u8; 3]>,
    /// Confidence weights omega(v_i).
    pub weights: Vec<f32>,
    /// Frame index of the last observation t_i.
    pub timestamps: Vec<u64>,
    /// Stability s_i.
    pub stability: Vec<f32>,
    /// Identity of each surfel, unique within a run and kept while it lives (evaluations follow
    /// surfels over frames by it); empty when the producer gives none.
    pub ids: Vec<u64>,
}

/// A triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions, mm.
    pub vertices: Vec<[f32; 3]>,
    /// Per-vertex unit normals, if known.
    pub normals: Option<Vec<[f32; 3]>>,
    /// Per-vertex colours, if known.
    pub colors: Option<Vec<[u8; 3]>>,
    /// Triangles as vertex indices, counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

/// A coloured point set.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    /// Positions, mm.
    pub positions: Vec<[f32; 3]>,
    /// Colours, if known.
    pub colors: Option<Vec<[u8; 3]>>,
}

/// Named figures measured on one frame (evaluation nodes), e.g. `depth.mae_mm`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Metrics {
    /// Key to value.
    pub values: BTreeMap<String, f64>,
}

/// The type of a port. Two ports connect only when their types are equal.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum PortType {
    /// [`StereoFrame`]
    Stereo,
    /// [`Image`]
    Image,
    /// [`DisparityMap`]
    Disparity,
    /// [`DepthMap`]
    Depth,
    /// [`VertexMap`]
    VertexMap,
    /// [`NormalMap`]
    NormalMap,
    /// [`Features`]
    Features,
    /// [`Matches`]
    Matches,
    /// [`Pose`]
    Pose,
    /// [`DeformationGraph`]
    DeformationGraph,
    /// [`SurfelModel`]
    Model,
    /// [`Mesh`]
    Mesh,
    /// [`PointCloud`]
    PointCloud,
    /// [`Metrics`]
    Metrics,
}

/// A payload of any type, cheap to clone (one `Arc`).
#[derive(Clone, Debug)]
pub enum Payload {
    /// A stereo pair.
    Stereo(Arc<StereoFrame>),
    /// An image.
    Image(Arc<Image>),
    /// A disparity map.
    Disparity(Arc<DisparityMap>),
    /// A depth map.
    Depth(Arc<DepthMap>),
    /// A vertex map.
    VertexMap(Arc<VertexMap>),
    /// A normal map.
    NormalMap(Arc<NormalMap>),
    /// Keypoints and descriptors.
    Features(Arc<Features>),
    /// Matches.
    Matches(Arc<Matches>),
    /// A pose.
    Pose(Arc<Pose>),
    /// A deformation graph.
    DeformationGraph(Arc<DeformationGraph>),
    /// A surfel model.
    Model(Arc<SurfelModel>),
    /// A mesh.
    Mesh(Arc<Mesh>),
    /// A point cloud.
    PointCloud(Arc<PointCloud>),
    /// Figures of one frame.
    Metrics(Arc<Metrics>),
}

/// A Rust type that is one of the payload variants.
pub trait PayloadType: Sized + Send + Sync + 'static {
    /// Its port type.
    const PORT_TYPE: PortType;
    /// Wraps it.
    fn into_payload(value: Arc<Self>) -> Payload;
    /// Borrows it out of a payload of the same type.
    fn from_payload(payload: &Payload) -> Option<&Arc<Self>>;
}

macro_rules! payload_types {
    ($($variant:ident => $ty:ty, $name:literal;)*) => {
        $(
            impl PayloadType for $ty {
                const PORT_TYPE: PortType = PortType::$variant;
                fn into_payload(value: Arc<Self>) -> Payload {
                    Payload::$variant(value)
                }
                fn from_payload(payload: &Payload) -> Option<&Arc<Self>> {
                    match payload {
                        Payload::$variant(v) => Some(v),
                        _ => None,
                    }
                }
            }
        )*

        impl Payload {
            /// The port type of this payload.
            pub fn port_type(&self) -> PortType {
                match self {
                    $(Payload::$variant(_) => PortType::$variant,)*
                }
            }
        }

        impl PortType {
            /// Every port type.
            pub const ALL: &'static [PortType] = &[$(PortType::$variant,)*];

            /// The name used in docs and plugin descriptors.
            pub fn name(self) -> &'static str {
                match self {
                    $(PortType::$variant => $name,)*
                }
            }
        }
    };
}

payload_types! {
    Stereo => StereoFrame, "stereo";
    Image => Image, "image";
    Disparity => DisparityMap, "disparity";
    Depth => DepthMap, "depth";
    VertexMap => VertexMap, "vertex_map";
    NormalMap => NormalMap, "normal_map";
    Features => Features, "features";
    Matches => Matches, "matches";
    Pose => Pose, "pose";
    DeformationGraph => DeformationGraph, "deformation_graph";
    Model => SurfelModel, "model";
    Mesh => Mesh, "mesh";
    PointCloud => PointCloud, "point_cloud";
    Metrics => Metrics, "metrics";
}

impl fmt::Display for PortType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_crowd_at_the_top_of_the_disparity_range_flags_the_frame() {
        let map = |data: Vec<f32>| FloatMap {
            width: data.len() as u32,
            height: 1,
            data,
        };
        let mut w = DisparityRangeWatch::default();
        // 2 of 10 valid pixels within half a pixel of 47 (NaN not counted): flagged.
        let mut d = vec![10.0f32; 8];
        d.extend([46.5, 47.0, f32::NAN, f32::NAN]);
        let c = w.check(0, &map(d), 47.0, "depth", "max_disparity");
        assert_eq!((c.share, c.valid), (0.2, 10));
        assert_eq!(w.frames, 1);
        // 46.4 is below the top's half pixel; 1 of 25 (4 %) stays under the 5 % bar.
        let mut d = vec![10.0f32; 24];
        d.push(46.4);
        let c = w.check(1, &map(d.clone()), 47.0, "depth", "max_disparity");
        assert_eq!((c.share, c.valid), (0.0, 25));
        d[0] = 47.0;
        let c = w.check(2, &map(d), 47.0, "depth", "max_disparity");
        assert_eq!(c.share, 0.04);
        assert_eq!(w.frames, 1);
        // No valid pixel: nothing to flag.
        let c = w.check(3, &map(vec![f32::NAN; 4]), 47.0, "depth", "max_disparity");
        assert_eq!((c.share, c.valid), (0.0, 0));
        assert_eq!(w.frames, 1);
    }

    fn calib() -> StereoCalib {
        StereoCalib {
            width: 640,
            height: 480,
            fx: 700.0,
            fy: 700.0,
            cx: 320.0,
            cy: 240.0,
            cx_right: 330.0,
            baseline_mm: 5.0,
        }
    }

    #[test]
    fn depth_and_disparity_are_inverse() {
        let c = calib();
        // Z = fx b / (d + doffs) = 700 * 5 / (25 + 10) = 100 mm.
        assert_eq!(c.depth_from_disparity(25.0), 100.0);
        assert!((c.disparity_from_depth(100.0) - 25.0).abs() < 1e-5);
        assert!(c.depth_from_disparity(-10.0).is_nan());
        assert!(c.depth_from_disparity(f32::NAN).is_nan());
    }

    #[test]
    fn calibration_errors_name_the_field() {
        let mut c = calib();
        c.baseline_mm = -1.0;
        assert!(c.validate().unwrap_err().contains("baseline_mm"));
        let mut c = calib();
        c.fy = f64::NAN;
        assert!(c.validate().unwrap_err().contains("`fy`"));
    }

    #[test]
    fn payload_clone_shares_the_data() {
        let img = Arc::new(Image::new(2, 1, 1, vec![1, 2]).unwrap());
        let p = Image::into_payload(img.clone());
        let q = p.clone();
        let a = Image::from_payload(&p).unwrap();
        let b = Image::from_payload(&q).unwrap();
        assert!(Arc::ptr_eq(a, b) && Arc::ptr_eq(a, &img));
        assert_eq!(q.port_type(), PortType::Image);
        assert!(DepthMap::from_payload(&q).is_none());
    }

    #[test]
    fn gray_uses_bt601() {
        let img = Image::new(2, 1, 3, vec![255, 0, 0, 10, 200, 30]).unwrap();
        let mut g = Vec::new();
        img.gray_into(&mut g);
        assert_eq!(g, vec![77, luma_bt601(10, 200, 30)]);
        assert_eq!(luma_bt601(255, 255, 255), 255);
        assert!(Image::new(2, 2, 3, vec![0; 5]).is_err());
    }
}
