//! Sparse correspondences for E_corr from the keypoints of consecutive frames (MIS-SLAM hands the
//! feature matches of its tracker to the ED solve as sparse constraints).
//!
//! At the end of a frame every keypoint with a 3D point is *anchored* to the model: its world
//! position (the frame's final pose), moved onto the tangent plane of the closest live surfel
//! within `anchor_distance_mm`, is expressed in the canonical frame (the surfel's canonical
//! position plus the offset mapped back through the warp, see [`anchor`]), with that surfel's
//! binding. On the next frame
//! each anchor is projected into the image through the prior pose and matched by descriptor to
//! the keypoints within `radius_px` of it (guided matching, ratio test, each keypoint keeping its
//! nearest anchor); each match asks the warp to carry the anchor onto the keypoint's new 3D point
//! (camera frame). A match whose 3D point lies farther than `max_jump_mm` from the anchor's live
//! position (under the prior pose) is dropped as wrong.
//!
//! A keypoint's 3D point is read from the depth's vertex map at its pixel (`points = "depth"`,
//! [`DepthPoints`]), the surface the data term fits, or is its own stereo point (`"stereo"`).
//! Both ends of a correspondence take it from the same source: with SURF stereo points as
//! anchors and depth points as targets the two depths disagreed, and the constraints twisted
//! the node affines.
//!
//! Dense descriptors (upright dense SURF) sit on a grid: the keypoint a match lands on is up to
//! half a grid step from where the tissue went. When the features carry a descriptor sampler
//! (and points come from the depth), each match is moved to the pixel whose descriptor fits the
//! anchor's best and then to the sub-pixel minimum ([`misslam_features_matching::dense`]), and
//! its 3D point is read there. On the phantom heart (6 px grid, 320x240) refinement takes the
//! mean distance between an anchor's tissue point and its match's from 0.42 to 0.08 mm.

use misslam_deformation_ed::graph::{Binding, EdGraph};
use misslam_deformation_ed::knn::GridIndex;
use misslam_deformation_ed::problem::Correspondence;
use misslam_deformation_ed::problem::Intrinsics;
use misslam_features_matching::dense::{refine_match, RefineScratch};
use misslam_features_matching::guided::{match_guided, GuidedParams, KeypointGrid};
use misslam_framework::nalgebra::{Isometry3, Matrix3, Point3, Vector3};
use misslam_framework::{Descriptors, Features};
use rayon::prelude::*;

/// Parameters of the sparse correspondences (with the `features` input connected).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct CorrParams {
    /// Use the keypoints as E_corr constraints (weight `solver.weights.corr`).
    pub enabled: bool,
    /// A keypoint anchors to the closest live surfel within this distance, mm.
    pub anchor_distance_mm: f64,
    /// A match is dropped when its 3D point lies farther than this from the anchor's live
    /// position (through the prior pose), mm.
    pub max_jump_mm: f64,
    /// Search radius around an anchor's projection, pixels.
    pub radius_px: f32,
    /// Lowe's ratio between the best and second-best descriptor distance within the radius.
    pub ratio: f32,
    /// Largest Hamming distance of binary descriptors (ORB), bits.
    pub max_distance: f32,
    /// Largest L2 distance of float descriptors (SURF).
    pub max_distance_l2: f32,
    /// Where a keypoint's 3D point (anchor and match alike) comes from: `depth` or `stereo`.
    pub points: PointSource,
    /// With dense descriptors (features that carry a sampler) and `points = "depth"`: how many
    /// pixels a match may move from its grid keypoint to the pixel that fits best; 0 keeps the
    /// grid keypoint.
    pub refine_steps: u32,
    /// With `points = "depth"`: a keypoint's 3D point is read from the four depth pixels around
    /// it, and it is dropped when their depths differ by more than this (an edge), mm.
    pub depth_max_step_mm: f64,
    /// Anchors persist as model keypoints: one matched again keeps the canonical point it was
    /// anchored at (not re-anchored each frame, so frame-to-frame errors do not add up), and is
    /// kept until it has gone unmatched for this many frames. A new anchor that is not matched
    /// on the next frame is dropped. 0: every frame's keypoints are anchored afresh and only
    /// the last frame's are matched. `mis_slam`, 1,000 frames: material drift 0.77 mm (300),
    /// 0.92 (30), 2.80 (0), 3.85 without correspondences.
    pub keep_frames: u32,
    /// Most anchors kept; beyond it those unseen longest, then matched least often, go.
    pub max_anchors: usize,
}

/// Where the 3D point of a keypoint comes from (`correspondences.points`).
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum PointSource {
    /// The depth map the data term fits (its vertex map, bilinear at the keypoint): both ends of
    /// a correspondence and the data term see one surface. Phantom heart, template fusion,
    /// 40 frames: whole-template error 0.43 mm against 0.55 with `stereo`.
    #[default]
    Depth,
    /// The keypoint's own stereo match (`Features::points`), independent of the depth map.
    Stereo,
}

impl Default for CorrParams {
    fn default() -> Self {
        CorrParams {
            enabled: true,
            anchor_distance_mm: 2.0,
            max_jump_mm: 10.0,
            radius_px: 15.0,
            ratio: 0.8,
            max_distance: 64.0,
            max_distance_l2: 0.4,
            points: PointSource::Depth,
            refine_steps: 6,
            depth_max_step_mm: 2.0,
            keep_frames: 300,
            max_anchors: 5000,
        }
    }
}

impl CorrParams {
    /// Checks the ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        for (name, v) in [
            ("anchor_distance_mm", self.anchor_distance_mm),
            ("max_jump_mm", self.max_jump_mm),
            ("radius_px", self.radius_px as f64),
            ("max_distance", self.max_distance as f64),
            ("max_distance_l2", self.max_distance_l2 as f64),
            ("depth_max_step_mm", self.depth_max_step_mm),
        ] {
            if v.is_nan() || v <= 0.0 {
                return Err(format!("`{name}` must be positive, got {v}"));
            }
        }
        if !(self.ratio > 0.0 && self.ratio <= 1.0) {
            return Err(format!("`ratio` must lie in (0, 1], got {}", self.ratio));
        }
        if self.max_anchors == 0 {
            return Err("`max_anchors` must be at least 1 (0 keeps no keypoint: set `enabled = false` to go without)".into());
        }
        Ok(())
    }
}

/// Keypoints anchored to the model: the last frame's, or the persistent model keypoints
/// (`keep_frames`).
#[derive(Default)]
pub struct Anchors {
    descriptors: Option<Descriptors>,
    canon: Vec<Vector3<f64>>,
    bindings: Vec<Binding>,
    live: Vec<Vector3<f64>>,
    /// Per anchor: the keypoint of its frame it came from ([`anchor`]).
    keypoint: Vec<u32>,
    /// Per anchor: the last frame it was anchored or matched in, and how often it was matched.
    last_seen: Vec<u64>,
    matched: Vec<u32>,
}

/// `d[i]` for each i of `keep`.
fn select(d: &Descriptors, keep: impl Iterator<Item = usize> + Clone) -> Descriptors {
    match d {
        Descriptors::Binary256(d) => Descriptors::Binary256(keep.map(|i| d[i]).collect()),
        Descriptors::Float64(d) => Descriptors::Float64(keep.map(|i| d[i]).collect()),
    }
}

impl Anchors {
    /// The anchors at `keep` (in that order).
    fn select(&self, keep: &[usize]) -> Anchors {
        Anchors {
            descriptors: self
                .descriptors
                .as_ref()
                .map(|d| select(d, keep.iter().copied())),
            canon: keep.iter().map(|&i| self.canon[i]).collect(),
            bindings: keep.iter().map(|&i| self.bindings[i]).collect(),
            live: keep.iter().map(|&i| self.live[i]).collect(),
            keypoint: keep.iter().map(|&i| self.keypoint[i]).collect(),
            last_seen: keep.iter().map(|&i| self.last_seen[i]).collect(),
            matched: keep.iter().map(|&i| self.matched[i]).collect(),
        }
    }

    /// Appends `other`'s anchors at `keep`; false (nothing appended) when the descriptor kinds
    /// differ.
    fn append(&mut self, other: &Anchors, keep: &[usize]) -> bool {
        if keep.is_empty() {
            return true;
        }
        let add = other.select(keep);
        match (&mut self.descriptors, add.descriptors) {
            (Some(Descriptors::Binary256(a)), Some(Descriptors::Binary256(b))) => a.extend(b),
            (Some(Descriptors::Float64(a)), Some(Descriptors::Float64(b))) => a.extend(b),
            (None, b) if self.canon.is_empty() => self.descriptors = b,
            _ => return false,
        }
        self.canon.extend(add.canon);
        self.bindings.extend(add.bindings);
        self.live.extend(add.live);
        self.keypoint.extend(add.keypoint);
        self.last_seen.extend(add.last_seen);
        self.matched.extend(add.matched);
        true
    }
}

impl Anchors {
    /// Number of anchored keypoints.
    pub fn len(&self) -> usize {
        self.canon.len()
    }

    /// True when none is anchored.
    pub fn is_empty(&self) -> bool {
        self.canon.is_empty()
    }
}

/// Reusable buffers of [`anchor`]: the live surfels near the keypoints bucketed in a grid, and
/// the keypoints' world points.
#[derive(Default)]
pub struct AnchorScratch {
    grid: GridIndex,
    world: Vec<Vector3<f64>>,
}

/// What a fusion node keeps between frames for E_corr: the last frame's anchors and the buffers.
#[derive(Default)]
pub struct CorrTracker {
    anchors: Anchors,
    /// This frame's matches: (anchor, keypoint), and the frame.
    matches: Vec<(u32, u32)>,
    matches_frame: Option<u64>,
    anchor_scratch: AnchorScratch,
    refine: RefineScratch,
}

impl CorrTracker {
    /// This frame's correspondences against the anchors (see [`correspondences`]: `scan` is
    /// the depth's vertex and normal maps), each anchor's live position taken through `graph`
    /// as it stands; the error names `frame`.
    #[allow(clippy::too_many_arguments)]
    pub fn correspondences(
        &mut self,
        frame: u64,
        features: Option<&Features>,
        prior: &Isometry3<f64>,
        k: &Intrinsics,
        scan: (&[[f32; 3]], &[[f32; 3]]),
        graph: &EdGraph,
        p: &CorrParams,
    ) -> Result<Vec<Correspondence>, String> {
        self.matches.clear();
        self.matches_frame = Some(frame);
        let Some(f) = features else {
            return Ok(Vec::new());
        };
        let a = &mut self.anchors;
        for (live, (c, b)) in a.live.iter_mut().zip(a.canon.iter().zip(&a.bindings)) {
            *live = graph.warp_point(c, b);
        }
        let found = matched_correspondences(f, &self.anchors, prior, k, scan, p, &mut self.refine)
            .map_err(|e| format!("frame {frame}: {e}"))?;
        self.matches.extend(found.iter().map(|&(_, a, q)| (a, q)));
        Ok(found.into_iter().map(|(c, _, _)| c).collect())
    }

    /// Number of anchors held.
    pub fn anchors(&self) -> usize {
        self.anchors.len()
    }

    /// Anchors this frame's keypoints to the deformed model (`live`, world frame, of the
    /// canonical points `canon` bound by `bindings` to `graph`, unit normals `live_normals`) for
    /// the next frames. With `points = "depth"` keypoints take their points from `vertices` (see
    /// [`DepthPoints`]). With `keep_frames = 0` they replace the anchors; otherwise anchors
    /// matched on this frame keep their canonical points, the keypoints no anchor matched are
    /// added, and anchors past their time are dropped (see [`CorrParams::keep_frames`]). A lost
    /// frame, whose pose is not the scope's, anchors nothing (without `keep_frames` the anchors
    /// are dropped; with it they are kept for later frames).
    #[allow(clippy::too_many_arguments)]
    pub fn anchor(
        &mut self,
        frame: u64,
        features: Option<&Features>,
        lost: bool,
        pose: &Isometry3<f64>,
        live: &[Vector3<f64>],
        live_normals: &[Vector3<f64>],
        canon: &[Vector3<f64>],
        bindings: &[Binding],
        graph: &EdGraph,
        vertices: &[[f32; 3]],
        k: &Intrinsics,
        p: &CorrParams,
    ) {
        let matches = if self.matches_frame == Some(frame) {
            std::mem::take(&mut self.matches)
        } else {
            Vec::new()
        };
        let fresh = match features {
            Some(f) if !lost => {
                let nm = graph.normal_matrices();
                let mut a = anchor(
                    f,
                    pose,
                    live,
                    live_normals,
                    canon,
                    bindings,
                    |s| local_inverses(&bindings[s], &nm).0,
                    |v, b| graph.warp_point(v, b),
                    p.anchor_distance_mm,
                    (p.points == PointSource::Depth).then_some(DepthPoints {
                        vertices,
                        intrinsics: *k,
                        max_step_mm: p.depth_max_step_mm,
                    }),
                    &mut self.anchor_scratch,
                );
                a.last_seen = vec![frame; a.len()];
                a.matched = vec![0; a.len()];
                a
            }
            _ => Anchors::default(),
        };
        if p.keep_frames == 0 {
            self.anchors = fresh;
            return;
        }
        if lost {
            return;
        }
        // The anchors matched on this frame were seen again.
        let old = &mut self.anchors;
        let mut taken = vec![false; features.map_or(0, |f| f.keypoints.len())];
        for &(a, q) in &matches {
            let a = a as usize;
            old.last_seen[a] = frame;
            old.matched[a] += 1;
            if let Some(t) = taken.get_mut(q as usize) {
                *t = true;
            }
        }
        // Those past their time go: new ones not matched on the frame after their own (every
        // anchor here is from an earlier frame), the others unmatched for more than
        // `keep_frames` frames.
        let keep: Vec<usize> = (0..old.len())
            .filter(|&i| {
                old.matched[i] > 0 && frame.saturating_sub(old.last_seen[i]) <= p.keep_frames as u64
            })
            .collect();
        let mut map = if keep.len() == old.len() {
            std::mem::take(old)
        } else {
            old.select(&keep)
        };
        // This frame's keypoints that no anchor matched become anchors.
        let new: Vec<usize> = (0..fresh.len())
            .filter(|&i| {
                !taken
                    .get(fresh.keypoint[i] as usize)
                    .copied()
                    .unwrap_or(false)
            })
            .collect();
        if !map.append(&fresh, &new) {
            // The features changed descriptor kind: start over with this frame's.
            map = fresh;
        }
        // Over the cap, those unseen longest and then matched least often go: the tissue in
        // view keeps its anchors, and new tissue can still get some.
        if map.len() > p.max_anchors {
            // The first `max_anchors` in that order (ties to the older anchor), found by a
            // selection rather than a sort of all of them, then kept in their order.
            let mut order: Vec<usize> = (0..map.len()).collect();
            order.select_nth_unstable_by_key(p.max_anchors, |&i| {
                (
                    std::cmp::Reverse(map.last_seen[i]),
                    std::cmp::Reverse(map.matched[i]),
                    i,
                )
            });
            order.truncate(p.max_anchors);
            order.sort_unstable();
            map = map.select(&order);
        }
        self.anchors = map;
    }
}

/// The warp's local linear part at a binding, as the pair (A^-1, A^T) derived from the blended
/// normal matrices A^-T: A^-1 maps a live displacement back to the canonical frame, A^T maps a
/// live normal back.
pub fn local_inverses(b: &Binding, nm: &[Matrix3<f64>]) -> (Matrix3<f64>, Matrix3<f64>) {
    if b.len == 0 {
        return (Matrix3::identity(), Matrix3::identity());
    }
    let mut m = Matrix3::zeros();
    for (j, w) in b.iter() {
        m += w * nm[j as usize];
    }
    (
        m.transpose(),
        m.try_inverse().unwrap_or_else(Matrix3::identity),
    )
}

/// The depth's vertex map (camera frame, `intrinsics.width` x `intrinsics.height`), from which
/// keypoints take their 3D points (`points = "depth"`), and the largest depth step between the
/// four pixels around a point, mm.
pub struct DepthPoints<'a> {
    /// Row-major points, NaN where invalid.
    pub vertices: &'a [[f32; 3]],
    /// The map's camera.
    pub intrinsics: Intrinsics,
    /// Largest depth difference between the four pixels a point is read from, mm.
    pub max_step_mm: f64,
}

/// Fixed-point corrections of an anchor's canonical point at most ([`anchor`]).
const ANCHOR_STEPS: usize = 4;

/// How close the warp must carry an anchor's canonical point to its keypoint, mm
/// ([`anchor`]).
pub const ANCHOR_TOLERANCE_MM: f64 = 0.01;

/// Anchors `features` (camera frame, seen at `pose`) to the live model: `live`/`canon`/
/// `bindings` per surfel, `local_inverse(s)` the warp's A^-1 at surfel `s`, `warp(v, b)` the
/// live position of canonical point `v` bound by `b`. Only the surfels in the keypoints'
/// bounding box (grown by `radius`) are binned, in cells at least `radius` wide, so the closest
/// within `radius` lies in the 27 cells around the keypoint's.
///
/// The anchor is the keypoint's point moved along the surfel's live normal (`live_normals`,
/// unit; empty: keypoints anchor at their own points) onto the surfel's tangent plane: the tissue point under the keypoint. A keypoint's
/// stereo point lies off the surface by its depth noise, a fresh draw every frame; anchored
/// off the surface, E_corr asked each node to map those offsets onto the next frame's, and the
/// least-squares answer to independent noise is to flatten them: node affines lost their
/// extent along the normal (a diagonal entry of A from 1 to 0.07 in one solve on the phantom
/// liver), which no other term resists to first order.
///
/// The canonical point starts at the surfel's plus the offset mapped back by A^-1, and is
/// corrected (fixed-point steps through A^-1) until the warp carries it onto the keypoint
/// within [`ANCHOR_TOLERANCE_MM`]; an anchor that does not get there is dropped. The first
/// step alone is exact only where the nodes of the binding share one affine: where they
/// differ, the warped anchor missed its keypoint, and the next frame's correspondence asked
/// the solve to close that gap too (on the phantom liver, gaps of 10 to 10,000 mm once the
/// affines had begun to twist, which twisted them further: the template slid 4.7 mm).
#[allow(clippy::too_many_arguments)]
pub fn anchor(
    features: &Features,
    pose: &Isometry3<f64>,
    live: &[Vector3<f64>],
    live_normals: &[Vector3<f64>],
    canon: &[Vector3<f64>],
    bindings: &[Binding],
    local_inverse: impl Fn(usize) -> Matrix3<f64> + Sync,
    warp: impl Fn(&Vector3<f64>, &Binding) -> Vector3<f64> + Sync,
    radius: f64,
    depth: Option<DepthPoints>,
    scratch: &mut AnchorScratch,
) -> Anchors {
    let mut out = Anchors::default();
    let Some(points) = &features.points else {
        return out;
    };
    let AnchorScratch { grid, world } = scratch;
    world.clear();
    world.extend(points.iter().zip(&features.keypoints).map(|(q, kp)| {
        let c = match &depth {
            Some(d) => vertex_at(d.vertices, &d.intrinsics, [kp.x, kp.y], d.max_step_mm)
                .unwrap_or(Vector3::repeat(f64::NAN)),
            None => Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64),
        };
        (pose * Point3::from(c)).coords
    }));
    let (mut lo, mut hi) = (
        Vector3::repeat(f64::INFINITY),
        Vector3::repeat(f64::NEG_INFINITY),
    );
    for p in world.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    // The surfels near the keypoints, bucketed in place by a counting sort (a parallel sort of
    // (cell, surfel) pairs took about half a millisecond a frame with 12,500 surfels).
    let any = lo.iter().all(|c| c.is_finite());
    if any {
        grid.rebuild(
            live,
            Some((lo.add_scalar(-radius), hi.add_scalar(radius))),
            radius,
        );
    }
    let grid = &*grid;
    // Each keypoint's anchor, in parallel; kept in keypoint order.
    // (canonical point, tissue point, surfel) of each keypoint that anchors.
    type Found = Option<(Vector3<f64>, Vector3<f64>, usize)>;
    let found: Vec<Found> = world
        .par_iter()
        .map(|w| {
            if !any {
                return None;
            }
            let (_, s) = grid.nearest_within(live, w, radius)?;
            let s = s as usize;
            // The tissue point under the keypoint: its 3D point moved onto the surfel's tangent
            // plane (see the function doc).
            let n = live_normals.get(s).copied().unwrap_or_else(Vector3::zeros);
            let w = w - n * n.dot(&(w - live[s]));
            let a_inv = local_inverse(s);
            let mut c = canon[s] + a_inv * (w - live[s]);
            for _ in 0..ANCHOR_STEPS {
                let r = w - warp(&c, &bindings[s]);
                if r.norm() <= ANCHOR_TOLERANCE_MM {
                    return Some((c, w, s));
                }
                c += a_inv * r;
            }
            None
        })
        .collect();
    let mut keep = Vec::new();
    for (i, f) in found.into_iter().enumerate() {
        let Some((c, w, s)) = f else { continue };
        keep.push(i);
        out.canon.push(c);
        out.bindings.push(bindings[s]);
        out.live.push(w);
        out.keypoint.push(i as u32);
    }
    out.descriptors = Some(select(&features.descriptors, keep.iter().copied()));
    let n = out.canon.len();
    (out.last_seen, out.matched) = (vec![0; n], vec![0; n]);
    out
}

/// The point of `vertices` (a `k.width` x `k.height` map, camera frame) at sub-pixel `xy`,
/// bilinear between the four pixels around it; None where one is missing or their depths differ
/// by more than `max_step` mm.
fn vertex_at(
    vertices: &[[f32; 3]],
    k: &Intrinsics,
    xy: [f32; 2],
    max_step: f64,
) -> Option<Vector3<f64>> {
    let (w, h) = (k.width as usize, k.height as usize);
    if vertices.len() != w * h || !(xy[0] >= 0.0 && xy[1] >= 0.0) {
        return None;
    }
    let (x0, y0) = (xy[0].floor() as usize, xy[1].floor() as usize);
    if x0 + 1 >= w || y0 + 1 >= h {
        return None;
    }
    let (fx, fy) = ((xy[0] - x0 as f32) as f64, (xy[1] - y0 as f32) as f64);
    let mut out = Vector3::zeros();
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (dx, dy, wgt) in [
        (0, 0, (1.0 - fx) * (1.0 - fy)),
        (1, 0, fx * (1.0 - fy)),
        (0, 1, (1.0 - fx) * fy),
        (1, 1, fx * fy),
    ] {
        let v = vertices[(y0 + dy) * w + x0 + dx];
        if !v.iter().all(|c| c.is_finite()) {
            return None;
        }
        let v = Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64);
        (lo, hi) = (lo.min(v.z), hi.max(v.z));
        out += v * wgt;
    }
    (hi - lo <= max_step).then_some(out)
}

/// This frame's correspondences: its keypoints (seen through intrinsics `k`) matched to the
/// anchored ones, each with a 3D point (camera frame) within `max_jump_mm` of the anchor under
/// `prior`. With `points = "depth"` a match takes its 3D point from `scan.0`, the depth's
/// vertex map (`k.width` x `k.height`), and the surface normal there from `scan.1` (its normal
/// map; E_corr along it is weighted by `weights.corr_normal`); with a descriptor sampler on the
/// features (dense descriptors) and `refine_steps > 0` it is first moved to where the anchor's
/// descriptor fits best.
pub fn correspondences(
    features: &Features,
    anchors: &Anchors,
    prior: &Isometry3<f64>,
    k: &Intrinsics,
    scan: (&[[f32; 3]], &[[f32; 3]]),
    p: &CorrParams,
    scratch: &mut RefineScratch,
) -> Result<Vec<Correspondence>, String> {
    Ok(
        matched_correspondences(features, anchors, prior, k, scan, p, scratch)?
            .into_iter()
            .map(|(c, _, _)| c)
            .collect(),
    )
}

/// [`correspondences`], each with its anchor and keypoint.
fn matched_correspondences(
    features: &Features,
    anchors: &Anchors,
    prior: &Isometry3<f64>,
    k: &Intrinsics,
    scan: (&[[f32; 3]], &[[f32; 3]]),
    p: &CorrParams,
    scratch: &mut RefineScratch,
) -> Result<Vec<(Correspondence, u32, u32)>, String> {
    let (vertices, normals) = scan;
    let normal_at = |xy: [f32; 2]| -> Option<Vector3<f64>> {
        let (u, v) = (xy[0].round(), xy[1].round());
        if !(u >= 0.0 && v >= 0.0 && u < k.width as f32 && v < k.height as f32) {
            return None;
        }
        let n = normals.get(v as usize * k.width as usize + u as usize)?;
        let n = Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64);
        n.try_normalize(1e-9)
            .filter(|n| n.iter().all(|c| c.is_finite()))
    };
    let (Some(points), Some(train)) = (&features.points, &anchors.descriptors) else {
        return Ok(Vec::new());
    };
    if anchors.is_empty() || features.descriptors.is_empty() {
        return Ok(Vec::new());
    }
    if std::mem::discriminant(train) != std::mem::discriminant(&features.descriptors) {
        return Err("the features changed descriptor kind between frames".into());
    }
    let cfw = prior.inverse();
    let predicted: Vec<[f32; 2]> = anchors
        .live
        .iter()
        .map(|w| {
            let c = cfw * Point3::from(*w);
            if c.z <= 0.0 {
                return [f32::NAN; 2];
            }
            [
                (k.fx * c.x / c.z + k.cx) as f32,
                (k.fy * c.y / c.z + k.cy) as f32,
            ]
        })
        .collect();
    let grid = KeypointGrid::build(&features.keypoints, k.width, k.height, p.radius_px);
    let limit = match train {
        Descriptors::Binary256(_) => p.max_distance,
        Descriptors::Float64(_) => p.max_distance_l2,
    };
    let guided = GuidedParams {
        radius_px: p.radius_px,
        max_distance: limit,
        ratio: p.ratio,
        max_octave_gap: -1,
    };
    let matches = match_guided(
        &predicted,
        &[],
        train,
        &features.keypoints,
        &features.descriptors,
        &grid,
        &guided,
    );
    let from_depth = p.points == PointSource::Depth;
    let refine = match (&features.sampler, train) {
        (Some(sampler), Descriptors::Float64(d)) if from_depth && p.refine_steps > 0 => {
            Some((sampler, d))
        }
        _ => None,
    };
    let mut out = Vec::with_capacity(matches.len());
    for m in matches {
        let (q, a) = (m.query as usize, m.train as usize);
        let kp = &features.keypoints[q];
        let (target, normal) = if from_depth {
            let xy = match refine {
                Some((sampler, anchor_d)) => {
                    let Some(xy) = refine_match(
                        sampler.0.as_ref(),
                        &anchor_d[a],
                        kp.x,
                        kp.y,
                        p.refine_steps,
                        scratch,
                    ) else {
                        continue;
                    };
                    xy
                }
                None => [kp.x, kp.y],
            };
            let Some(v) = vertex_at(vertices, k, xy, p.depth_max_step_mm) else {
                continue;
            };
            (v, normal_at(xy))
        } else {
            let Some(pt) = points.get(q).filter(|v| v.iter().all(|c| c.is_finite())) else {
                continue;
            };
            (Vector3::new(pt[0] as f64, pt[1] as f64, pt[2] as f64), None)
        };
        if ((prior * Point3::from(target)).coords - anchors.live[a]).norm() > p.max_jump_mm {
            continue;
        }
        out.push((
            Correspondence {
                point: anchors.canon[a],
                binding: anchors.bindings[a],
                target,
                normal,
            },
            a as u32,
            q as u32,
        ));
    }
    Ok(out)
}

#[cfg(test)]
mod tests;
