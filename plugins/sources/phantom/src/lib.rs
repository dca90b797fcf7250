//! `source.phantom`: a deforming organ rendered as rectified stereo video, with exact ground
//! truth per frame: depth and disparity of the left view, the scope pose, the surface mesh of
//! that instant, and for every left pixel the rest-shape point it sees.
//!
//! The organ is a procedural surface ([`scene`]) meshed on a regular grid, textured by a
//! function of the rest surface ([`texture`]) so the texture moves with the tissue, deformed by
//! heartbeat, breathing and a tool press, lit by a point light at the scope tip (Lambert plus a
//! Blinn-Phong highlight), and rasterised ([`render`]) into both views. Everything is
//! deterministic from the seed.
#![deny(missing_docs)]

mod ahead;
pub mod mesh_input;
pub mod render;
pub mod scene;
mod sensor;
mod shade;
mod surface;
pub mod texture;

use std::path::PathBuf;
use std::sync::Arc;

use misslam_framework::nalgebra::{Isometry3, Translation3, Vector3};
use misslam_framework::{
    BuildContext, BuildError, DepthMap, DisparityMap, FloatMap, Flow, FrameInfo, Image, Inputs,
    Mesh, Node, NodeContext, NodeResult, Outputs, PortSpec, PortType, Pose, Registry, StereoCalib,
    StereoFrame, TrackingState, TypedPlugin, VertexMap,
};

use ahead::Ahead;
use render::{Raster, View};
use scene::{Motion, Scene, Trajectory};
use sensor::{frame_seed, gauss_table, quantize, to_srgb8, Noise, SplitMix, GAMMA_LUT};
use surface::{bounds, grid_normals, mesh_normals, Albedo, Atlas, ATLAS_MM};

/// Parameters of `source.phantom`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Organ: "heart", "liver", "kidney" or "stomach" (ignored when `mesh` is set).
    pub scene: Scene,
    /// A template surface to render instead of a procedural organ (OBJ, PLY in mm; glTF in m), e.g.
    /// `../shared/data/heart/heart.obj`; its bounding-box centre is placed `distance_mm` ahead.
    /// A mesh spanning more than 1 m along an axis is refused, naming its farthest vertex.
    pub mesh: Option<PathBuf>,
    /// Per-frame vertex positions of `mesh` (`.npy`, frames x vertices x 3, mm), e.g.
    /// `../shared/data/heart/heart_trajectory.npy`; the sequence loops over its frames. All of
    /// its positions together must lie within 1 m along each axis.
    pub vertex_trajectory: Option<PathBuf>,
    /// Frame rate of `vertex_trajectory`, Hz (default: `fps`).
    pub trajectory_fps: Option<f64>,
    /// Rotation applied to `mesh` about its centre before placing it (x, y, z Euler angles), degrees.
    pub mesh_rotation_deg: [f32; 3],
    /// Length of the sequence in frames (the stream ends after it).
    pub frames: u64,
    /// Frame rate, Hz (frame n is at time n / fps).
    pub fps: f64,
    /// Seed of texture and noise; the graph's seed when absent.
    pub seed: Option<u64>,
    /// Image width, px.
    pub width: u32,
    /// Image height, px.
    pub height: u32,
    /// Focal length (fx = fy), px.
    pub focal_px: f64,
    /// Stereo baseline, mm.
    pub baseline_mm: f64,
    /// Distance from the scope to the organ's far plane, mm (its nearest parts come about 25 mm closer).
    pub distance_mm: f32,
    /// Size of the tissue patch (x, y), mm.
    pub extent_mm: [f32; 2],
    /// Mesh grid spacing, mm.
    pub mesh_step_mm: f32,
    /// Scope motion: "static", "sweep" or "fast" (sweep plus a jerk).
    pub trajectory: Trajectory,
    /// Sweep amplitude, mm.
    pub sweep_mm: f32,
    /// Sweep period, s.
    pub sweep_period_s: f32,
    /// Start of the fast segment, s.
    pub fast_start_s: f32,
    /// Duration of the fast segment, s.
    pub fast_duration_s: f32,
    /// Excursion of the fast segment, mm.
    pub fast_amplitude_mm: f32,
    /// Heartbeat peak displacement, mm; the scene's default (heart 3, others 0) when absent.
    pub heartbeat_mm: Option<f32>,
    /// Heartbeat rate, Hz.
    pub heartbeat_hz: f32,
    /// Breathing peak displacement, mm; the scene's default (heart 1, liver 4, others 2) when absent.
    pub breathing_mm: Option<f32>,
    /// Breathing rate, Hz.
    pub breathing_hz: f32,
    /// Tool press depth, mm (0: no tool).
    pub tool_press_mm: f32,
    /// Tool press centre (x, y) on the tissue patch, mm.
    pub tool_xy_mm: [f32; 2],
    /// Tool press radius (Gaussian sigma), mm.
    pub tool_radius_mm: f32,
    /// Tool press start, s.
    pub tool_start_s: f32,
    /// Tool press duration, s.
    pub tool_duration_s: f32,
    /// Vessel spacing of the texture, mm.
    pub vessel_scale_mm: f32,
    /// Fraction of the surface (0..1) in low-texture patches.
    pub low_texture_fraction: f32,
    /// Ambient light (0..1).
    pub ambient: f32,
    /// Strength of the specular highlight (0: matte).
    pub specular: f32,
    /// Blinn-Phong exponent of the highlight.
    pub shininess: f32,
    /// Lens vignetting: how much darker the image corners are (0..1, 0: none).
    pub vignetting: f32,
    /// Sensor noise, standard deviation in 8-bit levels (0: noise-free).
    pub noise_sigma: f32,
    /// Motion blur: renders averaged over the exposure (1: none). Costs this many renders.
    pub motion_blur_samples: u32,
    /// Exposure time for motion blur, s.
    pub exposure_s: f32,
    /// Renderers working ahead of the graph (the node's `render_threads`): 1 renders each frame
    /// when the graph asks for it; N > 1 runs N renderers on threads of their own, each a frame
    /// or two ahead (frame k on renderer k mod N), so the phantom delivers frames as a camera
    /// would while the graph measures its own speed (`graph.pipeline`). The frames are the
    /// same; memory grows by about 2N frames. Each renderer shades its frame on one thread of
    /// its own, not on the pool the graph's stages share (see `render_nice`).
    pub render_threads: u32,
    /// The CPU priority of the renderers ahead (`render_threads` > 1) as a Unix nice value,
    /// 0 to 19: 19 (the default) is the lowest, so a stage of the graph that wants a core takes
    /// it from a renderer at once and the renderers use the cores the graph leaves idle, as a
    /// camera's frames cost the graph nothing; 0 shares the cores equally. Linux only (elsewhere
    /// the renderers keep the process's priority).
    pub render_nice: u32,
    /// Frames rendered before the first one is handed out (0: none): the graph then reads them
    /// from memory, as from a capture card, and no renderer shares the cores with it while it
    /// runs, which is how the SLAM stages' own speed is measured (`misslam run ... --set
    /// src.prerender_frames=150`). Rendered in parallel on the pool's threads (a clone of the
    /// phantom per worker) from the first frame asked for; later frames, or all after a skipped
    /// one, are rendered as `render_threads` says. The frames are the same. About 40 bytes per
    /// pixel and frame: at most 8 GB in all.
    pub prerender_frames: u32,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            scene: Scene::Heart,
            mesh: None,
            vertex_trajectory: None,
            trajectory_fps: None,
            mesh_rotation_deg: [0.0, 0.0, 0.0],
            frames: 300,
            fps: 30.0,
            seed: None,
            width: 640,
            height: 480,
            focal_px: 700.0,
            baseline_mm: 5.0,
            distance_mm: 90.0,
            extent_mm: [150.0, 120.0],
            mesh_step_mm: 1.0,
            trajectory: Trajectory::Sweep,
            sweep_mm: 10.0,
            sweep_period_s: 8.0,
            fast_start_s: 4.0,
            fast_duration_s: 0.2,
            fast_amplitude_mm: 8.0,
            heartbeat_mm: None,
            heartbeat_hz: 1.2,
            breathing_mm: None,
            breathing_hz: 0.25,
            tool_press_mm: 0.0,
            tool_xy_mm: [8.0, 4.0],
            tool_radius_mm: 6.0,
            tool_start_s: 2.0,
            tool_duration_s: 2.0,
            vessel_scale_mm: 2.5,
            low_texture_fraction: 0.1,
            ambient: 0.25,
            specular: 0.35,
            shininess: 60.0,
            vignetting: 0.25,
            noise_sigma: 2.0,
            motion_blur_samples: 1,
            exposure_s: 0.02,
            render_threads: 1,
            render_nice: 19,
            prerender_frames: 0,
        }
    }
}

/// The most memory `prerender_frames` may take.
const PRERENDER_MAX_BYTES: u64 = 8_000_000_000;

/// About how much memory `p.prerender_frames` frames take, with `vertices` in the mesh: per
/// pixel two RGB views, depth, disparity and the rest point; per vertex its position, normal
/// and colour, and two triangles.
fn prerender_bytes(p: &Params, vertices: usize) -> u64 {
    let pixel = 2 * 3 + 4 + 4 + 12;
    let vertex = 12 + 12 + 3 + 2 * 12;
    u64::from(p.prerender_frames)
        * (u64::from(p.width) * u64::from(p.height) * pixel + vertices as u64 * vertex)
}

/// Everything the phantom knows about one frame.
#[derive(Clone, Debug)]
pub struct PhantomFrame {
    /// The rendered pair.
    pub stereo: StereoFrame,
    /// Depth of the left view, mm (NaN where no tissue).
    pub depth: DepthMap,
    /// Disparity of the left view, px.
    pub disparity: DisparityMap,
    /// The scope pose.
    pub pose: Pose,
    /// The surface of this instant, world frame.
    pub mesh: Mesh,
    /// Per left pixel, the rest-shape point it sees (world frame at t = 0), NaN where none.
    pub rest_points: VertexMap,
}

/// A phantom sequence. A clone renders the same frames and shares the baked albedo; the
/// renderers ahead (`render_threads`) are clones.
#[derive(Clone)]
pub struct Phantom {
    params: Params,
    motion: Motion,
    seed: u64,
    calib: StereoCalib,
    /// Rest positions of the grid vertices.
    rest: Vec<[f32; 3]>,
    rest_normals: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
    grid: Option<(usize, usize)>,
    /// Template motion: (frames, placed positions frame by frame).
    motion_frames: Option<(usize, Vec<[f32; 3]>)>,
    /// The baked albedo (tens of MB), shared by clones.
    albedo: Arc<Albedo>,
    vertex_colors: Vec<[u8; 3]>,
    gamma: Vec<f32>,
    gauss: Vec<f32>,
    // Scratch reused across frames, one per view.
    cam: [Vec<[f32; 3]>; 2],
    left: Raster,
    right: Raster,
}

fn check(ok: bool, field: &str, msg: &str) -> Result<(), String> {
    if ok {
        Ok(())
    } else {
        Err(format!("`{field}` {msg}"))
    }
}

impl Phantom {
    /// Builds the organ mesh and texture. `graph_seed` is used when `params.seed` is absent.
    pub fn new(params: Params, graph_seed: u64) -> Result<Self, String> {
        let p = &params;
        check(
            p.width >= 8 && p.height >= 8,
            "width/height",
            "must be at least 8 px",
        )?;
        check(
            p.focal_px > 0.0 && p.focal_px.is_finite(),
            "focal_px",
            "must be positive",
        )?;
        check(
            p.baseline_mm > 0.0 && p.baseline_mm.is_finite(),
            "baseline_mm",
            "must be positive",
        )?;
        check(p.fps > 0.0 && p.fps.is_finite(), "fps", "must be positive")?;
        // Every other number finite: a NaN or an infinity renders blank or garbled frames, which
        // the stages downstream would only report as missing depth.
        for (field, values) in [
            ("mesh_rotation_deg", &p.mesh_rotation_deg[..]),
            ("distance_mm", &[p.distance_mm][..]),
            ("extent_mm", &p.extent_mm[..]),
            ("sweep_mm", &[p.sweep_mm][..]),
            ("sweep_period_s", &[p.sweep_period_s][..]),
            ("fast_start_s", &[p.fast_start_s][..]),
            ("fast_duration_s", &[p.fast_duration_s][..]),
            ("fast_amplitude_mm", &[p.fast_amplitude_mm][..]),
            ("heartbeat_mm", &[p.heartbeat_mm.unwrap_or(0.0)][..]),
            ("heartbeat_hz", &[p.heartbeat_hz][..]),
            ("breathing_mm", &[p.breathing_mm.unwrap_or(0.0)][..]),
            ("breathing_hz", &[p.breathing_hz][..]),
            ("tool_press_mm", &[p.tool_press_mm][..]),
            ("tool_start_s", &[p.tool_start_s][..]),
            ("tool_xy_mm", &p.tool_xy_mm[..]),
            ("tool_duration_s", &[p.tool_duration_s][..]),
            ("vessel_scale_mm", &[p.vessel_scale_mm][..]),
            ("ambient", &[p.ambient][..]),
            ("specular", &[p.specular][..]),
            ("shininess", &[p.shininess][..]),
            ("vignetting", &[p.vignetting][..]),
            ("exposure_s", &[p.exposure_s][..]),
        ] {
            if let Some(v) = values.iter().find(|v| !v.is_finite()) {
                return Err(format!("`{field}` must be a finite number, got {v}"));
            }
        }
        if let Some(f) = p.trajectory_fps {
            check(
                f > 0.0 && f.is_finite(),
                "trajectory_fps",
                "must be positive",
            )?;
        }
        for (field, v) in [
            ("sweep_mm", p.sweep_mm),
            ("sweep_period_s", p.sweep_period_s),
            ("fast_duration_s", p.fast_duration_s),
            ("heartbeat_hz", p.heartbeat_hz),
            ("breathing_hz", p.breathing_hz),
            ("tool_duration_s", p.tool_duration_s),
            ("specular", p.specular),
            ("exposure_s", p.exposure_s),
        ] {
            check(v >= 0.0, field, &format!("must be >= 0, got {v}"))?;
        }
        check(
            p.vessel_scale_mm > 0.0,
            "vessel_scale_mm",
            "must be positive",
        )?;
        check(p.shininess > 0.0, "shininess", "must be positive")?;
        for (field, v) in [("ambient", p.ambient), ("vignetting", p.vignetting)] {
            check(
                (0.0..=1.0).contains(&v),
                field,
                &format!("must be in 0..1, got {v}"),
            )?;
        }
        check(
            p.motion_blur_samples >= 1,
            "motion_blur_samples",
            "must be at least 1",
        )?;
        check(
            p.distance_mm > 30.0,
            "distance_mm",
            "must exceed 30 mm (the organ bulges up to 25 mm toward the scope)",
        )?;
        check(
            p.mesh_step_mm > 0.05 && p.mesh_step_mm <= 10.0,
            "mesh_step_mm",
            "must be in (0.05, 10]",
        )?;
        check(
            p.extent_mm.iter().all(|&e| e > 2.0 * p.mesh_step_mm),
            "extent_mm",
            "must span several mesh cells",
        )?;
        check(
            (0.0..=1.0).contains(&p.low_texture_fraction),
            "low_texture_fraction",
            "must be in 0..1",
        )?;
        check(
            p.noise_sigma >= 0.0 && p.noise_sigma.is_finite(),
            "noise_sigma",
            "must be >= 0",
        )?;
        check(
            p.tool_radius_mm > 0.0 && p.tool_radius_mm.is_finite(),
            "tool_radius_mm",
            "must be positive",
        )?;
        check(
            (1..=64).contains(&p.render_threads),
            "render_threads",
            "must be in 1..=64",
        )?;
        check(p.render_nice <= 19, "render_nice", "must be in 0..=19")?;
        let nx = (p.extent_mm[0] / p.mesh_step_mm).round() as usize + 1;
        let ny = (p.extent_mm[1] / p.mesh_step_mm).round() as usize + 1;
        check(
            nx * ny <= 4_000_000,
            "mesh_step_mm",
            "makes a mesh of more than 4 million vertices",
        )?;
        let bytes = prerender_bytes(p, nx * ny);
        check(
            bytes <= PRERENDER_MAX_BYTES,
            "prerender_frames",
            &format!(
                "would hold about {:.1} GB of frames ({} of {}x{}), more than {} GB: prerender fewer",
                bytes as f64 / 1e9,
                p.prerender_frames,
                p.width,
                p.height,
                PRERENDER_MAX_BYTES / 1_000_000_000
            ),
        )?;
        let (default_beat, default_breath) = match p.scene {
            Scene::Heart => (3.0, 1.0),
            Scene::Liver => (0.0, 4.0),
            Scene::Kidney | Scene::Stomach => (0.0, 2.0),
        };
        let motion = Motion {
            heartbeat_mm: p.heartbeat_mm.unwrap_or(default_beat),
            heartbeat_hz: p.heartbeat_hz,
            breathing_mm: p.breathing_mm.unwrap_or(default_breath),
            breathing_hz: p.breathing_hz,
            tool_press_mm: p.tool_press_mm,
            tool_xy_mm: p.tool_xy_mm,
            tool_radius_mm: p.tool_radius_mm,
            tool_start_s: p.tool_start_s,
            tool_duration_s: p.tool_duration_s,
            trajectory: p.trajectory,
            sweep_mm: p.sweep_mm,
            sweep_period_s: p.sweep_period_s,
            fast_start_s: p.fast_start_s,
            fast_duration_s: p.fast_duration_s,
            fast_amplitude_mm: p.fast_amplitude_mm,
        };
        let seed = p.seed.unwrap_or(graph_seed);
        let tex = texture::TextureParams {
            seed: (seed ^ (seed >> 32)) as u32,
            vessel_scale_mm: p.vessel_scale_mm,
            low_texture_fraction: p.low_texture_fraction,
        };
        let (rest, rest_normals, triangles, grid, motion_frames, albedo) = match &p.mesh {
            None => {
                let mut rest = Vec::with_capacity(nx * ny);
                let mut rest_normals = Vec::with_capacity(nx * ny);
                for j in 0..ny {
                    for i in 0..nx {
                        let x = -0.5 * p.extent_mm[0] + i as f32 * p.extent_mm[0] / (nx - 1) as f32;
                        let y = -0.5 * p.extent_mm[1] + j as f32 * p.extent_mm[1] / (ny - 1) as f32;
                        rest.push(scene::rest_point(p.scene, x, y, p.distance_mm));
                        rest_normals.push(scene::rest_normal(p.scene, x, y, p.distance_mm));
                    }
                }
                let mut triangles = Vec::with_capacity((nx - 1) * (ny - 1) * 2);
                for j in 0..ny - 1 {
                    for i in 0..nx - 1 {
                        let a = (j * nx + i) as u32;
                        let b = a + 1;
                        let c = a + nx as u32;
                        let d = c + 1;
                        triangles.push([a, b, d]);
                        triangles.push([a, d, c]);
                    }
                }
                let half = [0.5 * p.extent_mm[0], 0.5 * p.extent_mm[1]];
                let atlas = Atlas::bake([-half[0], -half[1]], half, ATLAS_MM, |x, y, cache| {
                    texture::albedo_with(x, y, &tex, cache)
                });
                (
                    rest,
                    rest_normals,
                    triangles,
                    Some((nx, ny)),
                    None,
                    Albedo::Planar(atlas),
                )
            }
            Some(path) => {
                let m = mesh_input::read_mesh(path)?;
                mesh_input::check_extent(&m.vertices, m.vertices.len())
                    .map_err(|e| format!("{}: {e}", path.display()))?;
                let (vertices, frames) = match &p.vertex_trajectory {
                    None => (m.vertices.clone(), None),
                    Some(tp) => {
                        let (nf, nv, data) = mesh_input::read_npy_frames(tp)?;
                        if nv != m.vertices.len() || nf == 0 {
                            return Err(format!(
                                "`vertex_trajectory` {} has {nv} vertices per frame ({nf} frames), the mesh {} has {}",
                                tp.display(),
                                path.display(),
                                m.vertices.len()
                            ));
                        }
                        mesh_input::check_extent(&data, nv)
                            .map_err(|e| format!("`vertex_trajectory` {}: {e}", tp.display()))?;
                        (data[..nv].to_vec(), Some((nf, data)))
                    }
                };
                let (lo, hi) = bounds(&vertices);
                let centre = Vector3::from([0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k])));
                let r = p.mesh_rotation_deg.map(f32::to_radians);
                let rot = misslam_framework::nalgebra::UnitQuaternion::from_euler_angles(
                    r[0], r[1], r[2],
                );
                let place = |v: &[f32; 3]| {
                    let q =
                        rot * (Vector3::from(*v) - centre) + Vector3::new(0.0, 0.0, p.distance_mm);
                    [q.x, q.y, q.z]
                };
                let rest: Vec<[f32; 3]> = vertices.iter().map(place).collect();
                let motion =
                    frames.map(|(nf, data)| (nf, data.iter().map(place).collect::<Vec<_>>()));
                let rest_normals = mesh_normals(&rest, &m.triangles);
                let (lo, hi) = bounds(&rest);
                let plane = |a: usize, b: usize, shift: f32| {
                    Atlas::bake([lo[a], lo[b]], [hi[a], hi[b]], ATLAS_MM, |x, y, cache| {
                        texture::albedo_with(x + shift, y, &tex, cache)
                    })
                };
                let albedo = Albedo::Triplanar {
                    yz: plane(1, 2, 0.0),
                    xz: plane(0, 2, 1000.0),
                    xy: plane(0, 1, 2000.0),
                };
                (rest, rest_normals, m.triangles, None, motion, albedo)
            }
        };
        let vertex_colors = rest
            .iter()
            .zip(&rest_normals)
            .map(|(r, n)| albedo.sample(*r, *n).map(to_srgb8))
            .collect();
        let calib = StereoCalib {
            width: p.width,
            height: p.height,
            fx: p.focal_px,
            fy: p.focal_px,
            cx: (p.width as f64 - 1.0) / 2.0,
            cy: (p.height as f64 - 1.0) / 2.0,
            cx_right: (p.width as f64 - 1.0) / 2.0,
            baseline_mm: p.baseline_mm,
        };
        Ok(Phantom {
            params,
            motion,
            seed,
            calib,
            rest,
            rest_normals,
            triangles,
            grid,
            motion_frames,
            albedo: Arc::new(albedo),
            vertex_colors,
            gamma: (0..GAMMA_LUT)
                .map(|i| 255.0 * (i as f32 / (GAMMA_LUT - 1) as f32).powf(1.0 / 2.2))
                .collect(),
            gauss: gauss_table(),
            cam: [Vec::new(), Vec::new()],
            left: Raster::default(),
            right: Raster::default(),
        })
    }

    /// The calibration of the rendered pair.
    pub fn calib(&self) -> &StereoCalib {
        &self.calib
    }

    /// Rest positions of the mesh vertices (world frame at t = 0).
    pub fn rest_vertices(&self) -> &[[f32; 3]] {
        &self.rest
    }

    /// Rest normals of the mesh vertices.
    pub fn rest_normals(&self) -> &[[f32; 3]] {
        &self.rest_normals
    }

    /// The rest surface (world frame at t = 0) with normals and no colour: the "pre-operative"
    /// model of the template path, as a CT scan would give it.
    pub fn rest_mesh(&self) -> Mesh {
        Mesh {
            vertices: self.rest.clone(),
            normals: Some(self.rest_normals.clone()),
            colors: None,
            triangles: self.triangles.clone(),
        }
    }

    /// Mesh triangles (shared by the rest and deformed meshes).
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.triangles
    }

    /// Grid size of a procedural organ (vertices along x, along y; vertex (i, j) has index
    /// `j * nx + i`); `None` for a template mesh.
    pub fn grid(&self) -> Option<(usize, usize)> {
        self.grid
    }

    /// The parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Time of frame `index`, s.
    pub fn time(&self, index: u64) -> f32 {
        (index as f64 / self.params.fps) as f32
    }

    /// Deformed vertex positions at time `t`.
    pub fn deformed_vertices(&self, t: f32) -> Vec<[f32; 3]> {
        if let Some((nf, data)) = &self.motion_frames {
            // Linear between the template's frames, looping over them.
            let nv = self.rest.len();
            let f = (t as f64 * self.params.trajectory_fps.unwrap_or(self.params.fps)).max(0.0);
            let (k0, w) = (f.floor() as usize, (f - f.floor()) as f32);
            let (a, b) = (k0 % nf, (k0 + 1) % nf);
            let (fa, fb) = (&data[a * nv..(a + 1) * nv], &data[b * nv..(b + 1) * nv]);
            return fa
                .iter()
                .zip(fb)
                .map(|(p, q)| [0, 1, 2].map(|k| p[k] + w * (q[k] - p[k])))
                .collect();
        }
        self.rest
            .iter()
            .zip(&self.rest_normals)
            .map(|(r, n)| {
                let d = scene::displacement(self.params.scene, &self.motion, r[0], r[1], *n, t);
                [r[0] + d[0], r[1] + d[1], r[2] + d[2]]
            })
            .collect()
    }

    /// The scope's `world_from_camera` at time `t`.
    pub fn pose(&self, t: f32) -> Isometry3<f32> {
        scene::scope_pose(&self.motion, t)
    }

    /// Renders frame `index`; `None` past the end of the sequence.
    pub fn render(&mut self, index: u64) -> Option<PhantomFrame> {
        if index >= self.params.frames {
            return None;
        }
        let t = self.time(index);
        let seeds = [
            frame_seed(self.seed, index, 0),
            frame_seed(self.seed, index, 1),
        ];
        let samples = self.params.motion_blur_samples.max(1);
        let (left_img, right_img, vertices, normals, world_from_left) = if samples == 1 {
            let (vertices, normals, world_from_left) = self.rasterize_at(t);
            let (l, r) = self.shade_pair(
                &vertices,
                &normals,
                world_from_left,
                seeds,
                self.params.noise_sigma,
            );
            (l, r, vertices, normals, world_from_left)
        } else {
            // Average noise-free renders spread over the exposure, then add the sensor noise once.
            let exposure = self.params.exposure_s;
            let n_px = (self.params.width * self.params.height * 3) as usize;
            let (mut acc_l, mut acc_r) = (vec![0u32; n_px], vec![0u32; n_px]);
            for k in 0..samples {
                let ts = t + exposure * ((k as f32 + 0.5) / samples as f32 - 0.5);
                let (v, n, pose) = self.rasterize_at(ts);
                let (l, r) = self.shade_pair(&v, &n, pose, seeds, 0.0);
                acc_l
                    .iter_mut()
                    .zip(&l.data)
                    .for_each(|(a, &v)| *a += v as u32);
                acc_r
                    .iter_mut()
                    .zip(&r.data)
                    .for_each(|(a, &v)| *a += v as u32);
            }
            // Ground truth belongs to the middle of the exposure.
            let (vertices, normals, world_from_left) = self.rasterize_at(t);
            let finish = |acc: Vec<u32>, seed: u64| {
                let mut rng = SplitMix(seed);
                let mut noise = Noise::new(&self.gauss);
                let data = acc
                    .into_iter()
                    .map(|a| {
                        quantize(
                            a as f32 / samples as f32,
                            self.params.noise_sigma,
                            &mut noise,
                            &mut rng,
                        )
                    })
                    .collect();
                Image {
                    width: self.params.width,
                    height: self.params.height,
                    channels: 3,
                    data,
                }
            };
            let l = finish(acc_l, seeds[0]);
            let r = finish(acc_r, seeds[1]);
            (l, r, vertices, normals, world_from_left)
        };
        let (w, h) = (self.params.width, self.params.height);

        let depth = FloatMap {
            width: w,
            height: h,
            data: self.left.depth.clone(),
        };
        let disparity = FloatMap {
            width: w,
            height: h,
            data: depth
                .data
                .iter()
                .map(|&z| self.calib.disparity_from_depth(z))
                .collect(),
        };
        let rest_points: Vec<[f32; 3]> = (0..(w * h) as usize)
            .map(|i| {
                render::interpolate(&self.left, &self.triangles, &self.rest, i)
                    .unwrap_or([f32::NAN; 3])
            })
            .collect();
        let pose = Pose {
            world_from_camera: world_from_left.cast::<f64>(),
            state: TrackingState::Tracking,
        };
        Some(PhantomFrame {
            stereo: StereoFrame {
                index,
                timestamp: t as f64,
                left: Arc::new(left_img),
                right: Arc::new(right_img),
                calib: self.calib,
                left_mask: None,
                right_mask: None,
            },
            depth: DepthMap {
                map: depth,
                calib: self.calib,
            },
            disparity: DisparityMap {
                map: disparity,
                calib: self.calib,
            },
            pose,
            mesh: Mesh {
                vertices,
                normals: Some(normals),
                colors: Some(self.vertex_colors.clone()),
                triangles: self.triangles.clone(),
            },
            rest_points: VertexMap {
                width: w,
                height: h,
                points: rest_points,
            },
        })
    }

    /// Deforms the mesh to time `t` and rasterises both views into `self.left` / `self.right`.
    fn rasterize_at(&mut self, t: f32) -> (Vec<[f32; 3]>, Vec<[f32; 3]>, Isometry3<f32>) {
        let vertices = self.deformed_vertices(t);
        let normals = match self.grid {
            Some(grid) => grid_normals(&vertices, grid),
            None => mesh_normals(&vertices, &self.triangles),
        };
        let world_from_left = self.pose(t);
        let left_from_world = world_from_left.inverse();
        let b = self.params.baseline_mm as f32;
        let right_from_world = Translation3::new(-b, 0.0, 0.0) * left_from_world;
        let view = |cfw: Isometry3<f32>, cx: f64| View {
            fx: self.calib.fx as f32,
            fy: self.calib.fy as f32,
            cx: cx as f32,
            cy: self.calib.cy as f32,
            width: self.params.width,
            height: self.params.height,
            camera_from_world: cfw,
        };
        let lv = view(left_from_world, self.calib.cx);
        let rv = view(right_from_world, self.calib.cx_right);
        // The two views are independent: render them in parallel.
        let [cam_l, cam_r] = &mut self.cam;
        let (tris, left, right) = (&self.triangles, &mut self.left, &mut self.right);
        rayon::join(
            || render::rasterize(&lv, &vertices, tris, cam_l, left),
            || render::rasterize(&rv, &vertices, tris, cam_r, right),
        );
        (vertices, normals, world_from_left)
    }

    /// Albedo (linear RGB) at a rest point with its rest normal.
    pub fn albedo_at(&self, rest: [f32; 3], normal: [f32; 3]) -> [f32; 3] {
        self.albedo.sample(rest, normal)
    }
}

/// The node.
pub struct PhantomNode {
    phantom: Phantom,
    rest: Arc<Mesh>,
    /// The renderers ahead (`render_threads` > 1), started at the first frame asked for.
    ahead: Option<Ahead>,
    /// The frames rendered up front (`prerender_frames`), from the first frame asked for.
    prerendered: Option<ahead::Prerendered>,
}

impl Node for PhantomNode {
    fn process(
        &mut self,
        _: &mut NodeContext,
        frame: FrameInfo,
        _: &Inputs,
        out: &mut Outputs,
    ) -> NodeResult<Flow> {
        let Some(f) = self.frame(frame.index) else {
            return Ok(Flow::EndOfStream);
        };
        let stereo = Arc::new(f.stereo);
        out.put_arc("left", stereo.left.clone())?;
        out.put_arc("right", stereo.right.clone())?;
        out.put_arc("stereo", stereo)?;
        out.put("depth_gt", f.depth)?;
        out.put("disparity_gt", f.disparity)?;
        out.put("pose_gt", f.pose)?;
        out.put("mesh_gt", f.mesh)?;
        out.put_arc("mesh_rest", self.rest.clone())?;
        out.put("rest_points_gt", f.rest_points)?;
        Ok(Flow::Continue)
    }
}

/// The output ports.
pub fn outputs() -> Vec<PortSpec> {
    vec![
        PortSpec::new(
            "stereo",
            PortType::Stereo,
            "rectified pair with calibration",
        ),
        PortSpec::new("left", PortType::Image, "left image (shared)"),
        PortSpec::new("right", PortType::Image, "right image (shared)"),
        PortSpec::new(
            "depth_gt",
            PortType::Depth,
            "exact depth of the left view, mm",
        ),
        PortSpec::new(
            "disparity_gt",
            PortType::Disparity,
            "exact disparity of the left view, px",
        ),
        PortSpec::new(
            "pose_gt",
            PortType::Pose,
            "the scope's world_from_camera (left camera)",
        ),
        PortSpec::new(
            "mesh_gt",
            PortType::Mesh,
            "the tissue surface of this instant, world frame",
        ),
        PortSpec::new(
            "mesh_rest",
            PortType::Mesh,
            "the undeformed surface (world frame, no colour), the same every frame: a pre-operative template",
        ),
        PortSpec::new(
            "rest_points_gt",
            PortType::VertexMap,
            "per left pixel, the rest-shape point it sees",
        ),
    ]
}

/// Registers `source.phantom`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "source.phantom",
        "deforming organ phantom (heart, liver, kidney, stomach) as stereo video with exact ground truth",
        vec![],
        outputs(),
        |p: Params, ctx: &BuildContext| {
            let phantom = Phantom::new(p, ctx.seed).map_err(BuildError::Failed)?;
            let rest = Arc::new(phantom.rest_mesh());
            Ok(PhantomNode {
                phantom,
                rest,
                ahead: None,
                prerendered: None,
            })
        },
    ))
}
