//! Block-sparse normal equations J^T W J dx = -J^T W r with 12x12 blocks (one per node's [A|t]) and
//! an optional 6-wide pose block, assembled straight into block storage, reduced, and factorised by
//! faer's sparse Cholesky.
//!
//! **Reduction** (`schur`). A node that no data term touches (no model point, field sample or correspondence
//! is bound to it) has its 9 affine unknowns A coupled only to its own translation and to the
//! translations of the nodes its regularisation edges point to: E_rot involves A alone, and E_reg
//! of edge (j, k) is `A_j (g_k - g_j) + g_j + t_j - g_k - t_k`. Those A blocks are eliminated first,
//! node by node, by a dense 9x9 Cholesky and a Schur complement onto the translations of
//! `{j} + out(j)`; the sparse factorisation then sees 3 unknowns for such a node instead of 12
//! (12 for a node with data), and its A is recovered by back-substitution. This is exact (the same
//! solution as factorising the whole system, to rounding): it is the elimination order "A of
//! data-free nodes first", which a block ordering over 12-wide nodes cannot express. In a map
//! that grows while the camera sees a bounded region most nodes are data-free.
//!
//! The fill-reducing ordering is computed on the reduced block graph (nodes, not scalars) with
//! faer's AMD, nodes are renumbered in that order, and the pose block goes last (an arrowhead, no
//! fill). The symbolic factorisation is reused for as long as the set of solved nodes, the
//! eliminated nodes and the block pattern stay the same (across iterations, and across frames on a
//! static graph).
//!
//! **Symbolic factorisation from the blocks.** The reduced system's diagonal blocks are dense and
//! its couplings whole blocks, so its elimination tree and column counts follow from the block
//! pattern (a few hundred blocks) instead of the scalar one (tens of thousands of entries, where
//! faer's analysis took about half of a new pattern's layout): [`block_etree`] computes them, and
//! faer's supernodal analysis takes them. The numeric factorisation reads the lower triangle,
//! copied into a layout made once per pattern (faer would transpose the upper one at every
//! factorisation). A new pattern's layout (what assembly writes) and its factor structures (the
//! elimination plan, the scalar layouts, the supernodal analysis: a [`FactorJob`]) are built
//! apart, so that the solver builds the second beside the first assembly.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::supernodal::{
    factorize_supernodal_numeric_llt, SupernodalLltRef,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::Par;

use crate::schur::{sym12, Layout, KEEP_FULL, KEEP_T};

mod etree;
mod factor;
mod lower;
pub(crate) use etree::block_etree;
use factor::upper_pattern;
pub(crate) use factor::{Factor, FactorJob};

/// The unknowns of a slot the reduced system keeps, in its 12-layout: the translation of an
/// eliminated slot, all twelve (affine first) of one with data.
/// Systems with at most this many node blocks a side look their blocks up in a dense table
/// (4 MB at most) instead of searching the column ([`BlockSystem::find`]).
const DENSE_LOOKUP_MAX: usize = 1024;

fn kept(eliminated: bool) -> &'static [usize] {
    if eliminated {
        &KEEP_T
    } else {
        &KEEP_FULL
    }
}

/// Block pattern key: solved nodes, coupled node pairs (node ids, j < k), pose block or not.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct PatternKey {
    /// Solved node ids, ascending.
    pub free: Vec<u32>,
    /// Coupled pairs (j < k), sorted, unique.
    pub pairs: Vec<(u32, u32)>,
    /// Whether the pose is among the unknowns.
    pub pose: bool,
    /// Solved nodes whose affine part is eliminated before the sparse factorisation (no data term
    /// binds them), ascending.
    pub eliminated: Vec<u32>,
    /// Directed couplings (j, k), j eliminated, k solved, j != k: E_reg edges whose A_j term
    /// reaches t_k. Sorted, unique. Each (j, k) must also be in `pairs`.
    pub links: Vec<(u32, u32)>,
}

impl PatternKey {
    /// Whether a system laid out for `self` holds every block `other` asks for: the same
    /// unknowns and eliminations, and `other`'s coupled pairs among `self`'s. The blocks `other`
    /// does not couple are then assembled as zeros, and the symbolic factorisation serves.
    pub fn covers(&self, other: &PatternKey) -> bool {
        if self.free != other.free
            || self.pose != other.pose
            || self.eliminated != other.eliminated
            || self.links != other.links
        {
            return false;
        }
        // Both sorted: a merge.
        let mut mine = self.pairs.iter();
        other.pairs.iter().all(|p| mine.any(|q| q == p))
    }

    /// The pattern to build for `other` after `self`: with the same unknowns, the union of
    /// their coupled pairs (the visible set moves a little from frame to frame and couples the
    /// same nodes now and then: the union soon covers the frames to come, and each symbolic
    /// factorisation serves many frames); otherwise `other` itself.
    pub fn widened(&self, other: &PatternKey) -> PatternKey {
        if self.free != other.free
            || self.pose != other.pose
            || self.eliminated != other.eliminated
            || self.links != other.links
        {
            return other.clone();
        }
        let mut pairs = Vec::with_capacity(self.pairs.len().max(other.pairs.len()));
        let (mut a, mut b) = (self.pairs.iter().peekable(), other.pairs.iter().peekable());
        loop {
            let next = match (a.peek(), b.peek()) {
                (Some(&&x), Some(&&y)) if x == y => {
                    a.next();
                    b.next();
                    x
                }
                (Some(&&x), Some(&&y)) if x < y => {
                    a.next();
                    x
                }
                (_, Some(&&y)) => {
                    b.next();
                    y
                }
                (Some(&&x), None) => {
                    a.next();
                    x
                }
                (None, None) => break,
            };
            pairs.push(next);
        }
        PatternKey {
            pairs,
            ..other.clone()
        }
    }
}

/// The assembled system and its factorisation workspace.
pub struct BlockSystem {
    key: PatternKey,
    /// Whether the layout and its factor's structures are those of `key` (cleared while a new
    /// layout is built, until its [`FactorJob`] is installed).
    laid_out: bool,
    /// Node id -> block index (u32::MAX when the node is held fixed).
    pub slot: Vec<u32>,
    nb: usize,
    col_start: Vec<usize>,
    rows: Vec<u32>,
    /// Index of upper block (bi, bj) at `bi * nb + bj` (u32::MAX where none), when the system
    /// has at most [`DENSE_LOOKUP_MAX`] blocks a side; else empty and [`Self::find`] searches.
    lookup: Vec<u32>,
    /// Upper blocks, column-major 12x12.
    pub blocks: Vec<[f64; 144]>,
    /// Node-pose coupling, per block row, column-major 12x6.
    pub pose_cross: Vec<[f64; 72]>,
    /// Pose-pose block, column-major 6x6.
    pub pose_block: [f64; 36],
    /// Gradient J^T W r, block order (12 per block, then 6 for the pose).
    pub grad: Vec<f64>,
    /// Per slot: whether its affine part is eliminated.
    elim_slot: Vec<bool>,
    /// Per slot: offset of its kept unknowns in the reduced system (and the total at the end).
    koff: Vec<usize>,
    /// The factorisation's structures of this layout (empty while a [`FactorJob`] holds them).
    factor: Factor,
    /// How many symbolic factorisations were computed (the reuse is tested through this).
    pub symbolic_builds: usize,
    /// Whether `l_values` and the elimination hold a numeric factorisation of the current
    /// pattern (cleared when the pattern changes or a factorisation fails).
    factored: bool,
}

impl Default for BlockSystem {
    fn default() -> Self {
        BlockSystem {
            key: PatternKey::default(),
            laid_out: false,
            slot: Vec::new(),
            nb: 0,
            col_start: vec![0],
            rows: Vec::new(),
            lookup: Vec::new(),
            blocks: Vec::new(),
            pose_cross: Vec::new(),
            pose_block: [0.0; 36],
            grad: Vec::new(),
            elim_slot: Vec::new(),
            koff: vec![0],
            factor: Factor::default(),
            symbolic_builds: 0,
            factored: false,
        }
    }
}

impl BlockSystem {
    /// Number of scalar unknowns.
    pub fn dim(&self) -> usize {
        12 * self.nb + if self.key.pose { 6 } else { 0 }
    }

    /// Number of unknowns the sparse factorisation sees (after the data-free nodes' affine parts
    /// are eliminated).
    pub fn factor_dim(&self) -> usize {
        self.factor.rhs.len()
    }

    /// Number of solved node blocks.
    pub fn blocks_solved(&self) -> usize {
        self.nb
    }

    /// Sets the pattern and zeroes the system. The pattern laid out before (and its symbolic
    /// factorisation) serves while it covers `key` ([`PatternKey::covers`]); otherwise a new one is
    /// built, for `key` widened by the pairs before ([`PatternKey::widened`]).
    pub fn prepare(&mut self, n_nodes: usize, key: &PatternKey) -> Result<(), String> {
        if let Some(job) = self.prepare_deferred(n_nodes, key)? {
            self.install(job.build())?;
        }
        Ok(())
    }

    /// [`Self::prepare`] whose new layout's factor structures, if it lays one out, are left to
    /// the caller: the system can be assembled at once, and solved once the job's
    /// [`FactorJob::build`] is handed to [`Self::install`].
    pub(crate) fn prepare_deferred(
        &mut self,
        n_nodes: usize,
        key: &PatternKey,
    ) -> Result<Option<FactorJob>, String> {
        let job = if !self.laid_out || !self.key.covers(key) || self.slot.len() != n_nodes {
            self.factored = false;
            let key = self.key.widened(key);
            Some(self.lay_out(n_nodes, key)?)
        } else {
            None
        };
        self.blocks.iter_mut().for_each(|b| b.fill(0.0));
        self.pose_cross.iter_mut().for_each(|b| b.fill(0.0));
        self.pose_block.fill(0.0);
        self.grad.fill(0.0);
        Ok(job)
    }

    /// Takes the factor structures a [`FactorJob`] of the current layout built; a failure leaves
    /// the system unprepared (the next [`Self::prepare`] lays it out again).
    pub(crate) fn install(&mut self, built: Result<Factor, String>) -> Result<(), String> {
        self.factor = built?;
        self.symbolic_builds += 1;
        self.laid_out = true;
        Ok(())
    }

    /// Lays out the pattern of `key` (its ordering, its blocks and their lookup), and returns its
    /// factor structures' job.
    fn lay_out(&mut self, n_nodes: usize, key: PatternKey) -> Result<FactorJob, String> {
        // The old pattern's factorisation no longer holds once its buffers are taken below: a
        // failure on the way leaves the system unprepared (`solve` then says so).
        self.laid_out = false;
        self.factor.symbolic = None;
        let nf = key.free.len();
        let mut local = vec![u32::MAX; n_nodes];
        for (i, &j) in key.free.iter().enumerate() {
            local[j as usize] = i as u32;
        }
        let loc = |node: u32| -> Result<usize, String> {
            match local.get(node as usize) {
                Some(&l) if l != u32::MAX => Ok(l as usize),
                _ => Err(format!(
                    "node {node} of the pattern is not among the solved nodes"
                )),
            }
        };
        let mut elim_local = vec![false; nf];
        for &j in &key.eliminated {
            elim_local[loc(j)?] = true;
        }
        // Each eliminated node's reach: itself, then the nodes its A couples to (local ids).
        let mut reach: Vec<Vec<usize>> = vec![Vec::new(); nf];
        for &(j, k) in &key.links {
            let (lj, lk) = (loc(j)?, loc(k)?);
            if !elim_local[lj] || lj == lk {
                return Err(format!(
                    "link ({j}, {k}) does not start at an eliminated node"
                ));
            }
            reach[lj].push(lk);
        }
        // Reduced block graph (upper with diagonal) in local numbering: the original pairs and,
        // per eliminated node, the clique of its reach (the Schur complement's fill).
        let mut adj: Vec<Vec<usize>> = (0..nf).map(|i| vec![i]).collect();
        let mut link = |a: usize, b: usize| {
            if a != b {
                adj[a.max(b)].push(a.min(b));
            }
        };
        for &(a, b) in &key.pairs {
            let (la, lb) = (local[a as usize], local[b as usize]);
            if la == u32::MAX || lb == u32::MAX {
                continue;
            }
            link(la as usize, lb as usize);
        }
        for (lj, r) in reach.iter().enumerate() {
            for (x, &a) in r.iter().enumerate() {
                link(lj, a);
                for &b in &r[x + 1..] {
                    link(a, b);
                }
            }
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
        let elim_slot: Vec<bool> = perm.iter().map(|&l| elim_local[l]).collect();
        let mut koff = vec![0usize; nf + 1];
        for s in 0..nf {
            koff[s + 1] = koff[s] + if elim_slot[s] { 3 } else { 12 };
        }
        // Original upper block pattern (what assembly writes) in slot numbering, per column.
        let slot_pairs: Vec<(u32, u32)> = key
            .pairs
            .iter()
            .filter_map(|&(a, b)| {
                let (sa, sb) = (slot[a as usize], slot[b as usize]);
                (sa != u32::MAX && sb != u32::MAX).then_some((sa, sb))
            })
            .collect();
        let (col_start, rows) = upper_pattern(nf, slot_pairs.iter().copied());
        let pose = key.pose;
        self.nb = nf;
        self.slot = slot;
        // The buffers keep their allocations (and stale values) from pattern to pattern:
        // `prepare` zeroes the blocks, the pose parts and the gradient before each assembly.
        self.blocks.resize(rows.len(), [0.0; 144]);
        self.pose_cross.resize(if pose { nf } else { 0 }, [0.0; 72]);
        self.grad.resize(12 * nf + if pose { 6 } else { 0 }, 0.0);
        self.lookup.clear();
        if nf <= DENSE_LOOKUP_MAX {
            self.lookup.resize(nf * nf, u32::MAX);
            for bj in 0..nf {
                for (p, &bi) in rows
                    .iter()
                    .enumerate()
                    .take(col_start[bj + 1])
                    .skip(col_start[bj])
                {
                    self.lookup[bi as usize * nf + bj] = p as u32;
                }
            }
        }
        self.elim_slot.clone_from(&elim_slot);
        self.koff.clone_from(&koff);
        self.col_start.clone_from(&col_start);
        self.rows.clone_from(&rows);
        self.key = key;
        Ok(FactorJob {
            factor: std::mem::take(&mut self.factor),
            pose,
            reach,
            perm,
            perm_inv,
            elim_slot,
            koff,
            slot_pairs,
            col_start,
            rows,
        })
    }

    /// The upper blocks of block column `bj`: (block index, row block), ascending rows.
    pub fn column(&self, bj: u32) -> impl Iterator<Item = (usize, u32)> + '_ {
        let (c0, c1) = (self.col_start[bj as usize], self.col_start[bj as usize + 1]);
        (c0..c1).map(move |i| (i, self.rows[i]))
    }

    /// Index of upper block (bi, bj), bi <= bj.
    #[inline]
    pub fn find(&self, bi: u32, bj: u32) -> usize {
        if !self.lookup.is_empty() {
            let p = self.lookup[bi as usize * self.nb + bj as usize];
            if p != u32::MAX {
                return p as usize;
            }
        }
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
        self.factored = false;
        // Laid out without its factor structures installed (or they failed): the scalar
        // layouts below are not this layout's.
        if !self.laid_out {
            return Err("the system was not prepared".into());
        }
        let damp = |d: f64| d + lambda * (d.abs() + ridge) + 1e-12 * ridge;
        let nf = self.nb;
        let nk = self.koff[nf];
        // The kept parts of the assembled blocks, into the reduced CSC values.
        self.factor.values.fill(0.0);
        for bj in 0..nf {
            let kj = kept(self.elim_slot[bj]);
            let c0 = self.koff[bj];
            for idx in self.col_start[bj]..self.col_start[bj + 1] {
                let bi = self.rows[idx] as usize;
                let ki = kept(self.elim_slot[bi]);
                let blk = &self.blocks[idx];
                let ro = self.factor.blk_rowoff[idx] as usize;
                for (kc, &oc) in kj.iter().enumerate() {
                    let base = self.factor.col_ptr[c0 + kc] + ro;
                    if bi == bj {
                        for (kr, &or) in ki[..=kc].iter().enumerate() {
                            self.factor.values[base + kr] = blk[sym12(or, oc)];
                        }
                    } else {
                        for (kr, &or) in ki.iter().enumerate() {
                            self.factor.values[base + kr] = blk[oc * 12 + or];
                        }
                    }
                }
            }
        }
        if self.key.pose {
            for pc in 0..6 {
                let base = self.factor.col_ptr[nk + pc];
                for (s, cross) in self.pose_cross.iter().enumerate() {
                    for (kr, &or) in kept(self.elim_slot[s]).iter().enumerate() {
                        self.factor.values[base + self.koff[s] + kr] = cross[pc * 12 + or];
                    }
                }
                for r in 0..=pc {
                    self.factor.values[base + nk + r] = self.pose_block[pc * 6 + r];
                }
            }
        }
        self.rhs_from_grad();
        for &p in &self.factor.diag_pos {
            self.factor.values[p] = damp(self.factor.values[p]);
        }
        // Eliminate the affine parts of the data-free nodes.
        let layout = Layout {
            koff: &self.koff,
            elim_slot: &self.elim_slot,
        };
        if !self.factor.elimination.eliminate(
            &self.blocks,
            &self.grad,
            &layout,
            &self.factor.col_ptr,
            &mut self.factor.values,
            &mut self.factor.rhs,
            damp,
        ) {
            return Ok(false);
        }
        let symbolic = self
            .factor
            .symbolic
            .as_ref()
            .ok_or("the system was not prepared")?;
        let nr = self.factor.rhs.len();
        for (l, &u) in self.factor.lvalues.iter_mut().zip(&self.factor.from_upper) {
            *l = self.factor.values[u as usize];
        }
        let a = SparseColMatRef::new(
            SymbolicSparseColMatRef::new_checked(
                nr,
                nr,
                &self.factor.lcol_ptr,
                None,
                &self.factor.lrow_idx,
            ),
            &self.factor.lvalues,
        );
        let stack = MemStack::new(&mut self.factor.scratch);
        if factorize_supernodal_numeric_llt::<usize, f64>(
            &mut self.factor.l_values,
            a,
            Default::default(),
            symbolic,
            Par::Seq,
            stack,
            Default::default(),
        )
        .is_err()
        {
            return Ok(false);
        }
        self.factored = true;
        self.solve_factored(dx)
    }

    /// Whether [`Self::resolve`] can run: the last [`Self::solve`] factorised the current pattern.
    pub fn is_factored(&self) -> bool {
        self.factored
    }

    /// Solves with the matrix of the last successful [`Self::solve`] (its damping included) and
    /// the gradient now in `grad`: the step of a Gauss-Newton iteration whose Hessian is kept from
    /// the one before (no factorisation; the assembled blocks are not read). False when there is
    /// no factorisation of the current pattern, or the step is not finite.
    pub fn resolve(&mut self, dx: &mut Vec<f64>) -> Result<bool, String> {
        let n = self.dim();
        dx.clear();
        dx.resize(n, 0.0);
        if n == 0 {
            return Ok(true);
        }
        if !self.factored {
            return Ok(false);
        }
        self.rhs_from_grad();
        let layout = Layout {
            koff: &self.koff,
            elim_slot: &self.elim_slot,
        };
        self.factor
            .elimination
            .reduce_rhs(&self.grad, &layout, &mut self.factor.rhs);
        self.solve_factored(dx)
    }

    /// Solves the reduced system in `rhs` with the factor in `l_values`, then expands the
    /// solution into `dx` (see [`Self::expand`]).
    fn solve_factored(&mut self, dx: &mut [f64]) -> Result<bool, String> {
        let symbolic = self
            .factor
            .symbolic
            .as_ref()
            .ok_or("the system was not prepared")?;
        let nr = self.factor.rhs.len();
        let llt = SupernodalLltRef::<usize, f64>::new(symbolic, &self.factor.l_values);
        let rhs = faer::MatMut::from_column_major_slice_mut(self.factor.rhs.as_mut_slice(), nr, 1);
        llt.solve_in_place_with_conj(
            faer::Conj::No,
            rhs,
            Par::Seq,
            MemStack::new(&mut self.factor.scratch),
        );
        Ok(self.expand(dx))
    }

    /// The reduced right-hand side before elimination: `-grad` at the kept unknowns.
    fn rhs_from_grad(&mut self) {
        let nf = self.nb;
        for bj in 0..nf {
            let kj = kept(self.elim_slot[bj]);
            let c0 = self.koff[bj];
            for (kr, &or) in kj.iter().enumerate() {
                self.factor.rhs[c0 + kr] = -self.grad[12 * bj + or];
            }
        }
        if self.key.pose {
            let nk = self.koff[nf];
            for pc in 0..6 {
                self.factor.rhs[nk + pc] = -self.grad[12 * nf + pc];
            }
        }
    }

    /// The reduced solution in `rhs` back to the 12-layout `dx`: kept unknowns directly,
    /// eliminated ones by back-substitution. False when a step is not finite.
    fn expand(&self, dx: &mut [f64]) -> bool {
        let nf = self.nb;
        let nk = self.koff[nf];
        // Back to the 12-layout: kept unknowns directly, eliminated ones by back-substitution.
        for s in 0..nf {
            for (kr, &or) in kept(self.elim_slot[s]).iter().enumerate() {
                dx[12 * s + or] = self.factor.rhs[self.koff[s] + kr];
            }
        }
        if self.key.pose {
            dx[12 * nf..].copy_from_slice(&self.factor.rhs[nk..]);
        }
        let layout = Layout {
            koff: &self.koff,
            elim_slot: &self.elim_slot,
        };
        self.factor
            .elimination
            .back_substitute(&layout, &self.factor.rhs, dx);
        dx.iter().all(|x| x.is_finite())
    }
}

#[cfg(test)]
mod tests;
