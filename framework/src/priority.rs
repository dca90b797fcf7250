//! Thread priorities: the pipelined levels' pools of the nodes that ask for a lower one
//! (`nice = N`, [`crate::graph::NodeSpec::nice`]) and the phantom's renderers ahead.

/// Lowers the calling thread's CPU priority to nice value `nice` (Linux: `setpriority` on a
/// thread id sets that thread's alone); a thread already at `nice` or lower keeps its own.
/// A refusal is logged, naming `who`, and the thread keeps its priority. Elsewhere than on
/// Linux it does nothing.
pub fn lower_thread_priority(nice: u32, who: &str) {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: `gettid`, `getpriority` and `setpriority` take no pointers and act on this
        // thread only.
        let (now, r) = unsafe {
            let tid = libc::gettid() as libc::id_t;
            let now = libc::getpriority(libc::PRIO_PROCESS, tid);
            let r = if (nice as libc::c_int) > now {
                libc::setpriority(libc::PRIO_PROCESS, tid, nice as libc::c_int)
            } else {
                0
            };
            (now, r)
        };
        if r != 0 {
            tracing::warn!(
                "{who}: could not lower a thread's priority from nice {now} to {nice}: {}",
                std::io::Error::last_os_error()
            );
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (nice, who);
}

/// The calling thread's nice value (Linux; 0 elsewhere).
pub fn thread_nice() -> i32 {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: as above.
        unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) }
    }
    #[cfg(not(target_os = "linux"))]
    0
}
