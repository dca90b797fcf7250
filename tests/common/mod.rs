//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// The `misslam` binary, run from the checkout's root.
pub fn misslam() -> std::process::Command {
    let mut c = std::process::Command::new(env!("CARGO_BIN_EXE_misslam"));
    c.current_dir(env!("CARGO_MANIFEST_DIR"));
    c
}

/// `../shared/data` beside the checkout, when present.
pub fn shared_data() -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    p.is_dir().then_some(p)
}

/// A sequence folder under `../shared/data`, or a printed reason to skip.
pub fn data_set(name: &str) -> Option<PathBuf> {
    match shared_data().map(|d| d.join(name)).filter(|p| p.is_dir()) {
        Some(p) => Some(p),
        None => {
            println!("skipped: ../shared/data/{name} is absent");
            None
        }
    }
}

/// A fresh temporary folder for one test. The folders stay after the run (to look at), and the
/// first call of a test binary removes those of test processes that no longer run, so repeated
/// runs do not fill the disk (each run writes a few hundred MB).
pub fn tmp_dir(name: &str) -> PathBuf {
    static SWEEP: std::sync::Once = std::sync::Once::new();
    SWEEP.call_once(remove_stale_tmp_dirs);
    let d = std::env::temp_dir().join(format!("misslam-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("create temp dir");
    d
}

/// Removes `misslam-test-<pid>-*` folders whose process is gone (where `/proc` tells).
fn remove_stale_tmp_dirs() {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(pid) = name
            .strip_prefix("misslam-test-")
            .and_then(|r| r.split('-').next())
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// The `rerun` CLI (0.36.3, from `pip install rerun-sdk==0.36.3`): `MISSLAM_RERUN_BIN`, else `rerun`
/// on the PATH, when it answers `--version`.
pub fn rerun_cli() -> Option<PathBuf> {
    let bin =
        std::env::var_os("MISSLAM_RERUN_BIN").map_or_else(|| PathBuf::from("rerun"), PathBuf::from);
    let out = std::process::Command::new(&bin)
        .arg("--version")
        .output()
        .ok()?;
    let version = String::from_utf8_lossy(&out.stdout).into_owned();
    if !version.contains("0.36.3") {
        println!(
            "note: {} reports `{}`, not 0.36.3",
            bin.display(),
            version.trim()
        );
    }
    out.status.success().then_some(bin)
}

/// Builds a validated graph and runs it into `out`. Errors inside the run stay in the report
/// for the caller to check; building must succeed.
pub fn run_graph(g: misslam::framework::Graph, out: &Path) -> misslam::framework::RunReport {
    misslam::framework::Runtime::build(g)
        .expect("the graph builds")
        .run(misslam::framework::RunOptions {
            out_dir: Some(out.to_owned()),
            ..Default::default()
        })
        .expect("metrics could be written")
}

/// Runs a graph that must succeed: the run's error, if any, fails the test with its message.
pub fn run_graph_ok(g: misslam::framework::Graph, out: &Path) -> misslam::framework::RunReport {
    let report = run_graph(g, out);
    if let Some(e) = &report.error {
        panic!("the run failed: {e}");
    }
    report
}

/// Loads a graph file with `--set` overrides (it must be valid) and runs it (it must succeed).
pub fn run_graph_file(path: &str, sets: &[String], out: &Path) -> misslam::framework::RunReport {
    let g = misslam::framework::graph::load(Path::new(path), &misslam::builtin_registry(), sets)
        .unwrap_or_else(|e| panic!("{path}: {e}"));
    run_graph_ok(g, out)
}

/// Runs the graph file `graph` with one more node, a `sink.files` node `id` writing `inputs` (an
/// inline table such as `{ model = "fusion.model" }`) into `<run>/<id>` at the end of the run, and
/// the overrides `sets`; returns the run's folder, the fresh temporary folder `name`.
pub fn run_with_sink(graph: &str, id: &str, inputs: &str, sets: &[&str], name: &str) -> PathBuf {
    let text = std::fs::read_to_string(graph).unwrap_or_else(|e| panic!("{graph}: {e}"));
    let text = format!(
        "{text}\n[[node]]\nid = \"{id}\"\nplugin = \"sink.files\"\ninputs = {inputs}\n\
         params = {{ dir = \"{id}\", geometry_every = 0 }}\nlog = false\n"
    );
    let dir = tmp_dir(name);
    let path = dir.join("graph.toml");
    std::fs::write(&path, text).expect("write the graph");
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    let g = misslam::framework::graph::load(&path, &misslam::builtin_registry(), &sets)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    run_graph_ok(g, &dir);
    dir
}

/// Verifies a recording with the rerun CLI (`rrd verify`) and returns a function printing it
/// (`rrd print FLAG`); `None`, with the reason printed, when there is no CLI.
pub fn rerun_verified(rrd: &Path) -> Option<impl Fn(&str) -> String + '_> {
    let Some(rerun) = rerun_cli() else {
        println!("skipped the recording check: no rerun CLI (pip install rerun-sdk==0.36.3, or set MISSLAM_RERUN_BIN)");
        return None;
    };
    let verify = std::process::Command::new(&rerun)
        .args(["rrd", "verify"])
        .arg(rrd)
        .output()
        .expect("rerun runs");
    assert!(
        verify.status.success(),
        "rerun rrd verify: {}{}",
        String::from_utf8_lossy(&verify.stdout),
        String::from_utf8_lossy(&verify.stderr)
    );
    Some(move |flag: &str| {
        let out = std::process::Command::new(&rerun)
            .args(["rrd", "print", flag])
            .arg(rrd)
            .output()
            .expect("rerun runs");
        assert!(out.status.success(), "rerun rrd print {flag} failed");
        String::from_utf8_lossy(&out.stdout).into_owned()
    })
}

/// A vertex of a PLY as `sink.files` writes it: position, normal and colour (zero where the
/// file has none).
pub type PlyVertex = ([f32; 3], [f32; 3], [u8; 3]);

/// Reads a binary PLY as `sink.files` writes it: x, y, z, then nx, ny, nz (f32) and r, g, b when
/// its header lists them.
pub fn ply_vertices(path: &Path) -> Vec<PlyVertex> {
    let ply = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let start = ply
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("a PLY header")
        + 11;
    let header = String::from_utf8_lossy(&ply[..start]).to_string();
    let nv: usize = header
        .split("element vertex ")
        .nth(1)
        .and_then(|r| r.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .expect("a vertex count");
    let (normals, colors) = (
        header.contains("property float nx"),
        header.contains("property uchar red"),
    );
    let stride = 12 + if normals { 12 } else { 0 } + if colors { 3 } else { 0 };
    ply[start..start + stride * nv]
        .chunks_exact(stride)
        .map(|v| {
            let f =
                |k: usize| f32::from_le_bytes([v[4 * k], v[4 * k + 1], v[4 * k + 2], v[4 * k + 3]]);
            let n = if normals {
                [f(3), f(4), f(5)]
            } else {
                [0.0; 3]
            };
            let c = if colors {
                [v[stride - 3], v[stride - 2], v[stride - 1]]
            } else {
                [0; 3]
            };
            ([f(0), f(1), f(2)], n, c)
        })
        .collect()
}

/// [`ply_vertices`]' count, after checking that every coordinate is finite.
pub fn finite_ply_vertices(path: &Path) -> usize {
    let vertices = ply_vertices(path);
    for (p, n, _) in &vertices {
        assert!(
            p.iter().chain(n).all(|c| c.is_finite()),
            "{}: a non-finite coordinate",
            path.display()
        );
    }
    vertices.len()
}

/// Checks that the PLY `scope` holds the vertices of the PLY `world` in the scope's frame of the
/// last pose of the TUM file `poses` (`sink.files`' `pose.txt`): the pose carries each scope-frame
/// vertex and normal onto its world-frame one (within the files' rounding: poses to 1e-6, PLYs
/// in f32), colours alike. Returns the vertex count and the farthest a vertex lies from its
/// scope-frame self, mm (how far the two frames are apart).
pub fn assert_scope_frame(world: &Path, scope: &Path, poses: &Path) -> (usize, f64) {
    use misslam::framework::nalgebra::{Isometry3, Point3, Quaternion, UnitQuaternion, Vector3};
    let (world, scope) = (ply_vertices(world), ply_vertices(scope));
    assert_eq!(world.len(), scope.len());
    let poses = std::fs::read_to_string(poses).expect("pose.txt");
    let last: Vec<f64> = poses
        .lines()
        .rfind(|l| !l.starts_with('#'))
        .expect("a pose line")
        .split_whitespace()
        .map(|v| v.parse().expect("a number"))
        .collect();
    let world_from_camera = Isometry3::from_parts(
        Vector3::new(last[1], last[2], last[3]).into(),
        UnitQuaternion::from_quaternion(Quaternion::new(last[7], last[4], last[5], last[6])),
    );
    let f64s = |v: [f32; 3]| Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64);
    let (mut worst, mut worst_n, mut apart) = (0.0f64, 0.0f64, 0.0f64);
    for ((pw, nw, cw), (pc, nc, cc)) in world.iter().zip(&scope) {
        assert_eq!(cw, cc, "the colours are the same vertices'");
        let p = world_from_camera * Point3::from(f64s(*pc));
        let n = world_from_camera.rotation * f64s(*nc);
        worst = worst.max((p.coords - f64s(*pw)).norm());
        worst_n = worst_n.max((n - f64s(*nw)).norm());
        apart = apart.max((f64s(*pw) - f64s(*pc)).norm());
    }
    eprintln!(
        "scope frame: {} vertices, worst {worst:.2e} mm, normals {worst_n:.2e}",
        world.len()
    );
    assert!(
        worst < 1e-3 && worst_n < 1e-5,
        "{worst} mm, normals {worst_n}"
    );
    (world.len(), apart)
}

/// The shared GPU context, or `None` with the reason printed when no adapter exists; with
/// `MISSLAM_REQUIRE_GPU` set (CI) a missing adapter fails the test instead of hiding.
pub fn gpu() -> Option<std::sync::Arc<misslam::framework::GpuContext>> {
    match misslam::framework::gpu::GpuProvider::new().get() {
        Ok(ctx) => Some(ctx),
        Err(e) => {
            assert!(
                std::env::var_os("MISSLAM_REQUIRE_GPU").is_none(),
                "MISSLAM_REQUIRE_GPU is set but: {e}"
            );
            println!("skipped: {e}");
            None
        }
    }
}
