//! Upright SURF descriptors at any pixel, from Haar response maps computed once per image.
//!
//! An upright descriptor at scale s samples the Haar responses of size 2s on a 20 x 20 grid of
//! step s around its centre, weighted by a Gaussian of 3.3 s (see [`surf::descriptor`]). With
//! the responses of every pixel in two maps, a descriptor is 400 weighted reads: no box sums and
//! no exponentials. The dense grid's descriptors are computed this way, and the maps go out with
//! the features ([`misslam_framework::DescriptorSampler`]) so that a consumer can compute the
//! descriptor at any other pixel, e.g. to move a grid match to the pixel that fits it best. The
//! result equals [`surf::descriptor`] bit for bit at integer positions inside the image.

use crate::surf::{self, Integral};
use misslam_framework::DescriptorSampler;

/// Haar response maps of one image at one descriptor scale.
#[derive(Clone, Debug, Default)]
pub struct UprightSampler {
    w: usize,
    h: usize,
    scale: f32,
    /// Response in x and y of every pixel (row-major).
    rx: Vec<f32>,
    ry: Vec<f32>,
    /// Sample positions relative to the centre, units of s: -9.5, -8.5, ..., 9.5.
    u: [f32; 20],
    /// Gaussian weight of sample (i, j), row-major by j.
    weights: Vec<f32>,
}

impl UprightSampler {
    /// Computes the response maps of the image behind `ii` for descriptors at `scale`.
    pub fn build(&mut self, ii: &Integral, w: usize, h: usize, scale: f32) {
        let haar = surf::haar_size(scale);
        self.rx.resize(w * h, 0.0);
        self.ry.resize(w * h, 0.0);
        for y in 0..h {
            for x in 0..w {
                self.rx[y * w + x] = ii.haar_x(x as i64, y as i64, haar);
                self.ry[y * w + x] = ii.haar_y(x as i64, y as i64, haar);
            }
        }
        if self.weights.is_empty() || self.scale != scale {
            for (k, u) in self.u.iter_mut().enumerate() {
                *u = -10.0 + k as f32 + 0.5;
            }
            self.weights = (0..400)
                .map(|k| surf::descriptor_weight(self.u[k % 20], self.u[k / 20]))
                .collect();
        }
        (self.w, self.h, self.scale) = (w, h, scale);
    }

    /// The upright descriptor centred on pixel (x, y); None where a sample leaves the image.
    pub fn at(&self, x: i32, y: i32) -> Option<[f32; 64]> {
        // The sample rows and columns, rounded as `surf::descriptor` rounds them.
        let mut cols = [0usize; 20];
        let mut rows = [0usize; 20];
        for k in 0..20 {
            let px = (x as f32 + self.scale * self.u[k]).round();
            let py = (y as f32 + self.scale * self.u[k]).round();
            if !(px >= 0.0 && py >= 0.0 && (px as usize) < self.w && (py as usize) < self.h) {
                return None;
            }
            (cols[k], rows[k]) = (px as usize, py as usize);
        }
        let mut d = [0f32; 64];
        for sy in 0..4 {
            for sx in 0..4 {
                let mut acc = [0f32; 4];
                for (j, &r) in rows.iter().enumerate().skip(5 * sy).take(5) {
                    let row = r * self.w;
                    for (i, &c) in cols.iter().enumerate().skip(5 * sx).take(5) {
                        let wt = self.weights[j * 20 + i];
                        let du = wt * self.rx[row + c];
                        let dv = wt * self.ry[row + c];
                        acc[0] += du;
                        acc[1] += dv;
                        acc[2] += du.abs();
                        acc[3] += dv.abs();
                    }
                }
                d[(sy * 4 + sx) * 4..(sy * 4 + sx) * 4 + 4].copy_from_slice(&acc);
            }
        }
        surf::normalise(&mut d);
        Some(d)
    }
}

impl DescriptorSampler for UprightSampler {
    fn size(&self) -> (u32, u32) {
        (self.w as u32, self.h as u32)
    }

    fn float64_at(&self, x: i32, y: i32) -> Option<[f32; 64]> {
        self.at(x, y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn texture(w: usize, h: usize) -> Vec<u8> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                let v = 128.0
                    + 60.0 * (x * 0.31 + (y * 0.17).sin() * 3.0).sin()
                    + 40.0 * (y * 0.23 - x * 0.05).cos()
                    + ((i * 2_654_435_761) % 23) as f32;
                v.clamp(0.0, 255.0) as u8
            })
            .collect()
    }

    #[test]
    fn sampled_descriptors_equal_the_direct_ones_bit_for_bit() {
        let (w, h) = (97usize, 71usize);
        let img = texture(w, h);
        let mut ii = Integral::default();
        ii.build(&img, w, h);
        // An even-sized and an odd-rounded Haar size, and a scale whose sample offsets fall on
        // half pixels (rounding ties).
        for scale in [2.0f32, 1.2, 1.5] {
            let mut s = UprightSampler::default();
            s.build(&ii, w, h, scale);
            let (mut inside, mut outside) = (0, 0);
            for y in 0..h as i32 {
                for x in 0..w as i32 {
                    match s.at(x, y) {
                        Some(d) => {
                            let direct = surf::descriptor(&ii, x as f32, y as f32, scale, f32::NAN);
                            assert_eq!(d, direct, "scale {scale} at ({x}, {y})");
                            inside += 1;
                        }
                        None => {
                            // Only where a sample leaves the image.
                            let reach = (scale * 9.5).ceil() as i32 + 1;
                            assert!(
                                x < reach
                                    || y < reach
                                    || x >= w as i32 - reach
                                    || y >= h as i32 - reach,
                                "scale {scale}: no descriptor at ({x}, {y})"
                            );
                            outside += 1;
                        }
                    }
                }
            }
            assert!(inside > 1000 && outside > 0, "{inside} {outside}");
        }
    }
}
