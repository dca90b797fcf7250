//! The `misslam` package: the registry of built-in plugins and the command line on top of
//! `misslam-framework`. Integration tests and examples of the workspace live in this package.
#![deny(missing_docs)]

pub mod ablate;
pub mod bench;
pub mod eval_cli;
pub mod phantom_export;

pub use misslam_framework as framework;

use misslam_framework::Registry;

/// The registration function every plugin crate exports.
pub type RegisterFn = fn(&mut Registry) -> Result<(), String>;

/// Every built-in plugin crate, in the order `misslam plugins` does not depend on (ids sort).
pub const BUILTIN: &[RegisterFn] = &[
    misslam_source_stereo_folder::register,
    misslam_source_phantom::register,
    misslam_sink_files::register,
    misslam_image_gray::register,
    misslam_depth_sgm::register,
    misslam_depth_elas::register,
    misslam_depth_postprocess::register,
    misslam_eval_depth::register,
    misslam_eval_recon::register,
    misslam_eval_tracking::register,
    misslam_deformation_ed::node::register,
    misslam_features_orb::register,
    misslam_features_surf::register,
    misslam_tracking_stereo::register,
    misslam_fusion_surfel::register,
    misslam_fusion_template::register,
];

/// Every built-in plugin; an id clash is an error naming both.
pub fn try_builtin_registry() -> Result<Registry, String> {
    let mut r = Registry::new();
    for register in BUILTIN {
        register(&mut r)?;
    }
    Ok(r)
}

/// Every built-in plugin. A clash (a programming error, caught by this crate's tests) is logged
/// and the later plugin left out.
pub fn builtin_registry() -> Registry {
    let mut r = Registry::new();
    for register in BUILTIN {
        if let Err(e) = register(&mut r) {
            tracing::error!("{e}");
        }
    }
    r
}

#[cfg(test)]
mod tests {
    #[test]
    fn builtin_plugins_register_without_clashes() {
        let r = super::try_builtin_registry().expect("no id clash");
        let ids: Vec<&str> = r.ids().collect();
        assert_eq!(
            ids,
            [
                "deformation.batch",
                "deformation.decoupled",
                "depth.elas",
                "depth.postprocess",
                "depth.sgm",
                "eval.depth",
                "eval.recon",
                "eval.tracking",
                "features.orb",
                "features.surf",
                "fusion.surfel",
                "fusion.template",
                "image.gray",
                "sink.files",
                "source.phantom",
                "source.stereo_folder",
                "tracking.stereo",
            ]
        );
        for p in r.iter() {
            let info = p.info();
            assert!(info.id.contains('.'), "{}", info.id);
            assert!(!info.summary.is_empty(), "{} has no summary", info.id);
            for param in &info.params {
                assert!(
                    !param.doc.is_empty(),
                    "{}: parameter `{}` has no doc",
                    info.id,
                    param.name
                );
            }
        }
    }
}
