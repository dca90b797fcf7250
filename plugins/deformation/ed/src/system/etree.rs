//! The Cholesky factor's elimination tree and column counts from a block pattern (see
//! [`super`], "Symbolic factorisation from the blocks").

/// The elimination tree (parent of each scalar column, -1 at a root) and column counts (the
/// diagonal included) of the Cholesky factor of a symmetric matrix made of dense blocks: block
/// `b` spans `size[b]` unknowns from `off[b]` (ascending), `cols[b]` lists the blocks of its
/// upper block column (ascending, ending with `b`), and every listed coupling is a whole block,
/// the diagonal blocks dense. The factor's block structure follows block column by block
/// column: a column's blocks below the diagonal are its own and its children's, the first of
/// them is its parent, and the rest go to the parent (work and memory in proportion to the
/// factor's blocks). Within a block each column's parent is the next one, and its last
/// column's is the first of the block's parent.
pub(crate) fn block_etree(
    cols: &[&[u32]],
    size: &[usize],
    off: &[usize],
) -> (Vec<isize>, Vec<usize>) {
    let nb = cols.len();
    // below[j]: blocks below the diagonal in block column j of the factor (unsorted, with
    // repeats, until j is reached).
    let mut below: Vec<Vec<u32>> = vec![Vec::new(); nb];
    for (c, list) in cols.iter().enumerate() {
        for &r in list.iter() {
            if (r as usize) < c {
                below[r as usize].push(c as u32);
            }
        }
    }
    let mut parent = vec![usize::MAX; nb];
    let mut below_size = vec![0usize; nb];
    for j in 0..nb {
        let mut mine = std::mem::take(&mut below[j]);
        mine.sort_unstable();
        mine.dedup();
        below_size[j] = mine.iter().map(|&i| size[i as usize]).sum();
        if let Some((&first, rest)) = mine.split_first() {
            parent[j] = first as usize;
            below[first as usize].extend_from_slice(rest);
        }
    }
    let n: usize = size.iter().sum();
    let mut etree = vec![-1isize; n];
    let mut counts = vec![0usize; n];
    for b in 0..nb {
        let (o, m) = (off[b], size[b]);
        for t in 0..m {
            counts[o + t] = m - t + below_size[b];
            etree[o + t] = if t + 1 < m {
                (o + t + 1) as isize
            } else if parent[b] != usize::MAX {
                off[parent[b]] as isize
            } else {
                -1
            };
        }
    }
    (etree, counts)
}
