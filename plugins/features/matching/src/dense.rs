//! Moving a match on a dense descriptor grid to the pixel that fits it best.
//!
//! A descriptor matched to the nearest point of a grid of step s lands up to s / 2 pixels from
//! where the tissue went. With descriptors at any pixel ([`DescriptorSampler`], e.g. upright
//! dense SURF), the match walks downhill on the squared descriptor distance over the pixels
//! (to the best of the 8 neighbours while that improves), then to the minimum of the quadratic
//! through the 3 x 3 distances around the pixel it stops on.

use misslam_framework::DescriptorSampler;

use crate::l2_squared;

/// Reusable buffers of [`refine_match`]: the distances already computed around the start.
#[derive(Default)]
pub struct RefineScratch {
    seen: Vec<f32>,
}

/// Where descriptor `target`, matched to pixel (x, y), fits best within `max_steps` pixels of it
/// (Chebyshev): the sub-pixel position, or None where the sampler has no descriptor at the start
/// or around the pixel reached.
pub fn refine_match(
    sampler: &dyn DescriptorSampler,
    target: &[f32; 64],
    x: f32,
    y: f32,
    max_steps: u32,
    scratch: &mut RefineScratch,
) -> Option<[f32; 2]> {
    if !(x.is_finite() && y.is_finite()) {
        return None;
    }
    let (x0, y0) = (x.round() as i32, y.round() as i32);
    let r = max_steps as i32 + 1;
    let side = (2 * r + 1) as usize;
    scratch.seen.clear();
    scratch.seen.resize(side * side, f32::NAN);
    // Squared distance at offset (dx, dy) from the start, computed once; infinite without a
    // descriptor.
    let mut at = |dx: i32, dy: i32| -> f32 {
        let slot = &mut scratch.seen[((dy + r) as usize) * side + (dx + r) as usize];
        if slot.is_nan() {
            *slot = sampler
                .float64_at(x0 + dx, y0 + dy)
                .map_or(f32::INFINITY, |d| l2_squared(&d, target));
        }
        *slot
    };
    let (mut cx, mut cy) = (0i32, 0i32);
    let mut best = at(0, 0);
    if !best.is_finite() {
        return None;
    }
    loop {
        let mut next = (best, cx, cy);
        for dy in -1..=1 {
            for dx in -1..=1 {
                let (nx, ny) = (cx + dx, cy + dy);
                if (dx, dy) == (0, 0) || nx.abs() >= r || ny.abs() >= r {
                    continue;
                }
                let d = at(nx, ny);
                if d < next.0 {
                    next = (d, nx, ny);
                }
            }
        }
        if (next.1, next.2) == (cx, cy) {
            break;
        }
        (best, cx, cy) = next;
    }
    // The quadratic through the 3 x 3 distances around the minimum (central differences).
    let mut f = [[0f32; 3]; 3];
    for (j, row) in f.iter_mut().enumerate() {
        for (i, v) in row.iter_mut().enumerate() {
            *v = at(cx + i as i32 - 1, cy + j as i32 - 1);
        }
    }
    if f.iter().flatten().any(|v| !v.is_finite()) {
        return None;
    }
    let (ox, oy) = quadratic_minimum(&f);
    Some([(x0 + cx) as f32 + ox, (y0 + cy) as f32 + oy])
}

/// Offset of the minimum of the quadratic through `f` (3 x 3 samples at unit spacing, row-major
/// by y, centre the smallest), each component within half a sample; (0, 0) where the fit has no
/// minimum.
pub fn quadratic_minimum(f: &[[f32; 3]; 3]) -> (f32, f32) {
    let gx = (f[1][2] - f[1][0]) * 0.5;
    let gy = (f[2][1] - f[0][1]) * 0.5;
    let hxx = f[1][2] - 2.0 * f[1][1] + f[1][0];
    let hyy = f[2][1] - 2.0 * f[1][1] + f[0][1];
    let hxy = (f[2][2] - f[2][0] - f[0][2] + f[0][0]) * 0.25;
    let det = hxx * hyy - hxy * hxy;
    if !(hxx > 0.0 && det > 0.0) {
        return (0.0, 0.0);
    }
    let ox = -(hyy * gx - hxy * gy) / det;
    let oy = -(hxx * gy - hxy * gx) / det;
    (ox.clamp(-0.5, 0.5), oy.clamp(-0.5, 0.5))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Descriptors linear in position: component k is a_k x + b_k y, so the squared distance to
    /// the descriptor of (px, py) is an exact quadratic with its minimum there.
    struct Linear {
        w: i32,
        h: i32,
    }

    fn linear(x: f32, y: f32) -> [f32; 64] {
        let mut d = [0f32; 64];
        for (k, v) in d.iter_mut().enumerate() {
            let a = ((k * 7) % 11) as f32 / 11.0 - 0.4;
            let b = ((k * 5) % 13) as f32 / 13.0 - 0.6;
            *v = (a * x + b * y) * 0.01;
        }
        d
    }

    impl DescriptorSampler for Linear {
        fn size(&self) -> (u32, u32) {
            (self.w as u32, self.h as u32)
        }
        fn float64_at(&self, x: i32, y: i32) -> Option<[f32; 64]> {
            (x >= 0 && y >= 0 && x < self.w && y < self.h).then(|| linear(x as f32, y as f32))
        }
    }

    #[test]
    fn a_match_walks_to_the_best_pixel_and_its_sub_pixel_minimum() {
        let s = Linear { w: 60, h: 50 };
        let mut scratch = RefineScratch::default();
        for (tx, ty) in [(30.3f32, 20.45f32), (27.8, 24.1), (33.5, 19.0)] {
            let target = linear(tx, ty);
            // From a grid point up to 4 px away, in any direction.
            for (sx, sy) in [(27.0f32, 18.0f32), (33.0, 24.0), (30.0, 21.0), (29.0, 23.0)] {
                let p = refine_match(&s, &target, sx, sy, 6, &mut scratch).unwrap();
                assert!(
                    (p[0] - tx).abs() < 1e-2 && (p[1] - ty).abs() < 1e-2,
                    "target ({tx}, {ty}) from ({sx}, {sy}): {p:?}"
                );
            }
        }
        // The walk is bounded: a target 10 px away is not reached in 3 steps.
        let far = refine_match(&s, &linear(40.0, 20.0), 30.0, 20.0, 3, &mut scratch).unwrap();
        assert!(far[0] <= 33.5 + 1e-4, "{far:?}");
        // No descriptor at the start, or next to the pixel reached: no position.
        assert!(refine_match(&s, &linear(1.0, 1.0), 70.0, 20.0, 6, &mut scratch).is_none());
        assert!(refine_match(&s, &linear(0.0, 20.0), 2.0, 20.0, 6, &mut scratch).is_none());
    }

    #[test]
    fn the_quadratic_minimum_is_exact_on_a_quadratic_and_bounded() {
        // f(x, y) = 2 (x - 0.3)^2 + (y + 0.2)^2 + 0.5 (x - 0.3)(y + 0.2)
        let q = |x: f32, y: f32| {
            let (a, b) = (x - 0.3, y + 0.2);
            2.0 * a * a + b * b + 0.5 * a * b
        };
        let mut f = [[0f32; 3]; 3];
        for (j, row) in f.iter_mut().enumerate() {
            for (i, v) in row.iter_mut().enumerate() {
                *v = q(i as f32 - 1.0, j as f32 - 1.0);
            }
        }
        let (ox, oy) = quadratic_minimum(&f);
        assert!(
            (ox - 0.3).abs() < 1e-5 && (oy + 0.2).abs() < 1e-5,
            "{ox} {oy}"
        );
        // A saddle has no minimum; a far minimum is held within half a sample.
        let saddle = [[0.0, 1.0, 0.0], [-1.0, 0.0, -1.0], [0.0, 1.0, 0.0]];
        assert_eq!(quadratic_minimum(&saddle), (0.0, 0.0));
        let mut far = [[0f32; 3]; 3];
        for (j, row) in far.iter_mut().enumerate() {
            for (i, v) in row.iter_mut().enumerate() {
                *v = (i as f32 - 3.0).powi(2) + (j as f32 - 1.0).powi(2);
            }
        }
        assert_eq!(quadratic_minimum(&far), (0.5, 0.0));
    }
}
