//! `source.stereo_folder`: a rectified stereo sequence from a folder.
//!
//! Layout (`../shared/data/README.md`): `calib.toml` (or an ORB-SLAM YAML, or a Middlebury
//! `calib.txt`), `left/<n>.png` and `right/<n>.png` with numeric names sorted numerically. The
//! frame index of the graph counts images in that order (times `step`), not file numbers.
//! The black border of rectified endoscope images is masked.
#![deny(missing_docs)]

pub mod calib;
pub mod depth_gt;
pub mod mask;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use misslam_framework::{
    BuildContext, BuildError, DepthMap, Flow, FrameInfo, Image, Inputs, Node, NodeContext,
    NodeError, NodeResult, Outputs, PortSpec, PortType, Registry, StereoCalib, StereoFrame,
    TypedPlugin,
};

pub use calib::{read_calib, CalibError};

/// Parameters of `source.stereo_folder`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Sequence folder (relative to the working directory, or absolute).
    pub path: PathBuf,
    /// Calibration file relative to `path`; found automatically when empty (`calib.toml`, then
    /// `calib.txt`, then the first `*.yaml`).
    pub calib: Option<PathBuf>,
    /// Folder of left images inside `path`.
    pub left_dir: String,
    /// Folder of right images inside `path`.
    pub right_dir: String,
    /// Take every `step`-th image pair.
    pub step: u32,
    /// Frame rate for timestamps: `timestamp = file number / fps` seconds.
    pub fps: f64,
    /// Mask the black border left by rectification (pixels connected to the image edge with all
    /// channels at or below `border_threshold`).
    pub mask_border: bool,
    /// Intensity at or below which a border pixel counts as black.
    pub border_threshold: u8,
    /// Ground-truth depth beside the images: "none", "pfm" (`<n>.pfm`, mm) or "colonsyn_rgb"
    /// (`depth_<n:07>.png`, the synthetic colon sets' RGB code); sent on `depth_gt`.
    pub depth_gt: depth_gt::DepthGtFormat,
    /// Folder of the ground-truth depth inside `path`.
    pub depth_gt_dir: String,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            path: PathBuf::new(),
            calib: None,
            left_dir: "left".into(),
            right_dir: "right".into(),
            step: 1,
            fps: 30.0,
            mask_border: true,
            border_threshold: 8,
            depth_gt: depth_gt::DepthGtFormat::None,
            depth_gt_dir: "depth_gt".into(),
        }
    }
}

/// One pair of file names.
#[derive(Clone, Debug)]
pub struct PairFiles {
    /// File number (the name without extension).
    pub number: u64,
    /// Left image.
    pub left: PathBuf,
    /// Right image.
    pub right: PathBuf,
}

/// The sequence: calibration and the pairs in order.
pub struct StereoFolder {
    params: Params,
    root: PathBuf,
    calib: StereoCalib,
    calib_file: PathBuf,
    pairs: Vec<PairFiles>,
}

fn numbered_images(dir: &Path) -> Result<Vec<(u64, PathBuf)>, String> {
    let entries =
        std::fs::read_dir(dir).map_err(|e| format!("cannot list {}: {e}", dir.display()))?;
    let mut files = Vec::new();
    for entry in entries {
        let path = entry
            .map_err(|e| format!("cannot list {}: {e}", dir.display()))?
            .path();
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if !matches!(
            ext.as_deref(),
            Some("png" | "jpg" | "jpeg" | "bmp" | "ppm" | "pgm" | "tif" | "tiff")
        ) {
            continue;
        }
        // Numbers may carry a prefix (`im0`, `frame_000012`): take the trailing digits.
        let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
        let digits: String = stem
            .chars()
            .rev()
            .take_while(char::is_ascii_digit)
            .collect::<Vec<_>>()
            .into_iter()
            .rev()
            .collect();
        if let Ok(n) = digits.parse::<u64>() {
            files.push((n, path));
        }
    }
    files.sort();
    Ok(files)
}

impl StereoFolder {
    /// Opens a sequence: reads the calibration, lists the pairs, checks the first pair's size.
    pub fn open(params: Params, root: PathBuf) -> Result<Self, String> {
        if params.step == 0 {
            return Err("`step` must be at least 1".into());
        }
        if !(params.fps > 0.0 && params.fps.is_finite()) {
            return Err(format!("`fps` must be positive, got {}", params.fps));
        }
        if !root.is_dir() {
            return Err(format!("`path`: {} is not a folder", root.display()));
        }
        let left_dir = root.join(&params.left_dir);
        let right_dir = root.join(&params.right_dir);
        let lefts = numbered_images(&left_dir)?;
        if lefts.is_empty() {
            return Err(format!("{} holds no numbered images", left_dir.display()));
        }
        let pairs: Vec<PairFiles> = lefts
            .into_iter()
            .step_by(params.step as usize)
            .map(|(number, left)| PairFiles {
                number,
                right: right_dir.join(left.file_name().unwrap_or_default()),
                left,
            })
            .collect();
        let calib_file = match &params.calib {
            Some(c) => root.join(c),
            None => find_calib(&root)?,
        };
        let first = image::image_dimensions(&pairs[0].left)
            .map_err(|e| format!("{}: {e}", pairs[0].left.display()))?;
        let calib = read_calib(&calib_file, Some(first)).map_err(|e| e.to_string())?;
        if (calib.width, calib.height) != first {
            return Err(format!(
                "{} says {}x{}, but {} is {}x{}: the calibration does not fit the images",
                calib_file.display(),
                calib.width,
                calib.height,
                pairs[0].left.display(),
                first.0,
                first.1
            ));
        }
        Ok(StereoFolder {
            params,
            root,
            calib,
            calib_file,
            pairs,
        })
    }

    /// The calibration.
    pub fn calib(&self) -> &StereoCalib {
        &self.calib
    }

    /// Number of pairs (after `step`).
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    /// True when there are no pairs.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// The files of pair `i`.
    pub fn files(&self, i: usize) -> Option<&PairFiles> {
        self.pairs.get(i)
    }

    /// Reads pair `i`; `None` past the end. Errors name the file.
    pub fn read(&self, i: usize) -> Option<Result<StereoFrame, String>> {
        let files = self.pairs.get(i)?;
        Some(self.read_pair(i as u64, files))
    }

    fn read_image(&self, path: &Path) -> Result<Image, String> {
        if !path.exists() {
            return Err(format!("{} is missing", path.display()));
        }
        let img =
            image::open(path).map_err(|e| format!("{}: cannot decode: {e}", path.display()))?;
        let (w, h) = (img.width(), img.height());
        if (w, h) != (self.calib.width, self.calib.height) {
            return Err(format!(
                "{} is {w}x{h}, the calibration ({}) says {}x{}",
                path.display(),
                self.calib_file.display(),
                self.calib.width,
                self.calib.height
            ));
        }
        let (channels, data) = match img {
            image::DynamicImage::ImageLuma8(g) => (1, g.into_raw()),
            other => (3, other.into_rgb8().into_raw()),
        };
        Image::new(w, h, channels, data).map_err(|e| format!("{}: {e}", path.display()))
    }

    fn read_pair(&self, index: u64, files: &PairFiles) -> Result<StereoFrame, String> {
        let left = self.read_image(&files.left)?;
        let right = self.read_image(&files.right)?;
        let (left_mask, right_mask) = if self.params.mask_border {
            (
                Some(mask::border_mask(&left, self.params.border_threshold)),
                Some(mask::border_mask(&right, self.params.border_threshold)),
            )
        } else {
            (None, None)
        };
        Ok(StereoFrame {
            index,
            timestamp: files.number as f64 / self.params.fps,
            left: Arc::new(left),
            right: Arc::new(right),
            calib: self.calib,
            left_mask,
            right_mask,
        })
    }

    /// The folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Ground-truth depth of pair `i` (mm), when the folder has it (`depth_gt` parameter).
    pub fn read_depth_gt(&self, i: usize) -> Result<Option<DepthMap>, String> {
        let Some(files) = self.pairs.get(i) else {
            return Ok(None);
        };
        let dir = self.root.join(&self.params.depth_gt_dir);
        let size = (self.calib.width, self.calib.height);
        Ok(
            depth_gt::read_depth_gt(&dir, self.params.depth_gt, files.number, size)?.map(|map| {
                DepthMap {
                    map,
                    calib: self.calib,
                }
            }),
        )
    }
}

fn find_calib(root: &Path) -> Result<PathBuf, String> {
    for name in ["calib.toml", "calib.txt"] {
        let p = root.join(name);
        if p.is_file() {
            return Ok(p);
        }
    }
    if let Ok(entries) = std::fs::read_dir(root) {
        let mut yamls: Vec<PathBuf> = entries
            .flatten()
            .map(|e| e.path())
            .filter(|p| matches!(p.extension().and_then(|e| e.to_str()), Some("yaml" | "yml")))
            .collect();
        yamls.sort();
        if let Some(y) = yamls.into_iter().next() {
            return Ok(y);
        }
    }
    Err(format!(
        "{} has no calib.toml, calib.txt or *.yaml (set `calib`)",
        root.display()
    ))
}

/// The node.
pub struct StereoFolderNode {
    folder: StereoFolder,
}

impl Node for StereoFolderNode {
    fn process(
        &mut self,
        _ctx: &mut NodeContext,
        frame: FrameInfo,
        _inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let Some(pair) = self.folder.read(frame.index as usize) else {
            return Ok(Flow::EndOfStream);
        };
        let pair = Arc::new(pair.map_err(NodeError::msg)?);
        if let Some(gt) = self
            .folder
            .read_depth_gt(frame.index as usize)
            .map_err(NodeError::msg)?
        {
            outputs.put("depth_gt", gt)?;
        }
        outputs.put_arc("left", pair.left.clone())?;
        outputs.put_arc("right", pair.right.clone())?;
        outputs.put_arc("stereo", pair)?;
        Ok(Flow::Continue)
    }
}

/// Registers `source.stereo_folder`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "source.stereo_folder",
        "rectified stereo pairs from a folder (left/, right/, calib.toml | ORB-SLAM YAML | Middlebury calib.txt)",
        vec![],
        vec![
            PortSpec::new("stereo", PortType::Stereo, "the pair with calibration and border masks"),
            PortSpec::new("left", PortType::Image, "left image (shared, not copied)"),
            PortSpec::new("right", PortType::Image, "right image (shared, not copied)"),
            PortSpec::optional("depth_gt", PortType::Depth, "ground-truth depth of the left view, mm (with `depth_gt`)"),
        ],
        |p: Params, ctx: &BuildContext| {
            if p.path.as_os_str().is_empty() {
                return Err(BuildError::Param {
                    key: Some("path".into()),
                    path: "path".into(),
                    message: "set the sequence folder, e.g. `--set src.path=../shared/data/hamlyn20`".into(),
                });
            }
            let _ = ctx;
            let root = p.path.clone();
            let folder = StereoFolder::open(p, root).map_err(BuildError::Failed)?;
            Ok(StereoFolderNode { folder })
        },
    ))
}
