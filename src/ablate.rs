//! `misslam ablate`: one graph run over the cartesian product of parameter variants and seeds,
//! each run into its own folder, and a table of chosen figures per variant (mean and standard
//! deviation over the seeds). What a study such as the thesis's Table 3.1 (DFF against
//! back-projection on three organs) needs, without a shell loop: a failed run is recorded and the
//! others go on, and every run's `metrics.json` stays on disk.

use crate::framework::{graph, RunOptions, Runtime};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// What to run.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The graph file.
    pub graph: PathBuf,
    /// Overrides applied to every run.
    pub sets: Vec<String>,
    /// The varied parameters, each with its values (`--vary key=v1,v2`), in order.
    pub vary: Vec<(String, Vec<String>)>,
    /// `graph.seed` of each repetition (none: the graph's own seed, one run per variant).
    pub seeds: Vec<u64>,
    /// Frame limit for every run.
    pub frames: Option<u64>,
    /// The figures of the table: `eval` keys (`recon.mean_mm`), or `NODE.median_ms` for a node's
    /// median time per frame; empty: every `eval` key.
    pub keys: Vec<String>,
    /// Where the runs and `ablation.json` go.
    pub out: PathBuf,
    /// Runs at a time (each on its own thread; a run's nodes share the process's thread pool).
    /// The figures do not depend on it.
    pub jobs: usize,
}

/// One run of a variant.
#[derive(Clone, Debug, Serialize)]
pub struct RunResult {
    /// Its seed, if the plan has seeds.
    pub seed: Option<u64>,
    /// Its output folder.
    pub dir: PathBuf,
    /// Its figures (the plan's keys; those it did not report are absent).
    pub figures: BTreeMap<String, f64>,
    /// Why it failed, if it did (its figures then hold what it measured before).
    pub error: Option<String>,
}

/// One variant: a value for each varied parameter, run once per seed.
#[derive(Clone, Debug, Serialize)]
pub struct Row {
    /// The varied parameters' values.
    pub variant: Vec<(String, String)>,
    /// Every run.
    pub runs: Vec<RunResult>,
    /// Mean of each figure over the runs that reported it.
    pub mean: BTreeMap<String, f64>,
    /// Sample standard deviation of each figure (0 with one run).
    pub sd: BTreeMap<String, f64>,
}

/// The whole study, as written to `ablation.json`.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    /// The graph file.
    pub graph: PathBuf,
    /// The overrides of every run.
    pub sets: Vec<String>,
    /// The seeds.
    pub seeds: Vec<u64>,
    /// The figures of the table.
    pub keys: Vec<String>,
    /// One row per variant.
    pub rows: Vec<Row>,
}

impl Report {
    /// Runs that failed.
    pub fn failures(&self) -> usize {
        self.rows
            .iter()
            .flat_map(|r| &r.runs)
            .filter(|r| r.error.is_some())
            .count()
    }

    /// The table as text: one line per variant, `mean ± sd` per figure.
    pub fn table(&self) -> String {
        let mut header: Vec<String> = Vec::new();
        if let Some(r) = self.rows.first() {
            header.extend(r.variant.iter().map(|(k, _)| k.clone()));
        }
        header.extend(self.keys.iter().cloned());
        header.push("runs".into());
        let mut lines = vec![header];
        for r in &self.rows {
            let mut l: Vec<String> = r.variant.iter().map(|(_, v)| v.clone()).collect();
            for k in &self.keys {
                l.push(match (r.mean.get(k), r.sd.get(k)) {
                    (Some(m), Some(s)) if r.runs.len() > 1 => format!("{m:.4} ± {s:.4}"),
                    (Some(m), _) => format!("{m:.4}"),
                    _ => "-".into(),
                });
            }
            let failed = r.runs.iter().filter(|x| x.error.is_some()).count();
            l.push(if failed > 0 {
                format!("{} ({failed} failed)", r.runs.len())
            } else {
                r.runs.len().to_string()
            });
            lines.push(l);
        }
        let cols = lines.iter().map(Vec::len).max().unwrap_or(0);
        let widths: Vec<usize> = (0..cols)
            .map(|c| {
                lines
                    .iter()
                    .filter_map(|l| l.get(c))
                    .map(|s| s.chars().count())
                    .max()
                    .unwrap_or(0)
            })
            .collect();
        let mut out = String::new();
        for l in &lines {
            let cells: Vec<String> = l
                .iter()
                .zip(&widths)
                .map(|(s, w)| format!("{s:<w$}"))
                .collect();
            out.push_str(cells.join("  ").trim_end());
            out.push('\n');
        }
        out
    }
}

/// Parses `--vary key=v1,v2,...`: the values are split at commas outside brackets, braces and
/// quotes, so TOML arrays and tables stay whole (`align.translation_mm=[1, 2, 3],[0, 0, 0]`).
pub fn parse_vary(arg: &str) -> Result<(String, Vec<String>), String> {
    let (key, values) = arg
        .split_once('=')
        .ok_or_else(|| format!("--vary {arg}: expected KEY=VALUE[,VALUE...]"))?;
    let key = key.trim();
    if key.is_empty() {
        return Err(format!("--vary {arg}: the key is empty"));
    }
    let mut out = Vec::new();
    let (mut depth, mut quote, mut cur) = (0i32, None::<char>, String::new());
    for c in values.chars() {
        match (quote, c) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), _) => {}
            (None, '"' | '\'') => quote = Some(c),
            (None, '[' | '{') => depth += 1,
            (None, ']' | '}') => depth -= 1,
            (None, ',') if depth == 0 => {
                out.push(std::mem::take(&mut cur));
                continue;
            }
            _ => {}
        }
        cur.push(c);
    }
    out.push(cur);
    if depth != 0 || quote.is_some() {
        return Err(format!(
            "--vary {arg}: unbalanced brackets or quotes in the values"
        ));
    }
    let out: Vec<String> = out.into_iter().map(|v| v.trim().to_string()).collect();
    if out.iter().any(String::is_empty) {
        return Err(format!("--vary {arg}: an empty value"));
    }
    Ok((key.to_string(), out))
}

/// Every combination of the varied values, the first parameter varying slowest.
fn variants(vary: &[(String, Vec<String>)]) -> Vec<Vec<(String, String)>> {
    let mut all = vec![Vec::new()];
    for (k, values) in vary {
        let mut next = Vec::new();
        for prefix in &all {
            for v in values {
                let mut p = prefix.clone();
                p.push((k.clone(), v.clone()));
                next.push(p);
            }
        }
        all = next;
    }
    all
}

/// A folder name for a variant: its values, with what a file name should not hold replaced.
fn label(variant: &[(String, String)], seed: Option<u64>) -> String {
    let mut s: String = variant
        .iter()
        .map(|(_, v)| v.as_str())
        .collect::<Vec<_>>()
        .join("_");
    if let Some(seed) = seed {
        if !s.is_empty() {
            s.push('_');
        }
        s.push_str(&format!("seed{seed}"));
    }
    let s: String = s
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '.' || c == '-' || c == '_' {
                c
            } else {
                '-'
            }
        })
        .collect();
    if s.is_empty() {
        "run".into()
    } else {
        s
    }
}

/// The plan's figures from a run's metrics.
fn figures(m: &crate::framework::metrics::RunMetrics, keys: &[String]) -> BTreeMap<String, f64> {
    if keys.is_empty() {
        return m.eval.clone();
    }
    let mut f = BTreeMap::new();
    for k in keys {
        let v = m.eval.get(k).copied().or_else(|| {
            let node = k.strip_suffix(".median_ms")?;
            m.timing_ms.get(node).map(|t| t.median_ms)
        });
        if let Some(v) = v {
            f.insert(k.clone(), v);
        }
    }
    f
}

/// Runs the plan. A run that cannot be built or fails is recorded in its row and the study goes
/// on; `Err` only when the plan itself is wrong (no graph, an override that does not apply,
/// checked for every variant before the first run) or the output folder cannot be written.
pub fn run(plan: &Plan, registry: &crate::framework::Registry) -> Result<Report, String> {
    if !plan.graph.is_file() {
        return Err(format!("{}: no such graph file", plan.graph.display()));
    }
    std::fs::create_dir_all(&plan.out).map_err(|e| format!("{}: {e}", plan.out.display()))?;
    let seeds: Vec<Option<u64>> = if plan.seeds.is_empty() {
        vec![None]
    } else {
        plan.seeds.iter().map(|&s| Some(s)).collect()
    };
    let sets_of = |variant: &[(String, String)], seed: Option<u64>| {
        let mut sets = plan.sets.clone();
        sets.extend(variant.iter().map(|(k, v)| format!("{k}={v}")));
        if let Some(s) = seed {
            sets.push(format!("graph.seed={s}"));
        }
        sets
    };
    let all = variants(&plan.vary);
    // The plan is checked before anything runs: a misspelt key or value fails now, not after
    // the runs before it.
    for variant in &all {
        graph::load(&plan.graph, registry, &sets_of(variant, seeds[0])).map_err(|e| {
            let v: Vec<String> = variant.iter().map(|(k, v)| format!("{k}={v}")).collect();
            format!("variant {}: {e}", v.join(" "))
        })?;
    }
    // Every run, in a fixed order; `jobs` threads take them one at a time.
    let runs_todo: Vec<(usize, Option<u64>)> = (0..all.len())
        .flat_map(|v| seeds.iter().map(move |&s| (v, s)))
        .collect();
    let total = runs_todo.len();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let finished = std::sync::atomic::AtomicUsize::new(0);
    let results: std::sync::Mutex<Vec<Option<RunResult>>> =
        std::sync::Mutex::new(vec![None; total]);
    let work = || loop {
        let job = next.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let Some(&(v, seed)) = runs_todo.get(job) else {
            break;
        };
        let variant = &all[v];
        let dir = plan.out.join(format!("{v:03}_{}", label(variant, seed)));
        let outcome = graph::load(&plan.graph, registry, &sets_of(variant, seed))
            .map_err(|e| e.to_string())
            .and_then(|g| Runtime::build(g).map_err(|e| e.to_string()))
            .and_then(|rt| {
                rt.run(RunOptions {
                    out_dir: Some(dir.clone()),
                    frames: plan.frames,
                    recorder: None,
                    progress: None,
                })
                .map_err(|e| e.to_string())
            });
        let result = match outcome {
            Ok(report) => RunResult {
                seed,
                dir,
                figures: figures(&report.metrics, &plan.keys),
                error: report.error.map(|e| e.to_string()),
            },
            Err(e) => RunResult {
                seed,
                dir,
                figures: BTreeMap::new(),
                error: Some(e),
            },
        };
        let done = finished.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
        let mut what: Vec<String> = variant.iter().map(|(k, v)| format!("{k}={v}")).collect();
        if let Some(s) = seed {
            what.push(format!("seed {s}"));
        }
        match &result.error {
            Some(e) => tracing::warn!("run {done}/{total} ({}) failed: {e}", what.join(" ")),
            None => tracing::info!(
                "run {done}/{total} ({}): {}",
                what.join(" "),
                result
                    .figures
                    .iter()
                    .take(3)
                    .map(|(k, v)| format!("{k} {v:.4}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        }
        if let Ok(mut r) = results.lock() {
            r[job] = Some(result);
        }
    };
    std::thread::scope(|scope| {
        for _ in 1..plan.jobs.clamp(1, total.max(1)) {
            scope.spawn(work);
        }
        work();
    });
    let mut results = results
        .into_inner()
        .map_err(|_| "a run's thread panicked".to_string())?
        .into_iter();
    // The figures of the table: the plan's, or every one some run reported.
    let mut keys = plan.keys.clone();
    let mut rows = Vec::new();
    for variant in all {
        let mut runs = Vec::new();
        for _ in &seeds {
            let r = results
                .next()
                .flatten()
                .ok_or_else(|| "a run left no result".to_string())?;
            if plan.keys.is_empty() {
                for k in r.figures.keys() {
                    if !keys.contains(k) {
                        keys.push(k.clone());
                    }
                }
            }
            runs.push(r);
        }
        rows.push(Row {
            variant,
            runs,
            mean: BTreeMap::new(),
            sd: BTreeMap::new(),
        });
    }
    for row in &mut rows {
        for k in &keys {
            let v: Vec<f64> = row
                .runs
                .iter()
                .filter_map(|r| r.figures.get(k))
                .copied()
                .collect();
            if v.is_empty() {
                continue;
            }
            let n = v.len() as f64;
            let m = v.iter().sum::<f64>() / n;
            let var = if v.len() > 1 {
                v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (n - 1.0)
            } else {
                0.0
            };
            row.mean.insert(k.clone(), m);
            row.sd.insert(k.clone(), var.sqrt());
        }
    }
    keys.sort_by_key(|k| plan.keys.iter().position(|p| p == k).unwrap_or(usize::MAX));
    let report = Report {
        graph: plan.graph.clone(),
        sets: plan.sets.clone(),
        seeds: plan.seeds.clone(),
        keys,
        rows,
    };
    let path = plan.out.join("ablation.json");
    let json = serde_json::to_string_pretty(&report).map_err(|e| e.to_string())?;
    std::fs::write(&path, json).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vary_values_split_at_top_level_commas_only() {
        let (k, v) = parse_vary("fusion.data_term=dff,projective").unwrap();
        assert_eq!(k, "fusion.data_term");
        assert_eq!(v, ["dff", "projective"]);
        let (_, v) = parse_vary("a.t=[1, 2, 3], [0,0,0]").unwrap();
        assert_eq!(v, ["[1, 2, 3]", "[0,0,0]"]);
        let (_, v) = parse_vary("a.s={ x = 1, y = 2 },\"p,q\"").unwrap();
        assert_eq!(v, ["{ x = 1, y = 2 }", "\"p,q\""]);
        for bad in ["novalue", "=1,2", "a.b=1,,2", "a.b=[1, 2", "a.b=\"x"] {
            assert!(parse_vary(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn variants_are_the_cartesian_product_first_key_slowest() {
        let v = variants(&[
            ("a".into(), vec!["1".into(), "2".into()]),
            ("b".into(), vec!["x".into(), "y".into(), "z".into()]),
        ]);
        assert_eq!(v.len(), 6);
        assert_eq!(v[0], [("a".into(), "1".into()), ("b".into(), "x".into())]);
        assert_eq!(v[3], [("a".into(), "2".into()), ("b".into(), "x".into())]);
        assert_eq!(variants(&[]), vec![Vec::new()]);
        assert_eq!(
            label(&v[1], Some(7)),
            "1_y_seed7",
            "folder names hold the values and the seed"
        );
        assert_eq!(label(&[("k".into(), "[1, 2]".into())], None), "-1--2-");
    }
}
