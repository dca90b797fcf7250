//! Shading of the rasterised views: Lambert plus a specular highlight lit from the scope tip,
//! the albedo of the tissue point each pixel sees, vignetting, gamma and sensor noise. Rows are
//! shaded on the pool's threads, each with its own noise stream, so the images do not depend on
//! the threads.

use misslam_framework::nalgebra::{Isometry3, Point3};
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
        let w = p.width as usize;
        let mut data = vec![0u8; w * p.height as usize * 3];
        let c = self.row_shading(light, eye, seed, sigma);
        // Rows in parallel: each row has its own noise stream, so the image is the same
        // whatever the threads. Each worker's row arrays serve all its rows.
        data.par_chunks_exact_mut(w * 3).enumerate().for_each_init(
            || RowScratch::new(w),
            |s, (y, row)| self.shade_row(r, vertices, normals, &c, s, y, row),
        );
        Image {
            width: p.width,
            height: p.height,
            channels: 3,
            data,
        }
    }

    /// What every row of a view lit from `light` and seen from `eye` shares.
    fn row_shading(
        &self,
        light: Point3<f32>,
        eye: Point3<f32>,
        seed: u64,
        sigma: f32,
    ) -> RowShading {
        let p = &self.params;
        let (cx, cy) = (self.calib.cx as f32, self.calib.cy as f32);
        RowShading {
            light,
            eye,
            sigma,
            reference: p.distance_mm,
            centre: (cx, cy),
            r_max2: cx * cx + cy * cy,
            // The highlight is below half a level where n.h^shininess < 1/512.
            spec_floor: (1.0f32 / 512.0).powf(1.0 / p.shininess.max(1.0)),
            seed,
        }
    }

    /// Shades row `y` of a view into `row` (RGB), in three passes over the row: the
    /// attributes each pixel sees (gathered from its triangle's vertices and the albedo atlas),
    /// the lighting (plain arithmetic over the row's arrays, which the compiler vectorises), and
    /// the highlight, gamma and noise (in pixel order, so each row's noise stream is drawn as
    /// before). The arithmetic per pixel is that of one pass: the images are the same bits.
    #[allow(clippy::too_many_arguments)]
    fn shade_row(
        &self,
        r: &Raster,
        vertices: &[[f32; 3]],
        normals: &[[f32; 3]],
        c: &RowShading,
        s: &mut RowScratch,
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
        s.seen.fill(false);
        let tris = &r.triangle[y * w..(y + 1) * w];
        let bary = &r.bary[y * w..(y + 1) * w];
        // Pass 1: position, normal and albedo of the tissue point each pixel sees.
        for x in 0..w {
            let Some(t) = self.triangles.get(tris[x] as usize) else {
                continue;
            };
            s.seen[x] = true;
            let bw = bary[x];
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
            match *self.albedo {
                // Sampled in a loop of its own below (0 to 2 % faster than here, measured).
                Albedo::Planar(_) => {
                    s.albedo[0][x] = rest[0];
                    s.albedo[1][x] = rest[1];
                }
                Albedo::Triplanar { .. } => {
                    let a = self.albedo.sample(rest, lerp(&self.rest_normals));
                    for (channel, v) in s.albedo.iter_mut().zip(a) {
                        channel[x] = v;
                    }
                }
            }
            for k in 0..3 {
                s.pos[k][x] = pos[k];
                s.n[k][x] = n[k];
            }
        }
        if let Albedo::Planar(ref atlas) = *self.albedo {
            for x in 0..w {
                if s.seen[x] {
                    let a = atlas.sample(s.albedo[0][x], s.albedo[1][x]);
                    for (channel, v) in s.albedo.iter_mut().zip(a) {
                        channel[x] = v;
                    }
                }
            }
        }
        // Pass 2: Lambert and the highlight's n.h, branch-free over the row (a pixel that sees
        // nothing computes garbage, which pass 3 never reads).
        let specular = p.specular > 0.0;
        {
            let [px, py, pz] = &s.pos;
            let [nx, ny, nz] = &s.n;
            let (px, py, pz) = (&px[..w], &py[..w], &pz[..w]);
            let (nx, ny, nz) = (&nx[..w], &ny[..w], &nz[..w]);
            let diffuse = &mut s.diffuse[..w];
            let n_dot_h = &mut s.n_dot_h[..w];
            for x in 0..w {
                let pos = [px[x], py[x], pz[x]];
                // |n| and n / |n| as nalgebra's `normalize` computes them.
                let len = (nx[x] * nx[x] + ny[x] * ny[x] + nz[x] * nz[x]).sqrt();
                let mut n = [nx[x] / len, ny[x] / len, nz[x] / len];
                let to_eye = [eye.x - pos[0], eye.y - pos[1], eye.z - pos[2]];
                // Two-sided: a surface seen from its back is lit as its front.
                let back = n[0] * to_eye[0] + n[1] * to_eye[1] + n[2] * to_eye[2] < 0.0;
                n = if back { [-n[0], -n[1], -n[2]] } else { n };
                let to_light = [light.x - pos[0], light.y - pos[1], light.z - pos[2]];
                let dist = (to_light[0] * to_light[0]
                    + to_light[1] * to_light[1]
                    + to_light[2] * to_light[2])
                    .sqrt();
                let l = [to_light[0] / dist, to_light[1] / dist, to_light[2] / dist];
                let n_dot_l = n[0] * l[0] + n[1] * l[1] + n[2] * l[2];
                let falloff = reference / dist;
                diffuse[x] = n_dot_l.max(0.0) * (falloff * falloff);
                let ve =
                    (to_eye[0] * to_eye[0] + to_eye[1] * to_eye[1] + to_eye[2] * to_eye[2]).sqrt();
                let v = [to_eye[0] / ve, to_eye[1] / ve, to_eye[2] / ve];
                let h = [l[0] + v[0], l[1] + v[1], l[2] + v[2]];
                let hl = (h[0] * h[0] + h[1] * h[1] + h[2] * h[2]).sqrt();
                let h = [h[0] / hl, h[1] / hl, h[2] / hl];
                let ndh = n[0] * h[0] + n[1] * h[1] + n[2] * h[2];
                // Lit from behind, or no highlight: below every floor.
                n_dot_h[x] = if specular && n_dot_l > 0.0 {
                    ndh
                } else {
                    f32::NEG_INFINITY
                };
            }
        }
        // Pass 3: the highlight where it shows, vignetting, gamma and noise, in pixel order.
        // One noise stream per row.
        let mut rng = SplitMix(c.seed ^ (y as u64).wrapping_mul(0xd6e8_feb8_6659_fd93));
        let mut noise = Noise::new(&self.gauss);
        for x in 0..w {
            let px = &mut row[x * 3..x * 3 + 3];
            if !s.seen[x] {
                // Nothing seen: black (outside the tissue patch), noise included.
                for v in px.iter_mut() {
                    *v = quantize(0.0, sigma, &mut noise, &mut rng);
                }
                continue;
            }
            let n_dot_h = s.n_dot_h[x];
            let spec = if n_dot_h > spec_floor {
                p.specular * n_dot_h.powf(p.shininess)
            } else {
                0.0
            };
            let diffuse = s.diffuse[x];
            // Lens vignetting, darkest in the corners.
            let (dx, dy) = (x as f32 - cx, y as f32 - cy);
            let vignette = 1.0 - p.vignetting * (dx * dx + dy * dy) / r_max2;
            for (v, channel) in px.iter_mut().zip(&s.albedo) {
                let radiance =
                    vignette * (channel[x] * (p.ambient + (1.0 - p.ambient) * diffuse) + spec);
                let lut = (radiance.clamp(0.0, 1.0) * (GAMMA_LUT - 1) as f32 + 0.5) as i32 as usize;
                *v = quantize(self.gamma[lut], sigma, &mut noise, &mut rng);
            }
        }
    }
}

/// One row's intermediate arrays (structure of arrays, so the lighting pass vectorises).
struct RowScratch {
    seen: Vec<bool>,
    pos: [Vec<f32>; 3],
    n: [Vec<f32>; 3],
    albedo: [Vec<f32>; 3],
    diffuse: Vec<f32>,
    n_dot_h: Vec<f32>,
}

impl RowScratch {
    fn new(w: usize) -> Self {
        let v = || vec![0.0f32; w];
        RowScratch {
            seen: vec![false; w],
            pos: [v(), v(), v()],
            n: [v(), v(), v()],
            albedo: [v(), v(), v()],
            diffuse: v(),
            n_dot_h: v(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::Scene;
    use crate::Params;
    use misslam_framework::nalgebra::Vector3;

    /// The one-pass shading of a pixel at a time, as the rows were shaded before the passes
    /// (session 26), written with nalgebra's vector operations: the reference.
    #[allow(clippy::too_many_arguments)]
    fn reference_row(
        ph: &Phantom,
        r: &Raster,
        vertices: &[[f32; 3]],
        normals: &[[f32; 3]],
        c: &RowShading,
        y: usize,
        row: &mut [u8],
    ) {
        let p = &ph.params;
        let w = p.width as usize;
        let (cx, cy) = c.centre;
        let mut rng = SplitMix(c.seed ^ (y as u64).wrapping_mul(0xd6e8_feb8_6659_fd93));
        let mut noise = Noise::new(&ph.gauss);
        for x in 0..w {
            let i = y * w + x;
            let px = &mut row[x * 3..x * 3 + 3];
            let Some(t) = ph.triangles.get(r.triangle[i] as usize) else {
                for v in px.iter_mut() {
                    *v = quantize(0.0, c.sigma, &mut noise, &mut rng);
                }
                continue;
            };
            let b = r.bary[i];
            let lerp = |attr: &[[f32; 3]]| {
                let a = t.map(|k| attr[k as usize]);
                [0, 1, 2].map(|k| b[0] * a[0][k] + b[1] * a[1][k] + b[2] * a[2][k])
            };
            let (pos, n, rest) = (lerp(vertices), lerp(normals), lerp(&ph.rest));
            let a = ph.albedo.sample(rest, lerp(&ph.rest_normals));
            let pos = Vector3::from(pos);
            let mut n = Vector3::from(n).normalize();
            if n.dot(&(c.eye.coords - pos)) < 0.0 {
                n = -n;
            }
            let to_light = c.light.coords - pos;
            let dist = to_light.norm();
            let l = to_light / dist;
            let n_dot_l = n.dot(&l);
            let diffuse = n_dot_l.max(0.0) * (c.reference / dist).powi(2);
            let spec = if p.specular > 0.0 && n_dot_l > 0.0 {
                let v = (c.eye.coords - pos).normalize();
                let n_dot_h = n.dot(&(l + v).normalize());
                if n_dot_h > c.spec_floor {
                    p.specular * n_dot_h.powf(p.shininess)
                } else {
                    0.0
                }
            } else {
                0.0
            };
            let (dx, dy) = (x as f32 - cx, y as f32 - cy);
            let vignette = 1.0 - p.vignetting * (dx * dx + dy * dy) / c.r_max2;
            for k in 0..3 {
                let radiance = vignette * (a[k] * (p.ambient + (1.0 - p.ambient) * diffuse) + spec);
                let lut = ((radiance.clamp(0.0, 1.0) * (GAMMA_LUT - 1) as f32).round()) as usize;
                let noisy = if c.sigma > 0.0 {
                    ph.gamma[lut] + c.sigma * noise.next(&mut rng)
                } else {
                    ph.gamma[lut]
                };
                px[k] = noisy.clamp(0.0, 255.0).round() as u8;
            }
        }
    }

    /// A bumpy sheet as an OBJ file (a template mesh: triplanar albedo, face-averaged normals).
    fn sheet_obj() -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("misslam-shade-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("sheet.obj");
        let n = 30;
        let mut s = String::new();
        for j in 0..n {
            for i in 0..n {
                let (x, y) = (i as f32 * 2.0 - 29.0, j as f32 * 2.0 - 29.0);
                let z = 6.0 * (-(x * x + y * y) / 300.0).exp() + 2.0 * (x / 7.0).sin();
                s += &format!("v {x} {y} {z}\n");
            }
        }
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = j * n + i + 1;
                s += &format!(
                    "f {a} {} {}\nf {a} {} {}\n",
                    a + 1,
                    a + n + 1,
                    a + n + 1,
                    a + n
                );
            }
        }
        std::fs::write(&path, s).unwrap();
        path
    }

    #[test]
    fn the_row_passes_shade_each_pixel_as_the_one_pass_reference_does() {
        let base = Params {
            width: 96,
            height: 72,
            focal_px: 100.0,
            ..Params::default()
        };
        let sheet = sheet_obj();
        let cases = [
            // The default look: highlight, vignetting, noise.
            ("heart", base.clone()),
            // Close enough for a strong highlight, no noise.
            (
                "liver, near",
                Params {
                    scene: Scene::Liver,
                    distance_mm: 45.0,
                    noise_sigma: 0.0,
                    ..base.clone()
                },
            ),
            // Matte, heavy noise.
            (
                "kidney, matte",
                Params {
                    scene: Scene::Kidney,
                    specular: 0.0,
                    vignetting: 0.0,
                    noise_sigma: 9.0,
                    ..base.clone()
                },
            ),
            // A template mesh: triplanar albedo, and the view's edges see nothing.
            (
                "mesh",
                Params {
                    mesh: Some(sheet.clone()),
                    distance_mm: 60.0,
                    ..base.clone()
                },
            ),
        ];
        for (name, p) in cases {
            let mut ph = Phantom::new(p, 3).unwrap();
            let (w, h) = (ph.params.width as usize, ph.params.height as usize);
            let mut highlights = 0;
            let mut blank = 0;
            for frame in [0u64, 9] {
                let (vertices, normals, world_from_left) = ph.rasterize_at(ph.time(frame));
                let light = world_from_left * Point3::new(2.0, 0.0, 0.0);
                let eye = world_from_left * Point3::origin();
                let sigma = ph.params.noise_sigma;
                let got = ph.shade(&ph.left, &vertices, &normals, light, eye, 77, sigma);
                let c = ph.row_shading(light, eye, 77, sigma);
                let mut want = vec![0u8; w * h * 3];
                for (y, row) in want.chunks_exact_mut(w * 3).enumerate() {
                    reference_row(&ph, &ph.left, &vertices, &normals, &c, y, row);
                }
                assert!(got.data == want, "{name}, frame {frame}: the images differ");
                blank += ph.left.triangle.iter().filter(|&&t| t == u32::MAX).count();
                highlights += want.iter().filter(|&&v| v == 255).count();
            }
            // The cases reach what they are there for.
            match name {
                "mesh" => assert!(blank > 0, "{name}: every pixel sees the mesh"),
                "liver, near" => assert!(highlights > 0, "{name}: no highlight"),
                _ => {}
            }
        }
        if let Some(dir) = sheet.parent() {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}
