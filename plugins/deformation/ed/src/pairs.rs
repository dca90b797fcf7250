//! The pattern key of a solve (its solved nodes, coupled node pairs, eliminations) and the
//! set its coupled pairs are collected in (see [`crate::solver`]).

use crate::graph::{Binding, EdGraph};
use crate::problem::Problem;
use crate::solver::SolveSet;
use crate::system::PatternKey;
use rayon::prelude::*;

/// The set of coupled node pairs (j < k) of a solve, collected from every point's binding. With
/// up to [`CoupledPairs::DENSE_MAX`] solved nodes a bit per pair of their local ids (hundreds of
/// thousands of insertions a frame, most of them repeats); beyond, a list sorted once.
pub(crate) enum CoupledPairs {
    Dense {
        /// Node id -> local id among the solved nodes.
        local: Vec<u32>,
        free: Vec<u32>,
        bits: Vec<u64>,
    },
    List(Vec<(u32, u32)>),
}

impl CoupledPairs {
    pub(crate) const DENSE_MAX: usize = 2048;

    pub(crate) fn new(n_nodes: usize, free: &[u32]) -> Self {
        if free.len() > Self::DENSE_MAX || !free.windows(2).all(|w| w[0] < w[1]) {
            return CoupledPairs::List(Vec::new());
        }
        let mut local = vec![u32::MAX; n_nodes];
        for (i, &j) in free.iter().enumerate() {
            local[j as usize] = i as u32;
        }
        let n = free.len();
        CoupledPairs::Dense {
            local,
            free: free.to_vec(),
            bits: vec![0; (n * n).div_ceil(64)],
        }
    }

    /// Adds the pair of two distinct solved nodes, in either order.
    #[inline]
    pub(crate) fn insert(&mut self, x: u32, y: u32) {
        match self {
            CoupledPairs::Dense {
                local, free, bits, ..
            } => {
                let (a, b) = (local[x as usize] as usize, local[y as usize] as usize);
                let bit = a.min(b) * free.len() + a.max(b);
                bits[bit / 64] |= 1 << (bit % 64);
            }
            CoupledPairs::List(v) => v.push((x.min(y), x.max(y))),
        }
    }

    /// The pairs (j < k by node id), sorted, unique.
    pub(crate) fn into_sorted(self) -> Vec<(u32, u32)> {
        match self {
            CoupledPairs::Dense { free, bits, .. } => {
                // Local ids ascend with node ids (`free` is ascending), so row-major order over
                // (a < b) is the sorted order of (free[a], free[b]).
                let n = free.len();
                let mut out = Vec::new();
                for (w, &word) in bits.iter().enumerate() {
                    let mut m = word;
                    while m != 0 {
                        let bit = w * 64 + m.trailing_zeros() as usize;
                        m &= m - 1;
                        out.push((free[bit / n], free[bit % n]));
                    }
                }
                out
            }
            CoupledPairs::List(mut v) => {
                v.par_sort_unstable();
                v.dedup();
                v
            }
        }
    }
}

/// Block pattern of `set` ([`crate::solver::Solver`]'s pattern key); `full_factorisation` keeps every node's affine
/// part in the factorisation.
pub(crate) fn pattern_key(
    graph: &EdGraph,
    problem: &Problem,
    set: &SolveSet,
    full_factorisation: bool,
) -> PatternKey {
    let mut is_free = vec![false; graph.len()];
    for &j in &set.free {
        is_free[j as usize] = true;
    }
    let mut pairs = CoupledPairs::new(graph.len(), &set.free);
    for &(j, k) in &set.reg_edges {
        if is_free[j as usize] && is_free[k as usize] && j != k {
            pairs.insert(j, k);
        }
    }
    // Nodes some data term binds: their A couples to other nodes' A and to the pose.
    let mut has_data = vec![false; graph.len()];
    if set.data {
        let mut add = |b: &Binding| {
            for &x in &b.nodes[..b.len as usize] {
                has_data[x as usize] = true;
            }
            for a in 0..b.len as usize {
                for c in a + 1..b.len as usize {
                    let (x, y) = (b.nodes[a], b.nodes[c]);
                    if is_free[x as usize] && is_free[y as usize] && x != y {
                        pairs.insert(x, y);
                    }
                }
            }
        };
        for b in problem.model.bindings {
            add(b);
        }
        for c in problem.correspondences {
            add(&c.binding);
        }
    }
    let pairs = pairs.into_sorted();
    // The rest have their A eliminated before the sparse factorisation (see
    // [`crate::system`]): it reaches their own t and, through E_reg, the t of their edges' ends.
    let eliminated: Vec<u32> = set
        .free
        .iter()
        .copied()
        .filter(|&j| !has_data[j as usize] && !full_factorisation)
        .collect();
    let mut links: Vec<(u32, u32)> = set
        .reg_edges
        .iter()
        .copied()
        .filter(|&(j, k)| {
            j != k
                && is_free[j as usize]
                && is_free[k as usize]
                && !has_data[j as usize]
                && !full_factorisation
        })
        .collect();
    links.sort_unstable();
    links.dedup();
    PatternKey {
        free: set.free.clone(),
        pairs,
        pose: set.pose,
        eliminated,
        links,
    }
}

#[cfg(test)]
mod tests {
    use super::CoupledPairs;

    #[test]
    fn the_pair_bitmap_gives_the_sorted_unique_pairs_of_the_list() {
        // Solved nodes with gaps in their ids, pairs inserted in both orders and repeated.
        let free: Vec<u32> = (0..300).map(|i| 3 * i + 1).collect();
        let mut state = 0x853c_49e6_748f_ea9bu64;
        let mut next = |n: usize| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % n as u64) as usize
        };
        let mut dense = CoupledPairs::new(1000, &free);
        let mut list = CoupledPairs::List(Vec::new());
        assert!(matches!(dense, CoupledPairs::Dense { .. }));
        for _ in 0..20_000 {
            let (a, b) = (free[next(free.len())], free[next(free.len())]);
            if a != b {
                dense.insert(a, b);
                list.insert(b, a);
            }
        }
        let (d, l) = (dense.into_sorted(), list.into_sorted());
        assert!(l.windows(2).all(|w| w[0] < w[1]) && l.iter().all(|&(a, b)| a < b));
        assert_eq!(d, l);
        // Too many nodes, or ids not ascending: the list.
        let many: Vec<u32> = (0..=CoupledPairs::DENSE_MAX as u32).collect();
        assert!(matches!(
            CoupledPairs::new(many.len(), &many),
            CoupledPairs::List(_)
        ));
        assert!(matches!(
            CoupledPairs::new(10, &[4, 2]),
            CoupledPairs::List(_)
        ));
    }
}
