//! `fusion.template`: the template-based model (method.md 5.2). A pre-operative surface (CT, or
//! any mesh: OBJ, PLY, glTF from `template_path`, or a `template` port such as the phantom's
//! rest mesh) is placed once by a given pose, optionally refined by rigid ICP against the first
//! scan, and bound to an embedded deformation graph. Per frame:
//!
//! 1. lift the depth to vertex and normal maps;
//! 2. build the distance field function (DFF) of the scan: a truncated signed-distance volume
//!    around it (`data_term = "dff"`, the thesis's method), or keep the maps for projective
//!    point-to-plane association (`data_term = "projective"`, the back-projection baseline of the
//!    thesis's Table 3.1);
//! 3. select the visible template vertices and solve the ED warp on them (batch or decoupled),
//!    with the tracker's pose as prior; unseen parts follow as rigidly as the graph allows;
//! 4. colour the deformed template from the left image, keeping per vertex the colour of the
//!    most frontal and saturated observation.
//!
//! Outputs the deformed template (world frame, coloured), the graph, the pose, the visible
//! vertices, the field's zero level and the frame's figures.
//!
//! For ablations on the phantom, `oracle` adds exact correspondences from its ground truth (the
//! template vertices the true camera sees, or all of them), and `data_term = "none"` drops the
//! scan's term: what error remains is then the warp's own (`graphs/template_oracle.toml`).
#![deny(missing_docs)]

pub mod align;
pub mod gpu;
pub mod params;
pub mod scan_mesh;

use align::{align_to_field, AlignOptions};
use gpu::DffKernel;
use misslam_deformation_ed::engine::Engine;
use misslam_deformation_ed::graph::{Binding, EdGraph};
use misslam_deformation_ed::observe::{
    color_at, color_quality, scan_from_depth_into, template_points, visible_points,
};
use misslam_deformation_ed::problem::{
    Correspondence, FieldJacobian, Intrinsics, ModelSubset, Problem, Scan,
};
use misslam_deformation_ed::DistanceField;
use misslam_framework::geometry::{arr3, in_camera_frame, seen_vertices, vec3};
use misslam_framework::nalgebra::{Isometry3, Point3, Vector3};
use misslam_framework::{
    BuildContext, BuildError, DepthMap, Features, Flow, FrameInfo, GpuContext, Image, Inputs, Mesh,
    Metrics, Node, NodeContext, NodeError, NodeResult, Outputs, PointCloud, PortSpec, PortType,
    Pose, Registry, StageClock, StereoFrame, TrackingState, TypedPlugin,
};
use misslam_fusion_surfel::corr;
pub use params::{AlignMode, AlignParams, DataTerm, FieldParams, OracleMode, OracleParams, Params};
use scan_mesh::scan_mesh;
use std::sync::Arc;
use std::time::Instant;

/// The template bound to its graph, in the canonical (aligned, undeformed) world frame.
struct Model {
    /// The template's vertices: the first `nv` points (the rest are surface samples for the
    /// data term, `data_subdivision`).
    nv: usize,
    points: Vec<Vector3<f64>>,
    normals: Vec<Vector3<f64>>,
    bindings: Vec<Binding>,
    triangles: Vec<[u32; 3]>,
    colors: Vec<[u8; 3]>,
    color_quality: Vec<f32>,
    graph: EdGraph,
}

/// The node.
pub struct TemplateNode {
    p: Params,
    engine: Engine,
    /// The visible set handed to the solve (buffers kept across frames).
    subset: ModelSubset,
    /// The template read from `template_path` at build time.
    file_template: Option<Arc<Mesh>>,
    model: Option<Model>,
    vertices: Vec<[f32; 3]>,
    scan_normals: Vec<[f32; 3]>,
    /// Alignment figures for metrics.json.
    align_rms: Option<(f64, f64)>,
    /// The GPU field kernel, with `field.device` = "gpu" (or "auto" with an adapter).
    gpu: Option<(Arc<GpuContext>, DffKernel)>,
    /// The previous frame's keypoints anchored to the template (E_corr), and buffers.
    corr: corr::CorrTracker,
    /// The template has been solved once (`first_frame_motion` no longer applies).
    solved: bool,
    /// With `oracle`: the vertices it pulled, summed over frames, and the frames.
    oracle_points: (usize, usize),
}

/// The points of each triangle's barycentric grid of step 1/n other than its corners, the points
/// on an edge once for the triangles that share it, with barycentric normals (normalised): the
/// data term's samples of a surface whose vertices are far apart. n = 1 gives none.
pub fn surface_samples(
    points: &[Vector3<f64>],
    normals: &[Vector3<f64>],
    triangles: &[[u32; 3]],
    n: u32,
) -> (Vec<Vector3<f64>>, Vec<Vector3<f64>>) {
    let mut edges = std::collections::HashSet::new();
    let (mut sp, mut sn) = (Vec::new(), Vec::new());
    let nf = f64::from(n);
    let mut push = |w: [f64; 3], c: [usize; 3]| {
        sp.push(points[c[0]] * w[0] + points[c[1]] * w[1] + points[c[2]] * w[2]);
        let m = normals[c[0]] * w[0] + normals[c[1]] * w[1] + normals[c[2]] * w[2];
        sn.push(m.try_normalize(1e-12).unwrap_or(normals[c[0]]));
    };
    for t in triangles {
        let c = t.map(|i| i as usize);
        // Interior points.
        for i in 1..n {
            for j in 1..n - i {
                let k = n - i - j;
                push([f64::from(i) / nf, f64::from(j) / nf, f64::from(k) / nf], c);
            }
        }
        // Edge points, once per edge.
        for (a, b) in [(c[0], c[1]), (c[1], c[2]), (c[2], c[0])] {
            if edges.insert((a.min(b), a.max(b))) {
                for m in 1..n {
                    let s = f64::from(m) / nf;
                    push([1.0 - s, s, 0.0], [a, b, a]);
                }
            }
        }
    }
    (sp, sn)
}

/// Reads a template file into a mesh with normals.
pub fn read_template(path: &std::path::Path) -> Result<Mesh, String> {
    let m = misslam_source_phantom::mesh_input::read_mesh(path)?;
    misslam_source_phantom::mesh_input::check_extent(&m.vertices, m.vertices.len())
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if m.triangles.is_empty() {
        return Err(format!(
            "{}: the template has no triangles (a surface is needed for its normals)",
            path.display()
        ));
    }
    Ok(Mesh {
        vertices: m.vertices,
        normals: None,
        colors: None,
        triangles: m.triangles,
    })
}

fn intrinsics(d: &DepthMap) -> Intrinsics {
    Intrinsics {
        fx: d.calib.fx,
        fy: d.calib.fy,
        cx: d.calib.cx,
        cy: d.calib.cy,
        width: d.map.width,
        height: d.map.height,
    }
}

impl TemplateNode {
    /// Places the template (given pose, then ICP if asked), checks it and binds it to a new graph.
    fn init_model(
        &mut self,
        template: &Mesh,
        pose: &Isometry3<f64>,
        k: &Intrinsics,
        metrics: &mut Metrics,
    ) -> Result<Model, String> {
        let nv = template.vertices.len();
        let (mut points, mut normals) = template_points(template)?;
        let given = self.p.given_pose();
        for (p, n) in points.iter_mut().zip(normals.iter_mut()) {
            *p = (given * Point3::from(*p)).coords;
            *n = given.rotation * *n;
        }
        if self.p.align.mode == AlignMode::Icp {
            let a = &self.p.align;
            let field = DistanceField::from_scan(
                &self.vertices,
                &self.scan_normals,
                a.voxel_mm,
                a.truncation_mm,
                self.p.field.max_voxels,
            )
            .map_err(|e| format!("alignment field: {e}"))?;
            // Align in the camera frame. No normal test picks the side facing the scope: the
            // winding is not known yet (it is checked below, against the aligned template), and
            // parts the scan does not see lie outside the field's truncation or count less by
            // the Huber weights.
            let cfw = pose.inverse();
            let ahead: Vec<Vector3<f64>> = points
                .iter()
                .map(|p| (cfw * Point3::from(*p)).coords)
                .filter(|p| p.z > 0.0)
                .collect();
            let (t_cam, info) = align_to_field(
                &ahead,
                &field,
                &AlignOptions {
                    iterations: a.iterations,
                    huber_mm: a.huber_mm,
                    ..Default::default()
                },
            )?;
            let t_world = pose * t_cam * cfw;
            for p in points.iter_mut() {
                *p = (t_world * Point3::from(*p)).coords;
            }
            for n in normals.iter_mut() {
                *n = t_world.rotation * *n;
            }
            tracing::info!(
                iterations = info.iterations,
                rms_before_mm = info.rms_before_mm,
                rms_after_mm = info.rms_after_mm,
                "template aligned by ICP"
            );
            metrics
                .values
                .insert("template.align_rms_before_mm".into(), info.rms_before_mm);
            metrics
                .values
                .insert("template.align_rms_after_mm".into(), info.rms_after_mm);
            self.align_rms = Some((info.rms_before_mm, info.rms_after_mm));
        }
        let graph = EdGraph::from_points(&points, self.p.graph.clone())?;
        let bindings = graph.bind_all(&points);
        // Outward normals are needed to meet the scan's: if the vertices that lie on the scan
        // mostly face away from the scope, the template's winding is inverted.
        let near = visible_points(
            &graph,
            &points,
            &normals,
            &bindings,
            pose,
            k,
            &self.vertices,
            &self.scan_normals,
            self.p.visible_distance_mm,
            180.0,
        );
        let cfw = pose.inverse();
        let away = near
            .iter()
            .filter(|&&i| {
                let p = (cfw * Point3::from(points[i as usize])).coords;
                (cfw.rotation * normals[i as usize]).dot(&p) > 0.0
            })
            .count();
        if near.is_empty() {
            tracing::warn!(
                "no template vertex lies within visible_distance_mm of the first scan: check the alignment"
            );
        } else if 2 * away > near.len() {
            tracing::warn!(
                away,
                near = near.len(),
                "the template's normals point inwards (inverted winding): flipped"
            );
            for n in normals.iter_mut() {
                *n = -*n;
            }
        }
        let colors = template
            .colors
            .clone()
            .filter(|c| c.len() == nv)
            .unwrap_or_else(|| vec![[190, 190, 190]; nv]);
        let n = self.p.data_subdivision;
        let bindings = if n > 1 {
            let (sp, sn) = surface_samples(&points, &normals, &template.triangles, n);
            points.extend(sp);
            normals.extend(sn);
            graph.bind_all(&points)
        } else {
            bindings
        };
        Ok(Model {
            nv,
            color_quality: vec![0.0; nv],
            points,
            normals,
            bindings,
            triangles: template.triangles.clone(),
            colors,
            graph,
        })
    }

    fn frame(
        &mut self,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
        st: &mut StageClock,
    ) -> NodeResult<Flow> {
        let depth = inputs.get::<DepthMap>("depth")?;
        let k = intrinsics(depth);
        let (w, h) = (k.width as usize, k.height as usize);
        if depth.map.data.len() != w * h {
            return Err(NodeError::msg(format!(
                "depth map of frame {} has {} values for {w}x{h} pixels",
                frame.index,
                depth.map.data.len()
            )));
        }
        let pair = inputs.opt::<StereoFrame>("stereo")?;
        let left: Option<&Image> = pair
            .map(|p| p.left.as_ref())
            .filter(|im| self.p.color && im.width as usize == w && im.height as usize == h);
        let prior = inputs.opt::<Pose>("pose")?;
        let features = inputs
            .opt::<Features>("features")?
            .filter(|_| self.p.correspondences.enabled)
            .map(|f| f.as_ref());
        let mut pose = prior.map_or(Isometry3::identity(), |p| p.world_from_camera);
        let lost = prior.is_some_and(|p| p.state == TrackingState::Lost);
        scan_from_depth_into(
            &depth.map.data,
            &k,
            self.p.normal_max_step_mm,
            &mut self.vertices,
            &mut self.scan_normals,
        );
        st.lap("scan");
        let mut metrics = Metrics::default();
        if self.model.is_none() {
            let template = match (&self.file_template, &self.p.template_from_scan) {
                (Some(t), _) => t.clone(),
                (None, Some(sp)) => {
                    // The scan is in the camera frame; the tracker's pose puts it in the world,
                    // where the given placement (identity unless set) leaves it.
                    let m = scan_mesh(&self.vertices, w, h, left, &pose, sp).map_err(|e| {
                        NodeError::msg(format!("frame {}: template_from_scan: {e}", frame.index))
                    })?;
                    tracing::info!(
                        frame = frame.index,
                        vertices = m.vertices.len(),
                        triangles = m.triangles.len(),
                        "template made from the first scan"
                    );
                    Arc::new(m)
                }
                (None, None) => inputs.opt::<Mesh>("template")?.cloned().ok_or_else(|| {
                    NodeError::msg(
                        "fusion.template needs a template: set `template_path` or `template_from_scan`, or connect the `template` input",
                    )
                })?,
            };
            let m = self
                .init_model(&template, &pose, &k, &mut metrics)
                .map_err(|e| NodeError::msg(format!("frame {}: {e}", frame.index)))?;
            self.model = Some(m);
            st.lap("init");
        }
        let Some(model) = self.model.as_mut() else {
            return Err(NodeError::msg("no model"));
        };
        let mut visible = Vec::new();
        let mut field_surface = None;
        if lost {
            tracing::warn!(
                frame = frame.index,
                "tracking lost: the template is not deformed on this frame"
            );
        } else {
            visible = visible_points(
                &model.graph,
                &model.points,
                &model.normals,
                &model.bindings,
                &pose,
                &k,
                &self.vertices,
                &self.scan_normals,
                self.p.visible_distance_mm,
                self.p.visible_angle_deg,
            );
            st.lap("select");
            let field = match self.p.data_term {
                DataTerm::Dff => {
                    let t = Instant::now();
                    let fp = &self.p.field;
                    // The field's normals when the solve's field rows take them.
                    let with_normals = self.p.solver.field_jacobian == FieldJacobian::FieldNormal;
                    let from_maps = if with_normals {
                        DistanceField::from_maps_with_normals
                    } else {
                        DistanceField::from_maps
                    };
                    let f = match &self.gpu {
                        Some((ctx, kernel)) => kernel
                            .build(
                                ctx,
                                &self.vertices,
                                &self.scan_normals,
                                &k,
                                fp.voxel_mm,
                                fp.truncation_mm,
                                fp.window_px,
                                fp.max_voxels,
                                with_normals,
                            )
                            .map(|(f, _)| f),
                        None => from_maps(
                            &self.vertices,
                            &self.scan_normals,
                            &k,
                            fp.voxel_mm,
                            fp.truncation_mm,
                            fp.window_px,
                            fp.max_voxels,
                        ),
                    }
                    .map_err(|e| NodeError::msg(format!("frame {}: {e}", frame.index)))?;
                    metrics
                        .values
                        .insert("template.field_ms".into(), t.elapsed().as_secs_f64() * 1e3);
                    metrics
                        .values
                        .insert("template.voxels".into(), f.values.len() as f64);
                    Some(f)
                }
                DataTerm::Projective | DataTerm::None => None,
            };
            if field.is_some() {
                st.lap("field");
            }
            // With no dense data term the visible set feeds no rows (it still colours the
            // template and is the `visible` output).
            let fed: &[u32] = if self.p.data_term == DataTerm::None {
                &[]
            } else {
                &visible
            };
            self.subset
                .gather(fed, &model.points, &model.normals, &model.bindings);
            let mut corrs = self
                .corr
                .correspondences(
                    frame.index,
                    features,
                    &pose,
                    &k,
                    (&self.vertices, &self.scan_normals),
                    &model.graph,
                    &self.p.correspondences,
                )
                .map_err(NodeError::msg)?;
            metrics
                .values
                .insert("template.correspondences".into(), corrs.len() as f64);
            if self.p.oracle.mode != OracleMode::Off {
                let n = oracle_correspondences(inputs, &self.p.oracle, model, &mut corrs)
                    .map_err(|e| NodeError::msg(format!("frame {}: oracle: {e}", frame.index)))?;
                metrics
                    .values
                    .insert("template.oracle_points".into(), n as f64);
                self.oracle_points.0 += n;
                self.oracle_points.1 += 1;
            }
            metrics
                .values
                .insert("template.anchors".into(), self.corr.anchors() as f64);
            st.lap("corr");
            let problem = Problem {
                model: self.subset.view(),
                scan: match self.p.data_term {
                    DataTerm::Projective => Some(Scan {
                        intrinsics: k,
                        vertices: &self.vertices,
                        normals: &self.scan_normals,
                    }),
                    DataTerm::Dff | DataTerm::None => None,
                },
                field: field.as_ref(),
                correspondences: &corrs,
                pose_prior: pose,
            };
            let first;
            let solver = if self.solved {
                &self.p.solver
            } else {
                let mut sp = self.p.solver.clone();
                sp.weights.motion = sp.weights.motion.max(self.p.first_frame_motion);
                first = sp;
                &first
            };
            let (info, split) = self
                .engine
                .solve(
                    frame.index,
                    &mut model.graph,
                    &mut pose,
                    &problem,
                    solver,
                    &self.p.decoupled,
                )
                .map_err(NodeError::msg)?;
            st.lap("solve");
            st.times.extend(info.stages());
            if let Some(d) = &split {
                st.push("solve.level2", d.level2.ms_total);
            }
            self.solved = true;
            for (key, v) in [
                ("template.iterations", info.iterations as f64),
                ("template.rejected_steps", info.rejected_steps as f64),
                ("template.cost_before", info.cost_before),
                ("template.cost_after", info.cost_after),
                ("template.data_terms", info.data_terms as f64),
                ("template.solved_nodes", info.solved_nodes as f64),
                ("template.solve_ms", info.ms_total),
            ] {
                metrics.values.insert(key.into(), v);
            }
            if let Some(d) = split {
                metrics
                    .values
                    .insert("template.pr_nodes".into(), d.pr_nodes as f64);
            }
            if let Some(f) = &field {
                field_surface = Some(zero_level(f, &pose));
            }
        }
        // The deformed template, and its colour from this view.
        let (mut live, mut live_n) = (Vec::new(), Vec::new());
        model.graph.deform(
            &model.points,
            Some(&model.normals),
            &model.bindings,
            &mut live,
            &mut live_n,
        );
        // This frame's keypoints anchored to the deformed template for the next frame's
        // correspondences (none after a lost frame).
        self.corr.anchor(
            frame.index,
            features,
            lost,
            &pose,
            &live,
            &live_n,
            &model.points,
            &model.bindings,
            &model.graph,
            &self.vertices,
            &k,
            &self.p.correspondences,
        );
        if let Some(img) = left {
            let cfw = pose.inverse();
            for &i in &visible {
                let i = i as usize;
                if i >= model.nv {
                    continue;
                }
                let p = cfw * Point3::from(live[i]);
                let u = (k.fx * p.x / p.z + k.cx).round();
                let v = (k.fy * p.y / p.z + k.cy).round();
                if !(p.z > 0.0 && u >= 0.0 && v >= 0.0 && (u as usize) < w && (v as usize) < h) {
                    continue;
                }
                let c = color_at(Some(img), v as usize * w + u as usize);
                let q = color_quality(arr3(&(cfw.rotation * live_n[i])), c);
                if q >= model.color_quality[i] {
                    model.colors[i] = c;
                    model.color_quality[i] = q;
                }
            }
        }
        metrics
            .values
            .insert("template.visible".into(), visible.len() as f64);
        metrics
            .values
            .insert("template.nodes".into(), model.graph.len() as f64);
        if self.p.camera_mesh {
            let (vertices, normals) =
                in_camera_frame(&pose, &live[..model.nv], &live_n[..model.nv]);
            outputs.put(
                "mesh_camera",
                Mesh {
                    vertices,
                    normals: Some(normals),
                    colors: Some(model.colors.clone()),
                    triangles: model.triangles.clone(),
                },
            )?;
        }
        outputs.put(
            "mesh",
            Mesh {
                vertices: live[..model.nv].iter().map(arr3).collect(),
                normals: Some(live_n[..model.nv].iter().map(arr3).collect()),
                colors: Some(model.colors.clone()),
                triangles: model.triangles.clone(),
            },
        )?;
        outputs.put(
            "visible",
            PointCloud {
                positions: visible.iter().map(|&i| arr3(&live[i as usize])).collect(),
                colors: None,
            },
        )?;
        if let Some(s) = field_surface {
            outputs.put("field", s)?;
        }
        outputs.put("graph", model.graph.to_payload())?;
        outputs.put(
            "pose",
            Pose {
                world_from_camera: pose,
                state: prior.map_or(TrackingState::Tracking, |p| p.state),
            },
        )?;
        outputs.put("info", metrics)?;
        st.lap("output");
        Ok(Flow::Continue)
    }
}

/// Appends the oracle's E_corr constraints (see [`params::OracleParams`]): each template vertex
/// the mode selects, pulled to GT vertex i in the true camera's frame. Returns how many.
fn oracle_correspondences(
    inputs: &Inputs,
    p: &params::OracleParams,
    model: &Model,
    corrs: &mut Vec<Correspondence>,
) -> Result<usize, String> {
    let missing = |port: &str| {
        format!("`oracle.mode` needs the `{port}` input connected (the phantom's `{port}`)")
    };
    let gt = inputs
        .opt::<Mesh>("mesh_gt")
        .map_err(|e| e.to_string())?
        .ok_or_else(|| missing("mesh_gt"))?;
    let pose_gt = inputs
        .opt::<Pose>("pose_gt")
        .map_err(|e| e.to_string())?
        .ok_or_else(|| missing("pose_gt"))?;
    if gt.vertices.len() != model.nv {
        return Err(format!(
            "mesh_gt has {} vertices and the template {}: the oracle needs the phantom's rest mesh as the template (vertex i the same tissue point as GT vertex i)",
            gt.vertices.len(),
            model.nv
        ));
    }
    let seen = match p.mode {
        OracleMode::Visible => {
            let depth = inputs
                .opt::<DepthMap>("depth_gt")
                .map_err(|e| e.to_string())?
                .ok_or_else(|| missing("depth_gt"))?;
            seen_vertices(gt, &pose_gt.world_from_camera, depth, p.max_depth_gap_mm)
                .map_err(|e| format!("depth_gt: {e}"))?
        }
        OracleMode::All => vec![true; model.nv],
        OracleMode::Off => return Ok(0),
    };
    let cfw = pose_gt.world_from_camera.inverse();
    let before = corrs.len();
    corrs.extend(
        seen.iter()
            .enumerate()
            .filter(|(_, &s)| s)
            .map(|(i, _)| Correspondence {
                point: model.points[i],
                binding: model.bindings[i],
                target: (cfw * Point3::from(vec3(gt.vertices[i]))).coords,
                normal: None,
            }),
    );
    Ok(corrs.len() - before)
}

/// The field's voxels within half a voxel of the zero level, in the world frame: what the solve
/// pulled the template onto, to look at in the viewer.
fn zero_level(f: &DistanceField, world_from_camera: &Isometry3<f64>) -> PointCloud {
    let [nx, ny, _] = f.dims;
    let half = 0.5 * f.voxel;
    let positions = f
        .values
        .iter()
        .enumerate()
        .filter(|(_, v)| (**v as f64).abs() < half)
        .map(|(i, _)| {
            let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
            let c = f.origin + Vector3::new(x as f64, y as f64, z as f64) * f.voxel;
            arr3(&(world_from_camera * Point3::from(c)).coords)
        })
        .collect();
    PointCloud {
        positions,
        colors: None,
    }
}

impl Node for TemplateNode {
    fn process(
        &mut self,
        ctx: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        // Its stages under `timing_ms."<id>.<stage>"`: scan, init (the first frame), select,
        // field (DFF), corr, solve (and its parts), output; a lost frame runs no solve.
        let mut st = StageClock::start();
        let flow = self.frame(frame, inputs, outputs, &mut st);
        st.report(ctx);
        flow
    }

    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        if let Some(m) = &self.model {
            ctx.report_eval("template.vertices", m.nv as f64);
            ctx.report_eval("template.data_points", m.points.len() as f64);
            ctx.report_eval("template.nodes", m.graph.len() as f64);
        }
        if let (n, frames @ 1..) = self.oracle_points {
            ctx.report_eval("template.oracle_points", n as f64 / frames as f64);
        }
        if let Some((before, after)) = self.align_rms {
            ctx.report_eval("template.align_rms_before_mm", before);
            ctx.report_eval("template.align_rms_after_mm", after);
        }
        Ok(())
    }
}

/// Builds the node; reads `template_path` now so a missing or corrupt file fails before any frame.
pub fn build(p: Params, ctx: &BuildContext) -> Result<TemplateNode, BuildError> {
    p.check()?;
    let gpu = if p.data_term == DataTerm::Dff {
        ctx.gpu
            .for_device(p.field.device, ctx.node_id)
            .map_err(|e| BuildError::param("field.device", e.to_string()))?
            .map(|c| {
                let k = DffKernel::new(&c);
                (c, k)
            })
    } else {
        None
    };
    let file_template = match &p.template_path {
        Some(path) => Some(Arc::new(
            read_template(path).map_err(|e| BuildError::param("template_path", e))?,
        )),
        None => None,
    };
    Ok(TemplateNode {
        engine: Engine::new(p.solver_kind),
        subset: ModelSubset::default(),
        p,
        file_template,
        model: None,
        vertices: Vec::new(),
        scan_normals: Vec::new(),
        align_rms: None,
        gpu,
        corr: corr::CorrTracker::default(),
        solved: false,
        oracle_points: (0, 0),
    })
}

/// Registers `fusion.template`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "fusion.template",
        "template-based fusion: a pre-operative mesh aligned once, deformed by ED onto each scan through a distance field (DFF) or back-projection",
        vec![
            PortSpec::new(
                "depth",
                PortType::Depth,
                "the live depth (left camera): the scan",
            ),
            PortSpec::optional(
                "stereo",
                PortType::Stereo,
                "the pair, for the template's colour (left image)",
            ),
            PortSpec::optional(
                "pose",
                PortType::Pose,
                "world_from_camera from the tracker (prior); a lost frame is not deformed",
            ),
            PortSpec::optional(
                "features",
                PortType::Features,
                "keypoints with descriptors and camera-frame 3D points (features.orb / features.surf): matched frame to frame into E_corr constraints (`correspondences`)",
            ),
            PortSpec::optional(
                "template",
                PortType::Mesh,
                "the pre-operative surface, world frame, read on the first frame (without template_path)",
            ),
            PortSpec::optional(
                "mesh_gt",
                PortType::Mesh,
                "with `oracle`: the phantom's true surface, world frame (vertex i the template's vertex i)",
            ),
            PortSpec::optional(
                "pose_gt",
                PortType::Pose,
                "with `oracle`: the true world_from_camera",
            ),
            PortSpec::optional(
                "depth_gt",
                PortType::Depth,
                "with `oracle.mode = \"visible\"`: the true depth, which says what the camera sees",
            ),
        ],
        vec![
            PortSpec::new(
                "mesh",
                PortType::Mesh,
                "the deformed template, world frame, coloured",
            ),
            PortSpec::optional(
                "mesh_camera",
                PortType::Mesh,
                "with `camera_mesh = true`: the same mesh in the scope's frame (camera_from_world of `pose` applied to vertices and normals)",
            ),
            PortSpec::new(
                "visible",
                PortType::PointCloud,
                "the deformed vertices (and surface samples, with data_subdivision) that fed the data term",
            ),
            PortSpec::optional(
                "field",
                PortType::PointCloud,
                "the distance field's zero level (voxels within half a voxel), world frame",
            ),
            PortSpec::new("graph", PortType::DeformationGraph, "nodes, warps, edges"),
            PortSpec::new("pose", PortType::Pose, "the pose after the solve"),
            PortSpec::new(
                "info",
                PortType::Metrics,
                "template.visible, nodes, field_ms, voxels, solve_ms, iterations, rejected_steps, costs, correspondences, anchors, oracle_points",
            ),
        ],
        build,
    )
    .with_absent_outputs(|p: &Params| {
        let mut absent = Vec::new();
        if p.data_term != DataTerm::Dff {
            absent.push((
                "field".to_owned(),
                "only the DFF data term builds a field: set its `data_term = \"dff\"`".to_owned(),
            ));
        }
        if !p.camera_mesh {
            absent.push((
                "mesh_camera".to_owned(),
                "set its `camera_mesh = true`".to_owned(),
            ));
        }
        absent
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn surface_samples_cover_each_triangle_and_each_shared_edge_once() {
        // Two triangles of the unit square sharing the diagonal (0, 2).
        let p = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(3.0, 0.0, 0.0),
            Vector3::new(3.0, 3.0, 0.0),
            Vector3::new(0.0, 3.0, 0.0),
        ];
        let n = [Vector3::z(), Vector3::z(), Vector3::x(), Vector3::z()];
        let tris = [[0, 1, 2], [0, 2, 3]];
        assert!(surface_samples(&p, &n, &tris, 1).0.is_empty());
        // n = 2: the midpoints of the 5 distinct edges.
        let (s, _) = surface_samples(&p, &n, &tris, 2);
        assert_eq!(s.len(), 5);
        assert!(s.contains(&Vector3::new(1.5, 1.5, 0.0)));
        // n = 3: per triangle its centroid, per edge two points: 2 + 5 * 2.
        let (s, sn) = surface_samples(&p, &n, &tris, 3);
        assert_eq!(s.len(), 12);
        assert!(s
            .iter()
            .any(|q| (q - Vector3::new(2.0, 1.0, 0.0)).norm() < 1e-12));
        for m in &sn {
            assert!((m.norm() - 1.0).abs() < 1e-12);
        }
        // Every sample lies on the square.
        for q in &s {
            assert!(q.z == 0.0 && (0.0..=3.0).contains(&q.x) && (0.0..=3.0).contains(&q.y));
        }
    }
}
