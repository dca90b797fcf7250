//! The parameters of `fusion.surfel` and their checks.

use crate::corr::CorrParams;
use misslam_deformation_ed::decoupled::DecoupledParams;
use misslam_deformation_ed::engine::SolverKind;
use misslam_deformation_ed::graph::GraphParams;
use misslam_deformation_ed::problem::{SolverParams, Weights};
use misslam_framework::registry::BuildError;

/// Parameters of `fusion.surfel`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Deformation graph: spacing (mm), neighbours, sampling.
    pub graph: GraphParams,
    /// Energy weights and solver options. `weights.rot` is 10 here (the library's 1 suits a
    /// clean template): the model is built from noisy depth, and the column of a node's A that
    /// acts along the surface normal is bound by no edge and hardly by the data, only by E_rot,
    /// whose cost for collapsing a column is at most w_rot. With w_rot = 1 a node flattens its
    /// noisy surfels onto a plane once that pays, new surfels mapped back through A^-1 land far
    /// off, and the model falls apart (a node whose det A leaves [1/4, 4] is now reset to its
    /// nearest rotation and reported: `fusion.collapsed_frames`). The main graph over 40 frames
    /// at 640x480 with f = 350 px (46 surfels per node, 0.5 mm of depth noise) ended 46.5 mm off
    /// with w_rot = 1, E_data unscaled and no reset, 0.371 mm with the defaults; at 320x240 with
    /// f = 175 px 11.1 against 0.839; the graph's own view 0.147 and 0.148 mm.
    pub solver: SolverParams,
    /// E_data normalised by its term count (method.md: the weights depend on the number of
    /// terms): where the visible surfels handed to a solve average more than this many per node
    /// they bind, `solver.weights.data` is scaled by this number over their average, so that
    /// its balance with E_rot and E_reg does not change with the resolution, the field of view
    /// or `stride`. 0 turns it off. The main graph at 320x240 (`stride` 4) averages about 47;
    /// with `stride` 1 about 660, and unscaled its nodes collapsed (reset, above) and the surface
    /// slid: material drift 0.85 mm after 40 frames against 0.32; 640x480 at f = 700 px averages
    /// about 140 (0.084 mm against 0.081 unscaled).
    pub data_points_per_node: f64,
    /// Where the visible surfels average more than this many per node they bind, the solve
    /// takes one in ceil(average / this) of them (spread by a hash of their index; the data
    /// weight is then normalised on the ones taken, `data_points_per_node`); fusion still meets
    /// every depth sample. 0 turns it off. At 640x480 with f = 700 px (about 130 a node) the
    /// solve takes one in 3: over 150 frames (2 cores, one script) fusion 7.35 / 7.52 ms a frame
    /// against 9.48 / 9.51 with every surfel (64, one in 2: 9.08 / 8.06), recon.mean_mm 0.0831
    /// against 0.0836 (64: 0.0840), material drift 0.360 against 0.359 mm; 32 and 16 gave 0.0853
    /// and 0.0899 mm. The main graph at 320x240 (about 47) is thinned on some frames (the
    /// README's command takes 94 % of its visible surfels): seeds 7, 1 and 2 over 150 frames
    /// 0.1577 against 0.1575 mm, drift 0.480 against 0.483. `stride = 1` at 320x240 (about 660)
    /// gets one in 14: 0.1853 against 0.1844 mm after 20 frames, drift 0.319 against 0.314, at
    /// half the fusion time (17 against 34 ms). `fusion.solve_points_share` reports the share.
    pub solve_points_per_node: f64,
    /// Batch or decoupled.
    pub solver_kind: SolverKind,
    /// The decoupled split (with `solver_kind = "decoupled"`).
    pub decoupled: DecoupledParams,
    /// Fuse and add one depth pixel per `stride` x `stride`.
    pub stride: u32,
    /// Depth step (mm) to a neighbour above which a pixel gets no normal (where the node lifts
    /// the depth itself: without the `vertices` and `normals` inputs).
    pub normal_max_step_mm: f32,
    /// epsilon_dv: a surfel is visible when the depth it projects onto is this close, mm.
    pub visible_distance_mm: f64,
    /// epsilon_nv: and its normal within this angle, degrees.
    pub visible_angle_deg: f64,
    /// epsilon_df: a depth pixel fuses into a surfel this close, mm.
    pub fuse_distance_mm: f64,
    /// epsilon_nf: with normals within this angle, degrees.
    pub fuse_angle_deg: f64,
    /// omega_max: the confidence weight stops growing here.
    pub max_weight: f32,
    /// A surfel below this weight ...
    pub stable_weight: f32,
    /// ... unseen for this many frames is removed.
    pub unstable_frames: u64,
    /// Most surfels kept; beyond it no new ones are added (logged).
    pub max_surfels: usize,
    /// Most graph nodes; beyond it the graph stops growing (logged) and new surfels bind to the
    /// nodes there are.
    pub max_nodes: usize,
    /// A surfel whose canonical position fusion has moved farther than this from where its
    /// binding (nodes and Sumner weights) was made is bound again, mm; 0 binds every moved
    /// surfel again each frame. When the graph grows, the surfels a new node reaches are bound
    /// again too (and only those).
    pub rebind_distance_mm: f64,
    /// Sparse correspondences (E_corr) from the `features` input.
    pub correspondences: CorrParams,
    /// Also output the model in the scope's frame (`model_camera`: the live model seen from this
    /// frame's pose, as the robocentric formulation keeps it; what an overlay on the endoscope
    /// image or a scope-frame export needs). Off by default: it is a second copy of the model
    /// every frame (and in a recording); at 640x480 (16,000 surfels, 2 cores) it adds 0.12 to
    /// 0.15 ms to fusion's `output` stage.
    pub camera_model: bool,
    /// Also output the surfels selected as visible on each frame (`visible`, world frame, after
    /// the solve; coloured by whether the solve took them), for looking at the selection and
    /// `solve_points_per_node` in the viewer. Off by default.
    pub visible_output: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            graph: GraphParams::default(),
            // Each factorisation also serves the next iteration: the same accuracy, fusion 1.1
            // to 1.3x faster (see `SolverParams::reuse_factorisation` and `docs/pipeline.md`, "Speed").
            solver: SolverParams {
                reuse_factorisation: 1,
                weights: Weights {
                    rot: 10.0,
                    ..Weights::default()
                },
                ..SolverParams::default()
            },
            data_points_per_node: 32.0,
            solve_points_per_node: 48.0,
            solver_kind: SolverKind::Decoupled,
            decoupled: DecoupledParams::default(),
            stride: 4,
            normal_max_step_mm: 3.0,
            visible_distance_mm: 5.0,
            visible_angle_deg: 60.0,
            fuse_distance_mm: 2.0,
            fuse_angle_deg: 30.0,
            max_weight: 20.0,
            stable_weight: 3.0,
            unstable_frames: 10,
            max_surfels: 400_000,
            max_nodes: 20_000,
            rebind_distance_mm: 0.25,
            correspondences: CorrParams::default(),
            camera_model: false,
            visible_output: false,
        }
    }
}

impl Params {
    pub(crate) fn check(&self) -> Result<(), BuildError> {
        misslam_deformation_ed::node::check_graph_and_solver(&self.graph, &self.solver)?;
        if self.stride == 0 {
            return Err(BuildError::param("stride", "must be at least 1"));
        }
        for (name, v) in [
            ("normal_max_step_mm", self.normal_max_step_mm as f64),
            ("visible_distance_mm", self.visible_distance_mm),
            ("fuse_distance_mm", self.fuse_distance_mm),
            ("max_weight", self.max_weight as f64),
        ] {
            if v.is_nan() || v <= 0.0 {
                return Err(BuildError::param(
                    name,
                    format!("must be positive, got {v}"),
                ));
            }
        }
        for (name, v) in [
            ("visible_angle_deg", self.visible_angle_deg),
            ("fuse_angle_deg", self.fuse_angle_deg),
        ] {
            if !(v > 0.0 && v <= 180.0) {
                return Err(BuildError::param(
                    name,
                    format!("must lie in (0, 180], got {v}"),
                ));
            }
        }
        if !(self.stable_weight >= 0.0 && self.stable_weight.is_finite()) {
            return Err(BuildError::param(
                "stable_weight",
                format!("must be a finite number >= 0, got {}", self.stable_weight),
            ));
        }
        for (name, v) in [
            ("data_points_per_node", self.data_points_per_node),
            ("solve_points_per_node", self.solve_points_per_node),
        ] {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(BuildError::param(
                    name,
                    format!("must be a finite number >= 0 (0: off), got {v}"),
                ));
            }
        }
        if !(self.rebind_distance_mm >= 0.0 && self.rebind_distance_mm.is_finite()) {
            return Err(BuildError::param(
                "rebind_distance_mm",
                format!(
                    "must be a finite number >= 0, got {}",
                    self.rebind_distance_mm
                ),
            ));
        }
        if self.max_surfels == 0 {
            return Err(BuildError::param("max_surfels", "must be at least 1"));
        }
        if self.max_nodes == 0 {
            return Err(BuildError::param("max_nodes", "must be at least 1"));
        }
        self.correspondences
            .validate()
            .map_err(|m| BuildError::param("correspondences", m))?;
        Ok(())
    }
}
