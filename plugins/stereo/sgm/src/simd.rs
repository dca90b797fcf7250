//! Which lane code runs: AVX-512 where the CPU has the extensions the wide kernels use
//! (checked at run time), else AVX2, else the portable code (SSE2 through autovectorisation).
//! All give identical output. Tests cap the level to check each path on a machine that has
//! the wider ones.

use std::sync::atomic::{AtomicU8, Ordering};

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

/// The widest level the kernels may use (tests lower it).
static CAP: AtomicU8 = AtomicU8::new(Level::Avx512 as u8);

/// Caps the lane code at `level` (for tests and benchmarks of the narrower paths); the CPU's
/// own support still applies. `Level::Avx512` lifts the cap.
#[doc(hidden)]
pub fn cap(level: Level) {
    CAP.store(level as u8, Ordering::Relaxed);
}

/// Forces the portable code even where AVX2 exists (`false`: no cap).
#[doc(hidden)]
pub fn force_portable(on: bool) {
    cap(if on { Level::Portable } else { Level::Avx512 });
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
    let cap = CAP.load(Ordering::Relaxed);
    let s = supported();
    if (s as u8) <= cap {
        s
    } else if cap >= Level::Avx2 as u8 {
        Level::Avx2
    } else {
        Level::Portable
    }
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
