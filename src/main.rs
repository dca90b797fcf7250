//! `misslam`: run, validate and inspect TOML graphs of SLAM plugins.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use misslam_framework::recorder::{Recorder, RerunMode};
use misslam_framework::{graph, RunOptions, Runtime};

/// `println!` that ends the process quietly (exit status 0) when the reader of stdout has gone
/// (`misslam plugins | head`), as Unix tools do, instead of panicking; any other failure to write
/// is reported on stderr with exit status 1, so no output is lost silently.
macro_rules! out {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout(), $($t)*) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                std::process::exit(0);
            }
            eprintln!("error: writing to stdout: {e}");
            std::process::exit(1);
        }
    }};
}

mod bench_cli;
use bench_cli::BenchCommand;

#[derive(Parser)]
#[command(
    name = "misslam",
    version,
    about = "Non-rigid 3D SLAM for minimally invasive surgery: run graphs of swappable plugins"
)]
struct Cli {
    /// Log filter (tracing syntax), e.g. `info`, `debug`, `misslam_framework=debug`.
    #[arg(long, global = true, default_value = "info", env = "MISSLAM_LOG")]
    log: String,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a graph.
    Run {
        /// The graph file (TOML).
        graph: PathBuf,
        /// Override a parameter: `node.param=value`, `node.plugin=ID`, `graph.seed=3`. Repeatable.
        #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
        set: Vec<String>,
        /// Process at most N frames (overrides the graph's `frames.count`).
        #[arg(long)]
        frames: Option<u64>,
        /// Output folder (default: the graph's `out`, else `out/<graph name>`).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Recording: save:PATH.rrd | spawn | connect[:HOST:PORT] | off.
        #[arg(long, default_value = "off")]
        rerun: String,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Run a graph over every combination of parameter values (and seeds), each run into its
    /// own folder, and print a table of chosen figures per variant (mean ± sd over the seeds);
    /// `OUT/ablation.json` holds every run's figures.
    Ablate {
        /// The graph file (TOML).
        graph: PathBuf,
        /// A varied parameter and its values: `fusion.data_term=dff,projective` (commas inside
        /// brackets, braces or quotes do not split). Repeatable: every combination runs.
        #[arg(long = "vary", value_name = "NODE.PARAM=V1,V2,...")]
        vary: Vec<String>,
        /// Seeds (`graph.seed`), comma-separated: each variant runs once per seed.
        #[arg(long, value_delimiter = ',')]
        seeds: Vec<u64>,
        /// An override applied to every run. Repeatable.
        #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
        set: Vec<String>,
        /// Process at most N frames per run.
        #[arg(long)]
        frames: Option<u64>,
        /// Figures of the table, comma-separated: `eval` keys (`recon.mean_mm`) or
        /// `NODE.median_ms` (default: every `eval` key).
        #[arg(long, value_delimiter = ',')]
        keys: Vec<String>,
        /// Output folder.
        #[arg(long, default_value = "out/ablation")]
        out: PathBuf,
        /// Runs at a time (the figures do not depend on it).
        #[arg(long, default_value_t = 1, value_parser = count_usize)]
        jobs: usize,
    },
    /// Check a graph without running it.
    Validate {
        /// The graph file (TOML).
        graph: PathBuf,
        /// Overrides to check as well.
        #[arg(long = "set", value_name = "NODE.PARAM=VALUE")]
        set: Vec<String>,
    },
    /// List plugins, or describe one: ports and every parameter with type, default and doc.
    Plugins {
        /// A plugin id, e.g. `source.stereo_folder`.
        id: Option<String>,
        /// Also load the plugins of this library (repeatable).
        #[arg(long = "library", value_name = "PATH")]
        libraries: Vec<PathBuf>,
    },
    /// Score results saved by a run against ground truth.
    Eval {
        #[command(subcommand)]
        which: EvalCommand,
    },
    /// The built-in phantom.
    Phantom {
        #[command(subcommand)]
        which: PhantomCommand,
    },
    /// Benchmarks.
    Bench {
        #[command(subcommand)]
        which: BenchCommand,
    },
    /// The thesis's observability study (chapter 6): a scope moving inside a deforming planar
    /// organ; odometry, static, ED-based, FEM-based and time-series-prior SLAM by Monte Carlo (RMSE of
    /// position and heading), and the rank of each one's Fisher information without odometry.
    Observability {
        /// Organs, comma-separated: heart, stomach, liver, lung.
        #[arg(long, default_value = "heart,stomach,liver,lung")]
        organs: String,
        /// Monte Carlo runs per organ (seeds `seed` .. `seed + runs - 1`).
        #[arg(long, default_value_t = 20, value_parser = count_usize)]
        runs: usize,
        /// Steps per run.
        #[arg(long, default_value_t = 72)]
        steps: usize,
        /// Initial steps with the scope still (E_ini; the time series is fitted there).
        #[arg(long, default_value_t = 24)]
        static_steps: usize,
        /// Features (wall points).
        #[arg(long, default_value_t = 16)]
        features: usize,
        /// Observation noise per coordinate, mm.
        #[arg(long, default_value_t = 0.3)]
        obs_sigma_mm: f64,
        /// Standard deviation of the time-series prior E_f, mm.
        #[arg(long, default_value_t = 0.01)]
        ts_sigma_mm: f64,
        /// The time series' order (0: 2H + 1 for the organ's H frequencies).
        #[arg(long, default_value_t = 0)]
        order: usize,
        /// FEM: the wall's thickness, mm (the beam elements' bending stiffness EI = EA h^2 / 12).
        #[arg(long, default_value_t = 8.0)]
        fem_thickness_mm: f64,
        /// Hold the coefficients fitted on the still period instead of estimating them.
        #[arg(long)]
        fixed_coefficients: bool,
        /// Fit all the coefficients freely (total least squares) instead of as a periodic
        /// motion (the root at 1 and undamped harmonics imposed).
        #[arg(long)]
        free_fit: bool,
        /// Steps of the rank test's scene (half of them still).
        #[arg(long, default_value_t = 16)]
        rank_steps: usize,
        /// Seed of the first run.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Write the figures as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
        /// Recording of each organ's first run: save:PATH.rrd | spawn | connect[:HOST:PORT] |
        /// off (the truth's and every method's scope trajectory and wall points, step by step,
        /// under `/observability/<organ>/<method>`).
        #[arg(long, default_value = "off")]
        rerun: String,
    },
}

#[derive(Subcommand)]
enum EvalCommand {
    /// A saved reconstruction (e.g. `export/model/final.ply`) against a GT mesh (e.g. a phantom
    /// export's `mesh_gt/<frame>.ply`), both in the world frame: mean, RMS and p95 distance.
    Recon {
        /// The reconstruction (PLY, OBJ, glTF; its vertices are scored).
        #[arg(long)]
        est: PathBuf,
        /// The GT surface (a triangle mesh).
        #[arg(long)]
        gt: PathBuf,
    },
    /// An estimated trajectory (`sink.files`' pose.txt) against a GT one (`poses_gt.txt` of
    /// `misslam phantom export`): ATE, RPE, lost frames.
    Tracking {
        /// Estimated trajectory (first column: frame index; lost frames as comments).
        #[arg(long)]
        est: PathBuf,
        /// GT trajectory, TUM layout, line k = frame k.
        #[arg(long)]
        gt: PathBuf,
        /// Alignment before the ATE: rigid or none.
        #[arg(long, default_value = "rigid")]
        align: String,
        /// Also write the scores as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Depth maps (`<frame>.pfm`, mm, as sink.files writes them) against a dataset's GT depth.
    Depth {
        /// Folder of estimated depth, e.g. out/run/files/depth.
        #[arg(long)]
        est: PathBuf,
        /// The dataset folder the run read (its GT depth and calibration are used).
        #[arg(long)]
        dataset: PathBuf,
        /// How the dataset stores GT depth: pfm or colonsyn_rgb.
        #[arg(long, default_value = "pfm")]
        gt_format: String,
        /// Nearest GT depth evaluated, mm.
        #[arg(long, default_value_t = 0.0)]
        min_depth_mm: f32,
        /// Farthest GT depth evaluated, mm.
        #[arg(long, default_value_t = f32::MAX)]
        max_depth_mm: f32,
        /// Also write per-frame rows and the summary as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

#[derive(Subcommand)]
enum PhantomCommand {
    /// Write a phantom sequence as a dataset folder (images, calib.toml, GT depth, disparity,
    /// correspondences, meshes, poses; layout in the folder's README.md).
    Export {
        /// heart, liver, kidney or stomach.
        #[arg(long, default_value = "heart")]
        scene: String,
        /// Frames to write.
        #[arg(long, default_value_t = 30, value_parser = count)]
        frames: u64,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
        /// Seed (texture and noise).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Any other `source.phantom` parameter: `--set trajectory=fast`. Repeatable.
        #[arg(long = "set", value_name = "PARAM=VALUE")]
        set: Vec<String>,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let filter = tracing_subscriber::EnvFilter::try_new(&cli.log)
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .init();
    match run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // One line with the cause chain; graph errors keep their snippet below.
            let mut line = e.to_string();
            for cause in e.chain().skip(1) {
                line.push_str(": ");
                line.push_str(&cause.to_string());
            }
            eprintln!("error: {line}");
            ExitCode::FAILURE
        }
    }
}

fn run(command: Command) -> anyhow::Result<()> {
    let mut registry = misslam::builtin_registry();
    if let Command::Plugins { libraries, .. } = &command {
        for lib in libraries {
            let plugin =
                misslam_framework::dynamic::load_library(lib).map_err(anyhow::Error::msg)?;
            registry.register_arc(plugin).map_err(anyhow::Error::msg)?;
        }
    }
    match command {
        Command::Bench { which } => bench_cli::run(which),
        Command::Eval {
            which: EvalCommand::Recon { est, gt },
        } => {
            let s = misslam::eval_cli::eval_recon(&est, &gt).map_err(anyhow::Error::msg)?;
            out!("points           {}", s.points);
            out!("recon.mean_mm    {:.4}", s.mean_mm);
            out!("recon.rms_mm     {:.4}", s.rms_mm);
            out!("recon.p95_mm     {:.4}", s.p95_mm);
            Ok(())
        }
        Command::Eval {
            which:
                EvalCommand::Tracking {
                    est,
                    gt,
                    align,
                    out,
                },
        } => {
            let align = match align.as_str() {
                "rigid" => misslam_eval_tracking::Align::Rigid,
                "none" => misslam_eval_tracking::Align::None,
                other => anyhow::bail!("--align `{other}`: expected rigid or none"),
            };
            let s =
                misslam::eval_cli::eval_tracking(&est, &gt, align).map_err(anyhow::Error::msg)?;
            out!("frames with a pose  {}", s.frames);
            out!("tracking.ate_mm     {:.4}", s.ate_mm);
            out!("tracking.rpe_mm     {:.4}", s.rpe_mm);
            out!("tracking.rpe_deg    {:.4}", s.rpe_deg);
            out!("tracking.lost_pct   {:.2}", s.lost_pct);
            if let Some(path) = out {
                let v = serde_json::json!({
                    "frames": s.frames,
                    "tracking.ate_mm": s.ate_mm,
                    "tracking.rpe_mm": s.rpe_mm,
                    "tracking.rpe_deg": s.rpe_deg,
                    "tracking.lost_pct": s.lost_pct,
                });
                write_json(&path, &v)?;
            }
            Ok(())
        }
        Command::Eval {
            which:
                EvalCommand::Depth {
                    est,
                    dataset,
                    gt_format,
                    min_depth_mm,
                    max_depth_mm,
                    out,
                },
        } => {
            let format = match gt_format.as_str() {
                "pfm" => misslam_source_stereo_folder::depth_gt::DepthGtFormat::Pfm,
                "colonsyn_rgb" => {
                    misslam_source_stereo_folder::depth_gt::DepthGtFormat::ColonsynRgb
                }
                other => anyhow::bail!("--gt-format `{other}`: expected pfm or colonsyn_rgb"),
            };
            let params = misslam_eval_depth::Params {
                min_depth_mm,
                max_depth_mm,
                ..Default::default()
            };
            let rows = misslam::eval_cli::eval_depth(&est, &dataset, format, &params)
                .map_err(anyhow::Error::msg)?;
            out!(
                "{:>6} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9}",
                "frame",
                "bad1 %",
                "bad2 %",
                "bad2v %",
                "MAE mm",
                "bias mm",
                "density %"
            );
            for r in &rows {
                out!(
                    "{:>6} {:>8.2} {:>8.2} {:>8.2} {:>9.3} {:>+9.3} {:>9.1}",
                    r.frame,
                    r.bad1_pct,
                    r.bad2_pct,
                    r.bad2_valid_pct,
                    r.mae_mm,
                    r.bias_mm,
                    r.density_pct
                );
            }
            let summary = misslam::eval_cli::summary(&rows);
            for (k, v) in &summary {
                out!("{k:<22} {v:.4}");
            }
            if let Some(path) = out {
                let json = serde_json::json!({ "frames": rows, "eval": summary });
                write_json(&path, &json)?;
            }
            Ok(())
        }
        Command::Phantom {
            which:
                PhantomCommand::Export {
                    scene,
                    frames,
                    out,
                    seed,
                    set,
                },
        } => {
            let mut table = misslam_framework::toml::Table::new();
            table.insert("scene".into(), scene.into());
            table.insert("frames".into(), (frames as i64).into());
            for s in &set {
                let (k, v) = s
                    .split_once('=')
                    .with_context(|| format!("--set {s}: expected PARAM=VALUE"))?;
                let value = misslam_framework::toml::from_str::<misslam_framework::toml::Table>(
                    &format!("v = {v}"),
                )
                .ok()
                .and_then(|mut t| t.remove("v"))
                .unwrap_or_else(|| v.into());
                table.insert(k.trim().to_owned(), value);
            }
            let t = std::time::Instant::now();
            let n =
                misslam::phantom_export::export(&table, seed, &out).map_err(anyhow::Error::msg)?;
            eprintln!(
                "wrote {n} frames to {} ({:.1} frames/s including PNG, PFM and PLY writing)",
                out.display(),
                n as f64 / t.elapsed().as_secs_f64()
            );
            Ok(())
        }
        Command::Plugins { id: None, .. } => {
            for p in registry.iter() {
                let info = p.info();
                out!("{:<24} {}", info.id, info.summary);
            }
            Ok(())
        }
        Command::Plugins { id: Some(id), .. } => {
            let text = registry.describe(&id).with_context(|| {
                let ids: Vec<&str> = registry.ids().collect();
                format!("no plugin `{id}`; known: {}", ids.join(", "))
            })?;
            print!("{text}");
            Ok(())
        }
        Command::Ablate {
            graph: path,
            vary,
            seeds,
            set,
            frames,
            keys,
            out,
            jobs,
        } => {
            let vary = vary
                .iter()
                .map(|a| misslam::ablate::parse_vary(a))
                .collect::<Result<Vec<_>, _>>()
                .map_err(anyhow::Error::msg)?;
            let plan = misslam::ablate::Plan {
                graph: path,
                sets: set,
                vary,
                seeds,
                frames,
                keys,
                out,
                jobs,
            };
            let report = misslam::ablate::run(&plan, &registry).map_err(anyhow::Error::msg)?;
            out!("{}", report.table().trim_end());
            eprintln!("runs and ablation.json: {}", plan.out.display());
            match report.failures() {
                0 => Ok(()),
                n => Err(anyhow::anyhow!(
                    "{n} run(s) failed (their errors are in ablation.json)"
                )),
            }
        }
        Command::Observability {
            organs,
            runs,
            steps,
            static_steps,
            features,
            obs_sigma_mm,
            ts_sigma_mm,
            order,
            fem_thickness_mm,
            fixed_coefficients,
            free_fit,
            rank_steps,
            seed,
            out,
            rerun,
        } => {
            use misslam_eval_observability as obs;
            let mode: RerunMode = rerun
                .parse()
                .map_err(|e: String| anyhow::anyhow!("--rerun {e}"))?;
            let organs = organs
                .split(',')
                .map(|o| obs::scene::Organ::parse(o.trim()))
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| anyhow::anyhow!("--organs: {e}"))?;
            let p = obs::EstimatorParams {
                ts_sigma_mm,
                order,
                fem_thickness_mm,
                estimate_coefficients: !fixed_coefficients,
                periodic: !free_fit,
                ..Default::default()
            };
            let scene = |organ| obs::scene::SceneParams {
                steps,
                static_steps,
                features,
                obs_sigma_mm,
                seed,
                ..obs::scene::SceneParams::new(organ)
            };
            let study = obs::run_study(&organs, scene, &p, runs, rank_steps)
                .map_err(|e| anyhow::anyhow!(e))?;
            print!("{}", study.table());
            if let Some(path) = out {
                write_json(&path, &study)?;
            }
            if let Some(mut rec) = Recorder::open(&mode, "observability")
                .map_err(|e| anyhow::anyhow!("--rerun: {e}"))?
            {
                for &organ in &organs {
                    let (s, estimates) =
                        obs::run_once(&scene(organ), &p).map_err(anyhow::Error::msg)?;
                    log_observability(&mut rec, organ.name(), &s, &estimates)?;
                }
                rec.flush().map_err(|e| anyhow::anyhow!("--rerun: {e}"))?;
            }
            Ok(())
        }
        Command::Validate { graph: path, set } => {
            let g = graph::load(&path, &registry, &set)?;
            out!(
                "{}: ok ({} nodes in {} levels)",
                path.display(),
                g.nodes.len(),
                g.nodes.last().map_or(0, |n| n.level + 1)
            );
            Ok(())
        }
        Command::Run {
            graph: path,
            set,
            frames,
            out,
            rerun,
            quiet,
        } => {
            let mode: RerunMode = rerun
                .parse()
                .map_err(|e: String| anyhow::anyhow!("--rerun {e}"))?;
            let g = graph::load(&path, &registry, &set)?;
            let name = g.name.clone();
            let runtime = Runtime::build(g)?;
            let recorder = Recorder::open(&mode, &name)?;
            let progress = (!quiet).then(|| {
                let bar = indicatif::ProgressBar::new(0);
                bar.set_style(
                    indicatif::ProgressStyle::with_template(
                        "{spinner} {pos}/{len} frames [{elapsed_precise}] {per_sec}",
                    )
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
                );
                bar
            });
            let bar = progress.clone();
            let opts = RunOptions {
                out_dir: out,
                frames,
                recorder,
                progress: bar.map(|b| {
                    Box::new(move |done: u64, total: Option<u64>| {
                        if let Some(t) = total {
                            b.set_length(t);
                        } else {
                            b.set_length(done);
                        }
                        b.set_position(done);
                    }) as Box<dyn FnMut(u64, Option<u64>) + Send>
                }),
            };
            let report = runtime.run(opts)?;
            if let Some(b) = progress {
                b.finish_and_clear();
            }
            eprint!("{}", report.metrics.summary_table());
            eprintln!("metrics: {}", report.metrics_path.display());
            if let RerunMode::Save(p) = &mode {
                eprintln!("recording: {}", p.display());
            }
            match report.error {
                Some(e) => Err(e.into()),
                None => Ok(()),
            }
        }
    }
}

/// A count on the command line (frames, runs, repetitions, jobs): a whole number, at least 1.
pub(crate) fn count(s: &str) -> Result<u64, String> {
    match s.parse::<u64>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(v) => Ok(v),
        Err(_) => Err(format!("`{s}` is not a whole number")),
    }
}

/// [`count`] as a `usize`.
pub(crate) fn count_usize(s: &str) -> Result<usize, String> {
    count(s).and_then(|v| usize::try_from(v).map_err(|_| format!("`{s}` is too large")))
}

/// Writes `value` as pretty JSON to `path` (the `--out` of the benchmarks).
pub(crate) fn write_json(
    path: &std::path::Path,
    value: &impl serde::Serialize,
) -> anyhow::Result<()> {
    std::fs::write(path, serde_json::to_string_pretty(value)?)
        .with_context(|| format!("writing {}", path.display()))
}

/// Logs one observability run step by step: the truth's and each method's scope pose (with its
/// trajectory) and wall points, in the plane z = 0, under `/observability/<organ>/<who>`.
fn log_observability(
    rec: &mut Recorder,
    organ: &str,
    s: &misslam_eval_observability::scene::Scene,
    estimates: &[(
        misslam_eval_observability::Method,
        misslam_eval_observability::Estimate,
    )],
) -> anyhow::Result<()> {
    use misslam::framework::nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
    use misslam::framework::payload::{Payload, PointCloud, Pose, TrackingState};
    use misslam_eval_observability::scene::Pose2;
    use std::sync::Arc;
    let pose = |q: &Pose2| {
        Payload::Pose(Arc::new(Pose {
            world_from_camera: Isometry3::from_parts(
                Translation3::new(q.x, q.y, 0.0),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), q.th),
            ),
            state: TrackingState::Tracking,
        }))
    };
    let wall = |f: &[misslam::framework::nalgebra::Vector2<f64>]| {
        Payload::PointCloud(Arc::new(PointCloud {
            positions: f.iter().map(|p| [p.x as f32, p.y as f32, 0.0]).collect(),
            colors: None,
        }))
    };
    let e = |e: misslam::framework::recorder::RecorderError| anyhow::anyhow!("--rerun: {e}");
    for n in 0..s.params.steps {
        rec.begin_frame(n as u64, None);
        let base = format!("observability/{organ}");
        rec.log_payload(&format!("{base}/truth/pose"), &pose(&s.poses[n]))
            .map_err(e)?;
        rec.log_payload(&format!("{base}/truth/wall"), &wall(&s.truth[n]))
            .map_err(e)?;
        for (m, est) in estimates {
            let path = format!("{base}/{}", m.name());
            rec.log_payload(&format!("{path}/pose"), &pose(&est.poses[n]))
                .map_err(e)?;
            if let Some(f) = &est.features {
                rec.log_payload(&format!("{path}/wall"), &wall(&f[n]))
                    .map_err(e)?;
            }
        }
    }
    Ok(())
}
