//! The scope tracker: per frame, match the current 3D keypoints against the reference keyframe
//! (guided by a constant-velocity prediction, brute force when that finds too few), estimate
//! the pose robustly ([`crate::pose`]), insert a keyframe when the overlap drops, and after a
//! loss relocalise against every stored keyframe.

use misslam_features_matching::guided::{match_guided, GuidedParams, KeypointGrid};
use misslam_features_matching::{match_descriptors, MatchParams, MatchScratch};
use misslam_framework::nalgebra::{Isometry3, Matrix3, Point3, Vector3};
use misslam_framework::{Descriptors, Features, Keypoint, Match, TrackingState};

use crate::pose::{
    estimate, is_finite, refine, triangulation_cov, Observation, PoseEstimate, RansacParams,
    StereoCamera,
};

/// Parameters of the tracker (`tracking.stereo`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerParams {
    /// Brute-force matching (fallback and relocalisation): ratio, distance limits (Hamming bits
    /// for ORB, L2 for SURF), cross-check. The guided search uses the same limits.
    pub matching: MatchParams,
    /// Guided matching: search radius around the predicted position, pixels.
    pub guided_radius_px: f32,
    /// Guided matching: best-to-second ratio inside the radius (1 disables).
    pub guided_ratio: f32,
    /// RANSAC: most hypotheses.
    pub ransac_iterations: usize,
    /// RANSAC: confidence of having drawn an all-inlier sample.
    pub ransac_confidence: f64,
    /// Inlier test on the stereo reprojection error, chi-square with 3 degrees of freedom
    /// (7.815 is the 95 % quantile), in units of the keypoint's sigma.
    pub chi2_threshold: f64,
    /// Reprojection sigma of a level-0 keypoint, pixels; it grows with the keypoint's size / 31.
    pub sigma_px: f64,
    /// How far the tissue under the map's points moves (heartbeat, breathing), standard
    /// deviation in mm, added to every residual's covariance: on a deforming organ the pose
    /// then fits the points in millimetres rather than trading their motion for a rotation
    /// (0: a rigid scene, ORB-SLAM2's pure reprojection error).
    pub tissue_sigma_mm: f64,
    /// Refinement rounds (inliers re-classified between rounds) and Gauss-Newton iterations
    /// per round.
    pub refine_rounds: usize,
    /// Gauss-Newton iterations per refinement round.
    pub refine_iterations: usize,
    /// Fewest inliers for a tracked frame; below it the frame is lost.
    pub min_inliers: usize,
    /// A new keyframe is made when the inliers fall below this fraction of those of the first
    /// frame tracked against the reference keyframe.
    pub keyframe_overlap: f32,
    /// A frame that keeps fewer than this fraction of the previous frame's inliers is reported
    /// lost, with the reason. Such a collapse in one frame means a blurred, occluded or dark
    /// image rather than a changed view (a view changes over several frames): the few matches
    /// left mix the scope's positions during the exposure and give a pose off its path, and a
    /// keyframe made from it would pass that error on to every frame tracked against it. The
    /// next frames relocalise (0 disables the check).
    pub min_kept: f32,
    /// Keyframes kept for relocalisation and reuse (the oldest is dropped first).
    pub max_keyframes: usize,
    /// Map reuse: when the reference keyframe's overlap drops, this many stored keyframes that
    /// the current view sees best are tried first, and the oldest of them that still holds
    /// `keyframe_overlap` of its inliers becomes the reference instead of a new keyframe.
    /// Revisiting a place then tracks against the keyframe first made there, so the pose error
    /// does not accumulate along a chain of keyframes (0 disables: every drop makes a keyframe).
    pub reuse_candidates: usize,
    /// Map reuse: fewest of a keyframe's 3D points, as a fraction, that must project into the
    /// current image for it to be a candidate.
    pub reuse_min_visible: f32,
    /// Fewest inliers to accept a relocalisation.
    pub relocalise_min_inliers: usize,
}

impl Default for TrackerParams {
    fn default() -> Self {
        TrackerParams {
            matching: MatchParams {
                ratio: 0.8,
                max_distance: 64.0,
                max_distance_l2: 0.4,
                cross_check: false,
            },
            guided_radius_px: 20.0,
            guided_ratio: 0.9,
            ransac_iterations: 300,
            ransac_confidence: 0.999,
            chi2_threshold: 7.815,
            sigma_px: 1.0,
            tissue_sigma_mm: 1.0,
            refine_rounds: 4,
            refine_iterations: 10,
            min_inliers: 20,
            keyframe_overlap: 0.6,
            min_kept: 0.5,
            max_keyframes: 200,
            reuse_candidates: 4,
            reuse_min_visible: 0.5,
            relocalise_min_inliers: 30,
        }
    }
}

impl TrackerParams {
    /// Checks the ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        self.matching
            .validate()
            .map_err(|m| format!("matching: {m}"))?;
        let positive = [
            ("guided_radius_px", self.guided_radius_px as f64),
            ("chi2_threshold", self.chi2_threshold),
            ("sigma_px", self.sigma_px),
        ];
        if !(self.tissue_sigma_mm >= 0.0 && self.tissue_sigma_mm.is_finite()) {
            return Err(format!(
                "`tissue_sigma_mm` must be finite and not negative, got {}",
                self.tissue_sigma_mm
            ));
        }
        for (name, v) in positive {
            if v.is_nan() || v <= 0.0 {
                return Err(format!("`{name}` must be positive, got {v}"));
            }
        }
        if !(self.guided_ratio > 0.0 && self.guided_ratio <= 1.0) {
            return Err(format!(
                "`guided_ratio` must lie in (0, 1], got {}",
                self.guided_ratio
            ));
        }
        if !(self.ransac_confidence > 0.0 && self.ransac_confidence < 1.0) {
            return Err(format!(
                "`ransac_confidence` must lie in (0, 1), got {}",
                self.ransac_confidence
            ));
        }
        if self.ransac_iterations == 0 {
            return Err("`ransac_iterations` must be at least 1".into());
        }
        if self.min_inliers < 3 || self.relocalise_min_inliers < 3 {
            return Err(format!(
                "`min_inliers` ({}) and `relocalise_min_inliers` ({}) must be at least 3",
                self.min_inliers, self.relocalise_min_inliers
            ));
        }
        if !(self.keyframe_overlap > 0.0 && self.keyframe_overlap <= 1.0) {
            return Err(format!(
                "`keyframe_overlap` must lie in (0, 1], got {}",
                self.keyframe_overlap
            ));
        }
        if !(self.reuse_min_visible > 0.0 && self.reuse_min_visible <= 1.0) {
            return Err(format!(
                "`reuse_min_visible` must lie in (0, 1], got {}",
                self.reuse_min_visible
            ));
        }
        if !(0.0..=1.0).contains(&self.min_kept) {
            return Err(format!(
                "`min_kept` must lie in [0, 1], got {}",
                self.min_kept
            ));
        }
        if self.max_keyframes == 0 {
            return Err("`max_keyframes` must be at least 1".into());
        }
        Ok(())
    }

    fn ransac(&self, min_inliers: usize) -> RansacParams {
        RansacParams {
            max_iterations: self.ransac_iterations,
            confidence: self.ransac_confidence,
            chi2_threshold: self.chi2_threshold,
            refine_rounds: self.refine_rounds,
            refine_iterations: self.refine_iterations,
            min_inliers,
            tissue_sigma_mm: self.tissue_sigma_mm,
        }
    }
}

/// A stored keyframe: its pose and its 3D keypoints in the world frame.
#[derive(Clone, Debug)]
pub struct Keyframe {
    /// Frame index it was made from.
    pub frame: u64,
    /// Its `world_from_camera`.
    pub pose: Isometry3<f64>,
    /// Keypoints that have a 3D point.
    pub keypoints: Vec<Keypoint>,
    /// Their descriptors.
    pub descriptors: Descriptors,
    /// Their 3D points in the world frame, mm.
    pub world: Vec<Vector3<f64>>,
    /// The covariance of each, mm^2 (stereo triangulation, rotated into the world frame).
    pub world_cov: Vec<Matrix3<f64>>,
    /// Inliers of the first frame tracked against it (0 until then).
    pub reference_inliers: usize,
}

/// The result of one frame.
#[derive(Clone, Debug)]
pub struct TrackResult {
    /// `world_from_camera` (the last good pose when lost).
    pub pose: Isometry3<f64>,
    /// Tracking, lost, or relocalised.
    pub state: TrackingState,
    /// Inliers of the pose.
    pub inliers: usize,
    /// Candidate matches before RANSAC.
    pub matches: usize,
    /// Whether this frame became a keyframe.
    pub new_keyframe: bool,
    /// Inlier correspondences: current keypoint index, keyframe keypoint index (in the
    /// keyframe's own list), the current camera-frame point and the keyframe's world point.
    pub correspondences: Vec<Correspondence>,
    /// Keyframe matched against.
    pub keyframe: Option<u64>,
    /// Why the frame is lost, when it is.
    pub reason: Option<String>,
}

/// A 3D correspondence between the current frame and a keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Correspondence {
    /// Current keypoint index.
    pub current: u32,
    /// Keyframe keypoint index.
    pub keyframe: u32,
    /// Current keypoint position, pixels.
    pub current_xy: [f32; 2],
    /// Keyframe keypoint position (in the keyframe's image), pixels.
    pub keyframe_xy: [f32; 2],
    /// Current camera-frame point, mm.
    pub camera: [f32; 3],
    /// Keyframe point in the world frame, mm.
    pub world: [f32; 3],
}

/// The tracker's state across frames.
pub struct Tracker {
    params: TrackerParams,
    keyframes: Vec<Keyframe>,
    reference: usize,
    last: Option<Isometry3<f64>>,
    velocity: Isometry3<f64>,
    lost: bool,
    /// Inliers of the last tracked frame (0 after a loss).
    last_inliers: usize,
    scratch: MatchScratch,
}

/// Candidate matches (current index, keyframe index) turned into observations.
struct Candidates {
    pairs: Vec<(u32, u32)>,
    obs: Vec<Observation>,
}

impl Tracker {
    /// A tracker; `params` must have been validated.
    pub fn new(params: TrackerParams) -> Self {
        Tracker {
            params,
            keyframes: Vec::new(),
            reference: 0,
            last: None,
            velocity: Isometry3::identity(),
            lost: false,
            last_inliers: 0,
            scratch: MatchScratch::default(),
        }
    }

    /// The stored keyframes.
    pub fn keyframes(&self) -> &[Keyframe] {
        &self.keyframes
    }

    /// Tracks one frame. `initial` sets the world frame on the first frame (identity when
    /// absent); `width` and `height` bound the guided search.
    pub fn track(
        &mut self,
        frame: u64,
        features: &Features,
        cam: &StereoCamera,
        size: (u32, u32),
        initial: Option<Isometry3<f64>>,
    ) -> Result<TrackResult, String> {
        let points = features.points.as_ref().ok_or_else(|| {
            "the features carry no 3D points: connect a stereo pair to the feature node".to_owned()
        })?;
        if points.len() != features.keypoints.len()
            || features.descriptors.len() != features.keypoints.len()
        {
            return Err(format!(
                "{} keypoints, {} descriptors and {} points do not correspond",
                features.keypoints.len(),
                features.descriptors.len(),
                points.len()
            ));
        }
        let with_3d = points
            .iter()
            .filter(|p| p.iter().all(|v| v.is_finite()))
            .count();
        if self.keyframes.is_empty() {
            if with_3d < self.params.min_inliers {
                return Ok(self.lost_result(format!(
                    "not initialised: {with_3d} keypoints with a stereo match, {} needed",
                    self.params.min_inliers
                )));
            }
            let pose = initial.unwrap_or_else(Isometry3::identity);
            self.insert_keyframe(frame, features, cam, pose);
            self.last = Some(pose);
            return Ok(TrackResult {
                pose,
                state: TrackingState::Tracking,
                inliers: with_3d,
                matches: 0,
                new_keyframe: true,
                correspondences: Vec::new(),
                keyframe: Some(frame),
                reason: None,
            });
        }
        if with_3d < self.params.min_inliers {
            return Ok(self.lose(format!(
                "{with_3d} keypoints with a stereo match (black, blurred or missing frame?), {} needed",
                self.params.min_inliers
            )));
        }
        let last = self.last.unwrap_or_else(Isometry3::identity);
        if !self.lost {
            let predicted = last * self.velocity;
            let r = self.reference;
            let mut cand = self.guided(r, features, cam, size, &predicted);
            let ransac = self.params.ransac(self.params.min_inliers);
            let mut est = estimate(cam, &cand.obs, &ransac, frame);
            if est.is_none() {
                cand = self.brute(r, features, cam)?;
                est = estimate(cam, &cand.obs, &ransac, frame);
            }
            if let Some(e) = est {
                if (e.inlier_count as f32) < self.params.min_kept * self.last_inliers as f32 {
                    let reason = format!(
                        "the inliers fell from {} to {} in one frame (blurred, occluded or dark \
                         image?); below `min_kept` {} of them the pose is not trusted",
                        self.last_inliers, e.inlier_count, self.params.min_kept
                    );
                    return Ok(self.lose(reason));
                }
                let kf = &mut self.keyframes[r];
                if kf.reference_inliers == 0 {
                    kf.reference_inliers = e.inlier_count;
                }
                let need_kf = (e.inlier_count as f32)
                    < self.params.keyframe_overlap * kf.reference_inliers as f32;
                if need_kf {
                    if let Some((k, cand, e)) =
                        self.reuse(r, frame, features, cam, size, &e.world_from_camera)
                    {
                        self.reference = k;
                        let state = TrackingState::Tracking;
                        let r = self.success(frame, features, cam, &cand, &e, k, state, false);
                        return Ok(r);
                    }
                }
                let result = self.success(
                    frame,
                    features,
                    cam,
                    &cand,
                    &e,
                    r,
                    TrackingState::Tracking,
                    need_kf,
                );
                return Ok(result);
            }
        }
        // Lost, or lost on this frame: every keyframe by brute force (most recent first), then
        // the hypotheses in order of their inliers until one is confirmed.
        let ransac = self.params.ransac(self.params.relocalise_min_inliers);
        let mut found: Vec<(usize, usize, crate::pose::PoseEstimate)> = Vec::new();
        for k in (0..self.keyframes.len()).rev() {
            let cand = self.brute(k, features, cam)?;
            if let Some(e) = estimate(cam, &cand.obs, &ransac, frame ^ k as u64) {
                found.push((k, cand.obs.len(), e));
            }
        }
        // Stable: equal counts keep the most recent keyframe first.
        found.sort_by_key(|(_, _, e)| std::cmp::Reverse(e.inlier_count));
        let mut refused = None;
        for (k, brute_matches, e) in found {
            // Confirmed by a guided search at the pose found (as ORB-SLAM's relocalisation
            // searches by projection): the keyframe's points projected with that pose must
            // find their matches where they land. Brute-force matches of a blurred or
            // unfamiliar view can agree on a wrong pose (the inlier gate allows for tissue
            // motion, about 10 px per mm at 70 mm); the projections of a wrong pose land
            // where the image does not show those points.
            let cand = self.guided(k, features, cam, size, &e.world_from_camera);
            let (pose, inliers) = refine(cam, &cand.obs, e.world_from_camera, &ransac);
            let inlier_count = inliers.iter().filter(|&&b| b).count();
            if inlier_count < self.params.relocalise_min_inliers || !is_finite(&pose) {
                refused.get_or_insert_with(|| {
                    format!(
                        "relocalisation not confirmed: against keyframe {}, {} of {brute_matches} \
                         brute-force matches agreed on a pose, but a guided search there found \
                         {inlier_count} inliers of {} matches ({} needed)",
                        self.keyframes[k].frame,
                        e.inlier_count,
                        cand.obs.len(),
                        self.params.relocalise_min_inliers
                    )
                });
                continue;
            }
            let e = PoseEstimate {
                world_from_camera: pose,
                inliers,
                inlier_count,
                iterations: e.iterations,
            };
            // Recovered against a stored keyframe: after a loss, or on the frame where the
            // reference keyframe could no longer be tracked.
            let state = TrackingState::Relocalised;
            self.reference = k;
            self.velocity = Isometry3::identity();
            return Ok(self.success(frame, features, cam, &cand, &e, k, state, false));
        }
        let reason = refused.unwrap_or_else(|| {
            format!(
                "no keyframe of {} gives {} inliers",
                self.keyframes.len(),
                self.params.relocalise_min_inliers
            )
        });
        Ok(self.lose(reason))
    }

    /// Map reuse: the oldest of the `reuse_candidates` keyframes (other than `skip`, and only
    /// those already tracked against, which have reference inliers) that the view at `pose`
    /// sees best which still tracks with `keyframe_overlap` of its reference inliers.
    fn reuse(
        &self,
        skip: usize,
        frame: u64,
        features: &Features,
        cam: &StereoCamera,
        (w, h): (u32, u32),
        pose: &Isometry3<f64>,
    ) -> Option<(usize, Candidates, crate::pose::PoseEstimate)> {
        if self.params.reuse_candidates == 0 {
            return None;
        }
        let camera_from_world = pose.inverse();
        let mut seen: Vec<(f32, usize)> = self
            .keyframes
            .iter()
            .enumerate()
            .filter(|&(k, kf)| k != skip && kf.reference_inliers > 0 && !kf.world.is_empty())
            .filter_map(|(k, kf)| {
                let inside = kf
                    .world
                    .iter()
                    .filter(|p| in_image(cam, &camera_from_world, p, (w, h)).is_some())
                    .count();
                let fraction = inside as f32 / kf.world.len() as f32;
                (fraction >= self.params.reuse_min_visible).then_some((fraction, k))
            })
            .collect();
        seen.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        seen.truncate(self.params.reuse_candidates);
        seen.sort_by_key(|&(_, k)| k);
        let ransac = self.params.ransac(self.params.min_inliers);
        seen.into_iter().find_map(|(_, k)| {
            let cand = self.guided(k, features, cam, (w, h), pose);
            let e = estimate(cam, &cand.obs, &ransac, frame ^ k as u64)?;
            let need = self.params.keyframe_overlap * self.keyframes[k].reference_inliers as f32;
            ((e.inlier_count as f32) >= need).then_some((k, cand, e))
        })
    }

    fn lost_result(&self, reason: String) -> TrackResult {
        TrackResult {
            pose: self.last.unwrap_or_else(Isometry3::identity),
            state: TrackingState::Lost,
            inliers: 0,
            matches: 0,
            new_keyframe: false,
            correspondences: Vec::new(),
            keyframe: None,
            reason: Some(reason),
        }
    }

    fn lose(&mut self, reason: String) -> TrackResult {
        self.lost = true;
        self.last_inliers = 0;
        self.velocity = Isometry3::identity();
        self.lost_result(reason)
    }

    #[allow(clippy::too_many_arguments)]
    fn success(
        &mut self,
        frame: u64,
        features: &Features,
        cam: &StereoCamera,
        cand: &Candidates,
        e: &crate::pose::PoseEstimate,
        kf_index: usize,
        state: TrackingState,
        need_keyframe: bool,
    ) -> TrackResult {
        let pose = e.world_from_camera;
        if let (Some(last), false) = (self.last, self.lost) {
            self.velocity = last.inverse() * pose;
        }
        self.last = Some(pose);
        self.lost = false;
        self.last_inliers = e.inlier_count;
        let kf = &self.keyframes[kf_index];
        let kf_frame = kf.frame;
        let points = features.points.as_deref().unwrap_or(&[]);
        let correspondences = cand
            .pairs
            .iter()
            .zip(&e.inliers)
            .filter(|(_, &b)| b)
            .map(|(&(c, k), _)| {
                let kc = &features.keypoints[c as usize];
                let kk = &kf.keypoints[k as usize];
                let w = kf.world[k as usize];
                Correspondence {
                    current: c,
                    keyframe: k,
                    current_xy: [kc.x, kc.y],
                    keyframe_xy: [kk.x, kk.y],
                    camera: points[c as usize],
                    world: [w.x as f32, w.y as f32, w.z as f32],
                }
            })
            .collect();
        if need_keyframe {
            self.insert_keyframe(frame, features, cam, pose);
        }
        TrackResult {
            pose,
            state,
            inliers: e.inlier_count,
            matches: cand.pairs.len(),
            new_keyframe: need_keyframe,
            correspondences,
            keyframe: Some(kf_frame),
            reason: None,
        }
    }

    fn insert_keyframe(
        &mut self,
        frame: u64,
        features: &Features,
        cam: &StereoCamera,
        pose: Isometry3<f64>,
    ) {
        let points = features.points.as_deref().unwrap_or(&[]);
        let keep: Vec<usize> = (0..features.keypoints.len())
            .filter(|&i| points[i].iter().all(|v| v.is_finite()))
            .collect();
        let descriptors = match &features.descriptors {
            Descriptors::Binary256(d) => {
                Descriptors::Binary256(keep.iter().map(|&i| d[i]).collect())
            }
            Descriptors::Float64(d) => Descriptors::Float64(keep.iter().map(|&i| d[i]).collect()),
        };
        let world = keep
            .iter()
            .map(|&i| {
                let p = points[i];
                (pose * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64)).coords
            })
            .collect();
        let rotation = pose.rotation.to_rotation_matrix();
        let world_cov = keep
            .iter()
            .map(|&i| {
                let p = points[i];
                let p = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                let sigma = self.sigma(&features.keypoints[i]);
                rotation * triangulation_cov(cam, &p, sigma) * rotation.transpose()
            })
            .collect();
        self.keyframes.push(Keyframe {
            frame,
            pose,
            keypoints: keep.iter().map(|&i| features.keypoints[i]).collect(),
            descriptors,
            world,
            world_cov,
            reference_inliers: 0,
        });
        self.reference = self.keyframes.len() - 1;
        if self.keyframes.len() > self.params.max_keyframes {
            self.keyframes.remove(0);
            self.reference -= 1;
        }
    }

    fn observation(
        &self,
        features: &Features,
        cam: &StereoCamera,
        c: usize,
        world: Vector3<f64>,
        world_cov: Matrix3<f64>,
    ) -> Option<Observation> {
        let p = features.points.as_ref()?[c];
        if !p.iter().all(|v| v.is_finite()) || p[2] <= 0.0 {
            return None;
        }
        let k = &features.keypoints[c];
        let disparity = cam.fx * cam.baseline / p[2] as f64 - cam.doffs;
        Some(Observation {
            world,
            camera: Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64),
            uv: [k.x as f64, k.y as f64],
            u_right: k.x as f64 - disparity,
            sigma: self.sigma(k),
            world_cov,
        })
    }

    /// Image-position standard deviation of a keypoint, pixels.
    fn sigma(&self, k: &Keypoint) -> f64 {
        self.params.sigma_px * (k.size as f64 / 31.0).max(1.0)
    }

    fn candidates(
        &self,
        kf: usize,
        features: &Features,
        cam: &StereoCamera,
        m: &[Match],
    ) -> Candidates {
        let (world, cov) = (&self.keyframes[kf].world, &self.keyframes[kf].world_cov);
        let mut out = Candidates {
            pairs: Vec::with_capacity(m.len()),
            obs: Vec::with_capacity(m.len()),
        };
        for m in m {
            if let Some(o) = self.observation(
                features,
                cam,
                m.query as usize,
                world[m.train as usize],
                cov[m.train as usize],
            ) {
                out.pairs.push((m.query, m.train));
                out.obs.push(o);
            }
        }
        out
    }

    fn guided(
        &self,
        kf: usize,
        features: &Features,
        cam: &StereoCamera,
        (w, h): (u32, u32),
        predicted_pose: &Isometry3<f64>,
    ) -> Candidates {
        let k = &self.keyframes[kf];
        let camera_from_world = predicted_pose.inverse();
        let predicted: Vec<[f32; 2]> = k
            .world
            .iter()
            .map(|p| in_image(cam, &camera_from_world, p, (w, h)).unwrap_or([f32::NAN; 2]))
            .collect();
        let octaves: Vec<i32> = k.keypoints.iter().map(|k| k.octave).collect();
        let grid = KeypointGrid::build(&features.keypoints, w, h, 32.0);
        let m = match_guided(
            &predicted,
            &octaves,
            &k.descriptors,
            &features.keypoints,
            &features.descriptors,
            &grid,
            &GuidedParams {
                radius_px: self.params.guided_radius_px,
                max_distance: self.params.matching.limit(&features.descriptors),
                ratio: self.params.guided_ratio,
                max_octave_gap: 2,
            },
        );
        self.candidates(kf, features, cam, &m)
    }

    fn brute(
        &mut self,
        kf: usize,
        features: &Features,
        cam: &StereoCamera,
    ) -> Result<Candidates, String> {
        let m = match_descriptors(
            &features.descriptors,
            &self.keyframes[kf].descriptors,
            &self.params.matching,
            &mut self.scratch,
        )?;
        Ok(self.candidates(kf, features, cam, &m))
    }
}

/// The left-image position of the world point `p` seen through `camera_from_world`, when it
/// lies in front of the camera and inside the `(w, h)` image.
fn in_image(
    cam: &StereoCamera,
    camera_from_world: &Isometry3<f64>,
    p: &Vector3<f64>,
    (w, h): (u32, u32),
) -> Option<[f32; 2]> {
    let q = cam.project(&(camera_from_world * Point3::from(*p)).coords)?;
    (q[0] >= 0.0 && q[1] >= 0.0 && q[0] < w as f64 && q[1] < h as f64)
        .then_some([q[0] as f32, q[1] as f32])
}
