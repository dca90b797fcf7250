//! The invalid-graph suite: every file in `tests/graphs/invalid/` must be rejected before any
//! frame runs, with the error headline pinned in the `.err` file beside it (file, line, column,
//! field). `# set: node.param=value` lines at the top of a file are applied as `--set` overrides.
//! Run with `MISSLAM_BLESS=1` to rewrite the `.err` files after a deliberate change, then review
//! the diff.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

use std::path::{Path, PathBuf};

use misslam::builtin_registry;
use misslam::framework::graph;

fn overrides_of(text: &str) -> Vec<String> {
    text.lines()
        .filter_map(|l| l.strip_prefix("# set: "))
        .map(|s| s.trim().to_owned())
        .collect()
}

fn graph_files(dir: &str) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("test graph folder")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    files.sort();
    files
}

#[test]
fn invalid_graphs_are_rejected_with_located_errors() {
    let registry = builtin_registry();
    let bless = std::env::var_os("MISSLAM_BLESS").is_some();
    let files = graph_files("tests/graphs/invalid");
    assert!(files.len() >= 25, "the suite lost files: {}", files.len());
    let mut failures = Vec::new();
    for file in files {
        let text = std::fs::read_to_string(&file).expect("read test graph");
        let result = graph::parse(&file, &text, &registry, &overrides_of(&text));
        let Err(err) = result else {
            failures.push(format!("{}: accepted, expected an error", file.display()));
            continue;
        };
        let got = err.headline();
        let expected_path = file.with_extension("err");
        if bless {
            std::fs::write(&expected_path, format!("{got}\n")).expect("write .err");
            continue;
        }
        let expected = std::fs::read_to_string(&expected_path).unwrap_or_else(|_| {
            panic!(
                "{} missing (run with MISSLAM_BLESS=1)",
                expected_path.display()
            )
        });
        if expected.trim_end() != got {
            failures.push(format!(
                "{}:\n  expected: {}\n  got:      {got}",
                file.display(),
                expected.trim_end()
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn file_errors_carry_a_snippet_pointing_at_the_field() {
    let registry = builtin_registry();
    let file = Path::new("tests/graphs/invalid/ill_typed_param.toml");
    let err = graph::load(file, &registry, &[]).err().expect("rejected");
    let shown = err.to_string();
    assert!(
        shown.contains("4 | params = { path = \"x\", step = \"two\" }"),
        "{shown}"
    );
    assert!(
        shown
            .lines()
            .last()
            .is_some_and(|l| l.trim_end().ends_with("^^^^")),
        "{shown}"
    );
}

#[test]
fn valid_graph_with_overrides() {
    let registry = builtin_registry();
    let file = Path::new("tests/graphs/valid/swap_and_override.toml");
    let sets = [
        "src.step=3",
        "gray.device=auto",
        "graph.frames.count=2",
        "files.log=false",
    ]
    .map(String::from);
    let g = graph::load(file, &registry, &sets).expect("valid");
    assert_eq!(g.frames.start, 1);
    assert_eq!(g.frames.count, Some(2));
    let ids: Vec<&str> = g.nodes.iter().map(|n| n.id.as_str()).collect();
    assert_eq!(ids, ["src", "gray", "files"], "topological order");
    let levels: Vec<usize> = g.nodes.iter().map(|n| n.level).collect();
    assert_eq!(levels, [0, 1, 2]);
    assert_eq!(g.nodes[0].params["step"].as_integer(), Some(3));
    assert_eq!(g.nodes[1].params["device"].as_str(), Some("auto"));
    assert!(!g.nodes[2].log);
    // `files` takes `left` from src (node 0, port 1) and `image` from gray (node 1, port 0).
    let files = &g.nodes[2];
    let left = files
        .plugin
        .info()
        .inputs
        .iter()
        .position(|p| p.name == "left")
        .unwrap();
    let image = files
        .plugin
        .info()
        .inputs
        .iter()
        .position(|p| p.name == "image")
        .unwrap();
    assert_eq!(files.inputs[left], Some(graph::Source { node: 0, port: 1 }));
    assert_eq!(
        files.inputs[image],
        Some(graph::Source { node: 1, port: 0 })
    );
}

#[test]
fn swapping_a_plugin_by_override_drops_params_it_does_not_take() {
    let mut registry = builtin_registry();
    // A second gray-like plugin id to swap to, with no parameters at all.
    #[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema, Default)]
    #[serde(deny_unknown_fields)]
    struct NoParams {}
    struct Nop;
    impl misslam::framework::Node for Nop {
        fn process(
            &mut self,
            _: &mut misslam::framework::NodeContext,
            _: misslam::framework::FrameInfo,
            _: &misslam::framework::Inputs,
            _: &mut misslam::framework::Outputs,
        ) -> misslam::framework::NodeResult<misslam::framework::Flow> {
            Ok(misslam::framework::Flow::Continue)
        }
    }
    use misslam::framework::{PortSpec, PortType};
    registry
        .register(misslam::framework::TypedPlugin::new(
            "image.nop",
            "test",
            vec![PortSpec::new("image", PortType::Image, "")],
            vec![PortSpec::new("gray", PortType::Image, "")],
            |_: NoParams, _| Ok(Nop),
        ))
        .unwrap();
    let text = "[[node]]\nid = \"src\"\nplugin = \"source.stereo_folder\"\n\n[[node]]\nid = \"gray\"\nplugin = \"image.gray\"\ninputs = { image = \"src.left\" }\nparams = { device = \"cpu\" }\n";
    let g = graph::parse(
        Path::new("swap.toml"),
        text,
        &registry,
        &["gray.plugin=image.nop".into()],
    )
    .expect("swap accepted");
    assert_eq!(g.nodes[1].plugin.info().id, "image.nop");
    assert!(g.nodes[1].params.is_empty());
    // A parameter set on the command line for the new plugin is still checked.
    let err = graph::parse(
        Path::new("swap.toml"),
        text,
        &registry,
        &["gray.plugin=image.nop".into(), "gray.device=gpu".into()],
    )
    .err()
    .expect("rejected");
    assert_eq!(
        err.headline(),
        "swap.toml: --set gray.device=gpu: node `gray` (image.nop): unknown parameter `device`; this plugin takes no parameters"
    );
}

/// The nodes built on the ED graph (the deformation solver and both fusion nodes) refuse a
/// wrong `graph` or `solver` value when the graph is built, naming the table and the field.
#[test]
fn ed_nodes_refuse_a_wrong_graph_or_solver_value_naming_it() {
    let registry = builtin_registry();
    for (file, node) in [
        ("graphs/deform_heart.toml", "ed"),
        ("graphs/mis_slam.toml", "fusion"),
        ("graphs/template_dff.toml", "fusion"),
    ] {
        for (set, table, field) in [
            ("solver.weights.reg=-1", "solver", "weights.reg"),
            ("graph.spacing=0", "graph", "spacing"),
        ] {
            let sets = [format!("{node}.{set}")];
            let g = graph::load(Path::new(file), &registry, &sets).expect("a valid graph");
            let err = misslam::framework::Runtime::build(g)
                .err()
                .unwrap_or_else(|| panic!("{file}: {set} was accepted"))
                .to_string();
            assert!(
                err.contains(&format!("parameter `{table}`")) && err.contains(field),
                "{file}: {set}: {err}"
            );
        }
    }
}

#[test]
fn a_nan_or_an_infinity_where_a_number_is_needed_is_refused_naming_it() {
    let registry = builtin_registry();
    for (set, field) in [
        (
            "src.distance_mm=inf",
            "`distance_mm` must be a finite number, got inf",
        ),
        (
            "src.ambient=nan",
            "`ambient` must be a finite number, got NaN",
        ),
        ("src.specular=-1", "`specular` must be >= 0"),
        (
            "post.smooth_sigma_mm=inf",
            "`smooth_sigma_mm` must be a positive number, got inf",
        ),
        (
            "fusion.stable_weight=nan",
            "must be a finite number >= 0, got NaN",
        ),
        (
            "fusion.rebind_distance_mm=-0.5",
            "parameter `rebind_distance_mm`: must be a finite number >= 0, got -0.5",
        ),
        (
            "fusion.data_points_per_node=-1",
            "parameter `data_points_per_node`: must be a finite number >= 0 (0: off), got -1",
        ),
        (
            "fusion.solve_points_per_node=inf",
            "parameter `solve_points_per_node`: must be a finite number >= 0 (0: off), got inf",
        ),
    ] {
        let sets = [set.to_string()];
        let g = graph::load(Path::new("graphs/mis_slam.toml"), &registry, &sets)
            .expect("a valid graph");
        let err = misslam::framework::Runtime::build(g)
            .err()
            .unwrap_or_else(|| panic!("{set} was accepted"))
            .to_string();
        let node = set.split('.').next().unwrap();
        assert!(
            err.contains(&format!("node `{node}`")) && err.contains(field),
            "{set}: {err}"
        );
    }
}
