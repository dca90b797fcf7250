//! Tissue-like albedo as a function of a point on the rest surface (mm), so texture moves with
//! the tissue: a pink-red base with fine detail, a branching network of darker vessels, and
//! optional low-texture patches where detail fades out.

/// 32-bit integer hash (lowbias32), deterministic on every platform.
#[inline]
fn hash(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

#[inline]
fn lattice(ix: i32, iy: i32, seed: u32) -> f32 {
    let h = hash(
        (ix as u32).wrapping_mul(0x9e37_79b1) ^ hash((iy as u32) ^ seed.wrapping_mul(0x85eb_ca6b)),
    );
    h as f32 / u32::MAX as f32
}

/// `x.floor()` as an integer and as a float, for |x| < 2^31 (texture coordinates are a few
/// thousand at most): the same values as `floor`, which without SSE4.1 is a libm call.
#[inline]
fn floor(x: f32) -> (i32, f32) {
    let i = x as i32;
    let i = if (i as f32) > x { i - 1 } else { i };
    (i, i as f32)
}

#[inline]
fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Value noise in [0, 1] with period 1 in both axes.
pub fn value_noise(x: f32, y: f32, seed: u32) -> f32 {
    let ((ix, fx), (iy, fy)) = (floor(x), floor(y));
    let (tx, ty) = (smooth(x - fx), smooth(y - fy));
    let a = lattice(ix, iy, seed);
    let b = lattice(ix + 1, iy, seed);
    let c = lattice(ix, iy + 1, seed);
    let d = lattice(ix + 1, iy + 1, seed);
    let top = a + (b - a) * tx;
    let bottom = c + (d - c) * tx;
    top + (bottom - top) * ty
}

/// Gradient (Perlin) noise in about [-1, 1]: smooth, with curved zero crossings.
pub fn gradient_noise(x: f32, y: f32, seed: u32) -> f32 {
    gradient_noise_with(x, y, seed, &mut GradientCache::new())
}

/// The unit gradient of lattice point (gx, gy): (cos a, sin a) of an angle hashed from it.
#[inline]
fn lattice_gradient(gx: i32, gy: i32, seed: u32) -> [f32; 2] {
    let h = hash(
        (gx as u32).wrapping_mul(0x9e37_79b1) ^ hash((gy as u32) ^ seed.wrapping_mul(0x85eb_ca6b)),
    );
    let a = (h as f32 / u32::MAX as f32) * std::f32::consts::TAU;
    [a.cos(), a.sin()]
}

/// Entries of a [`GradientCache`].
const GRADIENT_CACHE: usize = 256;

/// The lattice gradients last computed, direct-mapped by lattice point and seed. Neighbouring
/// samples of a texture row fall in the same lattice cells (a cell spans 8 to 120 texels of the
/// atlas), so most of [`gradient_noise`]'s cosines and sines are read back instead of computed;
/// a value read back is the one computed, so the noise is the same bits.
pub struct GradientCache {
    keys: [(i32, i32, u32); GRADIENT_CACHE],
    valid: [bool; GRADIENT_CACHE],
    gradients: [[f32; 2]; GRADIENT_CACHE],
}

impl Default for GradientCache {
    fn default() -> Self {
        Self::new()
    }
}

impl GradientCache {
    /// An empty cache.
    pub fn new() -> Self {
        GradientCache {
            keys: [(0, 0, 0); GRADIENT_CACHE],
            valid: [false; GRADIENT_CACHE],
            gradients: [[0.0; 2]; GRADIENT_CACHE],
        }
    }

    #[inline]
    fn gradient(&mut self, gx: i32, gy: i32, seed: u32) -> [f32; 2] {
        let slot = ((gx as u32).wrapping_mul(0x9e37_79b1)
            ^ (gy as u32).wrapping_mul(0x85eb_ca6b)
            ^ seed.wrapping_mul(0xc2b2_ae35))
            >> 24;
        let slot = slot as usize % GRADIENT_CACHE;
        let key = (gx, gy, seed);
        if !(self.valid[slot] && self.keys[slot] == key) {
            self.keys[slot] = key;
            self.valid[slot] = true;
            self.gradients[slot] = lattice_gradient(gx, gy, seed);
        }
        self.gradients[slot]
    }
}

/// [`gradient_noise`], reading the lattice gradients through `cache`.
pub fn gradient_noise_with(x: f32, y: f32, seed: u32, cache: &mut GradientCache) -> f32 {
    let ((ix, fx), (iy, fy)) = (floor(x), floor(y));
    let (tx, ty) = (x - fx, y - fy);
    let mut grad = |gx: i32, gy: i32, dx: f32, dy: f32| {
        let [c, s] = cache.gradient(gx, gy, seed);
        c * dx + s * dy
    };
    let fade = |t: f32| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let (u, v) = (fade(tx), fade(ty));
    let n00 = grad(ix, iy, tx, ty);
    let n10 = grad(ix + 1, iy, tx - 1.0, ty);
    let n01 = grad(ix, iy + 1, tx, ty - 1.0);
    let n11 = grad(ix + 1, iy + 1, tx - 1.0, ty - 1.0);
    let top = n00 + (n10 - n00) * u;
    let bottom = n01 + (n11 - n01) * u;
    std::f32::consts::SQRT_2 * (top + (bottom - top) * v)
}

/// Fractal sum of `octaves` noise layers, in [0, 1].
pub fn fbm(x: f32, y: f32, octaves: u32, seed: u32) -> f32 {
    let (mut sum, mut amp, mut freq, mut norm) = (0.0, 1.0, 1.0, 0.0);
    for o in 0..octaves {
        sum += amp * value_noise(x * freq, y * freq, seed.wrapping_add(o * 1013));
        norm += amp;
        amp *= 0.5;
        freq *= 2.03;
    }
    sum / norm
}

/// Texture settings.
#[derive(Clone, Copy, Debug)]
pub struct TextureParams {
    /// Seed of every noise layer.
    pub seed: u32,
    /// Vessel spacing, mm (larger: fewer, wider vessels).
    pub vessel_scale_mm: f32,
    /// Fraction of the surface (0..1) covered by low-texture patches.
    pub low_texture_fraction: f32,
}

/// Albedo (linear 0..1 RGB) at a rest-surface point (x, y) in mm.
pub fn albedo(x: f32, y: f32, p: &TextureParams) -> [f32; 3] {
    albedo_with(x, y, p, &mut GradientCache::new())
}

/// [`albedo`], its gradient noise read through `cache` (the same values; faster over
/// neighbouring points, as when an atlas is baked row by row).
pub fn albedo_with(x: f32, y: f32, p: &TextureParams, cache: &mut GradientCache) -> [f32; 3] {
    let s = p.seed;
    // Low-texture mask: large blobs where detail fades.
    let blob = fbm(x / 25.0, y / 25.0, 3, s ^ 0x51);
    let low = if p.low_texture_fraction <= 0.0 {
        0.0
    } else {
        let threshold = 1.0 - p.low_texture_fraction;
        ((blob - threshold) / 0.08).clamp(0.0, 1.0)
    };
    let detail = 1.0 - low;
    // Fine mottling of the mucosa.
    let fine = fbm(x / 0.8, y / 0.8, 4, s ^ 0x77) - 0.5;
    // Vessels: zero crossings of domain-warped gradient noise are curved, branching lines.
    let vs = p.vessel_scale_mm.max(0.5);
    let wx = x + 0.8 * vs * gradient_noise_with(x / (3.0 * vs), y / (3.0 * vs), s ^ 0x13, cache);
    let wy =
        y + 0.8 * vs * gradient_noise_with(x / (3.0 * vs) + 5.3, y / (3.0 * vs), s ^ 0x17, cache);
    let mut line = |scale: f32, width: f32, seed: u32| {
        let n = gradient_noise_with(wx / scale, wy / scale, seed, cache)
            + 0.3 * gradient_noise_with(wx / (0.4 * scale), wy / (0.4 * scale), seed ^ 0x5, cache);
        // Distance to the zero crossing in noise units, about mm / scale.
        (1.0 - (n.abs() * scale / width)).clamp(0.0, 1.0)
    };
    let trunk = line(vs * 6.0, 0.5 * vs, s ^ 0x91);
    let branch = line(vs * 2.5, 0.22 * vs, s ^ 0xa3) * 0.8;
    let capillary = line(vs, 0.08 * vs, s ^ 0xb7) * 0.45;
    let vessel = trunk.max(branch).max(capillary) * detail;
    let base = [0.50, 0.11, 0.11];
    let vein = [0.20, 0.015, 0.035];
    let mottle = 1.0 + 0.45 * fine * detail;
    let mut c = [0.0; 3];
    for k in 0..3 {
        let b = base[k] * mottle;
        c[k] = (b + (vein[k] - b) * vessel.powf(0.7)).clamp(0.0, 1.0);
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_deterministic_and_bounded() {
        for i in 0..1000 {
            let (x, y) = (i as f32 * 0.37, i as f32 * 0.11);
            let v = fbm(x, y, 4, 7);
            assert!((0.0..=1.0).contains(&v));
            assert_eq!(v, fbm(x, y, 4, 7));
        }
        assert_ne!(value_noise(0.5, 0.5, 1), value_noise(0.5, 0.5, 2));
    }

    #[test]
    fn the_integer_floor_is_floor() {
        for i in -40_000..40_000 {
            let x = i as f32 * 0.013_7;
            for x in [x, x.floor(), -x.floor(), x + 1e-3] {
                let (k, f) = floor(x);
                // Equal values (the floor of -0 is +0 here, which no sum below tells apart).
                assert_eq!(f, x.floor(), "{x}");
                assert_eq!(k as f32, x.floor(), "{x}");
            }
        }
    }

    #[test]
    fn cached_gradients_give_the_same_bits() {
        // One cache over a texture row's worth of points, several seeds and scales, with the
        // slots' collisions that brings: every value is the uncached one, bit for bit.
        let mut cache = GradientCache::new();
        let p = TextureParams {
            seed: 11,
            vessel_scale_mm: 1.3,
            low_texture_fraction: 0.3,
        };
        for j in 0..40 {
            for i in 0..400 {
                let (x, y) = (i as f32 * 0.1 - 20.0, j as f32 * 0.37 - 7.0);
                for (scale, seed) in [(0.5f32, 1u32), (2.0, 2), (7.0, 0x13)] {
                    let a = gradient_noise_with(x / scale, y / scale, seed, &mut cache);
                    assert_eq!(
                        a.to_bits(),
                        gradient_noise(x / scale, y / scale, seed).to_bits()
                    );
                }
                let c = albedo_with(x, y, &p, &mut cache);
                assert_eq!(c.map(f32::to_bits), albedo(x, y, &p).map(f32::to_bits));
            }
        }
    }

    #[test]
    fn a_slot_shared_by_two_seeds_holds_the_gradient_of_each() {
        // Two seeds whose entries for the same lattice point share a slot: each read must
        // recompute the other's, not return it.
        let slot = |seed: u32| (seed.wrapping_mul(0xc2b2_ae35) >> 24) as usize % GRADIENT_CACHE;
        let other = (2..100_000u32).find(|&s| slot(s) == slot(1)).unwrap();
        let mut cache = GradientCache::new();
        for _ in 0..3 {
            for seed in [1, other] {
                let a = gradient_noise_with(0.3, 0.6, seed, &mut cache);
                assert_eq!(a.to_bits(), gradient_noise(0.3, 0.6, seed).to_bits());
            }
        }
        assert_ne!(gradient_noise(0.3, 0.6, 1), gradient_noise(0.3, 0.6, other));
    }

    #[test]
    fn low_texture_patches_reduce_contrast() {
        let textured = TextureParams {
            seed: 3,
            vessel_scale_mm: 2.0,
            low_texture_fraction: 0.0,
        };
        let flat = TextureParams {
            low_texture_fraction: 1.0,
            ..textured
        };
        let spread = |p: &TextureParams| {
            let v: Vec<f32> = (0..400)
                .map(|i| albedo((i % 20) as f32 * 0.7, (i / 20) as f32 * 0.7, p)[1])
                .collect();
            let m = v.iter().sum::<f32>() / v.len() as f32;
            v.iter().map(|x| (x - m).powi(2)).sum::<f32>() / v.len() as f32
        };
        assert!(spread(&flat) < 0.05 * spread(&textured));
    }
}
