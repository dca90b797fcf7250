//! The priors that depend on what binds each node in a solve: the motion prior E_m on the nodes
//! some model point binds (`weights.motion`), its unseen part on those no data term binds
//! (`weights.unseen_motion`), and the E_rot and E_reg weights of those unbound nodes
//! (`weights.rot_unseen`, `weights.reg_unseen`). Set once per solve, read by the assembly and by
//! the cost alike.

use crate::graph::EdGraph;
use crate::problem::{Problem, SolverParams};
use crate::solver::SolveSet;
use misslam_framework::nalgebra::Vector3;

/// Per-solve node priors (buffers kept across solves).
#[derive(Default)]
pub(crate) struct NodePriors {
    /// The motion priors' references: (node, translation at the start of the solve, weight) of
    /// each solved node a model point binds (E_m) or no data term binds (its unseen part).
    motion_ref: Vec<(u32, Vector3<f64>, f64)>,
    /// Per node: what binds it (scratch of [`Self::set`]).
    bound: Vec<u8>,
    /// Per node: no data term binds it (empty unless `weights.rot_unseen` or
    /// `weights.reg_unseen` is set).
    unbound: Vec<bool>,
}

impl NodePriors {
    /// Sets the priors for a solve of `set` from the graph's state now: the translations of the
    /// solved nodes some model point binds (E_m, `weights.motion`) and of those no data term binds
    /// (`weights.unseen_motion`), each with its weight, and the nodes no data term binds.
    pub(crate) fn set(
        &mut self,
        graph: &EdGraph,
        problem: &Problem,
        set: &SolveSet,
        params: &SolverParams,
    ) {
        self.motion_ref.clear();
        self.unbound.clear();
        let w = &params.weights;
        let seen = if set.data { w.motion } else { 0.0 };
        let split = w.rot_unseen.is_some() || w.reg_unseen.is_some();
        if seen == 0.0 && w.unseen_motion == 0.0 && !split {
            return;
        }
        // Per node: bound by a model point (2), only by correspondences (1), by nothing (0).
        let bound = &mut self.bound;
        bound.clear();
        bound.resize(graph.len(), 0);
        if set.data {
            for c in problem.correspondences {
                for &x in &c.binding.nodes[..c.binding.len as usize] {
                    bound[x as usize] = 1;
                }
            }
            for b in problem.model.bindings {
                for &x in &b.nodes[..b.len as usize] {
                    bound[x as usize] = 2;
                }
            }
        }
        if split {
            self.unbound.extend(bound.iter().map(|&b| b == 0));
        }
        for &j in &set.free {
            let wm = match bound[j as usize] {
                2 => seen,
                1 => 0.0,
                _ => w.unseen_motion,
            };
            if wm > 0.0 {
                let p = &graph.warp[j as usize];
                self.motion_ref
                    .push((j, Vector3::new(p[3], p[7], p[11]), wm));
            }
        }
    }

    /// The motion priors: (node, reference translation, weight).
    pub(crate) fn motion_ref(&self) -> &[(u32, Vector3<f64>, f64)] {
        &self.motion_ref
    }

    /// The weights of E_rot and E_reg, node by node and edge by edge.
    pub(crate) fn weights(&self, params: &SolverParams) -> PriorWeights<'_> {
        let w = &params.weights;
        PriorWeights {
            rot: w.rot,
            reg: w.reg,
            rot_unseen: w.rot_unseen.unwrap_or(w.rot),
            reg_unseen: w.reg_unseen.unwrap_or(w.reg),
            unbound: &self.unbound,
        }
    }
}

/// `weights.rot` and `weights.reg`, or `weights.rot_unseen` on a node no data term binds and
/// `weights.reg_unseen` on an edge with such an end.
#[derive(Clone, Copy)]
pub(crate) struct PriorWeights<'a> {
    rot: f64,
    reg: f64,
    rot_unseen: f64,
    reg_unseen: f64,
    unbound: &'a [bool],
}

impl PriorWeights<'_> {
    #[inline]
    fn unbound(&self, j: u32) -> bool {
        self.unbound.get(j as usize).copied().unwrap_or(false)
    }

    /// w_rot of node `j`.
    #[inline]
    pub(crate) fn rot(&self, j: u32) -> f64 {
        if self.unbound(j) {
            self.rot_unseen
        } else {
            self.rot
        }
    }

    /// w_reg of the edge (j, k).
    #[inline]
    pub(crate) fn reg(&self, j: u32, k: u32) -> f64 {
        if self.unbound(j) || self.unbound(k) {
            self.reg_unseen
        } else {
            self.reg
        }
    }
}
