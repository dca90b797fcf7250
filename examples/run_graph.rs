//! The smallest complete use of the library: load a graph file, apply `--set`-style overrides,
//! run it, print what it measured. What `misslam run` does, without the command line.
//!
//! `cargo run --example run_graph -- graphs/inspect.toml src.path=../shared/data/hamlyn20`

use std::path::PathBuf;

use misslam::framework::{graph, RunOptions, Runtime};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let file = PathBuf::from(args.next().unwrap_or_else(|| "graphs/inspect.toml".into()));
    let overrides: Vec<String> = args.collect();
    let registry = misslam::builtin_registry();
    let graph = graph::load(&file, &registry, &overrides)?;
    let report = Runtime::build(graph)?.run(RunOptions {
        frames: Some(5),
        ..Default::default()
    })?;
    print!("{}", report.metrics.summary_table());
    if let Some(e) = report.error {
        return Err(e.into());
    }
    Ok(())
}
