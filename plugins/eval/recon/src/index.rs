//! Exact distances from points to a triangle mesh: a branch-free point-to-triangle distance
//! evaluated on eight triangles at once (AVX2 where the CPU has it, the same arithmetic lane by
//! lane elsewhere), and a bounding volume hierarchy over the triangles ([`SurfaceIndex`]) that
//! finds the nearest one.
//!
//! The hierarchy is built top down: a node's triangles are split at the median of their centroids
//! along the longest axis of the centroids' box, at a multiple of [`LANES`], down to leaves of
//! [`LANES`] triangles, stored as structures of arrays (one lane per triangle). The ground truth
//! deforms every frame with the same triangles: [`SurfaceIndex::update`] then keeps the tree and
//! refits its leaves and boxes. Queries run on the tree collapsed to nodes of eight children
//! (`wide`): a query descends into the nearest child first and skips every box farther than the
//! best triangle found so far, so the answer is the least kernel value over all triangles.

mod wide;

use crate::{dot, sub, V3};
use misslam_framework::Mesh;
use rayon::prelude::*;

/// Triangles per leaf: one per lane of an AVX2 register of f32.
pub const LANES: usize = 8;

/// What the distance kernel needs of one triangle, precomputed.
#[derive(Clone, Copy, Debug)]
struct TriangleData {
    a: V3,
    ab: V3,
    ac: V3,
    bc: V3,
    /// Unit normal (zero for a degenerate triangle).
    n: V3,
    /// 1 / |ab|^2, 1 / |ac|^2, 1 / |bc|^2 (0 for an edge of zero length).
    inv_len2: [f32; 3],
    /// ab.ab, ab.ac, ac.ac.
    gram: [f32; 3],
    /// 1 / (ab.ab ac.ac - (ab.ac)^2), or 0 for a degenerate triangle (then only its edges count).
    inv_det: f32,
}

impl TriangleData {
    fn new(a: V3, b: V3, c: V3) -> Self {
        let (ab, ac, bc) = (sub(b, a), sub(c, a), sub(c, b));
        let inv = |l2: f32| if l2 > 0.0 { 1.0 / l2 } else { 0.0 };
        let gram = [dot(ab, ab), dot(ab, ac), dot(ac, ac)];
        let det = gram[0] * gram[2] - gram[1] * gram[1];
        let cross = [
            ab[1] * ac[2] - ab[2] * ac[1],
            ab[2] * ac[0] - ab[0] * ac[2],
            ab[0] * ac[1] - ab[1] * ac[0],
        ];
        let len = dot(cross, cross).sqrt();
        // A triangle whose area is lost to rounding has no face: its nearest point is on an edge.
        let face = det > f32::EPSILON * gram[0] * gram[2] && len > 0.0;
        TriangleData {
            a,
            ab,
            ac,
            bc,
            n: if face {
                cross.map(|v| v / len)
            } else {
                [0.0; 3]
            },
            inv_len2: [inv(gram[0]), inv(gram[2]), inv(dot(bc, bc))],
            gram,
            inv_det: if face { 1.0 / det } else { 0.0 },
        }
    }
}

/// Fields of a leaf: a (3), ab (3), ac (3), bc (3), n (3), inv_len2 (3), gram (3), inv_det.
const FIELDS: usize = 22;

/// [`LANES`] triangles, structure of arrays: field `k` of lane `l` is `v[k][l]`.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct Leaf {
    v: [[f32; LANES]; FIELDS],
}

impl Leaf {
    const EMPTY: Leaf = Leaf {
        v: [[0.0; LANES]; FIELDS],
    };

    fn set(&mut self, l: usize, t: &TriangleData) {
        let fields = [
            t.a[0],
            t.a[1],
            t.a[2],
            t.ab[0],
            t.ab[1],
            t.ab[2],
            t.ac[0],
            t.ac[1],
            t.ac[2],
            t.bc[0],
            t.bc[1],
            t.bc[2],
            t.n[0],
            t.n[1],
            t.n[2],
            t.inv_len2[0],
            t.inv_len2[1],
            t.inv_len2[2],
            t.gram[0],
            t.gram[1],
            t.gram[2],
            t.inv_det,
        ];
        for (k, f) in fields.into_iter().enumerate() {
            self.v[k][l] = f;
        }
    }
}

/// The lesser of two values as `minps` takes it (`b` when either is NaN).
#[inline(always)]
fn mn(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// The greater, as `maxps` takes it.
#[inline(always)]
fn mx(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// The distance kernel on lane `l` of a leaf: with (v, w) the barycentric coordinates of p's
/// projection on the triangle's plane, the squared distance to the plane where the projection
/// lies inside the triangle, else the least squared distance to its three edges (each
/// point-to-segment, the segment parameter clamped to [0, 1]). Branch-free; [`leaf_dist2_avx2`]
/// does the same operations in the same order on eight lanes.
#[inline(always)]
fn lane_dist2(p: V3, v: &[[f32; LANES]; FIELDS], l: usize) -> f32 {
    let f = |k: usize| v[k][l];
    let ap = [p[0] - f(0), p[1] - f(1), p[2] - f(2)];
    let (ab, ac, bc, n) = (
        [f(3), f(4), f(5)],
        [f(6), f(7), f(8)],
        [f(9), f(10), f(11)],
        [f(12), f(13), f(14)],
    );
    let d1 = ab[0] * ap[0] + ab[1] * ap[1] + ab[2] * ap[2];
    let d2 = ac[0] * ap[0] + ac[1] * ap[1] + ac[2] * ap[2];
    let h = n[0] * ap[0] + n[1] * ap[1] + n[2] * ap[2];
    let bp = [ap[0] - ab[0], ap[1] - ab[1], ap[2] - ab[2]];
    let d3 = bc[0] * bp[0] + bc[1] * bp[1] + bc[2] * bp[2];
    let seg = |d: V3, e: V3, t: f32| {
        let t = mn(mx(t, 0.0), 1.0);
        let r = [d[0] - t * e[0], d[1] - t * e[1], d[2] - t * e[2]];
        r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
    };
    let e_ab = seg(ap, ab, d1 * f(15));
    let e_ac = seg(ap, ac, d2 * f(16));
    let e_bc = seg(bp, bc, d3 * f(17));
    let (g00, g01, g11, inv_det) = (f(18), f(19), f(20), f(21));
    let vv = (g11 * d1 - g01 * d2) * inv_det;
    let ww = (g00 * d2 - g01 * d1) * inv_det;
    let inside = (inv_det > 0.0) & (vv >= 0.0) & (ww >= 0.0) & (vv + ww <= 1.0);
    let edges = mn(mn(e_ab, e_ac), e_bc);
    if inside {
        h * h
    } else {
        edges
    }
}

/// The least squared distance from `p` to the triangles of a leaf, lane by lane.
fn leaf_dist2_scalar(p: V3, leaf: &Leaf) -> f32 {
    (0..LANES).fold(f32::INFINITY, |m, l| mn(lane_dist2(p, &leaf.v, l), m))
}

/// [`leaf_dist2_scalar`] on eight lanes at once.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn leaf_dist2_avx2(p: V3, leaf: &Leaf) -> f32 {
    use std::arch::x86_64::*;
    let v = &leaf.v;
    // SAFETY: each field of a leaf is 8 f32 at a 32-byte boundary (`repr(align(32))`).
    let ld = |k: usize| unsafe { _mm256_load_ps(v[k].as_ptr()) };
    let (add, sb, mul) = (
        |a, b| _mm256_add_ps(a, b),
        |a, b| _mm256_sub_ps(a, b),
        |a, b| _mm256_mul_ps(a, b),
    );
    let dot3 = |x: [__m256; 3], y: [__m256; 3]| {
        add(add(mul(x[0], y[0]), mul(x[1], y[1])), mul(x[2], y[2]))
    };
    let ps = p.map(|c| _mm256_set1_ps(c));
    let ap = [sb(ps[0], ld(0)), sb(ps[1], ld(1)), sb(ps[2], ld(2))];
    let (ab, ac, bc, n) = (
        [ld(3), ld(4), ld(5)],
        [ld(6), ld(7), ld(8)],
        [ld(9), ld(10), ld(11)],
        [ld(12), ld(13), ld(14)],
    );
    let d1 = dot3(ab, ap);
    let d2 = dot3(ac, ap);
    let h = dot3(n, ap);
    let bp = [sb(ap[0], ab[0]), sb(ap[1], ab[1]), sb(ap[2], ab[2])];
    let d3 = dot3(bc, bp);
    let (zero, one) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0));
    let seg = |d: [__m256; 3], e: [__m256; 3], t: __m256| {
        let t = _mm256_min_ps(_mm256_max_ps(t, zero), one);
        let r = [
            sb(d[0], mul(t, e[0])),
            sb(d[1], mul(t, e[1])),
            sb(d[2], mul(t, e[2])),
        ];
        dot3(r, r)
    };
    let e_ab = seg(ap, ab, mul(d1, ld(15)));
    let e_ac = seg(ap, ac, mul(d2, ld(16)));
    let e_bc = seg(bp, bc, mul(d3, ld(17)));
    let (g00, g01, g11, inv_det) = (ld(18), ld(19), ld(20), ld(21));
    let vv = mul(sb(mul(g11, d1), mul(g01, d2)), inv_det);
    let ww = mul(sb(mul(g00, d2), mul(g01, d1)), inv_det);
    let inside = _mm256_and_ps(
        _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_GT_OQ>(inv_det, zero),
            _mm256_cmp_ps::<_CMP_GE_OQ>(vv, zero),
        ),
        _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_GE_OQ>(ww, zero),
            _mm256_cmp_ps::<_CMP_LE_OQ>(add(vv, ww), one),
        ),
    );
    let edges = _mm256_min_ps(_mm256_min_ps(e_ab, e_ac), e_bc);
    let d = _mm256_blendv_ps(edges, mul(h, h), inside);
    let mut out = [0f32; LANES];
    // SAFETY: `out` holds 8 f32.
    unsafe { _mm256_storeu_ps(out.as_mut_ptr(), d) };
    out.into_iter().fold(f32::INFINITY, |m, x| mn(x, m))
}

/// Squared distance from `p` to triangle `abc`: the kernel [`SurfaceIndex`] evaluates on its
/// leaves, for one triangle.
pub fn point_triangle_dist2(p: V3, a: V3, b: V3, c: V3) -> f32 {
    let mut leaf = Leaf::EMPTY;
    leaf.set(0, &TriangleData::new(a, b, c));
    lane_dist2(p, &leaf.v, 0)
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug)]
struct Aabb {
    lo: V3,
    hi: V3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        lo: [f32::INFINITY; 3],
        hi: [f32::NEG_INFINITY; 3],
    };

    fn grow(&mut self, p: V3) {
        for (k, &c) in p.iter().enumerate() {
            self.lo[k] = self.lo[k].min(c);
            self.hi[k] = self.hi[k].max(c);
        }
    }

    fn union(&self, o: &Aabb) -> Aabb {
        Aabb {
            lo: [0, 1, 2].map(|k| self.lo[k].min(o.lo[k])),
            hi: [0, 1, 2].map(|k| self.hi[k].max(o.hi[k])),
        }
    }

    /// Squared distance from `p` to the box (0 inside).
    #[inline(always)]
    fn dist2(&self, p: V3) -> f32 {
        let mut d2 = 0.0;
        for (k, &c) in p.iter().enumerate() {
            let e = mx(mx(self.lo[k] - c, c - self.hi[k]), 0.0);
            d2 += e * e;
        }
        d2
    }
}

/// A node of the hierarchy: its box, and either two children or a leaf.
#[derive(Clone, Copy, Debug)]
struct Node {
    bounds: Aabb,
    /// Internal: the index of the first child (the second follows its subtree, at `right`);
    /// leaf: the leaf's index with [`LEAF`] set.
    first: u32,
    /// Internal: the second child's index.
    right: u32,
}

/// Marks [`Node::first`] as a leaf index.
const LEAF: u32 = 1 << 31;

/// A bounding volume hierarchy over a mesh's triangles for nearest-triangle queries.
#[derive(Debug)]
pub struct SurfaceIndex {
    /// Depth first (a parent before its children), the root at 0.
    nodes: Vec<Node>,
    leaves: Vec<Leaf>,
    /// Per leaf, its node; per leaf lane, its triangle (for [`SurfaceIndex::update`]).
    leaf_node: Vec<u32>,
    lanes: Vec<u32>,
    /// Each leaf's box, filled by `refit` before the nodes take them.
    leaf_bounds: Vec<Aabb>,
    /// The mesh's triangles, to tell whether a new mesh is the same surface moved.
    triangles: Vec<[u32; 3]>,
    /// The leaves' summed box areas when the tree was built, against which a refit is judged.
    built_area: f64,
    /// The tree collapsed to nodes of eight children, which the queries walk.
    wide: wide::WideTree,
    avx2: bool,
}

/// Checks that `mesh` has triangles, that they index its vertices, and that the vertices they
/// use are finite.
fn check(mesh: &Mesh) -> Result<(), String> {
    if mesh.triangles.is_empty() {
        return Err("the ground-truth mesh has no triangles".into());
    }
    let nv = mesh.vertices.len();
    if mesh
        .triangles
        .par_iter()
        .any(|t| t.iter().any(|&i| i as usize >= nv))
    {
        return Err("a ground-truth triangle indexes past the vertices".into());
    }
    if mesh.triangles.par_iter().any(|t| {
        t.iter()
            .any(|&i| mesh.vertices[i as usize].iter().any(|v| !v.is_finite()))
    }) {
        return Err("the ground-truth mesh has non-finite vertices".into());
    }
    Ok(())
}

/// Triangle `t`'s corners.
#[inline]
fn corners(mesh: &Mesh, t: u32) -> [V3; 3] {
    mesh.triangles[t as usize].map(|i| mesh.vertices[i as usize])
}

/// Builds the subtree over `items` (triangle index, centroid) into `nodes`, and the triangles
/// of its leaves' lanes into `lanes`; returns its root's index.
fn build(items: &mut [(u32, V3)], nodes: &mut Vec<Node>, lanes: &mut Vec<u32>) -> u32 {
    let me = nodes.len() as u32;
    if items.len() <= LANES {
        // A short leaf repeats its last triangle in the spare lanes; its data and box are
        // filled in by `refit`.
        for l in 0..LANES {
            lanes.push(items[l.min(items.len() - 1)].0);
        }
        nodes.push(Node {
            bounds: Aabb::EMPTY,
            first: (lanes.len() / LANES - 1) as u32 | LEAF,
            right: 0,
        });
        return me;
    }
    let mut cb = Aabb::EMPTY;
    items.iter().for_each(|(_, c)| cb.grow(*c));
    let axis = (0..3)
        .max_by(|&a, &b| (cb.hi[a] - cb.lo[a]).total_cmp(&(cb.hi[b] - cb.lo[b])))
        .unwrap_or(0);
    // Split at the median, rounded to whole leaves: only the last leaf can be short.
    let mid = items.len().div_ceil(LANES) / 2 * LANES;
    items.select_nth_unstable_by(mid, |a, b| a.1[axis].total_cmp(&b.1[axis]));
    nodes.push(Node {
        bounds: Aabb::EMPTY,
        first: me + 1,
        right: 0,
    });
    let (l, r) = items.split_at_mut(mid);
    build(l, nodes, lanes);
    nodes[me as usize].right = build(r, nodes, lanes);
    me
}

impl SurfaceIndex {
    /// Indexes `mesh`. Fails on a mesh without triangles, a triangle indexing past the vertices,
    /// or a non-finite vertex of a triangle.
    pub fn new(mesh: &Mesh) -> Result<Self, String> {
        check(mesh)?;
        let mut items: Vec<(u32, V3)> = (0..mesh.triangles.len() as u32)
            .into_par_iter()
            .map(|i| {
                let c = corners(mesh, i);
                (i, [0, 1, 2].map(|k| (c[0][k] + c[1][k] + c[2][k]) / 3.0))
            })
            .collect();
        let n_leaves = items.len().div_ceil(LANES);
        let mut nodes = Vec::with_capacity(2 * n_leaves);
        let mut lanes = Vec::with_capacity(LANES * n_leaves);
        build(&mut items, &mut nodes, &mut lanes);
        let leaf_node = (0..nodes.len() as u32)
            .filter(|&i| nodes[i as usize].first & LEAF != 0)
            .collect();
        #[cfg(target_arch = "x86_64")]
        let avx2 = std::arch::is_x86_feature_detected!("avx2");
        #[cfg(not(target_arch = "x86_64"))]
        let avx2 = false;
        let mut index = SurfaceIndex {
            nodes,
            leaves: vec![Leaf::EMPTY; n_leaves],
            leaf_bounds: vec![Aabb::EMPTY; n_leaves],
            leaf_node,
            lanes,
            triangles: mesh.triangles.clone(),
            built_area: 0.0,
            wide: wide::WideTree::default(),
            avx2,
        };
        index.wide = wide::WideTree::new(&index.nodes)?;
        index.built_area = index.refit(mesh);
        Ok(index)
    }

    /// Makes the index answer for `mesh`. The same triangles with moved vertices (a deforming
    /// ground truth) keep the tree and only refit its leaves and boxes, unless that has made the
    /// leaves' boxes half as large again (in summed area) as when the tree was built; any other
    /// mesh is indexed afresh. The answers are exact either way: a refit tree is only slower.
    /// Fails as [`SurfaceIndex::new`] does, leaving the index as it was.
    pub fn update(&mut self, mesh: &Mesh) -> Result<(), String> {
        if mesh.triangles != self.triangles {
            *self = SurfaceIndex::new(mesh)?;
            return Ok(());
        }
        check(mesh)?;
        if self.refit(mesh) > 1.5 * self.built_area {
            *self = SurfaceIndex::new(mesh)?;
        }
        Ok(())
    }

    /// Fills the leaves and every box from `mesh` (checked, with the index's triangles); returns
    /// the leaves' summed box areas.
    fn refit(&mut self, mesh: &Mesh) -> f64 {
        self.leaves
            .par_iter_mut()
            .zip(self.leaf_bounds.par_iter_mut())
            .zip(self.lanes.par_chunks(LANES))
            .for_each(|((leaf, bounds), tris)| {
                *bounds = Aabb::EMPTY;
                for (l, &t) in tris.iter().enumerate() {
                    let c = corners(mesh, t);
                    leaf.set(l, &TriangleData::new(c[0], c[1], c[2]));
                    c.iter().for_each(|&p| bounds.grow(p));
                }
            });
        let mut area = 0.0;
        for (b, &n) in self.leaf_bounds.iter().zip(&self.leaf_node) {
            self.nodes[n as usize].bounds = *b;
            let e = [0, 1, 2].map(|k| (b.hi[k] - b.lo[k]) as f64);
            area += e[0] * e[1] + e[1] * e[2] + e[2] * e[0];
        }
        // Children follow their parent: from the back, each parent's children are done.
        for i in (0..self.nodes.len()).rev() {
            let n = self.nodes[i];
            if n.first & LEAF == 0 {
                self.nodes[i].bounds = self.nodes[n.first as usize]
                    .bounds
                    .union(&self.nodes[n.right as usize].bounds);
            }
        }
        self.wide.refit(&self.nodes);
        area
    }

    #[inline(always)]
    fn leaf_dist2(&self, p: V3, i: usize) -> f32 {
        #[cfg(target_arch = "x86_64")]
        if self.avx2 {
            // SAFETY: AVX2 was detected at run time.
            return unsafe { leaf_dist2_avx2(p, &self.leaves[i]) };
        }
        leaf_dist2_scalar(p, &self.leaves[i])
    }

    /// Distance from `p` to the nearest triangle: the least of the kernel over all triangles.
    pub fn distance(&self, p: V3) -> f32 {
        // A box is skipped only when it is farther than the best triangle by a margin well
        // above rounding, so that no triangle inside it can be nearer.
        self.wide
            .nearest(
                p,
                self.nodes[0].bounds.dist2(p),
                self.avx2,
                (1e-5, 1e-12),
                |p, i| self.leaf_dist2(p, i),
            )
            .sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform values in [0, 1) from a xorshift generator.
    fn uniform(mut st: u64) -> impl FnMut() -> f32 {
        move || {
            st ^= st << 13;
            st ^= st >> 7;
            st ^= st << 17;
            (st >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    /// The distance from `p` to the nearest triangle of `gt`, over every triangle.
    fn brute(gt: &Mesh, p: V3) -> f32 {
        gt.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| gt.vertices[i as usize]);
                point_triangle_dist2(p, a, b, c)
            })
            .fold(f32::INFINITY, f32::min)
            .sqrt()
    }

    /// Ericson's region-by-region closest point (Real-Time Collision Detection 5.1.5), an
    /// independent reference for the kernel.
    fn ericson_dist2(p: V3, a: V3, b: V3, c: V3) -> f32 {
        let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
        let (d1, d2) = (dot(ab, ap), dot(ac, ap));
        let at = |o: V3, e: V3, t: f32| [o[0] + t * e[0], o[1] + t * e[1], o[2] + t * e[2]];
        let closest = if d1 <= 0.0 && d2 <= 0.0 {
            a
        } else {
            let bp = sub(p, b);
            let (d3, d4) = (dot(ab, bp), dot(ac, bp));
            let vc = d1 * d4 - d3 * d2;
            let cp = sub(p, c);
            let (d5, d6) = (dot(ab, cp), dot(ac, cp));
            let vb = d5 * d2 - d1 * d6;
            let va = d3 * d6 - d5 * d4;
            if d3 >= 0.0 && d4 <= d3 {
                b
            } else if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
                at(a, ab, d1 / (d1 - d3))
            } else if d6 >= 0.0 && d5 <= d6 {
                c
            } else if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
                at(a, ac, d2 / (d2 - d6))
            } else if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
                at(b, sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6)))
            } else {
                let den = 1.0 / (va + vb + vc);
                let q = at(a, ab, vb * den);
                at(q, ac, vc * den)
            }
        };
        let d = sub(p, closest);
        dot(d, d)
    }

    #[test]
    fn point_triangle_regions() {
        let (a, b, c) = ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        assert_eq!(point_triangle_dist2([0.2, 0.2, 3.0], a, b, c), 9.0, "face");
        assert_eq!(
            point_triangle_dist2([-1.0, -1.0, 0.0], a, b, c),
            2.0,
            "vertex a"
        );
        assert_eq!(
            point_triangle_dist2([0.5, -2.0, 0.0], a, b, c),
            4.0,
            "edge ab"
        );
        assert!(
            (point_triangle_dist2([1.0, 1.0, 0.0], a, b, c) - 0.5).abs() < 1e-6,
            "edge bc"
        );
        assert_eq!(
            point_triangle_dist2([3.0, 4.0, 0.0], a, a, a),
            25.0,
            "point"
        );
        assert_eq!(
            point_triangle_dist2([0.5, 2.0, 0.0], a, b, [2.0, 0.0, 0.0]),
            4.0,
            "collinear corners: the segment"
        );
    }

    #[test]
    fn the_kernel_agrees_with_ericsons_regions() {
        let mut rnd = uniform(0x2545f4914f6cdd1d);
        for _ in 0..20_000 {
            let mut v = || [0, 1, 2].map(|_| (rnd() * 2.0 - 1.0) * 3.0);
            let (a, b, c, p) = (v(), v(), v(), v());
            let (k, e) = (point_triangle_dist2(p, a, b, c), ericson_dist2(p, a, b, c));
            assert!(
                (k - e).abs() <= 1e-4 * e.max(1.0),
                "{p:?} to {a:?} {b:?} {c:?}: {k} against {e}"
            );
        }
    }

    #[test]
    fn the_index_finds_the_nearest_of_all_triangles() {
        // A crumpled sheet (random heights on a 25x25 grid, uneven spacing) against brute force,
        // for points on it, near it, and far outside its box, with every leaf size (the last
        // leaf short or full).
        let mut rnd = uniform(0x9e3779b97f4a7c15);
        for n in [2, 3, 4, 25] {
            let gt = crate::grid_mesh(n, |i, j| {
                let (x, y) = (i as f32 * 2.0 + rnd(), j as f32 * 2.0 + rnd());
                [x, y, 100.0 + 6.0 * rnd()]
            });
            let mut index = SurfaceIndex::new(&gt).unwrap();
            for k in 0..400 {
                let spread = [2.0, 10.0, 200.0][k % 3];
                let p = [
                    24.0 + spread * (rnd() - 0.5),
                    24.0 + spread * (rnd() - 0.5),
                    103.0 + spread * (rnd() - 0.5),
                ];
                assert_eq!(index.distance(p), brute(&gt, p), "{n}x{n}, {p:?}");
                // The portable traversal and kernel too.
                let simd = std::mem::replace(&mut index.avx2, false);
                assert_eq!(index.distance(p), brute(&gt, p), "portable, {n}x{n}, {p:?}");
                index.avx2 = simd;
                // Both paths of the leaf kernel give the same bits.
                let leaf = &index.leaves[0];
                assert_eq!(
                    leaf_dist2_scalar(p, leaf).to_bits(),
                    index.leaf_dist2(p, 0).to_bits()
                );
            }
        }
    }

    #[test]
    fn an_updated_index_answers_for_the_new_mesh() {
        // The same triangles moved a little (refit), moved a lot (the refit tree too loose:
        // built again), other triangles (built again), and a bad mesh (refused, the index kept).
        let sheet = |f: &dyn Fn(f32, f32) -> V3| crate::grid_mesh(20, |i, j| f(i as f32, j as f32));
        let gt = sheet(&|x, y| [x, y, 50.0 + (x * 0.3).sin()]);
        let mut index = SurfaceIndex::new(&gt).unwrap();
        let bumped = sheet(&|x, y| [x, y, 50.0 + (x * 0.3).sin() + 0.4 * (y * 0.5).cos()]);
        let folded = sheet(&|x, y| [x, 6.0 * (y * 0.4).sin(), 50.0 + 5.0 * (y * 0.4).cos()]);
        let mut other = crate::grid_mesh(7, |i, j| [3.0 * i as f32, 3.0 * j as f32, 49.0]);
        other.triangles.reverse();
        for (gt, rebuilt) in [(&bumped, false), (&folded, true), (&other, true)] {
            let area = index.built_area;
            index.update(gt).unwrap();
            assert_eq!(index.built_area != area, rebuilt, "tree built again");
            for k in 0..300 {
                let p = [
                    (k % 23) as f32 * 0.9 - 1.0,
                    (k % 17) as f32 * 1.2 - 1.0,
                    46.0 + (k % 7) as f32 * 1.5,
                ];
                assert_eq!(index.distance(p), brute(gt, p), "{p:?}");
            }
        }
        let mut bad = other.clone();
        bad.vertices[3][0] = f32::INFINITY;
        assert!(index.update(&bad).unwrap_err().contains("non-finite"));
        assert_eq!(index.distance([4.0, 4.0, 52.0]), 3.0);
    }

    #[test]
    fn bad_meshes_are_refused() {
        let mut m = crate::grid_mesh(3, |i, j| [i as f32, j as f32, 0.0]);
        m.triangles.push([0, 1, 99]);
        assert!(SurfaceIndex::new(&m)
            .unwrap_err()
            .contains("past the vertices"));
        let mut m = crate::grid_mesh(3, |i, j| [i as f32, j as f32, 0.0]);
        m.vertices[4][2] = f32::NAN;
        assert!(SurfaceIndex::new(&m).unwrap_err().contains("non-finite"));
        let mut m = crate::grid_mesh(3, |i, j| [i as f32, j as f32, 0.0]);
        m.triangles.clear();
        assert!(SurfaceIndex::new(&m).unwrap_err().contains("no triangles"));
    }
}
