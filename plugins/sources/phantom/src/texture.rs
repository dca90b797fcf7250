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

#[inline]
fn smooth(t: f32) -> f32 {
    t * t * (3.0 - 2.0 * t)
}

/// Value noise in [0, 1] with period 1 in both axes.
pub fn value_noise(x: f32, y: f32, seed: u32) -> f32 {
    let (fx, fy) = (x.floor(), y.floor());
    let (ix, iy) = (fx as i32, fy as i32);
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
    let (fx, fy) = (x.floor(), y.floor());
    let (ix, iy) = (fx as i32, fy as i32);
    let (tx, ty) = (x - fx, y - fy);
    let grad = |gx: i32, gy: i32, dx: f32, dy: f32| {
        let h = hash(
            (gx as u32).wrapping_mul(0x9e37_79b1)
                ^ hash((gy as u32) ^ seed.wrapping_mul(0x85eb_ca6b)),
        );
        let a = (h as f32 / u32::MAX as f32) * std::f32::consts::TAU;
        a.cos() * dx + a.sin() * dy
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
    let wx = x + 0.8 * vs * gradient_noise(x / (3.0 * vs), y / (3.0 * vs), s ^ 0x13);
    let wy = y + 0.8 * vs * gradient_noise(x / (3.0 * vs) + 5.3, y / (3.0 * vs), s ^ 0x17);
    let line = |scale: f32, width: f32, seed: u32| {
        let n = gradient_noise(wx / scale, wy / scale, seed)
            + 0.3 * gradient_noise(wx / (0.4 * scale), wy / (0.4 * scale), seed ^ 0x5);
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
