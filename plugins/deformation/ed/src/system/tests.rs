#![allow(clippy::unwrap_used)]
use super::*;
use crate::schur::AFF;
use misslam_framework::nalgebra::{DMatrix, DVector};

/// A small deterministic generator (xorshift) for the test's random system.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}

/// Assembles a system with the structure the solver produces: E_reg edges along a ring and
/// chords, data points binding pairs of the data nodes, a PSD diagonal per node (E_rot's
/// place), and the pose coupled through the data nodes. Returns it and the node count.
fn random_system(pose: bool, eliminate: bool, rng: &mut Rng) -> BlockSystem {
    random_system_laid_out(pose, eliminate, &[], rng)
}

/// [`random_system`] in a system laid out first for its pattern with `extra` pairs too (which
/// then covers it: the blocks of `extra` stay zero).
fn random_system_laid_out(
    pose: bool,
    eliminate: bool,
    extra: &[(u32, u32)],
    rng: &mut Rng,
) -> BlockSystem {
    const N: u32 = 14;
    let data_nodes: Vec<u32> = vec![0, 1, 2, 5, 9];
    let mut edges = Vec::new();
    for j in 0..N {
        edges.push((j, (j + 1) % N));
        edges.push((j, (j + 3) % N));
        if j % 2 == 0 {
            edges.push((j, (j + N - 1) % N));
        }
    }
    let points: Vec<(u32, u32)> = vec![(0, 1), (1, 2), (2, 5), (5, 9), (9, 0), (0, 5)];
    let mut pairs: Vec<(u32, u32)> = edges
        .iter()
        .chain(&points)
        .map(|&(a, b)| (a.min(b), a.max(b)))
        .collect();
    pairs.sort_unstable();
    pairs.dedup();
    let eliminated: Vec<u32> = if eliminate {
        (0..N).filter(|j| !data_nodes.contains(j)).collect()
    } else {
        Vec::new()
    };
    let mut links: Vec<(u32, u32)> = edges
        .iter()
        .copied()
        .filter(|(j, _)| eliminated.contains(j))
        .collect();
    links.sort_unstable();
    links.dedup();
    let key = PatternKey {
        free: (0..N).collect(),
        pairs,
        pose,
        eliminated,
        links,
    };
    let mut sys = BlockSystem::default();
    if !extra.is_empty() {
        let mut wide = key.clone();
        wide.pairs.extend_from_slice(extra);
        wide.pairs.sort_unstable();
        wide.pairs.dedup();
        sys.prepare(N as usize, &wide).unwrap();
        assert!(wide.covers(&key) && !key.covers(&wide));
    }
    sys.prepare(N as usize, &key).unwrap();
    assert_eq!(sys.symbolic_builds, 1, "one pattern laid out");
    let slot = sys.slot.clone();
    let s = |j: u32| slot[j as usize];
    const E4: [f64; 4] = [0.0, 0.0, 0.0, 1.0];
    let rnd4 = |rng: &mut Rng| [rng.next() * 5.0, rng.next() * 5.0, rng.next() * 5.0, 1.0];
    for &(j, k) in &edges {
        let u = rnd4(rng);
        let w = 1.0 + rng.next().abs();
        let (sj, sk) = (s(j), s(k));
        sys.add_kron_identity(sj, sj, &u, &u, w);
        sys.add_kron_identity(sk, sk, &E4, &E4, w);
        sys.add_kron_identity(sj, sk, &u, &E4, -w);
    }
    for &(a, b) in &points {
        let n = [rng.next(), rng.next(), rng.next()];
        let m: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|k| n[i] * n[k]));
        let (ua, ub) = (rnd4(rng), rnd4(rng));
        let (wa, wb) = (0.5 + rng.next().abs(), 0.5 + rng.next().abs());
        let (sa, sb) = (s(a), s(b));
        sys.add_kron(sa, sa, &m, &ua, &ua, wa * wa);
        sys.add_kron(sb, sb, &m, &ub, &ub, wb * wb);
        sys.add_kron(sa, sb, &m, &ua, &ub, wa * wb);
    }
    for j in 0..N {
        // A PSD 12x12 of rank 6 (E_rot has 6 rows), plus the ridge the solver's damping adds.
        let g: Vec<f64> = (0..72).map(|_| rng.next()).collect();
        let mut h = [0.0; 144];
        for r in 0..12 {
            for c in 0..12 {
                h[c * 12 + r] = (0..6).map(|q| g[q * 12 + r] * g[q * 12 + c]).sum();
            }
        }
        sys.add_diag(s(j), &h);
    }
    let nb = sys.blocks_solved();
    // The gradient drawn node by node (not in block order, which depends on the layout).
    for j in 0..N {
        for q in 0..12 {
            sys.grad[12 * s(j) as usize + q] = rng.next();
        }
    }
    for x in sys.grad[12 * N as usize..].iter_mut() {
        *x = rng.next();
    }
    if pose {
        for p in 0..6 {
            sys.pose_block[p * 6 + p] = 50.0;
        }
        for &j in &data_nodes {
            for v in sys.pose_cross[s(j) as usize].iter_mut() {
                *v = 0.3 * rng.next();
            }
        }
    }
    assert_eq!(sys.blocks_solved(), nb);
    sys
}

fn dense_solve(sys: &BlockSystem, lambda: f64, ridge: f64) -> Option<Vec<f64>> {
    let n = sys.dim();
    let mut h = DMatrix::from_row_slice(n, n, &sys.to_dense());
    for i in 0..n {
        let d = h[(i, i)];
        h[(i, i)] = d + lambda * (d.abs() + ridge) + 1e-12 * ridge;
    }
    let g = DVector::from_column_slice(&sys.grad);
    h.cholesky().map(|c| c.solve(&(-g)).as_slice().to_vec())
}

#[test]
fn eliminating_the_data_free_affine_parts_gives_the_full_systems_solution() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for pose in [false, true] {
        for lambda in [0.0, 0.05] {
            let mut sys = random_system(pose, true, &mut rng);
            // 5 data nodes keep 12 unknowns, 9 data-free ones keep their translation.
            assert_eq!(sys.factor_dim(), 5 * 12 + 9 * 3 + if pose { 6 } else { 0 });
            let want = dense_solve(&sys, lambda, 1e-6).expect("the test system is SPD");
            let mut dx = Vec::new();
            assert!(sys.solve(lambda, 1e-6, &mut dx).unwrap());
            let scale = want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            let err = dx
                .iter()
                .zip(&want)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                err <= 1e-9 * scale.max(1.0),
                "pose {pose}, lambda {lambda}: max deviation {err:e} (scale {scale:e})"
            );
            // And the same system without elimination agrees too.
            let mut full = random_system(pose, false, &mut Rng(rng.0));
            assert_eq!(full.factor_dim(), 14 * 12 + if pose { 6 } else { 0 });
            let want = dense_solve(&full, lambda, 1e-6).unwrap();
            let mut dx = Vec::new();
            assert!(full.solve(lambda, 1e-6, &mut dx).unwrap());
            let err = dx
                .iter()
                .zip(&want)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(err <= 1e-9 * scale.max(1.0), "without elimination: {err:e}");
        }
    }
}

#[test]
fn a_kept_factorisation_solves_a_new_gradient_with_the_old_matrix() {
    let mut rng = Rng(0x2545_f491_4f6c_dd1d);
    for pose in [false, true] {
        for eliminate in [false, true] {
            let mut sys = random_system(pose, eliminate, &mut rng);
            let mut dx = Vec::new();
            // Nothing factorised yet: refused, not a stale answer.
            assert!(!sys.is_factored());
            assert!(!sys.resolve(&mut dx).unwrap());
            let lambda = 0.05;
            let old = dense_solve(&sys, lambda, 1e-6).unwrap();
            assert!(sys.solve(lambda, 1e-6, &mut dx).unwrap());
            assert!(sys.is_factored());
            // The same gradient again: the same step.
            let mut again = Vec::new();
            assert!(sys.resolve(&mut again).unwrap());
            let dev = again
                .iter()
                .zip(&dx)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(dev <= 1e-12 * old.iter().fold(1.0f64, |m, x| m.max(x.abs())));
            // A new gradient with the blocks zeroed (what a gradient-only assembly leaves):
            // the old damped matrix's solution for it.
            let h_old = sys.to_dense();
            let g: Vec<f64> = (0..sys.dim()).map(|_| rng.next()).collect();
            sys.blocks.iter_mut().for_each(|b| b.fill(0.0));
            sys.pose_cross.iter_mut().for_each(|b| b.fill(0.0));
            sys.pose_block.fill(0.0);
            sys.grad.copy_from_slice(&g);
            let n = sys.dim();
            let mut h = DMatrix::from_row_slice(n, n, &h_old);
            for i in 0..n {
                let d = h[(i, i)];
                h[(i, i)] = d + lambda * (d.abs() + 1e-6) + 1e-12 * 1e-6;
            }
            let want = h
                .cholesky()
                .unwrap()
                .solve(&(-DVector::from_column_slice(&g)));
            assert!(sys.resolve(&mut dx).unwrap());
            let scale = want.iter().fold(1.0f64, |m, x| m.max(x.abs()));
            let err = dx
                .iter()
                .zip(want.iter())
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                err <= 1e-9 * scale,
                "pose {pose}, eliminate {eliminate}: max deviation {err:e} (scale {scale:e})"
            );
            // A new pattern drops the factorisation.
            let key = PatternKey {
                pose: !sys.key.pose,
                ..sys.key.clone()
            };
            sys.prepare(sys.slot.len(), &key).unwrap();
            assert!(!sys.is_factored());
            assert!(!sys.resolve(&mut dx).unwrap());
        }
    }
}

#[test]
fn an_eliminated_block_that_is_not_positive_definite_is_reported() {
    let mut sys = random_system(false, true, &mut Rng(7));
    // Make the affine block of one eliminated node indefinite: its 9x9 Cholesky must fail.
    let s = sys.slot[3];
    let idx = sys.find(s, s);
    for r in AFF {
        sys.blocks[idx][r * 12 + r] = -1.0;
    }
    let mut dx = Vec::new();
    assert!(!sys.solve(0.0, 1e-6, &mut dx).unwrap());
}

#[test]
fn a_link_outside_the_pairs_is_an_error_not_a_panic() {
    let key = PatternKey {
        free: vec![0, 1, 2],
        pairs: vec![(0, 1)],
        pose: false,
        eliminated: vec![2],
        links: vec![(2, 0)],
    };
    let err = BlockSystem::default().prepare(3, &key).unwrap_err();
    assert!(err.contains("not among the pairs"), "{err}");
}

#[test]
fn a_deferred_factor_solves_as_the_prepared_one_and_is_needed_to_solve() {
    let mut rng = Rng(0x5851_f42d_4c95_7f2d);
    for pose in [false, true] {
        for eliminate in [false, true] {
            let mut want_sys = random_system(pose, eliminate, &mut rng);
            let (n_nodes, key) = (want_sys.slot.len(), want_sys.key.clone());
            let mut want = Vec::new();
            assert!(want_sys.solve(0.05, 1e-6, &mut want).unwrap());
            // Laid out with the factor structures left to a job, then assembled (here, the
            // same sums copied: the same key gives the same ordering and blocks).
            let mut sys = BlockSystem::default();
            let job = sys
                .prepare_deferred(n_nodes, &key)
                .unwrap()
                .expect("a new layout");
            assert_eq!(sys.slot, want_sys.slot);
            sys.blocks.copy_from_slice(&want_sys.blocks);
            sys.pose_cross.copy_from_slice(&want_sys.pose_cross);
            sys.pose_block = want_sys.pose_block;
            sys.grad.copy_from_slice(&want_sys.grad);
            // Before the job is installed: an error, not a panic nor a stale answer.
            let mut dx = Vec::new();
            let err = sys.solve(0.05, 1e-6, &mut dx).unwrap_err();
            assert!(err.contains("not prepared"), "{err}");
            sys.install(job.build()).unwrap();
            assert_eq!(sys.symbolic_builds, 1);
            assert_eq!(sys.factor_dim(), want_sys.factor_dim());
            assert!(sys.solve(0.05, 1e-6, &mut dx).unwrap());
            assert_eq!(dx, want, "pose {pose}, eliminate {eliminate}");
            // The pattern serves on: no new layout, no job.
            assert!(sys.prepare_deferred(n_nodes, &key).unwrap().is_none());
            // A job dropped unbuilt: the next preparation lays the pattern out again.
            let mut dropped = BlockSystem::default();
            drop(dropped.prepare_deferred(n_nodes, &key).unwrap());
            assert!(dropped.solve(0.05, 1e-6, &mut dx).is_err());
            dropped.prepare(n_nodes, &key).unwrap();
            assert_eq!(dropped.symbolic_builds, 1);
            assert!(dropped.prepare_deferred(n_nodes, &key).unwrap().is_none());
        }
    }
}

#[test]
fn a_wider_pattern_serves_and_widening_takes_the_union() {
    // Pairs among the data nodes (0, 1, 2, 5, 9) that no edge or point couples.
    let extra = [(1, 5), (1, 9), (2, 9)];
    let mut rng = Rng(0x1234_5678_9abc_def1);
    for pose in [false, true] {
        for eliminate in [false, true] {
            let seed = Rng(rng.0);
            let mut wide = random_system_laid_out(pose, eliminate, &extra, &mut Rng(seed.0));
            let mut exact = random_system(pose, eliminate, &mut Rng(seed.0));
            rng.next();
            assert!(wide.key.pairs.len() == exact.key.pairs.len() + extra.len());
            for (sys, what) in [(&mut wide, "wider"), (&mut exact, "exact")] {
                let want = dense_solve(sys, 0.05, 1e-6).unwrap();
                let mut dx = Vec::new();
                assert!(sys.solve(0.05, 1e-6, &mut dx).unwrap());
                let scale = want.iter().fold(1.0f64, |m, x| m.max(x.abs()));
                let err = dx
                    .iter()
                    .zip(&want)
                    .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                assert!(err <= 1e-9 * scale, "{what}, pose {pose}: {err:e}");
            }
            // The same matrix in both layouts (their block orders may differ): the same step,
            // node by node.
            let (mut a, mut b) = (Vec::new(), Vec::new());
            assert!(wide.solve(0.05, 1e-6, &mut a).unwrap());
            assert!(exact.solve(0.05, 1e-6, &mut b).unwrap());
            for j in 0..14 {
                let (sa, sb) = (wide.slot[j] as usize, exact.slot[j] as usize);
                for q in 0..12 {
                    let (x, y) = (a[12 * sa + q], b[12 * sb + q]);
                    assert!(
                        (x - y).abs() <= 1e-9 * x.abs().max(1.0),
                        "node {j}: {x} vs {y}"
                    );
                }
            }
        }
    }
    // Widening: the union when the unknowns match, the new key alone when they do not.
    let key = |free: Vec<u32>, pairs: Vec<(u32, u32)>| PatternKey {
        free,
        pairs,
        ..Default::default()
    };
    let a = key(vec![0, 1, 2, 3], vec![(0, 1), (1, 3)]);
    let b = key(vec![0, 1, 2, 3], vec![(0, 2), (1, 3), (2, 3)]);
    let u = a.widened(&b);
    assert_eq!(u.pairs, vec![(0, 1), (0, 2), (1, 3), (2, 3)]);
    assert!(u.covers(&a) && u.covers(&b) && !a.covers(&b));
    let c = key(vec![0, 1, 2], vec![(0, 1)]);
    assert_eq!(u.widened(&c), c);
    assert!(!u.covers(&c));
}

#[test]
fn blocks_are_found_by_the_table_and_by_the_search_alike() {
    // 50 nodes a side: the dense table; 1,100: beyond it, the column search.
    for n in [50u32, 1100] {
        let mut pairs: Vec<(u32, u32)> = (0..n - 1).map(|j| (j, j + 1)).collect();
        pairs.extend((0..n - 7).map(|j| (j, j + 7)));
        pairs.sort_unstable();
        let key = PatternKey {
            free: (0..n).collect(),
            pairs: pairs.clone(),
            ..Default::default()
        };
        let mut sys = BlockSystem::default();
        sys.prepare(n as usize, &key).unwrap();
        assert_eq!(sys.lookup.is_empty(), n as usize > DENSE_LOOKUP_MAX);
        for (a, b) in pairs.into_iter().chain((0..n).map(|j| (j, j))) {
            let (sa, sb) = (sys.slot[a as usize], sys.slot[b as usize]);
            let (lo, hi) = (sa.min(sb), sa.max(sb));
            let idx = sys.find(lo, hi);
            let col = sys.col_start[hi as usize]..sys.col_start[hi as usize + 1];
            assert!(
                col.contains(&idx),
                "n {n}: block ({lo}, {hi}) outside its column"
            );
            assert_eq!(sys.rows[idx], lo, "n {n}: block ({lo}, {hi})");
        }
    }
}

#[test]
fn the_elimination_tree_from_the_blocks_is_the_one_faer_computes_from_the_scalars() {
    use faer::sparse::linalg::cholesky::simplicial::prefactorize_symbolic_cholesky;
    // Random block patterns (blocks of 3 and 12 unknowns, sparse couplings, some with a last
    // block coupled to all, as the pose is), expanded to the scalar upper triangle the system
    // hands faer: the tree and column counts must be faer's own, which `from_inner` relies on.
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    for case in 0..60 {
        let nb = 1 + case % 23 + (case / 23) * 40;
        let pose = case % 3 == 0;
        let nodes = nb - usize::from(pose && nb > 1);
        let mut size: Vec<usize> = (0..nb)
            .map(|_| if rng.next() < 0.0 { 3 } else { 12 })
            .collect();
        if pose && nb > 1 {
            size[nb - 1] = 6;
        }
        let mut off = vec![0usize; nb];
        for b in 1..nb {
            off[b] = off[b - 1] + size[b - 1];
        }
        let density = 0.05 + 0.3 * (rng.next() + 1.0) / 2.0;
        let mut cols: Vec<Vec<u32>> = (0..nb).map(|b| vec![b as u32]).collect();
        for c in 0..nodes {
            for r in 0..c {
                if (rng.next() + 1.0) / 2.0 < density {
                    let at = cols[c].len() - 1;
                    cols[c].insert(at, r as u32);
                }
            }
        }
        if pose && nb > 1 {
            cols[nb - 1] = (0..nb as u32).collect();
        }
        let views: Vec<&[u32]> = cols.iter().map(|c| c.as_slice()).collect();
        let (etree, counts) = block_etree(&views, &size, &off);
        // The scalar upper triangle: whole off-diagonal blocks, dense diagonal ones.
        let n: usize = size.iter().sum();
        let mut col_ptr = vec![0usize];
        let mut row_idx = Vec::new();
        for (c, list) in cols.iter().enumerate() {
            for cc in 0..size[c] {
                for &r in &list[..list.len() - 1] {
                    row_idx.extend(off[r as usize]..off[r as usize] + size[r as usize]);
                }
                row_idx.extend(off[c]..=off[c] + cc);
                col_ptr.push(row_idx.len());
            }
        }
        let a = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        let mut want_tree = vec![0isize; n];
        let mut want_counts = vec![0usize; n];
        let mut mem = MemBuffer::new(faer::dyn_stack::StackReq::new::<usize>(n));
        prefactorize_symbolic_cholesky(
            &mut want_tree,
            &mut want_counts,
            a,
            MemStack::new(&mut mem),
        );
        assert_eq!(etree, want_tree, "case {case}: {nb} blocks");
        assert_eq!(counts, want_counts, "case {case}: {nb} blocks");
    }
}
