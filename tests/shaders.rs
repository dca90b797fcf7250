//! Every WGSL file under `shaders/` parses and validates with naga (the compiler wgpu uses).
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

use std::path::{Path, PathBuf};

fn wgsl_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("shaders folder") {
        let p = entry.expect("entry").path();
        if p.is_dir() {
            wgsl_files(&p, out);
        } else if p.extension().is_some_and(|e| e == "wgsl") {
            out.push(p);
        }
    }
}

#[test]
fn all_shaders_validate() {
    let mut files = Vec::new();
    wgsl_files(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("shaders"),
        &mut files,
    );
    assert!(!files.is_empty(), "no shaders found");
    // Kernels may use shared files of the same folder (`// uses: NAME.wgsl`); each file is
    // validated as the host assembles it.
    let sources: Vec<(String, String)> = files
        .iter()
        .map(|f| {
            let name = f.file_name().unwrap().to_string_lossy().into_owned();
            (name, std::fs::read_to_string(f).expect("read shader"))
        })
        .collect();
    let mut failures = Vec::new();
    for (f, (_, raw)) in files.iter().zip(&sources) {
        let folder: Vec<(&str, &str)> = files
            .iter()
            .zip(&sources)
            .filter(|(g, _)| g.parent() == f.parent())
            .map(|(_, (n, s))| (n.as_str(), s.as_str()))
            .collect();
        let src = match misslam_framework::gpu::wgsl_with_uses(raw, &folder) {
            Ok(s) => s,
            Err(e) => {
                failures.push(format!("{}: {e}", f.display()));
                continue;
            }
        };
        let module = match naga::front::wgsl::parse_str(&src) {
            Ok(m) => m,
            Err(e) => {
                failures.push(e.emit_to_string_with_path(&src, &f.display().to_string()));
                continue;
            }
        };
        // Subgroup kernels need the adapter's subgroups (the host picks them only then).
        let subgroups = src.contains("@builtin(subgroup_");
        let caps = if subgroups {
            naga::valid::Capabilities::SUBGROUP
        } else {
            naga::valid::Capabilities::default()
        };
        let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), caps);
        if subgroups {
            v.subgroup_stages(naga::valid::ShaderStages::COMPUTE)
                .subgroup_operations(naga::valid::SubgroupOperationSet::all());
        }
        if let Err(e) = v.validate(&module) {
            failures.push(e.emit_to_string_with_path(&src, &f.display().to_string()));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn a_broken_shader_is_caught() {
    let src = "@compute @workgroup_size(1) fn main() { let x: u32 = 1.5; }";
    let module = naga::front::wgsl::parse_str(src);
    let invalid = match module {
        Err(_) => true,
        Ok(m) => naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::default(),
        )
        .validate(&m)
        .is_err(),
    };
    assert!(invalid, "the validator must reject a type error");
}
