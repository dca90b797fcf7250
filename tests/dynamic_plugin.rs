//! Builds the out-of-tree plugin in `examples/dynamic_plugin` with cargo, loads it from a graph,
//! and checks the handshake's refusals (wrong ABI, missing file, not a plugin) and panic reports.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;

use misslam::builtin_registry;
use misslam::framework::dynamic::load_library;
use misslam::framework::{graph, Image, Inputs, Outputs, Payload};

fn build_plugin(features: &[&str], target: &str) -> PathBuf {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let base =
        std::env::var_os("CARGO_TARGET_DIR").map_or_else(|| root.join("target"), PathBuf::from);
    let target_dir = base.join("dynamic-plugin").join(target);
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let mut cmd = Command::new(cargo);
    cmd.args(["build", "--quiet", "--manifest-path"])
        .arg(root.join("examples/dynamic_plugin/Cargo.toml"))
        .arg("--target-dir")
        .arg(&target_dir)
        .env_remove("CARGO_TARGET_DIR");
    if !features.is_empty() {
        cmd.args(["--features", &features.join(",")]);
    }
    let out = cmd.output().expect("run cargo");
    assert!(
        out.status.success(),
        "building the plugin failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    target_dir.join("debug").join(format!(
        "{}misslam_example_invert{}",
        std::env::consts::DLL_PREFIX,
        std::env::consts::DLL_SUFFIX
    ))
}

#[test]
fn example_plugin_loads_runs_and_reports_panics() {
    let lib = build_plugin(&[], "ok");
    let plugin = load_library(&lib).expect("handshake accepted");
    assert_eq!(plugin.info().id, "example.invert");
    assert_eq!(plugin.info().params.len(), 2);

    // Driven directly: inverted pixels, host-allocated output.
    let params: misslam::framework::toml::Table =
        misslam::framework::toml::from_str("offset = 1").unwrap();
    let provider = misslam::framework::GpuProvider::new();
    let bctx = misslam::framework::BuildContext {
        node_id: "inv",
        graph_dir: Path::new("."),
        seed: 0,
        gpu: &provider,
    };
    let mut node = plugin.build(&params, &bctx).expect("built");
    let img = Image::new(2, 1, 3, vec![0, 10, 255, 100, 200, 254]).unwrap();
    let inputs_v = [Some(Payload::Image(Arc::new(img)))];
    let mut outputs_v = [None];
    let info = plugin.info();
    let out_dir = common::tmp_dir("dyn-direct");
    let mut eval = Default::default();
    let mut ctx = misslam::framework::NodeContext {
        id: "inv",
        out_dir: &out_dir,
        graph_dir: Path::new("."),
        seed: 0,
        gpu: &provider,
        eval: &mut eval,
        stages: &mut Default::default(),
    };
    let frame = misslam::framework::FrameInfo {
        index: 0,
        ordinal: 0,
    };
    node.process(
        &mut ctx,
        frame,
        &Inputs::new(&info.inputs, &inputs_v),
        &mut Outputs::new(&info.outputs, &mut outputs_v),
    )
    .expect("processed");
    let Some(Payload::Image(out)) = &outputs_v[0] else {
        panic!("no output")
    };
    // (255 - v) + 1, saturating.
    assert_eq!(out.data, vec![255, 246, 1, 156, 56, 2]);

    // Bad parameters are the plugin's own clear error.
    let bad: misslam::framework::toml::Table =
        misslam::framework::toml::from_str("offst = 1").unwrap();
    let e = plugin.check_params(&bad).unwrap_err().to_string();
    assert_eq!(
        e,
        "unknown parameter `offst`; known: offset, panic_on_frame"
    );

    // In a graph: a panic on frame 1 is reported, the run goes on under skip_frame.
    let text = format!(
        "[graph]\non_error = \"skip_frame\"\nlibraries = [\"{}\"]\n\n[[node]]\nid = \"src\"\nplugin = \"test.images\"\n\n[[node]]\nid = \"inv\"\nplugin = \"example.invert\"\ninputs = {{ image = \"src.image\" }}\nparams = {{ panic_on_frame = 1 }}\n",
        lib.display()
    );
    let mut registry = builtin_registry();
    registry.register(images_plugin()).unwrap();
    let g = graph::parse(Path::new("dyn.toml"), &text, &registry, &[]).expect("valid");
    let report = common::run_graph_ok(g, &common::tmp_dir("dyn-graph"));
    assert_eq!(report.metrics.frames.processed, 2);
    let skipped = &report.metrics.frames.skipped_frames;
    assert_eq!(skipped.len(), 1);
    assert_eq!(skipped[0].frame, 1);
    assert_eq!(
        skipped[0].error,
        "plugin panicked: example.invert was asked to panic on frame 1"
    );
}

#[test]
fn handshake_refuses_a_wrong_abi_version() {
    let lib = build_plugin(&["wrong-abi"], "wrong-abi");
    let e = load_library(&lib).err().expect("refused");
    assert!(
        e.contains("speaks plugin ABI version 999, this misslam speaks 1"),
        "{e}"
    );
}

#[test]
fn a_library_without_the_entry_point_is_refused() {
    // Any shared library that is not a plugin: the C math library is on every Linux.
    let candidates = [
        "/lib/x86_64-linux-gnu/libm.so.6",
        "/usr/lib/x86_64-linux-gnu/libm.so.6",
        "/lib64/libm.so.6",
    ];
    let Some(libm) = candidates.iter().map(Path::new).find(|p| p.exists()) else {
        println!("skipped: no libm.so.6 at the usual places");
        return;
    };
    let e = load_library(libm).err().expect("refused");
    assert!(
        e.contains("is not a misslam plugin: no entry point `misslam_plugin_entry_v1`"),
        "{e}"
    );
}

/// A source of three small RGB images, for graphs that need no data folder.
fn images_plugin() -> impl misslam::framework::Plugin {
    use misslam::framework::*;
    #[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema, Default)]
    #[serde(deny_unknown_fields)]
    struct P {}
    struct Src;
    impl Node for Src {
        fn process(
            &mut self,
            _: &mut NodeContext,
            f: FrameInfo,
            _: &Inputs,
            o: &mut Outputs,
        ) -> NodeResult<Flow> {
            if f.index >= 3 {
                return Ok(Flow::EndOfStream);
            }
            o.put(
                "image",
                Image::new(4, 2, 3, vec![f.index as u8; 24]).map_err(NodeError::msg)?,
            )?;
            Ok(Flow::Continue)
        }
    }
    TypedPlugin::new(
        "test.images",
        "three small images",
        vec![],
        vec![PortSpec::new("image", PortType::Image, "")],
        |_: P, _: &BuildContext| Ok(Src),
    )
}
