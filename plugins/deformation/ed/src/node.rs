//! The `deformation.batch` and `deformation.decoupled` nodes: per frame, lift the depth to a scan,
//! select the visible model points, solve the ED warp (all nodes, or PR then PI), and output the
//! deformed model, the graph and the solve's figures.
//!
//! The model is the `template` mesh of the first frame (template path), or, when none is connected,
//! the first depth map lifted to the world frame (one point per `model_stride` pixels). Nodes are
//! sampled on it once; growth belongs to fusion.

use crate::decoupled::DecoupledParams;
use crate::engine::{Engine, SolverKind};
use crate::graph::{Binding, EdGraph, GraphParams};
use crate::observe::{scan_from_depth_into, template_points, visible_points};
use crate::problem::{Intrinsics, ModelPoints, Problem, Scan, SolverParams};
use misslam_framework::geometry::{arr3, vec3};
use misslam_framework::nalgebra::{Isometry3, Point3, Vector3};
use misslam_framework::{
    BuildContext, BuildError, DepthMap, Flow, FrameInfo, Inputs, Mesh, Metrics, Node, NodeContext,
    NodeError, NodeResult, Outputs, PointCloud, PortSpec, PortType, Pose, Registry, TrackingState,
    TypedPlugin,
};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Parameters of `deformation.batch`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct BatchParams {
    /// Deformation graph: spacing (mm), neighbours, sampling.
    pub graph: GraphParams,
    /// Energy weights and solver options.
    pub solver: SolverParams,
    /// Without a template, the model is one point per `model_stride` x `model_stride` pixels of the
    /// first depth map.
    pub model_stride: u32,
    /// Depth step (mm) to a neighbour above which a pixel gets no normal (occlusion edge).
    pub normal_max_step_mm: f32,
    /// epsilon_dv: a model point is visible when the scan point it projects to is this close, mm.
    pub visible_distance_mm: f64,
    /// epsilon_nv: and its normal within this angle of the scan's, degrees.
    pub visible_angle_deg: f64,
}

impl Default for BatchParams {
    fn default() -> Self {
        BatchParams {
            graph: GraphParams::default(),
            solver: SolverParams::default(),
            model_stride: 4,
            normal_max_step_mm: 3.0,
            visible_distance_mm: 5.0,
            visible_angle_deg: 60.0,
        }
    }
}

/// Parameters of `deformation.decoupled`: those of the batch solver plus the split.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DecoupledNodeParams {
    /// Deformation graph: spacing (mm), neighbours, sampling.
    pub graph: GraphParams,
    /// Energy weights and solver options (level I; level II uses them without data terms).
    pub solver: SolverParams,
    /// The two-step split: boundary edges, level II rings and iterations.
    pub decoupled: DecoupledParams,
    /// As in `deformation.batch`.
    pub model_stride: u32,
    /// As in `deformation.batch`.
    pub normal_max_step_mm: f32,
    /// As in `deformation.batch`.
    pub visible_distance_mm: f64,
    /// As in `deformation.batch`.
    pub visible_angle_deg: f64,
}

impl Default for DecoupledNodeParams {
    fn default() -> Self {
        let b = BatchParams::default();
        DecoupledNodeParams {
            graph: b.graph,
            solver: b.solver,
            decoupled: DecoupledParams::default(),
            model_stride: b.model_stride,
            normal_max_step_mm: b.normal_max_step_mm,
            visible_distance_mm: b.visible_distance_mm,
            visible_angle_deg: b.visible_angle_deg,
        }
    }
}

struct Model {
    points: Vec<Vector3<f64>>,
    normals: Vec<Vector3<f64>>,
    bindings: Vec<Binding>,
    triangles: Vec<[u32; 3]>,
    graph: EdGraph,
}

/// Per-frame buffers, kept between frames.
#[derive(Default)]
struct Scratch {
    vertices: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    points: Vec<Vector3<f64>>,
    point_normals: Vec<Vector3<f64>>,
    bindings: Vec<Binding>,
}

/// The node behind both plugin ids.
pub struct EdNode {
    common: BatchParams,
    engine: Engine,
    decoupled: DecoupledParams,
    model: Option<Model>,
    scratch: Scratch,
}

/// The `graph` and `solver` tables of a node built on the ED graph (the deformation nodes and
/// both fusion nodes), each error naming its table.
pub fn check_graph_and_solver(
    graph: &GraphParams,
    solver: &SolverParams,
) -> Result<(), BuildError> {
    graph
        .validate()
        .map_err(|m| BuildError::param("graph", m))?;
    solver
        .validate()
        .map_err(|m| BuildError::param("solver", m))
}

fn check(p: &BatchParams) -> Result<(), BuildError> {
    check_graph_and_solver(&p.graph, &p.solver)?;
    if p.model_stride == 0 {
        return Err(BuildError::param("model_stride", "must be at least 1"));
    }
    if p.normal_max_step_mm.is_nan() || p.normal_max_step_mm <= 0.0 {
        return Err(BuildError::param("normal_max_step_mm", "must be positive"));
    }
    if p.visible_distance_mm.is_nan() || p.visible_distance_mm <= 0.0 {
        return Err(BuildError::param("visible_distance_mm", "must be positive"));
    }
    if !(p.visible_angle_deg > 0.0 && p.visible_angle_deg <= 180.0) {
        return Err(BuildError::param(
            "visible_angle_deg",
            "must be in (0, 180]",
        ));
    }
    Ok(())
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

impl EdNode {
    fn init_model(
        &self,
        template: Option<&Mesh>,
        depth: &DepthMap,
        scan: (&[[f32; 3]], &[[f32; 3]]),
        pose: &Isometry3<f64>,
    ) -> Result<Model, String> {
        let (points, normals, triangles) = if let Some(mesh) = template {
            let (v, n) = template_points(mesh)?;
            (v, n, mesh.triangles.clone())
        } else {
            let (w, h) = (depth.map.width as usize, depth.map.height as usize);
            let s = self.common.model_stride as usize;
            let mut v = Vec::new();
            let mut n = Vec::new();
            for y in (0..h).step_by(s) {
                for x in (0..w).step_by(s) {
                    let i = y * w + x;
                    let (p, q) = (scan.0[i], scan.1[i]);
                    if p.iter().chain(&q).all(|c| c.is_finite()) {
                        v.push((pose * Point3::from(vec3(p))).coords);
                        n.push(pose.rotation * vec3(q));
                    }
                }
            }
            if v.is_empty() {
                return Err(
                    "the first depth map has no valid pixel with a normal to build the model from"
                        .into(),
                );
            }
            (v, n, Vec::new())
        };
        let graph = EdGraph::from_points(&points, self.common.graph.clone())?;
        let bindings = graph.bind_all(&points);
        Ok(Model {
            points,
            normals,
            bindings,
            triangles,
            graph,
        })
    }
}

impl Node for EdNode {
    fn process(
        &mut self,
        _: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let depth = inputs.get::<DepthMap>("depth")?;
        let k = intrinsics(depth);
        if depth.map.data.len() != (k.width * k.height) as usize {
            return Err(NodeError::msg(format!(
                "depth map of frame {} has {} values for {}x{} pixels",
                frame.index,
                depth.map.data.len(),
                k.width,
                k.height
            )));
        }
        let prior = inputs.opt::<Pose>("pose")?;
        if let Some(p) = prior {
            if p.state == TrackingState::Lost {
                tracing::warn!(
                    frame = frame.index,
                    "tracking lost: the deformation uses the last pose as its prior"
                );
            }
        }
        let mut scratch = std::mem::take(&mut self.scratch);
        let result = self.solve_frame(frame, inputs, outputs, depth, k, prior, &mut scratch);
        self.scratch = scratch;
        result
    }
}

impl EdNode {
    #[allow(clippy::too_many_arguments)]
    fn solve_frame(
        &mut self,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
        depth: &DepthMap,
        k: Intrinsics,
        prior: Option<&std::sync::Arc<Pose>>,
        scratch: &mut Scratch,
    ) -> NodeResult<Flow> {
        let prior_pose = prior.map_or(Isometry3::identity(), |p| p.world_from_camera);
        let Scratch {
            vertices,
            normals,
            points: lp,
            point_normals: ln,
            bindings: lb,
        } = scratch;
        scan_from_depth_into(
            &depth.map.data,
            &k,
            self.common.normal_max_step_mm,
            vertices,
            normals,
        );
        let scan = (vertices.as_slice(), normals.as_slice());
        if self.model.is_none() {
            let template = inputs.opt::<Mesh>("template")?;
            let m = self
                .init_model(template.map(|a| a.as_ref()), depth, scan, &prior_pose)
                .map_err(NodeError::msg)?;
            self.model = Some(m);
        }
        let c = &self.common;
        let Some(model) = self.model.as_mut() else {
            return Err(NodeError::msg("no model"));
        };
        let visible = visible_points(
            &model.graph,
            &model.points,
            &model.normals,
            &model.bindings,
            &prior_pose,
            &k,
            scan.0,
            scan.1,
            c.visible_distance_mm,
            c.visible_angle_deg,
        );
        lp.clear();
        lp.extend(visible.iter().map(|&i| model.points[i as usize]));
        ln.clear();
        ln.extend(visible.iter().map(|&i| model.normals[i as usize]));
        lb.clear();
        lb.extend(visible.iter().map(|&i| model.bindings[i as usize]));
        let problem = Problem {
            model: ModelPoints {
                points: lp,
                normals: ln,
                bindings: lb,
            },
            scan: Some(Scan {
                intrinsics: k,
                vertices: scan.0,
                normals: scan.1,
            }),
            field: None,
            correspondences: &[],
            pose_prior: prior_pose,
        };
        let mut pose = prior_pose;
        let mut metrics = Metrics::default();
        let (info, split) = self
            .engine
            .solve(
                frame.index,
                &mut model.graph,
                &mut pose,
                &problem,
                &c.solver,
                &self.decoupled,
            )
            .map_err(NodeError::msg)?;
        if let Some(d) = split {
            metrics.values.insert("pr_nodes".into(), d.pr_nodes as f64);
            metrics
                .values
                .insert("pi_solved".into(), d.pi_solved as f64);
        }
        for (k, v) in [
            ("iterations", info.iterations as f64),
            ("cost_before", info.cost_before),
            ("cost_after", info.cost_after),
            ("solved_nodes", info.solved_nodes as f64),
            ("total_nodes", model.graph.len() as f64),
            ("visible_points", visible.len() as f64),
            ("data_terms", info.data_terms as f64),
            ("solve_ms", info.ms_total),
        ] {
            metrics.values.insert(k.into(), v);
        }
        for (i, cst) in info.costs.iter().enumerate() {
            metrics.values.insert(format!("cost_it{i}"), *cst);
        }
        let (mut dp, mut dn) = (Vec::new(), Vec::new());
        model.graph.deform(
            &model.points,
            Some(&model.normals),
            &model.bindings,
            &mut dp,
            &mut dn,
        );
        outputs.put(
            "mesh",
            Mesh {
                vertices: dp.iter().map(arr3).collect(),
                normals: Some(dn.iter().map(arr3).collect()),
                colors: None,
                triangles: model.triangles.clone(),
            },
        )?;
        outputs.put(
            "visible",
            PointCloud {
                positions: visible.iter().map(|&i| arr3(&dp[i as usize])).collect(),
                colors: None,
            },
        )?;
        outputs.put("graph", model.graph.to_payload())?;
        outputs.put(
            "pose",
            Pose {
                world_from_camera: pose,
                state: prior.map_or(TrackingState::Tracking, |p| p.state),
            },
        )?;
        outputs.put("info", metrics)?;
        Ok(Flow::Continue)
    }
}

fn inputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "depth",
            PortType::Depth,
            "the live depth (left camera), lifted to vertex and normal maps",
        ),
        PortSpec::optional(
            "pose",
            PortType::Pose,
            "world_from_camera from the rigid tracker (prior and start); identity if absent",
        ),
        PortSpec::optional(
            "template",
            PortType::Mesh,
            "the model to deform, world frame, read on the first frame only",
        ),
    ]
}

fn outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "mesh",
            PortType::Mesh,
            "the deformed model, world frame (the template's triangles, if any)",
        ),
        PortSpec::new(
            "visible",
            PortType::PointCloud,
            "the deformed visible points V^n that fed the data term",
        ),
        PortSpec::new(
            "graph",
            PortType::DeformationGraph,
            "nodes, their warps and edges",
        ),
        PortSpec::new(
            "pose",
            PortType::Pose,
            "the camera pose after the solve (the prior unless solver.optimize_pose)",
        ),
        PortSpec::new(
            "info",
            PortType::Metrics,
            "iterations, cost before/after and per iteration, nodes solved, ms",
        ),
    ]
}

/// Registers `deformation.batch` and `deformation.decoupled`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "deformation.batch",
        "embedded deformation: Gauss-Newton / LM over all nodes, block-sparse Cholesky (faer)",
        inputs(),
        outputs(),
        |p: BatchParams, _: &BuildContext| {
            check(&p)?;
            Ok(EdNode {
                common: p,
                engine: Engine::new(SolverKind::Batch),
                decoupled: DecoupledParams::default(),
                model: None,
                scratch: Scratch::default(),
            })
        },
    ))?;
    registry.register(TypedPlugin::new(
        "deformation.decoupled",
        "embedded deformation, two-step: seen (PR) nodes with the data, then unseen (PI) nodes as rigidly as possible",
        inputs(),
        outputs(),
        |p: DecoupledNodeParams, _: &BuildContext| {
            let common = BatchParams {
                graph: p.graph,
                solver: p.solver,
                model_stride: p.model_stride,
                normal_max_step_mm: p.normal_max_step_mm,
                visible_distance_mm: p.visible_distance_mm,
                visible_angle_deg: p.visible_angle_deg,
            };
            check(&common)?;
            Ok(EdNode {
                common,
                engine: Engine::new(SolverKind::Decoupled),
                decoupled: p.decoupled,
                model: None,
                scratch: Scratch::default(),
            })
        },
    ))
}
