//! The sensor model: sRGB encoding, Gaussian noise drawn from a table, and deterministic
//! random streams (SplitMix64) seeded per frame, view and row.

pub(crate) fn to_srgb8(c: f32) -> u8 {
    (255.0 * c.clamp(0.0, 1.0).powf(1.0 / 2.2)).round() as u8
}

/// Entries of the linear-to-sRGB table (fine enough that no 8-bit level is skipped above 1 %).
pub(crate) const GAMMA_LUT: usize = 16384;

pub(crate) fn quantize(v: f32, sigma: f32, noise: &mut Noise, rng: &mut SplitMix) -> u8 {
    let noisy = if sigma > 0.0 {
        v + sigma * noise.next(rng)
    } else {
        v
    };
    // Round half up of a non-negative value: the same as `round` here, without the libm call.
    // Through i32: the value is in range, and one conversion instruction does it where `as u8`
    // adds the saturation's compares (NaN goes to 0 either way).
    (noisy.clamp(0.0, 255.0) + 0.5) as i32 as u8
}

/// Entries of the table of standard normal samples the sensor noise draws from.
pub(crate) const GAUSS_TABLE: usize = 1 << 16;

/// A table of standard normal samples (Box-Muller from a fixed seed): drawing noise is then one
/// table read per value, four values per random number.
pub(crate) fn gauss_table() -> Vec<f32> {
    let mut rng = SplitMix(0x6e6f_6973_6521);
    let mut t = Vec::with_capacity(GAUSS_TABLE);
    while t.len() < GAUSS_TABLE {
        let (u1, u2) = (rng.uniform(), rng.uniform());
        let radius = (-2.0 * u1.ln()).sqrt();
        let (s, c) = (std::f32::consts::TAU * u2).sin_cos();
        t.push(radius * c);
        t.push(radius * s);
    }
    t
}

/// Standard normal values drawn from [`gauss_table`].
pub(crate) struct Noise<'a> {
    table: &'a [f32],
    bits: u64,
    left: u32,
}

impl<'a> Noise<'a> {
    pub(crate) fn new(table: &'a [f32]) -> Self {
        Noise {
            table,
            bits: 0,
            left: 0,
        }
    }

    pub(crate) fn next(&mut self, rng: &mut SplitMix) -> f32 {
        if self.left == 0 {
            self.bits = rng.next_u64();
            self.left = 4;
        }
        let i = (self.bits & 0xffff) as usize;
        self.bits >>= 16;
        self.left -= 1;
        self.table[i]
    }
}

pub(crate) fn frame_seed(seed: u64, frame: u64, view: u64) -> u64 {
    let mut s = SplitMix(
        seed ^ frame.wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ view.wrapping_mul(0xbf58_476d_1ce4_e5b9),
    );
    s.next_u64()
}

/// SplitMix64: small, fast, deterministic.
pub(crate) struct SplitMix(pub(crate) u64);

impl SplitMix {
    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    pub(crate) fn uniform(&mut self) -> f32 {
        ((self.next_u64() >> 40) as f32 + 0.5) / (1u64 << 24) as f32
    }
}
