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
}
