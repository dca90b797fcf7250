//! Calibration readers: the native `calib.toml`, ORB-SLAM style YAML, and Middlebury `calib.txt`.
//! Every error names the file and the field (and the line where the format has lines).

use std::path::{Path, PathBuf};

use misslam_framework::toml;
use misslam_framework::StereoCalib;

/// A calibration that could not be read.
#[derive(Debug, thiserror::Error)]
#[error("{file}: {message}")]
pub struct CalibError {
    /// The calibration file.
    pub file: PathBuf,
    /// What is wrong, naming the field.
    pub message: String,
}

fn fail(file: &Path, message: impl Into<String>) -> CalibError {
    CalibError {
        file: file.to_owned(),
        message: message.into(),
    }
}

/// The native format (see `../shared/data/README.md`).
#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct CalibToml {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    baseline_mm: f64,
    #[serde(default)]
    doffs: f64,
}

/// Reads a calibration file, choosing the format by name: `*.toml`, `*.yaml`/`*.yml`, `*.txt`.
/// `image_size` fills in the size for formats that may omit it (ORB-SLAM YAML).
pub fn read_calib(path: &Path, image_size: Option<(u32, u32)>) -> Result<StereoCalib, CalibError> {
    let text =
        std::fs::read_to_string(path).map_err(|e| fail(path, format!("cannot read: {e}")))?;
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    let calib = match ext {
        "toml" => parse_toml(path, &text)?,
        "yaml" | "yml" => parse_orbslam_yaml(path, &text, image_size)?,
        "txt" => parse_middlebury(path, &text)?,
        _ => {
            return Err(fail(
                path,
                "unknown calibration format (expected .toml, .yaml or Middlebury calib.txt)",
            ))
        }
    };
    calib.validate().map_err(|m| fail(path, m))?;
    Ok(calib)
}

/// Parses the native `calib.toml`.
pub fn parse_toml(path: &Path, text: &str) -> Result<StereoCalib, CalibError> {
    let c: CalibToml = toml::from_str(text).map_err(|e| {
        let line = e
            .span()
            .map(|s| text[..s.start.min(text.len())].matches('\n').count() + 1);
        match line {
            Some(l) => fail(path, format!("line {l}: {}", e.message().trim())),
            None => fail(path, e.message().trim().to_owned()),
        }
    })?;
    Ok(StereoCalib {
        width: c.width,
        height: c.height,
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        cx_right: c.cx + c.doffs,
        baseline_mm: c.baseline_mm,
    })
}

/// `key: value` lines of an OpenCV/ORB-SLAM YAML file (no nesting needed for these keys).
fn yaml_scalars(text: &str) -> Vec<(usize, String, String)> {
    text.lines()
        .enumerate()
        .filter_map(|(i, line)| {
            let line = line.split('#').next()?.trim();
            if line.starts_with('%') || line.starts_with("---") {
                return None;
            }
            let (k, v) = line.split_once(':')?;
            Some((
                i + 1,
                k.trim().to_owned(),
                v.trim().trim_matches('"').to_owned(),
            ))
        })
        .collect()
}

/// Parses ORB-SLAM2 (`Camera.fx`, `Camera.bf`) and ORB-SLAM3 (`Camera1.fx`, `Stereo.b`) style YAML.
/// Following ORB-SLAM, `Camera.bf` is `fx * baseline` with the baseline in metres, and `Stereo.b`
/// is the baseline in metres.
pub fn parse_orbslam_yaml(
    path: &Path,
    text: &str,
    image_size: Option<(u32, u32)>,
) -> Result<StereoCalib, CalibError> {
    let kv = yaml_scalars(text);
    let get = |names: &[&str]| -> Result<Option<f64>, CalibError> {
        for (line, k, v) in &kv {
            if names.contains(&k.as_str()) {
                return v
                    .parse::<f64>()
                    .map(Some)
                    .map_err(|_| fail(path, format!("line {line}: `{k}` is `{v}`, not a number")));
            }
        }
        Ok(None)
    };
    let need = |names: &[&str]| -> Result<f64, CalibError> {
        get(names)?.ok_or_else(|| fail(path, format!("missing `{}`", names[0])))
    };
    let fx = need(&["Camera.fx", "Camera1.fx"])?;
    let fy = need(&["Camera.fy", "Camera1.fy"])?;
    let cx = need(&["Camera.cx", "Camera1.cx"])?;
    let cy = need(&["Camera.cy", "Camera1.cy"])?;
    let baseline_m = match (get(&["Stereo.b"])?, get(&["Camera.bf"])?) {
        (Some(b), _) => b,
        (None, Some(bf)) => bf / fx,
        (None, None) => return Err(fail(path, "missing `Camera.bf` (or `Stereo.b`)")),
    };
    let width = get(&["Camera.width", "Camera1.width"])?;
    let height = get(&["Camera.height", "Camera1.height"])?;
    let (width, height) = match (width, height, image_size) {
        (Some(w), Some(h), _) => (w as u32, h as u32),
        (_, _, Some(size)) => size,
        _ => {
            return Err(fail(
                path,
                "missing `Camera.width`/`Camera.height` and no image to take them from",
            ))
        }
    };
    Ok(StereoCalib {
        width,
        height,
        fx,
        fy,
        cx,
        cy,
        cx_right: cx,
        baseline_mm: baseline_m * 1000.0,
    })
}

/// Parses a Middlebury 2014 `calib.txt` (`cam0=[f 0 cx; 0 f cy; 0 0 1]`, `doffs`, `baseline` in mm).
pub fn parse_middlebury(path: &Path, text: &str) -> Result<StereoCalib, CalibError> {
    let mut cam0: Option<[f64; 9]> = None;
    let mut cam1: Option<[f64; 9]> = None;
    let mut doffs = None;
    let mut baseline = None;
    let mut width = None;
    let mut height = None;
    for (i, line) in text.lines().enumerate() {
        let Some((k, v)) = line.split_once('=') else {
            continue;
        };
        let (k, v) = (k.trim(), v.trim());
        let num = |v: &str| {
            v.parse::<f64>().map_err(|_| {
                fail(
                    path,
                    format!("line {}: `{k}` is `{v}`, not a number", i + 1),
                )
            })
        };
        match k {
            "cam0" | "cam1" => {
                let vals: Vec<f64> = v
                    .trim_matches(|c| c == '[' || c == ']')
                    .split(|c: char| c == ';' || c.is_whitespace())
                    .filter(|s| !s.is_empty())
                    .map(num)
                    .collect::<Result<_, _>>()?;
                let m: [f64; 9] = vals.try_into().map_err(|_| {
                    fail(path, format!("line {}: `{k}` must be a 3x3 matrix", i + 1))
                })?;
                if k == "cam0" {
                    cam0 = Some(m);
                } else {
                    cam1 = Some(m);
                }
            }
            "doffs" => doffs = Some(num(v)?),
            "baseline" => baseline = Some(num(v)?),
            "width" => width = Some(num(v)? as u32),
            "height" => height = Some(num(v)? as u32),
            _ => {}
        }
    }
    let cam0 = cam0.ok_or_else(|| fail(path, "missing `cam0`"))?;
    let baseline = baseline.ok_or_else(|| fail(path, "missing `baseline`"))?;
    let cx_right = match (cam1, doffs) {
        (Some(c1), _) => c1[2],
        (None, Some(d)) => cam0[2] + d,
        (None, None) => return Err(fail(path, "missing `cam1` and `doffs`")),
    };
    Ok(StereoCalib {
        width: width.ok_or_else(|| fail(path, "missing `width`"))?,
        height: height.ok_or_else(|| fail(path, "missing `height`"))?,
        fx: cam0[0],
        fy: cam0[4],
        cx: cam0[2],
        cy: cam0[5],
        cx_right,
        baseline_mm: baseline,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn native_toml() {
        let t = "width = 720\nheight = 288\nfx = 343.7\nfy = 343.7\ncx = 362.9\ncy = 155.5\nbaseline_mm = 5.2\ndoffs = 1.5\n";
        let c = parse_toml(Path::new("calib.toml"), t).unwrap();
        assert_eq!((c.width, c.height), (720, 288));
        assert_eq!(c.doffs(), 1.5);
        let bad = t.replace("fy = 343.7", "fy = \"x\"");
        let e = parse_toml(Path::new("calib.toml"), &bad)
            .unwrap_err()
            .to_string();
        assert!(e.starts_with("calib.toml: line 4:"), "{e}");
        let typo = t.replace("baseline_mm", "baseline");
        let e = parse_toml(Path::new("calib.toml"), &typo)
            .unwrap_err()
            .to_string();
        assert!(e.contains("baseline"), "{e}");
    }

    #[test]
    fn orbslam_yaml() {
        let t = "%YAML:1.0\nCamera.fx: 435.2\nCamera.fy: 435.2\nCamera.cx: 367.4\nCamera.cy: 252.2\nCamera.width: 752\nCamera.height: 480\nCamera.bf: 47.9\n";
        let c = parse_orbslam_yaml(Path::new("c.yaml"), t, None).unwrap();
        assert!((c.baseline_mm - 47.9 / 435.2 * 1000.0).abs() < 1e-9);
        assert_eq!((c.width, c.height), (752, 480));
        let e = parse_orbslam_yaml(
            Path::new("c.yaml"),
            &t.replace("Camera.bf: 47.9", "Camera.bf: abc"),
            None,
        )
        .unwrap_err()
        .to_string();
        assert_eq!(e, "c.yaml: line 8: `Camera.bf` is `abc`, not a number");
    }

    #[test]
    fn middlebury_txt() {
        let t = "cam0=[3979.911 0 1244.772; 0 3979.911 1019.507; 0 0 1]\ncam1=[3979.911 0 1369.115; 0 3979.911 1019.507; 0 0 1]\ndoffs=124.343\nbaseline=193.001\nwidth=2964\nheight=1988\nndisp=270\n";
        let c = parse_middlebury(Path::new("calib.txt"), t).unwrap();
        assert!((c.doffs() - 124.343).abs() < 1e-9);
        assert_eq!(c.baseline_mm, 193.001);
        assert_eq!(c.fy, 3979.911);
        let e = parse_middlebury(Path::new("calib.txt"), &t.replace("baseline=193.001\n", ""))
            .unwrap_err()
            .to_string();
        assert_eq!(e, "calib.txt: missing `baseline`");
    }
}
