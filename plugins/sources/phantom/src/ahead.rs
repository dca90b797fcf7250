//! `render_threads`: renderers ahead of the graph, each a [`Phantom`] of its own on a thread of
//! its own, handing their frames to the node over bounded channels; `prerender_frames`: frames
//! rendered before the first one is handed out.

use crate::{Phantom, PhantomFrame, PhantomNode};
use misslam_framework::priority::lower_thread_priority;

/// Renderers on threads of their own, each rendering every `n`-th frame from its own first
/// one (`render_threads`); the node takes their frames in turn.
pub(crate) struct Ahead {
    /// A number of its own in this process, in its threads' names (`ph{id} render {k}`).
    id: u32,
    /// The first frame: renderer k renders first + k, first + k + n, ...
    first: u64,
    /// The next frame index the renderers deliver.
    next: u64,
    /// Per renderer: its frames, `None` past the end of the sequence.
    rx: Vec<std::sync::mpsc::Receiver<Option<PhantomFrame>>>,
}

impl Ahead {
    /// Starts `n` renderers, clones of `phantom`, at frame `first`. Each renders on a
    /// one-thread pool of its own at nice value `nice` (`Params::render_nice`): the rows of its
    /// frames never wait in the shared pool's queue in front of the graph's stages.
    pub(crate) fn start(
        phantom: &Phantom,
        first: u64,
        n: usize,
        nice: u32,
    ) -> Result<Ahead, String> {
        static STARTED: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
        let id = STARTED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut rx = Vec::with_capacity(n);
        for k in 0..n {
            let mut phantom = phantom.clone();
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .thread_name(move |_| format!("ph{id} render {k}"))
                .start_handler(move |_| lower_thread_priority(nice, "source.phantom renderer"))
                .build()
                .map_err(|e| format!("could not start a phantom renderer: {e}"))?;
            // One frame waiting and one being rendered, per renderer.
            let (tx, r) = std::sync::mpsc::sync_channel(1);
            // This thread waits on the pool's one worker, which renders; a panic there comes
            // back here, ends the thread, and the node hears that the renderer stopped.
            std::thread::Builder::new()
                .name(format!("ph{id} ahead {k}"))
                .spawn(move || {
                    let mut index = first + k as u64;
                    loop {
                        let frame = pool.install(|| phantom.render(index));
                        let end = frame.is_none();
                        // The node hung up (dropped or fell back): stop.
                        if tx.send(frame).is_err() || end {
                            return;
                        }
                        index += n as u64;
                    }
                })
                .map_err(|e| format!("could not start a phantom renderer: {e}"))?;
            rx.push(r);
        }
        tracing::info!(
            "source.phantom: {n} renderers ahead from frame {first}, threads `ph{id} render 0..{n}` at nice {nice}"
        );
        Ok(Ahead {
            id,
            first,
            next: first,
            rx,
        })
    }

    /// Frame `index` from its renderer; `Err` when the renderers are not at that frame (the
    /// graph skipped one) or one of them stopped.
    pub(crate) fn take(&mut self, index: u64) -> Result<Option<PhantomFrame>, String> {
        if index != self.next {
            return Err(format!(
                "the graph asked for frame {index}, the renderers were at {}",
                self.next
            ));
        }
        let k = ((index - self.first) % self.rx.len() as u64) as usize;
        let frame = self.rx[k].recv().map_err(|_| {
            format!(
                "the renderer of frame {index} (thread `ph{} render {k}`) stopped",
                self.id
            )
        })?;
        self.next += 1;
        Ok(frame)
    }
}

/// Frames rendered up front, handed out in order.
pub(crate) struct Prerendered {
    /// The index of the next frame held.
    next: u64,
    frames: std::collections::VecDeque<PhantomFrame>,
}

impl Prerendered {
    /// Renders frames `first .. first + n` (fewer where the sequence ends) on the pool's
    /// threads, each worker with a clone of `phantom`.
    fn render(phantom: &Phantom, first: u64, n: u64) -> Prerendered {
        use rayon::prelude::*;
        let t = std::time::Instant::now();
        let rendered: Vec<Option<PhantomFrame>> = (first..first + n)
            .into_par_iter()
            .map_init(|| phantom.clone(), |p, i| p.render(i))
            .collect();
        let frames: std::collections::VecDeque<_> = rendered.into_iter().map_while(|f| f).collect();
        tracing::info!(
            "source.phantom: {} frames rendered up front in {:.2} s",
            frames.len(),
            t.elapsed().as_secs_f64()
        );
        Prerendered {
            next: first,
            frames,
        }
    }

    /// Frame `index` if it is the next one held; `Err` when the graph asked for another.
    fn take(&mut self, index: u64) -> Result<Option<PhantomFrame>, String> {
        if index != self.next {
            return Err(format!(
                "the graph asked for frame {index}, the frames rendered up front were at {}",
                self.next
            ));
        }
        self.next += 1;
        Ok(self.frames.pop_front())
    }
}

impl PhantomNode {
    /// Frame `index`: from the frames rendered up front while they last, then from the
    /// renderers ahead where they run and are at that frame, else rendered here (a logged
    /// fall-back for the rest of the run).
    pub(crate) fn frame(&mut self, index: u64) -> Option<PhantomFrame> {
        let pre = u64::from(self.phantom.params.prerender_frames);
        if pre > 0 {
            let held = self
                .prerendered
                .get_or_insert_with(|| Prerendered::render(&self.phantom, index, pre));
            match held.take(index) {
                Ok(Some(frame)) => return Some(frame),
                // All handed out (or the sequence ended): go on as `render_threads` says.
                Ok(None) => {}
                Err(e) => {
                    tracing::warn!("source.phantom: {e}; rendering each frame when asked");
                    self.phantom.params.render_threads = 1;
                }
            }
            self.phantom.params.prerender_frames = 0;
            self.prerendered = None;
        }
        let n = self.phantom.params.render_threads as usize;
        if n > 1 && self.ahead.is_none() {
            match Ahead::start(&self.phantom, index, n, self.phantom.params.render_nice) {
                Ok(a) => self.ahead = Some(a),
                Err(e) => {
                    tracing::warn!("source.phantom: {e}; rendering each frame when asked");
                    self.phantom.params.render_threads = 1;
                }
            }
        }
        if let Some(a) = &mut self.ahead {
            match a.take(index) {
                Ok(frame) => return frame,
                Err(e) => {
                    tracing::warn!("source.phantom: {e}; rendering each frame when asked");
                    self.ahead = None;
                    self.phantom.params.render_threads = 1;
                }
            }
        }
        self.phantom.render(index)
    }
}

#[cfg(test)]
mod tests {
    use crate::*;

    fn small(render_threads: u32) -> Params {
        Params {
            width: 64,
            height: 48,
            focal_px: 70.0,
            frames: 7,
            render_threads,
            ..Params::default()
        }
    }

    fn same(a: &PhantomFrame, b: &PhantomFrame) -> bool {
        let bits = |m: &FloatMap| m.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        a.stereo.index == b.stereo.index
            && a.stereo.left.data == b.stereo.left.data
            && a.stereo.right.data == b.stereo.right.data
            && bits(&a.depth.map) == bits(&b.depth.map)
            && a.pose.world_from_camera == b.pose.world_from_camera
    }

    /// A node on the phantom of `p` (seed 3), as the registry builds it.
    fn node_of(p: Params) -> PhantomNode {
        let phantom = Phantom::new(p, 3).unwrap();
        let rest = Arc::new(phantom.rest_mesh());
        PhantomNode {
            phantom,
            rest,
            ahead: None,
            prerendered: None,
        }
    }

    #[test]
    fn renderers_ahead_deliver_the_same_frames_and_fall_back_on_a_skip() {
        let mut reference = Phantom::new(small(1), 3).unwrap();
        let node = |n| node_of(small(n));
        // Three renderers from frame 2 to the end of the sequence.
        let mut ahead = node(3);
        for i in 2..7 {
            let want = reference.render(i).unwrap();
            let got = ahead.frame(i).expect("a frame before the end");
            assert!(same(&got, &want), "frame {i}");
            assert!(ahead.ahead.is_some(), "frame {i} came from the renderers");
        }
        assert!(ahead.frame(7).is_none(), "the stream ends after `frames`");
        // A skipped frame: the renderers stop and the node renders, still the same frames.
        let mut skip = node(2);
        for i in [0, 1, 4, 5] {
            let got = skip.frame(i).unwrap();
            assert!(same(&got, &reference.render(i).unwrap()), "frame {i}");
        }
        assert!(skip.ahead.is_none(), "fell back after the skip");
        let err = Phantom::new(small(0), 3).err().unwrap();
        assert!(err.contains("render_threads"), "{err}");
    }

    /// The nice value and CPU ticks of this process's threads named `prefix*` (Linux).
    #[cfg(target_os = "linux")]
    fn threads(prefix: &str) -> Vec<(i64, u64)> {
        let mut out = Vec::new();
        for task in std::fs::read_dir("/proc/self/task").unwrap().flatten() {
            let Ok(stat) = std::fs::read_to_string(task.path().join("stat")) else {
                continue;
            };
            // `pid (comm) state ...`: the comm may hold spaces, the fields after it do not.
            let (open, close) = (stat.find('(').unwrap(), stat.rfind(')').unwrap());
            if !stat[open + 1..close].starts_with(prefix) {
                continue;
            }
            let f: Vec<&str> = stat[close + 2..].split_whitespace().collect();
            // Fields 14 and 15 (utime, stime) and 19 (nice), counted from 1 at the pid.
            let ticks = f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap();
            out.push((f[16].parse().unwrap(), ticks));
        }
        out
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn renderers_ahead_shade_on_threads_of_their_own_at_the_priority_asked() {
        // SAFETY: no pointers; this thread's own nice value.
        let own = i64::from(unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) });
        let params = |render_nice| Params {
            width: 320,
            height: 240,
            focal_px: 350.0,
            frames: 400,
            render_threads: 2,
            render_nice,
            ..Params::default()
        };
        // Lowest priority: both renderers' workers at nice 19, and they do the shading (their
        // CPU time grows while the node takes frames; on the shared pool it would stay 0).
        let mut low = node_of(params(19));
        low.frame(0).unwrap();
        let name = format!("ph{} render ", low.ahead.as_ref().unwrap().id);
        let mut ticks = 0;
        for i in 1..200 {
            low.frame(i).unwrap();
            let workers = threads(&name);
            assert_eq!(workers.len(), 2, "{workers:?}");
            assert!(
                workers.iter().all(|&(nice, _)| nice == own.max(19)),
                "{workers:?}"
            );
            ticks = workers.iter().map(|w| w.1).sum();
            if ticks > 0 {
                break;
            }
        }
        assert!(ticks > 0, "the renderers' own threads never ran");
        drop(low);
        // Nice 0: the process's own priority (a thread never raises its own).
        let mut same = node_of(params(0));
        same.frame(0).unwrap();
        let workers = threads(&format!("ph{} render ", same.ahead.as_ref().unwrap().id));
        assert_eq!(workers.len(), 2, "{workers:?}");
        assert!(workers.iter().all(|&(nice, _)| nice == own), "{workers:?}");
        let err = Phantom::new(params(20), 3).err().unwrap();
        assert!(err.contains("render_nice"), "{err}");
    }

    #[test]
    fn frames_rendered_up_front_are_the_same_and_the_rest_follow() {
        let mut reference = Phantom::new(small(1), 3).unwrap();
        let node = |render_threads, prerender_frames| {
            node_of(Params {
                prerender_frames,
                ..small(render_threads)
            })
        };
        // Three up front from frame 1, then two renderers ahead to the end of the sequence.
        let mut pre = node(2, 3);
        for i in 1..7 {
            let want = reference.render(i).unwrap();
            let got = pre.frame(i).expect("a frame before the end");
            assert!(same(&got, &want), "frame {i}");
            let held = pre.prerendered.as_ref().map(|p| p.frames.len());
            if i < 4 {
                assert_eq!(held, Some((3 - i) as usize), "frame {i} came from memory");
                assert!(pre.ahead.is_none());
            } else {
                assert!(
                    held.is_none() && pre.ahead.is_some(),
                    "frame {i} from the renderers"
                );
            }
        }
        assert!(pre.frame(7).is_none(), "the stream ends after `frames`");
        // More up front than the sequence holds: all of it, then the end.
        let mut all = node(1, 50);
        for i in 0..7 {
            assert!(same(&all.frame(i).unwrap(), &reference.render(i).unwrap()));
        }
        assert!(all.frame(7).is_none());
        // A skipped frame: rendered when asked from then on, still the same frames.
        let mut skip = node(1, 4);
        for i in [0, 1, 3, 4] {
            assert!(same(&skip.frame(i).unwrap(), &reference.render(i).unwrap()));
        }
        assert!(skip.prerendered.is_none(), "fell back after the skip");
        // Too much memory: refused, naming the field.
        let big = Params {
            prerender_frames: 100_000,
            ..Params::default()
        };
        let err = Phantom::new(big, 3).err().unwrap();
        assert!(
            err.contains("prerender_frames") && err.contains("GB"),
            "{err}"
        );
    }

    #[test]
    fn the_frames_do_not_depend_on_the_threads() {
        // The albedo is baked and the rows shaded on the pool's threads; one thread and three
        // give the same phantom (a texture with its fine scales and sensor noise on).
        let render = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut p = Phantom::new(small(1), 5).unwrap();
                (
                    p.albedo_at([1.3, -2.7, 70.0], [0.0, 0.0, -1.0]),
                    p.render(4).unwrap(),
                )
            })
        };
        let ((a1, f1), (a3, f3)) = (render(1), render(3));
        assert_eq!(a1, a3);
        assert!(same(&f1, &f3));
        assert!(f1
            .stereo
            .left
            .data
            .iter()
            .any(|&v| v != f1.stereo.left.data[0]));
    }
}
