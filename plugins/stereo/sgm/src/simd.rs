//! Which lane code runs: AVX2 when the CPU has it (checked at run time), else the portable
//! code (SSE2 through autovectorisation). Tests switch the portable path on to check it on
//! machines that have AVX2.

use std::sync::atomic::{AtomicBool, Ordering};

static PORTABLE: AtomicBool = AtomicBool::new(false);

/// Forces the portable code even where AVX2 exists (both give identical output; for tests
/// and benchmarks of the fallback).
#[doc(hidden)]
pub fn force_portable(on: bool) {
    PORTABLE.store(on, Ordering::Relaxed);
}

/// True when the AVX2 (and POPCNT) code may run.
#[inline]
pub(crate) fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        !PORTABLE.load(Ordering::Relaxed)
            && std::arch::is_x86_feature_detected!("avx2")
            && std::arch::is_x86_feature_detected!("popcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}
