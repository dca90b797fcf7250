//! Constructed stereo pairs with known disparities, for tests and benchmarks.

/// The right view of a scene whose left pixel (x, y) is seen by the right camera at
/// x - disp(x, y): `fill` (the right image where no left pixel lands, `w * h` bytes) with every
/// left pixel painted at its place, far to near so the nearer surface wins.
pub fn right_view(
    left: &[u8],
    w: usize,
    h: usize,
    disp: impl Fn(usize, usize) -> usize,
    fill: Vec<u8>,
) -> Vec<u8> {
    assert!(left.len() == w * h && fill.len() == w * h, "a {w}x{h} pair");
    let mut right = fill;
    let mut order: Vec<(usize, usize)> = (0..h).flat_map(|y| (0..w).map(move |x| (x, y))).collect();
    order.sort_by_key(|&(x, y)| disp(x, y));
    for (x, y) in order {
        let d = disp(x, y);
        if x >= d {
            right[y * w + x - d] = left[y * w + x];
        }
    }
    right
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_nearer_surface_wins_and_uncovered_pixels_keep_the_fill() {
        // Row 0..4 of a 6-wide image; pixel 3 is near (disparity 2), the rest far (1).
        let left = [10u8, 11, 12, 13, 14, 15];
        let right = super::right_view(&left, 6, 1, |x, _| if x == 3 { 2 } else { 1 }, vec![0; 6]);
        // x - d: 1->0, 2->1, 3->1 (near, wins over 2), 4->3, 5->4; nothing lands on 2 or 5.
        assert_eq!(right, vec![11, 13, 0, 14, 15, 0]);
    }
}
