//! The depth-map operations of `depth.postprocess`, as plain functions on row-major slices
//! (NaN marks an invalid pixel throughout).

use rayon::prelude::*;

mod bilateral;
pub use bilateral::bilateral;
pub(crate) use bilateral::{BilateralTables, RANGE_LUT};

/// Pinhole intrinsics of a map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pinhole {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

/// Sets depth outside `[min_mm, max_mm]` (and non-finite or non-positive depth) to NaN; returns
/// how many pixels it invalidated. Branch-free per pixel, so it vectorises.
pub fn limit_range(depth: &mut [f32], min_mm: f32, max_mm: f32) -> usize {
    depth
        .par_chunks_mut(4096)
        .map(|chunk| {
            let mut n = 0;
            for z in chunk {
                let v = *z;
                // Every comparison with NaN is false: NaN stays NaN and is not counted (it was
                // already invalid).
                let in_range = v.is_finite() & (v > 0.0) & (v >= min_mm) & (v <= max_mm);
                n += usize::from(!in_range & !v.is_nan());
                *z = if in_range { v } else { f32::NAN };
            }
            n
        })
        .sum()
}

/// Specular highlights of an RGB (or gray) image: pixels whose brightest channel reaches
/// `min_value` with saturation `(max - min) / max` at most `max_saturation`, grown by
/// `dilate_px` (the highlight's rim is unreliable too). Returns 1 where masked, a byte per
/// `channels` bytes of `data`.
pub fn specular_mask(
    data: &[u8],
    channels: usize,
    width: usize,
    height: usize,
    min_value: u8,
    max_saturation: f32,
    dilate_px: usize,
) -> Vec<u8> {
    let c = channels.max(1);
    let widest = widest_spreads(max_saturation);
    let test =
        |hi: u8, lo: u8| (hi >= min_value && i16::from(hi - lo) <= widest[hi as usize]) as u8;
    let mut m = vec![0u8; data.len() / c];
    const CHUNK: usize = 4096;
    let chunks = m.par_chunks_mut(CHUNK).zip(data.par_chunks(CHUNK * c));
    match c {
        1 => chunks.for_each(|(o, px)| {
            for (o, &v) in o.iter_mut().zip(px) {
                *o = test(v, v);
            }
        }),
        3 => chunks.for_each(|(o, px)| {
            for (o, p) in o.iter_mut().zip(px.as_chunks::<3>().0) {
                *o = test(p[0].max(p[1]).max(p[2]), p[0].min(p[1]).min(p[2]));
            }
        }),
        _ => chunks.for_each(|(o, px)| {
            for (o, p) in o.iter_mut().zip(px.chunks_exact(c)) {
                let hi = p.iter().copied().max().unwrap_or(0);
                let lo = p.iter().copied().min().unwrap_or(0);
                *o = test(hi, lo);
            }
        }),
    }
    if dilate_px > 0 {
        m = dilate(&m, width, height, dilate_px);
    }
    m
}

/// The specular saturation test as a table: per brightest value `hi`, the largest spread
/// `hi - lo` whose saturation `(hi - lo) / hi` is at most `max_saturation` (-1: none). The
/// division is monotonic in the spread, so `spread <= widest[hi]` is the test itself, without a
/// division per pixel (the GPU kernel reads the same table).
pub(crate) fn widest_spreads(max_saturation: f32) -> [i16; 256] {
    std::array::from_fn(|hi| {
        (0..=hi)
            .rev()
            .find(|&d| {
                let sat = if hi == 0 { 0.0 } else { d as f32 / hi as f32 };
                sat <= max_saturation
            })
            .map_or(-1, |d| d as i16)
    })
}

/// Square dilation of a 0/1 mask by `r` pixels (separable max filter: a row pass, then a column
/// pass, each a running maximum over shifted rows that vectorises; rows in parallel). A mask that
/// is not `w` x `h` (callers check their sizes first) is returned unchanged.
pub fn dilate(m: &[u8], w: usize, h: usize, r: usize) -> Vec<u8> {
    if w == 0 || h == 0 || m.len() != w * h {
        return m.to_vec();
    }
    let mut tmp = m.to_vec();
    tmp.par_chunks_mut(w)
        .zip(m.par_chunks(w))
        .for_each(|(t, row)| {
            for s in 1..=r.min(w - 1) {
                // t[x] = max(t[x], row[x + s]) and t[x + s] = max(t[x + s], row[x]).
                for (o, v) in t[..w - s].iter_mut().zip(&row[s..]) {
                    *o = (*o).max(*v);
                }
                for (o, v) in t[s..].iter_mut().zip(&row[..w - s]) {
                    *o = (*o).max(*v);
                }
            }
        });
    let mut out = vec![0u8; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, o)| {
        let (a, b) = (y.saturating_sub(r), (y + r).min(h - 1));
        o.copy_from_slice(&tmp[a * w..(a + 1) * w]);
        for yy in a + 1..=b {
            for (x, v) in o.iter_mut().zip(&tmp[yy * w..(yy + 1) * w]) {
                *x = (*x).max(*v);
            }
        }
    });
    out
}

/// Lifts depth to camera-frame vertices `Z K^-1 [u v 1]^T` and normals. A normal is the cross
/// product of central differences, turned towards the camera; it is NaN when a neighbour is
/// invalid or a depth step to a neighbour exceeds `max_step_mm` (an occlusion edge). Row by row,
/// with `(u - cx) / fx` from a table per column: the arithmetic of the per-pixel definition (the
/// test's reference), without a division per pixel. A `depth` shorter than `k`'s pixels leaves
/// the missing ones NaN (callers check the size, as [`crate::clean`] does).
pub fn vertex_normal_maps_into(
    depth: &[f32],
    k: &Pinhole,
    max_step_mm: f32,
    vertices: &mut Vec<[f32; 3]>,
    normals: &mut Vec<[f32; 3]>,
) {
    let (w, h) = (k.width, k.height);
    let nan = [f32::NAN; 3];
    // Every entry is written below, row by row in parallel. Buffers of the right size are
    // reused as they are; others are replaced by zeroed allocations, which are mapped lazily, so
    // their pages are faulted in by the parallel rows (a serial fill would touch every page on
    // one thread).
    for m in [&mut *vertices, &mut *normals] {
        if m.len() != w * h {
            *m = vec![[0.0; 3]; w * h];
        }
    }
    if w == 0 || h == 0 {
        return;
    }
    debug_assert_eq!(depth.len(), w * h, "depth and calibration disagree");
    let xs: Vec<f64> = (0..w).map(|u| (u as f64 - k.cx) / k.fx).collect();
    vertices
        .par_chunks_mut(w)
        .zip(depth.par_chunks(w))
        .enumerate()
        .for_each(|(v, (row, zs))| {
            let ys = (v as f64 - k.cy) / k.fy;
            row.fill(nan);
            for ((p, &z), &xs) in row.iter_mut().zip(zs).zip(&xs) {
                if z.is_finite() && z > 0.0 {
                    *p = [(xs * z as f64) as f32, (ys * z as f64) as f32, z];
                }
            }
        });
    let vertices = &*vertices;
    normals.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        row.fill(nan);
        if y == 0 || y + 1 >= h || w < 3 {
            return;
        }
        let (up, mid, down) = (
            &vertices[(y - 1) * w..y * w],
            &vertices[y * w..(y + 1) * w],
            &vertices[(y + 1) * w..(y + 2) * w],
        );
        for x in 1..w - 1 {
            let p = mid[x];
            let z = p[2];
            if !z.is_finite() {
                continue;
            }
            let (l, r, u, d) = (mid[x - 1], mid[x + 1], up[x], down[x]);
            if [l, r, u, d]
                .iter()
                .any(|q| !q[2].is_finite() || (q[2] - z).abs() > max_step_mm)
            {
                continue;
            }
            let a = [r[0] - l[0], r[1] - l[1], r[2] - l[2]];
            let b = [d[0] - u[0], d[1] - u[1], d[2] - u[2]];
            let n = [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ];
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len.is_nan() || len <= 0.0 {
                continue;
            }
            let s = if n[0] * p[0] + n[1] * p[1] + n[2] * p[2] > 0.0 {
                -1.0 / len
            } else {
                1.0 / len
            };
            row[x] = n.map(|c| c * s);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pinhole(w: usize, h: usize) -> Pinhole {
        Pinhole {
            width: w,
            height: h,
            fx: 500.0,
            fy: 500.0,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
        }
    }

    #[test]
    fn range_limits_invalidate_exactly_the_out_of_range_pixels() {
        let mut d = vec![5.0, 50.0, f32::NAN, 500.0, f32::INFINITY, -3.0, 100.0];
        let n = limit_range(&mut d, 10.0, 300.0);
        assert_eq!(n, 4);
        let valid: Vec<bool> = d.iter().map(|v| v.is_finite()).collect();
        assert_eq!(valid, [false, true, false, false, false, false, true]);
    }

    #[test]
    fn specular_mask_finds_white_saturated_pixels_and_dilates() {
        let (w, h) = (9usize, 7usize);
        let mut img = vec![[180u8, 60, 50]; w * h];
        img[3 * w + 4] = [250, 248, 245]; // a highlight
        img[w + 1] = [250, 120, 100]; // bright but red: tissue, not a highlight
        let flat: Vec<u8> = img.iter().flatten().copied().collect();
        let m = specular_mask(&flat, 3, w, h, 240, 0.15, 0);
        assert_eq!(m.iter().map(|&v| v as usize).sum::<usize>(), 1);
        assert_eq!(m[3 * w + 4], 1);
        let m = specular_mask(&flat, 3, w, h, 240, 0.15, 1);
        assert_eq!(m.iter().map(|&v| v as usize).sum::<usize>(), 9);
        assert_eq!(m[2 * w + 3], 1);
        assert_eq!(m[w + 1], 0);
    }

    #[test]
    fn specular_mask_equals_the_per_pixel_definition() {
        // Every (brightest, darkest) pair against the division the mask's table stands for, at
        // saturations on and between the steps of d / hi (0.2 is 1/5, 2/10, ...), for 1, 3 and
        // 4 channels (the last the generic path), over more pixels than one parallel chunk.
        let pixels: Vec<[u8; 4]> = (0..=255u8)
            .flat_map(|hi| (0..=hi).map(move |lo| [lo, hi, lo.midpoint(hi), lo]))
            .collect();
        for max_sat in [0.0, 0.15, 0.2, 1.0 / 3.0, 0.5, 1.0] {
            for min_value in [0u8, 1, 240] {
                let want = |px: &[u8]| {
                    let hi = *px.iter().max().unwrap();
                    let lo = *px.iter().min().unwrap();
                    let sat = if hi == 0 {
                        0.0
                    } else {
                        (hi - lo) as f32 / hi as f32
                    };
                    u8::from(hi >= min_value && sat <= max_sat)
                };
                for c in [1usize, 3, 4] {
                    let data: Vec<u8> = pixels.iter().flat_map(|p| p[4 - c..].to_vec()).collect();
                    let got = specular_mask(&data, c, data.len() / c, 1, min_value, max_sat, 0);
                    assert_eq!(got.len(), pixels.len());
                    for (i, px) in data.chunks_exact(c).enumerate() {
                        assert_eq!(got[i], want(px), "{px:?}, {c} channels, sat {max_sat}");
                    }
                }
            }
        }
    }

    #[test]
    fn dilation_equals_the_square_window_definition() {
        let mut s = 99u32;
        for (w, h, r) in [(1, 1, 2), (7, 5, 1), (19, 11, 3), (6, 9, 8), (30, 4, 0)] {
            let m: Vec<u8> = (0..w * h)
                .map(|_| {
                    s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    (s >> 28 == 0) as u8
                })
                .collect();
            let got = dilate(&m, w, h, r);
            for y in 0..h {
                for x in 0..w {
                    let mut want = 0;
                    for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                        for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                            want = want.max(m[yy * w + xx]);
                        }
                    }
                    assert_eq!(got[y * w + x], want, "{w}x{h} r {r} at ({x}, {y})");
                }
            }
        }
    }

    /// The per-pixel definition of [`vertex_normal_maps_into`].
    fn vertex_normal_maps_per_pixel(
        depth: &[f32],
        k: &Pinhole,
        max_step_mm: f32,
    ) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
        let (w, h) = (k.width, k.height);
        let nan = [f32::NAN; 3];
        let vertices: Vec<[f32; 3]> = (0..w * h)
            .map(|i| {
                let z = depth[i];
                if !(z.is_finite() && z > 0.0) {
                    return nan;
                }
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                [
                    ((u - k.cx) / k.fx * z as f64) as f32,
                    ((v - k.cy) / k.fy * z as f64) as f32,
                    z,
                ]
            })
            .collect();
        let normals = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if x == 0 || y == 0 || x + 1 >= w || y + 1 >= h || !vertices[i][2].is_finite() {
                    return nan;
                }
                let (l, r, u, d) = (
                    vertices[i - 1],
                    vertices[i + 1],
                    vertices[i - w],
                    vertices[i + w],
                );
                let z = vertices[i][2];
                if [l, r, u, d]
                    .iter()
                    .any(|p| !p[2].is_finite() || (p[2] - z).abs() > max_step_mm)
                {
                    return nan;
                }
                let a = [r[0] - l[0], r[1] - l[1], r[2] - l[2]];
                let b = [d[0] - u[0], d[1] - u[1], d[2] - u[2]];
                let n = [
                    a[1] * b[2] - a[2] * b[1],
                    a[2] * b[0] - a[0] * b[2],
                    a[0] * b[1] - a[1] * b[0],
                ];
                let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
                if len.is_nan() || len <= 0.0 {
                    return nan;
                }
                let p = vertices[i];
                let s = if n[0] * p[0] + n[1] * p[1] + n[2] * p[2] > 0.0 {
                    -1.0 / len
                } else {
                    1.0 / len
                };
                n.map(|c| c * s)
            })
            .collect();
        (vertices, normals)
    }

    #[test]
    fn maps_equal_the_per_pixel_definition() {
        // A bumpy surface with holes, non-positive depths and occlusion steps, on odd sizes
        // (and the degenerate ones).
        for (w, h) in [(37usize, 23usize), (2, 5), (5, 2), (1, 1)] {
            let k = pinhole(w, h);
            let mut s = 0x2545f4914f6cdd1du64;
            let mut rnd = || {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                (s >> 11) as f64 / (1u64 << 53) as f64
            };
            let depth: Vec<f32> = (0..w * h)
                .map(|i| {
                    let r = rnd();
                    let (x, y) = ((i % w) as f64, (i / w) as f64);
                    if r < 0.05 {
                        f32::NAN
                    } else if r < 0.07 {
                        -1.0
                    } else {
                        (80.0
                            + 3.0 * (0.3 * x).sin() * (0.2 * y).cos()
                            + 10.0 * f64::from(x > 20.0)
                            + rnd()) as f32
                    }
                })
                .collect();
            let (want_v, want_n) = vertex_normal_maps_per_pixel(&depth, &k, 3.0);
            let (mut v, mut n) = (vec![[1.0; 3]; 3], Vec::new());
            vertex_normal_maps_into(&depth, &k, 3.0, &mut v, &mut n);
            let bits = |m: &[[f32; 3]]| -> Vec<[u32; 3]> {
                m.iter()
                    .map(|p| p.map(|c| if c.is_nan() { u32::MAX } else { c.to_bits() }))
                    .collect()
            };
            assert_eq!(bits(&v), bits(&want_v), "{w}x{h} vertices");
            assert_eq!(bits(&n), bits(&want_n), "{w}x{h} normals");
            // Buffers reused at their size hold nothing of their last contents.
            v.iter_mut().chain(n.iter_mut()).for_each(|p| *p = [7.0; 3]);
            vertex_normal_maps_into(&depth, &k, 3.0, &mut v, &mut n);
            assert_eq!(bits(&v), bits(&want_v), "{w}x{h} vertices, reused");
            assert_eq!(bits(&n), bits(&want_n), "{w}x{h} normals, reused");
            if w > 20 {
                let normals = n.iter().filter(|q| q[0].is_finite()).count();
                assert!(normals > w * h / 2, "{w}x{h}: {normals} normals");
            }
        }
    }

    #[test]
    fn a_tilted_plane_lifts_exactly_with_its_normal() {
        let (w, h) = (32usize, 24usize);
        let k = pinhole(w, h);
        // Plane z = 100 + 0.5 X: depth per pixel solves z = 100 + 0.5 (u - cx) z / fx.
        let depth: Vec<f32> = (0..w * h)
            .map(|i| {
                let u = (i % w) as f64;
                (100.0 / (1.0 - 0.5 * (u - k.cx) / k.fx)) as f32
            })
            .collect();
        let (mut v, mut n) = (Vec::new(), Vec::new());
        vertex_normal_maps_into(&depth, &k, 5.0, &mut v, &mut n);
        let want = {
            let l = (0.25f32 + 1.0).sqrt();
            [0.5 / l, 0.0, -1.0 / l]
        };
        for y in 1..h - 1 {
            for x in 1..w - 1 {
                let p = v[y * w + x];
                assert!((p[2] - (100.0 + 0.5 * p[0])).abs() < 1e-3);
                let q = n[y * w + x];
                for c in 0..3 {
                    assert!((q[c] - want[c]).abs() < 1e-4, "{q:?}");
                }
            }
        }
        assert!(n[0][0].is_nan());
        // A depth step beyond max_step: no normal across it.
        let mut stepped = depth.clone();
        for y in 0..h {
            for x in 16..w {
                stepped[y * w + x] += 20.0;
            }
        }
        vertex_normal_maps_into(&stepped, &k, 5.0, &mut v, &mut n);
        assert!(n[10 * w + 15][0].is_nan() && n[10 * w + 16][0].is_nan());
        assert!(n[10 * w + 10][0].is_finite());
    }
}
