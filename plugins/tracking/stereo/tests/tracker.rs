#![allow(clippy::unwrap_used)]
//! The tracker on constructed sequences (exact 3D keypoints with unique descriptors, seen from a
//! known trajectory) and on the rendered phantom (ORB on real renders, fast blurred motion).

use misslam_framework::nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use misslam_framework::{Descriptors, Features, Keypoint, TrackingState};
use misslam_tracking_stereo::pose::StereoCamera;
use misslam_tracking_stereo::{Tracker, TrackerParams};

fn camera() -> StereoCamera {
    StereoCamera {
        fx: 700.0,
        fy: 700.0,
        cx: 320.0,
        cy: 240.0,
        baseline: 5.0,
        doffs: 0.0,
    }
}

fn splitmix(s: &mut u64) -> u64 {
    *s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *s;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A textured wall of 3000 points at z = 80..100 mm, each with its own random descriptor.
struct World {
    points: Vec<Vector3<f64>>,
    descriptors: Vec<[u64; 4]>,
}

impl World {
    fn new() -> Self {
        let mut s = 11u64;
        let u = |s: &mut u64| (splitmix(s) >> 11) as f64 / (1u64 << 53) as f64;
        let points = (0..3000)
            .map(|_| {
                Vector3::new(
                    200.0 * u(&mut s) - 100.0,
                    150.0 * u(&mut s) - 75.0,
                    80.0 + 20.0 * u(&mut s),
                )
            })
            .collect();
        let descriptors = (0..3000)
            .map(|_| {
                [
                    splitmix(&mut s),
                    splitmix(&mut s),
                    splitmix(&mut s),
                    splitmix(&mut s),
                ]
            })
            .collect();
        World {
            points,
            descriptors,
        }
    }

    /// What the camera at `pose` sees: keypoints, descriptors and camera-frame points of the
    /// visible world points (exact), in a shuffled order.
    fn observe(&self, pose: &Isometry3<f64>) -> Features {
        let cam = camera();
        let cw = pose.inverse();
        let mut kps = Vec::new();
        let mut desc = Vec::new();
        let mut pts = Vec::new();
        for (p, d) in self.points.iter().zip(&self.descriptors) {
            let pc = (cw * Point3::from(*p)).coords;
            let Some(q) = cam.project(&pc) else { continue };
            if q[0] < 20.0 || q[1] < 20.0 || q[0] > 620.0 || q[1] > 460.0 {
                continue;
            }
            kps.push(Keypoint {
                x: q[0] as f32,
                y: q[1] as f32,
                size: 31.0,
                angle: 0.0,
                response: 1.0,
                octave: 0,
            });
            desc.push(*d);
            pts.push([pc.x as f32, pc.y as f32, pc.z as f32]);
        }
        // Reverse, so indices differ between frames.
        kps.reverse();
        desc.reverse();
        pts.reverse();
        Features {
            keypoints: kps,
            descriptors: Descriptors::Binary256(desc),
            points: Some(pts),
            sampler: None,
        }
    }
}

fn pose_at(i: usize) -> Isometry3<f64> {
    let t = i as f64;
    Isometry3::from_parts(
        Translation3::new(1.5 * t, 0.4 * t, 0.0),
        UnitQuaternion::from_euler_angles(0.002 * t, -0.003 * t, 0.0),
    )
}

fn error_mm(a: &Isometry3<f64>, b: &Isometry3<f64>) -> f64 {
    (a.translation.vector - b.translation.vector).norm()
}

#[test]
fn exact_sequence_is_tracked_exactly_with_keyframes() {
    let world = World::new();
    let mut tracker = Tracker::new(TrackerParams::default());
    for i in 0..40 {
        let truth = pose_at(i);
        let f = world.observe(&truth);
        let r = tracker
            .track(i as u64, &f, &camera(), (640, 480), Some(pose_at(0)))
            .unwrap();
        assert_eq!(
            r.state,
            TrackingState::Tracking,
            "frame {i}: {:?}",
            r.reason
        );
        assert!(error_mm(&r.pose, &truth) < 1e-3, "frame {i}");
        assert!((r.pose.rotation.inverse() * truth.rotation).angle() < 1e-5);
        if i > 0 {
            assert!(r.inliers >= 100, "frame {i}: {} inliers", r.inliers);
            // Correspondences carry the current camera point and the keyframe's world point,
            // which the true pose relates.
            for c in &r.correspondences {
                let pc = Vector3::new(c.camera[0] as f64, c.camera[1] as f64, c.camera[2] as f64);
                let w = truth * Point3::from(pc);
                let d = (w.coords
                    - Vector3::new(c.world[0] as f64, c.world[1] as f64, c.world[2] as f64))
                .norm();
                assert!(d < 1e-3, "frame {i}: {d}");
            }
        }
    }
    // The camera travels 60 mm over a 200 mm wall: the overlap with the first keyframe drops,
    // so new keyframes were made.
    assert!(
        tracker.keyframes().len() >= 2,
        "{}",
        tracker.keyframes().len()
    );
}

#[test]
fn revisiting_reuses_the_stored_keyframes_instead_of_chaining_new_ones() {
    // Out and back along the wall three times: with map reuse the keyframes made on the first
    // way out serve every later pass (no new keyframe, so no chain along which an error could
    // grow); without it every drop of overlap makes one more.
    let world = World::new();
    let sweep = |i: usize| {
        let k = i % 78;
        if k < 40 {
            k
        } else {
            78 - k
        }
    };
    let run = |reuse_candidates: usize| {
        let params = TrackerParams {
            reuse_candidates,
            ..TrackerParams::default()
        };
        let mut tracker = Tracker::new(params);
        let mut after_first_pass = 0;
        let mut reused = 0;
        for i in 0..234 {
            let truth = pose_at(sweep(i));
            let r = tracker
                .track(
                    i as u64,
                    &world.observe(&truth),
                    &camera(),
                    (640, 480),
                    Some(truth),
                )
                .unwrap();
            assert_eq!(
                r.state,
                TrackingState::Tracking,
                "frame {i}: {:?}",
                r.reason
            );
            assert!(error_mm(&r.pose, &truth) < 1e-3, "frame {i}");
            if i == 39 {
                after_first_pass = tracker.keyframes().len();
            }
            if i > 39 && r.keyframe.is_some_and(|k| k < 40) && !r.new_keyframe {
                reused += 1;
            }
        }
        (after_first_pass, tracker.keyframes().len(), reused)
    };
    let (first, total, reused) = run(TrackerParams::default().reuse_candidates);
    assert!(first >= 2, "{first} keyframes on the way out");
    assert_eq!(total, first, "keyframes made after the first pass");
    assert!(
        reused > 150,
        "{reused} of 194 later frames tracked against first-pass keyframes"
    );
    let (first_off, total_off, _) = run(0);
    assert_eq!(first_off, first);
    // Measured: 2 keyframes with reuse, 3 without (the way back makes one more, at the start).
    assert!(total_off > total, "{total_off} keyframes without reuse");
}

#[test]
fn a_black_frame_is_lost_and_the_next_view_relocalises() {
    let world = World::new();
    let mut tracker = Tracker::new(TrackerParams::default());
    let mut states = Vec::new();
    for i in 0..12 {
        let truth = pose_at(i);
        let f = if i == 6 || i == 7 {
            // A black (or missing) frame: no keypoints at all.
            Features {
                keypoints: Vec::new(),
                descriptors: Descriptors::Binary256(Vec::new()),
                points: Some(Vec::new()),
                sampler: None,
            }
        } else if i == 8 {
            // Back to an early viewpoint: a jump no motion model predicts.
            world.observe(&pose_at(1))
        } else {
            world.observe(&truth)
        };
        let r = tracker
            .track(i as u64, &f, &camera(), (640, 480), None)
            .unwrap();
        let expected = if i == 8 { pose_at(1) } else { truth };
        match i {
            6 | 7 => {
                assert_eq!(r.state, TrackingState::Lost);
                assert!(r.reason.as_deref().unwrap_or("").contains("stereo match"));
                // The reported pose is the last good one, never NaN.
                assert!(error_mm(&r.pose, &pose_at(5)) < 1e-3);
            }
            8 => {
                assert_eq!(r.state, TrackingState::Relocalised, "{:?}", r.reason);
                assert!(error_mm(&r.pose, &expected) < 1e-3);
            }
            _ => {
                assert_eq!(r.state, TrackingState::Tracking, "frame {i}");
                assert!(error_mm(&r.pose, &expected) < 1e-3);
            }
        }
        states.push(r.state);
    }
    assert_eq!(
        states.iter().filter(|s| **s == TrackingState::Lost).count(),
        2
    );
}

#[test]
fn features_without_points_or_mismatched_lengths_are_errors() {
    let world = World::new();
    let mut f = world.observe(&pose_at(0));
    let mut tracker = Tracker::new(TrackerParams::default());
    f.points.as_mut().unwrap().pop();
    let e = tracker
        .track(0, &f, &camera(), (640, 480), None)
        .unwrap_err();
    assert!(e.contains("do not correspond"), "{e}");
    f.points = None;
    let e = tracker
        .track(0, &f, &camera(), (640, 480), None)
        .unwrap_err();
    assert!(e.contains("3D points"), "{e}");
    let bad = TrackerParams {
        keyframe_overlap: 0.0,
        ..TrackerParams::default()
    };
    assert!(bad.validate().unwrap_err().contains("keyframe_overlap"));
    for (bad, field) in [
        (
            TrackerParams {
                tissue_sigma_mm: -1.0,
                ..TrackerParams::default()
            },
            "tissue_sigma_mm",
        ),
        (
            TrackerParams {
                tissue_sigma_mm: f64::NAN,
                ..TrackerParams::default()
            },
            "tissue_sigma_mm",
        ),
        (
            TrackerParams {
                reuse_min_visible: 0.0,
                ..TrackerParams::default()
            },
            "reuse_min_visible",
        ),
        (
            TrackerParams {
                min_kept: 1.5,
                ..TrackerParams::default()
            },
            "min_kept",
        ),
    ] {
        assert!(bad.validate().unwrap_err().contains(field), "{field}");
    }
}

/// ORB on the rendered phantom (tissue texture, specular light, sensor noise) through a fast,
/// motion-blurred jerk of 40 mm: frames may be lost during the jerk, never with a wrong pose,
/// and tracking is back within 5 frames of its end. A blurred image shows the scope all along
/// its path during the exposure (at the jerk's first frame, half still and half moving up to 5
/// mm), so a pose is right when it lies within 1 mm of that path; on a sharp frame the path is
/// the mid-exposure pose.
#[test]
fn phantom_fast_blurred_motion_is_survived() {
    use misslam_features_orb::{build as build_orb, Params as OrbNodeParams};
    use misslam_source_phantom::{Params as PhantomParams, Phantom};
    let params: PhantomParams = misslam_framework::toml::from_str(
        "scene = \"heart\"\ntrajectory = \"fast\"\nheartbeat_mm = 0.0\nbreathing_mm = 0.0\n\
         fast_start_s = 1.0\nfast_amplitude_mm = 40.0\nmotion_blur_samples = 6\n",
    )
    .unwrap();
    let fps = params.fps;
    let exposure = params.exposure_s;
    let (start, dur) = (params.fast_start_s as f64, params.fast_duration_s as f64);
    let mut phantom = Phantom::new(params, 7).unwrap();
    let gpu = misslam_framework::GpuProvider::new();
    let ctx = misslam_framework::BuildContext {
        node_id: "features",
        graph_dir: std::path::Path::new("."),
        seed: 7,
        gpu: &gpu,
    };
    let mut orb = build_orb(OrbNodeParams::default(), &ctx).unwrap();
    let mut tracker = Tracker::new(TrackerParams::default());
    let first = (start * fps).floor() as u64;
    let last = ((start + dur) * fps).ceil() as u64;
    let mut back = None;
    for i in 0..(last + 8) {
        let frame = phantom.render(i).unwrap();
        let c = frame.stereo.calib;
        let cam = StereoCamera {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            baseline: c.baseline_mm,
            doffs: c.doffs(),
        };
        let (features, _) = orb.stereo_features(&frame.stereo).unwrap();
        let truth = frame.pose.world_from_camera;
        let r = tracker
            .track(i, &features, &cam, (c.width, c.height), Some(truth))
            .unwrap();
        assert!(r.pose.translation.vector.iter().all(|v| v.is_finite()));
        if r.state == TrackingState::Lost {
            assert!(
                (first..=last).contains(&i),
                "frame {i} lost outside the jerk ({first}..={last})"
            );
        } else {
            let t = phantom.time(i);
            let e = (0..=24)
                .map(|k| {
                    let ts = t + exposure * (k as f32 / 24.0 - 0.5);
                    error_mm(&r.pose, &phantom.pose(ts).cast::<f64>())
                })
                .fold(f64::INFINITY, f64::min);
            let mid = error_mm(&r.pose, &truth);
            assert!(
                e < 1.0,
                "frame {i}: {:?} pose {e} mm from the exposure's path ({mid} mm from its middle)",
                r.state
            );
            if i > last && back.is_none() {
                back = Some(i);
            }
        }
    }
    let back = back.expect("tracking resumed");
    assert!(
        back <= last + 5,
        "back at frame {back}, the jerk ended at {last}"
    );
}
