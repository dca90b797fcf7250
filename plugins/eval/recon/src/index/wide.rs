//! The hierarchy's queries on nodes of eight children ([`WideTree`]): the binary tree collapsed,
//! each wide node taking the binary subtrees below it down to eight (the one with the most
//! leaves split first), with their boxes as structures of arrays so that a visit measures all
//! eight in one pass (AVX2 where the CPU has it): fewer, wider visits than on the binary tree
//! (the scoring of the main graph at 640x480 took a fifth less time, docs/pipeline.md). Its
//! answer is the same to the bit: the least of the leaf kernel over the leaves it does not skip,
//! which always include the nearest triangle's.

use super::{mn, mx, Aabb, Node, LEAF};
use crate::V3;

/// Children per wide node.
pub(super) const WIDTH: usize = 8;

/// A slot without a child: an empty box, infinitely far from every point.
const NONE: u32 = u32::MAX;

/// Entries of a query's stack: a visit takes one and leaves at most [`WIDTH`], so a tree of
/// depth `d` needs at most `d * (WIDTH - 1) + 1` ([`WideTree::new`] checks it): nine levels,
/// 8^9 leaves of eight triangles. It is set up on every query, so it is kept small.
const STACK: usize = 64;

/// Eight children's boxes (per axis, per child) and references: a wide node's index, or a
/// leaf's with [`LEAF`] set; [`NONE`] in an empty slot.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(32))]
struct WideNode {
    lo: [[f32; WIDTH]; 3],
    hi: [[f32; WIDTH]; 3],
    child: [u32; WIDTH],
    /// Bit k set: slot k holds a child.
    used: u32,
}

/// The wide nodes over a binary tree, root first.
#[derive(Debug, Default)]
pub(super) struct WideTree {
    nodes: Vec<WideNode>,
    /// Per wide node and slot, the binary node whose box the slot holds (refit).
    from: Vec<[u32; WIDTH]>,
}

impl WideTree {
    /// Collapses the binary tree `bin` (root at 0, children after their parent). Fails on a
    /// tree too deep for a query's stack (more levels than a balanced tree of 2^27 leaves).
    pub(super) fn new(bin: &[Node]) -> Result<WideTree, String> {
        // Leaves under each binary node.
        let mut size = vec![1u32; bin.len()];
        for i in (0..bin.len()).rev() {
            let n = bin[i];
            if n.first & LEAF == 0 {
                size[i] = size[n.first as usize] + size[n.right as usize];
            }
        }
        let mut tree = WideTree::default();
        tree.collapse(bin, &size, 0);
        let depth = tree.depth(0);
        if depth * (WIDTH - 1) + 1 > STACK {
            return Err(format!(
                "the triangles' hierarchy is {depth} levels deep, more than a query can hold"
            ));
        }
        Ok(tree)
    }

    /// Levels of wide nodes from node `i` down.
    fn depth(&self, i: usize) -> usize {
        1 + self.nodes[i]
            .child
            .iter()
            .filter(|&&c| c != NONE && c & LEAF == 0)
            .map(|&c| self.depth(c as usize))
            .max()
            .unwrap_or(0)
    }

    /// Makes the wide node over binary node `root` (and those under it); returns its index.
    fn collapse(&mut self, bin: &[Node], size: &[u32], root: u32) -> u32 {
        let me = self.nodes.len();
        self.nodes.push(WideNode {
            lo: [[f32::INFINITY; WIDTH]; 3],
            hi: [[f32::NEG_INFINITY; WIDTH]; 3],
            child: [NONE; WIDTH],
            used: 0,
        });
        self.from.push([NONE; WIDTH]);
        let internal = |b: u32| bin[b as usize].first & LEAF == 0;
        let mut slots = vec![root];
        while slots.len() < WIDTH {
            // The internal subtree with the most leaves (the first of equals) gives way to its
            // two children.
            let Some(k) = (0..slots.len())
                .filter(|&k| internal(slots[k]))
                .max_by_key(|&k| (size[slots[k] as usize], std::cmp::Reverse(k)))
            else {
                break;
            };
            let n = bin[slots[k] as usize];
            slots[k] = n.first;
            slots.insert(k + 1, n.right);
        }
        for (k, &b) in slots.iter().enumerate() {
            let n = bin[b as usize];
            let child = if internal(b) {
                self.collapse(bin, size, b)
            } else {
                n.first
            };
            self.nodes[me].child[k] = child;
            self.nodes[me].used |= 1 << k;
            self.from[me][k] = b;
        }
        me as u32
    }

    /// Takes the boxes of the binary nodes the slots stand for.
    pub(super) fn refit(&mut self, bin: &[Node]) {
        for (node, from) in self.nodes.iter_mut().zip(&self.from) {
            for (k, &b) in from.iter().enumerate() {
                let bounds = if b == NONE {
                    Aabb::EMPTY
                } else {
                    bin[b as usize].bounds
                };
                for a in 0..3 {
                    node.lo[a][k] = bounds.lo[a];
                    node.hi[a][k] = bounds.hi[a];
                }
            }
        }
    }

    /// The least of `leaf(p, i)` over the leaves whose boxes are not farther than the best
    /// value found by more than `beyond` allows (a box is skipped where `d2 > best * (1 +
    /// rel) + abs`, `beyond = (rel, abs)`), starting from the root at squared distance
    /// `root_d2`; nearest children first.
    #[inline(always)]
    pub(super) fn nearest(
        &self,
        p: V3,
        root_d2: f32,
        avx2: bool,
        beyond: (f32, f32),
        leaf: impl Fn(V3, usize) -> f32,
    ) -> f32 {
        let far = |d2: f32, best: f32| d2 > best * (1.0 + beyond.0) + beyond.1;
        let mut best = f32::INFINITY;
        // Nodes still to visit with their boxes' squared distances, the nearest on top.
        let mut stack = [(0u32, 0f32); STACK];
        stack[0] = (0, root_d2);
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let (i, d2) = stack[top];
            if far(d2, best) {
                continue;
            }
            if i & LEAF != 0 {
                best = mn(leaf(p, (i & !LEAF) as usize), best);
                continue;
            }
            let node = &self.nodes[i as usize];
            let limit = best * (1.0 + beyond.0) + beyond.1;
            top = push_children(node, p, limit, avx2, &mut stack, top);
        }
        best
    }
}

/// Pushes the children of `node` whose boxes lie within squared distance `limit` of `p` onto
/// `stack` above `top`, each placed by its rank among them (the nearer, or the earlier of equals,
/// first) so that the nearest ends on top; returns the new top. No data-dependent branch but
/// the loop over the children pushed.
#[inline(always)]
fn push_children(
    node: &WideNode,
    p: V3,
    limit: f32,
    avx2: bool,
    stack: &mut [(u32, f32); STACK],
    top: usize,
) -> usize {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        // SAFETY: AVX2 and POPCNT were detected at run time.
        return unsafe { push_children_avx2(node, p, limit, stack, top) };
    }
    let _ = avx2;
    let d: [f32; WIDTH] = std::array::from_fn(|k| {
        let mut d2 = 0.0;
        for (a, &c) in p.iter().enumerate() {
            let e = mx(mx(node.lo[a][k] - c, c - node.hi[a][k]), 0.0);
            d2 += e * e;
        }
        d2
    });
    let mut valid = 0u32;
    for (k, &dk) in d.iter().enumerate() {
        valid |= u32::from(dk <= limit) << k;
    }
    valid &= node.used;
    let n = valid.count_ones() as usize;
    let mut m = valid;
    while m != 0 {
        let k = m.trailing_zeros() as usize;
        m &= m - 1;
        let (mut lt, mut eq) = (0u32, 0u32);
        for (j, &dj) in d.iter().enumerate() {
            lt |= u32::from(dj < d[k]) << j;
            eq |= u32::from(dj == d[k]) << j;
        }
        let rank = (valid & (lt | (eq & ((1 << k) - 1)))).count_ones() as usize;
        stack[top + n - 1 - rank] = (node.child[k], d[k]);
    }
    top + n
}

/// [`push_children`] with the eight boxes measured, compared and ranked in AVX2 registers
/// (the boxes' distances by [`Aabb::dist2`]'s operations).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,popcnt")]
fn push_children_avx2(
    node: &WideNode,
    p: V3,
    limit: f32,
    stack: &mut [(u32, f32); STACK],
    top: usize,
) -> usize {
    use std::arch::x86_64::*;
    let zero = _mm256_setzero_ps();
    let mut d2 = zero;
    for (a, &c) in p.iter().enumerate() {
        // SAFETY: each row is 8 f32 at a 32-byte boundary (`repr(align(32))`).
        let (lo, hi) = unsafe {
            (
                _mm256_load_ps(node.lo[a].as_ptr()),
                _mm256_load_ps(node.hi[a].as_ptr()),
            )
        };
        let c = _mm256_set1_ps(c);
        let e = _mm256_max_ps(
            _mm256_max_ps(_mm256_sub_ps(lo, c), _mm256_sub_ps(c, hi)),
            zero,
        );
        d2 = _mm256_add_ps(d2, _mm256_mul_ps(e, e));
    }
    let mask = |m: __m256| _mm256_movemask_ps(m) as u32;
    let valid = mask(_mm256_cmp_ps::<_CMP_LE_OQ>(d2, _mm256_set1_ps(limit))) & node.used;
    let mut d = [0f32; WIDTH];
    // SAFETY: `d` holds 8 f32.
    unsafe { _mm256_storeu_ps(d.as_mut_ptr(), d2) };
    let n = valid.count_ones() as usize;
    let mut m = valid;
    while m != 0 {
        let k = m.trailing_zeros() as usize;
        m &= m - 1;
        let dk = _mm256_set1_ps(d[k]);
        let (lt, eq) = (
            mask(_mm256_cmp_ps::<_CMP_LT_OQ>(d2, dk)),
            mask(_mm256_cmp_ps::<_CMP_EQ_OQ>(d2, dk)),
        );
        let rank = (valid & (lt | (eq & ((1 << k) - 1)))).count_ones() as usize;
        stack[top + n - 1 - rank] = (node.child[k], d[k]);
    }
    top + n
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A binary tree in the index's layout (children after their parent) whose every internal
    /// node has a leaf on the left and the rest of the chain on the right.
    fn chain(levels: usize) -> Vec<Node> {
        let mut nodes = Vec::new();
        for l in 0..levels {
            let me = nodes.len() as u32;
            nodes.push(Node {
                bounds: Aabb::EMPTY,
                first: me + 1,
                right: me + 2,
            });
            nodes.push(Node {
                bounds: Aabb::EMPTY,
                first: LEAF | l as u32,
                right: 0,
            });
        }
        nodes.push(Node {
            bounds: Aabb::EMPTY,
            first: LEAF | levels as u32,
            right: 0,
        });
        nodes
    }

    #[test]
    fn a_chain_collapses_seven_levels_a_node_and_a_too_deep_one_is_refused() {
        // Each wide node takes seven leaves of the chain and goes on with the eighth slot.
        let t = WideTree::new(&chain(20)).unwrap();
        assert_eq!(t.depth(0), 3);
        assert_eq!(t.nodes[0].used, 0xff);
        assert!(t.nodes[0].child[..7].iter().all(|&c| c & LEAF != 0));
        assert_eq!(t.nodes[0].child[7], 1);
        // 9 levels fill the stack's 64 entries exactly; a tenth does not fit.
        assert!(WideTree::new(&chain(7 * 9)).is_ok());
        let e = WideTree::new(&chain(7 * 9 + 1)).unwrap_err();
        assert!(e.contains("10 levels deep"), "{e}");
    }
}
