//! `misslam bench runtime-overhead`: the scheduler's own cost per node per frame, measured on
//! graphs of trivial nodes (a source and a chain or a fan of pass-through nodes that only clone
//! an `Arc`), so that what is measured is input gathering, timing, error handling and output
//! checks, not work. The budget is 50 microseconds per node per frame.

use std::path::Path;
use std::time::Instant;

use misslam_framework::graph;
use misslam_framework::{
    BuildContext, Flow, FrameInfo, Image, Inputs, Node, NodeContext, NodeResult, Outputs, PortSpec,
    PortType, Registry, RunOptions, Runtime, TypedPlugin,
};
use serde::Serialize;

#[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema, Default)]
#[serde(deny_unknown_fields)]
struct NoParams {}

struct Source {
    image: std::sync::Arc<Image>,
}

impl Node for Source {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        _: &Inputs,
        out: &mut Outputs,
    ) -> NodeResult<Flow> {
        out.put_arc("image", self.image.clone())?;
        Ok(Flow::Continue)
    }
}

struct Pass;

impl Node for Pass {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inp: &Inputs,
        out: &mut Outputs,
    ) -> NodeResult<Flow> {
        let img = inp.get::<Image>("image")?;
        out.put_arc("image", img.clone())?;
        Ok(Flow::Continue)
    }
}

fn registry() -> Registry {
    let mut r = Registry::new();
    let image = std::sync::Arc::new(Image {
        width: 64,
        height: 48,
        channels: 1,
        data: vec![0; 64 * 48],
    });
    let _ = r.register(TypedPlugin::new(
        "bench.source",
        "a shared image every frame",
        vec![],
        vec![PortSpec::new("image", PortType::Image, "")],
        move |_: NoParams, _: &BuildContext| {
            Ok(Source {
                image: image.clone(),
            })
        },
    ));
    let _ = r.register(TypedPlugin::new(
        "bench.pass",
        "passes its input on",
        vec![PortSpec::new("image", PortType::Image, "")],
        vec![PortSpec::new("image", PortType::Image, "")],
        |_: NoParams, _: &BuildContext| Ok(Pass),
    ));
    r
}

/// One measured configuration.
#[derive(Debug, Serialize)]
pub struct OverheadRow {
    /// `chain` (each node feeds the next) or `fan` (every node reads the source: one level).
    pub shape: String,
    /// Pass-through nodes (the source not counted).
    pub nodes: usize,
    /// Frames run.
    pub frames: u64,
    /// Whether a level's nodes ran in parallel.
    pub parallel: bool,
    /// Wall time per frame, microseconds.
    pub frame_us: f64,
    /// Wall time per node per frame, microseconds (everything: the nodes do no work).
    pub per_node_us: f64,
    /// `per_node_us` / 50 us budget.
    pub budget_ratio: f64,
}

fn graph_text(shape: &str, nodes: usize, parallel: bool) -> String {
    let mut t = format!("[graph]\nname = \"overhead\"\nparallel = {parallel}\n\n[[node]]\nid = \"src\"\nplugin = \"bench.source\"\n");
    for i in 0..nodes {
        let from = if shape == "chain" && i > 0 {
            format!("n{}", i - 1)
        } else {
            "src".into()
        };
        t.push_str(&format!(
            "\n[[node]]\nid = \"n{i}\"\nplugin = \"bench.pass\"\ninputs = {{ image = \"{from}.image\" }}\n"
        ));
    }
    t
}

/// Runs every configuration and returns the rows.
pub fn runtime_overhead(
    nodes: usize,
    frames: u64,
    out_dir: &Path,
) -> Result<Vec<OverheadRow>, String> {
    let reg = registry();
    let mut rows = Vec::new();
    for (shape, parallel) in [("chain", false), ("fan", false), ("fan", true)] {
        let text = graph_text(shape, nodes, parallel);
        let g = graph::parse(Path::new("overhead.toml"), &text, &reg, &[])
            .map_err(|e| e.to_string())?;
        let rt = Runtime::build(g).map_err(|e| e.to_string())?;
        let t = Instant::now();
        let report = rt
            .run(RunOptions {
                out_dir: Some(out_dir.to_owned()),
                frames: Some(frames),
                ..Default::default()
            })
            .map_err(|e| e.to_string())?;
        if let Some(e) = report.error {
            return Err(e.to_string());
        }
        let frame_us = t.elapsed().as_secs_f64() * 1e6 / frames as f64;
        let per_node_us = frame_us / (nodes + 1) as f64;
        rows.push(OverheadRow {
            shape: shape.into(),
            nodes,
            frames,
            parallel,
            frame_us,
            per_node_us,
            budget_ratio: per_node_us / 50.0,
        });
    }
    Ok(rows)
}

/// One phantom configuration's render speed.
#[derive(Debug, Serialize)]
pub struct PhantomRow {
    /// Scene.
    pub scene: String,
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Frames rendered.
    pub frames: u64,
    /// Mean wall time per frame (both views and all GT), ms.
    pub ms_per_frame: f64,
    /// Frames per second.
    pub fps: f64,
}

/// Renders `frames` frames of every scene at 640x480 and 360x288 and times them.
pub fn phantom(frames: u64) -> Result<Vec<PhantomRow>, String> {
    use misslam_source_phantom::scene::Scene;
    let mut rows = Vec::new();
    for (w, h, f) in [(640u32, 480u32, 700.0), (360, 288, 394.0)] {
        for scene in [Scene::Heart, Scene::Liver, Scene::Kidney, Scene::Stomach] {
            let p = misslam_source_phantom::Params {
                scene,
                width: w,
                height: h,
                focal_px: f,
                frames,
                ..Default::default()
            };
            let mut ph = misslam_source_phantom::Phantom::new(p, 0)?;
            let t = Instant::now();
            for i in 0..frames {
                std::hint::black_box(ph.render(i));
            }
            let ms = t.elapsed().as_secs_f64() * 1e3 / frames.max(1) as f64;
            rows.push(PhantomRow {
                scene: format!("{scene:?}").to_lowercase(),
                width: w,
                height: h,
                frames,
                ms_per_frame: ms,
                fps: 1e3 / ms,
            });
        }
    }
    Ok(rows)
}

/// One frame of `misslam bench ed-scaling`.
#[derive(Clone, Debug, serde::Serialize)]
pub struct EdScalingRow {
    /// Frame index.
    pub frame: usize,
    /// Nodes in the map (both solvers grow the same graph).
    pub total_nodes: usize,
    /// Model points in the map.
    pub map_points: usize,
    /// Model points visible this frame.
    pub visible_points: usize,
    /// Nodes the batch solver solved (all).
    pub batch_solved: usize,
    /// Batch solve time, ms.
    pub batch_ms: f64,
    /// Batch: Gauss-Newton / LM iterations run.
    pub batch_iterations: usize,
    /// Batch: assembly time summed over the iterations, ms.
    pub batch_assemble_ms: f64,
    /// Batch: numeric factorisation and triangular solves summed over the iterations, ms.
    pub batch_factor_ms: f64,
    /// Batch: mean distance of every map point from its GT position, mm.
    pub batch_err_mm: f64,
    /// Batch: mean distance from GT over the map points in view this frame, mm.
    pub batch_seen_err_mm: f64,
    /// Nodes the decoupled solver solved (PR plus the PI rings).
    pub decoupled_solved: usize,
    /// Decoupled solve time (both levels), ms.
    pub decoupled_ms: f64,
    /// Decoupled: mean distance of every map point from its GT position, mm.
    pub decoupled_err_mm: f64,
    /// Decoupled: mean distance from GT over the map points in view this frame, mm.
    pub decoupled_seen_err_mm: f64,
}

/// Options of the ED scaling benchmark.
#[derive(Clone, Debug)]
pub struct EdScalingParams {
    /// Frames.
    pub frames: usize,
    /// Camera advance along the strip per frame, mm.
    pub advance_mm: f64,
    /// Node spacing, mm.
    pub spacing_mm: f64,
    /// Model point spacing, mm.
    pub point_step_mm: f64,
    /// Solver iterations per frame.
    pub iterations: usize,
    /// Batch: factorise all 12 unknowns of every node (no elimination of the data-free nodes'
    /// affine parts), to time what that elimination saves.
    pub full_factorisation: bool,
}

impl Default for EdScalingParams {
    fn default() -> Self {
        EdScalingParams {
            frames: 30,
            advance_mm: 110.0,
            spacing_mm: 5.0,
            point_step_mm: 1.5,
            iterations: 3,
            full_factorisation: false,
        }
    }
}

/// The thesis's Fig. 5.9 experiment: a tissue strip 60 mm wide, 60 mm below a camera that moves
/// along it; the map (every point seen so far) and its graph grow each frame while the camera sees
/// a bounded window. The tissue breathes under the camera (a 2.5 mm bump that follows it and
/// pulses) and rests elsewhere. Per frame the batch and the decoupled solver each update their own
/// copy of the warp from the same exact depth (ray-cast analytically), and are scored against the
/// GT position of every map point. Every 15th visible point also gets its exact GT target as a
/// sparse correspondence (what feature matches provide).
pub fn ed_scaling(p: &EdScalingParams) -> Result<Vec<EdScalingRow>, String> {
    use misslam_deformation_ed::observe::visible_points;
    use misslam_deformation_ed::*;
    use misslam_framework::nalgebra::{Isometry3, Translation3, Vector3};
    const Z0: f64 = 60.0;
    const HALF_W: f64 = 30.0;
    let rest_h = |x: f64, y: f64| 2.0 * (x / 15.0).sin() * (y / 20.0).cos();
    let rest_grad = |x: f64, y: f64| {
        (
            2.0 / 15.0 * (x / 15.0).cos() * (y / 20.0).cos(),
            -2.0 / 20.0 * (x / 15.0).sin() * (y / 20.0).sin(),
        )
    };
    // GT displacement (z only) at frame f: a bump centred under the camera.
    let bump = |x: f64, y: f64, cam_x: f64, f: usize| {
        let a = 2.5 * (0.6 + 0.4 * (f as f64 * 0.9).sin());
        a * (-((x - cam_x).powi(2) + y * y) / (2.0 * 15.0f64.powi(2))).exp()
    };
    let bump_grad = |x: f64, y: f64, cam_x: f64, f: usize| {
        let b = bump(x, y, cam_x, f);
        (-b * (x - cam_x) / 225.0, -b * y / 225.0)
    };
    let k = Intrinsics {
        fx: 300.0,
        fy: 300.0,
        cx: 159.5,
        cy: 119.5,
        width: 320,
        height: 240,
    };
    let window = (k.width as f64 / 2.0) / k.fx * (Z0 + 4.0) + 2.0;
    let mut points: Vec<Vector3<f64>> = Vec::new();
    let mut normals: Vec<Vector3<f64>> = Vec::new();
    let mut covered_to = f64::NEG_INFINITY;
    let mut batch_graph: Option<EdGraph> = None;
    let mut dec_graph: Option<EdGraph> = None;
    let mut batch = Solver::default();
    batch.set_full_factorisation(p.full_factorisation);
    let mut dec = DecoupledSolver::default();
    let params = SolverParams {
        max_iterations: p.iterations,
        ..Default::default()
    };
    let gp = GraphParams {
        spacing: p.spacing_mm,
        ..Default::default()
    };
    let mut rows = Vec::new();
    // The first frame sees a longer stretch (so the map starts near 1,000 nodes).
    let start = -(p.advance_mm * 3.0).max(window);
    for f in 0..p.frames {
        let cam_x = f as f64 * p.advance_mm;
        // New map points: everything from the last covered x to the window's far edge.
        let from = if f == 0 { start } else { covered_to };
        let to = cam_x + window;
        let mut x = (from / p.point_step_mm).ceil() * p.point_step_mm;
        let first_new = points.len();
        while x <= to {
            let mut y = -HALF_W;
            while y <= HALF_W {
                let (gx, gy) = rest_grad(x, y);
                points.push(Vector3::new(x, y, Z0 + rest_h(x, y)));
                normals.push(Vector3::new(gx, gy, -1.0).normalize());
                y += p.point_step_mm;
            }
            x += p.point_step_mm;
        }
        covered_to = x;
        let new = &points[first_new..];
        match (&mut batch_graph, &mut dec_graph) {
            (Some(b), Some(d)) => {
                b.grow(new);
                d.grow(new);
            }
            _ => {
                batch_graph = Some(EdGraph::from_points(new, gp.clone())?);
                dec_graph = batch_graph.clone();
            }
        }
        let (Some(bg), Some(dg)) = (batch_graph.as_mut(), dec_graph.as_mut()) else {
            return Err("no graph".into());
        };
        if bg.topology_version() != dg.topology_version() || bg.len() != dg.len() {
            return Err("the two graphs grew differently".into());
        }
        // Bindings of all points against the (grown) graph; both graphs share the topology.
        let bindings = bg.bind_all(&points);
        // The scan: exact ray cast of the deformed strip from the camera at (cam_x, 0, 0).
        let (w, h) = (k.width as usize, k.height as usize);
        let mut verts = vec![[f32::NAN; 3]; w * h];
        let mut norms = vec![[f32::NAN; 3]; w * h];
        for v in 0..h {
            for u in 0..w {
                let (rx, ry) = ((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy);
                let mut z = Z0;
                for _ in 0..30 {
                    let (x, y) = (cam_x + rx * z, ry * z);
                    z = Z0 + rest_h(x, y) + bump(x, y, cam_x, f);
                }
                let (x, y) = (cam_x + rx * z, ry * z);
                if y.abs() > HALF_W {
                    continue;
                }
                let (gx, gy) = rest_grad(x, y);
                let (bx, by) = bump_grad(x, y, cam_x, f);
                let n = Vector3::new(gx + bx, gy + by, -1.0).normalize();
                verts[v * w + u] = [(x - cam_x) as f32, y as f32, z as f32];
                norms[v * w + u] = [n.x as f32, n.y as f32, n.z as f32];
            }
        }
        let pose = Isometry3::from_parts(Translation3::new(cam_x, 0.0, 0.0), Default::default());
        let truth: Vec<Vector3<f64>> = points
            .iter()
            .map(|q| q + Vector3::new(0.0, 0.0, bump(q.x, q.y, cam_x, f)))
            .collect();
        // In view: the true point projects into the image (the strip is a height field, nothing
        // occludes). The rest of the map is unseen: its GT relaxes back to rest as the bump moves
        // on, which no solver can observe, so the whole-map error mixes in that memory.
        let in_view: Vec<usize> = (0..points.len())
            .filter(|&i| {
                let c = truth[i] - Vector3::new(cam_x, 0.0, 0.0);
                let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
                u >= 0.0 && v >= 0.0 && u <= (k.width - 1) as f64 && v <= (k.height - 1) as f64
            })
            .collect();
        let dist =
            |g: &EdGraph, i: usize| (g.warp_point(&points[i], &bindings[i]) - truth[i]).norm();
        let err =
            |g: &EdGraph| (0..points.len()).map(|i| dist(g, i)).sum::<f64>() / points.len() as f64;
        let seen_err = |g: &EdGraph| {
            in_view.iter().map(|&i| dist(g, i)).sum::<f64>() / in_view.len().max(1) as f64
        };
        let mut solve =
            |g: &mut EdGraph, decoupled: bool| -> Result<(usize, f64, usize, Info), String> {
                let vis = visible_points(
                    g, &points, &normals, &bindings, &pose, &k, &verts, &norms, 5.0, 60.0,
                );
                let mut l = ModelSubset::default();
                l.gather(&vis, &points, &normals, &bindings);
                // Sparse correspondences on every 15th visible point (what feature matches give;
                // point-to-plane alone cannot see sliding along the surface).
                let corr: Vec<Correspondence> = vis
                    .iter()
                    .step_by(15)
                    .map(|&i| Correspondence {
                        point: points[i as usize],
                        binding: bindings[i as usize],
                        target: truth[i as usize] - Vector3::new(cam_x, 0.0, 0.0),
                    })
                    .collect();
                let problem = Problem {
                    model: l.view(),
                    scan: Some(Scan {
                        intrinsics: k,
                        vertices: &verts,
                        normals: &norms,
                    }),
                    field: None,
                    correspondences: &corr,
                    pose_prior: pose,
                };
                let mut ps = pose;
                let t = std::time::Instant::now();
                let (solved, info) = if decoupled {
                    dec.solve(g, &mut ps, &problem, &params, &DecoupledParams::default())?;
                    let i = dec.solve_info();
                    (i.pr_nodes + i.pi_solved, i.combined())
                } else {
                    let set = SolveSet::all(g, false);
                    let info = batch.solve(g, &mut ps, &problem, &set, &params)?;
                    (info.solved_nodes, info)
                };
                Ok((solved, t.elapsed().as_secs_f64() * 1e3, vis.len(), info))
            };
        let (bs, bms, nvis, binfo) = solve(bg, false)?;
        let (ds, dms, _, _) = solve(dg, true)?;
        rows.push(EdScalingRow {
            frame: f,
            total_nodes: bg.len(),
            map_points: points.len(),
            visible_points: nvis,
            batch_solved: bs,
            batch_ms: bms,
            batch_iterations: binfo.iterations,
            batch_assemble_ms: binfo.ms_assemble,
            batch_factor_ms: binfo.ms_factor,
            batch_err_mm: err(bg),
            batch_seen_err_mm: seen_err(bg),
            decoupled_solved: ds,
            decoupled_ms: dms,
            decoupled_err_mm: err(dg),
            decoupled_seen_err_mm: seen_err(dg),
        });
    }
    Ok(rows)
}

/// Result of `misslam bench features`.
#[derive(Debug, Serialize)]
pub struct FeaturesBench {
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Keypoints found in the first image.
    pub keypoints: usize,
    /// Keypoints found in the second image.
    pub keypoints2: usize,
    /// Median ORB detect-and-describe time on the first image, ms.
    pub orb_ms: f64,
    /// Median brute-force Hamming 2-NN time, first against second, ms.
    pub knn_ms: Option<f64>,
    /// Matches (ratio 0.8, cross-check) as `[x1, y1, x2, y2]`.
    pub matches: Vec<[f32; 4]>,
}

fn gray_image(path: &Path) -> Result<(u32, u32, Vec<u8>), String> {
    let img = image::open(path)
        .map_err(|e| format!("{}: {e}", path.display()))?
        .to_luma8();
    Ok((img.width(), img.height(), img.into_raw()))
}

/// Runs `f` `repeat` times (at least once) and returns the median wall time, ms.
fn median_ms<E>(repeat: usize, mut f: impl FnMut() -> Result<(), E>) -> Result<f64, E> {
    let mut v = Vec::with_capacity(repeat.max(1));
    for _ in 0..repeat.max(1) {
        let t = Instant::now();
        f()?;
        v.push(t.elapsed().as_secs_f64() * 1e3);
    }
    v.sort_by(f64::total_cmp);
    Ok(v[v.len() / 2])
}

/// ORB timing and matching on one image or a pair (see [`FeaturesBench`]).
pub fn features(
    image: &Path,
    image2: Option<&Path>,
    n_features: usize,
    distribution: &str,
    pattern: &str,
    repeat: usize,
) -> Result<FeaturesBench, String> {
    use misslam_features_matching::{knn2_hamming, match_descriptors, MatchParams, MatchScratch};
    use misslam_features_orb::extract::{
        extract, Distribution, OrbParams, OrbScratch, PatternKind,
    };
    use misslam_framework::Descriptors;
    let distribution = match distribution {
        "quadtree" => Distribution::Quadtree,
        "grid" => Distribution::Grid,
        "none" => Distribution::None,
        other => {
            return Err(format!(
                "--distribution `{other}`: expected quadtree, grid or none"
            ))
        }
    };
    let pattern = match pattern {
        "learned" => PatternKind::Learned,
        "gaussian" => PatternKind::Gaussian,
        other => return Err(format!("--pattern `{other}`: expected learned or gaussian")),
    };
    let p = OrbParams {
        n_features,
        distribution,
        pattern,
        ..OrbParams::default()
    };
    p.validate()?;
    let (w, h, gray) = gray_image(image)?;
    let mut scratch = OrbScratch::default();
    let (mut k1, mut d1) = (Vec::new(), Vec::new());
    let orb_ms = median_ms(repeat, || {
        extract(
            &gray,
            w as usize,
            h as usize,
            &p,
            &mut scratch,
            &mut k1,
            &mut d1,
        )
    })?;
    let mut out = FeaturesBench {
        width: w,
        height: h,
        keypoints: k1.len(),
        keypoints2: 0,
        orb_ms,
        knn_ms: None,
        matches: Vec::new(),
    };
    if let Some(path2) = image2 {
        let (w2, h2, gray2) = gray_image(path2)?;
        let (mut k2, mut d2) = (Vec::new(), Vec::new());
        extract(
            &gray2,
            w2 as usize,
            h2 as usize,
            &p,
            &mut scratch,
            &mut k2,
            &mut d2,
        )?;
        out.keypoints2 = k2.len();
        let mut nn = Vec::new();
        let knn_ms = median_ms(repeat, || {
            knn2_hamming(&d1, &d2, &mut nn);
            Ok::<(), String>(())
        })?;
        out.knn_ms = Some(knn_ms);
        let m = match_descriptors(
            &Descriptors::Binary256(d1),
            &Descriptors::Binary256(d2),
            &MatchParams {
                ratio: 0.8,
                max_distance: 64.0,
                max_distance_l2: 0.4,
                cross_check: true,
            },
            &mut MatchScratch::default(),
        )?;
        out.matches = m
            .iter()
            .map(|m| {
                let (a, b) = (&k1[m.query as usize], &k2[m.train as usize]);
                [a.x, a.y, b.x, b.y]
            })
            .collect();
    }
    Ok(out)
}

/// SURF detect-and-describe on one image, one thread: (keypoints, median ms).
pub fn surf(image: &Path, max_keypoints: usize, repeat: usize) -> Result<(usize, f64), String> {
    use misslam_features_surf::surf::{extract, SurfParams, SurfScratch};
    let p = SurfParams {
        max_keypoints,
        ..SurfParams::default()
    };
    let (w, h, gray) = gray_image(image)?;
    let mut scratch = SurfScratch::default();
    let (mut k, mut d) = (Vec::new(), Vec::new());
    let ms = median_ms(repeat, || {
        extract(
            &gray,
            w as usize,
            h as usize,
            &p,
            &mut scratch,
            &mut k,
            &mut d,
        )
    })?;
    Ok((k.len(), ms))
}

/// One ELAS run's figures ([`elas`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ElasBench {
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// Support points found.
    pub support_points: usize,
    /// Median total time, ms.
    pub ms: f64,
    /// Median time of each step, ms: descriptors, support, triangulation, dense, postprocess.
    pub steps_ms: [f64; 5],
    /// Left disparity of the last run (px, NaN invalid), row-major.
    #[serde(skip)]
    pub disparity: Vec<f32>,
}

/// ELAS on a pair (threads: as rayon is configured, e.g. `RAYON_NUM_THREADS=1`), with the time
/// of each step (median of `repeat`).
pub fn elas(
    left: &Path,
    right: &Path,
    p: &misslam_depth_elas::ElasParams,
    repeat: usize,
) -> Result<ElasBench, String> {
    let (w, h, l) = gray_image(left)?;
    let (w2, h2, r) = gray_image(right)?;
    if (w, h) != (w2, h2) {
        return Err(format!(
            "{} is {w}x{h} but {} is {w2}x{h2}",
            left.display(),
            right.display()
        ));
    }
    let mut steps: Vec<[f64; 5]> = Vec::new();
    let mut last = None;
    let mut scratch = misslam_depth_elas::Scratch::default();
    let ms = median_ms(repeat, || {
        let o = misslam_depth_elas::elas_with(&l, &r, w as usize, h as usize, p, &mut scratch)?;
        let t = o.timing;
        steps.push([
            t.descriptors,
            t.support,
            t.triangulation,
            t.dense,
            t.postprocess,
        ]);
        last = Some(o);
        Ok::<(), String>(())
    })?;
    let o = last.ok_or("no run")?;
    let steps_ms = std::array::from_fn(|k| {
        let mut v: Vec<f64> = steps.iter().map(|s| s[k]).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    });
    Ok(ElasBench {
        width: w,
        height: h,
        support_points: o.support.len(),
        ms,
        steps_ms,
        disparity: o.left,
    })
}

/// `misslam bench sgm`: the CPU SGM on one pair, the median of each stage ([`sgm_cpu`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SgmCpuBench {
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Disparities searched.
    pub disparities: u32,
    /// Paths (4 or 8).
    pub paths: u32,
    /// Rayon's threads.
    pub threads: usize,
    /// Timed runs (after one warm-up run).
    pub runs: usize,
    /// Median wall time of one pair, ms.
    pub ms: f64,
    /// Fastest of the same runs, ms.
    pub min_ms: f64,
    /// Median of each stage over the same runs, ms.
    pub stages_ms: misslam_depth_sgm::sgm::SgmTiming,
    /// Valid pixels of the output, % of all.
    pub density_pct: f64,
}

/// Loads a gray pair (or makes the random-dot pair of `size`), checking that the sizes agree.
fn sgm_pair(
    pair: Option<(&Path, &Path)>,
    size: (usize, usize),
    nd: u32,
) -> Result<(usize, usize, Vec<u8>, Vec<u8>), String> {
    match pair {
        Some((l, r)) => {
            let (w, h, left) = gray_image(l)?;
            let (w2, h2, right) = gray_image(r)?;
            if (w, h) != (w2, h2) {
                return Err(format!(
                    "{} is {w}x{h} but {} is {w2}x{h2}",
                    l.display(),
                    r.display()
                ));
            }
            Ok((w as usize, h as usize, left, right))
        }
        None => {
            let (l, r) = random_dot_pair(size.0, size.1, nd);
            Ok((size.0, size.1, l, r))
        }
    }
}

/// The CPU SGM ([`misslam_depth_sgm::sgm::sgm`]) on a pair, with the threads rayon has: the
/// median time per pair and of each stage over `repeat` runs after a warm-up run.
pub fn sgm_cpu(
    pair: Option<(&Path, &Path)>,
    size: (usize, usize),
    p: &misslam_depth_sgm::sgm::SgmParams,
    repeat: usize,
) -> Result<SgmCpuBench, String> {
    use misslam_depth_sgm::sgm::{sgm, Scratch, SgmTiming};
    let (w, h, left, right) = sgm_pair(pair, size, p.max_disparity)?;
    let mut scratch = Scratch::default();
    let mut out = sgm(&left, &right, w, h, None, p, &mut scratch)?;
    let mut stages: Vec<SgmTiming> = Vec::new();
    let mut totals = Vec::new();
    let ms = median_ms(repeat, || {
        let t = Instant::now();
        out = sgm(&left, &right, w, h, None, p, &mut scratch)?;
        totals.push(t.elapsed().as_secs_f64() * 1e3);
        stages.push(scratch.last_timing());
        Ok::<(), String>(())
    })?;
    let med = |f: &dyn Fn(&SgmTiming) -> f64| {
        let mut v: Vec<f64> = stages.iter().map(f).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let stages_ms = SgmTiming {
        census_ms: med(&|t| t.census_ms),
        forward_ms: med(&|t| t.forward_ms),
        backward_select_ms: med(&|t| t.backward_select_ms),
        finish_ms: med(&|t| t.finish_ms),
        total_ms: med(&|t| t.total_ms),
    };
    let valid = out.iter().filter(|v| v.is_finite()).count();
    Ok(SgmCpuBench {
        width: w,
        height: h,
        disparities: p.max_disparity,
        paths: p.paths,
        threads: rayon::current_num_threads(),
        runs: repeat.max(1),
        ms,
        min_ms: totals.iter().copied().fold(f64::INFINITY, f64::min),
        stages_ms,
        density_pct: 100.0 * valid as f64 / (w * h) as f64,
    })
}

/// `misslam bench sgm-gpu`: the WGSL SGM against the CPU path on the same pair in the same run
/// ([`sgm_gpu`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SgmGpuBench {
    /// The adapter (name, backend, type).
    pub adapter: String,
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Disparities searched.
    pub disparities: u32,
    /// Paths (4 or 8).
    pub paths: u32,
    /// Timed runs (after one warm-up run).
    pub runs: usize,
    /// Median wall time of one pair on the GPU, upload, every kernel, readback and the CPU's
    /// speckle removal included (no wait between the stages), ms.
    pub gpu_ms: f64,
    /// Fastest of the same runs, ms.
    pub gpu_min_ms: f64,
    /// Median of each stage, ms: from GPU timestamps over the same runs where the adapter has
    /// them, else over separate runs in which every stage is waited for (so their sum is above
    /// `gpu_ms`).
    pub stages_ms: misslam_depth_sgm::gpu::SgmGpuTiming,
    /// Median wall time of the CPU path ([`misslam_depth_sgm::sgm::sgm`]) on the same pair, with
    /// the threads rayon has, ms.
    pub cpu_ms: f64,
    /// Rayon's threads for the CPU runs.
    pub cpu_threads: usize,
    /// `cpu_ms / gpu_ms`.
    pub speedup: f64,
    /// Pixels whose validity differs between the GPU and the CPU output.
    pub validity_differs: usize,
    /// Largest |GPU - CPU| over pixels valid in both, px.
    pub max_abs_diff_px: f32,
    /// Valid pixels of the CPU output, % of all.
    pub density_pct: f64,
}

/// How two disparity maps (NaN invalid) differ: the pixels valid in one and not the other, and
/// the largest |a - b| over pixels valid in both.
pub fn disparity_parity(a: &[f32], b: &[f32]) -> (usize, f32) {
    let validity = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.is_finite() != y.is_finite())
        .count();
    let max_diff = a
        .iter()
        .zip(b)
        .filter(|(x, y)| x.is_finite() && y.is_finite())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    (validity, max_diff)
}

/// A rectified random-dot pair of `w` x `h` with a slanted background and a nearer block (so
/// there are occlusions), disparities within 0..`nd`.
pub fn random_dot_pair(w: usize, h: usize, nd: u32) -> (Vec<u8>, Vec<u8>) {
    let mut s = 0x9e37_79b9_7f4a_7c15u64 ^ (w * 31 + h) as u64;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 24) as u8
    };
    let left: Vec<u8> = (0..w * h).map(|_| next()).collect();
    let mut right: Vec<u8> = (0..w * h).map(|_| next()).collect();
    let top = (nd.max(4) - 2) as usize;
    let disp = |x: usize, y: usize| {
        if (w / 3..w / 2).contains(&x) && (h / 4..h / 2).contains(&y) {
            top
        } else {
            2 + (x + 2 * y) * (top / 2) / (w + 2 * h)
        }
    };
    let mut order: Vec<(usize, usize)> = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).collect();
    order.sort_by_key(|&(x, y)| disp(x, y));
    for (x, y) in order {
        let d = disp(x, y);
        if x >= d {
            right[y * w + x - d] = left[y * w + x];
        }
    }
    (left, right)
}

/// SGM on the GPU and on the CPU on one pair (the files, or [`random_dot_pair`] at `size`):
/// median times, the GPU's stage breakdown and the parity of the two outputs.
pub fn sgm_gpu(
    pair: Option<(&Path, &Path)>,
    size: (usize, usize),
    p: &misslam_depth_sgm::sgm::SgmParams,
    repeat: usize,
) -> Result<SgmGpuBench, String> {
    use misslam_depth_sgm::gpu::{SgmGpu, SgmGpuTiming};
    use misslam_depth_sgm::sgm::{sgm, Scratch};
    let (w, h, left, right) = sgm_pair(pair, size, p.max_disparity)?;
    let ctx = misslam_framework::gpu::GpuProvider::new()
        .get()
        .map_err(|e| e.to_string())?;
    let info = &ctx.adapter_info;
    let adapter = format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type);
    let mut kernels = SgmGpu::new(&ctx);
    let run = |k: &mut SgmGpu| k.run(&ctx, &left, &right, w, h, None, p);
    let (got, _) = run(&mut kernels)?;
    let mut totals = Vec::new();
    let mut gpu_out = got;
    let mut stages: Vec<SgmGpuTiming> = Vec::new();
    let gpu_ms = median_ms(repeat, || {
        let t = Instant::now();
        let (d, timing) = run(&mut kernels)?;
        totals.push(t.elapsed().as_secs_f64() * 1e3);
        gpu_out = d;
        stages.push(timing);
        Ok::<(), String>(())
    })?;
    let gpu_min_ms = totals.iter().copied().fold(f64::INFINITY, f64::min);
    if !stages.iter().all(|t| t.gpu_timestamps) {
        // No timestamps: time each stage on its own.
        kernels.set_staged(true);
        stages.clear();
        for _ in 0..repeat.max(1) {
            stages.push(run(&mut kernels)?.1);
        }
        kernels.set_staged(false);
    }
    let med = |f: &dyn Fn(&SgmGpuTiming) -> f64| {
        let mut v: Vec<f64> = stages.iter().map(f).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let stages_ms = SgmGpuTiming {
        upload_ms: med(&|t| t.upload_ms),
        census_ms: med(&|t| t.census_ms),
        aggregate_ms: med(&|t| t.aggregate_ms),
        select_ms: med(&|t| t.select_ms),
        median_ms: med(&|t| t.median_ms),
        readback_ms: med(&|t| t.readback_ms),
        speckle_ms: med(&|t| t.speckle_ms),
        total_ms: med(&|t| t.total_ms),
        gpu_timestamps: stages.iter().all(|t| t.gpu_timestamps),
    };
    let mut scratch = Scratch::default();
    let mut cpu_out = Vec::new();
    let cpu_ms = median_ms(repeat.clamp(1, 10), || {
        cpu_out = sgm(&left, &right, w, h, None, p, &mut scratch)?;
        Ok::<(), String>(())
    })?;
    let (validity_differs, max_abs_diff_px) = disparity_parity(&gpu_out, &cpu_out);
    let valid = cpu_out.iter().filter(|v| v.is_finite()).count();
    Ok(SgmGpuBench {
        adapter,
        width: w,
        height: h,
        disparities: p.max_disparity,
        paths: p.paths,
        runs: repeat.max(1),
        gpu_ms,
        gpu_min_ms,
        stages_ms,
        cpu_ms,
        cpu_threads: rayon::current_num_threads(),
        speedup: cpu_ms / gpu_ms,
        validity_differs,
        max_abs_diff_px,
        density_pct: 100.0 * valid as f64 / (w * h) as f64,
    })
}
