//! The efficient two-step optimisation (method.md section 4): nodes split into PR (some point of
//! the data terms depends on them) and PI (none does).
//!
//! - Level I solves the PR nodes (and the pose) with every data term and the E_rot / E_reg terms
//!   among PR nodes; PR-PI edges are cut (`boundary = "cut"`) or kept with the PI end held at its
//!   current value (`boundary = "anchor"`).
//! - Level II solves PI nodes with E_rot / E_reg only, PR fixed at the level I result, so the unseen
//!   part follows as rigidly as possible. It touches only the PI nodes within `level2_rings` graph
//!   hops of PR (0 = every PI node), so its cost depends on the visible region, not on the map.
//!
//! Lossy by design (the exact alternative, marginalising PI by a Schur complement, costs what the
//! batch solve costs).

use crate::graph::EdGraph;
use crate::problem::{Problem, SolverParams};
use crate::solver::{Info, SolveSet, Solver};
use misslam_framework::nalgebra::Isometry3;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;

/// What happens to the E_reg edges between PR and PI nodes in level I.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Boundary {
    /// Dropped (the method's "cut").
    #[default]
    Cut,
    /// Kept, with the PI end held at its current value.
    Anchor,
}

/// Options of the decoupled solver.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DecoupledParams {
    /// PR-PI edges in level I.
    pub boundary: Boundary,
    /// Level II solves the PI nodes within this many graph hops of PR (0 = all PI nodes).
    pub level2_rings: u32,
    /// Iterations of level II (its energy is nearly linear: 1 or 2 suffice).
    pub level2_iterations: usize,
}

impl Default for DecoupledParams {
    fn default() -> Self {
        DecoupledParams {
            boundary: Boundary::Cut,
            level2_rings: 3,
            level2_iterations: 2,
        }
    }
}

/// What the two levels did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DecoupledInfo {
    /// Level I.
    pub level1: Info,
    /// Level II.
    pub level2: Info,
    /// PR nodes.
    pub pr_nodes: usize,
    /// PI nodes solved in level II.
    pub pi_solved: usize,
}

impl DecoupledInfo {
    /// Both levels as one summary (cost of level I, times added).
    pub fn combined(&self) -> Info {
        let (a, b) = (&self.level1, &self.level2);
        Info {
            iterations: a.iterations + b.iterations,
            cost_before: a.cost_before,
            cost_after: a.cost_after,
            costs: a.costs.clone(),
            rejected_steps: a.rejected_steps + b.rejected_steps,
            factorisations: a.factorisations + b.factorisations,
            reused_factorisations: a.reused_factorisations + b.reused_factorisations,
            solved_nodes: a.solved_nodes + b.solved_nodes,
            data_terms: a.data_terms,
            symbolic_builds: a.symbolic_builds + b.symbolic_builds,
            ms_associate: a.ms_associate + b.ms_associate,
            ms_assemble: a.ms_assemble + b.ms_assemble,
            ms_factor: a.ms_factor + b.ms_factor,
            ms_prepare: a.ms_prepare + b.ms_prepare,
            ms_total: a.ms_total + b.ms_total,
        }
    }
}

/// The decoupled solver: two [`Solver`]s so each level keeps its own symbolic factorisation.
#[derive(Default)]
pub struct DecoupledSolver {
    level1: Solver,
    level2: Solver,
    last: DecoupledInfo,
}

/// PR nodes: those any data point (model point or correspondence) is bound to with a weight > 0.
pub fn relevant_nodes(graph: &EdGraph, problem: &Problem) -> Vec<bool> {
    let mut pr = vec![false; graph.len()];
    let bindings = problem
        .model
        .bindings
        .iter()
        .chain(problem.correspondences.iter().map(|c| &c.binding));
    for b in bindings {
        for (j, w) in b.iter() {
            if w > 0.0 {
                pr[j as usize] = true;
            }
        }
    }
    pr
}

impl DecoupledSolver {
    /// Symbolic factorisations computed by (level I, level II).
    pub fn symbolic_builds(&self) -> (usize, usize) {
        (self.level1.symbolic_builds(), self.level2.symbolic_builds())
    }

    /// What the last solve did.
    pub fn solve_info(&self) -> &DecoupledInfo {
        &self.last
    }

    /// Solves level I then level II, updating `graph.warp` and `pose`.
    pub fn solve(
        &mut self,
        graph: &mut EdGraph,
        pose: &mut Isometry3<f64>,
        problem: &Problem,
        params: &SolverParams,
        dparams: &DecoupledParams,
    ) -> Result<DecoupledInfo, String> {
        let pr = relevant_nodes(graph, problem);
        let n = graph.len();
        // Level I.
        let free1: Vec<u32> = (0..n as u32).filter(|&j| pr[j as usize]).collect();
        let mut edges1 = Vec::new();
        for &j in &free1 {
            for &k in graph.neighbors(j as usize) {
                let keep = match dparams.boundary {
                    Boundary::Cut => pr[k as usize],
                    Boundary::Anchor => true,
                };
                if keep {
                    edges1.push((j, k));
                    if !pr[k as usize] {
                        // The reverse direction also constrains j (through t_j): keep it with k fixed.
                        edges1.push((k, j));
                    }
                }
            }
        }
        let set1 = SolveSet {
            free: free1,
            reg_edges: edges1,
            data: true,
            pose: params.optimize_pose,
        };
        let level1 = if set1.free.is_empty() {
            Info::default()
        } else {
            self.level1.solve(graph, pose, problem, &set1, params)?
        };
        // Level II: PI nodes within the rings.
        let mut dist = vec![u32::MAX; n];
        let mut queue = VecDeque::new();
        for j in 0..n {
            if pr[j] {
                dist[j] = 0;
                queue.push_back(j);
            }
        }
        while let Some(j) = queue.pop_front() {
            if dparams.level2_rings > 0 && dist[j] >= dparams.level2_rings {
                continue;
            }
            for &k in graph.neighbors(j) {
                if dist[k as usize] == u32::MAX {
                    dist[k as usize] = dist[j] + 1;
                    queue.push_back(k as usize);
                }
            }
        }
        let all_pi = dparams.level2_rings == 0;
        let free2: Vec<u32> = (0..n as u32)
            .filter(|&j| !pr[j as usize] && (all_pi || dist[j as usize] != u32::MAX))
            .collect();
        let mut is_free2 = vec![false; n];
        for &j in &free2 {
            is_free2[j as usize] = true;
        }
        let mut edges2 = Vec::new();
        for j in 0..n {
            for &k in graph.neighbors(j) {
                if is_free2[j] || is_free2[k as usize] {
                    edges2.push((j as u32, k));
                }
            }
        }
        let pi_solved = free2.len();
        let set2 = SolveSet {
            free: free2,
            reg_edges: edges2,
            data: false,
            pose: false,
        };
        let level2 = if set2.free.is_empty() {
            Info::default()
        } else {
            let p2 = SolverParams {
                max_iterations: dparams.level2_iterations.max(1),
                optimize_pose: false,
                ..params.clone()
            };
            let mut fixed_pose = *pose;
            self.level2
                .solve(graph, &mut fixed_pose, problem, &set2, &p2)?
        };
        self.last = DecoupledInfo {
            level1,
            level2,
            pr_nodes: set1.free.len(),
            pi_solved,
        };
        Ok(self.last.clone())
    }
}
