//! A layout's factor structures (see [`super`]): the elimination plan, the reduced system's scalar
//! layouts upper and lower, and faer's supernodal analysis, built from the layout by a
//! [`FactorJob`] apart from the assembly (the solver builds them beside the first assembly on a new
//! layout).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::simplicial::EliminationTreeRef;
use faer::sparse::linalg::cholesky::supernodal::{
    factorize_supernodal_numeric_llt_scratch, factorize_supernodal_symbolic_cholesky,
    factorize_supernodal_symbolic_cholesky_scratch, SymbolicSupernodalCholesky,
};
use faer::sparse::SymbolicSparseColMatRef;
use faer::Par;

use super::block_etree;
use super::lower::{Blocks, Lower};
use crate::schur::Elimination;

/// What the factorisation of one layout reads besides the assembled blocks: the elimination
/// plan, the reduced system's scalar layouts and faer's supernodal analysis, and the buffers of
/// the numeric factorisation.
pub(crate) struct Factor {
    /// Per original block: offset of its rows within its reduced column.
    pub(super) blk_rowoff: Vec<u32>,
    /// The elimination of the data-free nodes' affine parts.
    pub(super) elimination: Elimination,
    /// Reduced right-hand side and solution.
    pub(super) rhs: Vec<f64>,
    pub(super) col_ptr: Vec<usize>,
    pub(super) row_idx: Vec<usize>,
    pub(super) values: Vec<f64>,
    pub(super) diag_pos: Vec<usize>,
    /// The lower triangle of the reduced matrix (what the supernodal factorisation reads), and
    /// the entry of `values` each of its entries copies.
    pub(super) lcol_ptr: Vec<usize>,
    pub(super) lrow_idx: Vec<usize>,
    pub(super) lvalues: Vec<f64>,
    pub(super) from_upper: Vec<u32>,
    pub(super) symbolic: Option<SymbolicSupernodalCholesky<usize>>,
    pub(super) l_values: Vec<f64>,
    pub(super) scratch: MemBuffer,
    /// Bytes `scratch` holds (as [`faer::dyn_stack::StackReq::unaligned_bytes_required`]).
    pub(super) scratch_bytes: usize,
}

impl Default for Factor {
    fn default() -> Self {
        Factor {
            blk_rowoff: Vec::new(),
            elimination: Elimination::default(),
            rhs: Vec::new(),
            col_ptr: Vec::new(),
            row_idx: Vec::new(),
            values: Vec::new(),
            diag_pos: Vec::new(),
            lcol_ptr: Vec::new(),
            lrow_idx: Vec::new(),
            lvalues: Vec::new(),
            from_upper: Vec::new(),
            symbolic: None,
            l_values: Vec::new(),
            scratch: MemBuffer::new(faer::dyn_stack::StackReq::EMPTY),
            scratch_bytes: 0,
        }
    }
}

/// The upper block pattern of `pairs` (slots) with every diagonal block, per column: column
/// starts and rows (ascending, the diagonal last).
pub(super) fn upper_pattern(
    nf: usize,
    pairs: impl Iterator<Item = (u32, u32)>,
) -> (Vec<usize>, Vec<u32>) {
    let mut cols: Vec<Vec<u32>> = (0..nf).map(|i| vec![i as u32]).collect();
    for (sa, sb) in pairs {
        if sa != sb {
            cols[sa.max(sb) as usize].push(sa.min(sb));
        }
    }
    let mut start = vec![0usize; nf + 1];
    let mut rows = Vec::new();
    for (c, list) in cols.iter_mut().enumerate() {
        list.sort_unstable();
        list.dedup();
        rows.extend_from_slice(list);
        start[c + 1] = rows.len();
    }
    (start, rows)
}

/// A new layout's factor structures, still to build ([`Self::build`]): the elimination plan,
/// the reduced system's scalar layouts (upper and lower) and faer's supernodal analysis. They
/// need the layout but not the assembled blocks, so the solver builds them beside the first
/// assembly on the new layout and hands them to [`BlockSystem::install`].
pub(crate) struct FactorJob {
    /// The buffers of the layout before, reused.
    pub(super) factor: Factor,
    pub(super) pose: bool,
    /// Each eliminated node's reach (local ids): the nodes its A couples to.
    pub(super) reach: Vec<Vec<usize>>,
    /// The elimination order: local id of each slot, and slot of each local id.
    pub(super) perm: Vec<usize>,
    pub(super) perm_inv: Vec<usize>,
    pub(super) elim_slot: Vec<bool>,
    pub(super) koff: Vec<usize>,
    /// The coupled pairs in slots.
    pub(super) slot_pairs: Vec<(u32, u32)>,
    /// The original upper block pattern (what assembly writes).
    pub(super) col_start: Vec<usize>,
    pub(super) rows: Vec<u32>,
}

impl FactorJob {
    /// Builds the structures; the buffers of the layout before keep their allocations.
    pub(crate) fn build(self) -> Result<Factor, String> {
        let FactorJob {
            mut factor,
            pose,
            reach,
            perm,
            perm_inv,
            elim_slot,
            koff,
            slot_pairs,
            col_start,
            rows,
        } = self;
        let nf = elim_slot.len();
        let size = |s: usize| if elim_slot[s] { 3 } else { 12 };
        // Reduced pattern: the original pairs and, per eliminated node, the clique of its reach
        // (the Schur complement's fill).
        let mut clique = Vec::new();
        for (lj, r) in reach.iter().enumerate() {
            let sj = perm_inv[lj] as u32;
            for (x, &a) in r.iter().enumerate() {
                let sa = perm_inv[a] as u32;
                clique.push((sj, sa));
                for &b in &r[x + 1..] {
                    clique.push((sa, perm_inv[b] as u32));
                }
            }
        }
        let (rcol_start, rrows) =
            upper_pattern(nf, slot_pairs.iter().copied().chain(clique.iter().copied()));
        // Row offset of reduced block (bi, bj), bi <= bj, within column bj.
        let mut rowoff = vec![0u32; rrows.len()];
        for bj in 0..nf {
            let mut off = 0u32;
            for p in rcol_start[bj]..rcol_start[bj + 1] {
                rowoff[p] = off;
                off += size(rrows[p] as usize) as u32;
            }
        }
        let rowoff_of = |bi: u32, bj: u32| -> Result<u32, String> {
            let (lo, hi) = (bi.min(bj), bi.max(bj));
            let list = &rrows[rcol_start[hi as usize]..rcol_start[hi as usize + 1]];
            list.binary_search(&lo)
                .map(|p| rowoff[rcol_start[hi as usize] + p])
                .map_err(|_| format!("reduced block ({lo}, {hi}) is missing"))
        };
        let find_orig = |bi: u32, bj: u32| -> Result<u32, String> {
            let (lo, hi) = (bi.min(bj), bi.max(bj));
            let list = &rows[col_start[hi as usize]..col_start[hi as usize + 1]];
            list.binary_search(&lo)
                .map(|p| (col_start[hi as usize] + p) as u32)
                .map_err(|_| {
                    format!("an eliminated node's link ({lo}, {hi}) is not among the pairs")
                })
        };
        let mut blk_rowoff = std::mem::take(&mut factor.blk_rowoff);
        blk_rowoff.clear();
        blk_rowoff.resize(rows.len(), 0);
        for bj in 0..nf {
            for p in col_start[bj]..col_start[bj + 1] {
                blk_rowoff[p] = rowoff_of(rows[p], bj as u32)?;
            }
        }
        // Eliminated slots: their reach in slots, the blocks holding the couplings, and the
        // reduced blocks their Schur complement lands in.
        let elimination =
            Elimination::plan(&elim_slot, &reach, &perm, &perm_inv, find_orig, rowoff_of)?;
        // Scalar CSC of the reduced system, upper triangle.
        let nk = koff[nf];
        let n = nk + if pose { 6 } else { 0 };
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        let mut diag_pos = Vec::with_capacity(n);
        col_ptr.push(0);
        for bj in 0..nf {
            let list = &rrows[rcol_start[bj]..rcol_start[bj + 1]];
            for cc in 0..size(bj) {
                for &bi in &list[..list.len() - 1] {
                    let b0 = koff[bi as usize];
                    row_idx.extend(b0..b0 + size(bi as usize));
                }
                row_idx.extend(koff[bj]..=koff[bj] + cc);
                diag_pos.push(row_idx.len() - 1);
                col_ptr.push(row_idx.len());
            }
        }
        if pose {
            for pc in 0..6 {
                row_idx.extend(0..nk);
                row_idx.extend((0..=pc).map(|r| nk + r));
                diag_pos.push(row_idx.len() - 1);
                col_ptr.push(row_idx.len());
            }
        }
        // The lower triangle's layout (buffers reused from the pattern before).
        let sizes: Vec<usize> = (0..nf).map(size).collect();
        let mut lower = Lower {
            col_ptr: std::mem::take(&mut factor.lcol_ptr),
            row_idx: std::mem::take(&mut factor.lrow_idx),
            from_upper: std::mem::take(&mut factor.from_upper),
        };
        lower.lay_out(
            &Blocks {
                size: &sizes,
                off: &koff[..nf],
                col_start: &rcol_start,
                rows: &rrows,
                rowoff: &rowoff,
            },
            &col_ptr,
            pose,
        )?;
        // Elimination tree and column counts from the reduced block pattern (plus the pose
        // block, coupled to every node), then faer's supernodal structure.
        let mut bsize = sizes;
        let mut boff: Vec<usize> = koff[..nf].to_vec();
        let mut bcols: Vec<&[u32]> = (0..nf)
            .map(|bj| &rrows[rcol_start[bj]..rcol_start[bj + 1]])
            .collect();
        let all: Vec<u32> = (0..=nf as u32).collect();
        if pose {
            bsize.push(6);
            boff.push(nk);
            bcols.push(&all);
        }
        let (etree, col_counts) = block_etree(&bcols, &bsize, &boff);
        let a = SymbolicSparseColMatRef::new_checked(n, n, &col_ptr, None, &row_idx);
        // SAFETY: `block_etree` gives the elimination tree `prefactorize_symbolic_cholesky` computes
        // for this pattern (the diagonal blocks dense, each coupling a whole block; checked against
        // it in this module's tests), which is all `from_inner` asks.
        let et = unsafe { EliminationTreeRef::<usize>::from_inner(&etree) };
        let mut mem =
            MemBuffer::try_new(factorize_supernodal_symbolic_cholesky_scratch::<usize>(n))
                .map_err(|_| "out of memory for the symbolic Cholesky")?;
        let symbolic = factorize_supernodal_symbolic_cholesky(
            a,
            et,
            &col_counts,
            MemStack::new(&mut mem),
            Default::default(),
        )
        .map_err(|e| format!("symbolic Cholesky failed: {e:?}"))?;
        tracing::debug!(
            "ED symbolic: n {n}, nnz(A upper) {}, nnz(L) {}, supernodes {}",
            row_idx.len(),
            symbolic.len_val(),
            symbolic.n_supernodes()
        );
        // Written whole by each factorisation.
        factor.l_values.resize(symbolic.len_val(), 0.0);
        let req = factorize_supernodal_numeric_llt_scratch::<usize, f64>(
            &symbolic,
            Par::Seq,
            Default::default(),
        )
        .or(symbolic.solve_in_place_scratch::<f64>(1, Par::Seq));
        // Reused while large enough (a new pattern is laid out on most frames of a sweep).
        if req.unaligned_bytes_required() > factor.scratch_bytes {
            factor.scratch =
                MemBuffer::try_new(req).map_err(|_| "out of memory for the Cholesky workspace")?;
            factor.scratch_bytes = req.unaligned_bytes_required();
        }
        // The buffers keep their allocations (and stale values) from pattern to pattern:
        // `solve` zeroes the values, and the right-hand side and the lower triangle are
        // written whole.
        factor.values.resize(row_idx.len(), 0.0);
        factor.lvalues.resize(row_idx.len(), 0.0);
        factor.rhs.resize(n, 0.0);
        factor.blk_rowoff = blk_rowoff;
        factor.elimination = elimination;
        factor.col_ptr = col_ptr;
        factor.row_idx = row_idx;
        factor.diag_pos = diag_pos;
        factor.lcol_ptr = lower.col_ptr;
        factor.lrow_idx = lower.row_idx;
        factor.from_upper = lower.from_upper;
        factor.symbolic = Some(symbolic);
        Ok(factor)
    }
}
