//! One ED solve per frame, batch or decoupled, behind one call: what the `deformation.*` nodes and
//! the fusion nodes share. A diverged solve resets the warp and reports an error naming the frame.

use crate::decoupled::{DecoupledInfo, DecoupledParams, DecoupledSolver};
use crate::graph::EdGraph;
use crate::problem::{Problem, SolverParams};
use crate::solver::{Info, SolveSet, Solver};
use misslam_framework::nalgebra::Isometry3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Which ED solver runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SolverKind {
    /// All nodes at once.
    Batch,
    /// PR then PI (the thesis's two-step solver).
    #[default]
    Decoupled,
}

/// A solver of either kind, keeping its symbolic factorisations between frames.
pub enum Engine {
    /// `deformation.batch`.
    Batch(Box<Solver>),
    /// `deformation.decoupled`.
    Decoupled(Box<DecoupledSolver>),
}

impl Engine {
    /// A fresh solver of `kind`.
    pub fn new(kind: SolverKind) -> Self {
        match kind {
            SolverKind::Batch => Engine::Batch(Box::default()),
            SolverKind::Decoupled => Engine::Decoupled(Box::default()),
        }
    }

    /// Solves one frame, updating `graph.warp` and `pose` (`decoupled` is read by the decoupled
    /// solver only). Returns the combined figures and, for the decoupled solver, its split. If
    /// the warp comes out non-finite it is reset to identity and the frame is an error.
    pub fn solve(
        &mut self,
        frame: u64,
        graph: &mut EdGraph,
        pose: &mut Isometry3<f64>,
        problem: &Problem,
        params: &SolverParams,
        decoupled: &DecoupledParams,
    ) -> Result<(Info, Option<DecoupledInfo>), String> {
        let start = *pose;
        let result = match self {
            Engine::Batch(s) => {
                let set = SolveSet::all(graph, params.optimize_pose);
                s.solve(graph, pose, problem, &set, params)
                    .map(|info| (info, None))
            }
            Engine::Decoupled(s) => s
                .solve(graph, pose, problem, params, decoupled)
                .map(|d| (d.combined(), Some(d))),
        };
        let finite = graph.warp.iter().flatten().all(|x| x.is_finite())
            && pose.translation.vector.iter().all(|x| x.is_finite())
            && pose.rotation.coords.iter().all(|x| x.is_finite());
        if !finite {
            graph.reset();
            *pose = start;
            return Err(format!(
                "the deformation solve of frame {frame} diverged; the warp was reset"
            ));
        }
        result
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::GraphParams;
    use crate::problem::ModelPoints;
    use misslam_framework::nalgebra::Vector3;

    #[test]
    fn a_diverged_warp_is_reset_and_reported_with_its_frame() {
        let pts: Vec<Vector3<f64>> = (0..40)
            .map(|i| Vector3::new((i % 8) as f64 * 5.0, (i / 8) as f64 * 5.0, 50.0))
            .collect();
        let mut graph = EdGraph::from_points(
            &pts,
            GraphParams {
                spacing: 10.0,
                ..Default::default()
            },
        )
        .unwrap();
        let problem = Problem {
            model: ModelPoints::EMPTY,
            scan: None,
            field: None,
            correspondences: &[],
            pose_prior: Isometry3::identity(),
        };
        for kind in [SolverKind::Batch, SolverKind::Decoupled] {
            let mut engine = Engine::new(kind);
            let mut pose = Isometry3::identity();
            // A warp that is already non-finite stays so through a solve without data.
            graph.warp[0][0] = f64::NAN;
            let err = engine
                .solve(
                    17,
                    &mut graph,
                    &mut pose,
                    &problem,
                    &SolverParams::default(),
                    &DecoupledParams::default(),
                )
                .unwrap_err();
            assert!(err.contains("frame 17"), "{err}");
            assert!(graph.warp.iter().flatten().all(|x| x.is_finite()));
            assert_eq!(pose, Isometry3::identity());
        }
    }
}
