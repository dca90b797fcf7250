//! The lower triangle of the reduced system, laid out from its blocks (see [`super`], "Symbolic
//! factorisation from the blocks"): what faer's supernodal factorisation reads.

/// The reduced system's block pattern in slot order.
pub(super) struct Blocks<'a> {
    /// Unknowns of each block (12, or 3 for an eliminated node).
    pub size: &'a [usize],
    /// Offset of each block's unknowns.
    pub off: &'a [usize],
    /// Block column `bj`'s upper blocks are `rows[col_start[bj]..col_start[bj + 1]]`, ascending,
    /// the diagonal last.
    pub col_start: &'a [usize],
    pub rows: &'a [u32],
    /// Row offset of each of those blocks within its scalar column.
    pub rowoff: &'a [u32],
}

/// The lower triangle's CSC pattern, and for each of its entries the upper entry it copies.
pub(super) struct Lower {
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
    pub from_upper: Vec<u32>,
}

impl Lower {
    /// Lays out the lower triangle of the matrix whose upper triangle has column starts
    /// `upper_col_ptr` (the node blocks, then the 6 pose columns if `pose`), reusing the
    /// buffers. Lower column r of block bi holds the rest of bi's diagonal block, then each
    /// block bj > bi coupled to bi, ascending, then the pose; the writes are sequential (a
    /// transposition of the scalar pattern scatters them). Err when the two triangles do not
    /// have the same number of entries.
    pub fn lay_out(
        &mut self,
        b: &Blocks,
        upper_col_ptr: &[usize],
        pose: bool,
    ) -> Result<(), String> {
        let nf = b.size.len();
        let nk = b.off.last().map_or(0, |&o| o + b.size[nf - 1]);
        let col_ptr = upper_col_ptr;
        let nnz = col_ptr.last().copied().unwrap_or(0);
        // Per block bi: the blocks bj > bi it couples to, with the coupling's index in `rows`.
        let mut lrows: Vec<Vec<(u32, usize)>> = vec![Vec::new(); nf];
        for bj in 0..nf {
            for p in b.col_start[bj]..b.col_start[bj + 1] - 1 {
                lrows[b.rows[p] as usize].push((bj as u32, p));
            }
        }
        let (lcol_ptr, lrow_idx, from_upper) =
            (&mut self.col_ptr, &mut self.row_idx, &mut self.from_upper);
        lcol_ptr.clear();
        lrow_idx.clear();
        from_upper.clear();
        lcol_ptr.push(0);
        for bi in 0..nf {
            let (oi, si) = (b.off[bi], b.size[bi]);
            let diag_off = b.rowoff[b.col_start[bi + 1] - 1] as usize;
            for kr in 0..si {
                lrow_idx.extend(oi + kr..oi + si);
                from_upper.extend((kr..si).map(|kc| (col_ptr[oi + kc] + diag_off + kr) as u32));
                for &(bj, p) in &lrows[bi] {
                    let (oj, sj) = (b.off[bj as usize], b.size[bj as usize]);
                    let at = b.rowoff[p] as usize + kr;
                    lrow_idx.extend(oj..oj + sj);
                    from_upper.extend((0..sj).map(|kc| (col_ptr[oj + kc] + at) as u32));
                }
                if pose {
                    lrow_idx.extend(nk..nk + 6);
                    from_upper.extend((0..6).map(|pc| (col_ptr[nk + pc] + oi + kr) as u32));
                }
                lcol_ptr.push(lrow_idx.len());
            }
        }
        if pose {
            for pc in 0..6 {
                lrow_idx.extend(nk + pc..nk + 6);
                from_upper.extend((pc..6).map(|q| (col_ptr[nk + q] + nk + pc) as u32));
                lcol_ptr.push(lrow_idx.len());
            }
        }
        if lrow_idx.len() != nnz || from_upper.len() != nnz {
            return Err(format!(
                "the lower triangle has {} entries, the upper {nnz}",
                lrow_idx.len()
            ));
        }
        Ok(())
    }
}
