//! The `misslam` package: the registry of built-in plugins and the command line on top of
//! `misslam-framework`. Integration tests and examples of the workspace live in this package.
#![deny(missing_docs)]

pub mod bench;

pub use misslam_framework as framework;

use misslam_framework::Registry;

/// Every built-in plugin.
pub fn builtin_registry() -> Registry {
    let mut r = Registry::new();
    let all: [fn(&mut Registry) -> Result<(), String>; 3] = [
        misslam_source_stereo_folder::register,
        misslam_sink_files::register,
        misslam_image_gray::register,
    ];
    for register in all {
        // Ids are distinct by construction; a clash is a programming error caught by the tests.
        if let Err(e) = register(&mut r) {
            tracing::error!("{e}");
        }
    }
    r
}
