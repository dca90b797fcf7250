//! The scheduler on graphs of small custom nodes: order, sharing, policies, panics, metrics.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use misslam::framework::graph::{self, ErrorPolicy};
use misslam::framework::{
    BuildContext, FloatMap, Flow, FrameInfo, Inputs, Metrics, Node, NodeContext, NodeError,
    NodeResult, Outputs, PortSpec, PortType, Registry, RunError, RunOptions, Runtime, TypedPlugin,
};

/// Emits a 1x1 map holding the frame index; ends after `frames` frames.
#[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema, Default)]
#[serde(deny_unknown_fields, default)]
struct CounterParams {
    /// Frames before the end of the stream.
    frames: u64,
}

struct Counter {
    frames: u64,
}

fn map_of(v: f32) -> misslam::framework::DisparityMap {
    misslam::framework::DisparityMap {
        map: FloatMap {
            width: 1,
            height: 1,
            data: vec![v],
        },
        calib: misslam::framework::StereoCalib {
            width: 1,
            height: 1,
            fx: 1.0,
            fy: 1.0,
            cx: 0.0,
            cy: 0.0,
            cx_right: 0.0,
            baseline_mm: 1.0,
        },
    }
}

impl Node for Counter {
    fn process(
        &mut self,
        _: &mut NodeContext,
        f: FrameInfo,
        _: &Inputs,
        out: &mut Outputs,
    ) -> NodeResult<Flow> {
        if f.index >= self.frames {
            return Ok(Flow::EndOfStream);
        }
        out.put("value", map_of(f.index as f32))?;
        Ok(Flow::Continue)
    }
}

/// (node id, frame, value seen, address of the input payload) per call.
type Seen = (String, u64, f32, usize);
type Log = Arc<Mutex<Vec<Seen>>>;

/// Adds `add` to its input; fails or panics on a chosen frame; records what it saw.
#[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema, Default)]
#[serde(deny_unknown_fields, default)]
struct StepParams {
    /// Added to the input.
    add: f32,
    /// Return an error on this frame.
    fail_on: Option<u64>,
    /// Panic on this frame.
    panic_on: Option<u64>,
    /// Wait for a partner node to run at the same time (parallel test).
    rendezvous: bool,
    /// On this frame, wait until some node is inside `process` on another frame (pipeline test).
    hold_on: Option<u64>,
}

struct Step {
    p: StepParams,
    log: Log,
    rendezvous: Arc<AtomicUsize>,
    /// The frames of the holding calls now inside `process`, and whether each has met another.
    inside: Arc<Mutex<Vec<(u64, bool)>>>,
    evals: usize,
    /// Calls made on a pipelined level's own threads (named `misslam-level...`).
    on_level_threads: usize,
    /// The most threads rayon had for a call's parallel work.
    pool_threads: usize,
    /// The highest nice value a call ran at.
    nice: i32,
}

impl Node for Step {
    fn process(
        &mut self,
        ctx: &mut NodeContext,
        f: FrameInfo,
        inp: &Inputs,
        out: &mut Outputs,
    ) -> NodeResult<Flow> {
        if self.p.fail_on == Some(f.index) {
            return Err(NodeError::msg("bad input on purpose"));
        }
        if self.p.panic_on == Some(f.index) {
            panic!("deliberate panic");
        }
        if self.p.rendezvous {
            // Both partners must be inside `process` at once: only possible if they run in parallel.
            self.rendezvous.fetch_add(1, Ordering::SeqCst);
            let t = Instant::now();
            while self.rendezvous.load(Ordering::SeqCst) < 2 * (f.ordinal as usize + 1) {
                if t.elapsed() > Duration::from_secs(10) {
                    return Err(NodeError::msg("partner never ran concurrently"));
                }
                std::hint::spin_loop();
            }
        }
        if self.p.hold_on == Some(f.index) {
            self.inside.lock().unwrap().push((f.index, false));
            let t = Instant::now();
            let overlapped = loop {
                {
                    let mut inside = self.inside.lock().unwrap();
                    // Another frame is inside now: both know it (the other may look only after
                    // this call has left).
                    if inside.iter().any(|&(g, _)| g != f.index) {
                        inside.iter_mut().for_each(|e| e.1 = true);
                    }
                    if inside.iter().any(|&(g, met)| g == f.index && met) {
                        break true;
                    }
                }
                if t.elapsed() > Duration::from_secs(3) {
                    break false;
                }
                std::thread::sleep(Duration::from_millis(1));
            };
            self.inside.lock().unwrap().retain(|&(g, _)| g != f.index);
            if !overlapped {
                return Err(NodeError::msg(
                    "no other frame was in the graph at the same time",
                ));
            }
        }
        let v = inp.get::<misslam::framework::DisparityMap>("value")?;
        let ptr = Arc::as_ptr(v) as usize;
        self.log
            .lock()
            .unwrap()
            .push((ctx.id.to_owned(), f.index, v.map.data[0], ptr));
        out.put("value", map_of(v.map.data[0] + self.p.add))?;
        ctx.report_stage_ms("add", 0.25 * (f.ordinal + 1) as f64);
        let mut m = Metrics::default();
        m.values.insert("value".into(), v.map.data[0] as f64);
        out.put("metrics", m)?;
        self.evals += 1;
        let thread = std::thread::current();
        if thread
            .name()
            .is_some_and(|n| n.starts_with("misslam-level"))
        {
            self.on_level_threads += 1;
        }
        self.pool_threads = self.pool_threads.max(rayon::current_num_threads());
        self.nice = self.nice.max(misslam::framework::priority::thread_nice());
        Ok(Flow::Continue)
    }

    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        ctx.report_eval(&format!("{}.frames", ctx.id), self.evals as f64);
        ctx.report_eval(
            &format!("{}.on_level_threads", ctx.id),
            self.on_level_threads as f64,
        );
        ctx.report_eval(
            &format!("{}.pool_threads", ctx.id),
            self.pool_threads as f64,
        );
        ctx.report_eval(&format!("{}.nice", ctx.id), self.nice as f64);
        Ok(())
    }
}

fn registry(log: Log) -> Registry {
    let mut r = Registry::new();
    r.register(TypedPlugin::new(
        "test.counter",
        "counts frames",
        vec![],
        vec![PortSpec::new("value", PortType::Disparity, "")],
        |p: CounterParams, _: &BuildContext| Ok(Counter { frames: p.frames }),
    ))
    .unwrap();
    let rendezvous = Arc::new(AtomicUsize::new(0));
    let inside = Arc::default();
    r.register(TypedPlugin::new(
        "test.step",
        "adds",
        vec![PortSpec::new("value", PortType::Disparity, "")],
        vec![
            PortSpec::new("value", PortType::Disparity, ""),
            PortSpec::new("metrics", PortType::Metrics, ""),
        ],
        move |p: StepParams, _: &BuildContext| {
            Ok(Step {
                p,
                log: log.clone(),
                rendezvous: rendezvous.clone(),
                inside: Arc::clone(&inside),
                evals: 0,
                on_level_threads: 0,
                pool_threads: 0,
                nice: i32::MIN,
            })
        },
    ))
    .unwrap();
    r
}

fn out_dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("misslam-runtime-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

const DIAMOND: &str = r#"
[graph]
name = "diamond"
on_error = "skip_frame"

[[node]]
id = "src"
plugin = "test.counter"
params = { frames = 5 }

[[node]]
id = "left"
plugin = "test.step"
inputs = { value = "src.value" }
params = { add = 1.0 }

[[node]]
id = "right"
plugin = "test.step"
inputs = { value = "src.value" }
params = { add = 10.0 }

[[node]]
id = "join"
plugin = "test.step"
inputs = { value = "left.value" }
"#;

fn run(
    text: &str,
    sets: &[&str],
    name: &str,
) -> (
    misslam::framework::RunReport,
    Vec<(String, u64, f32, usize)>,
) {
    let log: Log = Arc::default();
    let reg = registry(log.clone());
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    let g = graph::parse(Path::new("test.toml"), text, &reg, &sets).expect("valid graph");
    let rt = Runtime::build(g).expect("built");
    let report = rt
        .run(RunOptions {
            out_dir: Some(out_dir(name)),
            ..Default::default()
        })
        .expect("ran");
    let entries = log.lock().unwrap().clone();
    (report, entries)
}

#[test]
fn runs_in_dependency_order_and_shares_payloads() {
    let (report, log) = run(DIAMOND, &[], "order");
    assert!(report.error.is_none());
    assert_eq!(report.metrics.frames.processed, 5);
    for frame in 0..5u64 {
        let seen: Vec<_> = log.iter().filter(|e| e.1 == frame).collect();
        let by = |id: &str| seen.iter().find(|e| e.0 == id).copied().expect("node ran");
        assert_eq!(by("left").2, frame as f32);
        assert_eq!(by("right").2, frame as f32);
        assert_eq!(by("join").2, frame as f32 + 1.0, "join sees left's output");
        // Both consumers of src.value got the same allocation: no deep copy.
        assert_eq!(by("left").3, by("right").3);
    }
    // Evaluation figures from finish land under eval.
    assert_eq!(report.metrics.eval.get("join.frames"), Some(&5.0));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report.metrics_path).unwrap()).unwrap();
    assert_eq!(json["frames"]["processed"], 5);
    for node in ["src", "left", "right", "join", "_frame"] {
        let t = &json["timing_ms"][node];
        assert_eq!(t["frames"], 5, "{node}");
        for k in ["mean_ms", "median_ms", "p95_ms"] {
            assert!(t[k].as_f64().is_some_and(|v| v >= 0.0), "{node}.{k}");
        }
    }
    assert_eq!(json["params"]["right"]["add"], 10.0);
    // The parameters the node ran with, defaults filled in.
    assert_eq!(json["params"]["right"]["rendezvous"], false);
    assert!(json["params"]["right"]
        .as_object()
        .is_some_and(|o| o.contains_key("hold_on")));
    // A node's own stages: `<id>.<stage>`, one sample per call (0.25, 0.5, ... 1.25 ms).
    let t = &json["timing_ms"]["left.add"];
    assert_eq!(t["frames"], 5);
    assert_eq!(t["median_ms"], 0.75);
    assert_eq!(t["mean_ms"], 0.75);
}

#[test]
fn same_graph_same_outputs() {
    let (_, a) = run(DIAMOND, &[], "det_a");
    let (_, b) = run(DIAMOND, &[], "det_b");
    let values = |l: &[Seen]| {
        let mut v: Vec<(String, u64, u32)> = l
            .iter()
            .map(|e| (e.0.clone(), e.1, e.2.to_bits()))
            .collect();
        v.sort();
        v
    };
    assert_eq!(values(&a), values(&b));
}

#[test]
fn skip_frame_policy_skips_and_records() {
    let (report, log) = run(DIAMOND, &["left.fail_on=2"], "skip");
    assert!(report.error.is_none());
    assert_eq!(report.metrics.frames.processed, 4);
    assert_eq!(report.metrics.frames.skipped, 1);
    let s = &report.metrics.frames.skipped_frames[0];
    assert_eq!(
        (s.frame, s.node.as_str(), s.error.as_str()),
        (2, "left", "bad input on purpose")
    );
    assert!(
        !log.iter().any(|e| e.0 == "join" && e.1 == 2),
        "downstream of a failure does not run"
    );
    assert!(
        log.iter().any(|e| e.0 == "join" && e.1 == 3),
        "the next frame runs"
    );
}

#[test]
fn abort_policy_stops_and_still_writes_metrics() {
    let (report, _) = run(
        DIAMOND,
        &["graph.on_error=abort", "right.fail_on=3"],
        "abort",
    );
    let err = report.error.expect("aborted");
    assert!(
        matches!(&err, RunError::Frame { frame: 3, node, .. } if node == "right"),
        "{err}"
    );
    assert_eq!(
        err.to_string(),
        "frame 3: node `right`: bad input on purpose"
    );
    assert_eq!(report.metrics.frames.processed, 3);
    let json = std::fs::read_to_string(&report.metrics_path).expect("metrics written after abort");
    assert!(json.contains("\"aborted\": \"frame 3: node `right`: bad input on purpose\""));
    // finish ran after the abort: its evaluation figure is there.
    assert_eq!(report.metrics.eval.get("join.frames"), Some(&3.0));
}

#[test]
fn a_panicking_node_is_reported_not_fatal() {
    let (report, _) = run(DIAMOND, &["join.panic_on=1"], "panic");
    assert!(report.error.is_none());
    assert_eq!(report.metrics.frames.skipped, 1);
    let s = &report.metrics.frames.skipped_frames[0];
    assert_eq!((s.frame, s.node.as_str()), (1, "join"));
    assert_eq!(s.error, "panicked: deliberate panic");
    assert_eq!(report.metrics.frames.processed, 4);
}

#[test]
fn frame_range_and_count() {
    let (report, log) = run(
        DIAMOND,
        &["graph.frames.start=1", "graph.frames.count=2"],
        "range",
    );
    assert_eq!(report.metrics.frames.processed, 2);
    let frames: Vec<u64> = log.iter().filter(|e| e.0 == "join").map(|e| e.1).collect();
    assert_eq!(frames, [1, 2]);
}

#[test]
fn independent_branches_run_in_parallel() {
    if std::thread::available_parallelism().map_or(1, |n| n.get()) < 2 {
        println!("skipped: one CPU, nothing can run in parallel");
        return;
    }
    let (report, _) = run(
        DIAMOND,
        &[
            "left.rendezvous=true",
            "right.rendezvous=true",
            "graph.frames.count=3",
        ],
        "par",
    );
    assert!(report.error.is_none());
    assert_eq!(
        report.metrics.frames.skipped, 0,
        "{:?}",
        report.metrics.frames.skipped_frames
    );
    assert_eq!(report.metrics.frames.processed, 3);
}

#[test]
fn policy_names_parse() {
    let reg = registry(Arc::default());
    let g = graph::parse(Path::new("t.toml"), DIAMOND, &reg, &[]).unwrap();
    assert_eq!(g.on_error, ErrorPolicy::SkipFrame);
    let levels: Vec<(String, usize)> = g.nodes.iter().map(|n| (n.id.clone(), n.level)).collect();
    assert_eq!(
        levels,
        [
            ("src".into(), 0),
            ("left".into(), 1),
            ("right".into(), 1),
            ("join".into(), 2)
        ]
    );
}

/// What a run did, comparable between schedules: counts, skipped frames, the error, the last
/// level's figure, and what every node saw on every frame.
struct Outcome {
    summary: String,
    seen: Vec<(String, u64, u32)>,
}

fn outcome(text: &str, sets: &[&str], name: &str) -> Outcome {
    let (report, log) = run(text, sets, name);
    let m = &report.metrics;
    let summary = format!(
        "processed {} skipped {:?} join {:?} error {:?}",
        m.frames.processed,
        m.frames.skipped_frames,
        m.eval.get("join.frames"),
        report.error.map(|e| e.to_string())
    );
    let mut seen: Vec<(String, u64, u32)> = log
        .iter()
        .map(|e| (e.0.clone(), e.1, e.2.to_bits()))
        .collect();
    seen.sort();
    Outcome { summary, seen }
}

#[test]
fn the_pipelined_schedule_gives_the_serial_outputs() {
    // (overrides, the frame an abort stops the run at)
    let cases: [(&[&str], Option<u64>); 6] = [
        (&[], None),
        (&["left.fail_on=2"], None),
        (&["join.panic_on=1"], None),
        (&["graph.on_error=abort", "right.fail_on=3"], Some(3)),
        (&["graph.on_error=abort", "join.fail_on=2"], Some(2)),
        (&["graph.frames.start=1", "graph.frames.count=2"], None),
    ];
    for (i, &(sets, stop)) in cases.iter().enumerate() {
        let serial = outcome(DIAMOND, sets, &format!("serial{i}"));
        let piped = [sets, &["graph.pipeline=3"]].concat();
        let (report, _) = run(DIAMOND, &piped, &format!("piped_report{i}"));
        assert_eq!(report.metrics.pipeline, 3, "{sets:?}");
        let p = outcome(DIAMOND, &piped, &format!("piped{i}"));
        assert_eq!(p.summary, serial.summary, "{sets:?}");
        let Some(stop) = stop else {
            assert_eq!(p.seen, serial.seen, "{sets:?}");
            continue;
        };
        // After an abort the serial schedule's calls are all there; earlier levels may have
        // run up to 2 (frames in flight - 1) frames further, and nothing else.
        let extra: Vec<&(String, u64, u32)> =
            p.seen.iter().filter(|e| !serial.seen.contains(e)).collect();
        assert!(serial.seen.iter().all(|e| p.seen.contains(e)), "{sets:?}");
        assert!(
            extra
                .iter()
                .all(|e| e.0 != "join" && e.1 > stop && e.1 <= stop + 2),
            "{sets:?}: {extra:?}"
        );
    }
}

#[test]
fn the_pipelined_schedule_overlaps_frames() {
    if std::thread::available_parallelism().map_or(1, |n| n.get()) < 2 {
        println!("skipped: one CPU, nothing can run in parallel");
        return;
    }
    // `join` (the last level) holds frame 2 until another frame is inside a node, and `left`
    // (the level before it) holds frame 3 likewise: both return only if the two frames are in
    // the graph at once.
    let sets = ["join.hold_on=2", "left.hold_on=3", "graph.pipeline=3"];
    let (report, log) = run(DIAMOND, &sets, "overlap");
    assert!(report.error.is_none());
    assert_eq!(
        report.metrics.frames.skipped, 0,
        "{:?}",
        report.metrics.frames.skipped_frames
    );
    assert_eq!(report.metrics.frames.processed, 5);
    assert_eq!(log.iter().filter(|e| e.0 == "join").count(), 5);
    // Each level's work ran on its own pool's threads.
    for node in ["left", "right", "join"] {
        assert_eq!(
            report.metrics.eval[&format!("{node}.on_level_threads")],
            5.0,
            "{node}"
        );
    }
    let t = &report.metrics.timing_ms;
    assert_eq!(t["_frame"].frames, 5);
    assert_eq!(t["_interval"].frames, 4, "between 5 completed frames");
    // The serial schedule cannot overlap them: both frames are skipped, each after its wait.
    let (serial, _) = run(DIAMOND, &sets[..2], "no_overlap");
    let skipped: Vec<(u64, &str)> = serial
        .metrics
        .frames
        .skipped_frames
        .iter()
        .map(|s| (s.frame, s.node.as_str()))
        .collect();
    assert_eq!(skipped, [(2, "join"), (3, "left")]);
    assert_eq!(serial.metrics.eval["right.on_level_threads"], 0.0);
}

#[test]
fn each_pipelined_level_has_a_pool_of_level_threads() {
    // By default half the cores (at least 2), so the levels' pools do not oversubscribe the
    // machine; `graph.level_threads` sets it; a node's `threads` sets its level's (the most
    // its nodes ask: `left` and `right` share one); one frame at a time there are no level
    // pools.
    let cores = rayon::current_num_threads();
    let half = cores.div_ceil(2).max(2);
    for (sets, want, level) in [
        (&["graph.pipeline=3"][..], half, [half; 3]),
        (
            &["graph.pipeline=3", "graph.level_threads=3"][..],
            3,
            [3; 3],
        ),
        (
            &[
                "graph.pipeline=3",
                "graph.level_threads=3",
                "right.threads=5",
            ][..],
            3,
            [5, 5, 3],
        ),
        (
            &[
                "graph.pipeline=3",
                "left.threads=2",
                "right.threads=1",
                "join.threads=4",
            ][..],
            half,
            [2, 2, 4],
        ),
    ] {
        let (report, _) = run(DIAMOND, sets, "level_threads");
        assert!(report.error.is_none(), "{sets:?}");
        assert_eq!(report.metrics.level_threads, want, "{sets:?}");
        // Per level: the source's, then the two below it.
        assert_eq!(
            report.metrics.level_pools,
            [want, level[0], level[2]],
            "{sets:?}"
        );
        for (node, want) in ["left", "right", "join"].into_iter().zip(level) {
            assert_eq!(
                report.metrics.eval[&format!("{node}.pool_threads")],
                want as f64,
                "{sets:?}: {node}"
            );
        }
    }
    let (serial, _) = run(DIAMOND, &["graph.level_threads=3"], "level_threads_serial");
    assert_eq!(serial.metrics.level_threads, 0);
    assert!(serial.metrics.level_pools.is_empty());
    let err = graph::parse(
        Path::new("test.toml"),
        DIAMOND,
        &registry(Log::default()),
        &["graph.level_threads=-1".to_owned()],
    )
    .err()
    .expect("a negative thread count is refused")
    .to_string();
    assert!(err.contains("graph.level_threads"), "{err}");
}

#[test]
fn a_pipelined_level_runs_at_the_lowest_priority_all_its_nodes_ask() {
    // `nice` lowers a level's pool's priority only where every node of the level asks (the
    // lowest value asked): `left` and `right` share a level, `join` has one of its own. One
    // frame at a time there are no level pools and nothing changes.
    let own = misslam::framework::priority::thread_nice();
    let at = |asked: i32| {
        if cfg!(target_os = "linux") {
            asked.max(own)
        } else {
            own
        }
    };
    for (sets, level, seen) in [
        (&["graph.pipeline=3"][..], [0, 0, 0], [0, 0, 0]),
        (
            &["graph.pipeline=3", "join.nice=7"][..],
            [0, 0, 7],
            [0, 0, 7],
        ),
        (
            &["graph.pipeline=3", "left.nice=5"][..],
            [0, 0, 0],
            [0, 0, 0],
        ),
        (
            &[
                "graph.pipeline=3",
                "left.nice=9",
                "right.nice=5",
                "join.nice=0",
            ][..],
            [0, 5, 0],
            [5, 5, 0],
        ),
        (&["join.nice=7"][..], [0, 0, 0], [0, 0, 0]),
    ] {
        let (report, _) = run(DIAMOND, sets, "nice");
        assert!(report.error.is_none(), "{sets:?}");
        let pipelined = report.metrics.pipeline > 1;
        let want: Vec<u32> = if pipelined {
            level.to_vec()
        } else {
            Vec::new()
        };
        assert_eq!(report.metrics.level_nice, want, "{sets:?}");
        for (node, asked) in ["left", "right", "join"].into_iter().zip(seen) {
            assert_eq!(
                report.metrics.eval[&format!("{node}.nice")],
                at(asked) as f64,
                "{sets:?}: {node}"
            );
        }
    }
}

#[test]
fn the_pipelined_schedule_stops_at_the_end_of_the_stream() {
    // No frame count: the source's end of the stream ends the run, in both schedules.
    for sets in [&[][..], &["graph.pipeline=3"][..]] {
        let (report, log) = run(DIAMOND, sets, "eos");
        assert!(report.error.is_none());
        assert_eq!(report.metrics.frames.processed, 5, "{sets:?}");
        let frames: Vec<u64> = log.iter().filter(|e| e.0 == "join").map(|e| e.1).collect();
        assert_eq!(frames, [0, 1, 2, 3, 4], "{sets:?}");
    }
}
