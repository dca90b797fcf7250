//! Dense matching (ELAS steps 3 to 5): disparity planes of the triangles, the candidate grid,
//! and the maximum a-posteriori disparity of every pixel inside the triangulation.
//!
//! Cost of disparity d at a pixel: SAD of the two descriptors, plus (on a plane that is not too
//! slanted) the prior `P(|d - d_plane|) = (ln(gamma) - ln(gamma + exp(-Δ²/2σ²))) / beta`, which is
//! negative near the plane and 0 far from it. The candidates are the cell's grid disparities and
//! every d within the plane radius `max(ceil(sigma * sradius), 2)`.

use crate::descriptor::{sad, texture, Desc};
use crate::support::SupportPoint;
use crate::ElasParams;

/// `x.round() as i32` (half away from zero, saturating, NaN to 0) without the library call
/// `round` is on the x86-64 baseline (no SSE4.1): the truncation is one instruction and the
/// fraction x - trunc(x) is exact in f32.
#[inline(always)]
pub fn round_i32(x: f32) -> i32 {
    let t = x as i32;
    let f = x - t as f32;
    if f >= 0.5 {
        t.saturating_add(1)
    } else if f <= -0.5 {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// A disparity plane d = a u + b v + c.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Plane {
    /// Slope along u.
    pub a: f32,
    /// Slope along v.
    pub b: f32,
    /// Offset.
    pub c: f32,
}

impl Plane {
    /// The plane through three (u, v, d) points, `None` when they are collinear in (u, v).
    pub fn through(p: [(f64, f64, f64); 3]) -> Option<Plane> {
        let [(u0, v0, d0), (u1, v1, d1), (u2, v2, d2)] = p;
        let (a1, b1, e1) = (u1 - u0, v1 - v0, d1 - d0);
        let (a2, b2, e2) = (u2 - u0, v2 - v0, d2 - d0);
        let det = a1 * b2 - a2 * b1;
        if det.abs() < 1e-9 {
            return None;
        }
        let a = (e1 * b2 - e2 * b1) / det;
        let b = (a1 * e2 - a2 * e1) / det;
        Some(Plane {
            a: a as f32,
            b: b as f32,
            c: (d0 - a * u0 - b * v0) as f32,
        })
    }

    /// The plane's disparity at (u, v).
    #[inline(always)]
    pub fn at(&self, u: f32, v: f32) -> f32 {
        self.a * u + self.b * v + self.c
    }
}

/// A triangle's planes in the left and in the right image coordinates (u_right = u - d), and
/// whether it gives a prior: only when both exist and |a| < 0.7 in both images.
#[derive(Clone, Copy, Debug)]
pub struct TrianglePlanes {
    /// In left coordinates.
    pub left: Option<Plane>,
    /// In right coordinates.
    pub right: Option<Plane>,
}

impl TrianglePlanes {
    /// Planes of a triangle of support points.
    pub fn of(s: [SupportPoint; 3]) -> TrianglePlanes {
        let l = s.map(|p| (p.u as f64, p.v as f64, p.d as f64));
        let r = s.map(|p| ((p.u - p.d) as f64, p.v as f64, p.d as f64));
        TrianglePlanes {
            left: Plane::through(l),
            right: Plane::through(r),
        }
    }

    /// The plane of `image` (false: left) and whether it is a valid prior.
    pub fn for_image(&self, right: bool) -> (Option<Plane>, bool) {
        let (own, other) = if right {
            (self.right, self.left)
        } else {
            (self.left, self.right)
        };
        let valid =
            matches!((own, other), (Some(p), Some(q)) if p.a.abs() < 0.7 && q.a.abs() < 0.7);
        (own, valid)
    }
}

/// Candidate disparities per `grid_size` cell: d-1, d, d+1 of every support point in the cell
/// and its 8 neighbours (positions in the image the grid is for), ascending.
pub struct DisparityGrid {
    /// Cell size, px.
    pub size: usize,
    /// Cells per row.
    pub gw: usize,
    /// Cells per column.
    pub gh: usize,
    offsets: Vec<u32>,
    cands: Vec<u16>,
}

impl DisparityGrid {
    /// Builds the grid of the left (`right == false`) or the right image.
    pub fn new(pts: &[SupportPoint], w: usize, h: usize, right: bool, p: &ElasParams) -> Self {
        let size = p.grid_size as usize;
        let (gw, gh) = (w.div_ceil(size), h.div_ceil(size));
        let nd = p.disp_max as usize + 1;
        let mut flags = vec![false; gw * gh * nd];
        for s in pts {
            let u = if right { s.u - s.d } else { s.u };
            if u < 0 || s.v < 0 {
                continue;
            }
            let (x, y) = (u as usize / size, s.v as usize / size);
            if x >= gw || y >= gh {
                continue;
            }
            let lo = (s.d - 1).max(p.disp_min as i32) as usize;
            let hi = (s.d + 1).min(p.disp_max as i32) as usize;
            for d in lo..=hi {
                flags[(y * gw + x) * nd + d] = true;
            }
        }
        let mut offsets = Vec::with_capacity(gw * gh + 1);
        let mut cands = Vec::new();
        let mut any = vec![false; nd];
        offsets.push(0);
        for y in 0..gh {
            for x in 0..gw {
                any.fill(false);
                for yy in y.saturating_sub(1)..(y + 2).min(gh) {
                    for xx in x.saturating_sub(1)..(x + 2).min(gw) {
                        let f = &flags[(yy * gw + xx) * nd..(yy * gw + xx + 1) * nd];
                        for (a, &b) in any.iter_mut().zip(f) {
                            *a |= b;
                        }
                    }
                }
                cands.extend((0..nd).filter(|&d| any[d]).map(|d| d as u16));
                offsets.push(cands.len() as u32);
            }
        }
        DisparityGrid {
            size,
            gw,
            gh,
            offsets,
            cands,
        }
    }

    /// The packed grid: `gw * gh + 1` offsets into the candidates, and the candidates.
    pub fn raw(&self) -> (&[u32], &[u16]) {
        (&self.offsets, &self.cands)
    }

    /// Candidates of the cell holding pixel (u, v).
    #[inline(always)]
    pub fn at(&self, u: usize, v: usize) -> &[u16] {
        let c = (v / self.size).min(self.gh - 1) * self.gw + (u / self.size).min(self.gw - 1);
        &self.cands[self.offsets[c] as usize..self.offsets[c + 1] as usize]
    }
}

/// The prior table P\[Δ\] for Δ = 0..=radius, in SAD units, and the radius.
pub fn prior(p: &ElasParams) -> (Vec<i32>, usize) {
    let radius = ((p.sigma * p.sradius).ceil() as usize).max(2);
    let two_s2 = 2.0 * p.sigma as f64 * p.sigma as f64;
    let g = p.gamma as f64;
    let table = (0..=radius)
        .map(|d| {
            let d = d as f64;
            ((g.ln() - (g + (-d * d / two_s2).exp()).ln()) / p.beta as f64) as i32
        })
        .collect();
    (table, radius)
}

/// Everything the per-pixel search reads, for one image.
pub struct Matcher<'a> {
    /// Descriptors of the image being computed.
    pub own: &'a [Desc],
    /// Descriptors of the other image.
    pub other: &'a [Desc],
    /// Width, px.
    pub w: usize,
    /// Height, px.
    pub h: usize,
    /// Computing the right image's disparities (search at u + d).
    pub right: bool,
    /// Prior table and radius ([`prior`]).
    pub prior: (&'a [i32], usize),
    /// Parameters.
    pub p: &'a ElasParams,
}

const WINDOW: usize = 2;

impl Matcher<'_> {
    #[inline(always)]
    fn warp(&self, u: usize, d: usize) -> Option<usize> {
        let uw = if self.right { u + d } else { u.checked_sub(d)? };
        (uw >= WINDOW && uw + WINDOW < self.w).then_some(uw)
    }

    /// MAP disparity of pixel (u, v) given the plane of its triangle, NaN when there is none.
    #[inline]
    pub fn pixel(
        &self,
        u: usize,
        v: usize,
        plane: Option<Plane>,
        valid: bool,
        grid: &[u16],
    ) -> f32 {
        if u < WINDOW || u + WINDOW >= self.w {
            return f32::NAN;
        }
        let row = v * self.w;
        let a = &self.own[row + u];
        if texture(a) < self.p.match_texture {
            return f32::NAN;
        }
        let other = &self.other[row..row + self.w];
        let (dmin, dmax) = (self.p.disp_min as i32, self.p.disp_max as i32);
        let (table, radius) = self.prior;
        let dp = plane.map_or(i32::MIN / 2, |pl| round_i32(pl.at(u as f32, v as f32)));
        let (lo, hi) = if plane.is_some() {
            (
                (dp - radius as i32).max(dmin),
                (dp + radius as i32).min(dmax),
            )
        } else {
            (1, 0)
        };
        let mut best = (i32::MAX, -1i32);
        for &d in grid {
            let d = d as i32;
            if d >= lo && d <= hi {
                continue;
            }
            if let Some(uw) = self.warp(u, d as usize) {
                let e = sad(a, &other[uw]) as i32;
                if e < best.0 {
                    best = (e, d);
                }
            }
        }
        for d in lo..=hi {
            if let Some(uw) = self.warp(u, d as usize) {
                let mut e = sad(a, &other[uw]) as i32;
                if valid {
                    e += table[(d - dp).unsigned_abs() as usize];
                }
                if e < best.0 {
                    best = (e, d);
                }
            }
        }
        if best.1 < 0 {
            return f32::NAN;
        }
        let d = best.1;
        if !self.p.subpixel {
            return d as f32;
        }
        // Equiangular (V-shaped) fit through the costs at d-1, d, d+1, each with its prior.
        let cost = |d: i32| -> Option<i32> {
            if d < dmin || d > dmax {
                return None;
            }
            let uw = self.warp(u, d as usize)?;
            let mut e = sad(a, &other[uw]) as i32;
            if valid && (d - dp).unsigned_abs() as usize <= radius {
                e += table[(d - dp).unsigned_abs() as usize];
            }
            Some(e)
        };
        match (cost(d - 1), cost(d + 1)) {
            (Some(cm), Some(cp)) => {
                let c0 = best.0;
                let slope = (cm - c0).max(cp - c0);
                if slope > 0 {
                    d as f32 + (cm - cp) as f32 / (2 * slope) as f32
                } else {
                    d as f32
                }
            }
            _ => d as f32,
        }
    }

    /// Disparities of every pixel inside the triangles (NaN elsewhere) into `out` (w x h).
    pub fn run(
        &self,
        pts: &[SupportPoint],
        tris: &[[u32; 3]],
        planes: &[TrianglePlanes],
        grid: &DisparityGrid,
        out: &mut [f32],
    ) {
        out.fill(f32::NAN);
        for (t, tp) in tris.iter().zip(planes) {
            let (plane, valid) = tp.for_image(self.right);
            let corners = t.map(|i| {
                let s = pts[i as usize];
                let u = if self.right { s.u - s.d } else { s.u };
                (u as f32, s.v as f32)
            });
            raster(corners, self.w, self.h, |u, v| {
                out[v * self.w + u] = self.pixel(u, v, plane, valid, grid.at(u, v));
            });
        }
    }
}

/// Visits the pixels of a triangle column by column, half-open in u and v (libelas's scan):
/// triangles sharing an edge visit each pixel once.
pub fn raster(c: [(f32, f32); 3], w: usize, h: usize, f: impl FnMut(usize, usize)) {
    raster_columns(c, w, h, 0..w, f);
}

/// [`raster`] restricted to the columns `cols`: the same pixels of those columns, so that
/// column ranges can be rasterised apart.
pub fn raster_columns(
    c: [(f32, f32); 3],
    w: usize,
    h: usize,
    cols: std::ops::Range<usize>,
    mut f: impl FnMut(usize, usize),
) {
    let mut c = c;
    c.sort_by(|a, b| a.0.total_cmp(&b.0));
    let [a, b, cc] = c;
    let line = |p: (f32, f32), q: (f32, f32)| {
        if p.0 as i32 != q.0 as i32 {
            let s = (p.1 - q.1) / (p.0 - q.0);
            (s, p.1 - s * p.0)
        } else {
            (0.0, p.1)
        }
    };
    let (ab, ac, bc) = (line(a, b), line(a, cc), line(b, cc));
    for (lo, hi, e) in [(a.0, b.0, ab), (b.0, cc.0, bc)] {
        if lo as i32 == hi as i32 {
            continue;
        }
        let u0 = (lo as i32).max(0).max(cols.start as i32);
        let u1 = (hi as i32).min(w as i32).min(cols.end as i32);
        for u in u0..u1 {
            let v1 = (ac.0 * u as f32 + ac.1) as i32;
            let v2 = (e.0 * u as f32 + e.1) as i32;
            let (va, vb) = (v1.min(v2).max(0), v1.max(v2).min(h as i32));
            for v in va..vb {
                f(u as usize, v as usize);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn round_i32_is_std_round_cast() {
        let mut s = 0x2545_f491u32;
        let mut vals = vec![
            0.5f32,
            -0.5,
            1.5,
            -1.5,
            2.5,
            0.49999997,
            -0.49999997,
            8388607.5,
            -8388607.5,
            1e10,
            -1e10,
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            2147483520.0,
            -2147483648.0,
            0.0,
            -0.0,
        ];
        for _ in 0..100_000 {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            vals.push(f32::from_bits(s));
            vals.push((s % 100_000) as f32 / 64.0 - 700.0);
        }
        for x in vals {
            assert_eq!(round_i32(x), x.round() as i32, "{x:e}");
        }
    }

    #[test]
    fn plane_through_three_points_is_exact() {
        let pl = Plane::through([(0.0, 0.0, 10.0), (10.0, 0.0, 15.0), (0.0, 20.0, 6.0)]).unwrap();
        assert!(
            (pl.a - 0.5).abs() < 1e-6 && (pl.b + 0.2).abs() < 1e-6 && (pl.c - 10.0).abs() < 1e-6
        );
        assert!(Plane::through([(0.0, 0.0, 1.0), (1.0, 1.0, 2.0), (2.0, 2.0, 3.0)]).is_none());
    }

    #[test]
    fn slanted_planes_give_no_prior() {
        let s = |u, v, d| SupportPoint { u, v, d };
        // d = 0.1 u + 5: fine in both images.
        let t = TrianglePlanes::of([s(0, 0, 5), s(50, 0, 10), s(0, 50, 5)]);
        assert!(t.for_image(false).1 && t.for_image(true).1);
        // d = 0.8 u: too slanted.
        let t = TrianglePlanes::of([s(10, 0, 8), s(20, 0, 16), s(10, 50, 8)]);
        assert!(!t.for_image(false).1 && !t.for_image(true).1);
    }

    #[test]
    fn two_triangles_sharing_an_edge_cover_the_square_once() {
        let mut count = vec![0u8; 20 * 20];
        for tri in [
            [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0)],
            [(0.0, 0.0), (10.0, 10.0), (0.0, 10.0)],
        ] {
            raster(tri, 20, 20, |u, v| count[v * 20 + u] += 1);
        }
        for v in 0..20 {
            for u in 0..20 {
                let inside = u < 10 && v < 10;
                assert_eq!(count[v * 20 + u], inside as u8, "pixel ({u}, {v})");
            }
        }
    }

    #[test]
    fn column_ranges_rasterise_the_same_pixels() {
        let tri = [(3.2f32, 1.5f32), (37.9, 12.1), (11.4, 29.8)];
        let mut whole = Vec::new();
        raster(tri, 40, 32, |u, v| whole.push((u, v)));
        let mut parts = Vec::new();
        for cols in [0..7, 7..8, 8..20, 20..40] {
            raster_columns(tri, 40, 32, cols, |u, v| parts.push((u, v)));
        }
        assert!(whole.len() > 200);
        assert_eq!(whole, parts);
    }

    #[test]
    fn prior_is_a_bonus_near_the_plane_only() {
        let p = ElasParams::robotics();
        let (t, r) = prior(&p);
        assert_eq!(r, 2);
        // Δ = 0: ln(3/4) / 0.02 = -14.4.
        assert_eq!(t[0], -14);
        assert!(t[0] < t[1] && t[1] < t[2] && t[2] <= 0);
    }

    #[test]
    fn grid_holds_neighbouring_support_disparities() {
        let p = ElasParams::robotics();
        let s = |u, v, d| SupportPoint { u, v, d };
        let g = DisparityGrid::new(&[s(5, 5, 10), s(65, 5, 30)], 100, 40, false, &p);
        assert_eq!(g.at(0, 0), &[9, 10, 11]);
        assert_eq!(g.at(25, 25), &[9, 10, 11]);
        assert_eq!(g.at(45, 0), &[29, 30, 31]);
        assert_eq!(g.at(99, 39), &[29, 30, 31]);
        // In the right image the second point sits at 65 - 30 = 35 (cell 1, seen from cell 0);
        // the first at 5 - 10 < 0 is outside the image and left out.
        let g = DisparityGrid::new(&[s(5, 5, 10), s(65, 5, 30)], 100, 40, true, &p);
        assert_eq!(g.at(0, 0), &[29, 30, 31]);
        let g = DisparityGrid::new(&[s(15, 5, 10), s(65, 5, 30)], 100, 40, true, &p);
        assert_eq!(g.at(0, 0), &[9, 10, 11, 29, 30, 31]);
    }
}
