//! Parallel, deterministic assembly of the data terms (projective E_data, distance-field E_data,
//! E_corr) into the block system.
//!
//! A data point bound to nodes j, k with weights w_j, w_k adds `w_j w_k M (x) (u_j u_k^T)` to block
//! (j, k), `w_j (b (x) u_j)` to node j's gradient and, with the pose among the unknowns,
//! `w_j (u_j (x) Q)` to node j's pose column, where M = R (sum w a a^T) R^T, b = R sum w r a and
//! Q = R sum w a J_xi over the point's residual rows (see [`crate::solver`]). The work is split in
//! three:
//!
//! 1. once per solve (the pattern and the bindings are fixed within it), every (point, node pair)
//!    coupling is listed under the 12x12 block it lands in, by a counting sort in point order
//!    (lazily, beside step 2 of the solve's first assembly: the two do not depend on each other);
//! 2. per iteration, a parallel pass over the points computes each point's M, b and Q into compact
//!    arrays, and sums the pose block in fixed chunks;
//! 3. each block then sums its own couplings (one task per block, nothing shared), and each
//!    solved node its gradient and pose column.
//!
//! Every sum runs in an order fixed by the data, so the system is the same on any number of
//! threads. The serial reference it is tested against is `Solver::linearize_dense_reference`.

use crate::evaluate::{Assoc, Pass};
use crate::graph::{Binding, EdGraph, MAX_K};
use crate::problem::{Correspondence, FieldJacobian, Problem, SolverParams};
use crate::system::BlockSystem;
use misslam_framework::nalgebra::{Isometry3, Matrix3, Point3, Vector3};
use rayon::prelude::*;

/// Points per chunk of the pose-block reduction (fixed, so the sum does not depend on threads).
const CHUNK: usize = 512;

/// Source bit of a coupling: set for a correspondence, clear for a model point.
const CORR: u32 = 1 << 31;

/// One coupling of a point to a block: the point, and the binding weights of the block's row
/// node and column node. `incidence` marks the coupling of a node with itself (a == c), which
/// also carries the node's gradient and pose column.
#[derive(Clone, Copy, Debug, Default)]
struct Coupling {
    src: u32,
    incidence: bool,
    w_row: f64,
    w_col: f64,
}

/// What a block sum reads per point: the 6 unique entries of M (world frame; all zero when the
/// point has no term this iteration) and the point.
#[derive(Clone, Copy, Debug, Default)]
struct PointTerm {
    m: [f64; 6],
    v: [f64; 3],
}

/// What a node sum reads per point: b and, with the pose, Q (3 rows of 6).
#[derive(Clone, Copy, Debug, Default)]
struct NodeTerm {
    b: [f64; 3],
    q: [[f64; 6]; 3],
}

/// Residual rows of one point: (a, r, weight) with r = a . (p_cam - target); up to five (the
/// projective plane and point rows, and the field row).
type Rows = ([(Vector3<f64>, f64, f64); 5], usize);

/// Buffers of the parallel assembly, reused across iterations and frames.
#[derive(Default)]
pub(crate) struct DataAssembly {
    couplings: Couplings,
    terms: Terms,
    /// The couplings are listed again at the next assembly ([`Self::invalidate`]).
    stale: bool,
}

/// Every (point, node pair) coupling under its block, listed once per solve.
#[derive(Default)]
struct Couplings {
    /// Per block: its couplings are `items[start[b]..start[b + 1]]`.
    start: Vec<u32>,
    items: Vec<Coupling>,
    /// Per block: (row node, column node).
    block_nodes: Vec<(u32, u32)>,
    /// Per solved slot: the index of its diagonal block and its node.
    diag: Vec<(u32, u32)>,
    /// Per list of couplings (a chunk of model points, then the correspondences), sorted by
    /// block (buffers kept across solves).
    sorted: Vec<SortedList>,
}

/// Each point's terms at the current state, computed per iteration.
#[derive(Default)]
struct Terms {
    model_pt: Vec<PointTerm>,
    model_nt: Vec<NodeTerm>,
    corr_pt: Vec<PointTerm>,
    corr_nt: Vec<NodeTerm>,
    /// A^-T of every node, for the warped normals of [`FieldJacobian::Normal`].
    normal_matrices: Vec<Matrix3<f64>>,
}

/// One list's couplings sorted by block: block b's are `out[start[b]..start[b + 1]]`.
#[derive(Default)]
struct SortedList {
    start: Vec<u32>,
    out: Vec<Coupling>,
    /// The couplings as found, with their block, and the counting sort's cursors.
    raw: Vec<(u32, Coupling)>,
    next: Vec<u32>,
}

impl SortedList {
    /// Lists the couplings of `bindings` (sources `first`, `first + 1`, ...) or, with `corr`,
    /// of the correspondences, and sorts them by block.
    fn build(
        &mut self,
        sys: &BlockSystem,
        nblocks: usize,
        first: u32,
        bindings: &[Binding],
        corr: Option<&[Correspondence]>,
    ) {
        self.raw.clear();
        let mut buf = [(0u32, Coupling::default()); 2 * MAX_K * MAX_K];
        let mut add = |k: usize, b: &Binding| {
            let n = couplings_of(sys, b, first + k as u32, &mut buf);
            self.raw.extend_from_slice(&buf[..n]);
        };
        match corr {
            Some(c) => c.iter().enumerate().for_each(|(k, c)| add(k, &c.binding)),
            None => bindings.iter().enumerate().for_each(|(k, b)| add(k, b)),
        }
        self.start.clear();
        self.start.resize(nblocks + 1, 0);
        for (blk, _) in &self.raw {
            self.start[*blk as usize + 1] += 1;
        }
        for b in 0..nblocks {
            self.start[b + 1] += self.start[b];
        }
        self.next.clear();
        self.next.extend_from_slice(&self.start[..nblocks]);
        // Every entry is written by the scatter: the buffer is not cleared first.
        self.out.resize(self.raw.len(), Coupling::default());
        for &(blk, c) in &self.raw {
            let p = &mut self.next[blk as usize];
            self.out[*p as usize] = c;
            *p += 1;
        }
    }
}

/// The couplings of one binding: (block index, coupling); at most 2 K^2.
fn couplings_of(
    sys: &BlockSystem,
    b: &Binding,
    src: u32,
    out: &mut [(u32, Coupling); 2 * MAX_K * MAX_K],
) -> usize {
    let n = b.len as usize;
    let mut len = 0;
    let mut push = |blk: usize, r: usize, c: usize| {
        out[len] = (
            blk as u32,
            Coupling {
                src,
                incidence: r == c,
                w_row: b.weights[r],
                w_col: b.weights[c],
            },
        );
        len += 1;
    };
    for a in 0..n {
        let sa = sys.slot[b.nodes[a] as usize];
        if sa == u32::MAX {
            continue;
        }
        for c in a..n {
            let sc = sys.slot[b.nodes[c] as usize];
            if sc == u32::MAX {
                continue;
            }
            if a == c {
                push(sys.find(sa, sa), a, a);
            } else if sa == sc {
                // The same node twice in one binding (never for a proper k-NN): both orders.
                push(sys.find(sa, sa), a, c);
                push(sys.find(sa, sa), c, a);
            } else if sa < sc {
                push(sys.find(sa, sc), a, c);
            } else {
                push(sys.find(sc, sa), c, a);
            }
        }
    }
    len
}

/// One point's terms from its rows (camera frame); adds its pose block (lower triangle,
/// row-major i * 6 + k) and pose gradient into `pose_acc` (36 + 6).
fn terms_of(
    rows: &Rows,
    p_cam: &Vector3<f64>,
    r_wc: &Matrix3<f64>,
    pose: bool,
    nt: &mut NodeTerm,
    pose_acc: &mut [f64; 42],
) -> [f64; 6] {
    let rows = &rows.0[..rows.1];
    let mut m_cam = Matrix3::zeros();
    let mut b_cam = Vector3::zeros();
    for (a, r, w) in rows {
        m_cam += *w * a * a.transpose();
        b_cam += *w * *r * a;
    }
    let m_w = r_wc * m_cam * r_wc.transpose();
    let b_w = r_wc * b_cam;
    nt.b = [b_w.x, b_w.y, b_w.z];
    if pose {
        let mut q_cam = [[0.0; 6]; 3];
        for (a, r, w) in rows {
            let axp = a.cross(p_cam);
            let jx = [-a.x, -a.y, -a.z, axp.x, axp.y, axp.z];
            for i in 0..6 {
                for k in 0..=i {
                    pose_acc[i * 6 + k] += w * jx[i] * jx[k];
                }
                pose_acc[36 + i] += w * jx[i] * r;
                for (mm, q) in q_cam.iter_mut().enumerate() {
                    q[i] += w * a[mm] * jx[i];
                }
            }
        }
        for i in 0..6 {
            for mm in 0..3 {
                nt.q[mm][i] = (0..3).map(|s| r_wc[(mm, s)] * q_cam[s][i]).sum();
            }
        }
    }
    [
        m_w[(0, 0)],
        m_w[(0, 1)],
        m_w[(0, 2)],
        m_w[(1, 1)],
        m_w[(1, 2)],
        m_w[(2, 2)],
    ]
}

/// Fills the terms of `n` points in parallel from `of(i) = (point, rows and p_cam)`; returns the
/// pose block and gradient, summed chunk by chunk in order.
fn fill<F>(
    pt: &mut Vec<PointTerm>,
    nt: &mut Vec<NodeTerm>,
    n: usize,
    r_wc: &Matrix3<f64>,
    pose: bool,
    of: F,
) -> [f64; 42]
where
    F: Fn(usize) -> (Vector3<f64>, Option<(Rows, Vector3<f64>)>) + Sync,
{
    // No clearing: the loop writes every point's v and m, and a point's node term wherever its
    // m is not zero (the only points whose node term is read).
    pt.resize(n, PointTerm::default());
    nt.resize(n, NodeTerm::default());
    let partials: Vec<[f64; 42]> = pt
        .par_chunks_mut(CHUNK)
        .zip(nt.par_chunks_mut(CHUNK))
        .enumerate()
        .map(|(ci, (pch, nch))| {
            let mut acc = [0.0; 42];
            for (k, (p, q)) in pch.iter_mut().zip(nch.iter_mut()).enumerate() {
                let (v, rows) = of(ci * CHUNK + k);
                p.v = [v.x, v.y, v.z];
                p.m = match rows {
                    Some((rows, p_cam)) => terms_of(&rows, &p_cam, r_wc, pose, q, &mut acc),
                    None => [0.0; 6],
                };
            }
            acc
        })
        .collect();
    let mut total = [0.0; 42];
    for p in &partials {
        for (t, x) in total.iter_mut().zip(p) {
            *t += x;
        }
    }
    total
}

/// The per-point arrays a sum reads.
struct Sources<'a> {
    model_pt: &'a [PointTerm],
    model_nt: &'a [NodeTerm],
    corr_pt: &'a [PointTerm],
    corr_nt: &'a [NodeTerm],
}

impl Sources<'_> {
    #[inline(always)]
    fn point(&self, src: u32) -> &PointTerm {
        if src & CORR != 0 {
            &self.corr_pt[(src & !CORR) as usize]
        } else {
            &self.model_pt[src as usize]
        }
    }

    #[inline(always)]
    fn node(&self, src: u32) -> &NodeTerm {
        if src & CORR != 0 {
            &self.corr_nt[(src & !CORR) as usize]
        } else {
            &self.model_nt[src as usize]
        }
    }
}

/// M is positive semi-definite: a zero trace means no term.
#[inline(always)]
fn is_zero(m: &[f64; 6]) -> bool {
    m[0] + m[3] + m[5] == 0.0
}

/// Index of (i, j) in the 10 unique entries of a symmetric 4x4.
const SYM4: [[usize; 4]; 4] = [[0, 1, 2, 3], [1, 4, 5, 6], [2, 5, 7, 8], [3, 6, 8, 9]];
/// Index of (i, j) in the 6 unique entries of a symmetric 3x3.
const SYM3: [[usize; 3]; 3] = [[0, 1, 2], [1, 3, 4], [2, 4, 5]];

/// One block's sum. Every coupling of a block has the same row node r and column node c, so with
/// h = u_r = [v - g_r; 1] and u_c = h + [g_r - g_c; 0] = h + delta,
/// `sum s M (x) (u_r u_c^T) = S + S_{.,3} delta^T` where `S = sum s M (x) (h h^T)`: per coupling
/// only the 6 x 10 unique products of the two symmetric factors, the 12x12 block once at the end.
#[inline(always)]
fn block_sum_body(
    items: &[Coupling],
    s: &Sources,
    gr: &Vector3<f64>,
    gc: &Vector3<f64>,
    out: &mut [f64; 144],
) {
    // acc[k][q]: k over the unique entries of h h^T (SYM4), q over those of M (SYM3), padded.
    let mut acc = [[0.0f64; 8]; 10];
    for it in items {
        let p = s.point(it.src);
        if is_zero(&p.m) {
            continue;
        }
        let scale = it.w_row * it.w_col;
        let mut m = [0.0f64; 8];
        for q in 0..6 {
            m[q] = p.m[q] * scale;
        }
        let h = [p.v[0] - gr.x, p.v[1] - gr.y, p.v[2] - gr.z];
        let hh = [
            h[0] * h[0],
            h[0] * h[1],
            h[0] * h[2],
            h[0],
            h[1] * h[1],
            h[1] * h[2],
            h[1],
            h[2] * h[2],
            h[2],
            1.0,
        ];
        for k in 0..10 {
            for q in 0..8 {
                acc[k][q] += hh[k] * m[q];
            }
        }
    }
    let delta = [gr.x - gc.x, gr.y - gc.y, gr.z - gc.z, 0.0];
    for sc in 0..3 {
        for e in 0..4 {
            let col = (sc * 4 + e) * 12;
            for mm in 0..3 {
                let q = SYM3[mm][sc];
                for c in 0..4 {
                    out[col + mm * 4 + c] += acc[SYM4[c][e]][q] + acc[SYM4[c][3]][q] * delta[e];
                }
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn block_sum_avx2(
    items: &[Coupling],
    s: &Sources,
    gr: &Vector3<f64>,
    gc: &Vector3<f64>,
    out: &mut [f64; 144],
) {
    block_sum_body(items, s, gr, gc, out);
}

fn block_sum(
    items: &[Coupling],
    s: &Sources,
    gr: &Vector3<f64>,
    gc: &Vector3<f64>,
    out: &mut [f64; 144],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { block_sum_avx2(items, s, gr, gc, out) };
        return;
    }
    block_sum_body(items, s, gr, gc, out);
}

/// A node's gradient and pose column from the incidences among its diagonal block's couplings.
fn node_sum(
    items: &[Coupling],
    s: &Sources,
    g_node: &Vector3<f64>,
    grad: &mut [f64],
    cross: Option<&mut [f64; 72]>,
) {
    let mut g = [0.0; 12];
    let mut x = [0.0; 72];
    for it in items.iter().filter(|it| it.incidence) {
        let p = s.point(it.src);
        if is_zero(&p.m) {
            continue;
        }
        let t = s.node(it.src);
        let wa = it.w_row;
        let u = [
            wa * (p.v[0] - g_node.x),
            wa * (p.v[1] - g_node.y),
            wa * (p.v[2] - g_node.z),
            wa,
        ];
        for mm in 0..3 {
            for c in 0..4 {
                g[mm * 4 + c] += t.b[mm] * u[c];
            }
        }
        if cross.is_some() {
            for pc in 0..6 {
                for mm in 0..3 {
                    for c in 0..4 {
                        x[pc * 12 + mm * 4 + c] += u[c] * t.q[mm][pc];
                    }
                }
            }
        }
    }
    for (o, v) in grad.iter_mut().zip(&g) {
        *o += v;
    }
    if let Some(cross) = cross {
        for (o, v) in cross.iter_mut().zip(&x) {
            *o += v;
        }
    }
}

impl Couplings {
    /// Lists every coupling of the problem's points under its block (once per solve: the
    /// pattern of `sys` and the bindings must not change until the next call).
    fn build(&mut self, sys: &BlockSystem, problem: &Problem) {
        // Per list (a chunk of model points, then the correspondences): its couplings, then
        // sorted by block with a counting sort, stable (point order within a block), each list
        // on its own and all in parallel; then each block gathers its runs list by list. Every
        // buffer keeps its allocation from solve to solve (they were fresh on every solve, a
        // few hundred kB a list).
        let nblocks = sys.blocks.len();
        let model = &problem.model.bindings;
        let nlists = model.len().div_ceil(CHUNK) + 1;
        self.sorted.resize_with(nlists, Default::default);
        self.sorted[..nlists]
            .par_iter_mut()
            .enumerate()
            .for_each(|(li, list)| {
                let (first, bindings) = if li + 1 < nlists {
                    let a = li * CHUNK;
                    (a as u32, &model[a..(a + CHUNK).min(model.len())])
                } else {
                    (CORR, &[][..])
                };
                let corr = (li + 1 == nlists).then_some(problem.correspondences);
                list.build(sys, nblocks, first, bindings, corr);
            });
        let sorted = &self.sorted[..nlists];
        self.start.clear();
        self.start.resize(nblocks + 1, 0);
        for b in 0..nblocks {
            let n: u32 = sorted.iter().map(|l| l.start[b + 1] - l.start[b]).sum();
            self.start[b + 1] = self.start[b] + n;
        }
        // Every coupling is written below: the buffer is not cleared first.
        self.items
            .resize(self.start[nblocks] as usize, Coupling::default());
        let mut parts = Vec::with_capacity(nblocks);
        let mut rest = &mut self.items[..];
        for b in 0..nblocks {
            let (head, tail) = rest.split_at_mut((self.start[b + 1] - self.start[b]) as usize);
            parts.push(head);
            rest = tail;
        }
        parts
            .into_par_iter()
            .enumerate()
            .with_min_len(8)
            .for_each(|(b, dst)| {
                let mut at = 0;
                for l in sorted {
                    let run = &l.out[l.start[b] as usize..l.start[b + 1] as usize];
                    dst[at..at + run.len()].copy_from_slice(run);
                    at += run.len();
                }
            });
        // Each block's node pair, from the slots.
        let mut node_of_slot = vec![0u32; sys.blocks_solved()];
        for (node, &s) in sys.slot.iter().enumerate() {
            if s != u32::MAX {
                node_of_slot[s as usize] = node as u32;
            }
        }
        self.block_nodes.clear();
        self.block_nodes.resize(nblocks, (0, 0));
        for (bj, &node_c) in node_of_slot.iter().enumerate() {
            for (idx, bi) in sys.column(bj as u32) {
                self.block_nodes[idx] = (node_of_slot[bi as usize], node_c);
            }
        }
        self.diag = node_of_slot
            .iter()
            .enumerate()
            .map(|(s, &node)| (sys.find(s as u32, s as u32) as u32, node))
            .collect();
    }
}

/// The field's value at `p` and the direction of its row: the trilinear gradient, or the field's
/// stored normal with [`FieldJacobian::FieldNormal`] (see [`FieldJacobian`]).
pub(crate) fn sample_field(
    field: &crate::DistanceField,
    p: &Vector3<f64>,
    params: &SolverParams,
) -> Option<(f64, Vector3<f64>)> {
    match params.field_jacobian {
        FieldJacobian::FieldNormal => field.sample_normal(p),
        FieldJacobian::Gradient | FieldJacobian::Normal => field.sample(p),
    }
}

impl Terms {
    /// Each model point's and correspondence's terms at the current state (the warped points
    /// and the association of `pass`, run at that state); returns the pose block and gradient.
    #[allow(clippy::too_many_arguments)]
    fn fill(
        &mut self,
        graph: &EdGraph,
        problem: &Problem,
        pose: &Isometry3<f64>,
        pose_on: bool,
        params: &SolverParams,
        pass: &Pass,
    ) -> [f64; 42] {
        let w = &params.weights;
        let cfw = pose.inverse();
        let r_wc = *pose.rotation.to_rotation_matrix().matrix();
        let model = &problem.model;
        let c = params.robust_scale_mm;
        let cam =
            |v: &Vector3<f64>, b: &Binding| (cfw * Point3::from(graph.warp_point(v, b))).coords;
        let none = (Vector3::zeros(), 0.0, 0.0);
        // The field row's Jacobian: the field's gradient, or its part along the warped model
        // normal (see `FieldJacobian`).
        let normal_jac = problem.field.is_some() && params.field_jacobian == FieldJacobian::Normal;
        if normal_jac {
            graph.normal_matrices_into(&mut self.normal_matrices);
        }
        let nmats = &self.normal_matrices;
        let r_cw = r_wc.transpose();
        let mut pose_acc = fill(
            &mut self.model_pt,
            &mut self.model_nt,
            model.points.len(),
            &r_wc,
            pose_on,
            |i| {
                let v = model.points[i];
                let mut rows: Rows = ([none; 5], 0);
                let proj = pass
                    .assoc_at
                    .get(i)
                    .and_then(|&k| pass.assoc.get(k as usize));
                if proj.is_none() && problem.field.is_none() {
                    return (v, None);
                }
                let p = pass
                    .p_cam
                    .get(i)
                    .copied()
                    .unwrap_or_else(|| cam(&v, &model.bindings[i]));
                if let Some(Assoc { q, n, .. }) = proj {
                    let d = p - q;
                    let rn = n.dot(&d);
                    let r2 = rn * rn + w.point_to_point * d.norm_squared();
                    let (rw, _) = params.robust.weight_cost(r2.sqrt(), c);
                    let wd = w.data * rw;
                    rows.0[0] = (*n, rn, wd);
                    rows.1 = 1;
                    if w.point_to_point > 0.0 {
                        let pp = w.point_to_point * wd;
                        rows.0[1] = (Vector3::x(), d.x, pp);
                        rows.0[2] = (Vector3::y(), d.y, pp);
                        rows.0[3] = (Vector3::z(), d.z, pp);
                        rows.1 = 4;
                    }
                }
                if let Some((dv, grad)) = problem.field.and_then(|f| sample_field(f, &p, params)) {
                    let (rw, _) = params.robust.weight_cost(dv.abs(), c);
                    let grad = if normal_jac {
                        let n =
                            r_cw * graph.warp_normal(&model.normals[i], &model.bindings[i], nmats);
                        n * n.dot(&grad)
                    } else {
                        grad
                    };
                    rows.0[rows.1] = (grad, dv, w.field * rw);
                    rows.1 += 1;
                }
                (v, (rows.1 > 0).then_some((rows, p)))
            },
        );
        let corr_acc = fill(
            &mut self.corr_pt,
            &mut self.corr_nt,
            problem.correspondences.len(),
            &r_wc,
            pose_on,
            |i| {
                let corr = &problem.correspondences[i];
                let p = cam(&corr.point, &corr.binding);
                let (r3, norm) = corr.rows(&p, w.corr_normal);
                let (rw, _) = params.robust.weight_cost(norm, c);
                let wc = w.corr * rw;
                let row = |k: usize| (r3[k].0, r3[k].1, wc * r3[k].2);
                let rows = [row(0), row(1), row(2), none, none];
                (corr.point, Some(((rows, 3), p)))
            },
        );
        for (t, k) in pose_acc.iter_mut().zip(&corr_acc) {
            *t += k;
        }
        pose_acc
    }
}

impl DataAssembly {
    /// The problem's points, their bindings or the system's pattern changed (a new solve): the
    /// couplings are listed again at the next assembly.
    pub(crate) fn invalidate(&mut self) {
        self.stale = true;
    }

    /// Adds the data terms at the current state to `sys` (whose pattern must not change
    /// between [`Self::invalidate`] calls), with the warped points and the association of
    /// `pass`, run at that state. After an invalidation the couplings are listed beside the
    /// points' terms (the two do not depend on each other).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn assemble(
        &mut self,
        sys: &mut BlockSystem,
        graph: &EdGraph,
        problem: &Problem,
        pose: &Isometry3<f64>,
        pose_on: bool,
        params: &SolverParams,
        pass: &Pass,
        grad_only: bool,
    ) {
        let (couplings, terms) = (&mut self.couplings, &mut self.terms);
        let fill = |terms: &mut Terms| terms.fill(graph, problem, pose, pose_on, params, pass);
        let pose_acc = if std::mem::take(&mut self.stale) {
            let sys = &*sys;
            rayon::join(|| couplings.build(sys, problem), || fill(terms)).1
        } else {
            fill(terms)
        };
        let (couplings, terms) = (&self.couplings, &self.terms);
        let src = Sources {
            model_pt: &terms.model_pt,
            model_nt: &terms.model_nt,
            corr_pt: &terms.corr_pt,
            corr_nt: &terms.corr_nt,
        };
        let (start, items) = (&couplings.start, &couplings.items);
        let list = |b: usize| &items[start[b] as usize..start[b + 1] as usize];
        let nodes = graph.nodes();
        let block_nodes = &couplings.block_nodes;
        let nb = sys.blocks_solved();
        let diag = &couplings.diag;
        let node_list = |s: usize| (list(diag[s].0 as usize), &nodes[diag[s].1 as usize]);
        if grad_only {
            // The gradient alone (the blocks and the pose block and columns are not written).
            sys.grad[..12 * nb]
                .par_chunks_mut(12)
                .enumerate()
                .for_each(|(s, g)| {
                    let (its, gn) = node_list(s);
                    node_sum(its, &src, gn, g, None);
                });
            if pose_on {
                let off = 12 * nb;
                for i in 0..6 {
                    sys.grad[off + i] += pose_acc[36 + i];
                }
            }
            return;
        }
        sys.blocks
            .par_iter_mut()
            .enumerate()
            .with_min_len(4)
            .for_each(|(b, blk)| {
                let its = list(b);
                if !its.is_empty() {
                    let (r, c) = block_nodes[b];
                    block_sum(its, &src, &nodes[r as usize], &nodes[c as usize], blk);
                }
            });
        let grads = sys.grad[..12 * nb].par_chunks_mut(12).enumerate();
        if pose_on {
            grads
                .zip(sys.pose_cross.par_iter_mut())
                .for_each(|((s, g), x)| {
                    let (its, gn) = node_list(s);
                    node_sum(its, &src, gn, g, Some(x));
                });
            let off = 12 * nb;
            for i in 0..6 {
                for k in 0..=i {
                    sys.pose_block[i * 6 + k] += pose_acc[i * 6 + k];
                }
                sys.grad[off + i] += pose_acc[36 + i];
            }
        } else {
            grads.for_each(|(s, g)| {
                let (its, gn) = node_list(s);
                node_sum(its, &src, gn, g, None);
            });
        }
    }
}
