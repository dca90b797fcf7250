//! Tests of [`super`]: anchoring through the warp, persistence, matching, refinement, the depth
//! reads and bad parameters.
#![allow(clippy::unwrap_used)]
use super::*;
use misslam_framework::Keypoint;

/// A 320x240 camera with f = 300 px.
fn camera() -> Intrinsics {
    Intrinsics {
        fx: 300.0,
        fy: 300.0,
        cx: 160.0,
        cy: 120.0,
        width: 320,
        height: 240,
    }
}

fn binding(node: u32) -> Binding {
    let mut b = Binding {
        nodes: [0; misslam_deformation_ed::graph::MAX_K],
        weights: [0.0; misslam_deformation_ed::graph::MAX_K],
        len: 1,
        ..Binding::EMPTY
    };
    b.nodes[0] = node;
    b.weights[0] = 1.0;
    b
}

/// Keypoints at camera-frame `points` (projected by `k`), descriptor i = [i; 4] * a pattern.
fn features(points: &[[f32; 3]], k: &Intrinsics) -> Features {
    Features {
        keypoints: points
            .iter()
            .map(|p| Keypoint {
                x: (k.fx * p[0] as f64 / p[2] as f64 + k.cx) as f32,
                y: (k.fy * p[1] as f64 / p[2] as f64 + k.cy) as f32,
                size: 31.0,
                angle: 0.0,
                response: 1.0,
                octave: 0,
            })
            .collect(),
        descriptors: Descriptors::Binary256(
            (0..points.len() as u64)
                .map(|i| [i.wrapping_mul(0x9E37_79B9_7F4A_7C15), !i, i << 7, i ^ 0xFF])
                .collect(),
        ),
        points: Some(points.to_vec()),
        sampler: None,
    }
}

#[test]
fn keypoints_anchor_through_the_warp_and_match_their_moved_selves() {
    let k = camera();
    // Surfels on the plane z = 60 every 1 mm; the live model is the canonical one shifted by
    // (0.5, 0, 0) with A = 2 I (so A^-1 maps a live offset back at half length).
    let mut canon = Vec::new();
    for y in -10..=10 {
        for x in -10..=10 {
            canon.push(Vector3::new(x as f64, y as f64, 60.0));
        }
    }
    let shift = Vector3::new(0.5, 0.0, 0.0);
    let live: Vec<Vector3<f64>> = canon.iter().map(|c| c + shift).collect();
    let bindings: Vec<Binding> = (0..canon.len() as u32).map(binding).collect();
    let a_inv = Matrix3::identity() * 0.5;
    // The warp of a point bound to surfel s: A = 2 I about the surfel.
    let warp = |v: &Vector3<f64>, b: &Binding| {
        let s = b.nodes[0] as usize;
        live[s] + (v - canon[s]) * 2.0
    };
    // Three keypoints on the model, one 5 mm in front of it (not anchored).
    let pts = [
        [0.8f32, 0.3, 60.0],
        [-3.6, 2.1, 60.0],
        [4.2, -5.4, 60.0],
        [1.0, 1.0, 55.0],
    ];
    let pose = Isometry3::identity();
    let mut scratch = AnchorScratch::default();
    let normals = vec![Vector3::z(); live.len()];
    let a = anchor(
        &features(&pts, &k),
        &pose,
        &live,
        &normals,
        &canon,
        &bindings,
        |_| a_inv,
        warp,
        1.0,
        None,
        &mut scratch,
    );
    assert_eq!(a.len(), 3);
    // The binned search finds what a scan of every surfel finds, on points around cell
    // corners and beyond the radius (the scratch reused from the call above).
    let probes: Vec<[f32; 3]> = (0..200)
        .map(|i| {
            let t = i as f32 * 0.37;
            [
                (t.sin() * 9.7),
                (t * 1.3).cos() * 9.9,
                60.0 + (t * 0.7).sin() * 1.2,
            ]
        })
        .collect();
    // (Against the canonical grid itself: surfels on cell corners, so the nearest is often
    // in a neighbouring cell.)
    let b = anchor(
        &features(&probes, &k),
        &pose,
        &canon,
        &[],
        &canon,
        &bindings,
        |_| Matrix3::identity(),
        |v: &Vector3<f64>, _: &Binding| *v,
        1.0,
        None,
        &mut scratch,
    );
    let mut found = 0;
    for q in &probes {
        let q = Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64);
        let nearest = (0..canon.len())
            .filter(|&s| (canon[s] - q).norm() <= 1.0)
            .min_by(|&x, &y| (canon[x] - q).norm().total_cmp(&(canon[y] - q).norm()));
        if let Some(s) = nearest {
            // Under the identity warp the anchor is the probe itself, bound to the nearest
            // surfel (ties may pick either).
            assert!((b.canon[found] - q).norm() < 1e-12, "probe {q:?}");
            let picked = b.bindings[found].nodes[0] as usize;
            assert!(
                ((canon[picked] - q).norm() - (canon[s] - q).norm()).abs() < 1e-12,
                "probe {q:?}"
            );
            found += 1;
        }
    }
    assert_eq!(found, b.len());
    assert!(found > 50 && found < 200, "{found} of 200 probes anchored");
    // (0.8, 0.3): closest live surfel (0.5, 0) = canonical (0, 0); canonical anchor
    // (0, 0) + 0.5 * (0.3, 0.3).
    assert!((a.canon[0] - Vector3::new(0.15, 0.15, 60.0)).norm() < 1e-6);
    assert_eq!(a.bindings[0].nodes[0], (10 * 21 + 10) as u32);

    // The next frame: the same keypoints moved by 0.4 mm (and listed in another order),
    // plus the last one 20 mm away (a wrong match, beyond max_jump_mm).
    let moved = [[4.6f32, -5.4, 60.0], [1.2, 0.3, 60.0], [-3.2, 2.1, 60.0]];
    let mut f = features(&moved, &k);
    if let Descriptors::Binary256(d) = &mut f.descriptors {
        d.swap(0, 2); // moved[0] is pts[2]: its descriptor is [2]
        d.swap(1, 2); // moved[1] is pts[0], moved[2] is pts[1]
    }
    let p = CorrParams {
        points: PointSource::Stereo,
        ..CorrParams::default()
    };
    let mut rs = RefineScratch::default();
    let c = correspondences(&f, &a, &pose, &k, (&[], &[]), &p, &mut rs).unwrap();
    assert_eq!(c.len(), 3);
    for corr in &c {
        // Each target is its anchor's live point moved by 0.4 mm in x.
        let i = a.canon.iter().position(|x| *x == corr.point).unwrap();
        assert!((corr.target - (a.live[i] + Vector3::new(0.4, 0.0, 0.0))).norm() < 1e-5);
    }
    // From the depth instead: a depth map of the plane z = 60.5 gives each target the point
    // of that plane on the keypoint's ray.
    let vertices: Vec<[f32; 3]> = (0..k.width * k.height)
        .map(|i| {
            let (u, v) = ((i % k.width) as f64, (i / k.width) as f64);
            let z = 60.5;
            [
                ((u - k.cx) / k.fx * z) as f32,
                ((v - k.cy) / k.fy * z) as f32,
                z as f32,
            ]
        })
        .collect();
    let from_depth = CorrParams::default();
    assert_eq!(from_depth.points, PointSource::Depth);
    let d = correspondences(&f, &a, &pose, &k, (&vertices, &[]), &from_depth, &mut rs).unwrap();
    assert_eq!(d.len(), 3);
    for (corr, stereo) in d.iter().zip(&c) {
        let want = stereo.target * (60.5 / stereo.target.z);
        assert!(
            (corr.target - want).norm() < 1e-3,
            "{:?} vs {want:?}",
            corr.target
        );
    }
    // A jump beyond max_jump_mm is refused.
    let far = CorrParams {
        max_jump_mm: 0.3,
        ..p.clone()
    };
    assert!(
        correspondences(&f, &a, &pose, &k, (&[], &[]), &far, &mut rs)
            .unwrap()
            .is_empty()
    );
    // Descriptors of another kind between frames are an error, not silent garbage.
    let mut surf = f.clone();
    surf.descriptors = Descriptors::Float64(vec![[0.0; 64]; 3]);
    assert!(correspondences(&surf, &a, &pose, &k, (&[], &[]), &p, &mut rs).is_err());
}

#[test]
fn matched_anchors_persist_with_their_first_canonical_point() {
    use misslam_deformation_ed::graph::GraphParams;
    let k = camera();
    // A still plane of surfels (z = 60, every mm) under an identity warp.
    let mut canon = Vec::new();
    for y in -10..=10 {
        for x in -10..=10 {
            canon.push(Vector3::new(x as f64, y as f64, 60.0));
        }
    }
    let graph = EdGraph::from_points(
        &canon,
        GraphParams {
            spacing: 4.0,
            ..Default::default()
        },
    )
    .unwrap();
    let bindings = graph.bind_all(&canon);
    let normals = vec![Vector3::z(); canon.len()];
    let pose = Isometry3::identity();
    // Keypoint i of frame n: A and B slide 0.4 mm in x a frame; C is seen on frame 0 only,
    // D on frame 1 only (descriptors by index: A 0, B 1, C and D 2, far apart).
    let frame = |n: usize| -> Features {
        let s = 0.4 * n as f32;
        let pts: Vec<[f32; 3]> = match n {
            0 => vec![[0.8, 0.3, 60.0], [-3.6, 2.1, 60.0], [4.2, -5.4, 60.0]],
            1 => vec![
                [0.8 + s, 0.3, 60.0],
                [-3.6 + s, 2.1, 60.0],
                [-6.0, -6.0, 60.0],
            ],
            _ => vec![[0.8 + s, 0.3, 60.0], [-3.6 + s, 2.1, 60.0]],
        };
        features(&pts, &k)
    };
    let run = |keep_frames: u32, max_anchors: usize| {
        let p = CorrParams {
            points: PointSource::Stereo,
            keep_frames,
            max_anchors,
            ..CorrParams::default()
        };
        let mut t = CorrTracker::default();
        // One frame: match, then anchor; returns the correspondences.
        let step = |t: &mut CorrTracker, n: u64, f: Option<&Features>| {
            let c = t
                .correspondences(n, f, &pose, &k, (&[], &[]), &graph, &p)
                .unwrap();
            t.anchor(
                n,
                f,
                false,
                &pose,
                &canon,
                &normals,
                &canon,
                &bindings,
                &graph,
                &[],
                &k,
                &p,
            );
            c
        };
        let mut counts = Vec::new();
        let mut corrs = Vec::new();
        for n in 0..3u64 {
            corrs = step(&mut t, n, Some(&frame(n as usize)));
            counts.push(t.anchors());
        }
        // Six frames with no keypoints.
        for n in 3..9u64 {
            step(&mut t, n, None);
            counts.push(t.anchors());
        }
        // Frame 9: new tissue, keypoint E, far from the others.
        step(&mut t, 9, Some(&features(&[[-7.0, 7.0, 60.0]], &k)));
        counts.push(t.anchors());
        let last_seen = t.anchors.last_seen.clone();
        (corrs, counts, last_seen)
    };
    let x_of = |corrs: &[Correspondence], target_x: f64| {
        corrs
            .iter()
            .find(|c| (c.target.x - target_x).abs() < 1e-4)
            .map(|c| c.point.x)
            .unwrap()
    };
    // Persistent: on frame 2, A is asked to go from where it was anchored on frame 0.
    let (corrs, counts, _) = run(5, 100);
    assert_eq!(corrs.len(), 2);
    assert!((x_of(&corrs, 1.6) - 0.8).abs() < 1e-4);
    assert!((x_of(&corrs, -2.8) + 3.6).abs() < 1e-4);
    // Frame 0: A, B, C. Frame 1: A and B matched and kept, C dropped (never matched), D
    // added. Frame 2: D dropped. Then A and B stay until unmatched for more than 5 frames;
    // frame 9 adds E.
    assert_eq!(counts, vec![3, 3, 2, 2, 2, 2, 2, 2, 0, 1]);
    // Frame to frame: from where it was on frame 1.
    let (corrs, counts, _) = run(0, 100);
    assert!((x_of(&corrs, 1.6) - 1.2).abs() < 1e-4);
    assert_eq!(counts[..3], [3, 3, 2]);
    assert_eq!(counts[3], 0);
    // A cap of 2: on frame 1 A and B (matched) stay and D (new) goes. On frame 9, with A and B
    // still within `keep_frames` but unseen since frame 2, the new tissue's E gets its anchor.
    let (_, counts, last_seen) = run(20, 2);
    assert_eq!(counts, vec![2, 2, 2, 2, 2, 2, 2, 2, 2, 2]);
    assert!(last_seen.contains(&9), "{last_seen:?}");
}

#[test]
fn anchors_sit_on_the_surface_and_the_warp_carries_them_onto_it() {
    use misslam_deformation_ed::graph::GraphParams;
    let k = camera();
    // Surfels on the plane z = 60 every 1.5 mm, bound to a graph whose nodes carry different
    // affines (a stretch growing with x, a shear, a translation): one linear step through
    // the blended A^-1 misses the keypoint.
    let mut canon = Vec::new();
    for y in -4..=4 {
        for x in -4..=4 {
            canon.push(Vector3::new(1.5 * x as f64, 1.5 * y as f64, 60.0));
        }
    }
    let mut graph = EdGraph::from_points(
        &canon,
        GraphParams {
            spacing: 4.0,
            ..Default::default()
        },
    )
    .unwrap();
    for (j, g) in graph.nodes().to_vec().iter().enumerate() {
        let s = 1.0 + 0.08 * g.x;
        let t = 1.0 - 0.06 * g.y;
        graph.warp[j] = [
            s,
            0.05 * g.y,
            0.0,
            0.3,
            0.04 * g.x,
            t,
            0.0,
            -0.2,
            0.0,
            0.0,
            1.0,
            0.1,
        ];
    }
    let bindings = graph.bind_all(&canon);
    let (mut live, mut normals) = (Vec::new(), Vec::new());
    let canon_n = vec![Vector3::z(); canon.len()];
    graph.deform(&canon, Some(&canon_n), &bindings, &mut live, &mut normals);
    let nm = graph.normal_matrices();
    // Keypoints 0.3 mm in front of the live surface, between surfels.
    let on_surface: Vec<Vector3<f64>> = [(0.4, 0.3), (-2.6, 1.7), (3.1, -2.4)]
        .iter()
        .map(|&(u, v)| {
            let c = Vector3::new(u, v, 60.0);
            let s = (0..canon.len())
                .min_by(|&a, &b| (canon[a] - c).norm().total_cmp(&(canon[b] - c).norm()))
                .unwrap();
            graph.warp_point(&c, &bindings[s])
        })
        .collect();
    let pts: Vec<[f32; 3]> = on_surface
        .iter()
        .map(|p| {
            let q = p - Vector3::z() * 0.3;
            [q.x as f32, q.y as f32, q.z as f32]
        })
        .collect();
    let pose = Isometry3::identity();
    let anchored = |steps_ok: bool| {
        anchor(
            &features(&pts, &k),
            &pose,
            &live,
            &normals,
            &canon,
            &bindings,
            |s| local_inverses(&bindings[s], &nm).0,
            |v: &Vector3<f64>, b: &Binding| {
                if steps_ok {
                    graph.warp_point(v, b)
                } else {
                    // A warp the fixed-point steps cannot follow (it doubles every offset).
                    graph.warp_point(v, b) * 2.0
                }
            },
            2.0,
            None,
            &mut AnchorScratch::default(),
        )
    };
    let a = anchored(true);
    assert_eq!(a.len(), 3);
    for (i, c) in a.canon.iter().enumerate() {
        let w = graph.warp_point(c, &a.bindings[i]);
        // The warp carries the anchor onto its live point, which lies on the surface (the
        // live normal is the plane's, turned by the affines): within the tolerance.
        assert!(
            (w - a.live[i]).norm() <= ANCHOR_TOLERANCE_MM,
            "{i}: {w:?} vs {:?}",
            a.live[i]
        );
        let s = (0..live.len())
            .min_by(|&x, &y| (live[x] - w).norm().total_cmp(&(live[y] - w).norm()))
            .unwrap();
        let off = normals[s].dot(&(w - live[s]));
        assert!(off.abs() < 0.02, "{i}: {off} mm off the tangent plane");
    }
    // One linear step alone would have missed by more than the tolerance.
    let missed = (0..a.len())
        .map(|i| {
            let s = (0..live.len())
                .min_by(|&x, &y| {
                    (live[x] - a.live[i])
                        .norm()
                        .total_cmp(&(live[y] - a.live[i]).norm())
                })
                .unwrap();
            let c = canon[s] + local_inverses(&bindings[s], &nm).0 * (a.live[i] - live[s]);
            (graph.warp_point(&c, &bindings[s]) - a.live[i]).norm()
        })
        .fold(0.0f64, f64::max);
    assert!(
        missed > 1.5 * ANCHOR_TOLERANCE_MM,
        "one step misses by {missed}"
    );
    // Anchors the warp cannot carry onto their keypoints are dropped.
    assert_eq!(anchored(false).len(), 0);
}

#[test]
fn a_refined_match_reads_its_point_between_depth_pixels() {
    let k = Intrinsics {
        fx: 100.0,
        fy: 100.0,
        cx: 2.0,
        cy: 2.0,
        width: 5,
        height: 4,
    };
    // A plane z = 50 + x, and one pixel 3 mm in front of it (an edge).
    let mut v: Vec<[f32; 3]> = (0..20)
        .map(|i| {
            let (x, y) = ((i % 5) as f32, (i / 5) as f32);
            [x, y, 50.0 + x]
        })
        .collect();
    let at = |v: &[[f32; 3]], x, y| vertex_at(v, &k, [x, y], 2.0);
    let p = at(&v, 1.25, 2.5).unwrap();
    assert!((p - Vector3::new(1.25, 2.5, 51.25)).norm() < 1e-6, "{p}");
    v[3 * 5 + 4][2] -= 3.0;
    assert!(at(&v, 3.5, 2.5).is_none(), "across the edge");
    assert!(at(&v, 2.5, 2.5).is_some());
    v[0] = [f32::NAN; 3];
    assert!(at(&v, 0.5, 0.5).is_none(), "a hole");
    // The last row and column have no pixel beyond them; a map of another size is refused.
    assert!(at(&v, 4.0, 1.0).is_none() && at(&v, 1.0, 3.0).is_none());
    assert!(vertex_at(&v[..19], &k, [1.0, 1.0], 2.0).is_none());
}

#[test]
fn bad_parameters_are_named() {
    let p = CorrParams {
        radius_px: 0.0,
        ..CorrParams::default()
    };
    assert!(p.validate().unwrap_err().contains("radius_px"));
    let p = CorrParams {
        ratio: 1.5,
        ..CorrParams::default()
    };
    assert!(p.validate().unwrap_err().contains("ratio"));
    let p = CorrParams {
        max_anchors: 0,
        ..CorrParams::default()
    };
    assert!(p.validate().unwrap_err().contains("max_anchors"));
}
