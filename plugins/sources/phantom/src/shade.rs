//! Shading of the rasterised views: Lambert plus a specular highlight lit from the scope tip,
//! the albedo of the tissue point each pixel sees, vignetting, gamma and sensor noise. Rows are
//! shaded on the pool's threads, each with its own noise stream, so the images do not depend on
//! the threads.

use misslam_framework::nalgebra::{Isometry3, Point3, Vector3};
use misslam_framework::Image;
use rayon::prelude::*;

use crate::render::Raster;
use crate::sensor::{quantize, Noise, SplitMix, GAMMA_LUT};
use crate::surface::Albedo;
use crate::Phantom;

/// What every row of a shaded view shares.
#[derive(Clone, Copy)]
struct RowShading {
    light: Point3<f32>,
    eye: Point3<f32>,
    sigma: f32,
    /// The distance at which the light's falloff is 1, mm.
    reference: f32,
    /// The principal point.
    centre: (f32, f32),
    /// Squared distance from the principal point to the image corner (vignetting).
    r_max2: f32,
    /// Below this n.h the highlight is under half a grey level.
    spec_floor: f32,
    seed: u64,
}

impl Phantom {
    /// Shades both rasterised views, with sensor noise `sigma`.
    pub(crate) fn shade_pair(
        &self,
        vertices: &[[f32; 3]],
        normals: &[[f32; 3]],
        world_from_left: Isometry3<f32>,
        seeds: [u64; 2],
        sigma: f32,
    ) -> (Image, Image) {
        let b = self.params.baseline_mm as f32;
        // The light sits at the scope tip, between the two cameras.
        let light = world_from_left * Point3::new(0.5 * b, 0.0, 0.0);
        let left_centre = world_from_left * Point3::origin();
        let right_centre = world_from_left * Point3::new(b, 0.0, 0.0);
        rayon::join(
            || {
                self.shade(
                    &self.left,
                    vertices,
                    normals,
                    light,
                    left_centre,
                    seeds[0],
                    sigma,
                )
            },
            || {
                self.shade(
                    &self.right,
                    vertices,
                    normals,
                    light,
                    right_centre,
                    seeds[1],
                    sigma,
                )
            },
        )
    }

    #[allow(clippy::too_many_arguments)]
    fn shade(
        &self,
        r: &Raster,
        vertices: &[[f32; 3]],
        normals: &[[f32; 3]],
        light: Point3<f32>,
        eye: Point3<f32>,
        seed: u64,
        sigma: f32,
    ) -> Image {
        let p = &self.params;
        let (w, h) = (p.width as usize, p.height as usize);
        let mut data = vec![0u8; w * h * 3];
        let (cx, cy) = (self.calib.cx as f32, self.calib.cy as f32);
        let r_max2 = cx * cx + cy * cy;
        // The highlight is below half a level where n.h^shininess < 1/512.
        let spec_floor = (1.0f32 / 512.0).powf(1.0 / p.shininess.max(1.0));
        let c = RowShading {
            light,
            eye,
            sigma,
            reference: p.distance_mm,
            centre: (cx, cy),
            r_max2,
            spec_floor,
            seed,
        };
        // Rows in parallel: each row has its own noise stream, so the image is the same
        // whatever the threads.
        data.par_chunks_exact_mut(w * 3)
            .enumerate()
            .for_each(|(y, row)| self.shade_row(r, vertices, normals, &c, y, row));
        Image {
            width: p.width,
            height: p.height,
            channels: 3,
            data,
        }
    }

    /// Shades row `y` of a view into `row` (RGB).
    fn shade_row(
        &self,
        r: &Raster,
        vertices: &[[f32; 3]],
        normals: &[[f32; 3]],
        c: &RowShading,
        y: usize,
        row: &mut [u8],
    ) {
        let p = &self.params;
        let w = p.width as usize;
        let RowShading {
            light,
            eye,
            sigma,
            reference,
            centre: (cx, cy),
            r_max2,
            spec_floor,
            ..
        } = *c;
        // One noise stream per row.
        let mut rng = SplitMix(c.seed ^ (y as u64).wrapping_mul(0xd6e8_feb8_6659_fd93));
        let mut noise = Noise::new(&self.gauss);
        for x in 0..w {
            let i = y * w + x;
            let px = &mut row[x * 3..x * 3 + 3];
            let Some(t) = self.triangles.get(r.triangle[i] as usize) else {
                // Nothing seen: black (outside the tissue patch), noise included.
                for v in px.iter_mut() {
                    *v = quantize(0.0, sigma, &mut noise, &mut rng);
                }
                continue;
            };
            let bw = r.bary[i];
            let lerp = |attr: &[[f32; 3]]| {
                let (a0, a1, a2) = (
                    attr[t[0] as usize],
                    attr[t[1] as usize],
                    attr[t[2] as usize],
                );
                // Written out: an array `map` here is left as a call in this hot loop.
                [
                    bw[0] * a0[0] + bw[1] * a1[0] + bw[2] * a2[0],
                    bw[0] * a0[1] + bw[1] * a1[1] + bw[2] * a2[1],
                    bw[0] * a0[2] + bw[1] * a1[2] + bw[2] * a2[2],
                ]
            };
            let (pos, n, rest) = (lerp(vertices), lerp(normals), lerp(&self.rest));
            let a = match *self.albedo {
                Albedo::Planar(ref atlas) => atlas.sample(rest[0], rest[1]),
                Albedo::Triplanar { .. } => self.albedo.sample(rest, lerp(&self.rest_normals)),
            };
            let pos = Vector3::new(pos[0], pos[1], pos[2]);
            let mut n = Vector3::new(n[0], n[1], n[2]).normalize();
            // Two-sided: a surface seen from its back is lit as its front.
            if n.dot(&(eye.coords - pos)) < 0.0 {
                n = -n;
            }
            let to_light = light.coords - pos;
            let dist = to_light.norm();
            let l = to_light / dist;
            let n_dot_l = n.dot(&l);
            let diffuse = n_dot_l.max(0.0) * (reference / dist).powi(2);
            let spec = if p.specular > 0.0 && n_dot_l > 0.0 {
                let v = (eye.coords - pos).normalize();
                let n_dot_h = n.dot(&(l + v).normalize());
                if n_dot_h > spec_floor {
                    p.specular * n_dot_h.powf(p.shininess)
                } else {
                    0.0
                }
            } else {
                0.0
            };
            // Lens vignetting, darkest in the corners.
            let (dx, dy) = (x as f32 - cx, y as f32 - cy);
            let vignette = 1.0 - p.vignetting * (dx * dx + dy * dy) / r_max2;
            for k in 0..3 {
                let radiance = vignette * (a[k] * (p.ambient + (1.0 - p.ambient) * diffuse) + spec);
                let lut = (radiance.clamp(0.0, 1.0) * (GAMMA_LUT - 1) as f32 + 0.5) as usize;
                px[k] = quantize(self.gamma[lut], sigma, &mut noise, &mut rng);
            }
        }
    }
}
