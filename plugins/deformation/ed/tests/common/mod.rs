//! Constructed scenes for the solver tests: a sheet of tissue seen by a camera, deformed by known
//! fields and rendered into exact vertex and normal maps by the phantom's rasteriser.
#![allow(dead_code)]

use misslam_deformation_ed::{
    Binding, Correspondence, DecoupledParams, DecoupledSolver, DistanceField, EdGraph, Info,
    Intrinsics, Problem, Scan, SolveSet, Solver, SolverParams,
};
use misslam_framework::nalgebra::{Isometry3, Rotation3, Vector3};
use misslam_source_phantom::render::{rasterize, scan_maps, Raster, View};

/// One solve by fresh solvers: the decoupled one with the options `decoupled` gives, else the
/// batch one over every node, without the pose. Returns the info (both levels combined).
pub fn solve_once(
    graph: &mut EdGraph,
    problem: &Problem,
    params: &SolverParams,
    decoupled: Option<&DecoupledParams>,
) -> Info {
    let mut pose = Isometry3::identity();
    match decoupled {
        Some(dp) => DecoupledSolver::default()
            .solve(graph, &mut pose, problem, params, dp)
            .unwrap()
            .combined(),
        None => {
            let set = SolveSet::all(graph, false);
            Solver::default()
                .solve(graph, &mut pose, problem, &set, params)
                .unwrap()
        }
    }
}

pub const W: u32 = 160;
pub const H: u32 = 120;

pub fn intrinsics() -> Intrinsics {
    Intrinsics {
        fx: 150.0,
        fy: 150.0,
        cx: 79.5,
        cy: 59.5,
        width: W,
        height: H,
    }
}

/// A (nx x ny) grid sheet with `step` mm spacing, centred on x, y = 0 at depth z0, and its triangles.
pub fn sheet(nx: usize, ny: usize, step: f64, z0: f64) -> (Vec<Vector3<f64>>, Vec<[u32; 3]>) {
    let mut v = Vec::new();
    for y in 0..ny {
        for x in 0..nx {
            v.push(Vector3::new(
                (x as f64 - (nx - 1) as f64 / 2.0) * step,
                (y as f64 - (ny - 1) as f64 / 2.0) * step,
                z0 + 0.02 * ((x as f64) * step).powi(2) / 10.0,
            ));
        }
    }
    let mut t = Vec::new();
    for y in 0..ny - 1 {
        for x in 0..nx - 1 {
            let i = (y * nx + x) as u32;
            let n = nx as u32;
            t.push([i, i + 1, i + n + 1]);
            t.push([i, i + n + 1, i + n]);
        }
    }
    (v, t)
}

/// Unit normals of a mesh (area-weighted), turned towards the origin (the camera).
pub fn vertex_normals(v: &[Vector3<f64>], t: &[[u32; 3]]) -> Vec<Vector3<f64>> {
    misslam_deformation_ed::observe::mesh_normals(v, t)
        .into_iter()
        .zip(v)
        .map(|(u, p)| if u.dot(p) > 0.0 { -u } else { u })
        .collect()
}

/// Renders world-frame vertices seen from `world_from_camera` into scan maps (camera frame).
pub fn render(
    v: &[Vector3<f64>],
    t: &[[u32; 3]],
    world_from_camera: &Isometry3<f64>,
) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let k = intrinsics();
    let view = View {
        fx: k.fx as f32,
        fy: k.fy as f32,
        cx: k.cx as f32,
        cy: k.cy as f32,
        width: W,
        height: H,
        camera_from_world: world_from_camera.inverse().cast::<f32>(),
    };
    let verts: Vec<[f32; 3]> = v
        .iter()
        .map(|p| [p.x as f32, p.y as f32, p.z as f32])
        .collect();
    let mut r = Raster::default();
    let mut cam = Vec::new();
    rasterize(&view, &verts, t, &mut cam, &mut r);
    scan_maps(&view, &r, &cam, t)
}

pub fn scan<'a>(maps: &'a (Vec<[f32; 3]>, Vec<[f32; 3]>)) -> Scan<'a> {
    Scan {
        intrinsics: intrinsics(),
        vertices: &maps.0,
        normals: &maps.1,
    }
}

/// Mean and max distance between two point lists.
pub fn errors(a: &[Vector3<f64>], b: &[Vector3<f64>]) -> (f64, f64) {
    let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| (x - y).norm()).collect();
    (
        d.iter().sum::<f64>() / d.len() as f64,
        d.iter().cloned().fold(0.0, f64::max),
    )
}

/// Deterministic uniform numbers in [-1, 1].
pub struct Lcg(pub u64);
impl Lcg {
    pub fn next(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    }
}

/// A sheet with its normals, a deformation graph on it and every point's binding.
pub struct Sheet {
    pub points: Vec<Vector3<f64>>,
    pub tris: Vec<[u32; 3]>,
    pub normals: Vec<Vector3<f64>>,
    pub graph: misslam_deformation_ed::EdGraph,
    pub bindings: Vec<misslam_deformation_ed::Binding>,
}

impl Sheet {
    /// An (nx x ny) sheet at 1 mm steps, 60 mm from the camera, nodes `spacing` mm apart.
    pub fn new(nx: usize, ny: usize, spacing: f64) -> Self {
        let (points, tris) = sheet(nx, ny, 1.0, 60.0);
        let normals = vertex_normals(&points, &tris);
        let params = misslam_deformation_ed::GraphParams {
            spacing,
            ..Default::default()
        };
        let graph = misslam_deformation_ed::EdGraph::from_points(&points, params).expect("graph");
        let bindings = graph.bind_all(&points);
        Sheet {
            points,
            tris,
            normals,
            graph,
            bindings,
        }
    }
}

/// Correspondences from the points at `indices` to `target(i)` (camera frame).
pub fn correspondences(
    points: &[Vector3<f64>],
    bindings: &[misslam_deformation_ed::Binding],
    indices: impl Iterator<Item = usize>,
    target: impl Fn(usize) -> Vector3<f64>,
) -> Vec<misslam_deformation_ed::Correspondence> {
    indices
        .map(|i| misslam_deformation_ed::Correspondence {
            point: points[i],
            binding: bindings[i],
            target: target(i),
            normal: None,
        })
        .collect()
}

pub fn rigid(rx: f64, ry: f64, rz: f64, t: [f64; 3]) -> (Rotation3<f64>, Vector3<f64>) {
    (
        Rotation3::from_euler_angles(rx, ry, rz),
        Vector3::new(t[0], t[1], t[2]),
    )
}

/// A small scene for derivative checks: sheet, graph, scan of a deformed copy, field, correspondences.
pub struct Scene {
    pub points: Vec<Vector3<f64>>,
    pub normals: Vec<Vector3<f64>>,
    pub bindings: Vec<Binding>,
    pub graph: EdGraph,
    pub maps: (Vec<[f32; 3]>, Vec<[f32; 3]>),
    pub field: DistanceField,
    pub corr: Vec<Correspondence>,
}

pub fn small_scene() -> Scene {
    let Sheet {
        points,
        tris,
        normals,
        graph,
        bindings,
    } = Sheet::new(21, 15, 6.0);
    let moved: Vec<Vector3<f64>> = points
        .iter()
        .map(|p| p + Vector3::new(0.3, -0.2, 0.8 + 0.01 * p.x))
        .collect();
    let maps = render(&moved, &tris, &Isometry3::identity());
    let field = DistanceField::from_scan(&maps.0, &maps.1, 0.5, 4.0, 10_000_000).unwrap();
    let mut corr = correspondences(&points, &bindings, (0..points.len()).step_by(37), |i| {
        moved[i] + Vector3::new(0.1, 0.0, -0.1)
    });
    // Every other one knows the surface normal at its target (E_corr split along it).
    for c in corr.iter_mut().step_by(2) {
        c.normal = Some(Vector3::new(0.1, -0.2, -1.0).normalize());
    }
    Scene {
        points,
        normals,
        bindings,
        graph,
        maps,
        field,
        corr,
    }
}
