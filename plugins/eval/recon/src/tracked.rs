//! What follows tissue points over time: the material drift of surfels or mesh vertices
//! ([`Drift`]) and the error of a deformed template's vertices against the GT vertices they track
//! ([`vertex_error`], over the vertices the true camera sees:
//! [`misslam_framework::geometry::seen_vertices`]).

use crate::{bilinear, dot, sub, V3};
use misslam_framework::{DepthMap, Mesh, VertexMap};
use rayon::prelude::*;
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// A hasher for the ids of surfels and vertices (counters and indices, not chosen by an
/// adversary): a multiply by an odd constant, which maps consecutive ids to distinct buckets.
/// The standard SipHash cost about 100 ns a lookup, most of [`Drift::frame`]'s time.
#[derive(Default)]
struct IdHash(u64);

impl Hasher for IdHash {
    fn finish(&self) -> u64 {
        self.0
    }

    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(u64::from(b));
        }
    }

    fn write_u64(&mut self, id: u64) {
        self.0 = (self.0.rotate_left(5) ^ id).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
}

/// The material drift of surfels followed by id (see the module doc).
#[derive(Default)]
pub struct Drift {
    /// The rest-shape point under each surfel when first scored.
    first: HashMap<u64, V3, BuildHasherDefault<IdHash>>,
}

impl Drift {
    /// Scores one frame: `camera` the surfels in the camera frame (scope-relative), `ids`
    /// theirs (each once a frame, as a model's or a mesh's are), the true depth and rest-shape
    /// points of the view. Returns the mean drift over the
    /// surfels scored before (None when there are none yet).
    pub fn frame(
        &mut self,
        camera: &[V3],
        ids: &[u64],
        depth: &DepthMap,
        rest: &VertexMap,
        max_gap: f32,
    ) -> Result<Option<f64>, String> {
        let (w, h) = (depth.map.width as usize, depth.map.height as usize);
        if depth.map.data.len() != w * h
            || (rest.width, rest.height) != (depth.map.width, depth.map.height)
            || rest.points.len() != w * h
        {
            return Err(format!(
                "depth_gt ({w}x{h}) and rest_points_gt ({}x{}) do not describe one view",
                rest.width, rest.height
            ));
        }
        if ids.len() != camera.len() {
            return Err(format!(
                "the model has {} ids for {} surfels",
                ids.len(),
                camera.len()
            ));
        }
        let c = &depth.calib;
        // Each surfel's rest-shape point (in parallel, reading the map of first points only);
        // then, in surfel order, the drift of those scored before and the first point of the
        // others.
        let first = &self.first;
        let found: Vec<Option<(V3, Option<f32>)>> = camera
            .par_iter()
            .zip(ids)
            .map(|(p, id)| {
                if p[2].is_nan() || p[2] <= 0.0 {
                    return None;
                }
                let u = (c.fx * p[0] as f64 / p[2] as f64 + c.cx) as f32;
                let v = (c.fy * p[1] as f64 / p[2] as f64 + c.cy) as f32;
                if !(u >= 0.0 && v >= 0.0 && (u as usize) + 1 < w && (v as usize) + 1 < h) {
                    return None;
                }
                let z = depth.map.data[v.round() as usize * w + u.round() as usize];
                let gap = (p[2] - z).abs();
                if gap.is_nan() || gap > max_gap {
                    return None;
                }
                let r = bilinear(&rest.points, w, u, v)?;
                Some((
                    r,
                    first.get(id).map(|r0| dot(sub(r, *r0), sub(r, *r0)).sqrt()),
                ))
            })
            .collect();
        let (mut sum, mut n) = (0.0f64, 0usize);
        for (f, id) in found.into_iter().zip(ids) {
            match f {
                Some((_, Some(d))) => {
                    sum += d as f64;
                    n += 1;
                }
                Some((r, None)) => {
                    self.first.insert(*id, r);
                }
                None => {}
            }
        }
        Ok((n > 0).then(|| sum / n as f64))
    }
}

/// Mean distance between the points of a deformed copy of `gt` (`points`, in `gt`'s frame) and
/// the GT vertices they track (vertex i to vertex i): the error of tracked surface points
/// against their true positions (method.md 7), tangential sliding included.
pub fn vertex_error(points: &[V3], gt: &Mesh, from_mesh: bool) -> Result<f64, String> {
    if !from_mesh {
        return Err(
            "`vertex_error` needs the `mesh` input (a deformed copy of the GT mesh)".into(),
        );
    }
    if points.len() != gt.vertices.len() {
        return Err(format!(
            "`vertex_error`: the mesh has {} vertices and the GT mesh {}: it is not a deformed copy",
            points.len(),
            gt.vertices.len()
        ));
    }
    let sum: f64 = points
        .iter()
        .zip(&gt.vertices)
        .map(|(p, g)| {
            let d = sub(*p, *g);
            (dot(d, d) as f64).sqrt()
        })
        .sum();
    Ok(sum / points.len().max(1) as f64)
}

/// The GT vertices a true camera has seen so far, which split a template's surface error into
/// what the data has placed and what only the warp's extrapolation has (never seen yet).
#[derive(Default)]
pub struct Observed {
    seen: Vec<bool>,
}

impl Observed {
    /// Adds this frame's `seen` vertices, then returns the mean of `dist` (per vertex) over the
    /// vertices seen so far and over the others (None for an empty side). A change of the vertex
    /// count starts over.
    pub fn frame(&mut self, seen: &[bool], dist: &[f32]) -> (Option<f64>, Option<f64>) {
        if self.seen.len() != seen.len() {
            self.seen = vec![false; seen.len()];
        }
        let (mut sum, mut n) = ([0.0f64; 2], [0usize; 2]);
        for ((o, &s), &d) in self.seen.iter_mut().zip(seen).zip(dist) {
            *o |= s;
            let side = usize::from(!*o);
            sum[side] += d as f64;
            n[side] += 1;
        }
        let mean = |s: usize| (n[s] > 0).then(|| sum[s] / n[s] as f64);
        (mean(0), mean(1))
    }
}
