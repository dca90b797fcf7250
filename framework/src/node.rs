//! The node trait: a small lifecycle (`start`, `process` once per frame, `finish`) with typed ports.
//!
//! A node is built from typed parameters by its plugin (see [`crate::registry`]), keeps whatever
//! state it needs across frames, and reads and writes payloads through [`Inputs`] and [`Outputs`].

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;
use std::sync::Arc;

use crate::gpu::GpuProvider;
use crate::payload::{Payload, PayloadType, PortType};

/// Declaration of one port.
#[derive(Clone, Debug, PartialEq)]
pub struct PortSpec {
    /// Name, unique among the node's inputs (or outputs).
    pub name: String,
    /// Payload type.
    pub ty: PortType,
    /// An optional input may stay unconnected; an optional output may be left unset on a frame.
    pub optional: bool,
    /// One line for `misslam plugins ID`.
    pub doc: String,
}

impl PortSpec {
    /// A required port.
    pub fn new(name: &str, ty: PortType, doc: &str) -> Self {
        PortSpec {
            name: name.to_owned(),
            ty,
            optional: false,
            doc: doc.to_owned(),
        }
    }

    /// An optional port.
    pub fn optional(name: &str, ty: PortType, doc: &str) -> Self {
        PortSpec {
            optional: true,
            ..PortSpec::new(name, ty, doc)
        }
    }
}

/// What a node tells the scheduler after a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Flow {
    /// Carry on.
    Continue,
    /// A source has no more frames: the run ends before this frame.
    EndOfStream,
}

/// Why a node failed on a frame. Carries a message for the user; the scheduler adds node and frame.
#[derive(Debug)]
pub struct NodeError {
    message: String,
}

impl NodeError {
    /// An error with a message.
    pub fn msg(message: impl Into<String>) -> Self {
        NodeError {
            message: message.into(),
        }
    }

    /// The message.
    pub fn message(&self) -> &str {
        &self.message
    }
}

impl fmt::Display for NodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)
    }
}

impl<E: std::error::Error> From<E> for NodeError {
    fn from(e: E) -> Self {
        // Keep the whole cause chain in the message: it is all the user will see.
        let mut message = e.to_string();
        let mut source = e.source();
        while let Some(s) = source {
            message.push_str(": ");
            message.push_str(&s.to_string());
            source = s.source();
        }
        NodeError { message }
    }
}

/// Shorthand for node results.
pub type NodeResult<T> = Result<T, NodeError>;

/// Facts about the frame being processed.
#[derive(Clone, Copy, Debug)]
pub struct FrameInfo {
    /// Index of the frame in the sequence (`frames.start` for the first frame of a run).
    pub index: u64,
    /// Position of this frame in the run (0 for the first).
    pub ordinal: u64,
}

/// Run-wide services a node may use in `start`, `process` and `finish`.
pub struct NodeContext<'a> {
    /// The node's id in the graph.
    pub id: &'a str,
    /// The run's output folder (created before `start`).
    pub out_dir: &'a Path,
    /// The folder of the graph file.
    pub graph_dir: &'a Path,
    /// The graph's seed.
    pub seed: u64,
    /// The shared GPU device, created on first use.
    pub gpu: &'a GpuProvider,
    /// Evaluation figures reported by this node (in `finish`), gathered under `eval` in `metrics.json`.
    pub eval: &'a mut BTreeMap<String, f64>,
    /// Times of the node's own stages, ms per call, gathered under `timing_ms` in `metrics.json`
    /// as `<node id>.<stage>`.
    pub stages: &'a mut BTreeMap<String, Vec<f64>>,
}

impl NodeContext<'_> {
    /// Reports an evaluation figure for `metrics.json`, e.g. `("depth.mae_mm", 0.31)`.
    pub fn report_eval(&mut self, key: &str, value: f64) {
        self.eval.insert(key.to_owned(), value);
    }

    /// Reports the time of one of the node's stages in this call, e.g. `("solve", 12.5)`: its
    /// median, mean and p95 over the run appear in `metrics.json` under
    /// `timing_ms."<node id>.<stage>"` and in the timing table `misslam run` prints.
    pub fn report_stage_ms(&mut self, stage: &str, ms: f64) {
        match self.stages.get_mut(stage) {
            Some(v) => v.push(ms),
            None => {
                self.stages.insert(stage.to_owned(), vec![ms]);
            }
        }
    }
}

/// Times a node's stages within one call, for [`NodeContext::report_stage_ms`]: each
/// [`StageClock::lap`] ends the stage running since the last lap (or the start); stages timed
/// elsewhere (a solver's own parts) are pushed with [`StageClock::push`].
#[derive(Debug)]
pub struct StageClock {
    /// The stages so far, in order, ms.
    pub times: Vec<(&'static str, f64)>,
    lap: std::time::Instant,
}

impl StageClock {
    /// Starts timing the first stage now.
    pub fn start() -> Self {
        StageClock {
            times: Vec::new(),
            lap: std::time::Instant::now(),
        }
    }

    /// Ends the stage running since the last lap (or the start) as `name`.
    pub fn lap(&mut self, name: &'static str) {
        let now = std::time::Instant::now();
        self.times
            .push((name, (now - self.lap).as_secs_f64() * 1e3));
        self.lap = now;
    }

    /// Adds a stage timed elsewhere (it does not end the running one).
    pub fn push(&mut self, name: &'static str, ms: f64) {
        self.times.push((name, ms));
    }

    /// Hands every stage to `ctx` (only the stages this call ran).
    pub fn report(self, ctx: &mut NodeContext) {
        for (stage, ms) in self.times {
            ctx.report_stage_ms(stage, ms);
        }
    }
}

/// A node of the graph. `start` and `finish` default to doing nothing.
pub trait Node: Send {
    /// Called once before the first frame.
    fn start(&mut self, _ctx: &mut NodeContext) -> NodeResult<()> {
        Ok(())
    }

    /// Called once per frame, after every node it depends on.
    fn process(
        &mut self,
        ctx: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow>;

    /// Called once after the last frame (also after an aborted run), e.g. to write exports.
    fn finish(&mut self, _ctx: &mut NodeContext) -> NodeResult<()> {
        Ok(())
    }
}

/// The inputs of one node on one frame.
pub struct Inputs<'a> {
    pub(crate) specs: &'a [PortSpec],
    pub(crate) values: &'a [Option<Payload>],
}

impl<'a> Inputs<'a> {
    /// Inputs built by hand, for tests and for driving a node without the runtime.
    pub fn new(specs: &'a [PortSpec], values: &'a [Option<Payload>]) -> Self {
        Inputs { specs, values }
    }

    fn index(&self, name: &str) -> NodeResult<usize> {
        self.specs
            .iter()
            .position(|s| s.name == name)
            .ok_or_else(|| NodeError::msg(format!("no input port `{name}`")))
    }

    /// The payload on input `name`, which must be present and of type `T`.
    pub fn get<T: PayloadType>(&self, name: &str) -> NodeResult<&'a Arc<T>> {
        self.opt(name)?
            .ok_or_else(|| NodeError::msg(format!("input `{name}` received nothing on this frame")))
    }

    /// The payload on an optional input `name`, if any arrived.
    pub fn opt<T: PayloadType>(&self, name: &str) -> NodeResult<Option<&'a Arc<T>>> {
        let i = self.index(name)?;
        match &self.values[i] {
            None => Ok(None),
            Some(p) => T::from_payload(p).map(Some).ok_or_else(|| {
                NodeError::msg(format!(
                    "input `{name}` carries {}, expected {}",
                    p.port_type(),
                    T::PORT_TYPE
                ))
            }),
        }
    }

    /// The raw payload on input `i` (declaration order).
    pub fn raw(&self, i: usize) -> Option<&'a Payload> {
        self.values.get(i).and_then(Option::as_ref)
    }
}

/// The outputs of one node on one frame.
pub struct Outputs<'a> {
    pub(crate) specs: &'a [PortSpec],
    pub(crate) values: &'a mut [Option<Payload>],
}

impl<'a> Outputs<'a> {
    /// Outputs built by hand, for tests and for driving a node without the runtime.
    pub fn new(specs: &'a [PortSpec], values: &'a mut [Option<Payload>]) -> Self {
        Outputs { specs, values }
    }

    /// Sets output `name` to a new payload.
    pub fn put<T: PayloadType>(&mut self, name: &str, value: T) -> NodeResult<()> {
        self.put_arc(name, Arc::new(value))
    }

    /// Sets output `name` to a shared payload (no copy).
    pub fn put_arc<T: PayloadType>(&mut self, name: &str, value: Arc<T>) -> NodeResult<()> {
        self.put_payload(name, T::into_payload(value))
    }

    /// Sets output `name` to a payload of any type; its type must match the port's.
    pub fn put_payload(&mut self, name: &str, value: Payload) -> NodeResult<()> {
        let i = self
            .specs
            .iter()
            .position(|s| s.name == name)
            .ok_or_else(|| NodeError::msg(format!("no output port `{name}`")))?;
        if self.specs[i].ty != value.port_type() {
            return Err(NodeError::msg(format!(
                "output `{name}` is {}, the node produced {}",
                self.specs[i].ty,
                value.port_type()
            )));
        }
        self.values[i] = Some(value);
        Ok(())
    }

    /// The payload already set on output `i`, if any.
    pub fn get(&self, i: usize) -> Option<&Payload> {
        self.values.get(i).and_then(Option::as_ref)
    }
}
