//! The pipelined schedule (`[graph] pipeline = N`, N > 1): one thread per level, each taking the
//! frames in order from the level before it, with at most N frames in the graph at once, so
//! frame f + 1 is in the early levels while frame f is in the late ones. Every node still sees
//! its frames in order and with the same inputs, so the outputs are those of the serial
//! schedule; the run's throughput approaches that of its slowest level instead of the sum of
//! all of them, given the cores.
//!
//! Each level runs its nodes' parallel work (rayon) on a thread pool of its own: on one shared
//! pool the bottleneck level waited behind the others' tasks (on 2 cores, 320x240: 39 to 41 ms
//! between frames against 31 to 33 with a pool each). A pool has `[graph] level_threads`
//! threads, by default half the cores ([`crate::graph::Graph::level_pool_threads`]): pools of
//! all the cores each oversubscribed a 16-core machine. A node may ask its level's pool for
//! another number (`threads = N` in its table, [`crate::graph::NodeSpec::threads`]), and for a
//! lower CPU priority (`nice = N`, [`crate::graph::NodeSpec::nice`]): a level whose nodes all ask
//! for it runs at the lowest value they ask, so that the levels on the critical path take
//! the cores first and it takes what they leave.
//!
//! A frame that ends the run (end of the stream, or a failure under `on_error = "abort"`) stops
//! it at that frame: the frames before it complete, and the ones after it that earlier levels
//! had already taken are dropped unfinished. Those earlier levels may thus have run up to N - 1
//! frames past the last one the run counts (`timing_ms.<node>.frames` shows it), where the
//! serial schedule stops them at the failed frame.

use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};

use super::{run_level, Collector, Env, FrameOutcome, FrameState, Frames, Slot};
use crate::graph::ErrorPolicy;

/// What the pipeline runs.
pub(crate) struct Schedule<'a> {
    /// The graph's levels, as ranges of the slots.
    pub(crate) levels: &'a [Range<usize>],
    pub(crate) frames: &'a Frames,
    /// Frames in the graph at once (at least 2).
    pub(crate) in_flight: u32,
    /// Threads of each level's pool.
    pub(crate) level_threads: &'a [usize],
    /// Nice value of each level's pool's threads (0: the process's priority).
    pub(crate) level_nice: &'a [u32],
    pub(crate) policy: ErrorPolicy,
}

/// Runs the frames through the levels, one thread per level, handing each completed frame to
/// `collector` on the calling thread, in order.
pub(crate) fn run(slots: &mut [Slot], schedule: &Schedule, env: &Env, collector: &mut Collector) {
    // The ordinal of the frame the run stops at (none yet: u64::MAX).
    let stop_at = AtomicU64::new(u64::MAX);
    let mut parts = Vec::with_capacity(schedule.levels.len());
    let mut rest = slots;
    for level in schedule.levels {
        let (part, tail) = rest.split_at_mut(level.len());
        parts.push((level.start, part));
        rest = tail;
    }
    // A token per frame allowed in the graph: the first level takes one before it starts a
    // frame, and the collector gives it back when the frame leaves the graph.
    let (give_token, tokens) = sync_channel::<()>(schedule.in_flight as usize);
    for _ in 0..schedule.in_flight {
        let _ = give_token.send(());
    }
    std::thread::scope(|scope| {
        let mut upstream: Option<Receiver<FrameState>> = None;
        let mut tokens = Some(tokens);
        let pools = schedule.level_threads.iter().zip(schedule.level_nice);
        for ((offset, part), (&threads, &nice)) in parts.into_iter().zip(pools) {
            // A rendezvous channel: a level hands a frame on when the next one takes it.
            let (tx, rx) = sync_channel::<FrameState>(0);
            let input = match upstream.replace(rx) {
                Some(rx) => Input::Level(rx),
                None => Input::Source(tokens.take().expect("one first level")),
            };
            let stop_at = &stop_at;
            scope.spawn(move || {
                let level = Level {
                    slots: part,
                    offset,
                    env,
                    policy: schedule.policy,
                    stop_at,
                };
                // The level's parallel work runs on a pool of its own: on the shared pool a
                // level would wait behind the tasks of the others (fusion's short parallel
                // stages queued behind a depth pass), where with a pool each the system's
                // scheduler shares the cores among the levels.
                let mut pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .thread_name(move |i| format!("misslam-level{offset}-{i}"));
                if nice > 0 {
                    pool = pool.start_handler(move |_| {
                        crate::priority::lower_thread_priority(nice, "a pipelined level's pool")
                    });
                }
                let pool = pool.build();
                match pool {
                    Ok(pool) => pool.install(|| level.serve(input, schedule.frames, tx)),
                    Err(e) => {
                        tracing::warn!(
                            "no thread pool of its own for a level ({e}): it shares the global one"
                        );
                        level.serve(input, schedule.frames, tx);
                    }
                }
            });
        }
        let Some(done) = upstream else {
            return;
        };
        for state in done {
            let ordinal = state.info.ordinal;
            if collector.take(state) {
                stop_at.fetch_min(ordinal, Ordering::SeqCst);
                break;
            }
            let _ = give_token.send(());
        }
        // Dropping the token sender and the last receiver ends the first level's wait for a
        // token and makes the last level's next hand-over fail: each thread ends, and with it
        // the channel of the level after it.
        drop(give_token);
    });
}

/// Where a level takes its frames from.
enum Input {
    /// The first level makes them, one per token.
    Source(Receiver<()>),
    /// The others take them from the level before.
    Level(Receiver<FrameState>),
}

struct Level<'s, 'e> {
    slots: &'s mut [Slot],
    offset: usize,
    env: &'e Env<'e>,
    policy: ErrorPolicy,
    stop_at: &'e AtomicU64,
}

impl Level<'_, '_> {
    /// Runs the level on each frame in turn and hands it on, until the frames end or the next
    /// level stops taking them.
    fn serve(mut self, input: Input, frames: &Frames, output: SyncSender<FrameState>) {
        match input {
            Input::Source(tokens) => {
                let mut ordinal = 0u64;
                while frames.limit.is_none_or(|n| ordinal < n) && tokens.recv().is_ok() {
                    if ordinal > self.stop_at.load(Ordering::SeqCst) {
                        break;
                    }
                    let Some(state) = self.step(frames.state(ordinal)) else {
                        break;
                    };
                    if output.send(state).is_err() {
                        break;
                    }
                    ordinal += 1;
                }
            }
            Input::Level(input) => {
                for state in input {
                    let Some(state) = self.step(state) else {
                        continue;
                    };
                    if output.send(state).is_err() {
                        break;
                    }
                }
            }
        }
    }

    /// Runs this level on a frame that is still going and passes a finished one on untouched;
    /// drops a frame past the one the run stops at.
    fn step(&mut self, mut state: FrameState) -> Option<FrameState> {
        let ordinal = state.info.ordinal;
        if ordinal > self.stop_at.load(Ordering::SeqCst) {
            return None;
        }
        if matches!(state.outcome, FrameOutcome::Done) {
            run_level(self.slots, self.offset, &mut state, self.env);
            let stops = match state.outcome {
                FrameOutcome::Done => false,
                FrameOutcome::EndOfStream => true,
                FrameOutcome::Failed { .. } => self.policy == ErrorPolicy::Abort,
            };
            if stops {
                // Earlier levels stop taking new frames now, not when it leaves the graph.
                self.stop_at.fetch_min(ordinal, Ordering::SeqCst);
            }
        }
        Some(state)
    }
}
