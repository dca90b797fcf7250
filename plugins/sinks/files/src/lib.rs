//! `sink.files`: writes what reaches it into the run's output folder, one file per frame:
//! images as PNG, disparity and depth as PFM, point clouds, surfel models and meshes as PLY and
//! glTF binary. The codecs are plain functions ([`pfm`], [`mesh_io`]) usable on their own.
#![deny(missing_docs)]

pub mod mesh_io;
/// PFM codec (lives in the framework, shared with sources).
pub use misslam_framework::pfm;

use std::path::{Path, PathBuf};

use misslam_framework::{
    BuildContext, Flow, FrameInfo, Image, Inputs, Node, NodeContext, NodeError, NodeResult,
    Outputs, Payload, PortSpec, PortType, Registry, TypedPlugin,
};

use mesh_io::Geometry;

/// Formats for point clouds, models and meshes.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum GeometryFormat {
    /// Binary PLY.
    Ply,
    /// glTF 2.0 binary (`.glb`).
    Glb,
}

/// Parameters of `sink.files`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Folder inside the run's output folder; one sub-folder per input port.
    pub dir: PathBuf,
    /// Write images, disparity and depth every `every` frames (1: every frame).
    pub every: u32,
    /// Write point clouds, models and meshes every this many frames (0: only the last, at the end).
    pub geometry_every: u32,
    /// Formats for point clouds, models and meshes.
    pub geometry_formats: Vec<GeometryFormat>,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            dir: PathBuf::from("files"),
            every: 1,
            geometry_every: 0,
            geometry_formats: vec![GeometryFormat::Ply, GeometryFormat::Glb],
        }
    }
}

/// The node.
pub struct FilesSink {
    params: Params,
    ports: Vec<PortSpec>,
    last_geometry: Vec<Option<Payload>>,
}

fn ensure_dir(dir: &Path) -> NodeResult<()> {
    std::fs::create_dir_all(dir)
        .map_err(|e| NodeError::msg(format!("cannot create {}: {e}", dir.display())))
}

fn write_png(path: &Path, img: &Image) -> NodeResult<()> {
    let color = if img.channels == 1 {
        image::ExtendedColorType::L8
    } else {
        image::ExtendedColorType::Rgb8
    };
    image::save_buffer(path, &img.data, img.width, img.height, color)
        .map_err(|e| NodeError::msg(format!("{}: {e}", path.display())))
}

impl FilesSink {
    fn write_geometry(&self, dir: &Path, stem: &str, payload: &Payload) -> NodeResult<()> {
        let owned_normals;
        let geometry = match payload {
            Payload::PointCloud(pc) => Geometry {
                positions: &pc.positions,
                normals: None,
                colors: pc.colors.as_deref(),
                triangles: &[],
            },
            Payload::Model(m) => {
                owned_normals = (m.normals.len() == m.positions.len()).then_some(&m.normals);
                Geometry {
                    positions: &m.positions,
                    normals: owned_normals.map(Vec::as_slice),
                    colors: (m.colors.len() == m.positions.len()).then_some(m.colors.as_slice()),
                    triangles: &[],
                }
            }
            Payload::Mesh(m) => Geometry {
                positions: &m.vertices,
                normals: m.normals.as_deref(),
                colors: m.colors.as_deref(),
                triangles: &m.triangles,
            },
            _ => return Ok(()),
        };
        ensure_dir(dir)?;
        for f in &self.params.geometry_formats {
            let (path, res) = match f {
                GeometryFormat::Ply => {
                    let p = dir.join(format!("{stem}.ply"));
                    let r = mesh_io::write_ply(&p, &geometry);
                    (p, r)
                }
                GeometryFormat::Glb => {
                    let p = dir.join(format!("{stem}.glb"));
                    let r = mesh_io::write_glb(&p, &geometry);
                    (p, r)
                }
            };
            res.map_err(|e| NodeError::msg(format!("{}: {e}", path.display())))?;
        }
        Ok(())
    }
}

impl Node for FilesSink {
    fn process(
        &mut self,
        ctx: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        _outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let root = ctx.out_dir.join(&self.params.dir);
        let stem = format!("{:06}", frame.index);
        let dense_due = frame.ordinal.is_multiple_of(self.params.every as u64);
        let geom_due = self.params.geometry_every > 0
            && frame
                .ordinal
                .is_multiple_of(self.params.geometry_every as u64);
        for (i, spec) in self.ports.iter().enumerate() {
            let Some(payload) = inputs.raw(i) else {
                continue;
            };
            let dir = root.join(&spec.name);
            match payload {
                Payload::Image(img) if dense_due => {
                    ensure_dir(&dir)?;
                    write_png(&dir.join(format!("{stem}.png")), img)?;
                }
                Payload::Disparity(d) if dense_due => {
                    ensure_dir(&dir)?;
                    let p = dir.join(format!("{stem}.pfm"));
                    pfm::write_pfm(&p, &d.map)
                        .map_err(|e| NodeError::msg(format!("{}: {e}", p.display())))?;
                }
                Payload::Depth(d) if dense_due => {
                    ensure_dir(&dir)?;
                    let p = dir.join(format!("{stem}.pfm"));
                    pfm::write_pfm(&p, &d.map)
                        .map_err(|e| NodeError::msg(format!("{}: {e}", p.display())))?;
                }
                Payload::Pose(pose) => {
                    // Every frame, as a TUM trajectory (`frame tx ty tz qx qy qz qw`); a lost
                    // frame is a comment line, so readers skip it and nothing is guessed.
                    ensure_dir(&root)?;
                    let path = root.join(format!("{}.txt", spec.name));
                    let iso = pose.world_from_camera;
                    let (t, q) = (iso.translation.vector, iso.rotation);
                    let line = if pose.state == misslam_framework::TrackingState::Lost {
                        format!("# frame {} lost\n", frame.index)
                    } else {
                        format!(
                            "{} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}\n",
                            frame.index, t.x, t.y, t.z, q.i, q.j, q.k, q.w
                        )
                    };
                    append(&path, &line)?;
                }
                Payload::Metrics(m) => {
                    // Every frame, one JSON object per line: the frame index and the values
                    // (a value that is not finite is written as null, as JSON has no NaN).
                    ensure_dir(&root)?;
                    let path = root.join(format!("{}.jsonl", spec.name));
                    let mut line = serde_json::Map::new();
                    line.insert("frame".into(), frame.index.into());
                    for (k, &v) in &m.values {
                        let v = serde_json::Number::from_f64(v)
                            .map_or(serde_json::Value::Null, serde_json::Value::Number);
                        line.insert(k.clone(), v);
                    }
                    let mut text = serde_json::Value::Object(line).to_string();
                    text.push('\n');
                    append(&path, &text)?;
                }
                Payload::PointCloud(_) | Payload::Model(_) | Payload::Mesh(_) => {
                    self.last_geometry[i] = Some(payload.clone());
                    if geom_due {
                        self.write_geometry(&dir, &stem, payload)?;
                    }
                }
                _ => {}
            }
        }
        Ok(Flow::Continue)
    }

    fn start(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        // Trajectories and metrics are appended frame by frame: start from an empty file.
        let root = ctx.out_dir.join(&self.params.dir);
        for spec in &self.ports {
            let path = match spec.ty {
                PortType::Pose => root.join(format!("{}.txt", spec.name)),
                PortType::Metrics => root.join(format!("{}.jsonl", spec.name)),
                _ => continue,
            };
            if path.exists() {
                std::fs::remove_file(&path)
                    .map_err(|e| NodeError::msg(format!("{}: {e}", path.display())))?;
            }
        }
        Ok(())
    }

    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        let root = ctx.out_dir.join(&self.params.dir);
        for (i, spec) in self.ports.iter().enumerate() {
            if let Some(p) = &self.last_geometry[i] {
                self.write_geometry(&root.join(&spec.name), "final", p)?;
            }
        }
        Ok(())
    }
}

/// Appends `text` to the file at `path`, creating it.
fn append(path: &Path, text: &str) -> NodeResult<()> {
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| NodeError::msg(format!("{}: {e}", path.display())))?;
    std::io::Write::write_all(&mut f, text.as_bytes())
        .map_err(|e| NodeError::msg(format!("{}: {e}", path.display())))
}

fn ports() -> Vec<PortSpec> {
    vec![
        PortSpec::optional(
            "image",
            PortType::Image,
            "written as <dir>/image/<frame>.png",
        ),
        PortSpec::optional("left", PortType::Image, "written as <dir>/left/<frame>.png"),
        PortSpec::optional(
            "disparity",
            PortType::Disparity,
            "written as <dir>/disparity/<frame>.pfm",
        ),
        PortSpec::optional(
            "depth",
            PortType::Depth,
            "written as <dir>/depth/<frame>.pfm (mm)",
        ),
        PortSpec::optional(
            "points",
            PortType::PointCloud,
            "PLY/glb every `geometry_every` frames and at the end",
        ),
        PortSpec::optional(
            "model",
            PortType::Model,
            "PLY/glb every `geometry_every` frames and at the end",
        ),
        PortSpec::optional(
            "mesh",
            PortType::Mesh,
            "PLY/glb every `geometry_every` frames and at the end",
        ),
        PortSpec::optional(
            "pose",
            PortType::Pose,
            "every frame into <dir>/pose.txt (TUM: frame tx ty tz qx qy qz qw; lost frames as comments)",
        ),
        PortSpec::optional(
            "metrics",
            PortType::Metrics,
            "a node's per-frame metrics, every frame as a line of <dir>/metrics.jsonl ({\"frame\": n, key: value, ...}; not finite: null)",
        ),
    ]
}

/// Registers `sink.files`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "sink.files",
        "writes images (PNG), disparity and depth (PFM), point clouds, models and meshes (PLY, glb) per frame",
        ports(),
        vec![],
        |p: Params, _ctx: &BuildContext| {
            if p.every == 0 {
                return Err(misslam_framework::BuildError::Param {
                    key: Some("every".into()),
                    path: "every".into(),
                    message: "must be at least 1".into(),
                });
            }
            let ports = ports();
            let n = ports.len();
            Ok(FilesSink {
                params: p,
                ports,
                last_geometry: vec![None; n],
            })
        },
    )
    .with_output_dirs(|p: &Params| vec![("dir".to_owned(), p.dir.clone())]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use misslam_framework::FloatMap;

    fn tmp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("misslam-sink-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn pfm_round_trip_keeps_nan_and_row_order() {
        let map = FloatMap {
            width: 3,
            height: 2,
            data: vec![1.0, 2.0, f32::NAN, 4.0, 5.5, -6.0],
        };
        let p = tmp("pfm").join("a.pfm");
        pfm::write_pfm(&p, &map).unwrap();
        let back = pfm::read_pfm(&p).unwrap();
        assert_eq!((back.width, back.height), (3, 2));
        for (a, b) in map.data.iter().zip(&back.data) {
            assert!(a == b || (a.is_nan() && b.is_nan()));
        }
        // First stored row is the bottom row.
        let bytes = std::fs::read(&p).unwrap();
        let header = b"Pf\n3 2\n-1.0\n".len();
        assert_eq!(
            f32::from_le_bytes(bytes[header..header + 4].try_into().unwrap()),
            4.0
        );
    }

    #[test]
    fn glb_and_ply_are_readable() {
        let positions = [[0.0, 0.0, 100.0], [10.0, 0.0, 100.0], [0.0, 10.0, 100.0]];
        let colors = [[255u8, 0, 0], [0, 255, 0], [0, 0, 255]];
        let g = Geometry {
            positions: &positions,
            normals: None,
            colors: Some(&colors),
            triangles: &[[0, 1, 2]],
        };
        let d = tmp("geom");
        mesh_io::write_glb(&d.join("m.glb"), &g).unwrap();
        let bytes = std::fs::read(d.join("m.glb")).unwrap();
        let gltf = gltf::Gltf::from_slice(&bytes).expect("valid glb");
        let mesh = gltf.meshes().next().unwrap();
        let prim = mesh.primitives().next().unwrap();
        assert_eq!(prim.mode(), gltf::mesh::Mode::Triangles);
        let pos = prim.get(&gltf::Semantic::Positions).unwrap();
        assert_eq!(pos.count(), 3);
        // 10 mm written in metres, as f32.
        let max_x = pos.max().unwrap()[0].as_f64().unwrap();
        assert!((max_x - 0.01).abs() < 1e-8, "{max_x}");
        assert!(prim.get(&gltf::Semantic::Colors(0)).is_some());

        mesh_io::write_ply(&d.join("m.ply"), &g).unwrap();
        let ply = std::fs::read(d.join("m.ply")).unwrap();
        let header_end = ply.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let text = String::from_utf8_lossy(&ply[..header_end]);
        assert!(
            text.contains("element vertex 3") && text.contains("element face 1"),
            "{text}"
        );
        // 3 vertices x (12 + 3) bytes + 1 face x 13 bytes.
        assert_eq!(ply.len() - header_end, 3 * 15 + 13);
    }
}
