//! Elimination of the affine unknowns of data-free nodes before the sparse factorisation (see
//! [`crate::system`]): per such node j, a dense 9x9 Cholesky of its damped affine block H_AA and
//! a Schur complement onto the translations it couples to (its own and those of the ends of its
//! E_reg edges), then, after the sparse solve, its A by back-substitution.
//!
//! With L L^T = H_AA, W = L^-1 C (C: the affine rows against those translations) and
//! w = L^-1 g_A, the reduced system gets `S -= W^T W` and right-hand side `-g_K + W^T w`, and
//! `dA = L^-T (-w - W dK)`.

/// Kept (factorised) unknowns of a node with data, in its 12-layout `[A row 0 | t0, ...]`:
/// the 9 affine entries, then the translation.
pub(crate) const KEEP_FULL: [usize; 12] = [0, 1, 2, 4, 5, 6, 8, 9, 10, 3, 7, 11];
/// Kept unknowns of an eliminated node: its translation.
pub(crate) const KEEP_T: [usize; 3] = [3, 7, 11];
/// The affine entries of a node in its 12-layout.
pub(crate) const AFF: [usize; 9] = [0, 1, 2, 4, 5, 6, 8, 9, 10];

/// Upper-triangle index of entry (r, c) of a symmetric 12x12 stored column-major.
#[inline(always)]
pub(crate) fn sym12(r: usize, c: usize) -> usize {
    if r <= c {
        c * 12 + r
    } else {
        r * 12 + c
    }
}

/// Where each slot's kept unknowns sit in the reduced system.
pub(crate) struct Layout<'a> {
    /// Per slot: offset of its kept unknowns.
    pub koff: &'a [usize],
    /// Per slot: whether its affine part is eliminated.
    pub elim_slot: &'a [bool],
}

impl Layout<'_> {
    /// Offset of the slot's translation in the reduced system (its kept unknowns end with it).
    #[inline]
    fn t_offset(&self, s: u32) -> usize {
        self.koff[s as usize] + if self.elim_slot[s as usize] { 0 } else { 9 }
    }
}

/// The plan (fixed per pattern) and workspace of the elimination.
#[derive(Default)]
pub(crate) struct Elimination {
    /// Eliminated slots; per eliminated slot e, `t_start[e]..t_start[e + 1]` indexes `t_slots`
    /// (its own slot first, then the slots its A reaches) and `t_blk` (the assembled block
    /// holding that coupling, and whether it is stored transposed, i.e. the eliminated slot is
    /// its column).
    elim: Vec<u32>,
    t_start: Vec<usize>,
    t_slots: Vec<u32>,
    t_blk: Vec<(u32, bool)>,
    /// Per eliminated slot e, from `pair_start[e]`: |T|^2 row offsets of reduced block
    /// (T[a], T[b]) in its column (meaningful where slot T[a] <= slot T[b]).
    pair_start: Vec<usize>,
    pair_rowoff: Vec<u32>,
    /// Per eliminated slot: L (row-major lower), W (9 x 3|T|, row-major, from `w_start`), w.
    chol: Vec<[f64; 81]>,
    w_start: Vec<usize>,
    w_mat: Vec<f64>,
    w_vec: Vec<[f64; 9]>,
}

impl Elimination {
    /// The plan for the eliminated slots (`elim_slot`); `reach[perm[s]]` lists, in local ids,
    /// the nodes slot s's A couples to (`perm_inv` maps them to slots); `block(a, b)` is the
    /// assembled block of slots (a, b) and `rowoff(a, b)` the row offset of reduced block (a, b)
    /// in its column.
    pub(crate) fn plan(
        elim_slot: &[bool],
        reach: &[Vec<usize>],
        perm: &[usize],
        perm_inv: &[usize],
        block: impl Fn(u32, u32) -> Result<u32, String>,
        rowoff: impl Fn(u32, u32) -> Result<u32, String>,
    ) -> Result<Self, String> {
        let mut p = Elimination {
            t_start: vec![0],
            ..Default::default()
        };
        let mut w_len = 0;
        for (s, _) in elim_slot.iter().enumerate().filter(|(_, &e)| e) {
            let s = s as u32;
            p.elim.push(s);
            let first = p.t_slots.len();
            p.t_slots.push(s);
            p.t_blk.push((block(s, s)?, false));
            for &a in &reach[perm[s as usize]] {
                let sa = perm_inv[a] as u32;
                p.t_slots.push(sa);
                p.t_blk.push((block(s, sa)?, sa < s));
            }
            p.t_start.push(p.t_slots.len());
            let t = &p.t_slots[first..];
            p.pair_start.push(p.pair_rowoff.len());
            for &a in t {
                for &b in t {
                    p.pair_rowoff.push(rowoff(a, b)?);
                }
            }
            p.w_start.push(w_len);
            w_len += 27 * t.len();
        }
        p.chol = vec![[0.0; 81]; p.elim.len()];
        p.w_vec = vec![[0.0; 9]; p.elim.len()];
        p.w_mat = vec![0.0; w_len];
        Ok(p)
    }

    /// Eliminates every planned node: subtracts W^T W from the reduced CSC `values` (columns
    /// `col_ptr`) and adds W^T w to `rhs`. `damp` maps a diagonal entry of H to its damped value.
    /// False when an affine block is not positive definite.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn eliminate(
        &mut self,
        blocks: &[[f64; 144]],
        grad: &[f64],
        layout: &Layout,
        col_ptr: &[usize],
        values: &mut [f64],
        rhs: &mut [f64],
        damp: impl Fn(f64) -> f64,
    ) -> bool {
        for e in 0..self.elim.len() {
            let (t0, t1) = (self.t_start[e], self.t_start[e + 1]);
            let nt = t1 - t0;
            let diag = &blocks[self.t_blk[t0].0 as usize];
            let l = &mut self.chol[e];
            for r in 0..9 {
                for c in 0..=r {
                    let v = diag[sym12(AFF[r], AFF[c])];
                    l[r * 9 + c] = if r == c { damp(v) } else { v };
                }
            }
            if !cholesky9(l) {
                return false;
            }
            let width = 3 * nt;
            let wm = &mut self.w_mat[self.w_start[e]..self.w_start[e] + 9 * width];
            for (q, &(idx, transposed)) in self.t_blk[t0..t1].iter().enumerate() {
                let blk = &blocks[idx as usize];
                for r in 0..9 {
                    for (c, &tc) in KEEP_T.iter().enumerate() {
                        wm[r * width + 3 * q + c] = if q == 0 {
                            blk[sym12(AFF[r], tc)]
                        } else if transposed {
                            blk[AFF[r] * 12 + tc]
                        } else {
                            blk[tc * 12 + AFF[r]]
                        };
                    }
                }
            }
            forward9(l, wm, width);
            let t = &self.t_slots[t0..t1];
            let pr = &self.pair_rowoff[self.pair_start[e]..self.pair_start[e] + nt * nt];
            for (qb, &sb) in t.iter().enumerate() {
                let cb = layout.t_offset(sb);
                for (qa, &sa) in t.iter().enumerate() {
                    if sa > sb {
                        continue;
                    }
                    let ro = pr[qa * nt + qb] as usize
                        + if layout.elim_slot[sa as usize] { 0 } else { 9 };
                    for c in 0..3 {
                        let base = col_ptr[cb + c] + ro;
                        let rmax = if sa == sb { c } else { 2 };
                        for r in 0..=rmax {
                            let mut acc = 0.0;
                            for k in 0..9 {
                                acc += wm[k * width + 3 * qa + r] * wm[k * width + 3 * qb + c];
                            }
                            values[base + r] -= acc;
                        }
                    }
                }
            }
        }
        self.reduce_rhs(grad, layout, rhs);
        true
    }

    /// The right-hand side part of the elimination, with the factors of the last
    /// [`Self::eliminate`] (which ends with it) and the gradient `grad`: `w = L^-1 g_A`,
    /// `rhs += W^T w` (the reduced `rhs` must hold `-g_K` already). [`Self::back_substitute`]
    /// then uses this `w`.
    pub(crate) fn reduce_rhs(&mut self, grad: &[f64], layout: &Layout, rhs: &mut [f64]) {
        for (e, &s) in self.elim.iter().enumerate() {
            let s = s as usize;
            let (t0, t1) = (self.t_start[e], self.t_start[e + 1]);
            let width = 3 * (t1 - t0);
            let wm = &self.w_mat[self.w_start[e]..self.w_start[e] + 9 * width];
            let wv = &mut self.w_vec[e];
            for r in 0..9 {
                wv[r] = grad[12 * s + AFF[r]];
            }
            forward9(&self.chol[e], wv, 1);
            for (qb, &sb) in self.t_slots[t0..t1].iter().enumerate() {
                let cb = layout.t_offset(sb);
                for c in 0..3 {
                    rhs[cb + c] += (0..9)
                        .map(|k| wm[k * width + 3 * qb + c] * wv[k])
                        .sum::<f64>();
                }
            }
        }
    }

    /// Writes each eliminated node's affine step `dA = L^-T (-w - W dK)` into `dx` (12-layout),
    /// from the reduced solution `sol`.
    pub(crate) fn back_substitute(&self, layout: &Layout, sol: &[f64], dx: &mut [f64]) {
        for (e, &s) in self.elim.iter().enumerate() {
            let (t0, t1) = (self.t_start[e], self.t_start[e + 1]);
            let width = 3 * (t1 - t0);
            let wm = &self.w_mat[self.w_start[e]..self.w_start[e] + 9 * width];
            let mut y = [0.0; 9];
            for (r, yr) in y.iter_mut().enumerate() {
                let mut acc = -self.w_vec[e][r];
                for (q, &sq) in self.t_slots[t0..t1].iter().enumerate() {
                    let b = layout.t_offset(sq);
                    for c in 0..3 {
                        acc -= wm[r * width + 3 * q + c] * sol[b + c];
                    }
                }
                *yr = acc;
            }
            backward9(&self.chol[e], &mut y);
            for r in 0..9 {
                dx[12 * s as usize + AFF[r]] = y[r];
            }
        }
    }
}

/// In-place Cholesky of a symmetric positive definite 9x9 (row-major, lower triangle read and
/// written). False when it is not positive definite.
fn cholesky9(a: &mut [f64; 81]) -> bool {
    for j in 0..9 {
        let mut d = a[j * 9 + j];
        for k in 0..j {
            d -= a[j * 9 + k] * a[j * 9 + k];
        }
        if d.is_nan() || d <= 0.0 || d.is_infinite() {
            return false;
        }
        let d = d.sqrt();
        a[j * 9 + j] = d;
        for i in j + 1..9 {
            let mut v = a[i * 9 + j];
            for k in 0..j {
                v -= a[i * 9 + k] * a[j * 9 + k];
            }
            a[i * 9 + j] = v / d;
        }
    }
    true
}

/// Solves L X = B in place for the 9 x `width` row-major B.
fn forward9(l: &[f64; 81], b: &mut [f64], width: usize) {
    for i in 0..9 {
        let inv = 1.0 / l[i * 9 + i];
        for k in 0..i {
            let f = l[i * 9 + k];
            if f != 0.0 {
                for c in 0..width {
                    b[i * width + c] -= f * b[k * width + c];
                }
            }
        }
        for c in 0..width {
            b[i * width + c] *= inv;
        }
    }
}

/// Solves L^T x = y in place.
fn backward9(l: &[f64; 81], y: &mut [f64; 9]) {
    for i in (0..9).rev() {
        let mut v = y[i];
        for k in i + 1..9 {
            v -= l[k * 9 + i] * y[k];
        }
        y[i] = v / l[i * 9 + i];
    }
}
