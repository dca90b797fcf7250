//! Which lane code runs: AVX-512 where the CPU has the extensions the wide kernels use
//! (checked at run time), else AVX2, else the portable code (SSE2 through autovectorisation).
//! All give identical output. Tests cap the level to check each path on a machine that has
//! the wider ones; the environment variable `MISSLAM_SIMD` (`avx512`, `avx2` or `portable`)
//! caps it for a whole run, to compare the paths on one machine or to rule one out.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::OnceLock;

/// A lane code, narrowest first.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Level {
    /// The portable code.
    Portable = 0,
    /// AVX2 and POPCNT.
    Avx2 = 1,
    /// AVX2 and the AVX-512 foundation, byte and word (BW), vector-length (VL) and 64-bit
    /// population count (VPOPCNTDQ) extensions: Intel Ice Lake and later servers, AMD Zen 4
    /// and later.
    Avx512 = 2,
}

/// No cap set by [`cap`]: `MISSLAM_SIMD` applies.
const UNSET: u8 = u8::MAX;

/// The widest level the kernels may use, as set by [`cap`] (tests and benchmarks lower it).
static CAP: AtomicU8 = AtomicU8::new(UNSET);

/// Caps the lane code at `level` (for tests and benchmarks of the narrower paths), over
/// `MISSLAM_SIMD`; the CPU's own support still applies. `Level::Avx512` lifts the cap.
#[doc(hidden)]
pub fn cap(level: Level) {
    CAP.store(level as u8, Ordering::Relaxed);
}

/// Removes the cap [`cap`] set: `MISSLAM_SIMD` applies again.
#[doc(hidden)]
pub fn uncap() {
    CAP.store(UNSET, Ordering::Relaxed);
}

/// A level by its name in `MISSLAM_SIMD`.
pub fn parse_level(s: &str) -> Result<Level, String> {
    match s.trim().to_ascii_lowercase().as_str() {
        "avx512" => Ok(Level::Avx512),
        "avx2" => Ok(Level::Avx2),
        "portable" => Ok(Level::Portable),
        _ => Err(format!("`{s}` is not one of avx512, avx2, portable")),
    }
}

/// The cap `MISSLAM_SIMD` sets (none when unset; a wrong value is said once and ignored).
fn env_cap() -> Level {
    static ENV: OnceLock<Level> = OnceLock::new();
    *ENV.get_or_init(|| match std::env::var("MISSLAM_SIMD") {
        Ok(v) => parse_level(&v).unwrap_or_else(|e| {
            tracing::warn!("MISSLAM_SIMD: {e}; ignored (the widest lane code the CPU has runs)");
            Level::Avx512
        }),
        Err(_) => Level::Avx512,
    })
}

/// Forces the portable code even where AVX2 exists (`false`: no cap).
#[doc(hidden)]
pub fn force_portable(on: bool) {
    if on {
        cap(Level::Portable);
    } else {
        uncap();
    }
}

/// The widest level this CPU supports, whatever the cap.
pub fn supported() -> Level {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if !(has!("avx2") && has!("popcnt")) {
            Level::Portable
        } else if has!("avx512f") && has!("avx512bw") && has!("avx512vl") && has!("avx512vpopcntdq")
        {
            Level::Avx512
        } else {
            Level::Avx2
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        Level::Portable
    }
}

/// The level the kernels run at: what the CPU supports, at most the cap.
#[inline]
pub fn level() -> Level {
    let cap = match CAP.load(Ordering::Relaxed) {
        UNSET => env_cap(),
        0 => Level::Portable,
        1 => Level::Avx2,
        _ => Level::Avx512,
    };
    supported().min(cap)
}

/// True when the AVX2 (and POPCNT) code may run.
#[inline]
pub(crate) fn avx2() -> bool {
    level() >= Level::Avx2
}

/// True when the AVX-512 code may run (AVX2 too, then).
#[inline]
pub(crate) fn avx512() -> bool {
    level() >= Level::Avx512
}
