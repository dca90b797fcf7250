//! The `misslam` binary end to end: validate, plugins, run with a saved Rerun recording.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

mod common;

use common::misslam;

#[test]
fn validate_accepts_and_rejects_with_one_located_line() {
    let ok = misslam()
        .args(["validate", "graphs/inspect.toml"])
        .output()
        .unwrap();
    assert!(
        ok.status.success(),
        "{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert!(String::from_utf8_lossy(&ok.stdout)
        .contains("graphs/inspect.toml: ok (3 nodes in 3 levels)"));

    let bad = misslam()
        .args(["validate", "tests/graphs/invalid/type_mismatch.toml"])
        .output()
        .unwrap();
    assert_eq!(bad.status.code(), Some(1));
    let err = String::from_utf8_lossy(&bad.stderr);
    let first = err.lines().next().unwrap_or_default();
    assert_eq!(
        first,
        "error: tests/graphs/invalid/type_mismatch.toml:8:20: node `files`: input `depth` takes depth, but `src.left` is image"
    );

    // Two sinks writing one folder (tests/graph_validation.rs pins the file's own clash): a
    // `--set` that makes the clash is named; one that separates them passes.
    let clash = misslam()
        .args([
            "validate",
            "tests/graphs/invalid/two_sinks_one_dir.toml",
            "--set",
            "b.dir=files",
        ])
        .output()
        .unwrap();
    assert_eq!(clash.status.code(), Some(1));
    let err = String::from_utf8_lossy(&clash.stderr);
    assert!(
        err.starts_with("error: tests/graphs/invalid/two_sinks_one_dir.toml: --set b.dir=files: node `b` (sink.files): `dir` = \"files\" is the folder node `a` already writes"),
        "{err}"
    );
    let apart = misslam()
        .args([
            "validate",
            "tests/graphs/invalid/two_sinks_one_dir.toml",
            "--set",
            "b.dir=files/b",
        ])
        .output()
        .unwrap();
    assert!(
        apart.status.success(),
        "{}",
        String::from_utf8_lossy(&apart.stderr)
    );

    let bad_set = misslam()
        .args(["validate", "graphs/inspect.toml", "--set", "src.step=zero"])
        .output()
        .unwrap();
    assert!(!bad_set.status.success());
    assert!(String::from_utf8_lossy(&bad_set.stderr).contains("--set src.step=zero"));
}

#[test]
fn plugins_lists_and_describes() {
    let out = misslam().arg("plugins").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    for id in ["source.stereo_folder", "sink.files", "image.gray"] {
        assert!(text.contains(id), "{id} missing from:\n{text}");
    }
    let out = misslam().args(["plugins", "image.gray"]).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("device: \"cpu\" | \"gpu\" | \"auto\" = \"cpu\""),
        "{text}"
    );
    assert!(
        text.contains("image (image)") && text.contains("gray (image)"),
        "{text}"
    );
    let out = misslam()
        .args(["plugins", "depth.nothing"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no plugin `depth.nothing`"));
}

#[test]
fn a_run_that_processes_no_frame_says_why() {
    let dir = std::env::temp_dir().join(format!("misslam-cli-none-{}", std::process::id()));
    let out = misslam()
        .args([
            "run",
            "graphs/phantom.toml",
            "--set",
            "graph.frames.start=100000",
            "--out",
        ])
        .arg(&dir)
        .output()
        .unwrap();
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("no frame was processed: the source gave none from frame 100000 on"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn a_count_of_zero_is_refused_naming_the_flag() {
    for args in [
        &["bench", "phantom", "--frames", "0"][..],
        &["bench", "ed-scaling", "--frames", "0"],
        &["bench", "runtime-overhead", "--frames", "0"],
        &["ablate", "graphs/phantom.toml", "--jobs", "0"],
        &["phantom", "export", "--frames", "0", "--out", "out/never"],
        &["observability", "--runs", "0"],
    ] {
        let out = misslam().args(args).output().unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        let flag = args.iter().find(|a| a.starts_with("--")).unwrap();
        assert!(
            err.starts_with(&format!("error: invalid value '0' for '{flag} "))
                && err.contains("must be at least 1"),
            "{args:?}: {err}"
        );
    }
}

#[test]
fn bad_rerun_mode_is_a_one_line_error() {
    let out = misslam()
        .args(["run", "graphs/inspect.toml", "--rerun", "view"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.starts_with("error: --rerun `view`: expected save:PATH.rrd"),
        "{err}"
    );
}

#[test]
fn an_unwritable_output_folder_and_an_absent_viewer_are_one_line_errors() {
    // The output folder under a regular file: named once, with its cause once.
    let dir = std::env::temp_dir().join(format!("misslam-cli-out-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("a-file");
    std::fs::write(&file, b"").unwrap();
    let out_dir = file.join("out");
    // One frame of the phantom into `out`.
    let run = |out: &std::path::Path| {
        let mut c = misslam();
        c.args([
            "run",
            "graphs/phantom.toml",
            "--set",
            "graph.frames.count=1",
        ])
        .arg("--out")
        .arg(out);
        c
    };
    let out = run(&out_dir).output().unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let line = err
        .lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_default();
    assert!(line.contains(&out_dir.display().to_string()), "{err}");
    assert_eq!(line.matches("(os error").count(), 1, "{line}");
    // `--rerun connect` with no viewer at the address: refused before the run, saying what to do.
    let free = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = free.local_addr().unwrap().port();
    drop(free);
    let out = run(&dir.join("run"))
        .args(["--rerun", &format!("connect:127.0.0.1:{port}")])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains(&format!(
            "no Rerun viewer at rerun+http://127.0.0.1:{port}/proxy"
        )) && err.contains("--rerun save:"),
        "{err}"
    );
    assert!(!dir.join("run/metrics.json").exists(), "the run went ahead");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn inspect_on_hamlyn_saves_a_recording_the_rerun_cli_verifies() {
    let Some(data) = common::data_set("hamlyn20") else {
        return;
    };
    // Both schedules record every frame: one frame at a time, and pipelined (the collector
    // logs each frame as it leaves the last level).
    for pipeline in ["1", "2"] {
        inspect_recording(&data, pipeline);
    }
}

/// `misslam run GRAPH --quiet` with `--set`s (and at most `frames` frames) into `out`, recorded
/// to `rrd`; fails the test with the run's stderr when the run fails.
fn run_recorded(
    graph: &str,
    sets: &[String],
    frames: Option<u32>,
    out: &std::path::Path,
    rrd: &std::path::Path,
) {
    let mut cmd = misslam();
    cmd.args(["run", graph, "--quiet"]);
    for s in sets {
        cmd.arg("--set").arg(s);
    }
    if let Some(n) = frames {
        cmd.arg("--frames").arg(n.to_string());
    }
    let run = cmd
        .arg("--out")
        .arg(out)
        .arg("--rerun")
        .arg(format!("save:{}", rrd.display()))
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
}

/// `graph.log_every` thins a recording's images, maps and meshes, not its scalars.
#[test]
fn log_every_thins_the_recording() {
    let dir = common::tmp_dir("log_every");
    let record = |every: u32| {
        let rrd = dir.join(format!("every{every}.rrd"));
        let sets = [
            "src.width=160".to_owned(),
            "src.height=120".to_owned(),
            format!("graph.log_every={every}"),
        ];
        let out = dir.join(format!("out{every}"));
        run_recorded("graphs/phantom.toml", &sets, Some(6), &out, &rrd);
        rrd
    };
    let (all, thin) = (record(1), record(3));
    let size = |p: &std::path::Path| std::fs::metadata(p).unwrap().len();
    // Frames 0 and 3 of 6 in full: about a third of the bytes.
    assert!(
        size(&thin) * 2 < size(&all),
        "log_every = 3: {} bytes against {}",
        size(&thin),
        size(&all)
    );
    let Some(print) = common::rerun_verified(&thin) else {
        return;
    };
    // `-v`: a line per chunk, "Chunk(..) with N rows (..) - /entity - data columns: [..]".
    let chunks = print("-v");
    let rows = |entity: &str| -> usize {
        chunks
            .lines()
            .filter(|l| l.contains(&format!(" - {entity} - ")))
            .filter_map(|l| {
                l.split(" with ")
                    .nth(1)?
                    .split(' ')
                    .next()?
                    .parse::<usize>()
                    .ok()
            })
            .sum()
    };
    // The source's timing, a scalar, on all 6 frames; its images and GT mesh on frames 0 and 3.
    assert_eq!(rows("/timing/src"), 6, "{chunks}");
    assert_eq!(rows("/src/left"), 2, "{chunks}");
    assert_eq!(rows("/src/mesh_gt"), 2, "{chunks}");
}

fn inspect_recording(data: &std::path::Path, pipeline: &str) {
    let out_dir = common::tmp_dir(&format!("inspect{pipeline}"));
    let rrd = out_dir.join("out.rrd");
    let sets = [
        format!("src.path={}", data.display()),
        format!("graph.pipeline={pipeline}"),
    ];
    run_recorded("graphs/inspect.toml", &sets, None, &out_dir, &rrd);
    let metrics: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("metrics.json")).unwrap())
            .unwrap();
    assert_eq!(metrics["frames"]["processed"], 17);
    assert_eq!(metrics["pipeline"].to_string(), pipeline);
    assert_eq!(metrics["frames"]["skipped"], 0);
    assert!(out_dir.join("files/left/000016.png").is_file());
    assert!(out_dir.join("files/image/000000.png").is_file());
    assert!(
        std::fs::metadata(&rrd).unwrap().len() > 1_000_000,
        "17 pairs of images are in it"
    );

    let Some(print) = common::rerun_verified(&rrd) else {
        return;
    };
    // `-v` lists entity@component per chunk; `-vv` prints the tables with their index columns.
    let text = print("-v");
    let tables = print("-vv");
    for timeline in ["index_name: frame", "index_name: input_time"] {
        assert!(tables.contains(timeline), "timeline `{timeline}` missing");
    }
    for needle in [
        "/src/stereo/left@Image:buffer",
        "/src/stereo/left@Pinhole:image_from_camera",
        "/src/stereo/right@Transform3D:translation",
        "/gray/gray@Image:buffer",
        "/graph@TextDocument:text",
        "/timing/src@Scalars:scalars",
    ] {
        assert!(text.contains(needle), "`{needle}` not in the recording");
    }
    assert!(!text.contains("/files/"), "`files` has log = false");
}

#[test]
fn eval_recon_scores_a_saved_model_against_a_gt_mesh_exactly() {
    // GT: the square z = 0, 100 mm wide, as two triangles. Estimate: points 0.5 mm above it.
    use misslam_sink_files::mesh_io::{write_ply, Geometry};
    let dir = common::tmp_dir("eval_recon_cli");
    std::fs::create_dir_all(&dir).unwrap();
    let gt = dir.join("gt.ply");
    let square = [
        [-50.0, -50.0, 0.0],
        [50.0, -50.0, 0.0],
        [50.0, 50.0, 0.0],
        [-50.0, 50.0, 0.0],
    ];
    write_ply(
        &gt,
        &Geometry {
            positions: &square,
            normals: None,
            colors: None,
            triangles: &[[0, 1, 2], [0, 2, 3]],
        },
    )
    .unwrap();
    let est = dir.join("est.ply");
    let pts: Vec<[f32; 3]> = (0..50)
        .map(|i| {
            [
                (i % 10) as f32 * 8.0 - 40.0,
                (i / 10) as f32 * 15.0 - 30.0,
                0.5,
            ]
        })
        .collect();
    write_ply(
        &est,
        &Geometry {
            positions: &pts,
            normals: None,
            colors: None,
            triangles: &[],
        },
    )
    .unwrap();
    let s = misslam::eval_cli::eval_recon(&est, &gt).unwrap();
    assert_eq!(s.points, 50);
    for v in [s.mean_mm, s.rms_mm, s.p95_mm] {
        assert!((v - 0.5).abs() < 1e-5, "{v}");
    }
    // A point cloud is no GT surface.
    let e = misslam::eval_cli::eval_recon(&gt, &est).unwrap_err();
    assert!(e.contains("triangles"), "{e}");
}

#[test]
fn a_closed_or_full_stdout_ends_the_command_without_a_panic() {
    use std::process::Stdio;
    // The reader goes away before the first line (as `| head -0` would): exit 0, no panic.
    let mut child = misslam()
        .args([
            "bench", "sgm", "--width", "64", "--height", "32", "--repeat", "1",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(!err.contains("panicked"), "{err}");
    // A write that fails otherwise (a full device) is an error naming stdout.
    if let Ok(full) = std::fs::OpenOptions::new().write(true).open("/dev/full") {
        let out = misslam().arg("plugins").stdout(full).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{err}");
        assert!(err.contains("writing to stdout"), "{err}");
        assert!(!err.contains("panicked"), "{err}");
    } else {
        println!("skipped the full-device case: no /dev/full");
    }
}

/// Reads a JSON file.
fn json(path: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap()
}

/// `misslam ablate graphs/template_dff.toml ARGS... --out OUT`.
fn ablate(args: &[&str], out: &std::path::Path) -> std::process::Output {
    misslam()
        .args(["ablate", "graphs/template_dff.toml"])
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap()
}

#[test]
fn ablate_runs_every_variant_and_seed_and_keeps_every_result() {
    let dir = common::tmp_dir("ablate");
    let study = dir.join("study");
    let study_args = [
        "--vary",
        "fusion.data_term=dff,projective",
        "--seeds",
        "7,1",
        "--frames",
        "3",
        "--keys",
        "recon.mean_mm,fusion.median_ms",
    ];
    let out = ablate(&study_args, &study);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let table = String::from_utf8_lossy(&out.stdout).to_string();
    let lines: Vec<&str> = table.lines().collect();
    assert_eq!(lines.len(), 3, "{table}");
    assert!(
        lines[0].starts_with("fusion.data_term  recon.mean_mm"),
        "{table}"
    );
    assert!(
        lines[1].starts_with("dff") && lines[1].contains(" ± "),
        "{table}"
    );
    let report = json(&study.join("ablation.json"));
    let rows = report["rows"].as_array().unwrap();
    assert_eq!(rows.len(), 2);
    let mut means = Vec::new();
    for row in rows {
        let runs = row["runs"].as_array().unwrap();
        assert_eq!(runs.len(), 2);
        let mut sum = 0.0;
        for r in runs {
            assert!(r["error"].is_null(), "{r}");
            // Each run's own metrics.json stays, and the table's figure is its figure.
            let m =
                json(&std::path::PathBuf::from(r["dir"].as_str().unwrap()).join("metrics.json"));
            let v = r["figures"]["recon.mean_mm"].as_f64().unwrap();
            assert_eq!(m["eval"]["recon.mean_mm"].as_f64().unwrap(), v);
            assert_eq!(m["frames"]["processed"], 3);
            let seed = r["seed"].as_u64().unwrap();
            assert!(
                m["overrides"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|o| o.as_str() == Some(&format!("graph.seed={seed}"))),
                "{m}"
            );
            assert!(r["figures"]["fusion.median_ms"].as_f64().unwrap() > 0.0);
            sum += v;
        }
        let mean = row["mean"]["recon.mean_mm"].as_f64().unwrap();
        assert!((mean - sum / 2.0).abs() < 1e-12, "{mean} vs {}", sum / 2.0);
        means.push(mean);
    }
    // The variants are not the same run twice.
    assert_ne!(means[0], means[1]);

    // Two runs at a time: the same figures, in the same rows.
    let parallel = dir.join("parallel");
    let out = ablate(&[&study_args[..], &["--jobs", "2"]].concat(), &parallel);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let p = json(&parallel.join("ablation.json"));
    for (row, prow) in rows.iter().zip(p["rows"].as_array().unwrap()) {
        assert_eq!(row["variant"], prow["variant"]);
        for (r, pr) in row["runs"]
            .as_array()
            .unwrap()
            .iter()
            .zip(prow["runs"].as_array().unwrap())
        {
            assert_eq!(r["seed"], pr["seed"]);
            assert_eq!(
                r["figures"]["recon.mean_mm"],
                pr["figures"]["recon.mean_mm"]
            );
        }
    }

    // A run that fails is recorded, the others go on, and the command says so.
    let failing = dir.join("failing");
    let out = ablate(
        &[
            "--vary",
            "fusion.field.max_voxels=16000000,1",
            "--frames",
            "2",
            "--keys",
            "recon.mean_mm",
        ],
        &failing,
    );
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("1 run(s) failed"), "{err}");
    let report = json(&failing.join("ablation.json"));
    let rows = report["rows"].as_array().unwrap();
    assert!(rows[0]["runs"][0]["error"].is_null());
    assert!(rows[0]["mean"]["recon.mean_mm"].as_f64().unwrap() > 0.0);
    let e = rows[1]["runs"][0]["error"].as_str().unwrap();
    assert!(e.contains("max_voxels"), "{e}");

    // A misspelt key is refused before anything runs, naming the variant.
    let typo = dir.join("typo");
    let out = ablate(&["--vary", "fusion.data_trem=dff,projective"], &typo);
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("variant fusion.data_trem=dff") && err.contains("data_trem"),
        "{err}"
    );
    assert!(!typo.join("ablation.json").exists());
    let out = misslam()
        .args([
            "ablate",
            "graphs/template_dff.toml",
            "--vary",
            "fusion.data_term",
        ])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("expected KEY=VALUE"));
}

/// `misslam observability` prints its table and writes the JSON; an unknown organ is one line
/// naming the option.
#[test]
fn observability_study_prints_the_table_and_writes_json() {
    let dir = std::env::temp_dir().join(format!("misslam-obs-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let json = dir.join("obs.json");
    let rrd = dir.join("obs.rrd");
    let out = misslam()
        .args(["observability", "--organs", "liver", "--runs", "2", "--out"])
        .arg(&json)
        .arg("--rerun")
        .arg(format!("save:{}", rrd.display()))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text} {}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        text.contains("liver (2 runs") && text.contains("time_series"),
        "{text}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let organ = &v["organs"][0];
    assert_eq!(organ["organ"], "liver");
    assert_eq!(organ["methods"].as_array().unwrap().len(), 5);
    assert_eq!(organ["rank"][1]["method"], "ed");
    assert_eq!(organ["rank"][1]["deficiency"], 24);
    assert_eq!(organ["rank"][2]["method"], "fem");
    assert_eq!(organ["rank"][2]["deficiency"], 24);
    assert_eq!(organ["rank"][3]["method"], "time_series");
    assert_eq!(organ["rank"][3]["deficiency"], 0);
    // The first run, step by step, in the recording.
    assert!(std::fs::metadata(&rrd).unwrap().len() > 0);
    if let Some(print) = common::rerun_verified(&rrd) {
        let text = print("-v");
        for needle in [
            "/observability/liver/truth/pose@Transform3D:mat3x3",
            "/observability/liver/truth/wall@Points3D:positions",
            "/observability/liver/time_series/pose_trajectory@LineStrips3D:strips",
            "/observability/liver/ed/wall@Points3D:positions",
            "/observability/liver/odometry/pose@Transform3D:translation",
        ] {
            assert!(text.contains(needle), "{needle} missing from the recording");
        }
    }
    let bad = misslam()
        .args(["observability", "--organs", "heart,spleen"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success());
    assert!(err.contains("--organs: unknown organ `spleen`"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
