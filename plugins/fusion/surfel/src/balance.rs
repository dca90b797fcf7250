//! The balance of a solve's energy terms: E_data scaled by its term count
//! ([`data_points_per_node`], [`data_weight_scale`]) and the bound on a node's affine past which
//! it counts as collapsed ([`COLLAPSE_DET`]).

use misslam_deformation_ed::graph::Binding;

/// A node's affine A whose determinant leaves [1 / `COLLAPSE_DET`, `COLLAPSE_DET`] has collapsed
/// (a column flattened: the node projects its surfels onto a plane, and the canonical points of
/// new surfels, mapped back through A^-1, land far off) or blown up; soft tissue does not change
/// its volume fourfold from one frame to the next.
pub const COLLAPSE_DET: f64 = 4.0;

/// The visible surfels per node they bind (with a non-zero weight): E_data's term count per
/// node. `bound` is a reused buffer.
pub fn data_points_per_node(
    visible: &[u32],
    bindings: &[Binding],
    nodes: usize,
    bound: &mut Vec<bool>,
) -> f64 {
    bound.clear();
    bound.resize(nodes, false);
    let mut n = 0usize;
    for &i in visible {
        for (j, w) in bindings[i as usize].iter() {
            if w > 0.0 && !std::mem::replace(&mut bound[j as usize], true) {
                n += 1;
            }
        }
    }
    if n == 0 {
        0.0
    } else {
        visible.len() as f64 / n as f64
    }
}

/// The factor on `weights.data` for a solve whose data terms average `per_node` per node, with
/// `Params::data_points_per_node` = `reference` (0: off): `reference / per_node` above it, else 1.
pub fn data_weight_scale(per_node: f64, reference: f64) -> f64 {
    if reference > 0.0 && per_node > reference {
        reference / per_node
    } else {
        1.0
    }
}

/// The visible surfels a solve takes: all of them while they average at most `cap` per node
/// they bind (`per_node`, [`data_points_per_node`]; `cap` 0: off), else one in
/// ceil(`per_node` / `cap`), picked by a hash of the surfel's index so that the ones kept spread
/// over the surface without following the order in which the surfels were added. `None`: all.
pub fn thin_visible(visible: &[u32], per_node: f64, cap: f64) -> Option<Vec<u32>> {
    if !(cap > 0.0 && per_node > cap) {
        return None;
    }
    let k = (per_node / cap).ceil() as u64;
    Some(
        visible
            .iter()
            .copied()
            .filter(|&i| {
                // A 64-bit multiplicative hash (Fibonacci hashing), its high bits modulo k.
                (u64::from(i).wrapping_mul(0x9e37_79b9_7f4a_7c15) >> 32) % k == 0
            })
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn data_terms_per_node_count_the_nodes_the_visible_points_bind() {
        let bind = |pairs: &[(u32, f64)]| {
            let mut b = Binding::EMPTY;
            for (i, &(j, w)) in pairs.iter().enumerate() {
                b.nodes[i] = j;
                b.weights[i] = w;
            }
            b.len = pairs.len() as u8;
            b
        };
        let bindings = [
            bind(&[(0, 0.5), (1, 0.5)]),
            bind(&[(1, 0.7), (2, 0.3)]),
            // A zero weight binds nothing.
            bind(&[(2, 1.0), (3, 0.0)]),
            bind(&[(4, 1.0)]),
        ];
        let mut buf = vec![true; 2];
        // Points 0, 1 and 2 bind nodes 0, 1 and 2: one point per node.
        assert_eq!(
            data_points_per_node(&[0, 1, 2], &bindings, 5, &mut buf),
            1.0
        );
        // Points 0 and 1 bind nodes 0, 1 and 2 (the buffer is reset between calls).
        assert_eq!(
            data_points_per_node(&[0, 1], &bindings, 5, &mut buf),
            2.0 / 3.0
        );
        assert_eq!(data_points_per_node(&[3], &bindings, 5, &mut buf), 1.0);
        assert_eq!(data_points_per_node(&[], &bindings, 5, &mut buf), 0.0);
        // The weight is scaled down only above the reference, and not at all with 0.
        assert_eq!(data_weight_scale(880.0, 32.0), 32.0 / 880.0);
        assert_eq!(data_weight_scale(20.0, 32.0), 1.0);
        assert_eq!(data_weight_scale(880.0, 0.0), 1.0);
    }

    #[test]
    fn thinning_keeps_one_in_k_spread_over_the_indices() {
        let visible: Vec<u32> = (0..30_000).collect();
        // At or under the cap, or with the cap off, every point stays.
        assert_eq!(thin_visible(&visible, 48.0, 64.0), None);
        assert_eq!(thin_visible(&visible, 64.0, 64.0), None);
        assert_eq!(thin_visible(&visible, 500.0, 0.0), None);
        // 140 per node with a cap of 64: one in 3.
        let kept = thin_visible(&visible, 140.0, 64.0).unwrap();
        let share = kept.len() as f64 / visible.len() as f64;
        assert!((share - 1.0 / 3.0).abs() < 0.01, "kept {share}");
        // In order, and spread: every block of 300 consecutive indices keeps 100 +- 30.
        assert!(kept.windows(2).all(|p| p[0] < p[1]));
        for b in 0..100u32 {
            let n = kept.iter().filter(|&&i| i / 300 == b).count();
            assert!((70..=130).contains(&n), "block {b} kept {n}");
        }
        // Not a regular stride: gaps of 1 to 3 and longer all occur.
        let gaps: std::collections::BTreeSet<u32> = kept.windows(2).map(|p| p[1] - p[0]).collect();
        assert!(gaps.contains(&1) && gaps.len() > 4, "gaps {gaps:?}");
    }
}
