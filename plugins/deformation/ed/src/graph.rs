//! The embedded deformation graph (Sumner, Schmid, Pauly 2007): nodes g_j sampled on the model at
//! spacing epsilon, each with an affine part A_j and a translation t_j; a point v is deformed by its
//! k nearest nodes,
//!
//! ```text
//! v~ = sum_j w_j(v) [ A_j (v - g_j) + g_j + t_j ],   n~ = normalise( sum_j w_j(v) A_j^-T n ),
//! w_j(v) = (1 - |v - g_j| / d_max)^2 normalised to sum 1, d_max = distance to the (k+1)-th node.
//! ```
//!
//! Node positions and bound points live in the canonical (reference) frame; the warp maps them to
//! the live (world) frame. Each node's unknowns are the 3x4 matrix `[A_j | t_j]` stored row-major
//! (`P[r * 4 + c]`, column 3 is t), the layout the solver's Jacobians use.

use crate::knn::GridIndex;
use crate::sampling::{poisson_disc, voxel_sample};
use misslam_framework::geometry::arr3;
use misslam_framework::nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Vector3};
use rayon::prelude::*;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Largest number of nodes one point may be bound to.
pub const MAX_K: usize = 8;

/// The identity warp of one node: A = I, t = 0.
pub const IDENTITY: [f64; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];

/// How nodes are sampled on a point set.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Sampling {
    /// Poisson disc: points are taken in order and kept when no kept node lies within the spacing.
    #[default]
    PoissonDisc,
    /// Uniform voxel grid of side `spacing`: per occupied voxel, the point nearest its centroid.
    Voxel,
}

/// Graph construction parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct GraphParams {
    /// Node spacing epsilon, mm (the literature uses 5 to 25 mm; tissue a few mm).
    pub spacing: f64,
    /// Node-to-node graph: each node is joined to this many nearest nodes (the union of the
    /// k-nearest relations is the edge set, so it is symmetric).
    pub node_neighbors: usize,
    /// Nodes that deform one point (k; Sumner uses 4). At most 8.
    pub point_neighbors: usize,
    /// Sampling scheme.
    pub sampling: Sampling,
}

impl Default for GraphParams {
    fn default() -> Self {
        GraphParams {
            spacing: 8.0,
            node_neighbors: 6,
            point_neighbors: 4,
            sampling: Sampling::PoissonDisc,
        }
    }
}

impl GraphParams {
    /// Checks ranges, naming the field.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.spacing.is_finite() && self.spacing > 0.0) {
            return Err(format!(
                "spacing must be a positive number of mm, got {}",
                self.spacing
            ));
        }
        if self.node_neighbors == 0 || self.node_neighbors > 32 {
            return Err(format!(
                "node_neighbors must be in 1..=32, got {}",
                self.node_neighbors
            ));
        }
        if self.point_neighbors == 0 || self.point_neighbors > MAX_K {
            return Err(format!(
                "point_neighbors must be in 1..={MAX_K}, got {}",
                self.point_neighbors
            ));
        }
        Ok(())
    }
}

/// The nodes that deform one point and their weights (sum 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Binding {
    /// Node indices; the first `len` are used.
    pub nodes: [u32; MAX_K],
    /// Weights w_j, summing to 1.
    pub weights: [f64; MAX_K],
    /// Number of nodes used (0 when the graph is empty).
    pub len: u8,
    /// The support radius d_max the weights were computed with, rounded up to f32 (it fits the
    /// struct's padding): a node added farther than this from the point leaves the binding as it
    /// is ([`NewNodes::reach`]). 0 for an empty binding.
    pub support: f32,
}

impl Binding {
    /// No node (the point does not move).
    pub const EMPTY: Binding = Binding {
        nodes: [0; MAX_K],
        weights: [0.0; MAX_K],
        len: 0,
        support: 0.0,
    };

    /// (node, weight) pairs.
    pub fn iter(&self) -> impl Iterator<Item = (u32, f64)> + '_ {
        (0..self.len as usize).map(|i| (self.nodes[i], self.weights[i]))
    }
}

/// An embedded deformation graph.
#[derive(Clone, Debug)]
pub struct EdGraph {
    params: GraphParams,
    /// Node positions g_j (canonical frame), mm.
    nodes: Vec<Vector3<f64>>,
    /// `[A_j | t_j]` row-major per node.
    pub warp: Vec<[f64; 12]>,
    /// Sorted neighbour lists (symmetric).
    neighbors: Vec<Vec<u32>>,
    index: GridIndex,
    topology: u64,
}

/// New nodes up to this many are checked one by one in [`NewNodes::reach`], more through a grid.
const REBIND_SCAN_MAX: usize = 32;

/// Nodes just added to a graph ([`EdGraph::new_nodes`]).
pub struct NewNodes<'a> {
    new: &'a [Vector3<f64>],
    lo: Vector3<f64>,
    hi: Vector3<f64>,
    index: Option<GridIndex>,
    all: bool,
}

impl NewNodes<'_> {
    /// Whether the new nodes change the binding `b` of point `v` (made before they came): a
    /// node farther from `v` than the binding's support is neither among its k nearest nor
    /// nearer than its (k + 1)-th, so its nodes and weights stay. Every binding when the graph
    /// had no more than k nodes before (the support came from its k-th node, or there was no
    /// binding); else an empty binding (a non-finite point) stays empty.
    pub fn reach(&self, v: &Vector3<f64>, b: &Binding) -> bool {
        if self.new.is_empty() {
            return false;
        }
        if self.all {
            return true;
        }
        if b.len == 0 {
            return false;
        }
        let r = b.support as f64;
        if (0..3).any(|a| v[a] < self.lo[a] - r || v[a] > self.hi[a] + r) {
            return false;
        }
        match &self.index {
            Some(index) => index.nearest_within(self.new, v, r).is_some(),
            None => self.new.iter().any(|g| (g - v).norm_squared() <= r * r),
        }
    }
}

/// The smallest f32 at or above `x` (non-negative, finite).
fn round_up_f32(x: f64) -> f32 {
    let f = x as f32;
    if (f as f64) < x {
        f32::from_bits(f.to_bits() + 1)
    } else {
        f
    }
}

/// Applies one node's warp to `v`: A (v - g) + g + t.
#[inline]
pub fn apply_node(p: &[f64; 12], g: &Vector3<f64>, v: &Vector3<f64>) -> Vector3<f64> {
    let d = v - g;
    Vector3::new(
        p[0] * d.x + p[1] * d.y + p[2] * d.z + p[3] + g.x,
        p[4] * d.x + p[5] * d.y + p[6] * d.z + p[7] + g.y,
        p[8] * d.x + p[9] * d.y + p[10] * d.z + p[11] + g.z,
    )
}

/// The affine part A of a node's warp.
#[inline]
pub fn affine(p: &[f64; 12]) -> Matrix3<f64> {
    Matrix3::new(p[0], p[1], p[2], p[4], p[5], p[6], p[8], p[9], p[10])
}

/// The translation t of a node's warp.
#[inline]
pub fn translation(p: &[f64; 12]) -> Vector3<f64> {
    Vector3::new(p[3], p[7], p[11])
}

/// The warp followed by a rigid map `to` (into the camera's frame, say), folded into each node:
/// `to * warp(v) = sum_j w_j (M_j v + c_j)`, with `M_j = R A_j` and `c_j = R (g_j + t_j - A_j
/// g_j) + t`, as a binding's weights sum to one; and the warped unit normal turned by R, through
/// `R A_j^-T`. Per point about half the arithmetic of the warp and then the map
/// ([`EdGraph::framed`]).
pub struct FramedWarp {
    to: Isometry3<f64>,
    m: Vec<Matrix3<f64>>,
    c: Vec<Vector3<f64>>,
    n: Vec<Matrix3<f64>>,
}

impl FramedWarp {
    /// `to * warp(v)` for canonical point `v` bound by `b`.
    #[inline]
    pub fn point(&self, v: &Vector3<f64>, b: &Binding) -> Vector3<f64> {
        if b.len == 0 {
            return (self.to * Point3::from(*v)).coords;
        }
        let mut out = Vector3::zeros();
        for (j, w) in b.iter() {
            let j = j as usize;
            out += w * (self.m[j] * v + self.c[j]);
        }
        out
    }

    /// `R * warp_normal(n)` for unit normal `n` bound by `b` ([`EdGraph::warp_normal`]).
    #[inline]
    pub fn normal(&self, n: &Vector3<f64>, b: &Binding) -> Vector3<f64> {
        let turned = self.to.rotation * n;
        if b.len == 0 {
            return turned;
        }
        let mut out = Vector3::zeros();
        for (j, w) in b.iter() {
            out += w * (self.n[j as usize] * n);
        }
        out.try_normalize(1e-12).unwrap_or(turned)
    }
}

impl EdGraph {
    /// The warp followed by `to`, folded into each node ([`FramedWarp`]).
    pub fn framed(&self, to: &Isometry3<f64>) -> FramedWarp {
        let r = to.rotation.to_rotation_matrix().into_inner();
        let mut f = FramedWarp {
            to: *to,
            m: Vec::with_capacity(self.len()),
            c: Vec::with_capacity(self.len()),
            n: Vec::with_capacity(self.len()),
        };
        for (p, g) in self.warp.iter().zip(&self.nodes) {
            let a = affine(p);
            f.m.push(r * a);
            f.c.push(r * (g + translation(p) - a * g) + to.translation.vector);
            let nm = a
                .try_inverse()
                .map(|m| m.transpose())
                .unwrap_or_else(Matrix3::identity);
            f.n.push(r * nm);
        }
        f
    }

    /// Samples nodes on `points` (canonical frame); every warp starts at the identity.
    pub fn from_points(points: &[Vector3<f64>], params: GraphParams) -> Result<Self, String> {
        params.validate()?;
        let mut graph = EdGraph {
            params,
            nodes: Vec::new(),
            warp: Vec::new(),
            neighbors: Vec::new(),
            index: GridIndex::default(),
            topology: 0,
        };
        let nodes = match graph.params.sampling {
            Sampling::PoissonDisc => poisson_disc(points, &[], graph.params.spacing),
            Sampling::Voxel => voxel_sample(points, graph.params.spacing),
        };
        if nodes.is_empty() {
            return Err("no finite point to sample deformation nodes from".into());
        }
        graph.warp = vec![IDENTITY; nodes.len()];
        graph.nodes = nodes;
        graph.rebuild();
        Ok(graph)
    }

    /// A graph on given node positions (tests, templates with hand-placed nodes).
    pub fn from_nodes(nodes: Vec<Vector3<f64>>, params: GraphParams) -> Result<Self, String> {
        params.validate()?;
        if nodes.is_empty() || nodes.iter().any(|g| !g.iter().all(|c| c.is_finite())) {
            return Err("node positions must be finite and not empty".into());
        }
        let mut graph = EdGraph {
            params,
            warp: vec![IDENTITY; nodes.len()],
            nodes,
            neighbors: Vec::new(),
            index: GridIndex::default(),
            topology: 0,
        };
        graph.rebuild();
        Ok(graph)
    }

    fn rebuild(&mut self) {
        self.index = GridIndex::build(&self.nodes, self.params.spacing);
        let k = self.params.node_neighbors;
        let knn: Vec<Vec<u32>> = (0..self.nodes.len())
            .into_par_iter()
            .map_init(Vec::new, |buf, j| {
                self.index.knn(&self.nodes, &self.nodes[j], k + 1, buf);
                buf.iter()
                    .map(|e| e.1)
                    .filter(|&i| i as usize != j)
                    .take(k)
                    .collect()
            })
            .collect();
        let mut neighbors = vec![Vec::new(); self.nodes.len()];
        for (j, list) in knn.iter().enumerate() {
            for &i in list {
                neighbors[j].push(i);
                neighbors[i as usize].push(j as u32);
            }
        }
        for list in &mut neighbors {
            list.sort_unstable();
            list.dedup();
        }
        self.neighbors = neighbors;
        self.topology += 1;
    }

    /// Parameters the graph was built with.
    pub fn params(&self) -> &GraphParams {
        &self.params
    }

    /// Node positions g_j (canonical).
    pub fn nodes(&self) -> &[Vector3<f64>] {
        &self.nodes
    }

    /// Number of nodes.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// True without nodes (never, for a constructed graph).
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Neighbours of node `j` (sorted).
    pub fn neighbors(&self, j: usize) -> &[u32] {
        &self.neighbors[j]
    }

    /// Undirected edges (j < k).
    pub fn edges(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        self.neighbors.iter().enumerate().flat_map(|(j, l)| {
            l.iter()
                .filter(move |&&k| k as usize > j)
                .map(move |&k| (j as u32, k))
        })
    }

    /// Increments whenever nodes or edges change (solvers key their symbolic factorisations on it).
    pub fn topology_version(&self) -> u64 {
        self.topology
    }

    /// Resets every node to the identity warp.
    pub fn reset(&mut self) {
        self.warp.iter_mut().for_each(|p| *p = IDENTITY);
    }

    /// Binds a canonical point to its k nearest nodes with Sumner's weights.
    pub fn bind(&self, v: &Vector3<f64>) -> Binding {
        let mut buf = Vec::with_capacity(MAX_K + 1);
        self.bind_into(v, &mut buf)
    }

    /// [`Self::bind`] with a reused search buffer (no allocation).
    pub fn bind_into(&self, v: &Vector3<f64>, buf: &mut Vec<(f64, u32)>) -> Binding {
        let k = self.params.point_neighbors.min(self.nodes.len());
        self.index.knn(&self.nodes, v, k + 1, buf);
        if buf.len() < k || k == 0 {
            return Binding::EMPTY;
        }
        let d_max = if buf.len() > k {
            buf[k].0.sqrt()
        } else {
            // Fewer than k + 1 nodes in all: the farthest one bounds the support.
            buf[k - 1].0.sqrt() * 1.5 + 1e-9
        };
        let mut b = Binding::EMPTY;
        let mut sum = 0.0;
        for (i, &(d2, j)) in buf.iter().take(k).enumerate() {
            let w = (1.0 - d2.sqrt() / d_max).max(0.0).powi(2);
            b.nodes[i] = j;
            b.weights[i] = w;
            sum += w;
        }
        b.len = k as u8;
        b.support = round_up_f32(d_max);
        if sum > 1e-12 {
            b.weights[..k].iter_mut().for_each(|w| *w /= sum);
        } else {
            // Equidistant from k + 1 nodes: share equally.
            b.weights[..k].iter_mut().for_each(|w| *w = 1.0 / k as f64);
        }
        b
    }

    /// Binds many points (in parallel).
    pub fn bind_all(&self, points: &[Vector3<f64>]) -> Vec<Binding> {
        points
            .par_iter()
            .map_init(
                || Vec::with_capacity(MAX_K + 1),
                |buf, v| self.bind_into(v, buf),
            )
            .collect()
    }

    /// What the nodes from index `first_new` on (added by [`Self::grow`]) can change: see
    /// [`NewNodes::reach`].
    pub fn new_nodes(&self, first_new: usize) -> NewNodes<'_> {
        let new = &self.nodes[first_new.min(self.nodes.len())..];
        let (mut lo, mut hi) = (
            Vector3::repeat(f64::INFINITY),
            Vector3::repeat(f64::NEG_INFINITY),
        );
        for g in new {
            lo = lo.inf(g);
            hi = hi.sup(g);
        }
        NewNodes {
            new,
            lo,
            hi,
            // A few new nodes (a frame's growth) are checked one by one; many (a first frame's)
            // through a grid of their own.
            index: (new.len() > REBIND_SCAN_MAX)
                .then(|| GridIndex::build(new, self.params.spacing)),
            // The support came from the k-th node, not the (k + 1)-th: every binding changes.
            all: !new.is_empty() && first_new <= self.params.point_neighbors,
        }
    }

    /// The warped position of canonical point `v` bound by `b`.
    #[inline]
    pub fn warp_point(&self, v: &Vector3<f64>, b: &Binding) -> Vector3<f64> {
        if b.len == 0 {
            return *v;
        }
        let mut out = Vector3::zeros();
        for (j, w) in b.iter() {
            out += w * apply_node(&self.warp[j as usize], &self.nodes[j as usize], v);
        }
        out
    }

    /// [`Self::normal_matrices`] into a reused buffer.
    pub fn normal_matrices_into(&self, out: &mut Vec<Matrix3<f64>>) {
        out.clear();
        out.extend(self.warp.iter().map(|p| {
            affine(p)
                .try_inverse()
                .map(|m| m.transpose())
                .unwrap_or_else(Matrix3::identity)
        }));
    }

    /// A^-T of every node (for normals); a singular A maps normals as the identity would.
    pub fn normal_matrices(&self) -> Vec<Matrix3<f64>> {
        let mut m = Vec::new();
        self.normal_matrices_into(&mut m);
        m
    }

    /// The warped unit normal of `n` bound by `b`, given [`Self::normal_matrices`].
    #[inline]
    pub fn warp_normal(
        &self,
        n: &Vector3<f64>,
        b: &Binding,
        normal_matrices: &[Matrix3<f64>],
    ) -> Vector3<f64> {
        if b.len == 0 {
            return *n;
        }
        let mut out = Vector3::zeros();
        for (j, w) in b.iter() {
            out += w * (normal_matrices[j as usize] * n);
        }
        out.try_normalize(1e-12).unwrap_or(*n)
    }

    /// Warps points (and normals, when given) into `out_points` / `out_normals`.
    pub fn deform(
        &self,
        points: &[Vector3<f64>],
        normals: Option<&[Vector3<f64>]>,
        bindings: &[Binding],
        out_points: &mut Vec<Vector3<f64>>,
        out_normals: &mut Vec<Vector3<f64>>,
    ) {
        points
            .par_iter()
            .zip(bindings)
            .map(|(v, b)| self.warp_point(v, b))
            .collect_into_vec(out_points);
        out_normals.clear();
        if let Some(normals) = normals {
            let m = self.normal_matrices();
            normals
                .par_iter()
                .zip(bindings)
                .map(|(n, b)| self.warp_normal(n, b, &m))
                .collect_into_vec(out_normals);
        }
    }

    /// The graph as the framework's payload (nodes, A and t per node, edges), for Rerun and
    /// downstream nodes.
    pub fn to_payload(&self) -> misslam_framework::DeformationGraph {
        misslam_framework::DeformationGraph {
            nodes: self.nodes.iter().map(arr3).collect(),
            affines: self
                .warp
                .iter()
                .map(|p| [p[0], p[1], p[2], p[4], p[5], p[6], p[8], p[9], p[10]].map(|x| x as f32))
                .collect(),
            translations: self
                .warp
                .iter()
                .map(|p| [p[3] as f32, p[7] as f32, p[11] as f32])
                .collect(),
            edges: self.edges().map(|(a, b)| [a, b]).collect(),
        }
    }

    /// Distance from canonical point `v` to its nearest node (infinite for an empty graph).
    pub fn nearest_node_distance(&self, v: &Vector3<f64>) -> f64 {
        let mut buf = Vec::with_capacity(1);
        self.index.knn(&self.nodes, v, 1, &mut buf);
        buf.first().map_or(f64::INFINITY, |e| e.0.sqrt())
    }

    /// Adds nodes where points lie farther than the spacing from every node (Poisson disc over the
    /// new points). A new node within two spacings of the existing graph starts with the warp the
    /// graph gives it there (A interpolated, t so that the node lands where the graph maps it), so
    /// growth at the edge of the map does not move anything. A node farther out starts with A = I
    /// and the interpolated translation only: extrapolating the affine parts over a long distance
    /// would amplify any rotation error by that distance. Returns the number of nodes added.
    pub fn grow(&mut self, points: &[Vector3<f64>]) -> usize {
        let eps = self.params.spacing;
        let far: Vec<Vector3<f64>> = points
            .iter()
            .filter(|v| {
                v.iter().all(|c| c.is_finite())
                    && self.index.nearest_within(&self.nodes, v, eps).is_none()
            })
            .copied()
            .collect();
        if far.is_empty() {
            return 0;
        }
        let new = poisson_disc(&far, &self.nodes, eps);
        if new.is_empty() {
            return 0;
        }
        let warps: Vec<[f64; 12]> = new
            .iter()
            .map(|g| {
                let b = self.bind(g);
                if b.len == 0 {
                    return IDENTITY;
                }
                let near = self
                    .index
                    .nearest_within(&self.nodes, g, 2.0 * eps)
                    .is_some();
                let mut p = if near { [0.0; 12] } else { IDENTITY };
                let mut t = Vector3::zeros();
                for (j, w) in b.iter() {
                    let pj = &self.warp[j as usize];
                    if near {
                        for (a, x) in p.iter_mut().zip(pj) {
                            *a += w * x;
                        }
                    }
                    t += w * translation(pj);
                }
                if near {
                    // t = warp(g) - g, the affine part interpolated.
                    t = self.warp_point(g, &b) - g;
                }
                p[3] = t.x;
                p[7] = t.y;
                p[11] = t.z;
                p
            })
            .collect();
        let added = new.len();
        self.nodes.extend(new);
        self.warp.extend(warps);
        self.rebuild();
        added
    }

    /// Resets every node whose affine A has collapsed or blown up, det A outside
    /// [1 / `max_det`, `max_det`] or not finite, to the rotation nearest it (the polar factor of
    /// A; the identity where A is not finite), its translation kept (zero where not finite);
    /// returns how many. A collapsed column maps a node's points onto a plane, and points mapped
    /// back through A^-1 land far off.
    pub fn reset_collapsed(&mut self, max_det: f64) -> usize {
        let mut n = 0;
        for w in self.warp.iter_mut() {
            let a = affine(w);
            if (1.0 / max_det..=max_det).contains(&a.determinant()) {
                continue;
            }
            n += 1;
            let r = if a.iter().all(|c| c.is_finite()) {
                let svd = a.svd(true, true);
                match (svd.u, svd.v_t) {
                    (Some(u), Some(v_t)) => {
                        let mut d = Matrix3::identity();
                        d[(2, 2)] = (u * v_t).determinant().signum();
                        u * d * v_t
                    }
                    _ => Matrix3::identity(),
                }
            } else {
                Matrix3::identity()
            };
            for row in 0..3 {
                for col in 0..3 {
                    w[4 * row + col] = r[(row, col)];
                }
                if !w[4 * row + 3].is_finite() {
                    w[4 * row + 3] = 0.0;
                }
            }
        }
        n
    }
}

/// A rigid transform as a node warp about `g`: A = R, t = R g + t - g, so the node maps v to
/// R v + t.
pub fn rigid_warp(rotation: &Rotation3<f64>, t: &Vector3<f64>, g: &Vector3<f64>) -> [f64; 12] {
    let m = rotation.matrix();
    let tj = rotation * g + t - g;
    let (a, b, c) = (m.row(0), m.row(1), m.row(2));
    [
        a[0], a[1], a[2], tj.x, b[0], b[1], b[2], tj.y, c[0], c[1], c[2], tj.z,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sheet(n: usize, step: f64) -> Vec<Vector3<f64>> {
        let mut v = Vec::new();
        for y in 0..n {
            for x in 0..n {
                v.push(Vector3::new(
                    x as f64 * step,
                    y as f64 * step,
                    0.1 * (x as f64 * step).sin(),
                ));
            }
        }
        v
    }

    #[test]
    fn poisson_disc_nodes_are_spaced_and_cover_the_points() {
        let pts = sheet(60, 0.5);
        let g = EdGraph::from_points(
            &pts,
            GraphParams {
                spacing: 4.0,
                ..Default::default()
            },
        )
        .unwrap();
        for (i, a) in g.nodes().iter().enumerate() {
            for b in &g.nodes()[i + 1..] {
                assert!((a - b).norm() >= 4.0 - 1e-9);
            }
        }
        for p in &pts {
            assert!(g.nearest_node_distance(p) <= 4.0 + 1e-9);
        }
        // Symmetric edges, no self loops, at least k neighbours each.
        for j in 0..g.len() {
            assert!(g.neighbors(j).len() >= 6);
            for &k in g.neighbors(j) {
                assert_ne!(k as usize, j);
                assert!(g.neighbors(k as usize).contains(&(j as u32)));
            }
        }
    }

    #[test]
    fn voxel_sampling_keeps_one_node_per_occupied_voxel() {
        let pts = sheet(40, 0.5); // 19.5 mm square
        let g = EdGraph::from_points(
            &pts,
            GraphParams {
                spacing: 5.0,
                sampling: Sampling::Voxel,
                ..Default::default()
            },
        )
        .unwrap();
        let mut keys: Vec<[i64; 3]> = pts
            .iter()
            .map(|p| {
                [
                    (p.x / 5.0).floor() as i64,
                    (p.y / 5.0).floor() as i64,
                    (p.z / 5.0).floor() as i64,
                ]
            })
            .collect();
        keys.sort();
        keys.dedup();
        assert_eq!(g.len(), keys.len());
        let mut node_keys: Vec<[i64; 3]> = g
            .nodes()
            .iter()
            .map(|p| {
                [
                    (p.x / 5.0).floor() as i64,
                    (p.y / 5.0).floor() as i64,
                    (p.z / 5.0).floor() as i64,
                ]
            })
            .collect();
        node_keys.sort();
        assert_eq!(node_keys, keys);
    }

    #[test]
    fn sumner_weights_sum_to_one_and_fall_with_distance() {
        let nodes = vec![
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(10.0, 0.0, 0.0),
            Vector3::new(0.0, 10.0, 0.0),
            Vector3::new(10.0, 10.0, 0.0),
            Vector3::new(20.0, 20.0, 0.0),
        ];
        let g = EdGraph::from_nodes(
            nodes.clone(),
            GraphParams {
                point_neighbors: 4,
                ..Default::default()
            },
        )
        .unwrap();
        let v = Vector3::new(2.0, 3.0, 0.0);
        let b = g.bind(&v);
        assert_eq!(b.len, 4);
        let s: f64 = b.iter().map(|e| e.1).sum();
        assert!((s - 1.0).abs() < 1e-12);
        // Hand computation: d_max is the distance to the 5th node.
        let d: Vec<f64> = nodes.iter().map(|g| (g - v).norm()).collect();
        let raw: Vec<f64> = d[..4].iter().map(|x| (1.0 - x / d[4]).powi(2)).collect();
        let total: f64 = raw.iter().sum();
        for (j, w) in b.iter() {
            assert!((w - raw[j as usize] / total).abs() < 1e-12, "node {j}");
        }
        // The identity warp leaves points where they are.
        assert!((g.warp_point(&v, &b) - v).norm() < 1e-12);
    }

    #[test]
    fn a_rigid_motion_of_all_nodes_moves_points_and_normals_rigidly() {
        let pts = sheet(30, 1.0);
        let mut g = EdGraph::from_points(
            &pts,
            GraphParams {
                spacing: 6.0,
                ..Default::default()
            },
        )
        .unwrap();
        let r = misslam_framework::nalgebra::Rotation3::from_euler_angles(0.2, -0.1, 0.3);
        let t = Vector3::new(3.0, -2.0, 5.0);
        for j in 0..g.len() {
            g.warp[j] = rigid_warp(&r, &t, &g.nodes()[j]);
        }
        let b = g.bind_all(&pts);
        let n = vec![Vector3::new(0.0, 0.6, 0.8); pts.len()];
        let (mut op, mut on) = (Vec::new(), Vec::new());
        g.deform(&pts, Some(&n), &b, &mut op, &mut on);
        for i in 0..pts.len() {
            assert!((op[i] - (r * pts[i] + t)).norm() < 1e-9);
            assert!((on[i] - r * n[i]).norm() < 1e-9);
        }
    }

    #[test]
    fn collapsed_nodes_are_reset_to_their_nearest_rotation() {
        let nodes = (0..6)
            .map(|i| Vector3::new(10.0 * i as f64, 0.0, 0.0))
            .collect();
        let mut g = EdGraph::from_nodes(nodes, GraphParams::default()).unwrap();
        assert_eq!(g.reset_collapsed(4.0), 0);
        // A column flattened (det 0.14, as a node that projects its points onto a plane), a
        // blow-up (det 4.1), a flip (det -1), NaN, and two within the bounds (det 0.26 and 3.9).
        let set = |g: &mut EdGraph, j: usize, a: [f64; 9]| {
            let w = &mut g.warp[j];
            for r in 0..3 {
                w[4 * r..4 * r + 3].copy_from_slice(&a[3 * r..3 * r + 3]);
                w[4 * r + 3] = (j + r) as f64;
            }
        };
        set(&mut g, 0, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, -0.37, 0.2, 0.14]);
        set(&mut g, 1, [4.1, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        set(&mut g, 2, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]);
        set(
            &mut g,
            3,
            [f64::NAN, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        );
        set(&mut g, 4, [0.26, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        set(&mut g, 5, [3.9, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);
        let kept = [g.warp[4], g.warp[5]];
        assert_eq!(g.reset_collapsed(4.0), 4);
        for j in 0..4 {
            let a = affine(&g.warp[j]);
            assert!(
                (a.transpose() * a - Matrix3::identity()).norm() < 1e-9,
                "{j}: {a}"
            );
            assert!((a.determinant() - 1.0).abs() < 1e-9, "{j}: {a}");
            let t = translation(&g.warp[j]);
            assert_eq!(
                t,
                Vector3::new(j as f64, j as f64 + 1.0, j as f64 + 2.0),
                "{j}"
            );
        }
        // A pure stretch and NaN go back to the identity.
        for j in [1, 3] {
            let a = affine(&g.warp[j]);
            assert!((a - Matrix3::identity()).norm() < 1e-9, "{j}: {a}");
        }
        assert_eq!([g.warp[4], g.warp[5]], kept);
        assert_eq!(g.reset_collapsed(4.0), 0);
    }

    #[test]
    fn growth_adds_nodes_only_where_needed_and_does_not_move_anything() {
        let pts = sheet(20, 1.0);
        let mut g = EdGraph::from_points(
            &pts,
            GraphParams {
                spacing: 5.0,
                ..Default::default()
            },
        )
        .unwrap();
        // Deform with a smooth field first.
        for j in 0..g.len() {
            let gj = g.nodes()[j];
            g.warp[j][3] = 0.1 * gj.x;
            g.warp[j][11] = 0.05 * gj.y;
        }
        let n0 = g.len();
        assert_eq!(g.grow(&pts), 0);
        let v0 = g.topology_version();
        let more: Vec<Vector3<f64>> = (0..20)
            .map(|i| Vector3::new(25.0 + i as f64, 5.0, 0.0))
            .collect();
        let probe = Vector3::new(26.0, 5.0, 0.0);
        let before = g.warp_point(&probe, &g.bind(&probe));
        let added = g.grow(&more);
        assert!(added >= 3, "added {added}");
        assert_eq!(g.len(), n0 + added);
        assert!(g.topology_version() > v0);
        for p in &more {
            assert!(g.nearest_node_distance(p) <= 5.0 + 1e-9);
        }
        // The new node near the probe inherits the warp: the probe moves by less than the field's
        // curvature would explain (the field is linear, so interpolation reproduces it closely).
        let after = g.warp_point(&probe, &g.bind(&probe));
        assert!((after - before).norm() < 0.3, "{before:?} -> {after:?}");
    }

    /// Bindings made before a growth, bound again where the new nodes reach them
    /// ([`NewNodes::reach`]), equal `bind_all`'s after it, bit for bit. Returns the nodes added
    /// and the points bound again.
    fn check_rebind_after_growth(
        g: &mut EdGraph,
        pts: &[Vector3<f64>],
        more: &[Vector3<f64>],
    ) -> (usize, usize) {
        let before = g.bind_all(pts);
        let first_new = g.len();
        let added = g.grow(more);
        assert!(added > 0);
        let fresh = g.bind_all(pts);
        let new = g.new_nodes(first_new);
        let mut rebound = 0;
        for (i, (v, (old, now))) in pts.iter().zip(before.iter().zip(&fresh)).enumerate() {
            if new.reach(v, old) {
                rebound += 1;
            } else {
                assert_eq!(
                    old, now,
                    "point {i}: a new node changed a binding it does not reach"
                );
            }
        }
        (added, rebound)
    }

    #[test]
    fn rebinding_after_growth_matches_binding_everything_again() {
        let mut pts = sheet(40, 1.0);
        pts.push(Vector3::new(f64::NAN, 0.0, 0.0));
        let params = GraphParams {
            spacing: 5.0,
            ..Default::default()
        };
        // A few nodes at one edge (checked one by one): few points rebound.
        let mut g = EdGraph::from_points(&pts, params.clone()).unwrap();
        let strip: Vec<Vector3<f64>> = (0..15)
            .map(|i| Vector3::new(45.0 + 0.5 * (i % 3) as f64, 2.0 * i as f64, 0.5))
            .collect();
        let (added, rebound) = check_rebind_after_growth(&mut g, &pts, &strip);
        assert!(added <= REBIND_SCAN_MAX, "added {added}");
        assert!(rebound > 0 && rebound < pts.len() / 4, "rebound {rebound}");
        // Many nodes (through a grid): a second sheet below the first.
        let below: Vec<Vector3<f64>> = sheet(40, 1.0)
            .into_iter()
            .map(|p| p + Vector3::new(0.0, 0.0, -6.0))
            .collect();
        let (added, rebound) = check_rebind_after_growth(&mut g, &pts, &below);
        assert!(added > REBIND_SCAN_MAX, "added {added}");
        assert!(rebound > 0, "rebound {rebound}");
        // A graph of no more than k nodes binds with the k-th node's distance: every point again.
        let few: Vec<Vector3<f64>> = (0..3)
            .map(|i| Vector3::new(8.0 * i as f64, 0.0, 0.0))
            .collect();
        let mut g = EdGraph::from_nodes(few, params).unwrap();
        let (_, rebound) = check_rebind_after_growth(&mut g, &pts, &pts[..200]);
        assert_eq!(rebound, pts.len());
    }
}
