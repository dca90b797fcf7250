//! One pass over the model points at a state of the warp: each point warped into the camera frame
//! once, and from it the projective association, the data cost with that new association, the
//! data cost with a previous one (for the Levenberg-Marquardt test of a step), and the
//! distance-field cost. The assembly then reads the warped points instead of warping again.
//!
//! Sums run over fixed chunks of points in order, so the costs (and the steps they accept) do
//! not depend on the number of threads.

use crate::graph::EdGraph;
use crate::problem::{Problem, SolverParams};
use misslam_framework::nalgebra::{Isometry3, Vector3};
use rayon::prelude::*;

/// Points per chunk (fixed: the sums must not depend on the thread count).
const CHUNK: usize = 1024;

/// Points per group within a chunk: projected together, then their scan pixels loaded together.
const GROUP: usize = 32;

/// A projective association: model point i meets scan point `q` with normal `n` (camera frame).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Assoc {
    pub(crate) i: u32,
    pub(crate) q: Vector3<f64>,
    pub(crate) n: Vector3<f64>,
}

/// What one pass found at one state.
#[derive(Default)]
pub(crate) struct Pass {
    /// Every model point warped into the camera frame (empty without data terms on them).
    pub(crate) p_cam: Vec<Vector3<f64>>,
    /// The projective associations at this state, ascending point index.
    pub(crate) assoc: Vec<Assoc>,
    /// Model point -> index in `assoc` (u32::MAX when not associated).
    pub(crate) assoc_at: Vec<u32>,
    /// Projective cost with the new association plus the field cost.
    pub(crate) cost_new: f64,
    /// Projective cost with the previous association plus the field cost.
    pub(crate) cost_old: f64,
    chunks: Vec<(f64, f64, Vec<Assoc>)>,
}

/// The projective term's cost of model point `p` (camera frame) against scan point `q`, normal `n`.
#[inline]
fn projective_cost(p: &Vector3<f64>, a: &Assoc, params: &SolverParams) -> f64 {
    let w = &params.weights;
    let d = p - a.q;
    let rn = a.n.dot(&d);
    let r2 = rn * rn + w.point_to_point * d.norm_squared();
    w.data
        * params
            .robust
            .weight_cost(r2.sqrt(), params.robust_scale_mm)
            .1
}

impl Pass {
    /// Runs the pass at (`graph`, `pose`). With `associate`, finds the new association (the scan
    /// must be there); with `old`, also costs the previous pass's association at this state.
    pub(crate) fn run(
        &mut self,
        graph: &EdGraph,
        problem: &Problem,
        pose: &Isometry3<f64>,
        params: &SolverParams,
        associate: bool,
        old: Option<&Pass>,
    ) {
        let model = &problem.model;
        let n = model.points.len();
        self.assoc.clear();
        self.assoc_at.clear();
        self.cost_new = 0.0;
        self.cost_old = 0.0;
        let scan = problem.scan.filter(|_| associate);
        if scan.is_none() && problem.field.is_none() && old.is_none_or(|o| o.assoc.is_empty()) {
            self.p_cam.clear();
            return;
        }
        // The warp and the map into the camera's frame, folded into each node.
        let cam = graph.framed(&pose.inverse());
        let cos_max = params.max_normal_angle_deg.to_radians().cos();
        let max_d2 = params.max_distance_mm * params.max_distance_mm;
        let c = params.robust_scale_mm;
        let wf = params.weights.field;
        let old_at = old.map(|o| (&o.assoc_at[..], &o.assoc[..]));
        // Every point's entry is written below; the per-chunk lists keep their allocations from
        // pass to pass.
        self.p_cam.resize(n, Vector3::zeros());
        self.chunks.resize_with(n.div_ceil(CHUNK), Default::default);
        self.p_cam
            .par_chunks_mut(CHUNK)
            .zip(self.chunks.par_iter_mut())
            .enumerate()
            .for_each(|(ci, (out, (chunk_new, chunk_old, found)))| {
                let (mut c_new, mut c_old) = (0.0, 0.0);
                found.clear();
                // Runs of GROUP points in three steps: warp and project each; load the scan's
                // vertex and normal at every pixel hit (independent loads, so their cache
                // misses overlap: one at a time, these loads were most of the pass); then
                // the costs and the association, point by point in order as before.
                let mut pix = [None; GROUP];
                let mut at = [([0f32; 3], [0f32; 3]); GROUP];
                for (gi, group) in out.chunks_mut(GROUP).enumerate() {
                    let i0 = ci * CHUNK + gi * GROUP;
                    for (k, p_out) in group.iter_mut().enumerate() {
                        let i = i0 + k;
                        let p = cam.point(&model.points[i], &model.bindings[i]);
                        *p_out = p;
                        pix[k] = scan.and_then(|scan| scan.intrinsics.pixel(&p));
                    }
                    if let Some(scan) = scan {
                        for k in 0..group.len() {
                            if let Some(idx) = pix[k] {
                                at[k] = (scan.vertices[idx], scan.normals[idx]);
                            }
                        }
                    }
                    for (k, p) in group.iter().enumerate() {
                        let i = i0 + k;
                        if let Some(field) = problem.field {
                            if let Some((d, _)) = field.sample(p) {
                                let fc = wf * params.robust.weight_cost(d.abs(), c).1;
                                c_new += fc;
                                c_old += fc;
                            }
                        }
                        if let Some((at_old, assoc)) = old_at {
                            if let Some(a) = at_old.get(i).and_then(|&k| assoc.get(k as usize)) {
                                c_old += projective_cost(p, a, params);
                            }
                        }
                        if pix[k].is_none() {
                            continue;
                        }
                        let (q, sn) = at[k];
                        if !q.iter().chain(sn.iter()).all(|c| c.is_finite()) {
                            continue;
                        }
                        let q = Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64);
                        let sn = Vector3::new(sn[0] as f64, sn[1] as f64, sn[2] as f64);
                        if (p - q).norm_squared() > max_d2 {
                            continue;
                        }
                        if let Some(mn) = model.normals.get(i) {
                            let nc = cam.normal(mn, &model.bindings[i]);
                            if nc.dot(&sn) < cos_max {
                                continue;
                            }
                        }
                        let a = Assoc {
                            i: i as u32,
                            q,
                            n: sn,
                        };
                        c_new += projective_cost(p, &a, params);
                        found.push(a);
                    }
                }
                (*chunk_new, *chunk_old) = (c_new, c_old);
            });
        self.assoc_at.resize(n, u32::MAX);
        for (c_new, c_old, found) in &self.chunks {
            self.cost_new += c_new;
            self.cost_old += c_old;
            for a in found {
                self.assoc_at[a.i as usize] = self.assoc.len() as u32;
                self.assoc.push(*a);
            }
        }
    }
}
