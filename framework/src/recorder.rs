//! Rerun recording: every output port of every node with `log = true`, under `/<node>/<port>`,
//! on the timelines `frame` (sequence) and `input_time` (the source's timestamp, seconds).
//! Images, maps, clouds, models and meshes can be thinned to every N-th frame
//! ([`Recorder::set_log_every`], `[graph] log_every`); scalars and poses never are.
//!
//! Scene units are millimetres: depth images use `meter = 1` (one depth unit per scene unit) so
//! that they line up with the points, poses and meshes logged in mm. The camera convention is
//! OpenCV's (x right, y down, z forward), declared on the root.

use std::collections::HashMap;
use std::path::PathBuf;
use std::str::FromStr;
use std::sync::Arc;
use std::time::Duration;

use crate::graph::Graph;
use crate::payload::{Mesh, Payload, StereoCalib};

/// Where the recording goes (`--rerun`).
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub enum RerunMode {
    /// No recording.
    #[default]
    Off,
    /// Save to an `.rrd` file.
    Save(PathBuf),
    /// Spawn a viewer (`rerun` on the PATH, from `pip install rerun-sdk==0.36.3`) and stream to it.
    Spawn,
    /// Stream to a running viewer at a gRPC proxy URL (default `rerun+http://127.0.0.1:9876/proxy`).
    Connect(Option<String>),
}

impl FromStr for RerunMode {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "off" => Ok(RerunMode::Off),
            "spawn" => Ok(RerunMode::Spawn),
            "connect" => Ok(RerunMode::Connect(None)),
            _ => {
                if let Some(path) = s.strip_prefix("save:") {
                    if path.is_empty() {
                        return Err("`save:` needs a file, e.g. save:out.rrd".into());
                    }
                    Ok(RerunMode::Save(PathBuf::from(path)))
                } else if let Some(addr) = s.strip_prefix("connect:") {
                    let url = if addr.contains("://") {
                        addr.to_owned()
                    } else {
                        format!("rerun+http://{addr}/proxy")
                    };
                    Ok(RerunMode::Connect(Some(url)))
                } else {
                    Err(format!(
                        "`{s}`: expected save:PATH.rrd, spawn, connect, connect:HOST:PORT or off"
                    ))
                }
            }
        }
    }
}

/// Why the recording could not be opened or written.
#[derive(Debug, thiserror::Error)]
#[error("rerun: {0}")]
pub struct RecorderError(String);

/// A Rerun recording stream plus the state needed to draw trajectories.
pub struct Recorder {
    rec: rerun::RecordingStream,
    /// Images, maps, clouds, models and meshes are logged on every `every`-th frame from the
    /// first (`[graph] log_every`); scalars and poses on every frame.
    every: u64,
    /// The first frame begun, which is logged in full.
    first: Option<u64>,
    /// Whether the frame begun last is logged in full.
    full: bool,
    trajectories: HashMap<String, Vec<[f32; 3]>>,
    /// The mesh last logged at each path, held so that an output repeated frame after frame (the
    /// same `Arc`, e.g. a static template) is logged once: Rerun shows the latest value anyway.
    meshes: HashMap<String, Arc<Mesh>>,
    /// How long [`Recorder::flush`], and the recorder's drop, wait for a viewer to take what is
    /// left; `None`: until it is written (a file).
    flush_timeout: Option<Duration>,
    /// A flush timed out: the drop does not wait for the viewer again.
    gave_up: std::sync::atomic::AtomicBool,
}

impl Drop for Recorder {
    /// Closes the stream. A file is written to its end. A viewer that does not take the rest
    /// within the timeout (gone, or never answering) is left behind with a warning: Rerun's gRPC
    /// client, dropped, waits for it for ever, so the stream is dropped on a thread of its own,
    /// which the process's exit ends.
    fn drop(&mut self) {
        let rec = std::mem::replace(&mut self.rec, rerun::RecordingStream::disabled());
        let Some(timeout) = self.flush_timeout else {
            drop(rec);
            return;
        };
        let (done, wait) = std::sync::mpsc::channel();
        let closing = std::thread::Builder::new()
            .name("rerun close".into())
            .spawn(move || {
                drop(rec);
                done.send(()).ok();
            });
        if self.gave_up.load(std::sync::atomic::Ordering::Relaxed) {
            return;
        }
        if closing.is_ok() && wait.recv_timeout(timeout).is_err() {
            tracing::warn!(
                "rerun: the viewer did not take the rest of the recording within {:.1} s; the run's results are saved, the viewer may miss its last frames",
                timeout.as_secs_f64()
            );
        }
    }
}

/// The default viewer address of `--rerun connect`.
const DEFAULT_VIEWER: &str = "rerun+http://127.0.0.1:9876/proxy";

/// How long the end of a streamed run waits for the viewer to take the rest of the recording.
const STREAM_FLUSH_TIMEOUT: Duration = Duration::from_secs(20);

/// Checks that something listens at the host and port of a viewer URL
/// (`scheme://host:port/...`), so that `--rerun connect` with no viewer running fails before the
/// run instead of the run waiting for one at its end. A URL without a port is not checked.
fn probe_viewer(url: &str) -> Result<(), RecorderError> {
    use std::net::ToSocketAddrs;
    let rest = url.split_once("://").map_or(url, |(_, r)| r);
    let authority = rest.split('/').next().unwrap_or(rest);
    if authority
        .rsplit_once(':')
        .is_none_or(|(_, p)| p.parse::<u16>().is_err())
    {
        return Ok(());
    }
    let no_viewer = |why: String| {
        RecorderError(format!(
            "no Rerun viewer at {url} ({why}): start one with `rerun` (pip install rerun-sdk==0.36.3), or record to a file with --rerun save:FILE.rrd"
        ))
    };
    let addrs: Vec<_> = authority
        .to_socket_addrs()
        .map_err(|e| no_viewer(format!("cannot resolve {authority}: {e}")))?
        .collect();
    let mut last = String::from("no address");
    for a in &addrs {
        match std::net::TcpStream::connect_timeout(a, Duration::from_secs(2)) {
            Ok(_) => return Ok(()),
            Err(e) => last = format!("{a}: {e}"),
        }
    }
    Err(no_viewer(last))
}

impl Recorder {
    /// Opens a recording for `mode`; `None` for [`RerunMode::Off`].
    pub fn open(mode: &RerunMode, recording_name: &str) -> Result<Option<Recorder>, RecorderError> {
        let builder = rerun::RecordingStreamBuilder::new("misslam").recording_name(recording_name);
        let rec = match mode {
            RerunMode::Off => return Ok(None),
            RerunMode::Save(path) => {
                if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
                    std::fs::create_dir_all(parent).map_err(|e| {
                        RecorderError(format!("cannot create {}: {e}", parent.display()))
                    })?;
                }
                builder.save(path)
            }
            RerunMode::Spawn => builder.spawn(),
            RerunMode::Connect(url) => {
                let url = url.as_deref().unwrap_or(DEFAULT_VIEWER);
                probe_viewer(url)?;
                builder.connect_grpc_opts(url.to_owned())
            }
        }
        .map_err(|e| RecorderError(e.to_string()))?;
        Ok(Some(Recorder {
            rec,
            every: 1,
            first: None,
            full: true,
            trajectories: HashMap::new(),
            meshes: HashMap::new(),
            gave_up: false.into(),
            flush_timeout: match mode {
                RerunMode::Save(_) | RerunMode::Off => None,
                RerunMode::Spawn | RerunMode::Connect(_) => Some(STREAM_FLUSH_TIMEOUT),
            },
        }))
    }

    /// Logs the graph's TOML (and overrides) as a static text document at `/graph`.
    pub fn log_graph(&self, graph: &Graph) -> Result<(), RecorderError> {
        let mut md = format!("# {}\n\n`{}`\n\n", graph.name, graph.file.display());
        if !graph.overrides.is_empty() {
            md.push_str("Overrides: ");
            for o in &graph.overrides {
                md.push_str(&format!("`--set {o}` "));
            }
            md.push_str("\n\n");
        }
        md.push_str("```toml\n");
        md.push_str(&graph.text);
        md.push_str("\n```\n");
        self.rec
            .log_static("graph", &rerun::TextDocument::from_markdown(md))
            .map_err(err)?;
        self.rec
            .log_static("/", &rerun::ViewCoordinates::RIGHT_HAND_Y_DOWN())
            .map_err(err)
    }

    /// Logs images, depth and vertex maps, features, matches, graphs, models, meshes and point
    /// clouds on the first frame and every `every`-th after it only; metrics, timings and poses
    /// (the transform every frame, the trajectory's strip with the full frames) on every frame.
    /// At 320x240 the main graph logs about 5 MB a frame in full. 0 counts as 1.
    pub fn set_log_every(&mut self, every: u32) {
        self.every = u64::from(every.max(1));
    }

    /// Sets the time for what is logged next, and whether this frame is logged in full
    /// ([`Recorder::set_log_every`]).
    pub fn begin_frame(&mut self, frame: u64, input_time: Option<f64>) {
        let first = *self.first.get_or_insert(frame);
        self.full = frame.checked_sub(first).is_none_or(|d| d % self.every == 0);
        self.rec.set_time_sequence("frame", frame as i64);
        if let Some(t) = input_time {
            self.rec.set_duration_secs("input_time", t);
        }
    }

    /// Logs one node's wall time on this frame under `/timing/<node>`.
    pub fn log_timing(&self, node: &str, ms: f64) -> Result<(), RecorderError> {
        self.rec
            .log(format!("timing/{node}"), &rerun::Scalars::single(ms))
            .map_err(err)
    }

    /// Logs a payload at `path` with the archetypes that fit it.
    pub fn log_payload(&mut self, path: &str, payload: &Payload) -> Result<(), RecorderError> {
        if !self.full && !matches!(payload, Payload::Metrics(_) | Payload::Pose(_)) {
            return Ok(());
        }
        if let Payload::Mesh(mesh) = payload {
            if self.meshes.get(path).is_some_and(|m| Arc::ptr_eq(m, mesh)) {
                return Ok(());
            }
            self.meshes.insert(path.to_string(), mesh.clone());
        }
        let rec = &self.rec;
        match payload {
            Payload::Stereo(s) => {
                let left = format!("{path}/left");
                rec.log(left.as_str(), &pinhole(&s.calib, s.calib.cx))
                    .map_err(err)?;
                rec.log(left.as_str(), &image(&s.left)).map_err(err)?;
                let right = format!("{path}/right");
                // The right camera sits `baseline` to the right of the left one.
                rec.log(
                    right.as_str(),
                    &rerun::Transform3D::from_translation([s.calib.baseline_mm as f32, 0.0, 0.0]),
                )
                .map_err(err)?;
                rec.log(right.as_str(), &pinhole(&s.calib, s.calib.cx_right))
                    .map_err(err)?;
                rec.log(right.as_str(), &image(&s.right)).map_err(err)?;
                if let Some(mask) = &s.left_mask {
                    rec.log(
                        format!("{path}/left_mask"),
                        &rerun::Image::from_l8(
                            mask.data.iter().map(|&v| v * 255).collect::<Vec<u8>>(),
                            [mask.width, mask.height],
                        ),
                    )
                    .map_err(err)?;
                }
            }
            Payload::Image(img) => rec.log(path, &image(img)).map_err(err)?,
            Payload::Disparity(d) => rec
                .log(path, &depth_image(&d.map.data, d.map.width, d.map.height))
                .map_err(err)?,
            Payload::Depth(d) => {
                rec.log(path, &pinhole(&d.calib, d.calib.cx)).map_err(err)?;
                rec.log(path, &depth_image(&d.map.data, d.map.width, d.map.height))
                    .map_err(err)?;
            }
            Payload::VertexMap(v) => {
                let pts: Vec<[f32; 3]> = v
                    .points
                    .iter()
                    .copied()
                    .filter(|p| p[2].is_finite())
                    .collect();
                rec.log(path, &rerun::Points3D::new(pts).with_radii([0.2f32]))
                    .map_err(err)?;
            }
            Payload::NormalMap(n) => {
                let rgb: Vec<u8> = n
                    .normals
                    .iter()
                    .flat_map(|v| {
                        v.map(|c| {
                            if c.is_finite() {
                                ((c * 0.5 + 0.5) * 255.0).clamp(0.0, 255.0) as u8
                            } else {
                                0
                            }
                        })
                    })
                    .collect();
                rec.log(path, &rerun::Image::from_rgb24(rgb, [n.width, n.height]))
                    .map_err(err)?;
            }
            Payload::Features(f) => {
                let pts: Vec<[f32; 2]> = f.keypoints.iter().map(|k| [k.x, k.y]).collect();
                let radii: Vec<f32> = f
                    .keypoints
                    .iter()
                    .map(|k| (k.size * 0.5).max(1.0))
                    .collect();
                rec.log(path, &rerun::Points2D::new(pts).with_radii(radii))
                    .map_err(err)?;
                if let Some(p3) = &f.points {
                    let pts: Vec<[f32; 3]> =
                        p3.iter().copied().filter(|p| p[2].is_finite()).collect();
                    rec.log(format!("{path}/points3d"), &rerun::Points3D::new(pts))
                        .map_err(err)?;
                }
            }
            Payload::Matches(m) => {
                let strips: Vec<[[f32; 2]; 2]> = m
                    .query_xy
                    .iter()
                    .zip(&m.train_xy)
                    .map(|(a, b)| [*a, *b])
                    .collect();
                rec.log(path, &rerun::LineStrips2D::new(strips))
                    .map_err(err)?;
                if !m.train_points.is_empty() {
                    // The 3D ends of a tracker's correspondences (its train side is the world).
                    rec.log(
                        format!("{path}/train_points"),
                        &rerun::Points3D::new(m.train_points.clone()).with_radii([0.3f32]),
                    )
                    .map_err(err)?;
                }
            }
            Payload::Pose(p) => {
                let iso = p.world_from_camera;
                let t = iso.translation.vector.map(|v| v as f32);
                let r = iso.rotation.to_rotation_matrix();
                let m = r.matrix().map(|v| v as f32);
                let cols = [
                    [m[(0, 0)], m[(1, 0)], m[(2, 0)]],
                    [m[(0, 1)], m[(1, 1)], m[(2, 1)]],
                    [m[(0, 2)], m[(1, 2)], m[(2, 2)]],
                ];
                rec.log(
                    path,
                    &rerun::Transform3D::from_translation_mat3x3([t.x, t.y, t.z], cols),
                )
                .map_err(err)?;
                let traj = self.trajectories.entry(path.to_owned()).or_default();
                traj.push([t.x, t.y, t.z]);
                // The whole strip each time: its size grows with the run, so only on full frames.
                if self.full {
                    rec.log(
                        format!("{path}_trajectory"),
                        &rerun::LineStrips3D::new([traj.clone()]),
                    )
                    .map_err(err)?;
                }
            }
            Payload::DeformationGraph(g) => {
                let deformed: Vec<[f32; 3]> = g
                    .nodes
                    .iter()
                    .zip(&g.translations)
                    .map(|(n, t)| [n[0] + t[0], n[1] + t[1], n[2] + t[2]])
                    .collect();
                let edges: Vec<[[f32; 3]; 2]> = g
                    .edges
                    .iter()
                    .filter(|e| {
                        (e[0] as usize) < deformed.len() && (e[1] as usize) < deformed.len()
                    })
                    .map(|e| [deformed[e[0] as usize], deformed[e[1] as usize]])
                    .collect();
                rec.log(
                    format!("{path}/nodes"),
                    &rerun::Points3D::new(deformed).with_radii([0.5f32]),
                )
                .map_err(err)?;
                rec.log(format!("{path}/edges"), &rerun::LineStrips3D::new(edges))
                    .map_err(err)?;
            }
            Payload::Model(m) => {
                let colors: Vec<rerun::Color> = m
                    .colors
                    .iter()
                    .map(|c| rerun::Color::from_rgb(c[0], c[1], c[2]))
                    .collect();
                rec.log(
                    path,
                    &rerun::Points3D::new(m.positions.clone())
                        .with_colors(colors)
                        .with_radii([0.25f32]),
                )
                .map_err(err)?;
            }
            Payload::Mesh(mesh) => {
                let mut a = rerun::Mesh3D::new(mesh.vertices.clone())
                    .with_triangle_indices(mesh.triangles.clone());
                if let Some(n) = &mesh.normals {
                    a = a.with_vertex_normals(n.clone());
                }
                if let Some(c) = &mesh.colors {
                    a = a.with_vertex_colors(
                        c.iter().map(|c| rerun::Color::from_rgb(c[0], c[1], c[2])),
                    );
                }
                rec.log(path, &a).map_err(err)?;
            }
            Payload::PointCloud(pc) => {
                let mut a = rerun::Points3D::new(pc.positions.clone()).with_radii([0.25f32]);
                if let Some(c) = &pc.colors {
                    a = a.with_colors(c.iter().map(|c| rerun::Color::from_rgb(c[0], c[1], c[2])));
                }
                rec.log(path, &a).map_err(err)?;
            }
            Payload::Metrics(m) => {
                for (k, v) in &m.values {
                    rec.log(format!("{path}/{k}"), &rerun::Scalars::single(*v))
                        .map_err(err)?;
                }
            }
        }
        Ok(())
    }

    /// Blocks until everything logged so far has been written to the file, or sent to the
    /// viewer; a viewer that has not taken it within 20 s (gone, or never there) is an error, and
    /// what was not sent is dropped.
    pub fn flush(&self) -> Result<(), RecorderError> {
        let r = match self.flush_timeout {
            None => self.rec.flush_blocking(),
            Some(t) => self.rec.flush_with_timeout(t),
        };
        if r.is_err() && self.flush_timeout.is_some() {
            self.gave_up
                .store(true, std::sync::atomic::Ordering::Relaxed);
        }
        r.map_err(|e| {
            RecorderError(match self.flush_timeout {
                Some(t) => format!(
                    "the viewer did not take the rest of the recording within {:.1} s: {e}",
                    t.as_secs_f64()
                ),
                None => e.to_string(),
            })
        })
    }
}

fn err(e: impl std::fmt::Display) -> RecorderError {
    RecorderError(e.to_string())
}

fn pinhole(c: &StereoCalib, cx: f64) -> rerun::Pinhole {
    rerun::Pinhole::from_focal_length_and_resolution(
        [c.fx as f32, c.fy as f32],
        [c.width as f32, c.height as f32],
    )
    .with_principal_point([cx as f32, c.cy as f32])
    .with_image_plane_distance(20.0f32)
}

fn image(img: &crate::payload::Image) -> rerun::Image {
    if img.channels == 1 {
        rerun::Image::from_l8(img.data.clone(), [img.width, img.height])
    } else {
        rerun::Image::from_rgb24(img.data.clone(), [img.width, img.height])
    }
}

fn depth_image(data: &[f32], width: u32, height: u32) -> rerun::DepthImage {
    let bytes: Vec<u8> = bytemuck::cast_slice(data).to_vec();
    rerun::DepthImage::from_data_type_and_bytes(
        bytes,
        [width, height],
        rerun::datatypes::ChannelDatatype::F32,
    )
    .with_meter(1.0f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn modes_parse() {
        assert_eq!("off".parse::<RerunMode>(), Ok(RerunMode::Off));
        assert_eq!(
            "save:a/b.rrd".parse::<RerunMode>(),
            Ok(RerunMode::Save("a/b.rrd".into()))
        );
        assert_eq!(
            "connect:127.0.0.1:9877".parse::<RerunMode>(),
            Ok(RerunMode::Connect(Some(
                "rerun+http://127.0.0.1:9877/proxy".into()
            )))
        );
        assert!("save:".parse::<RerunMode>().is_err());
        assert!("view"
            .parse::<RerunMode>()
            .unwrap_err()
            .contains("save:PATH.rrd"));
    }

    #[test]
    fn connecting_to_no_viewer_fails_before_the_run_and_a_silent_one_times_out() {
        // A port nothing listens on: refused at once, naming the address and what to do.
        let free = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = free.local_addr().unwrap().port();
        drop(free);
        let mode: RerunMode = format!("connect:127.0.0.1:{port}").parse().unwrap();
        let err = Recorder::open(&mode, "t").err().expect("no viewer there");
        let msg = err.to_string();
        assert!(
            msg.contains(&format!("127.0.0.1:{port}")) && msg.contains("save:"),
            "{msg}"
        );
        // Something that accepts the connection but never answers as a viewer: the flush at the
        // end of the run gives up after its timeout instead of waiting for ever.
        let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let port = silent.local_addr().unwrap().port();
        let mode: RerunMode = format!("connect:127.0.0.1:{port}").parse().unwrap();
        let mut r = Recorder::open(&mode, "t").unwrap().expect("a recorder");
        r.flush_timeout = Some(Duration::from_millis(300));
        r.rec.log("x", &rerun::Scalars::single(1.0)).unwrap();
        let (done, wait) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            r.flush().ok();
            drop(r);
            done.send(()).ok();
        });
        assert!(
            wait.recv_timeout(Duration::from_secs(20)).is_ok(),
            "flushing and closing a stream to a silent viewer did not end"
        );
        drop(silent);
        // A URL without a port is left to Rerun.
        assert!(probe_viewer("rerun+http://localhost/proxy").is_ok());
    }

    /// A recorder writing into memory, and what it wrote.
    fn memory_recorder() -> (Recorder, rerun::sink::MemorySinkStorage) {
        let (rec, storage) = rerun::RecordingStreamBuilder::new("misslam-test")
            .memory()
            .unwrap();
        let r = Recorder {
            rec,
            every: 1,
            first: None,
            full: true,
            trajectories: HashMap::new(),
            meshes: HashMap::new(),
            flush_timeout: None,
            gave_up: false.into(),
        };
        (r, storage)
    }

    #[test]
    fn a_mesh_repeated_as_the_same_arc_is_logged_once() {
        let (mut r, storage) = memory_recorder();
        let mesh = Arc::new(Mesh {
            vertices: vec![[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]],
            normals: None,
            colors: None,
            triangles: vec![[0, 1, 2]],
        });
        let count = |r: &mut Recorder, frame: u64, p: &Payload| {
            r.begin_frame(frame, None);
            r.log_payload("a/mesh", p).unwrap();
            storage.take().len()
        };
        let p = Payload::Mesh(mesh.clone());
        assert!(count(&mut r, 0, &p) > 0);
        assert_eq!(count(&mut r, 1, &p), 0, "the same Arc was logged again");
        // Equal content in a new Arc is a new value: logged.
        let q = Payload::Mesh(Arc::new((*mesh).clone()));
        assert!(count(&mut r, 2, &q) > 0);
        // The same Arc at another path is logged there.
        r.begin_frame(3, None);
        r.log_payload("b/mesh", &q).unwrap();
        assert!(!storage.take().is_empty());
    }

    #[test]
    fn log_every_keeps_scalars_and_poses_on_every_frame() {
        let (mut r, storage) = memory_recorder();
        r.set_log_every(3);
        let image = Payload::Image(Arc::new(
            crate::payload::Image::new(2, 2, 1, vec![7; 4]).unwrap(),
        ));
        let metrics = Payload::Metrics(Arc::new(crate::payload::Metrics {
            values: [("a.b".to_owned(), 1.0)].into(),
        }));
        let pose = Payload::Pose(Arc::new(crate::payload::Pose {
            world_from_camera: nalgebra::Isometry3::identity(),
            state: crate::payload::TrackingState::Tracking,
        }));
        // Messages written per payload on frames 5 to 11 (the first frame begun is 5).
        let mut logged = |frame: u64, p: &Payload| {
            r.begin_frame(frame, None);
            r.log_payload("n/x", p).unwrap();
            r.rec.flush_blocking().unwrap();
            storage.take().len()
        };
        let images: Vec<usize> = (5..12).map(|f| logged(f, &image)).collect();
        let full: Vec<bool> = images.iter().map(|&n| n > 0).collect();
        assert_eq!(full, [true, false, false, true, false, false, true]);
        for f in 12..15 {
            assert!(logged(f, &metrics) > 0, "frame {f}: metrics not logged");
        }
        // The pose's transform every frame; its trajectory's strip with the full frames only.
        let poses: Vec<usize> = (15..21).map(|f| logged(f, &pose)).collect();
        assert!(poses.iter().all(|&n| n > 0), "{poses:?}");
        assert!(poses[5] > poses[4], "frame 20 adds its strip: {poses:?}");
        assert!(poses[2] > poses[0], "frame 17 adds its strip: {poses:?}");
    }
}
