//! TOML graphs: loading, `--set` overrides, and validation before any frame runs.
//!
//! ```toml
//! [graph]
//! name = "inspect"
//! frames = { start = 0, count = 10 }
//! on_error = "skip_frame"            # or "abort"
//!
//! [[node]]
//! id = "src"
//! plugin = "source.stereo_folder"
//! params = { path = "../shared/data/hamlyn20" }
//!
//! [[node]]
//! id = "gray"
//! plugin = "image.gray"
//! inputs = { image = "src.left" }
//! log = false
//! ```
//! Every error names the file, the line and column, and the field ([`GraphError`]).

mod error;

pub use error::{line_col, GraphError, Location};

use std::collections::{BTreeMap, HashMap};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;
use toml::Spanned;

use crate::registry::{closest, unknown_key_message, BuildError, Plugin, Registry};

/// The most threads a node may ask of its level's pool (`threads = N`).
pub const MAX_LEVEL_THREADS: u32 = 1024;
/// The highest nice value a node may ask for its level's pool (`nice = N`; Linux's lowest
/// priority).
pub const MAX_NICE: u32 = 19;

/// What the runtime does when a node fails on a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ErrorPolicy {
    /// Stop the run (after writing what was measured so far).
    #[default]
    Abort,
    /// Log the error, count the frame as skipped, go on with the next frame.
    SkipFrame,
}

/// Which frames of the input to run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct FrameRange {
    /// First frame index (default 0).
    #[serde(default)]
    pub start: u64,
    /// How many frames at most; all when absent.
    #[serde(default)]
    pub count: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileDoc {
    graph: Option<Spanned<GraphSection>>,
    #[serde(default)]
    node: Vec<Spanned<NodeSection>>,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields)]
struct GraphSection {
    name: Option<String>,
    description: Option<String>,
    frames: Option<FrameRange>,
    seed: Option<u64>,
    out: Option<String>,
    on_error: Option<ErrorPolicy>,
    parallel: Option<bool>,
    pipeline: Option<Spanned<u32>>,
    level_threads: Option<u32>,
    log_every: Option<Spanned<u32>>,
    #[serde(default)]
    libraries: Vec<Spanned<String>>,
}

/// Per input port of one node: its source and the span of the wiring in the file.
type Wiring = Vec<Option<(Source, Range<usize>)>>;

type SpannedTable = BTreeMap<Spanned<String>, Spanned<toml::Value>>;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct NodeSection {
    id: Spanned<String>,
    plugin: Spanned<String>,
    #[serde(default)]
    params: Option<Spanned<SpannedTable>>,
    #[serde(default)]
    inputs: Option<Spanned<BTreeMap<Spanned<String>, Spanned<String>>>>,
    log: Option<bool>,
    threads: Option<Spanned<i64>>,
    nice: Option<Spanned<i64>>,
}

/// Where an input of a validated node comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Source {
    /// Index of the producing node in [`Graph::nodes`].
    pub node: usize,
    /// Index of the output port in that node's outputs.
    pub port: usize,
}

/// A validated node.
#[derive(Clone)]
pub struct NodeSpec {
    /// Id in the graph.
    pub id: String,
    /// Its plugin.
    pub plugin: Arc<dyn Plugin>,
    /// Parameters after overrides, checked against the plugin.
    pub params: toml::Table,
    /// Source of each input port (declaration order); `None` for an unconnected optional input.
    pub inputs: Vec<Option<Source>>,
    /// Whether the recorder logs this node's outputs.
    pub log: bool,
    /// Threads this node asks of its level's pool in the pipelined schedule (`threads = N` in
    /// its table); a level's pool has the most any of its nodes asks, those without it asking
    /// for `[graph] level_threads` ([`Graph::level_pool_threads`]).
    pub threads: Option<u32>,
    /// Nice value this node asks for its level's pool in the pipelined schedule (`nice = N` in
    /// its table, 0 to [`MAX_NICE`]): a lower CPU priority, for nodes off the pipeline's
    /// critical path (scoring, export) so that they take the cores the others leave. A level's
    /// pool runs at the lowest value its nodes ask, those without it asking 0
    /// ([`Graph::level_pool_nice_of`]), so a node is never slowed by another's setting.
    pub nice: Option<u32>,
    /// Topological level: 0 for sources, else 1 + the highest level of its inputs.
    pub level: usize,
}

/// A validated graph, nodes in topological order (sorted by level, then by file order).
#[derive(Clone)]
pub struct Graph {
    /// The graph file.
    pub file: PathBuf,
    /// Its text (recorded with the run).
    pub text: String,
    /// `--set` arguments applied.
    pub overrides: Vec<String>,
    /// Name (the file stem when not given).
    pub name: String,
    /// Description.
    pub description: Option<String>,
    /// Frame range.
    pub frames: FrameRange,
    /// Seed for every random choice.
    pub seed: u64,
    /// Output folder, resolved against the current directory.
    pub out: PathBuf,
    /// Error policy.
    pub on_error: ErrorPolicy,
    /// Whether independent nodes of one level may run in parallel.
    pub parallel: bool,
    /// Frames in the graph at once: 1 runs each frame through every level before the next
    /// starts; more run the levels as a pipeline, each on its own thread, so that later frames
    /// are in the early levels while earlier ones are in the late levels (the same outputs, a
    /// higher throughput).
    pub pipeline: u32,
    /// Threads of each level's pool in the pipelined schedule (0: half the cores, at least 2;
    /// see [`Graph::level_pool_threads`]).
    pub level_threads: u32,
    /// The recorder logs images, maps, clouds, models and meshes on every `log_every`-th frame
    /// from the first, scalars and poses on every frame (at least 1; 1: everything every frame).
    pub log_every: u32,
    /// Nodes in topological order.
    pub nodes: Vec<NodeSpec>,
}

impl Graph {
    /// Threads of each level's pool in the pipelined schedule: `level_threads`, or with 0 half
    /// of `cores` (the threads rayon's global pool has, which `RAYON_NUM_THREADS` sets), at
    /// least 2. Every level with a pool of all the cores oversubscribed them: on the 16-core
    /// H100 machine (640x480, 3 frames in flight, 8 renderers) fusion's first parallel stage
    /// waited 7.4 to 7.6 ms for its threads, against 2.4 to 2.6 with pools of 8 (35.0 / 35.3
    /// against 39.5 / 40.9 frames a second).
    pub fn level_pool_threads(&self, cores: usize) -> usize {
        match self.level_threads {
            0 => cores.div_ceil(2).max(2),
            n => n as usize,
        }
    }

    /// Threads of the pool of the level made of `nodes` (indices into [`Graph::nodes`]): the
    /// most any of them asks ([`NodeSpec::threads`]), `default` for those that do not say.
    pub fn level_pool_threads_of(&self, nodes: Range<usize>, default: usize) -> usize {
        self.nodes[nodes]
            .iter()
            .map(|n| n.threads.map_or(default, |t| t as usize))
            .max()
            .unwrap_or(default)
    }

    /// Nice value of the pool of the level made of `nodes`: the lowest any of them asks
    /// ([`NodeSpec::nice`]), 0 for those that do not say.
    pub fn level_pool_nice_of(&self, nodes: Range<usize>) -> u32 {
        self.nodes[nodes]
            .iter()
            .map(|n| n.nice.unwrap_or(0))
            .min()
            .unwrap_or(0)
    }

    /// Folder of the graph file.
    pub fn dir(&self) -> &Path {
        self.file.parent().unwrap_or(Path::new("."))
    }

    /// Index of the node with this id.
    pub fn node_index(&self, id: &str) -> Option<usize> {
        self.nodes.iter().position(|n| n.id == id)
    }
}

/// A parsed `--set id.path=value` argument.
#[derive(Clone, Debug)]
struct Override {
    arg: String,
    target: String,
    path: Vec<String>,
    value: toml::Value,
}

fn parse_override(file: &Path, arg: &str) -> Result<Override, GraphError> {
    let err = |m: &str| GraphError::at_override(file, arg, m.to_owned());
    let (lhs, rhs) = arg
        .split_once('=')
        .ok_or_else(|| err("expected `node.param=value`"))?;
    let mut parts = lhs.trim().split('.');
    let target = parts.next().unwrap_or_default().to_owned();
    let path: Vec<String> = parts.map(str::to_owned).collect();
    if target.is_empty() || path.is_empty() || path.iter().any(String::is_empty) {
        return Err(err(
            "expected `node.param=value` (a node id, a dot, a parameter)",
        ));
    }
    let rhs = rhs.trim();
    // A TOML value when it parses as one (8, 0.5, true, "x", [1, 2]); else a bare string.
    let value = toml::from_str::<toml::Table>(&format!("v = {rhs}"))
        .ok()
        .and_then(|mut t| t.remove("v"))
        .unwrap_or_else(|| toml::Value::String(rhs.to_owned()));
    Ok(Override {
        arg: arg.to_owned(),
        target,
        path,
        value,
    })
}

/// Reads, overrides and validates a graph file. `registry` supplies the built-in plugins; the
/// graph's `libraries` add dynamic ones.
pub fn load(path: &Path, registry: &Registry, overrides: &[String]) -> Result<Graph, GraphError> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| GraphError::whole(path, format!("cannot read the graph file: {e}")))?;
    parse(path, &text, registry, overrides)
}

/// Like [`load`], from text already read.
pub fn parse(
    file: &Path,
    text: &str,
    registry: &Registry,
    overrides: &[String],
) -> Result<Graph, GraphError> {
    let doc: FileDoc = toml::from_str(text).map_err(|e| {
        let span = e.span().unwrap_or(0..0);
        GraphError::at(file, text, span, e.message().trim().to_owned())
    })?;
    let at = |span: Range<usize>, msg: String| GraphError::at(file, text, span, msg);

    let mut section = doc.graph.map(Spanned::into_inner).unwrap_or_default();

    // Dynamic plugin libraries extend the registry.
    let mut registry = registry.clone();
    for lib in &section.libraries {
        // Relative to the working directory, like every path in a graph.
        let lib_path = PathBuf::from(lib.get_ref());
        let plugin = crate::dynamic::load_library(&lib_path)
            .map_err(|e| at(lib.span(), format!("plugin library: {e}")))?;
        registry
            .register_arc(plugin)
            .map_err(|e| at(lib.span(), e))?;
    }

    // Parse overrides; graph-level ones apply now, node ones below.
    let parsed: Vec<Override> = overrides
        .iter()
        .map(|a| parse_override(file, a))
        .collect::<Result<_, _>>()?;
    for o in parsed.iter().filter(|o| o.target == "graph") {
        apply_graph_override(file, &mut section, o)?;
    }
    if let Some(p) = section.log_every.as_ref().filter(|p| *p.get_ref() == 0) {
        return Err(at(
            p.span(),
            "`log_every` takes a number of frames, at least 1 (1: log everything every frame)"
                .into(),
        ));
    }
    if let Some(p) = section.pipeline.as_ref().filter(|p| *p.get_ref() == 0) {
        return Err(at(
            p.span(),
            "`pipeline` takes the number of frames in the graph at once, at least 1 (1: one frame at a time)".into(),
        ));
    }

    // Nodes: ids, plugins, params.
    struct Pending {
        id: String,
        plugin: Arc<dyn Plugin>,
        params: toml::Table,
        inputs: Vec<(Spanned<String>, Spanned<String>)>,
        inputs_span: Range<usize>,
        log: bool,
        threads: Option<u32>,
        nice: Option<u32>,
    }
    let mut seen: HashMap<String, Range<usize>> = HashMap::new();
    let mut pending: Vec<Pending> = Vec::new();
    // Output folders claimed so far (see `Plugin::output_dirs`), with the claiming node.
    let mut claimed: HashMap<PathBuf, String> = HashMap::new();
    for node in doc.node {
        let node_span = node.span();
        let node = node.into_inner();
        let id = node.id.get_ref().clone();
        if !valid_id(&id) {
            return Err(at(
                node.id.span(),
                format!("node id `{id}` must be letters, digits and `_` (it names Rerun paths and `--set` targets)"),
            ));
        }
        if let Some(first) = seen.get(&id) {
            let (line, _) = line_col(text, first.start);
            return Err(at(
                node.id.span(),
                format!("duplicate node id `{id}` (first defined on line {line})"),
            ));
        }
        seen.insert(id.clone(), node.id.span());
        let my_overrides: Vec<&Override> = parsed.iter().filter(|o| o.target == id).collect();

        // The plugin, possibly swapped by `--set id.plugin=...`.
        let mut plugin_id = node.plugin.get_ref().clone();
        let mut plugin_override: Option<&Override> = None;
        for o in &my_overrides {
            if o.path == ["plugin"] {
                plugin_id = o
                    .value
                    .as_str()
                    .ok_or_else(|| {
                        GraphError::at_override(file, &o.arg, "`plugin` takes a plugin id")
                    })?
                    .to_owned();
                plugin_override = Some(o);
            }
        }
        let plugin = registry.get(&plugin_id).cloned().ok_or_else(|| {
            let mut msg = format!("node `{id}`: unknown plugin `{plugin_id}`");
            if let Some(best) = closest(&plugin_id, registry.ids()) {
                msg.push_str(&format!(" (did you mean `{best}`?)"));
            }
            msg.push_str("; `misslam plugins` lists them");
            match plugin_override {
                Some(o) => GraphError::at_override(file, &o.arg, msg),
                None => at(node.plugin.span(), msg),
            }
        })?;

        // Params from the file, with the span of each key.
        let mut params = toml::Table::new();
        let mut key_spans: HashMap<String, Range<usize>> = HashMap::new();
        if let Some(p) = &node.params {
            for (k, v) in p.get_ref() {
                key_spans.insert(k.get_ref().clone(), k.span());
                params.insert(k.get_ref().clone(), v.get_ref().clone());
            }
        }
        // A plugin swapped from the command line drops the file's params it does not know.
        if plugin_override.is_some() && plugin_id != *node.plugin.get_ref() {
            let info = plugin.info();
            let dropped: Vec<String> = params
                .keys()
                .filter(|k| info.param(k).is_none())
                .cloned()
                .collect();
            for k in &dropped {
                params.remove(k);
            }
            if !dropped.is_empty() {
                tracing::warn!(
                    "node `{id}`: plugin swapped to `{plugin_id}`, which does not take {}; dropped",
                    dropped.join(", ")
                );
            }
        }
        let mut log = node.log.unwrap_or(true);
        let threads_msg = |n: i64| {
            format!(
                "node `{id}`: `threads` takes a number of threads from 1 to {MAX_LEVEL_THREADS}, \
                 got {n}"
            )
        };
        let check_threads = |n: i64| (1..=MAX_LEVEL_THREADS as i64).contains(&n);
        let mut threads = match &node.threads {
            Some(t) if !check_threads(*t.get_ref()) => {
                return Err(at(t.span(), threads_msg(*t.get_ref())))
            }
            t => t.as_ref().map(|t| *t.get_ref() as u32),
        };
        let nice_msg = |n: i64| {
            format!("node `{id}`: `nice` takes a nice value from 0 to {MAX_NICE} (a lower priority), got {n}")
        };
        let check_nice = |n: i64| (0..=MAX_NICE as i64).contains(&n);
        let mut nice = match &node.nice {
            Some(t) if !check_nice(*t.get_ref()) => {
                return Err(at(t.span(), nice_msg(*t.get_ref())))
            }
            t => t.as_ref().map(|t| *t.get_ref() as u32),
        };
        let mut overridden: HashMap<String, String> = HashMap::new();
        for o in &my_overrides {
            match o.path.first().map(String::as_str) {
                Some("plugin") if o.path.len() == 1 => {}
                Some("log") if o.path.len() == 1 => {
                    log = o.value.as_bool().ok_or_else(|| {
                        GraphError::at_override(file, &o.arg, "`log` takes true or false")
                    })?;
                }
                Some("threads") if o.path.len() == 1 => {
                    let n = o.value.as_integer().ok_or_else(|| {
                        GraphError::at_override(file, &o.arg, "`threads` takes an integer")
                    })?;
                    if !check_threads(n) {
                        return Err(GraphError::at_override(file, &o.arg, threads_msg(n)));
                    }
                    threads = Some(n as u32);
                }
                Some("nice") if o.path.len() == 1 => {
                    let n = o.value.as_integer().ok_or_else(|| {
                        GraphError::at_override(file, &o.arg, "`nice` takes an integer")
                    })?;
                    if !check_nice(n) {
                        return Err(GraphError::at_override(file, &o.arg, nice_msg(n)));
                    }
                    nice = Some(n as u32);
                }
                _ => {
                    set_path(&mut params, &o.path, o.value.clone()).map_err(|m| {
                        GraphError::at_override(file, &o.arg, format!("node `{id}`: {m}"))
                    })?;
                    overridden.insert(o.path[0].clone(), o.arg.clone());
                }
            }
        }
        plugin.check_params(&params).map_err(|e| {
            let key = match &e {
                BuildError::Param { key, .. } => key.clone(),
                BuildError::Failed(_) => None,
            };
            let msg = format!("node `{id}` ({plugin_id}): {e}");
            match key {
                Some(k) if overridden.contains_key(&k) => {
                    GraphError::at_override(file, &overridden[&k], msg)
                }
                Some(k) if key_spans.contains_key(&k) => at(key_spans[&k].clone(), msg),
                _ => at(
                    node.params.as_ref().map_or(node_span.clone(), |p| p.span()),
                    msg,
                ),
            }
        })?;

        // Two nodes writing one folder would overwrite each other's files.
        for (key, dir) in plugin.output_dirs(&params) {
            let norm: PathBuf = dir
                .components()
                .filter(|c| !matches!(c, std::path::Component::CurDir))
                .collect();
            if let Some(other) = claimed.get(&norm) {
                let msg = format!(
                    "node `{id}` ({plugin_id}): `{key}` = \"{}\" is the folder node `{other}` \
                     already writes (the files of one would overwrite the other's); give each \
                     its own `{key}`",
                    dir.display()
                );
                return Err(match overridden.get(&key) {
                    Some(arg) => GraphError::at_override(file, arg, msg),
                    None => at(key_spans.get(&key).cloned().unwrap_or(node_span), msg),
                });
            }
            claimed.insert(norm, id.clone());
        }

        let inputs_span = node.inputs.as_ref().map_or(node.id.span(), |i| i.span());
        let inputs = node
            .inputs
            .map(|i| i.into_inner().into_iter().collect())
            .unwrap_or_default();
        pending.push(Pending {
            id,
            plugin,
            params,
            inputs,
            inputs_span,
            log,
            threads,
            nice,
        });
    }
    if pending.is_empty() {
        return Err(GraphError::whole(
            file,
            "the graph has no nodes (add `[[node]]` tables)",
        ));
    }
    for o in parsed.iter().filter(|o| o.target != "graph") {
        if !seen.contains_key(&o.target) {
            let ids: Vec<String> = pending.iter().map(|p| p.id.clone()).collect();
            return Err(GraphError::at_override(
                file,
                &o.arg,
                unknown_key_message("node", &o.target, &ids),
            ));
        }
    }

    // Wiring: resolve "node.port" against declared ports and check types.
    let index: HashMap<&str, usize> = pending
        .iter()
        .enumerate()
        .map(|(i, p)| (p.id.as_str(), i))
        .collect();
    let mut wired: Vec<Wiring> = Vec::with_capacity(pending.len());
    for p in &pending {
        let info = p.plugin.info();
        let mut slots: Wiring = vec![None; info.inputs.len()];
        for (port, from) in &p.inputs {
            let Some(pi) = info.inputs.iter().position(|s| s.name == *port.get_ref()) else {
                let known: Vec<String> = info.inputs.iter().map(|s| s.name.clone()).collect();
                return Err(at(
                    port.span(),
                    format!(
                        "node `{}` ({}): {}",
                        p.id,
                        info.id,
                        unknown_key_message("input port", port.get_ref(), &known)
                    ),
                ));
            };
            let Some((src_id, src_port)) = from.get_ref().split_once('.') else {
                return Err(at(
                    from.span(),
                    format!(
                        "node `{}`: input `{}` must name `node.port`, got `{}`",
                        p.id,
                        port.get_ref(),
                        from.get_ref()
                    ),
                ));
            };
            let Some(&si) = index.get(src_id) else {
                let ids: Vec<String> = pending.iter().map(|q| q.id.clone()).collect();
                return Err(at(
                    from.span(),
                    format!(
                        "node `{}`: input `{}`: {}",
                        p.id,
                        port.get_ref(),
                        unknown_key_message("node", src_id, &ids)
                    ),
                ));
            };
            let src_info = pending[si].plugin.info();
            let Some(so) = src_info.outputs.iter().position(|s| s.name == src_port) else {
                let known: Vec<String> = src_info.outputs.iter().map(|s| s.name.clone()).collect();
                return Err(at(
                    from.span(),
                    format!(
                        "node `{}`: input `{}`: node `{src_id}` ({}) has {}",
                        p.id,
                        port.get_ref(),
                        src_info.id,
                        unknown_key_message("output port", src_port, &known)
                            .replacen("unknown ", "no ", 1)
                    ),
                ));
            };
            // An optional output the source's parameters leave unproduced would reach an
            // optional input as nothing, frame after frame.
            if let Some((_, how)) = pending[si]
                .plugin
                .absent_outputs(&pending[si].params)
                .into_iter()
                .find(|(name, _)| name == src_port)
            {
                return Err(at(
                    from.span(),
                    format!(
                        "node `{}`: input `{}`: node `{src_id}` ({}) does not produce `{src_port}` \
                         with its parameters: {how}",
                        p.id,
                        port.get_ref(),
                        src_info.id,
                    ),
                ));
            }
            let (want, have) = (info.inputs[pi].ty, src_info.outputs[so].ty);
            if want != have {
                return Err(at(
                    from.span(),
                    format!(
                        "node `{}`: input `{}` takes {want}, but `{}` is {have}",
                        p.id,
                        port.get_ref(),
                        from.get_ref()
                    ),
                ));
            }
            slots[pi] = Some((Source { node: si, port: so }, from.span()));
        }
        for (pi, spec) in info.inputs.iter().enumerate() {
            if slots[pi].is_none() && !spec.optional {
                return Err(at(
                    p.inputs_span.clone(),
                    format!(
                        "node `{}` ({}): required input `{}` ({}) is not connected",
                        p.id, info.id, spec.name, spec.ty
                    ),
                ));
            }
        }
        wired.push(slots);
    }

    // Topological levels (Kahn); what remains is a cycle.
    let n = pending.len();
    let mut level = vec![usize::MAX; n];
    let mut done = 0;
    while done < n {
        let mut progressed = false;
        for i in 0..n {
            if level[i] != usize::MAX {
                continue;
            }
            let mut lvl = 0;
            let mut ready = true;
            for (src, _) in wired[i].iter().flatten() {
                if level[src.node] == usize::MAX {
                    ready = false;
                    break;
                }
                lvl = lvl.max(level[src.node] + 1);
            }
            if ready {
                level[i] = lvl;
                done += 1;
                progressed = true;
            }
        }
        if !progressed {
            let (cycle, span) = find_cycle(
                &wired,
                &level,
                &pending.iter().map(|p| p.id.as_str()).collect::<Vec<_>>(),
            );
            return Err(at(span, format!("cycle: {cycle}")));
        }
    }

    // Order nodes by level (stable: file order within a level) and remap sources.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by_key(|&i| level[i]);
    let mut new_index = vec![0; n];
    for (new, &old) in order.iter().enumerate() {
        new_index[old] = new;
    }
    let mut pending: Vec<Option<Pending>> = pending.into_iter().map(Some).collect();
    let mut nodes = Vec::with_capacity(n);
    for &old in &order {
        let p = pending[old].take().expect("each node is taken once");
        nodes.push(NodeSpec {
            id: p.id,
            plugin: p.plugin,
            params: p.params,
            inputs: wired[old]
                .iter()
                .map(|s| {
                    s.as_ref().map(|(src, _)| Source {
                        node: new_index[src.node],
                        port: src.port,
                    })
                })
                .collect(),
            log: p.log,
            threads: p.threads,
            nice: p.nice,
            level: level[old],
        });
    }

    let name = section.name.clone().unwrap_or_else(|| {
        file.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "graph".to_owned())
    });
    let out = section
        .out
        .clone()
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new("out").join(&name));
    Ok(Graph {
        file: file.to_owned(),
        text: text.to_owned(),
        overrides: overrides.to_vec(),
        name,
        description: section.description.clone(),
        frames: section.frames.unwrap_or_default(),
        seed: section.seed.unwrap_or(0),
        out,
        on_error: section.on_error.unwrap_or_default(),
        parallel: section.parallel.unwrap_or(true),
        pipeline: section.pipeline.as_ref().map_or(1, |p| *p.get_ref()),
        level_threads: section.level_threads.unwrap_or(0),
        log_every: section.log_every.as_ref().map_or(1, |p| *p.get_ref()),
        nodes,
    })
}

fn valid_id(id: &str) -> bool {
    !id.is_empty() && id.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') && id != "graph"
}

fn apply_graph_override(file: &Path, g: &mut GraphSection, o: &Override) -> Result<(), GraphError> {
    let err = |m: String| GraphError::at_override(file, &o.arg, m);
    let key = o.path.join(".");
    let v = &o.value;
    let want_int = || {
        v.as_integer()
            .filter(|i| *i >= 0)
            .map(|i| i as u64)
            .ok_or_else(|| err(format!("`graph.{key}` takes a non-negative integer")))
    };
    // A u32 of at least `min`, else the error `what` names.
    let want_u32 = |min: u32, what: &str| {
        v.as_integer()
            .and_then(|n| u32::try_from(n).ok())
            .filter(|&n| n >= min)
            .ok_or_else(|| err(format!("`graph.{key}` takes {what}")))
    };
    match key.as_str() {
        "seed" => g.seed = Some(want_int()?),
        "frames.start" => g.frames.get_or_insert_with(FrameRange::default).start = want_int()?,
        "frames.count" => g.frames.get_or_insert_with(FrameRange::default).count = Some(want_int()?),
        "name" => g.name = Some(v.as_str().ok_or_else(|| err("`graph.name` takes a string".into()))?.to_owned()),
        "out" => g.out = Some(v.as_str().ok_or_else(|| err("`graph.out` takes a path".into()))?.to_owned()),
        "parallel" => g.parallel = Some(v.as_bool().ok_or_else(|| err("`graph.parallel` takes true or false".into()))?),
        "pipeline" => {
            let n = want_u32(1, "the number of frames in the graph at once, at least 1")?;
            g.pipeline = Some(Spanned::new(0..0, n));
        }
        "level_threads" => {
            g.level_threads = Some(want_u32(0, "a number of threads (0: half the cores)")?);
        }
        "log_every" => {
            let n = want_u32(1, "a number of frames, at least 1")?;
            g.log_every = Some(Spanned::new(0..0, n));
        }
        "on_error" => {
            g.on_error = Some(match v.as_str() {
                Some("abort") => ErrorPolicy::Abort,
                Some("skip_frame") => ErrorPolicy::SkipFrame,
                _ => return Err(err("`graph.on_error` takes \"abort\" or \"skip_frame\"".into())),
            })
        }
        _ => {
            return Err(err(format!(
                "unknown graph setting `{key}`; known: seed, frames.start, frames.count, name, out, parallel, pipeline, level_threads, log_every, on_error"
            )))
        }
    }
    Ok(())
}

fn set_path(table: &mut toml::Table, path: &[String], value: toml::Value) -> Result<(), String> {
    let (last, parents) = path.split_last().ok_or("empty parameter path")?;
    let mut t = table;
    for (i, p) in parents.iter().enumerate() {
        let entry = t
            .entry(p.clone())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        t = entry
            .as_table_mut()
            .ok_or_else(|| format!("`{}` is not a table", path[..=i].join(".")))?;
    }
    t.insert(last.clone(), value);
    Ok(())
}

fn find_cycle(wired: &[Wiring], level: &[usize], ids: &[&str]) -> (String, Range<usize>) {
    // Walk backwards along unresolved inputs from an unresolved node until a node repeats.
    let start = level.iter().position(|&l| l == usize::MAX).unwrap_or(0);
    let mut path = vec![start];
    let mut spans = Vec::new();
    let mut cur = start;
    loop {
        let next = wired[cur]
            .iter()
            .flatten()
            .find(|(s, _)| level[s.node] == usize::MAX);
        let Some((src, span)) = next else { break };
        spans.push(span.clone());
        if let Some(pos) = path.iter().position(|&n| n == src.node) {
            // `path` runs against the data flow; print it along the flow, closing the loop.
            let mut cyc = vec![ids[src.node]];
            cyc.extend(path[pos + 1..].iter().rev().map(|&i| ids[i]));
            cyc.push(ids[src.node]);
            let names: Vec<String> = cyc.iter().map(|s| format!("`{s}`")).collect();
            return (names.join(" -> "), spans[pos].clone());
        }
        path.push(src.node);
        cur = src.node;
    }
    (format!("`{}` depends on itself", ids[start]), 0..0)
}
