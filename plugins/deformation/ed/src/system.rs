//! Block-sparse normal equations J^T W J dx = -J^T W r with 12x12 blocks (one per node's [A|t]) and
//! an optional 6-wide pose block, assembled straight into block storage, then copied into the upper
//! triangle of a scalar CSC matrix whose pattern is fixed per block pattern, and factorised by faer's
//! sparse Cholesky.
//!
//! The fill-reducing ordering is computed on the block graph (nodes, not scalars: 144 times fewer
//! entries) with faer's AMD, nodes are renumbered in that order, and the pose block goes last (an
//! arrowhead, no fill). The symbolic factorisation is reused for as long as the set of solved nodes
//! and the block pattern stay the same (across iterations, and across frames on a static graph).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Par, Side};

/// Block pattern key: solved nodes, coupled node pairs (node ids, j < k), pose block or not.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PatternKey {
    /// Solved node ids, ascending.
    pub free: Vec<u32>,
    /// Coupled pairs (j < k), sorted, unique.
    pub pairs: Vec<(u32, u32)>,
    /// Whether the pose is among the unknowns.
    pub pose: bool,
}

/// The assembled system and its factorisation workspace.
pub struct BlockSystem {
    key: PatternKey,
    /// Node id -> block index (u32::MAX when the node is held fixed).
    pub slot: Vec<u32>,
    nb: usize,
    col_start: Vec<usize>,
    rows: Vec<u32>,
    /// Upper blocks, column-major 12x12.
    pub blocks: Vec<[f64; 144]>,
    /// Node-pose coupling, per block row, column-major 12x6.
    pub pose_cross: Vec<[f64; 72]>,
    /// Pose-pose block, column-major 6x6.
    pub pose_block: [f64; 36],
    /// Gradient J^T W r, block order (12 per block, then 6 for the pose).
    pub grad: Vec<f64>,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    values: Vec<f64>,
    diag_pos: Vec<usize>,
    symbolic: Option<SymbolicCholesky<usize>>,
    l_values: Vec<f64>,
    scratch: MemBuffer,
    /// How many symbolic factorisations were computed (the reuse is tested through this).
    pub symbolic_builds: usize,
}

impl Default for BlockSystem {
    fn default() -> Self {
        BlockSystem {
            key: PatternKey::default(),
            slot: Vec::new(),
            nb: 0,
            col_start: vec![0],
            rows: Vec::new(),
            blocks: Vec::new(),
            pose_cross: Vec::new(),
            pose_block: [0.0; 36],
            grad: Vec::new(),
            col_ptr: Vec::new(),
            row_idx: Vec::new(),
            values: Vec::new(),
            diag_pos: Vec::new(),
            symbolic: None,
            l_values: Vec::new(),
            scratch: MemBuffer::new(faer::dyn_stack::StackReq::EMPTY),
            symbolic_builds: 0,
        }
    }
}

impl BlockSystem {
    /// Number of scalar unknowns.
    pub fn dim(&self) -> usize {
        12 * self.nb + if self.key.pose { 6 } else { 0 }
    }

    /// Number of solved node blocks.
    pub fn blocks_solved(&self) -> usize {
        self.nb
    }

    /// Sets the pattern (reusing everything when it equals the previous one) and zeroes the system.
    pub fn prepare(&mut self, n_nodes: usize, key: &PatternKey) -> Result<(), String> {
        if *key != self.key || self.symbolic.is_none() || self.slot.len() != n_nodes {
            self.build_pattern(n_nodes, key.clone())?;
        }
        self.blocks.iter_mut().for_each(|b| b.fill(0.0));
        self.pose_cross.iter_mut().for_each(|b| b.fill(0.0));
        self.pose_block.fill(0.0);
        self.grad.fill(0.0);
        Ok(())
    }

    fn build_pattern(&mut self, n_nodes: usize, key: PatternKey) -> Result<(), String> {
        let nf = key.free.len();
        let mut local = vec![u32::MAX; n_nodes];
        for (i, &j) in key.free.iter().enumerate() {
            local[j as usize] = i as u32;
        }
        // Block graph (upper with diagonal) in local numbering, for AMD.
        let mut adj: Vec<Vec<usize>> = (0..nf).map(|i| vec![i]).collect();
        for &(a, b) in &key.pairs {
            let (la, lb) = (local[a as usize], local[b as usize]);
            if la == u32::MAX || lb == u32::MAX {
                continue;
            }
            let (lo, hi) = if la < lb { (la, lb) } else { (lb, la) };
            adj[hi as usize].push(lo as usize);
        }
        let mut cp = vec![0usize; nf + 1];
        let mut ri = Vec::new();
        for (c, list) in adj.iter_mut().enumerate() {
            list.sort_unstable();
            list.dedup();
            ri.extend_from_slice(list);
            cp[c + 1] = ri.len();
        }
        let mut perm = vec![0usize; nf];
        let mut perm_inv = vec![0usize; nf];
        if nf > 0 {
            let sym = SymbolicSparseColMatRef::new_checked(nf, nf, &cp, None, &ri);
            let req = faer::sparse::linalg::amd::order_scratch::<usize>(nf, ri.len());
            let mut mem = MemBuffer::try_new(req)
                .map_err(|_| "out of memory ordering the deformation graph")?;
            faer::sparse::linalg::amd::order(
                &mut perm,
                &mut perm_inv,
                sym,
                Default::default(),
                MemStack::new(&mut mem),
            )
            .map_err(|e| format!("AMD ordering failed: {e:?}"))?;
        }
        // slot[node] = position in the elimination order.
        let mut slot = vec![u32::MAX; n_nodes];
        for (new, &old_local) in perm.iter().enumerate() {
            slot[key.free[old_local] as usize] = new as u32;
        }
        // Upper block pattern in slot numbering, per column.
        let mut cols: Vec<Vec<u32>> = (0..nf).map(|i| vec![i as u32]).collect();
        for &(a, b) in &key.pairs {
            let (sa, sb) = (slot[a as usize], slot[b as usize]);
            if sa == u32::MAX || sb == u32::MAX || sa == sb {
                continue;
            }
            let (lo, hi) = if sa < sb { (sa, sb) } else { (sb, sa) };
            cols[hi as usize].push(lo);
        }
        let mut col_start = vec![0usize; nf + 1];
        let mut rows = Vec::new();
        for (c, list) in cols.iter_mut().enumerate() {
            list.sort_unstable();
            list.dedup();
            rows.extend_from_slice(list);
            col_start[c + 1] = rows.len();
        }
        // Scalar CSC, upper triangle.
        let pose = key.pose;
        let n = 12 * nf + if pose { 6 } else { 0 };
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        let mut diag_pos = Vec::with_capacity(n);
        col_ptr.push(0);
        for bj in 0..nf {
            let list = &rows[col_start[bj]..col_start[bj + 1]];
            for cc in 0..12 {
                for &bi in &list[..list.len() - 1] {
                    row_idx.extend((0..12).map(|r| 12 * bi as usize + r));
                }
                row_idx.extend((0..=cc).map(|r| 12 * bj + r));
                diag_pos.push(row_idx.len() - 1);
                col_ptr.push(row_idx.len());
            }
        }
        if pose {
            for pc in 0..6 {
                row_idx.extend(0..12 * nf);
                row_idx.extend((0..=pc).map(|r| 12 * nf + r));
                diag_pos.push(row_idx.len() - 1);
                col_ptr.push(row_idx.len());
            }
        }
        let symbolic = if n > 0 {
            let a = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
            Some(
                factorize_symbolic_cholesky(
                    a,
                    Side::Upper,
                    SymmetricOrdering::Identity,
                    CholeskySymbolicParams::default(),
                )
                .map_err(|e| format!("symbolic Cholesky failed: {e:?}"))?,
            )
        } else {
            None
        };
        if let Some(s) = &symbolic {
            self.l_values = vec![0.0; s.len_val()];
            let req = s
                .factorize_numeric_llt_scratch::<f64>(Par::Seq, Default::default())
                .or(s.solve_in_place_scratch::<f64>(1, Par::Seq));
            self.scratch =
                MemBuffer::try_new(req).map_err(|_| "out of memory for the Cholesky workspace")?;
        }
        self.symbolic_builds += 1;
        self.nb = nf;
        self.slot = slot;
        self.blocks = vec![[0.0; 144]; rows.len()];
        self.pose_cross = if pose {
            vec![[0.0; 72]; nf]
        } else {
            Vec::new()
        };
        self.grad = vec![0.0; n];
        self.values = vec![0.0; row_idx.len()];
        self.col_start = col_start;
        self.rows = rows;
        self.col_ptr = col_ptr;
        self.row_idx = row_idx;
        self.diag_pos = diag_pos;
        // An empty system still counts as prepared.
        self.symbolic = symbolic.or_else(|| {
            let a = SymbolicSparseColMatRef::new_checked(0, 0, &[0usize][..], None, &[][..]);
            factorize_symbolic_cholesky(
                a,
                Side::Upper,
                SymmetricOrdering::Identity,
                CholeskySymbolicParams::default(),
            )
            .ok()
        });
        self.key = key;
        Ok(())
    }

    /// The upper blocks of block column `bj`: (block index, row block), ascending rows.
    pub fn column(&self, bj: u32) -> impl Iterator<Item = (usize, u32)> + '_ {
        let (c0, c1) = (self.col_start[bj as usize], self.col_start[bj as usize + 1]);
        (c0..c1).map(move |i| (i, self.rows[i]))
    }

    /// Index of upper block (bi, bj), bi <= bj.
    #[inline]
    pub fn find(&self, bi: u32, bj: u32) -> usize {
        let list = &self.rows[self.col_start[bj as usize]..self.col_start[bj as usize + 1]];
        match list.binary_search(&bi) {
            Ok(p) => self.col_start[bj as usize] + p,
            Err(_) => panic!(
                "block ({bi}, {bj}) is not in the pattern: the pattern key missed a coupling"
            ),
        }
    }

    /// Adds `scale * M (x) (ua ub^T)` to the block of solved nodes (sa, sb) (rows of sa, columns of
    /// sb), where M is symmetric 3x3 and u are 4-vectors; the transpose goes to the upper block.
    #[inline]
    pub fn add_kron(
        &mut self,
        sa: u32,
        sb: u32,
        m: &[[f64; 3]; 3],
        ua: &[f64; 4],
        ub: &[f64; 4],
        scale: f64,
    ) {
        let (bi, bj, ur, uc) = if sa <= sb {
            (sa, sb, ua, ub)
        } else {
            (sb, sa, ub, ua)
        };
        let idx = self.find(bi, bj);
        let blk = &mut self.blocks[idx];
        for s in 0..3 {
            for e in 0..4 {
                let col = (s * 4 + e) * 12;
                let ce = scale * uc[e];
                for mm in 0..3 {
                    let f = m[mm][s] * ce;
                    if f == 0.0 {
                        continue;
                    }
                    let base = col + mm * 4;
                    for c in 0..4 {
                        blk[base + c] += f * ur[c];
                    }
                }
            }
        }
    }

    /// Adds `scale * I (x) (ua ub^T)` (no 3x3 mixing), the shape of the regularisation term.
    #[inline]
    pub fn add_kron_identity(
        &mut self,
        sa: u32,
        sb: u32,
        ua: &[f64; 4],
        ub: &[f64; 4],
        scale: f64,
    ) {
        const I3: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        self.add_kron(sa, sb, &I3, ua, ub, scale);
    }

    /// Adds a dense symmetric 12x12 (row-major or column-major, it is symmetric) to a diagonal block.
    #[inline]
    pub fn add_diag(&mut self, s: u32, h: &[f64; 144]) {
        let idx = self.find(s, s);
        for (a, b) in self.blocks[idx].iter_mut().zip(h) {
            *a += b;
        }
    }

    /// The assembled system as a dense symmetric matrix (row-major n x n), for tests and
    /// diagnostics on small problems.
    pub fn to_dense(&self) -> Vec<f64> {
        let n = self.dim();
        let mut h = vec![0.0; n * n];
        let mut put = |r: usize, c: usize, v: f64| {
            h[r * n + c] = v;
            h[c * n + r] = v;
        };
        for bj in 0..self.nb {
            for idx in self.col_start[bj]..self.col_start[bj + 1] {
                let bi = self.rows[idx] as usize;
                for cc in 0..12 {
                    for r in 0..12 {
                        if bi == bj && r > cc {
                            continue;
                        }
                        put(12 * bi + r, 12 * bj + cc, self.blocks[idx][cc * 12 + r]);
                    }
                }
            }
        }
        if self.key.pose {
            let off = 12 * self.nb;
            for pc in 0..6 {
                for (bi, cross) in self.pose_cross.iter().enumerate() {
                    for r in 0..12 {
                        put(12 * bi + r, off + pc, cross[pc * 12 + r]);
                    }
                }
                for r in 0..=pc {
                    put(off + r, off + pc, self.pose_block[pc * 6 + r]);
                }
            }
        }
        h
    }

    /// Solves (H + lambda (diag(H) + ridge)) dx = -g into `dx`. Returns false when the matrix is not
    /// positive definite.
    pub fn solve(&mut self, lambda: f64, ridge: f64, dx: &mut Vec<f64>) -> Result<bool, String> {
        let n = self.dim();
        dx.clear();
        dx.resize(n, 0.0);
        if n == 0 {
            return Ok(true);
        }
        // Copy blocks into the scalar CSC values (same order as the pattern built above).
        let mut k = 0;
        let nf = self.nb;
        for bj in 0..nf {
            let (c0, c1) = (self.col_start[bj], self.col_start[bj + 1]);
            for cc in 0..12 {
                for bidx in c0..c1 - 1 {
                    self.values[k..k + 12]
                        .copy_from_slice(&self.blocks[bidx][cc * 12..cc * 12 + 12]);
                    k += 12;
                }
                let d = &self.blocks[c1 - 1];
                self.values[k..k + cc + 1].copy_from_slice(&d[cc * 12..cc * 12 + cc + 1]);
                k += cc + 1;
            }
        }
        if self.key.pose {
            for pc in 0..6 {
                for cross in &self.pose_cross {
                    self.values[k..k + 12].copy_from_slice(&cross[pc * 12..pc * 12 + 12]);
                    k += 12;
                }
                self.values[k..k + pc + 1]
                    .copy_from_slice(&self.pose_block[pc * 6..pc * 6 + pc + 1]);
                k += pc + 1;
            }
        }
        debug_assert_eq!(k, self.values.len());
        for &p in &self.diag_pos {
            let d = self.values[p];
            self.values[p] = d + lambda * (d.abs() + ridge) + 1e-12 * ridge;
        }
        let symbolic = self
            .symbolic
            .as_ref()
            .ok_or("the system was not prepared")?;
        let a = SparseColMatRef::new(
            SymbolicSparseColMatRef::new_checked(n, n, &self.col_ptr, None, &self.row_idx),
            &self.values,
        );
        let stack = MemStack::new(&mut self.scratch);
        let llt = match symbolic.factorize_numeric_llt::<f64>(
            &mut self.l_values,
            a,
            Side::Upper,
            Default::default(),
            Par::Seq,
            stack,
            Default::default(),
        ) {
            Ok(l) => l,
            Err(_) => return Ok(false),
        };
        for (x, g) in dx.iter_mut().zip(&self.grad) {
            *x = -g;
        }
        let rhs = faer::MatMut::from_column_major_slice_mut(dx.as_mut_slice(), n, 1);
        llt.solve_in_place_with_conj(
            faer::Conj::No,
            rhs,
            Par::Seq,
            MemStack::new(&mut self.scratch),
        );
        Ok(dx.iter().all(|x| x.is_finite()))
    }
}
