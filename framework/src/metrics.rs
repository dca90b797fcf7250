//! What a run measured: frame counts, per-node timing statistics, evaluation figures.
//! Serialised as `metrics.json` in the run's output folder (fields documented in the README).

use std::collections::BTreeMap;

use serde::Serialize;

/// Timing statistics of one node over the frames it ran, in milliseconds.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TimingStats {
    /// Frames measured.
    pub frames: usize,
    /// Mean.
    pub mean_ms: f64,
    /// Median.
    pub median_ms: f64,
    /// 95th percentile (nearest rank).
    pub p95_ms: f64,
    /// Maximum.
    pub max_ms: f64,
}

impl TimingStats {
    /// Statistics of a set of samples (all zero when empty).
    pub fn from_samples(samples: &[f64]) -> Self {
        if samples.is_empty() {
            return TimingStats {
                frames: 0,
                mean_ms: 0.0,
                median_ms: 0.0,
                p95_ms: 0.0,
                max_ms: 0.0,
            };
        }
        let mut s = samples.to_vec();
        s.sort_by(f64::total_cmp);
        let n = s.len();
        let median = if n % 2 == 1 {
            s[n / 2]
        } else {
            0.5 * (s[n / 2 - 1] + s[n / 2])
        };
        let rank = ((0.95 * n as f64).ceil() as usize).clamp(1, n);
        TimingStats {
            frames: n,
            mean_ms: s.iter().sum::<f64>() / n as f64,
            median_ms: median,
            p95_ms: s[rank - 1],
            max_ms: s[n - 1],
        }
    }
}

/// A frame that was skipped under `on_error = "skip_frame"`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SkippedFrame {
    /// Frame index.
    pub frame: u64,
    /// Node that failed.
    pub node: String,
    /// Why.
    pub error: String,
}

/// Frame counts.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FrameCounts {
    /// Frames every node processed.
    pub processed: u64,
    /// Frames dropped by the error policy.
    pub skipped: u64,
    /// Details of each skipped frame.
    pub skipped_frames: Vec<SkippedFrame>,
}

/// Everything `metrics.json` holds.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RunMetrics {
    /// Graph name.
    pub graph: String,
    /// Graph file.
    pub graph_file: String,
    /// `--set` overrides applied.
    pub overrides: Vec<String>,
    /// Frame counts.
    pub frames: FrameCounts,
    /// Per-node timing in ms, plus `_frame` for the whole frame (from its start in the first
    /// level to its end in the last, scheduling included), `_interval` for the time between two
    /// completed frames (the run's throughput) and `_rerun` for logging.
    pub timing_ms: BTreeMap<String, TimingStats>,
    /// Figures reported by evaluation nodes, e.g. `depth.mae_mm`.
    pub eval: BTreeMap<String, f64>,
    /// Wall time of the whole run, seconds.
    pub wall_s: f64,
    /// Frames in the graph at once (`[graph] pipeline`; 1 when the levels ran one frame at a
    /// time).
    pub pipeline: u32,
    /// Threads of each level's pool when the levels ran as a pipeline (`[graph] level_threads`,
    /// resolved); 0 when they ran one frame at a time.
    #[serde(default)]
    pub level_threads: usize,
    /// Threads of each level's pool, level by level, when the levels ran as a pipeline (a
    /// node's `threads` setting changes its level's); empty when they ran one frame at a time.
    #[serde(default)]
    pub level_pools: Vec<usize>,
    /// Nice value of each level's pool, level by level, when the levels ran as a pipeline (the
    /// lowest its nodes' `nice` settings ask, 0 without); empty when they ran one frame at a
    /// time.
    #[serde(default)]
    pub level_nice: Vec<u32>,
    /// Set when the run stopped on an error: what happened.
    pub aborted: Option<String>,
    /// The parameters every node ran with, after defaults and overrides.
    pub params: BTreeMap<String, serde_json::Value>,
}

impl RunMetrics {
    /// A table for the terminal.
    pub fn summary_table(&self) -> String {
        let mut s = format!(
            "{:<24} {:>7} {:>10} {:>10} {:>10}\n",
            "node", "frames", "mean ms", "median ms", "p95 ms"
        );
        for (node, t) in &self.timing_ms {
            s.push_str(&format!(
                "{:<24} {:>7} {:>10.3} {:>10.3} {:>10.3}\n",
                node, t.frames, t.mean_ms, t.median_ms, t.p95_ms
            ));
        }
        s.push_str(&format!(
            "frames processed: {}, skipped: {}, wall {:.2} s\n",
            self.frames.processed, self.frames.skipped, self.wall_s
        ));
        if let (Some(i), Some(f)) = (
            self.timing_ms.get("_interval"),
            self.timing_ms.get("_frame"),
        ) {
            if i.frames > 0 && i.median_ms > 0.0 {
                s.push_str(&format!(
                    "throughput {:.1} fps (median {:.1} ms between frames), latency {:.1} ms (median), {} in the graph at once\n",
                    1e3 / i.median_ms,
                    i.median_ms,
                    f.median_ms,
                    self.pipeline
                ));
            }
        }
        for (k, v) in &self.eval {
            s.push_str(&format!("{k:<24} {v:.4}\n"));
        }
        s
    }
}

/// Per-frame figures of an evaluation node, averaged over the run: the node adds each frame's
/// values (also returned as the frame's [`crate::Metrics`]) and reports the means in `finish`.
/// Non-finite values (a frame with nothing to score) add nothing to the means.
#[derive(Clone, Debug, Default)]
pub struct FrameMeans {
    sums: BTreeMap<String, (f64, u32)>,
}

impl FrameMeans {
    /// Adds one frame's figures and returns them as that frame's metrics payload.
    pub fn add(&mut self, values: impl IntoIterator<Item = (String, f64)>) -> crate::Metrics {
        let mut m = crate::Metrics::default();
        for (k, v) in values {
            if v.is_finite() {
                let e = self.sums.entry(k.clone()).or_insert((0.0, 0));
                e.0 += v;
                e.1 += 1;
            }
            m.values.insert(k, v);
        }
        m
    }

    /// The mean of every key seen with a finite value.
    pub fn means(&self) -> impl Iterator<Item = (&str, f64)> {
        self.sums
            .iter()
            .map(|(k, (s, n))| (k.as_str(), s / *n as f64))
    }

    /// Reports the means as evaluation figures (for `metrics.json`).
    pub fn report(&self, ctx: &mut crate::NodeContext) {
        for (k, v) in self.means() {
            ctx.report_eval(k, v);
        }
    }
}

/// CPU time this process has used so far (every thread, user and system), ms; `None` where the
/// platform does not say. For benchmarks that ask what a stage costs the other threads, not only
/// how long it takes.
pub fn process_cpu_ms() -> Option<f64> {
    #[cfg(target_os = "linux")]
    {
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: `t` is a valid timespec the call writes.
        let r = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut t) };
        (r == 0).then_some(t.tv_sec as f64 * 1e3 + t.tv_nsec as f64 * 1e-6)
    }
    #[cfg(not(target_os = "linux"))]
    {
        None
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn process_cpu_time_grows_with_work() {
        let Some(a) = super::process_cpu_ms() else {
            println!("skipped: no process CPU clock on this platform");
            return;
        };
        // Work until the clock has moved 10 ms (other threads may hold the cores for a while:
        // up to 10 s of wall time), then check it did and did not go back.
        let mut x = 1u64;
        let t = std::time::Instant::now();
        let mut b = a;
        while b - a < 10.0 && t.elapsed().as_secs() < 10 {
            for _ in 0..10_000 {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
            }
            let now = super::process_cpu_ms().unwrap();
            assert!(now >= b, "the clock went back: {b} -> {now} ms");
            b = now;
        }
        assert!(b - a >= 10.0, "{a} -> {b} ms");
    }

    use super::*;

    #[test]
    fn frame_means_skip_non_finite_values() {
        let mut f = FrameMeans::default();
        let m = f.add([("a".to_owned(), 1.0), ("b".to_owned(), f64::NAN)]);
        assert!(
            m.values["b"].is_nan(),
            "the frame's payload keeps what was measured"
        );
        f.add([("a".to_owned(), 3.0), ("b".to_owned(), 4.0)]);
        let means: Vec<(&str, f64)> = f.means().collect();
        assert_eq!(means, [("a", 2.0), ("b", 4.0)]);
    }

    #[test]
    fn the_summary_gives_the_throughput_and_the_latency() {
        let mut m = RunMetrics {
            pipeline: 2,
            level_threads: 4,
            ..Default::default()
        };
        assert!(
            !m.summary_table().contains("throughput"),
            "no frames, no rate"
        );
        m.timing_ms.insert(
            "_interval".into(),
            TimingStats::from_samples(&[25.0, 20.0, 30.0]),
        );
        m.timing_ms.insert(
            "_frame".into(),
            TimingStats::from_samples(&[50.0, 40.0, 60.0, 45.0]),
        );
        let t = m.summary_table();
        assert!(
            t.contains("throughput 40.0 fps (median 25.0 ms between frames), latency 47.5 ms (median), 2 in the graph at once"),
            "{t}"
        );
    }

    #[test]
    fn stats_of_known_samples() {
        let t = TimingStats::from_samples(&[4.0, 1.0, 3.0, 2.0]);
        assert_eq!(t.frames, 4);
        assert_eq!(t.mean_ms, 2.5);
        assert_eq!(t.median_ms, 2.5);
        assert_eq!(t.p95_ms, 4.0);
        let samples: Vec<f64> = (1..=100).map(f64::from).collect();
        let t = TimingStats::from_samples(&samples);
        assert_eq!(t.p95_ms, 95.0);
        assert_eq!(t.median_ms, 50.5);
        assert_eq!(TimingStats::from_samples(&[]).frames, 0);
    }
}
