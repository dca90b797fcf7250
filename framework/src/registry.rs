//! Plugins by id: what each one declares (ports, parameters) and how it builds a node.
//!
//! A built-in plugin is a typed parameter struct (serde + schemars, `deny_unknown_fields`, a doc
//! comment and a default on every field) and a function that builds the node from it. The docs
//! that `misslam plugins ID` prints are generated from the same struct, so they cannot drift.

use std::collections::BTreeMap;
use std::marker::PhantomData;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::gpu::GpuProvider;
use crate::node::{Node, NodeError, PortSpec};

/// One documented parameter.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ParamDoc {
    /// Key in the graph's `params` table.
    pub name: String,
    /// Type in words, e.g. `integer (u32)`, `"cpu" | "gpu" | "auto"`.
    pub ty: String,
    /// Default as TOML, when the parameter has one.
    pub default: Option<String>,
    /// What it does.
    pub doc: String,
}

/// What a plugin declares.
#[derive(Clone, Debug)]
pub struct PluginInfo {
    /// Id used in graphs, `role.name`.
    pub id: String,
    /// One line.
    pub summary: String,
    /// Input ports.
    pub inputs: Vec<PortSpec>,
    /// Output ports.
    pub outputs: Vec<PortSpec>,
    /// Parameters.
    pub params: Vec<ParamDoc>,
    /// Where it comes from: `built-in` or a library path.
    pub origin: String,
}

impl PluginInfo {
    /// The input port named `name`.
    pub fn input(&self, name: &str) -> Option<&PortSpec> {
        self.inputs.iter().find(|p| p.name == name)
    }

    /// The output port named `name`.
    pub fn output(&self, name: &str) -> Option<&PortSpec> {
        self.outputs.iter().find(|p| p.name == name)
    }

    /// The parameter named `name`.
    pub fn param(&self, name: &str) -> Option<&ParamDoc> {
        self.params.iter().find(|p| p.name == name)
    }
}

/// Why a node could not be built.
#[derive(Debug, Clone, PartialEq)]
pub enum BuildError {
    /// A parameter is wrong; `key` is the top-level parameter at fault, when known.
    Param {
        /// Top-level key.
        key: Option<String>,
        /// Full path inside the parameter, e.g. `window.width`.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// Anything else (a file that cannot be read, no GPU, ...).
    Failed(String),
}

impl BuildError {
    /// A wrong parameter at `path` (e.g. `graph.spacing`); its first component is the key.
    pub fn param(path: &str, message: impl Into<String>) -> Self {
        BuildError::Param {
            key: Some(path.split('.').next().unwrap_or(path).to_owned()),
            path: path.to_owned(),
            message: message.into(),
        }
    }
}

impl std::fmt::Display for BuildError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            BuildError::Param { path, message, .. } if path.is_empty() || path == "." => {
                f.write_str(message)
            }
            BuildError::Param { path, message, .. } => write!(f, "parameter `{path}`: {message}"),
            BuildError::Failed(m) => f.write_str(m),
        }
    }
}

impl From<NodeError> for BuildError {
    fn from(e: NodeError) -> Self {
        BuildError::Failed(e.message().to_owned())
    }
}

/// What a plugin may use while it builds its node.
pub struct BuildContext<'a> {
    /// The node's id.
    pub node_id: &'a str,
    /// Folder of the graph file (relative paths in parameters are relative to the working
    /// directory, like paths given on the command line; this is for plugins that want more).
    pub graph_dir: &'a Path,
    /// The graph's seed.
    pub seed: u64,
    /// The shared GPU device.
    pub gpu: &'a GpuProvider,
}

/// A plugin: declares itself and builds nodes.
pub trait Plugin: Send + Sync {
    /// Ports, parameters and docs.
    fn info(&self) -> &PluginInfo;
    /// Checks parameters without building (no files opened, no device created).
    fn check_params(&self, params: &toml::Table) -> Result<(), BuildError>;
    /// Builds a node from parameters.
    fn build(&self, params: &toml::Table, ctx: &BuildContext) -> Result<Box<dyn Node>, BuildError>;
    /// Folders under the run's output folder that a node with these (checked) parameters
    /// writes, each with the parameter that names it. Graph loading refuses two nodes that
    /// claim the same folder (they would overwrite each other's files).
    fn output_dirs(&self, _params: &toml::Table) -> Vec<(String, PathBuf)> {
        Vec::new()
    }
    /// Optional outputs a node with these (checked) parameters never produces, each with what
    /// would make it produce them (such as "set `camera_model = true`"). Graph loading refuses
    /// an input wired to one: an optional input would otherwise silently get nothing.
    fn absent_outputs(&self, _params: &toml::Table) -> Vec<(String, String)> {
        Vec::new()
    }
    /// Every parameter a node built from `params` runs with, defaults filled in (what
    /// `metrics.json` records); `None` where the plugin cannot say (a dynamic plugin).
    fn resolved_params(&self, _params: &toml::Table) -> Option<serde_json::Value> {
        None
    }
}

/// The folders a typed plugin's node writes, from its parameters.
type OutputDirsFn<P> = dyn Fn(&P) -> Vec<(String, PathBuf)> + Send + Sync;

/// The optional outputs a typed plugin's node never produces, from its parameters.
type AbsentOutputsFn<P> = dyn Fn(&P) -> Vec<(String, String)> + Send + Sync;

/// Parses a typed parameter struct from a TOML table, naming the path of whatever is wrong.
///
/// The table is laid over `P::default()`, table by table: a nested table the graph gives only
/// in part (`solver = { max_iterations = 2 }`) keeps the plugin's own defaults for the rest,
/// where plain deserialisation would take the nested type's defaults (a plugin that sets a
/// nested default of its own, such as `fusion.template`'s `decoupled.level2_rings = 0`, would
/// lose it as soon as any other key of that table is set). A parameter type must not use
/// `#[serde(alias)]`: the alias and the default's own key would both be present.
pub fn parse_params<P: DeserializeOwned + Serialize + Default>(
    params: &toml::Table,
) -> Result<P, BuildError> {
    let mut value = match toml::Value::try_from(P::default()) {
        Ok(v @ toml::Value::Table(_)) => v,
        Ok(_) => toml::Value::Table(toml::Table::new()),
        Err(e) => {
            return Err(BuildError::Failed(format!(
                "the plugin's default parameters cannot be written as TOML: {e}"
            )))
        }
    };
    merge_over(&mut value, params);
    serde_path_to_error::deserialize::<_, P>(value).map_err(|e| {
        let path = e.path().to_string();
        let key = e.path().iter().next().and_then(|seg| match seg {
            serde_path_to_error::Segment::Map { key } => Some(key.clone()),
            _ => None,
        });
        // toml appends "in `key`" on a second line; the path already says where.
        let message = e.into_inner().to_string();
        let message = message.lines().next().unwrap_or_default().trim().to_owned();
        BuildError::Param { key, path, message }
    })
}

/// Lays `over` onto `base` key by key: tables present in both merge, anything else replaces.
fn merge_over(base: &mut toml::Value, over: &toml::Table) {
    let toml::Value::Table(b) = base else {
        *base = toml::Value::Table(over.clone());
        return;
    };
    for (k, v) in over {
        match (b.get_mut(k), v) {
            (Some(bv @ toml::Value::Table(_)), toml::Value::Table(ov)) => merge_over(bv, ov),
            _ => {
                b.insert(k.clone(), v.clone());
            }
        }
    }
}

type BuildFn<P> = dyn Fn(P, &BuildContext) -> Result<Box<dyn Node>, BuildError> + Send + Sync;

/// A plugin made of a typed parameter struct `P` and a build function.
pub struct TypedPlugin<P> {
    info: PluginInfo,
    known: Option<Vec<String>>,
    build: Box<BuildFn<P>>,
    output_dirs: Option<Box<OutputDirsFn<P>>>,
    absent_outputs: Option<Box<AbsentOutputsFn<P>>>,
    _p: PhantomData<fn() -> P>,
}

impl<P> TypedPlugin<P>
where
    P: DeserializeOwned + Serialize + Default + schemars::JsonSchema + 'static,
{
    /// A plugin `id` with `summary`, ports, and a function building its node from `P`.
    pub fn new<N: Node + 'static>(
        id: &str,
        summary: &str,
        inputs: Vec<PortSpec>,
        outputs: Vec<PortSpec>,
        build: impl Fn(P, &BuildContext) -> Result<N, BuildError> + Send + Sync + 'static,
    ) -> Self {
        let schema = schemars::schema_for!(P);
        let (params, known) = param_docs(schema.as_value());
        TypedPlugin {
            info: PluginInfo {
                id: id.to_owned(),
                summary: summary.to_owned(),
                inputs,
                outputs,
                params,
                origin: "built-in".to_owned(),
            },
            known,
            build: Box::new(move |p, ctx| build(p, ctx).map(|n| Box::new(n) as Box<dyn Node>)),
            output_dirs: None,
            absent_outputs: None,
            _p: PhantomData,
        }
    }

    /// Declares the folders (under the run's output folder) a node writes, each with the
    /// parameter naming it (see [`Plugin::output_dirs`]).
    pub fn with_output_dirs(
        mut self,
        f: impl Fn(&P) -> Vec<(String, PathBuf)> + Send + Sync + 'static,
    ) -> Self {
        self.output_dirs = Some(Box::new(f));
        self
    }

    /// Declares the optional outputs a node with given parameters never produces, each with
    /// what would make it produce them (see [`Plugin::absent_outputs`]).
    pub fn with_absent_outputs(
        mut self,
        f: impl Fn(&P) -> Vec<(String, String)> + Send + Sync + 'static,
    ) -> Self {
        self.absent_outputs = Some(Box::new(f));
        self
    }
}

impl<P> Plugin for TypedPlugin<P>
where
    P: DeserializeOwned + Serialize + Default + schemars::JsonSchema + 'static,
{
    fn info(&self) -> &PluginInfo {
        &self.info
    }

    fn check_params(&self, params: &toml::Table) -> Result<(), BuildError> {
        if let Some(known) = &self.known {
            for key in params.keys() {
                if !known.iter().any(|k| k == key) {
                    return Err(BuildError::Param {
                        key: Some(key.clone()),
                        path: String::new(),
                        message: unknown_key_message("parameter", key, known),
                    });
                }
            }
        }
        parse_params::<P>(params).map(|_| ())
    }

    fn build(&self, params: &toml::Table, ctx: &BuildContext) -> Result<Box<dyn Node>, BuildError> {
        self.check_params(params)?;
        let p = parse_params::<P>(params)?;
        (self.build)(p, ctx)
    }

    fn output_dirs(&self, params: &toml::Table) -> Vec<(String, PathBuf)> {
        match (&self.output_dirs, parse_params::<P>(params)) {
            (Some(f), Ok(p)) => f(&p),
            _ => Vec::new(),
        }
    }

    fn absent_outputs(&self, params: &toml::Table) -> Vec<(String, String)> {
        match (&self.absent_outputs, parse_params::<P>(params)) {
            (Some(f), Ok(p)) => f(&p),
            _ => Vec::new(),
        }
    }

    fn resolved_params(&self, params: &toml::Table) -> Option<serde_json::Value> {
        parse_params::<P>(params)
            .ok()
            .and_then(|p| serde_json::to_value(&p).ok())
    }
}

/// "unknown parameter `pths` (did you mean `paths`?); known: a, b".
pub fn unknown_key_message(what: &str, key: &str, known: &[String]) -> String {
    let mut msg = format!("unknown {what} `{key}`");
    if let Some(best) = closest(key, known.iter().map(String::as_str)) {
        msg.push_str(&format!(" (did you mean `{best}`?)"));
    }
    if known.is_empty() {
        msg.push_str(&format!("; this plugin takes no {what}s"));
    } else {
        msg.push_str(&format!("; known: {}", known.join(", ")));
    }
    msg
}

/// The candidate closest to `word` by edit distance, if close enough to be a typo.
pub fn closest<'a>(word: &str, candidates: impl Iterator<Item = &'a str>) -> Option<&'a str> {
    candidates
        .map(|c| (edit_distance(word, c), c))
        .filter(|&(d, c)| d <= (c.len().max(word.len()) / 3).max(1))
        .min_by_key(|&(d, _)| d)
        .map(|(_, c)| c)
}

/// Optimal string alignment distance: edits plus adjacent transpositions (`stpe` -> `step` is 1).
fn edit_distance(a: &str, b: &str) -> usize {
    let a: Vec<char> = a.chars().collect();
    let b: Vec<char> = b.chars().collect();
    let w = b.len() + 1;
    let mut d = vec![0usize; (a.len() + 1) * w];
    for i in 0..=a.len() {
        d[i * w] = i;
    }
    for (j, v) in d.iter_mut().enumerate().take(w) {
        *v = j;
    }
    for i in 1..=a.len() {
        for j in 1..=b.len() {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut best = (d[(i - 1) * w + j] + 1)
                .min(d[i * w + j - 1] + 1)
                .min(d[(i - 1) * w + j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                best = best.min(d[(i - 2) * w + j - 2] + 1);
            }
            d[i * w + j] = best;
        }
    }
    d[a.len() * w + b.len()]
}

/// Parameter docs from a JSON schema, and the known keys when unknown ones are denied.
fn param_docs(schema: &serde_json::Value) -> (Vec<ParamDoc>, Option<Vec<String>>) {
    let defs = schema.get("$defs");
    let mut docs = Vec::new();
    let Some(props) = schema.get("properties").and_then(|p| p.as_object()) else {
        let closed = schema.get("additionalProperties") == Some(&serde_json::Value::Bool(false));
        return (docs, closed.then(Vec::new));
    };
    for (name, prop) in props {
        docs.push(ParamDoc {
            name: name.clone(),
            ty: type_words(prop, defs),
            default: prop
                .get("default")
                .filter(|d| !d.is_null())
                .map(json_to_toml_text),
            doc: prop
                .get("description")
                .and_then(|d| d.as_str())
                .unwrap_or("")
                .replace('\n', " "),
        });
    }
    let closed = schema.get("additionalProperties") == Some(&serde_json::Value::Bool(false));
    let known = closed.then(|| docs.iter().map(|d| d.name.clone()).collect());
    (docs, known)
}

fn type_words(prop: &serde_json::Value, defs: Option<&serde_json::Value>) -> String {
    if let Some(r) = prop.get("$ref").and_then(|r| r.as_str()) {
        let name = r.rsplit('/').next().unwrap_or(r);
        if let Some(def) = defs.and_then(|d| d.get(name)) {
            let inner = type_words(def, defs);
            return if inner == "object" {
                name.to_owned()
            } else {
                inner
            };
        }
        return name.to_owned();
    }
    if let Some(c) = prop.get("const") {
        return c.to_string();
    }
    if let Some(values) = prop.get("enum").and_then(|e| e.as_array()) {
        return values
            .iter()
            .map(|v| v.to_string())
            .collect::<Vec<_>>()
            .join(" | ");
    }
    for key in ["oneOf", "anyOf"] {
        if let Some(alts) = prop.get(key).and_then(|a| a.as_array()) {
            let words: Vec<String> = alts
                .iter()
                .filter(|a| a.get("type").and_then(|t| t.as_str()) != Some("null"))
                .map(|a| type_words(a, defs))
                .collect();
            let optional = alts.len() != words.len();
            let joined = words.join(" | ");
            return if optional {
                format!("{joined} (optional)")
            } else {
                joined
            };
        }
    }
    let base = match prop.get("type") {
        Some(serde_json::Value::String(t)) => t.clone(),
        Some(serde_json::Value::Array(ts)) => {
            let names: Vec<&str> = ts
                .iter()
                .filter_map(|t| t.as_str())
                .filter(|t| *t != "null")
                .collect();
            let optional = names.len() != ts.len();
            let joined = names.join(" | ");
            if optional {
                format!("{joined} (optional)")
            } else {
                joined
            }
        }
        _ => "any".to_owned(),
    };
    let base = if base.starts_with("array") {
        match prop.get("items") {
            Some(items) => format!("array of {}", type_words(items, defs)),
            None => base,
        }
    } else {
        base
    };
    match prop.get("format").and_then(|f| f.as_str()) {
        Some(fmt) => format!("{base} ({fmt})"),
        None => base,
    }
}

fn json_to_toml_text(v: &serde_json::Value) -> String {
    match toml::Value::try_from(v) {
        Ok(t) => t.to_string(),
        Err(_) => v.to_string(), // null (no TOML equivalent): shown as JSON
    }
}

/// Plugins by id.
#[derive(Default, Clone)]
pub struct Registry {
    plugins: BTreeMap<String, Arc<dyn Plugin>>,
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a plugin; an id registered twice is an error naming it.
    pub fn register(&mut self, plugin: impl Plugin + 'static) -> Result<(), String> {
        self.register_arc(Arc::new(plugin))
    }

    /// Adds a shared plugin.
    pub fn register_arc(&mut self, plugin: Arc<dyn Plugin>) -> Result<(), String> {
        let id = plugin.info().id.clone();
        if let Some(old) = self.plugins.get(&id) {
            return Err(format!(
                "plugin id `{id}` is registered twice ({} and {})",
                old.info().origin,
                plugin.info().origin
            ));
        }
        self.plugins.insert(id, plugin);
        Ok(())
    }

    /// The plugin with this id.
    pub fn get(&self, id: &str) -> Option<&Arc<dyn Plugin>> {
        self.plugins.get(id)
    }

    /// All plugins, sorted by id.
    pub fn iter(&self) -> impl Iterator<Item = &Arc<dyn Plugin>> {
        self.plugins.values()
    }

    /// All ids, sorted.
    pub fn ids(&self) -> impl Iterator<Item = &str> {
        self.plugins.keys().map(String::as_str)
    }

    /// A human-readable description of one plugin: ports and every parameter.
    pub fn describe(&self, id: &str) -> Option<String> {
        let info = self.get(id)?.info();
        let mut s = format!("{}: {}\n  origin: {}\n", info.id, info.summary, info.origin);
        for (title, ports) in [("inputs", &info.inputs), ("outputs", &info.outputs)] {
            s.push_str(&format!("  {title}:\n"));
            if ports.is_empty() {
                s.push_str("    (none)\n");
            }
            for p in ports.iter() {
                let opt = if p.optional { ", optional" } else { "" };
                s.push_str(&format!("    {} ({}{opt})  {}\n", p.name, p.ty, p.doc));
            }
        }
        s.push_str("  params:\n");
        if info.params.is_empty() {
            s.push_str("    (none)\n");
        }
        for p in &info.params {
            let default = p
                .default
                .as_deref()
                .map(|d| format!(" = {d}"))
                .unwrap_or_default();
            s.push_str(&format!(
                "    {}: {}{default}\n        {}\n",
                p.name, p.ty, p.doc
            ));
        }
        Some(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edit_distance_and_suggestions() {
        assert_eq!(edit_distance("paths", "pths"), 1);
        assert_eq!(edit_distance("stpe", "step"), 1);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(edit_distance("", "abc"), 3);
        let known = ["paths", "max_disparity", "device"];
        assert_eq!(closest("pahts", known.iter().copied()), Some("paths"));
        assert_eq!(closest("zzzzzz", known.iter().copied()), None);
    }

    #[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
    #[serde(deny_unknown_fields, default)]
    struct Inner {
        a: u32,
        b: f64,
        name: String,
    }

    impl Default for Inner {
        fn default() -> Self {
            Inner {
                a: 1,
                b: 2.0,
                name: "inner".into(),
            }
        }
    }

    #[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
    #[serde(deny_unknown_fields, default)]
    struct Outer {
        inner: Inner,
        list: Vec<u32>,
        top: bool,
    }

    impl Default for Outer {
        // The plugin's own nested default differs from `Inner::default()`.
        fn default() -> Self {
            Outer {
                inner: Inner {
                    a: 7,
                    ..Inner::default()
                },
                list: vec![1, 2, 3],
                top: true,
            }
        }
    }

    #[test]
    fn a_nested_table_given_in_part_keeps_the_plugins_own_defaults() {
        let t: toml::Table = toml::from_str("inner = { b = 5.0 }\nlist = [9]").unwrap();
        let p: Outer = parse_params(&t).unwrap();
        assert_eq!(
            p,
            Outer {
                inner: Inner {
                    a: 7,
                    b: 5.0,
                    name: "inner".into()
                },
                list: vec![9],
                top: true,
            }
        );
        assert_eq!(
            parse_params::<Outer>(&toml::Table::new()).unwrap(),
            Outer::default()
        );
        // Wrong keys and types are still named by their path.
        let t: toml::Table = toml::from_str("inner = { c = 1 }").unwrap();
        let e = parse_params::<Outer>(&t).unwrap_err().to_string();
        assert!(e.contains("inner") && e.contains('c'), "{e}");
        let t: toml::Table = toml::from_str("inner = { a = \"x\" }").unwrap();
        let e = parse_params::<Outer>(&t).unwrap_err().to_string();
        assert!(e.contains("inner.a"), "{e}");
        let t: toml::Table = toml::from_str("inner = 3").unwrap();
        assert!(parse_params::<Outer>(&t).is_err());
    }
}
