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
    // A used file is validated inside the kernels that use it, not alone; a file that says
    // `// replaces: NAME.wgsl` (the host may put it in NAME's place) is validated alone and in
    // every kernel of its folder that uses NAME, in NAME's place.
    let used: Vec<&str> = sources
        .iter()
        .flat_map(|(_, s)| s.lines().filter_map(|l| l.trim().strip_prefix("// uses:")))
        .map(str::trim)
        .collect();
    let replaces = |s: &str| {
        s.lines()
            .find_map(|l| l.trim().strip_prefix("// replaces:"))
            .map(|n| n.trim().to_owned())
    };
    let mut failures = Vec::new();
    let mut units: Vec<(String, String)> = Vec::new();
    for (f, (name, raw)) in files.iter().zip(&sources) {
        if used.contains(&name.as_str()) {
            continue;
        }
        let folder: Vec<(&str, &str)> = files
            .iter()
            .zip(&sources)
            .filter(|(g, _)| g.parent() == f.parent())
            .map(|(_, (n, s))| (n.as_str(), s.as_str()))
            .collect();
        let mut variants = vec![(f.display().to_string(), folder.clone())];
        for (g, (_, alt)) in files.iter().zip(&sources) {
            if let Some(target) = replaces(alt).filter(|_| g.parent() == f.parent()) {
                if raw.contains(&format!("// uses: {target}")) {
                    let swapped = folder
                        .iter()
                        .map(|&(n, s)| {
                            if n == target {
                                (n, alt.as_str())
                            } else {
                                (n, s)
                            }
                        })
                        .collect();
                    variants.push((format!("{} with {}", f.display(), g.display()), swapped));
                }
            }
        }
        for (label, files_of) in variants {
            match misslam_framework::gpu::wgsl_with_uses(raw, &files_of) {
                Ok(s) => units.push((label, s)),
                Err(e) => failures.push(format!("{label}: {e}")),
            }
        }
    }
    assert!(
        units.iter().any(|(l, _)| l.contains(" with ")),
        "no replacement was validated in place"
    );
    for (label, src) in &units {
        let module = match naga::front::wgsl::parse_str(src) {
            Ok(m) => m,
            Err(e) => {
                failures.push(e.emit_to_string_with_path(src, label));
                continue;
            }
        };
        // Subgroup kernels need the adapter's subgroups (the host picks them only then).
        let subgroups = src.contains("@builtin(subgroup_");
        let mut caps = naga::valid::Capabilities::default();
        if subgroups {
            caps |= naga::valid::Capabilities::SUBGROUP;
        }
        // 64-bit atomics likewise (`sgm_sums64.wgsl`).
        if src.contains("atomic<u64>") {
            caps |= naga::valid::Capabilities::SHADER_INT64
                | naga::valid::Capabilities::SHADER_INT64_ATOMIC_ALL_OPS;
        }
        let mut v = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), caps);
        if subgroups {
            v.subgroup_stages(naga::valid::ShaderStages::COMPUTE)
                .subgroup_operations(naga::valid::SubgroupOperationSet::all());
        }
        if let Err(e) = v.validate(&module) {
            failures.push(e.emit_to_string_with_path(src, label));
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
