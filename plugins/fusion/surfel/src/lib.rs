//! `fusion.surfel`: the template-free model of MIS-SLAM (method.md 5.1). The model is a set of
//! surfels (position, normal, colour, confidence weight, last-seen frame, stability) kept in a
//! canonical frame and bound to an embedded deformation graph whose warp maps them to the live
//! tissue. Per frame:
//!
//! 1. lift the depth to vertex and normal maps;
//! 2. select the visible surfels V^n (they project onto valid depth within `visible_distance_mm`
//!    and `visible_angle_deg`) and solve the ED warp on them (batch, or decoupled PR / PI), with
//!    the tracker's pose as prior; unseen surfels follow as rigidly as the graph allows;
//! 3. fuse every `stride`-th depth pixel into the surfel it meets within `fuse_distance_mm` /
//!    `fuse_angle_deg` (the closest of the front-most surfels of its index-map cell and the 8
//!    around it; confidence-weighted average, weight capped at `max_weight`; colour from
//!    the most frontal and saturated observation, so the texture stays vivid and specular
//!    highlights do not bake in), or add a new surfel;
//! 4. remove unstable surfels (weight below `stable_weight` and unseen for `unstable_frames`);
//! 5. grow the graph where surfels lie farther than the node spacing from every node; bind again
//!    the surfels a new node reaches and those fusion has moved past `rebind_distance_mm` from
//!    where they were bound.
//!
//! With the `features` input connected, keypoints matched frame to frame add E_corr constraints
//! to the solve (see [`corr`]).
//!
//! Outputs the live model (world frame, and with `camera_model` in the scope's frame), the graph,
//! the refined pose and the frame's figures.
#![deny(missing_docs)]

mod balance;
pub mod corr;
mod model;
mod params;
pub use params::Params;

use misslam_deformation_ed::engine::Engine;
use misslam_deformation_ed::graph::{Binding, EdGraph, NewNodes};
use misslam_deformation_ed::observe::{
    color_at, color_quality, scan_from_depth_into, visible_points,
};
use misslam_deformation_ed::problem::{Intrinsics, ModelSubset, Problem, Scan};
use misslam_framework::geometry::{arr3, in_camera_frame, vec3};
use misslam_framework::nalgebra::{Isometry3, Point3, Vector3};
use misslam_framework::{
    BuildContext, BuildError, DepthMap, Features, Flow, FrameInfo, Image, Inputs, Metrics, Node,
    NodeContext, NodeError, NodeResult, NormalMap, Outputs, PointCloud, PortSpec, PortType, Pose,
    Registry, StageClock, StereoFrame, SurfelModel, TrackingState, TypedPlugin, VertexMap,
};
use rayon::prelude::*;

pub use balance::{data_points_per_node, data_weight_scale, thin_visible, COLLAPSE_DET};
use corr::local_inverses;
pub use corr::CorrParams;
pub use misslam_deformation_ed::engine::SolverKind;
use model::{Model, Sample};

/// Binds again each point that has moved farther than `distance` from where its binding was
/// made (`bound_at`), or whose binding the graph's new nodes change (`new`, after a growth), and
/// records where; returns how many.
fn rebind(
    graph: &EdGraph,
    points: &[Vector3<f64>],
    bindings: &mut [Binding],
    bound_at: &mut [Vector3<f64>],
    new: Option<&NewNodes>,
    distance: f64,
) -> usize {
    let d2 = distance * distance;
    bindings
        .par_iter_mut()
        .zip(bound_at.par_iter_mut())
        .zip(points.par_iter())
        .map_init(Vec::new, |buf, ((b, at), v)| {
            // NaN-safe: a non-finite point is never "within" the distance.
            let stays = (v - *at).norm_squared() <= d2 && !new.is_some_and(|n| n.reach(v, b));
            if stays {
                return 0usize;
            }
            *b = graph.bind_into(v, buf);
            *at = *v;
            1
        })
        .sum()
}

/// The node.
pub struct SurfelNode {
    p: Params,
    engine: Engine,
    /// The visible set handed to the solve (buffers kept across frames).
    subset: ModelSubset,
    model: Model,
    graph: Option<EdGraph>,
    vertices: Vec<[f32; 3]>,
    scan_normals: Vec<[f32; 3]>,
    /// Frames whose depth disagreed with the model (see [`DISAGREE_MIN_SAMPLES`]).
    disagreed: u64,
    /// Whether the previous frame disagreed (one warning per run of such frames).
    disagreeing: bool,
    /// Frames after whose solve some node's affine had collapsed or blown up (see
    /// [`COLLAPSE_DET`]; reset by `EdGraph::reset_collapsed`), and whether the previous frame's
    /// had (one warning per run).
    collapsed: u64,
    collapsing: bool,
    /// Per node: whether a visible surfel binds it (reused by [`data_points_per_node`]).
    bound: Vec<bool>,
    /// The previous frame's keypoints anchored to the model (E_corr).
    corr: corr::CorrTracker,
    /// Solves run, the correspondences they used, and their numeric factorisations made and
    /// kept for a later iteration (for `metrics.json`).
    solves: u64,
    corr_used: u64,
    /// Visible surfels over the solves, and those the solves took (`solve_points_per_node`).
    visible_used: (u64, u64),
    factorisations: u64,
    reused_factorisations: u64,
    /// Sparse patterns laid out (symbolic factorisations), both levels of a decoupled solve.
    layouts: u64,
}

/// A fused frame whose depth mostly did not meet the model: more samples became new surfels
/// than fused into existing ones, out of at least this many. On a tracked scene this means the
/// pose (or the warp) no longer puts the model where the depth is, and the model fills with
/// duplicates; it is warned about and counted (`fusion.disagreeing_frames` in `metrics.json`).
pub const DISAGREE_MIN_SAMPLES: usize = 100;

impl SurfelNode {
    #[allow(clippy::too_many_arguments)]
    fn frame(
        &mut self,
        frame: FrameInfo,
        depth: &DepthMap,
        left: Option<&Image>,
        prior: Option<&Pose>,
        features: Option<&Features>,
        maps: Option<(&VertexMap, &NormalMap)>,
        outputs: &mut Outputs,
        st: &mut StageClock,
    ) -> NodeResult<Flow> {
        let features = features.filter(|_| self.p.correspondences.enabled);
        let (w, h) = (depth.map.width as usize, depth.map.height as usize);
        if depth.map.data.len() != w * h {
            return Err(NodeError::msg(format!(
                "depth map of frame {} has {} values for {w}x{h} pixels",
                frame.index,
                depth.map.data.len()
            )));
        }
        let left = left.filter(|im| im.width as usize == w && im.height as usize == h);
        let k = Intrinsics {
            fx: depth.calib.fx,
            fy: depth.calib.fy,
            cx: depth.calib.cx,
            cy: depth.calib.cy,
            width: w as u32,
            height: h as u32,
        };
        // The vertex and normal maps: post-processing's when connected, else lifted here.
        if let Some((v, n)) = maps {
            if (v.width, v.height, n.width, n.height) != (k.width, k.height, k.width, k.height)
                || v.points.len() != w * h
                || n.normals.len() != w * h
            {
                return Err(NodeError::msg(format!(
                    "frame {}: the vertex and normal maps ({}x{}, {}x{}) do not fit the {w}x{h} depth",
                    frame.index, v.width, v.height, n.width, n.height
                )));
            }
        } else {
            scan_from_depth_into(
                &depth.map.data,
                &k,
                self.p.normal_max_step_mm,
                &mut self.vertices,
                &mut self.scan_normals,
            );
        }
        let (vertices, scan_normals): (&[[f32; 3]], &[[f32; 3]]) = match maps {
            Some((v, n)) => (&v.points, &n.normals),
            None => (&self.vertices, &self.scan_normals),
        };
        st.lap("scan");
        let mut pose = prior.map_or(Isometry3::identity(), |p| p.world_from_camera);
        let lost = prior.is_some_and(|p| p.state == TrackingState::Lost);
        let stride = self.p.stride as usize;
        let mut metrics = Metrics::default();
        let (mut fused, mut added, mut removed, mut rebound) = (0usize, 0usize, 0usize, 0usize);
        // With `visible_output`: this frame's visible surfels after the solve (none on the first
        // frame and on lost frames, which select none).
        let mut visible_cloud = None;

        if self.graph.is_none() {
            // The first frame: the model is the depth itself.
            let mut pts = Vec::new();
            for y in (0..h).step_by(stride) {
                for x in (0..w).step_by(stride) {
                    let i = y * w + x;
                    let (v, n) = (vertices[i], scan_normals[i]);
                    if v.iter().chain(&n).all(|c| c.is_finite()) {
                        let c = (pose * Point3::from(vec3(v))).coords;
                        let col = color_at(left, i);
                        pts.push((c, pose.rotation * vec3(n), col, color_quality(n, col)));
                    }
                }
            }
            if pts.is_empty() {
                return Err(NodeError::msg(format!(
                    "frame {}: no valid depth with a normal to start the model from",
                    frame.index
                )));
            }
            let canon: Vec<Vector3<f64>> = pts.iter().map(|p| p.0).collect();
            let graph =
                EdGraph::from_points(&canon, self.p.graph.clone()).map_err(NodeError::msg)?;
            for (c, n, col, q) in pts {
                let b = graph.bind(&c);
                self.model.push(c, n, col, q, frame.index, b);
            }
            added = self.model.len();
            self.graph = Some(graph);
        } else if lost {
            tracing::warn!(
                frame = frame.index,
                "tracking lost: the model is neither deformed nor fused on this frame"
            );
        } else {
            let Some(graph) = self.graph.as_mut() else {
                return Err(NodeError::msg("no graph"));
            };
            let m = &mut self.model;
            // 2. Visible surfels and the warp; beside them, the keypoints matched to the anchors.
            let (graph_ref, corr, corr_params) = (&*graph, &mut self.corr, &self.p.correspondences);
            let (visible, (corrs, ms_corr)) = rayon::join(
                || {
                    visible_points(
                        graph_ref,
                        &m.canon,
                        &m.normals,
                        &m.bindings,
                        &pose,
                        &k,
                        vertices,
                        scan_normals,
                        self.p.visible_distance_mm,
                        self.p.visible_angle_deg,
                    )
                },
                || {
                    let t = std::time::Instant::now();
                    let c = corr.correspondences(
                        frame.index,
                        features,
                        &pose,
                        &k,
                        (vertices, scan_normals),
                        graph_ref,
                        corr_params,
                    );
                    (c, t.elapsed().as_secs_f64() * 1e3)
                },
            );
            let corrs = corrs.map_err(NodeError::msg)?;
            // E_data on at most `solve_points_per_node` per node, normalised by its term count.
            let mut per_node =
                data_points_per_node(&visible, &m.bindings, graph.len(), &mut self.bound);
            let thinned = thin_visible(&visible, per_node, self.p.solve_points_per_node);
            if let Some(t) = &thinned {
                per_node = data_points_per_node(t, &m.bindings, graph.len(), &mut self.bound);
            }
            let solved = thinned.as_deref().unwrap_or(&visible);
            self.subset
                .gather(solved, &m.canon, &m.normals, &m.bindings);
            metrics
                .values
                .insert("fusion.solve_points".into(), solved.len() as f64);
            let mut solver = self.p.solver.clone();
            solver.weights.data *= data_weight_scale(per_node, self.p.data_points_per_node);
            metrics
                .values
                .insert("fusion.data_points_per_node".into(), per_node);
            metrics
                .values
                .insert("fusion.correspondences".into(), corrs.len() as f64);
            metrics
                .values
                .insert("fusion.anchors".into(), self.corr.anchors() as f64);
            self.solves += 1;
            self.corr_used += corrs.len() as u64;
            self.visible_used.0 += visible.len() as u64;
            self.visible_used.1 += self.subset.points.len() as u64;
            let problem = Problem {
                model: self.subset.view(),
                scan: Some(Scan {
                    intrinsics: k,
                    vertices,
                    normals: scan_normals,
                }),
                field: None,
                correspondences: &corrs,
                pose_prior: pose,
            };
            st.push("select.corr", ms_corr);
            st.lap("select");
            let (info, decoupled) = self
                .engine
                .solve(
                    frame.index,
                    graph,
                    &mut pose,
                    &problem,
                    &solver,
                    &self.p.decoupled,
                )
                .map_err(NodeError::msg)?;
            st.lap("solve");
            let collapsed = graph.reset_collapsed(COLLAPSE_DET);
            metrics
                .values
                .insert("fusion.collapsed_nodes".into(), collapsed as f64);
            if collapsed > 0 {
                self.collapsed += 1;
                if !self.collapsing {
                    tracing::warn!(
                        frame = frame.index,
                        "{collapsed} of {} graph nodes collapsed or blew up in the solve (det A \
                         outside [1/{COLLAPSE_DET}, {COLLAPSE_DET}]) and were reset to their \
                         nearest rotation: the data terms outweigh E_rot there (noisy depth, \
                         dense samples, wrong correspondences); if it recurs, raise fusion's \
                         solver.weights.rot or lower data_points_per_node. Counted in \
                         fusion.collapsed_frames",
                        graph.len()
                    );
                }
            }
            self.collapsing = collapsed > 0;
            st.times.extend(info.stages());
            if let Some(d) = decoupled {
                st.push("solve.level2", d.level2.ms_total);
            }
            metrics
                .values
                .insert("fusion.visible".into(), visible.len() as f64);
            metrics
                .values
                .insert("fusion.solve_ms".into(), info.ms_total);
            self.factorisations += info.factorisations as u64;
            self.reused_factorisations += info.reused_factorisations as u64;
            self.layouts += info.symbolic_builds as u64;
            for (key, v) in [
                ("fusion.iterations", info.iterations),
                ("fusion.factorisations", info.factorisations),
                ("fusion.reused_factorisations", info.reused_factorisations),
                ("fusion.layouts", info.symbolic_builds),
                ("fusion.rejected_steps", info.rejected_steps),
            ] {
                metrics.values.insert(key.into(), v as f64);
            }

            // 3. Fusion into the live model, through an index map at stride resolution.
            let (mut live, mut live_n) = (Vec::new(), Vec::new());
            graph.deform(
                &m.canon,
                Some(&m.normals),
                &m.bindings,
                &mut live,
                &mut live_n,
            );
            if self.p.visible_output {
                visible_cloud = Some(visible_cloud_of(&visible, thinned.as_deref(), &live));
            }
            let nm = graph.normal_matrices();
            let cfw = pose.inverse();
            let (gw, gh) = (w.div_ceil(stride), h.div_ceil(stride));
            // Each surfel's cell and depth (in parallel), then the front-most surfel of each
            // cell (in surfel order, so ties go to the first as in one pass).
            let projected: Vec<(u32, f32)> = live
                .par_iter()
                .map(|p| {
                    let pc = cfw * Point3::from(*p);
                    if pc.z <= 0.0 {
                        return (u32::MAX, 0.0);
                    }
                    let u = (k.fx * pc.x / pc.z + k.cx).round();
                    let v = (k.fy * pc.y / pc.z + k.cy).round();
                    if u < 0.0 || v < 0.0 || u >= w as f64 || v >= h as f64 {
                        return (u32::MAX, 0.0);
                    }
                    (
                        ((v as usize / stride) * gw + u as usize / stride) as u32,
                        pc.z as f32,
                    )
                })
                .collect();
            let mut cell: Vec<(f32, u32)> = vec![(f32::INFINITY, u32::MAX); gw * gh];
            for (s, &(c, z)) in projected.iter().enumerate() {
                if c != u32::MAX && z < cell[c as usize].0 {
                    cell[c as usize] = (z, s as u32);
                }
            }
            let cos_f = self.p.fuse_angle_deg.to_radians().cos();
            // What each sample meets, row by row in parallel (reading the live model only); the
            // updates are then applied in sample order, as one pass over the samples would.
            let (canon_bindings, fuse_distance) = (&m.bindings, self.p.fuse_distance_mm);
            let hits: Vec<Vec<Sample>> = (0..gh)
                .into_par_iter()
                .map(|gy| {
                    let mut row = Vec::new();
                    for gx in 0..gw {
                        let (x, y) = (gx * stride, gy * stride);
                        let i = y * w + x;
                        let (v, n) = (vertices[i], scan_normals[i]);
                        if !v.iter().chain(&n).all(|c| c.is_finite()) {
                            continue;
                        }
                        let wp = (pose * Point3::from(vec3(v))).coords;
                        let wn = pose.rotation * vec3(n);
                        let color = color_at(left, i);
                        let quality = color_quality(n, color);
                        // The surfel this sample meets: the closest, within epsilon_df, of the
                        // front-most surfels of its cell and the 8 around it. Surfels are
                        // points, so a cell can be empty where the surface is modelled (the view
                        // moved or came closer): looking one cell further keeps such a sample
                        // from adding a duplicate beside a surfel of the same surface.
                        let mut best: Option<(f64, usize)> = None;
                        let mut turned_away = false;
                        for cy in gy.saturating_sub(1)..(gy + 2).min(gh) {
                            for cx in gx.saturating_sub(1)..(gx + 2).min(gw) {
                                let (_, s) = cell[cy * gw + cx];
                                if s == u32::MAX {
                                    continue;
                                }
                                let s = s as usize;
                                let dist = (wp - live[s]).norm();
                                if dist > fuse_distance {
                                    continue;
                                }
                                if wn.dot(&live_n[s]) < cos_f {
                                    turned_away = true;
                                } else if best.is_none_or(|(b, _)| dist < b) {
                                    best = Some((dist, s));
                                }
                            }
                        }
                        if let Some((_, s)) = best {
                            // The live offset and normal taken back to the canonical frame.
                            let (a_inv, a_t) = local_inverses(&canon_bindings[s], &nm);
                            row.push(Sample::Fuse {
                                surfel: s as u32,
                                offset: a_inv * (wp - live[s]),
                                normal: a_t * wn,
                                color,
                                quality,
                            });
                        } else if !turned_away {
                            // Close but turned away: neither fused nor a duplicate.
                            row.push(Sample::New {
                                point: wp,
                                normal: wn,
                                color,
                                quality,
                            });
                        }
                    }
                    row
                })
                .collect();
            fused += m.fuse(&hits, frame.index, self.p.max_weight);
            let mut new_points: Vec<_> = hits
                .into_iter()
                .flatten()
                .filter_map(|sample| match sample {
                    Sample::New {
                        point,
                        normal,
                        color,
                        quality,
                    } => Some((point, normal, color, quality)),
                    Sample::Fuse { .. } => None,
                })
                .collect();
            st.lap("fuse");
            // New surfels: canonical position by inverting the warp (fixed point iteration).
            let room = self.p.max_surfels.saturating_sub(m.len());
            if new_points.len() > room {
                tracing::warn!(
                    frame = frame.index,
                    "surfel cap {} reached: {} new surfels dropped",
                    self.p.max_surfels,
                    new_points.len() - room
                );
                new_points.truncate(room);
            }
            let graph_ref = &*graph;
            let placed: Vec<(Vector3<f64>, Vector3<f64>, Binding)> = new_points
                .par_iter()
                .map(|(wp, wn, _, _)| {
                    let mut c = *wp;
                    for _ in 0..3 {
                        let b = graph_ref.bind(&c);
                        c += wp - graph_ref.warp_point(&c, &b);
                    }
                    let b = graph_ref.bind(&c);
                    let (_, a_t) = local_inverses(&b, &nm);
                    (c, (a_t * wn).try_normalize(1e-12).unwrap_or(*wn), b)
                })
                .collect();
            let mut grown = Vec::with_capacity(new_points.len());
            for ((c, cn, b), (_, _, color, q)) in placed.into_iter().zip(new_points) {
                m.push(c, cn, color, q, frame.index, b);
                grown.push(c);
                added += 1;
            }
            st.lap("add");
            // A depth that mostly misses the model: said, not silently absorbed.
            let disagrees = added > fused && added + fused >= DISAGREE_MIN_SAMPLES;
            if disagrees {
                self.disagreed += 1;
                if !self.disagreeing {
                    tracing::warn!(
                        frame = frame.index,
                        "the depth disagrees with the model: {fused} samples fused, {added} added \
                         as new surfels (tracking drift or a wrong pose?); counted in \
                         fusion.disagreeing_frames"
                    );
                }
            }
            self.disagreeing = disagrees;
            // 4. Unstable surfels.
            let keep: Vec<bool> = (0..m.len())
                .map(|s| {
                    m.weights[s] >= self.p.stable_weight
                        || frame.index.saturating_sub(m.seen[s]) <= self.p.unstable_frames
                })
                .collect();
            removed = keep.iter().filter(|&&b| !b).count();
            if removed > 0 {
                m.retain(&keep);
            }
            // 5. Graph growth; then the bindings the new nodes change, and those of the surfels
            // fusion has moved, bound again.
            let first_new = graph.len();
            if graph.len() < self.p.max_nodes {
                graph.grow(&grown);
            } else if !grown.is_empty() {
                tracing::warn!(
                    frame = frame.index,
                    "graph cap {} reached: the graph no longer grows",
                    self.p.max_nodes
                );
            }
            let new = (graph.len() > first_new).then(|| graph.new_nodes(first_new));
            rebound = rebind(
                graph,
                &m.canon,
                &mut m.bindings,
                &mut m.bound_at,
                new.as_ref(),
                self.p.rebind_distance_mm,
            );
        }

        st.lap("grow");
        let Some(graph) = self.graph.as_ref() else {
            return Err(NodeError::msg("no graph"));
        };
        let m = &self.model;
        let t_out = std::time::Instant::now();
        let (mut live, mut live_n) = (Vec::new(), Vec::new());
        graph.deform(
            &m.canon,
            Some(&m.normals),
            &m.bindings,
            &mut live,
            &mut live_n,
        );
        st.times
            .push(("output.deform", t_out.elapsed().as_secs_f64() * 1e3));
        let t_anchor = std::time::Instant::now();
        // This frame's keypoints anchored for the next frame's correspondences (none after a
        // lost frame: its pose is not the scope's).
        self.corr.anchor(
            frame.index,
            features,
            lost,
            &pose,
            &live,
            &live_n,
            &m.canon,
            &m.bindings,
            graph,
            vertices,
            &k,
            &self.p.correspondences,
        );
        st.times
            .push(("output.anchor", t_anchor.elapsed().as_secs_f64() * 1e3));
        for (key, v) in [
            ("fusion.surfels", m.len() as f64),
            ("fusion.nodes", graph.len() as f64),
            ("fusion.fused", fused as f64),
            ("fusion.added", added as f64),
            ("fusion.removed", removed as f64),
            ("fusion.rebound", rebound as f64),
        ] {
            metrics.values.insert(key.into(), v);
        }
        let world = SurfelModel {
            positions: live.iter().map(arr3).collect(),
            normals: live_n.iter().map(arr3).collect(),
            colors: m.colors.clone(),
            weights: m.weights.clone(),
            timestamps: m.seen.clone(),
            stability: m.stability.clone(),
            ids: m.ids.clone(),
        };
        if self.p.camera_model {
            let (positions, normals) = in_camera_frame(&pose, &live, &live_n);
            outputs.put(
                "model_camera",
                SurfelModel {
                    positions,
                    normals,
                    colors: world.colors.clone(),
                    weights: world.weights.clone(),
                    timestamps: world.timestamps.clone(),
                    stability: world.stability.clone(),
                    ids: world.ids.clone(),
                },
            )?;
        }
        outputs.put("model", world)?;
        if self.p.visible_output {
            outputs.put("visible", visible_cloud.unwrap_or_default())?;
        }
        outputs.put("graph", graph.to_payload())?;
        outputs.put(
            "pose",
            Pose {
                world_from_camera: pose,
                state: prior.map_or(TrackingState::Tracking, |p| p.state),
            },
        )?;
        outputs.put("info", metrics)?;
        st.lap("output");
        Ok(Flow::Continue)
    }
}

impl Node for SurfelNode {
    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        // The final model's size, for metrics.json (bounded-memory checks and ablations).
        ctx.report_eval("fusion.surfels", self.model.len() as f64);
        ctx.report_eval(
            "fusion.nodes",
            self.graph.as_ref().map_or(0, |g| g.len()) as f64,
        );
        ctx.report_eval("fusion.disagreeing_frames", self.disagreed as f64);
        ctx.report_eval("fusion.collapsed_frames", self.collapsed as f64);
        ctx.report_eval(
            "fusion.correspondences_per_solve",
            self.corr_used as f64 / self.solves.max(1) as f64,
        );
        // Both levels of a decoupled solve count.
        ctx.report_eval(
            "fusion.factorisations_per_solve",
            self.factorisations as f64 / self.solves.max(1) as f64,
        );
        ctx.report_eval(
            "fusion.reused_factorisations_per_solve",
            self.reused_factorisations as f64 / self.solves.max(1) as f64,
        );
        ctx.report_eval(
            "fusion.layouts_per_solve",
            self.layouts as f64 / self.solves.max(1) as f64,
        );
        ctx.report_eval("fusion.anchors", self.corr.anchors() as f64);
        let (visible, used) = self.visible_used;
        if visible > 0 {
            ctx.report_eval("fusion.solve_points_share", used as f64 / visible as f64);
        }
        Ok(())
    }

    fn process(
        &mut self,
        ctx: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let depth = inputs.get::<DepthMap>("depth")?;
        let pair = inputs.opt::<StereoFrame>("stereo")?;
        let prior = inputs.opt::<Pose>("pose")?;
        let features = inputs.opt::<Features>("features")?;
        let maps = match (
            inputs.opt::<VertexMap>("vertices")?,
            inputs.opt::<NormalMap>("normals")?,
        ) {
            (Some(v), Some(n)) => Some((v, n)),
            (None, None) => None,
            _ => {
                return Err(NodeError::msg(format!(
                    "frame {}: connect both `vertices` and `normals` (depth.postprocess's maps) or neither",
                    frame.index
                )))
            }
        };
        let left = pair.map(|p| p.left.as_ref());
        let mut st = StageClock::start();
        let flow = self.frame(
            frame,
            depth,
            left,
            prior.map(|p| p.as_ref()),
            features.map(|f| f.as_ref()),
            maps.as_ref().map(|(v, n)| (v.as_ref(), n.as_ref())),
            outputs,
            &mut st,
        );
        // The first frame and lost frames have no solve: only the stages they ran are reported.
        st.report(ctx);
        flow
    }
}

/// The colour of a visible surfel the solve took ([`visible_cloud_of`]).
pub const VISIBLE_SOLVED: [u8; 3] = [40, 200, 80];
/// The colour of a visible surfel the solve left out (`solve_points_per_node`).
pub const VISIBLE_LEFT: [u8; 3] = [150, 150, 150];

/// The surfels of `visible` (ascending indices into `live`, the world-frame positions) as a
/// cloud, those of `solved` (a subset, ascending; `None`: all of them) in [`VISIBLE_SOLVED`], the
/// others in [`VISIBLE_LEFT`].
fn visible_cloud_of(visible: &[u32], solved: Option<&[u32]>, live: &[Vector3<f64>]) -> PointCloud {
    let mut taken = solved.map(|s| s.iter().peekable());
    let colors = visible
        .iter()
        .map(|i| {
            let took = match taken.as_mut() {
                None => true,
                Some(t) => t.next_if_eq(&i).is_some(),
            };
            if took {
                VISIBLE_SOLVED
            } else {
                VISIBLE_LEFT
            }
        })
        .collect();
    PointCloud {
        positions: visible.iter().map(|&i| arr3(&live[i as usize])).collect(),
        colors: Some(colors),
    }
}

/// Builds the node.
pub fn build(p: Params, _: &BuildContext) -> Result<SurfelNode, BuildError> {
    p.check()?;
    let engine = Engine::new(p.solver_kind);
    Ok(SurfelNode {
        p,
        engine,
        subset: ModelSubset::default(),
        model: Model::default(),
        graph: None,
        vertices: Vec::new(),
        scan_normals: Vec::new(),
        disagreed: 0,
        disagreeing: false,
        collapsed: 0,
        collapsing: false,
        bound: Vec::new(),
        corr: corr::CorrTracker::default(),
        solves: 0,
        corr_used: 0,
        visible_used: (0, 0),
        factorisations: 0,
        reused_factorisations: 0,
        layouts: 0,
    })
}

/// Registers `fusion.surfel`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "fusion.surfel",
        "template-free surfel fusion with an ED warp (MIS-SLAM): visible selection, ED solve, weighted fusion, growth",
        vec![
            PortSpec::new("depth", PortType::Depth, "the live depth (postprocessed), mm"),
            PortSpec::optional(
                "stereo",
                PortType::Stereo,
                "the pair (the left image colours the surfels; without it they get one neutral tissue colour)",
            ),
            PortSpec::optional(
                "pose",
                PortType::Pose,
                "world_from_camera from the tracker (prior); a lost frame is not fused",
            ),
            PortSpec::optional(
                "vertices",
                PortType::VertexMap,
                "the depth's camera-frame points (depth.postprocess's `vertices`, with `normals`): used instead of lifting the depth again here, so its `max_normal_step_mm` applies instead of `normal_max_step_mm`",
            ),
            PortSpec::optional(
                "normals",
                PortType::NormalMap,
                "the depth's unit normals (depth.postprocess's `normals`, with `vertices`)",
            ),
            PortSpec::optional(
                "features",
                PortType::Features,
                "keypoints with descriptors and camera-frame 3D points (features.orb / features.surf): matched frame to frame into E_corr constraints (`correspondences`)",
            ),
        ],
        vec![
            PortSpec::new("model", PortType::Model, "the live surfel model, world frame"),
            PortSpec::optional(
                "visible",
                PortType::PointCloud,
                "with `visible_output = true`: the surfels selected as visible (epsilon_dv, epsilon_nv), world frame, after the solve; green those the solve took, grey those `solve_points_per_node` left out (empty on the first frame and on lost frames)",
            ),
            PortSpec::optional(
                "model_camera",
                PortType::Model,
                "with `camera_model = true`: the same model in the scope's frame (camera_from_world of `pose` applied to positions and normals)",
            ),
            PortSpec::new("graph", PortType::DeformationGraph, "nodes, warps, edges"),
            PortSpec::new("pose", PortType::Pose, "the pose after the solve"),
            PortSpec::new(
                "info",
                PortType::Metrics,
                "fusion.surfels, nodes, fused, added, removed, rebound (surfels bound again: those a new node reaches or fusion moved past `rebind_distance_mm`), visible, solve_ms, iterations, factorisations, reused_factorisations, layouts (sparse patterns laid out), rejected_steps, correspondences, anchors, data_points_per_node (E_data's term count per node), solve_points (the visible surfels the solve took, `solve_points_per_node`), collapsed_nodes (nodes whose affine collapsed, reset to their nearest rotation)",
            ),
        ],
        build,
    )
    .with_absent_outputs(|p: &Params| {
        let mut absent = Vec::new();
        if !p.camera_model {
            absent.push((
                "model_camera".to_owned(),
                "set its `camera_model = true`".to_owned(),
            ));
        }
        if !p.visible_output {
            absent.push((
                "visible".to_owned(),
                "set its `visible_output = true`".to_owned(),
            ));
        }
        absent
    }))
}

#[cfg(test)]
mod tests;
