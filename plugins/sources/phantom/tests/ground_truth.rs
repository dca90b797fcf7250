//! The phantom's ground truth checked against independent computations: the GT disparity maps
//! left pixels onto right pixels of the same colour; the GT mesh ray-cast from the GT pose gives
//! the GT depth; the GT rest-point correspondences land on the pixels that see them.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

use misslam_framework::nalgebra::{Point3, Vector3};
use misslam_source_phantom::mesh_input::encode_npy_frames;
use misslam_source_phantom::scene::{Scene, Trajectory};
use misslam_source_phantom::{Params, Phantom, PhantomFrame};

fn noise_free(scene: Scene) -> Params {
    Params {
        scene,
        width: 320,
        height: 240,
        focal_px: 350.0,
        trajectory: Trajectory::Sweep,
        tool_press_mm: 2.0,
        specular: 0.0,
        vignetting: 0.0,
        noise_sigma: 0.0,
        ..Params::default()
    }
}

fn render(p: Params, frame: u64) -> (Phantom, PhantomFrame) {
    let mut ph = Phantom::new(p, 7).unwrap();
    let f = ph.render(frame).unwrap();
    (ph, f)
}

#[test]
fn gt_disparity_maps_left_pixels_onto_right_pixels_of_the_same_colour() {
    for scene in [Scene::Heart, Scene::Stomach] {
        // Frame 75 = 2.5 s: heartbeat, breathing, tool press and sweep all under way.
        let (_, f) = render(noise_free(scene), 75);
        let (w, h) = (f.depth.map.width as usize, f.depth.map.height as usize);
        let (l, r) = (&f.stereo.left.data, &f.stereo.right.data);
        let mut errors = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let d = f.disparity.map.data[y * w + x];
                if !d.is_finite() {
                    continue;
                }
                // Only where the partner lands within 0.05 px of a right pixel centre.
                let xr = x as f32 - d;
                let xi = xr.round();
                if (xr - xi).abs() > 0.05 || xi < 0.0 || xi >= w as f32 {
                    continue;
                }
                for k in 0..3 {
                    let a = l[(y * w + x) * 3 + k] as f32;
                    let b = r[(y * w + xi as usize) * 3 + k] as f32;
                    errors.push((a - b).abs());
                }
            }
        }
        assert!(
            errors.len() > 3 * 5_000,
            "{scene:?}: only {} samples",
            errors.len()
        );
        errors.sort_by(f32::total_cmp);
        let mean = errors.iter().sum::<f32>() / errors.len() as f32;
        let p99 = errors[errors.len() * 99 / 100];
        println!("{scene:?}: photometric error through GT disparity: mean {mean:.3}, p99 {p99} levels, {} samples", errors.len());
        // Tolerance: the partner may sit 0.05 px off and occluded pixels are included; the
        // texture changes by at most a few levels per pixel.
        assert!(
            mean < 0.6 && p99 <= 4.0,
            "{scene:?}: mean {mean:.3}, p99 {p99} levels over {} samples",
            errors.len()
        );
    }
}

/// Nearest intersection of a ray from the origin along `dir` with a triangle (Moller-Trumbore).
fn ray_triangle(
    dir: Vector3<f64>,
    a: Vector3<f64>,
    b: Vector3<f64>,
    c: Vector3<f64>,
) -> Option<f64> {
    let (e1, e2) = (b - a, c - a);
    let pv = dir.cross(&e2);
    let det = e1.dot(&pv);
    if det.abs() < 1e-12 {
        return None;
    }
    let tv = -a;
    let u = tv.dot(&pv) / det;
    let qv = tv.cross(&e1);
    let v = dir.dot(&qv) / det;
    let t = e2.dot(&qv) / det;
    (u >= -1e-9 && v >= -1e-9 && u + v <= 1.0 + 1e-9 && t > 0.0).then_some(t)
}

#[test]
fn gt_mesh_ray_cast_from_gt_pose_gives_gt_depth() {
    let (_, f) = render(
        Params {
            mesh_step_mm: 2.0,
            ..noise_free(Scene::Kidney)
        },
        40,
    );
    let c = f.depth.calib;
    let camera_from_world = f.pose.world_from_camera.inverse();
    let verts: Vec<Vector3<f64>> = f
        .mesh
        .vertices
        .iter()
        .map(|v| (camera_from_world * Point3::new(v[0] as f64, v[1] as f64, v[2] as f64)).coords)
        .collect();
    let (w, h) = (c.width as usize, c.height as usize);
    let mut checked = 0;
    for y in (3..h).step_by(23) {
        for x in (5..w).step_by(29) {
            let dir = Vector3::new((x as f64 - c.cx) / c.fx, (y as f64 - c.cy) / c.fy, 1.0);
            let mut best = f64::INFINITY;
            for t in &f.mesh.triangles {
                if let Some(s) = ray_triangle(
                    dir,
                    verts[t[0] as usize],
                    verts[t[1] as usize],
                    verts[t[2] as usize],
                ) {
                    best = best.min(s);
                }
            }
            let gt = f.depth.map.data[y * w + x] as f64;
            if best.is_finite() {
                // dir has z = 1, so the ray parameter is the depth. f32 rendering: 1e-3 mm.
                assert!(
                    (best - gt).abs() < 1e-3,
                    "pixel ({x},{y}): ray {best}, GT {gt}"
                );
                // Disparity agrees with depth.
                let d = f.disparity.map.data[y * w + x] as f64;
                assert!((c.fx * c.baseline_mm / (d + c.doffs()) - gt).abs() < 1e-3);
                checked += 1;
            } else {
                assert!(
                    gt.is_nan(),
                    "pixel ({x},{y}) sees nothing but has GT depth {gt}"
                );
            }
        }
    }
    assert!(checked > 80, "{checked}");
}

#[test]
fn gt_correspondences_land_on_the_pixels_that_see_them() {
    let p = noise_free(Scene::Heart);
    let (ph, f) = render(p, 60);
    let (nx, ny) = ph.grid().unwrap();
    let rest = ph.rest_vertices();
    let step = [
        (rest[1][0] - rest[0][0]) as f64,
        (rest[nx][1] - rest[0][1]) as f64,
    ];
    let origin = [rest[0][0] as f64, rest[0][1] as f64];
    let c = f.depth.calib;
    let camera_from_world = f.pose.world_from_camera.inverse();
    let (w, h) = (c.width as usize, c.height as usize);
    let mut checked = 0;
    for y in (0..h).step_by(7) {
        for x in (0..w).step_by(11) {
            let r = f.rest_points.points[y * w + x];
            if !r[0].is_finite() {
                continue;
            }
            // The rest surface is a height field over the grid: find the cell and the triangle
            // holding (r.x, r.y), and its barycentric weights there.
            let gx = (r[0] as f64 - origin[0]) / step[0];
            let gy = (r[1] as f64 - origin[1]) / step[1];
            let (i, j) = (
                (gx.floor() as usize).min(nx - 2),
                (gy.floor() as usize).min(ny - 2),
            );
            let (u, v) = (gx - i as f64, gy - j as f64);
            let (a, b, cc, d) = (
                j * nx + i,
                j * nx + i + 1,
                (j + 1) * nx + i,
                (j + 1) * nx + i + 1,
            );
            // Triangles [a, b, d] (u >= v) and [a, d, c] (v > u), as the phantom builds them.
            let weights: [(usize, f64); 3] = if u >= v {
                [(a, 1.0 - u), (b, u - v), (d, v)]
            } else {
                [(a, 1.0 - v), (d, u), (cc, v - u)]
            };
            let mut q = Vector3::zeros();
            for (vi, wgt) in weights {
                let m = f.mesh.vertices[vi];
                q += wgt * Vector3::new(m[0] as f64, m[1] as f64, m[2] as f64);
            }
            let pc = camera_from_world * Point3::from(q);
            let (px, py) = (c.fx * pc.x / pc.z + c.cx, c.fy * pc.y / pc.z + c.cy);
            assert!(
                (px - x as f64).abs() < 0.02 && (py - y as f64).abs() < 0.02,
                "pixel ({x},{y}) -> ({px:.4},{py:.4})"
            );
            let gt = f.depth.map.data[y * w + x] as f64;
            assert!(
                (pc.z - gt).abs() < 2e-3,
                "pixel ({x},{y}): z {} vs GT {gt}",
                pc.z
            );
            checked += 1;
        }
    }
    assert!(checked > 500, "{checked}");
}

#[test]
fn deterministic_from_the_seed() {
    let p = Params {
        width: 64,
        height: 48,
        focal_px: 70.0,
        ..Params::default()
    };
    let (_, a) = render(p.clone(), 3);
    let (_, b) = render(p.clone(), 3);
    assert_eq!(a.stereo.left.data, b.stereo.left.data);
    assert_eq!(a.stereo.right.data, b.stereo.right.data);
    let (_, c) = render(
        Params {
            seed: Some(99),
            ..p
        },
        3,
    );
    assert_ne!(a.stereo.left.data, c.stereo.left.data);
}

#[test]
fn sequence_ends_and_bad_parameters_name_the_field() {
    let mut ph = Phantom::new(
        Params {
            frames: 2,
            width: 32,
            height: 24,
            focal_px: 35.0,
            ..Params::default()
        },
        0,
    )
    .unwrap();
    assert!(ph.render(1).is_some());
    assert!(ph.render(2).is_none());
    let e = Phantom::new(
        Params {
            baseline_mm: -5.0,
            ..Params::default()
        },
        0,
    )
    .err()
    .unwrap();
    assert_eq!(e, "`baseline_mm` must be positive");
    let e = Phantom::new(
        Params {
            distance_mm: 20.0,
            ..Params::default()
        },
        0,
    )
    .err()
    .unwrap();
    assert!(e.starts_with("`distance_mm` must exceed 30 mm"), "{e}");
    // A NaN or an infinity anywhere, or a value out of its range, names its field.
    let d = Params::default;
    for (p, want) in [
        (
            Params {
                distance_mm: f32::INFINITY,
                ..d()
            },
            "`distance_mm` must be a finite number, got inf",
        ),
        (
            Params {
                sweep_mm: f32::NAN,
                ..d()
            },
            "`sweep_mm` must be a finite number, got NaN",
        ),
        (
            Params {
                heartbeat_mm: Some(f32::NAN),
                ..d()
            },
            "`heartbeat_mm` must be a finite",
        ),
        (
            Params {
                breathing_mm: Some(f32::INFINITY),
                ..d()
            },
            "`breathing_mm` must be a finite",
        ),
        (
            Params {
                mesh_rotation_deg: [0.0, f32::NAN, 0.0],
                ..d()
            },
            "`mesh_rotation_deg` must be a finite",
        ),
        (
            Params {
                tool_xy_mm: [f32::NAN, 0.0],
                ..d()
            },
            "`tool_xy_mm` must be a finite",
        ),
        (
            Params {
                specular: f32::NAN,
                ..d()
            },
            "`specular` must be a finite",
        ),
        (
            Params {
                exposure_s: f32::NAN,
                ..d()
            },
            "`exposure_s` must be a finite",
        ),
        (
            Params {
                ambient: 2.0,
                ..d()
            },
            "`ambient` must be in 0..1, got 2",
        ),
        (
            Params {
                vignetting: -0.5,
                ..d()
            },
            "`vignetting` must be in 0..1",
        ),
        (
            Params {
                sweep_period_s: -1.0,
                ..d()
            },
            "`sweep_period_s` must be >= 0",
        ),
        (
            Params {
                shininess: 0.0,
                ..d()
            },
            "`shininess` must be positive",
        ),
        (
            Params {
                vessel_scale_mm: 0.0,
                ..d()
            },
            "`vessel_scale_mm` must be positive",
        ),
        (
            Params {
                tool_radius_mm: f32::INFINITY,
                ..d()
            },
            "`tool_radius_mm` must be positive",
        ),
        (
            Params {
                motion_blur_samples: 0,
                ..d()
            },
            "`motion_blur_samples` must be at least 1",
        ),
        (
            Params {
                trajectory_fps: Some(0.0),
                ..d()
            },
            "`trajectory_fps` must be positive",
        ),
    ] {
        let e = Phantom::new(p, 0).err().unwrap_or_default();
        assert!(e.starts_with(want), "{want}: {e}");
    }
}

#[test]
fn depth_spans_the_hamlyn_like_range() {
    let (_, f) = render(
        Params {
            width: 160,
            height: 120,
            focal_px: 175.0,
            ..Params::default()
        },
        0,
    );
    let valid: Vec<f32> = f
        .depth
        .map
        .data
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    assert_eq!(
        valid.len(),
        f.depth.map.data.len(),
        "the tissue fills the view"
    );
    let (lo, hi) = valid
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(lo > 40.0 && hi < 120.0, "depth {lo}..{hi} mm");
    assert!(hi - lo > 15.0, "the heart bulges: {lo}..{hi} mm");
}

#[test]
fn motion_blur_averages_over_the_exposure() {
    let still = Params {
        width: 96,
        height: 72,
        focal_px: 105.0,
        trajectory: Trajectory::Static,
        heartbeat_mm: Some(0.0),
        breathing_mm: Some(0.0),
        noise_sigma: 0.0,
        ..Params::default()
    };
    // Nothing moves: the blurred image is the sharp one.
    let (_, sharp) = render(still.clone(), 4);
    let (_, blurred) = render(
        Params {
            motion_blur_samples: 5,
            exposure_s: 0.05,
            ..still.clone()
        },
        4,
    );
    assert_eq!(sharp.stereo.left.data, blurred.stereo.left.data);
    // The fast segment: blur lowers the image's gradient energy; GT stays that of mid-exposure.
    let fast = Params {
        trajectory: Trajectory::Fast,
        fast_start_s: 0.0,
        fast_duration_s: 0.4,
        ..still
    };
    let energy = |img: &[u8]| {
        img.chunks_exact(3)
            .collect::<Vec<_>>()
            .windows(2)
            .map(|w| (w[0][1] as i32 - w[1][1] as i32).pow(2) as u64)
            .sum::<u64>()
    };
    let (_, sharp) = render(fast.clone(), 6);
    let (_, blurred) = render(
        Params {
            motion_blur_samples: 8,
            exposure_s: 0.05,
            ..fast
        },
        6,
    );
    assert!(energy(&blurred.stereo.left.data) < energy(&sharp.stereo.left.data));
    assert_eq!(sharp.depth.map.data, blurred.depth.map.data);
}

fn heart_data() -> Option<(std::path::PathBuf, std::path::PathBuf)> {
    let dir =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../../shared/data/heart");
    let (obj, npy) = (dir.join("heart.obj"), dir.join("heart_trajectory.npy"));
    if obj.is_file() && npy.is_file() {
        Some((obj, npy))
    } else {
        println!("skipped: ../shared/data/heart is absent");
        None
    }
}

#[test]
fn heart_mesh_follows_its_trajectory_with_exact_ground_truth() {
    let Some((obj, npy)) = heart_data() else {
        return;
    };
    let p = Params {
        mesh: Some(obj),
        vertex_trajectory: Some(npy),
        width: 160,
        height: 120,
        focal_px: 175.0,
        trajectory: Trajectory::Static,
        noise_sigma: 0.0,
        ..Params::default()
    };
    let mut ph = Phantom::new(p, 3).unwrap();
    let rest = ph.rest_vertices().to_vec();
    // Displacements are those of the data (placing the mesh is a rigid motion): from
    // heart_trajectory.npy, the largest vertex displacement is 0.0884 mm at frame 1 and
    // 1.0167 mm at frame 11.
    for (frame, want) in [(1u64, 0.0884), (11, 1.0167)] {
        let f = ph.render(frame).unwrap();
        let max = f
            .mesh
            .vertices
            .iter()
            .zip(&rest)
            .map(|(a, b)| {
                ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
            })
            .fold(0.0f32, f32::max);
        assert!((max - want).abs() < 2e-3, "frame {frame}: {max} vs {want}");
    }
    // Ray cast of the GT mesh from the GT pose gives the GT depth; correspondences land home.
    let f = ph.render(30).unwrap();
    let c = f.depth.calib;
    let cfw = f.pose.world_from_camera.inverse();
    let to_cam = |v: [f32; 3]| (cfw * Point3::new(v[0] as f64, v[1] as f64, v[2] as f64)).coords;
    let verts: Vec<Vector3<f64>> = f.mesh.vertices.iter().map(|v| to_cam(*v)).collect();
    let tris = ph.triangles();
    let (w, h) = (c.width as usize, c.height as usize);
    let (mut hits, mut checked) = (0, 0);
    for y in (2..h).step_by(9) {
        for x in (3..w).step_by(11) {
            let dir = Vector3::new((x as f64 - c.cx) / c.fx, (y as f64 - c.cy) / c.fy, 1.0);
            let best = tris
                .iter()
                .filter_map(|t| {
                    ray_triangle(
                        dir,
                        verts[t[0] as usize],
                        verts[t[1] as usize],
                        verts[t[2] as usize],
                    )
                })
                .fold(f64::INFINITY, f64::min);
            let gt = f.depth.map.data[y * w + x] as f64;
            if !best.is_finite() {
                assert!(gt.is_nan(), "({x},{y}) sees nothing but has GT {gt}");
                continue;
            }
            assert!((best - gt).abs() < 2e-3, "({x},{y}): ray {best} vs GT {gt}");
            hits += 1;
            // The rest point lies on one rest triangle; the same barycentrics on the deformed
            // mesh give a point that projects onto this pixel.
            let r = f.rest_points.points[y * w + x];
            let r = Vector3::new(r[0] as f64, r[1] as f64, r[2] as f64);
            let mut found = false;
            for t in tris {
                let [a, b, cc] = t.map(|i| {
                    let v = rest[i as usize];
                    Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)
                });
                let (e1, e2, d) = (b - a, cc - a, r - a);
                let n = e1.cross(&e2);
                if n.norm() < 1e-12 || (d.dot(&n) / n.norm()).abs() > 1e-3 {
                    continue;
                }
                let (d00, d01, d11, d20, d21) = (
                    e1.dot(&e1),
                    e1.dot(&e2),
                    e2.dot(&e2),
                    d.dot(&e1),
                    d.dot(&e2),
                );
                let den = d00 * d11 - d01 * d01;
                let (v, wgt) = ((d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den);
                let u = 1.0 - v - wgt;
                if u < -1e-4 || v < -1e-4 || wgt < -1e-4 {
                    continue;
                }
                let q = u * verts[t[0] as usize]
                    + v * verts[t[1] as usize]
                    + wgt * verts[t[2] as usize];
                let (px, py) = (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy);
                if (px - x as f64).abs() < 0.02
                    && (py - y as f64).abs() < 0.02
                    && (q.z - gt).abs() < 2e-3
                {
                    found = true;
                    break;
                }
            }
            assert!(found, "({x},{y}): its rest point does not map back to it");
            checked += 1;
        }
    }
    assert!(
        hits > 50 && checked == hits,
        "{hits} hits, {checked} checked"
    );
}

#[test]
fn a_trajectory_for_another_mesh_is_refused() {
    let dir = std::env::temp_dir().join(format!("misslam-phantom-mesh-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("tri.obj"),
        "v 0 0 0\nv 10 0 0\nv 0 10 0\nf 1 2 3\n",
    )
    .unwrap();
    // A (1, 2, 3) f4 array: two vertices, the mesh has three.
    std::fs::write(dir.join("traj.npy"), encode_npy_frames(1, &[[0.0; 3]; 2])).unwrap();
    let e = Phantom::new(
        Params {
            mesh: Some(dir.join("tri.obj")),
            vertex_trajectory: Some(dir.join("traj.npy")),
            ..Params::default()
        },
        0,
    )
    .err()
    .unwrap();
    assert!(
        e.contains("traj.npy has 2 vertices per frame (1 frames), the mesh")
            && e.ends_with("tri.obj has 3"),
        "{e}"
    );
}

#[test]
fn a_mesh_or_trajectory_far_beyond_an_organ_is_refused_naming_the_position() {
    // A corrupt vertex 54 m off once had the phantom bake its albedo (every 0.1 mm over the
    // mesh's box) for hours; a template is checked the same way (the workspace's
    // `tests/template.rs`).
    let dir = std::env::temp_dir().join(format!("misslam-phantom-stray-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // A 30 x 30 mm sheet of 4 x 4 vertices.
    let grid: Vec<[f32; 3]> = (0..16)
        .map(|i| [10.0 * (i % 4) as f32, 10.0 * (i / 4) as f32, 0.0])
        .collect();
    let mut obj: String = grid
        .iter()
        .map(|v| format!("v {} {} {}\n", v[0], v[1], v[2]))
        .collect();
    for y in 0..3 {
        for x in 0..3 {
            let i = y * 4 + x + 1;
            obj += &format!("f {} {} {} {}\n", i, i + 1, i + 5, i + 4);
        }
    }
    let sheet = dir.join("sheet.obj");
    std::fs::write(&sheet, &obj).unwrap();
    let mut moving: Vec<[f32; 3]> = (0..3)
        .flat_map(|f| grid.iter().map(move |v| [v[0], v[1], 0.3 * f as f32]))
        .collect();
    let good = dir.join("good.npy");
    std::fs::write(&good, encode_npy_frames(3, &moving)).unwrap();
    moving[2 * 16 + 1][2] = -53_816.9;
    let bad = dir.join("bad.npy");
    std::fs::write(&bad, encode_npy_frames(3, &moving)).unwrap();
    let stray = dir.join("stray.obj");
    std::fs::write(&stray, obj.replacen("v 10 0 0", "v 6e19 0 0", 1)).unwrap();
    let open = |mesh: &std::path::Path, trajectory: Option<&std::path::Path>| {
        let p = Params {
            mesh: Some(mesh.to_path_buf()),
            vertex_trajectory: trajectory.map(|t| t.to_path_buf()),
            width: 64,
            height: 48,
            focal_px: 70.0,
            distance_mm: 80.0,
            ..Default::default()
        };
        Phantom::new(p, 0).map(|_| ())
    };
    open(&sheet, Some(&good)).unwrap();
    let e = open(&sheet, Some(&bad)).unwrap_err();
    assert!(
        e.contains("bad.npy") && e.contains("frame 2, vertex 1 ") && e.contains("along z"),
        "{e}"
    );
    let e = open(&stray, None).unwrap_err();
    assert!(e.contains("stray.obj") && e.contains("vertex 1 "), "{e}");
}
