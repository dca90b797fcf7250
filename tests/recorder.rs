//! Every payload type goes through the recorder into a saved `.rrd` that the rerun CLI verifies,
//! with the archetype each type maps to.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

mod common;

use std::collections::BTreeMap;
use std::sync::Arc;

use misslam::framework::nalgebra::{Isometry3, Translation3, UnitQuaternion};
use misslam::framework::recorder::{Recorder, RerunMode};
use misslam::framework::*;

fn calib() -> StereoCalib {
    StereoCalib {
        width: 4,
        height: 2,
        fx: 10.0,
        fy: 10.0,
        cx: 2.0,
        cy: 1.0,
        cx_right: 2.0,
        baseline_mm: 5.0,
    }
}

fn all_payloads() -> Vec<(&'static str, Payload)> {
    let img = Arc::new(Image::new(4, 2, 3, vec![90; 24]).unwrap());
    let map = FloatMap {
        width: 4,
        height: 2,
        data: vec![50.0, 51.0, f32::NAN, 52.0, 53.0, 54.0, 55.0, 56.0],
    };
    let pose = Pose {
        world_from_camera: Isometry3::from_parts(
            Translation3::new(1.0, 2.0, 3.0),
            UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3),
        ),
        state: TrackingState::Tracking,
    };
    vec![
        (
            "stereo",
            Payload::Stereo(Arc::new(StereoFrame {
                index: 0,
                timestamp: 0.5,
                left: img.clone(),
                right: img.clone(),
                calib: calib(),
                left_mask: Some(Mask {
                    width: 4,
                    height: 2,
                    data: vec![1; 8],
                }),
                right_mask: None,
            })),
        ),
        ("image", Payload::Image(img)),
        (
            "disparity",
            Payload::Disparity(Arc::new(DisparityMap {
                map: map.clone(),
                calib: calib(),
            })),
        ),
        (
            "depth",
            Payload::Depth(Arc::new(DepthMap {
                map,
                calib: calib(),
            })),
        ),
        (
            "vertices",
            Payload::VertexMap(Arc::new(VertexMap {
                width: 2,
                height: 1,
                points: vec![[0.0, 0.0, 50.0], [f32::NAN; 3]],
            })),
        ),
        (
            "normals",
            Payload::NormalMap(Arc::new(NormalMap {
                width: 2,
                height: 1,
                normals: vec![[0.0, 0.0, -1.0], [f32::NAN; 3]],
            })),
        ),
        (
            "features",
            Payload::Features(Arc::new(Features {
                keypoints: vec![Keypoint {
                    x: 1.0,
                    y: 1.0,
                    size: 7.0,
                    ..Default::default()
                }],
                descriptors: Descriptors::Binary256(vec![[0; 4]]),
                points: Some(vec![[0.0, 0.0, 40.0]]),
                sampler: None,
            })),
        ),
        (
            "matches",
            Payload::Matches(Arc::new(Matches {
                pairs: vec![Match {
                    query: 0,
                    train: 0,
                    distance: 3.0,
                }],
                query_xy: vec![[1.0, 1.0]],
                train_xy: vec![[2.0, 1.0]],
                query_points: vec![[0.0, 0.0, 50.0]],
                train_points: vec![[1.0, 0.0, 50.0]],
            })),
        ),
        ("pose", Payload::Pose(Arc::new(pose))),
        (
            "graph",
            Payload::DeformationGraph(Arc::new(DeformationGraph {
                nodes: vec![[0.0; 3], [5.0, 0.0, 0.0]],
                affines: vec![[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]; 2],
                translations: vec![[0.0; 3]; 2],
                edges: vec![[0, 1]],
            })),
        ),
        (
            "model",
            Payload::Model(Arc::new(SurfelModel {
                positions: vec![[0.0; 3]],
                normals: vec![[0.0, 0.0, -1.0]],
                colors: vec![[200, 100, 100]],
                weights: vec![1.0],
                timestamps: vec![0],
                stability: vec![1.0],
                ids: vec![0],
            })),
        ),
        (
            "mesh",
            Payload::Mesh(Arc::new(Mesh {
                vertices: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                normals: None,
                colors: Some(vec![[255, 0, 0]; 3]),
                triangles: vec![[0, 1, 2]],
            })),
        ),
        (
            "cloud",
            Payload::PointCloud(Arc::new(PointCloud {
                positions: vec![[1.0; 3]],
                colors: None,
            })),
        ),
        (
            "metrics",
            Payload::Metrics(Arc::new(Metrics {
                values: BTreeMap::from([("depth.mae_mm".to_owned(), 0.25)]),
            })),
        ),
    ]
}

#[test]
fn every_payload_type_records_and_verifies() {
    let payloads = all_payloads();
    // Every port type is covered.
    let mut types: Vec<PortType> = payloads.iter().map(|(_, p)| p.port_type()).collect();
    types.sort();
    types.dedup();
    assert_eq!(types.len(), PortType::ALL.len());

    let dir = common::tmp_dir("recorder");
    let rrd = dir.join("all.rrd");
    let mut rec = Recorder::open(&RerunMode::Save(rrd.clone()), "payloads")
        .unwrap()
        .unwrap();
    for frame in 0..2u64 {
        rec.begin_frame(frame, Some(frame as f64 * 0.1));
        for (name, p) in &payloads {
            rec.log_payload(&format!("node/{name}"), p).unwrap();
        }
        rec.log_timing("node", 1.5).unwrap();
    }
    rec.flush().unwrap();
    drop(rec);
    assert!(std::fs::metadata(&rrd).unwrap().len() > 0);

    let Some(print) = common::rerun_verified(&rrd) else {
        return;
    };
    let text = print("-v");
    for needle in [
        "/node/stereo/left@Pinhole:image_from_camera",
        "/node/stereo/left@Image:buffer",
        "/node/stereo/right@Transform3D:translation",
        "/node/image@Image:buffer",
        "/node/disparity@DepthImage:buffer",
        "/node/depth@DepthImage:meter",
        "/node/depth@Pinhole:image_from_camera",
        "/node/vertices@Points3D:positions",
        "/node/normals@Image:buffer",
        "/node/features@Points2D:positions",
        "/node/features/points3d@Points3D:positions",
        "/node/matches@LineStrips2D:strips",
        "/node/pose@Transform3D:mat3x3",
        "/node/pose_trajectory@LineStrips3D:strips",
        "/node/graph/nodes@Points3D:positions",
        "/node/graph/edges@LineStrips3D:strips",
        "/node/model@Points3D:colors",
        "/node/mesh@Mesh3D:triangle_indices",
        "/node/cloud@Points3D:positions",
        "/node/metrics/depth.mae_mm@Scalars:scalars",
        "/timing/node@Scalars:scalars",
    ] {
        assert!(text.contains(needle), "`{needle}` not in the recording");
    }
}
