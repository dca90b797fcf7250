//! misslam's runtime: payloads, the node trait, the plugin registry, TOML graphs and their
//! validation, the scheduler, the Rerun recorder, the shared GPU context and dynamic plugins.
//!
//! Plugins live in their own crates under `plugins/<role>/<name>/` and depend on this crate only.
#![deny(missing_docs)]

pub mod dynamic;
pub mod geometry;
pub mod gpu;
pub mod graph;
pub mod metrics;
pub mod node;
pub mod payload;
pub mod pfm;
pub mod priority;
pub mod recorder;
pub mod registry;
pub mod runtime;

pub use gpu::{Device, GpuContext, GpuError, GpuProvider};
pub use graph::{Graph, GraphError};
pub use node::{
    Flow, FrameInfo, Inputs, Node, NodeContext, NodeError, NodeResult, Outputs, PortSpec,
    StageClock,
};
pub use payload::*;
pub use registry::{BuildContext, BuildError, Plugin, PluginInfo, Registry, TypedPlugin};
pub use runtime::{RunError, RunOptions, RunReport, Runtime};

/// Re-exported so plugins use the same versions.
pub use nalgebra;
pub use schemars;
pub use toml;
