//! The parameters of `fusion.template`, with their checks.

use crate::scan_mesh::ScanTemplateParams;
use misslam_deformation_ed::decoupled::DecoupledParams;
use misslam_deformation_ed::engine::SolverKind;
use misslam_deformation_ed::graph::GraphParams;
use misslam_deformation_ed::problem::{FieldJacobian, SolverParams};
use misslam_framework::nalgebra::{Isometry3, Translation3, UnitQuaternion};
use misslam_framework::{BuildError, Device};
use misslam_fusion_surfel::corr::CorrParams;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;

/// The data term that pulls the template onto the scan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum DataTerm {
    /// Distance field function: trilinear lookup of a truncated signed-distance volume built
    /// from the scan; no correspondence search (the thesis's method).
    #[default]
    Dff,
    /// Back-projection: each vertex is projected into the depth map and associated with the
    /// scan point at that pixel, point-to-plane, re-associated every iteration (the baseline).
    Projective,
    /// No dense data term: only the sparse correspondences (`correspondences`) and the
    /// `oracle`'s pull the template (an ablation).
    None,
}

/// Which template vertices the oracle pulls to their true positions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum OracleMode {
    /// No oracle (every real use).
    #[default]
    Off,
    /// The vertices the true camera sees on this frame: exact data where a scan has any, so
    /// what the rest of the template does is the warp's extrapolation alone.
    Visible,
    /// Every vertex, seen or not: what the deformation graph can represent at all.
    All,
}

/// Ground-truth correspondences for ablation studies on the phantom (an oracle, never for real
/// data): template vertex i, which the phantom's rest mesh makes the same tissue point as GT
/// vertex i, gets an E_corr constraint (weight `solver.weights.corr`, no normal) to that vertex's
/// true position in the true camera's frame, from the `mesh_gt`, `pose_gt` and `depth_gt`
/// inputs. With `data_term = "none"` and `correspondences.enabled = false` it is the only data:
/// the error that remains is the warp's (its graph and its regularisation), not the scan's.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct OracleParams {
    /// "off", "visible" or "all".
    pub mode: OracleMode,
    /// With "visible": a vertex is seen when its true depth is within this of `depth_gt` at its
    /// pixel, mm (as `eval.recon`'s split into seen and never seen).
    pub max_depth_gap_mm: f32,
}

impl Default for OracleParams {
    fn default() -> Self {
        OracleParams {
            mode: OracleMode::Off,
            max_depth_gap_mm: 1.0,
        }
    }
}

/// How the template is placed on the first frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum AlignMode {
    /// The given placement only (`translation_mm`, `rotation_deg`).
    #[default]
    Given,
    /// The given placement refined by rigid ICP against the first scan's distance field.
    Icp,
}

/// The one-time rigid alignment of the template.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct AlignParams {
    /// "given" or "icp".
    pub mode: AlignMode,
    /// world_from_template translation, mm (applied after the rotation).
    pub translation_mm: [f64; 3],
    /// world_from_template rotation as x, y, z Euler angles (roll, pitch, yaw), degrees.
    pub rotation_deg: [f64; 3],
    /// ICP: truncation of the alignment's distance field, mm; the given placement must bring
    /// the template within about this distance of the scan.
    pub truncation_mm: f64,
    /// ICP: voxel side of the alignment's distance field, mm.
    pub voxel_mm: f64,
    /// ICP: Gauss-Newton iterations at most.
    pub iterations: usize,
    /// ICP: Huber scale, mm (template parts the scan does not see count less beyond it).
    pub huber_mm: f64,
}

impl Default for AlignParams {
    fn default() -> Self {
        AlignParams {
            mode: AlignMode::Given,
            translation_mm: [0.0; 3],
            rotation_deg: [0.0; 3],
            truncation_mm: 10.0,
            voxel_mm: 1.0,
            iterations: 30,
            huber_mm: 1.0,
        }
    }
}

/// The per-frame distance field function.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct FieldParams {
    /// Voxel side, mm.
    pub voxel_mm: f64,
    /// Truncation, mm: voxels farther than this from every scan point are unknown, and a vertex
    /// there has no data term this frame.
    pub truncation_mm: f64,
    /// Refuse a scan whose field would need more voxels than this (a depth outlier far away
    /// stretches the box): the frame fails with a message instead of exhausting memory.
    pub max_voxels: usize,
    /// Half-size, in pixels, of the block of scan pixels averaged into each voxel (0: the
    /// nearest pixel only); about half the voxel's footprint (voxel * fx / depth / 2) smooths the
    /// scan's noise without blurring its shape.
    pub window_px: u32,
    /// Where the field is built: "cpu", "gpu" (an error without an adapter) or "auto".
    pub device: Device,
}

impl Default for FieldParams {
    fn default() -> Self {
        FieldParams {
            voxel_mm: 1.0,
            truncation_mm: 5.0,
            max_voxels: 16_000_000,
            window_px: 0,
            device: Device::Cpu,
        }
    }
}

/// Parameters of `fusion.template`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The pre-operative mesh (OBJ or PLY in mm, glTF in metres), relative to the working
    /// directory; without it the `template` input is read on the first frame. A mesh spanning
    /// more than 1 m along an axis is refused, naming its farthest vertex.
    pub template_path: Option<PathBuf>,
    /// Without a pre-operative mesh: the first frame's scan, triangulated on a pixel grid, is
    /// the template (e.g. `template_from_scan = { stride_px = 4, max_edge_mm = 3.0 }`); the
    /// given pose places it (it is already on the scan), and the later frames deform it. Set,
    /// it is used even when the `template` input is connected; with `template_path` it is an
    /// error.
    pub template_from_scan: Option<ScanTemplateParams>,
    /// "dff" (distance field), "projective" (back-projection) or "none" (the sparse
    /// correspondences and the oracle only).
    pub data_term: DataTerm,
    /// The distance field of each frame (with `data_term = "dff"`).
    pub field: FieldParams,
    /// The one-time rigid alignment.
    pub align: AlignParams,
    /// Deformation graph: spacing (mm), neighbours, sampling.
    pub graph: GraphParams,
    /// Energy weights and solver options (`weights.field` weighs the DFF term, `weights.data`
    /// the projective one).
    pub solver: SolverParams,
    /// "batch" or "decoupled".
    pub solver_kind: SolverKind,
    /// The decoupled split (with `solver_kind = "decoupled"`). Level II solves every unseen node
    /// by default here (`level2_rings = 0`): a template is one organ of bounded size, and its
    /// unseen side moves with it (on the phantom heart, 20 frames: 1.58 mm over the whole
    /// template with 3 rings, where the far side stayed behind; 0.26 mm with all).
    pub decoupled: DecoupledParams,
    /// Depth step (mm) to a neighbour above which a pixel gets no normal (occlusion edge).
    pub normal_max_step_mm: f32,
    /// epsilon_dv: a vertex is visible when the scan point it projects to is this close, mm.
    pub visible_distance_mm: f64,
    /// epsilon_nv: and its normal within this angle of the scan's, degrees.
    pub visible_angle_deg: f64,
    /// Colour the template from the left image (when the `stereo` input is connected).
    pub color: bool,
    /// Sparse correspondences (E_corr) from the `features` input: keypoints anchored to the
    /// deformed template at the end of a frame and matched on the next (as in `fusion.surfel`).
    pub correspondences: CorrParams,
    /// w_m of the motion prior E_m on the template's first solve (mm^-2; the larger of this and
    /// `solver.weights.motion` applies there; 0: off). The placed template is the model the
    /// surgeon trusts, and on the first frame no keypoint anchor holds it yet: fitted to noisy
    /// depth alone, the solve slid it along the surface, which the depth cannot see, and the
    /// anchors made after it kept the slide. Over 4 seeds, 40 frames: whole-template surface
    /// heart 0.329 to 0.313 mm, kidney 0.209 to 0.194, liver 0.255 to 0.244.
    pub first_frame_motion: f64,
    /// Surface samples for the data term: each template triangle adds the points of an n x n
    /// barycentric grid that are not its corners (edges shared once), bound to the graph like
    /// the vertices; the output mesh stays the template's vertices. 1: the vertices only. A
    /// coarse pre-operative mesh (vertices several mm apart) otherwise leaves few data rows per
    /// node.
    pub data_subdivision: u32,
    /// Ground-truth correspondences, for ablations on the phantom (default off).
    pub oracle: OracleParams,
    /// Also output the deformed template in the scope's frame (`mesh_camera`: the mesh seen from
    /// this frame's pose; what an overlay of the pre-operative model on the endoscope image
    /// takes). Off by default: a second copy of the mesh every frame (and in a recording).
    pub camera_mesh: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            template_path: None,
            template_from_scan: None,
            data_term: DataTerm::Dff,
            field: FieldParams::default(),
            align: AlignParams::default(),
            graph: GraphParams::default(),
            // Each factorisation also serves the next iteration (as in `fusion.surfel`).
            // The field's rows along the scan normal it stores (`field_jacobian`, see
            // `FieldJacobian::FieldNormal`): with it DFF is level with back-projection on the
            // liver's long run, where the warped model normal left it 1.5 % behind.
            solver: SolverParams {
                reuse_factorisation: 1,
                field_jacobian: FieldJacobian::FieldNormal,
                ..SolverParams::default()
            },
            solver_kind: SolverKind::Decoupled,
            decoupled: DecoupledParams {
                level2_rings: 0,
                ..Default::default()
            },
            normal_max_step_mm: 3.0,
            visible_distance_mm: 5.0,
            visible_angle_deg: 60.0,
            color: true,
            correspondences: CorrParams::default(),
            first_frame_motion: 3.0,
            data_subdivision: 1,
            oracle: OracleParams::default(),
            camera_mesh: false,
        }
    }
}

fn positive(v: f64, field: &str) -> Result<(), BuildError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(BuildError::param(field, format!("must be > 0, got {v}")))
    }
}

impl Params {
    pub(crate) fn check(&self) -> Result<(), BuildError> {
        misslam_deformation_ed::node::check_graph_and_solver(&self.graph, &self.solver)?;
        if let Some(t) = &self.template_from_scan {
            t.validate()
                .map_err(|m| BuildError::param("template_from_scan", m))?;
            if self.template_path.is_some() {
                return Err(BuildError::param(
                    "template_from_scan",
                    "set either template_path or template_from_scan, not both",
                ));
            }
        }
        positive(self.field.voxel_mm, "field.voxel_mm")?;
        positive(self.field.truncation_mm, "field.truncation_mm")?;
        if self.field.max_voxels == 0 {
            return Err(BuildError::param("field.max_voxels", "must be at least 1"));
        }
        positive(self.align.truncation_mm, "align.truncation_mm")?;
        self.correspondences
            .validate()
            .map_err(|m| BuildError::param("correspondences", m))?;
        positive(self.align.voxel_mm, "align.voxel_mm")?;
        positive(self.align.huber_mm, "align.huber_mm")?;
        if self.align.iterations == 0 && self.align.mode == AlignMode::Icp {
            return Err(BuildError::param(
                "align.iterations",
                "must be at least 1 with mode = \"icp\"",
            ));
        }
        for (k, v) in self
            .align
            .translation_mm
            .iter()
            .chain(&self.align.rotation_deg)
            .enumerate()
        {
            if !v.is_finite() {
                let name = if k < 3 {
                    "align.translation_mm"
                } else {
                    "align.rotation_deg"
                };
                return Err(BuildError::param(name, format!("must be finite, got {v}")));
            }
        }
        if !(self.first_frame_motion.is_finite() && self.first_frame_motion >= 0.0) {
            return Err(BuildError::param(
                "first_frame_motion",
                format!(
                    "must be a finite number >= 0, got {}",
                    self.first_frame_motion
                ),
            ));
        }
        if !(1..=8).contains(&self.data_subdivision) {
            return Err(BuildError::param(
                "data_subdivision",
                format!("must be 1 to 8, got {}", self.data_subdivision),
            ));
        }
        positive(self.normal_max_step_mm as f64, "normal_max_step_mm")?;
        positive(
            self.oracle.max_depth_gap_mm as f64,
            "oracle.max_depth_gap_mm",
        )?;
        if self.data_term == DataTerm::None
            && !self.correspondences.enabled
            && self.oracle.mode == OracleMode::Off
        {
            return Err(BuildError::param(
                "data_term",
                "\"none\" with `correspondences.enabled = false` and no `oracle` leaves nothing to pull the template onto the scan",
            ));
        }
        positive(self.visible_distance_mm, "visible_distance_mm")?;
        if !(self.visible_angle_deg > 0.0 && self.visible_angle_deg <= 180.0) {
            return Err(BuildError::param(
                "visible_angle_deg",
                "must be in (0, 180]",
            ));
        }
        Ok(())
    }

    /// The given placement, world_from_template.
    pub fn given_pose(&self) -> Isometry3<f64> {
        let [rx, ry, rz] = self.align.rotation_deg.map(f64::to_radians);
        let [tx, ty, tz] = self.align.translation_mm;
        Isometry3::from_parts(
            Translation3::new(tx, ty, tz),
            UnitQuaternion::from_euler_angles(rx, ry, rz),
        )
    }
}
