//! The canonical surfel model of `fusion.surfel` (structure of arrays) and how this frame's
//! depth samples are fused into it.

use misslam_deformation_ed::graph::Binding;
use misslam_framework::nalgebra::Vector3;
use rayon::prelude::*;

/// The canonical model and its graph.
#[derive(Default)]
pub(crate) struct Model {
    pub(crate) canon: Vec<Vector3<f64>>,
    pub(crate) normals: Vec<Vector3<f64>>,
    pub(crate) colors: Vec<[u8; 3]>,
    /// [`color_quality`] of the observation the colour came from.
    pub(crate) color_quality: Vec<f32>,
    pub(crate) weights: Vec<f32>,
    pub(crate) seen: Vec<u64>,
    pub(crate) stability: Vec<f32>,
    pub(crate) bindings: Vec<Binding>,
    /// The canonical position each binding was made at (fusion moves the surfel on).
    pub(crate) bound_at: Vec<Vector3<f64>>,
    /// Each surfel's identity, and the next one to give.
    pub(crate) ids: Vec<u64>,
    pub(crate) next_id: u64,
}

impl Model {
    pub(crate) fn len(&self) -> usize {
        self.canon.len()
    }

    pub(crate) fn push(
        &mut self,
        c: Vector3<f64>,
        n: Vector3<f64>,
        color: [u8; 3],
        q: f32,
        frame: u64,
        b: Binding,
    ) {
        self.canon.push(c);
        self.normals.push(n);
        self.colors.push(color);
        self.color_quality.push(q);
        self.weights.push(1.0);
        self.seen.push(frame);
        self.stability.push(0.0);
        self.bindings.push(b);
        self.bound_at.push(c);
        self.ids.push(self.next_id);
        self.next_id += 1;
    }

    /// Fuses the samples that meet a surfel into it ([`SurfelMut::fuse`]), in sample order
    /// (rows, then columns); returns how many. The
    /// surfels are split into ranges, one task a range, each applying the samples of its own
    /// surfels in that order: a surfel met by several samples gets them in the same order as in
    /// one pass, so the same bits (tested against [`Model::fuse_one_pass`]).
    pub(crate) fn fuse(&mut self, rows: &[Vec<Sample>], frame: u64, max_weight: f32) -> usize {
        let n = self.len();
        let hits: Vec<(u32, &Sample)> = rows
            .iter()
            .flatten()
            .filter_map(|s| match s {
                Sample::Fuse { surfel, .. } if (*surfel as usize) < n => Some((*surfel, s)),
                _ => None,
            })
            .collect();
        if hits.is_empty() {
            return 0;
        }
        let size = n.div_ceil(rayon::current_num_threads().clamp(1, 64)).max(1);
        let hits = &hits;
        self.canon
            .par_chunks_mut(size)
            .zip(self.normals.par_chunks_mut(size))
            .zip(self.colors.par_chunks_mut(size))
            .zip(self.color_quality.par_chunks_mut(size))
            .zip(self.weights.par_chunks_mut(size))
            .zip(self.seen.par_chunks_mut(size))
            .zip(self.stability.par_chunks_mut(size))
            .enumerate()
            .for_each(
                |(j, ((((((canon, normals), colors), quality), weights), seen), stability))| {
                    let lo = j * size;
                    for &(surfel, sample) in hits {
                        let Some(i) = (surfel as usize)
                            .checked_sub(lo)
                            .filter(|&i| i < canon.len())
                        else {
                            continue;
                        };
                        SurfelMut {
                            canon: &mut canon[i],
                            normal: &mut normals[i],
                            color: &mut colors[i],
                            quality: &mut quality[i],
                            weight: &mut weights[i],
                            seen: &mut seen[i],
                            stability: &mut stability[i],
                        }
                        .fuse(sample, frame, max_weight);
                    }
                },
            );
        hits.len()
    }

    /// [`Model::fuse`] as one pass over the samples: the reference its test compares with.
    #[cfg(test)]
    fn fuse_one_pass(&mut self, rows: &[Vec<Sample>], frame: u64, max_weight: f32) -> usize {
        let mut fused = 0;
        for sample in rows.iter().flatten() {
            let Sample::Fuse { surfel, .. } = sample else {
                continue;
            };
            let s = *surfel as usize;
            if s >= self.len() {
                continue;
            }
            SurfelMut {
                canon: &mut self.canon[s],
                normal: &mut self.normals[s],
                color: &mut self.colors[s],
                quality: &mut self.color_quality[s],
                weight: &mut self.weights[s],
                seen: &mut self.seen[s],
                stability: &mut self.stability[s],
            }
            .fuse(sample, frame, max_weight);
            fused += 1;
        }
        fused
    }

    pub(crate) fn retain(&mut self, keep: &[bool]) {
        fn filter<T: Copy>(v: &mut Vec<T>, keep: &[bool]) {
            let mut i = 0;
            v.retain(|_| {
                i += 1;
                keep[i - 1]
            });
        }
        filter(&mut self.canon, keep);
        filter(&mut self.normals, keep);
        filter(&mut self.colors, keep);
        filter(&mut self.color_quality, keep);
        filter(&mut self.weights, keep);
        filter(&mut self.seen, keep);
        filter(&mut self.stability, keep);
        filter(&mut self.bindings, keep);
        filter(&mut self.bound_at, keep);
        filter(&mut self.ids, keep);
    }
}

/// One surfel's fused state, borrowed from the model's arrays.
struct SurfelMut<'a> {
    canon: &'a mut Vector3<f64>,
    normal: &'a mut Vector3<f64>,
    color: &'a mut [u8; 3],
    quality: &'a mut f32,
    weight: &'a mut f32,
    seen: &'a mut u64,
    stability: &'a mut f32,
}

impl SurfelMut<'_> {
    /// Fuses a sample that meets this surfel (a `Sample::New` changes nothing): position and
    /// normal averaged with the surfel's weight, the colour of the most vivid observation, the
    /// weight capped at `max_weight`.
    fn fuse(self, sample: &Sample, frame: u64, max_weight: f32) {
        let Sample::Fuse {
            offset,
            normal,
            color,
            quality,
            ..
        } = sample
        else {
            return;
        };
        let wgt = *self.weight;
        let alpha = 1.0 / (wgt as f64 + 1.0);
        *self.canon += offset * alpha;
        let cn = *self.normal * (1.0 - alpha) + normal * alpha;
        *self.normal = cn.try_normalize(1e-12).unwrap_or(*self.normal);
        if *quality >= *self.quality {
            *self.color = *color;
            *self.quality = *quality;
        }
        *self.weight = (wgt + 1.0).min(max_weight);
        *self.seen = frame;
        *self.stability += 1.0;
    }
}

/// What one depth sample does to the model.
pub(crate) enum Sample {
    /// It meets surfel `surfel`: its offset from the surfel's live position and its normal, both
    /// taken back to the canonical frame, and its colour.
    Fuse {
        surfel: u32,
        offset: Vector3<f64>,
        normal: Vector3<f64>,
        color: [u8; 3],
        quality: f32,
    },
    /// It meets none: a new surfel (world frame).
    New {
        point: Vector3<f64>,
        normal: Vector3<f64>,
        color: [u8; 3],
        quality: f32,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fusing_in_surfel_ranges_gives_the_bits_of_one_pass() {
        // 1,003 surfels (ranges of unequal length), samples in rows that meet some surfels
        // several times, in an order that interleaves them, with new points between.
        let mut lcg = 12345u64;
        let mut next = move || {
            lcg = lcg
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((lcg >> 33) as f64) / (1u64 << 31) as f64
        };
        let mut model = Model::default();
        for i in 0..1003u64 {
            let c = Vector3::new(next(), next(), next()) * 50.0;
            let n = Vector3::new(next() - 0.5, next() - 0.5, -1.0).normalize();
            model.push(c, n, [i as u8, 7, 9], next() as f32, 0, Binding::EMPTY);
            model.weights[i as usize] = (next() * 20.0) as f32;
        }
        let rows: Vec<Vec<Sample>> = (0..40)
            .map(|_| {
                (0..60)
                    .map(|k| {
                        let v = Vector3::new(next() - 0.5, next() - 0.5, next() - 0.5);
                        if k % 7 == 3 {
                            return Sample::New {
                                point: v,
                                normal: v,
                                color: [1, 2, 3],
                                quality: 0.5,
                            };
                        }
                        // Half the samples on the first 30 surfels: met many times each.
                        let surfel = if k % 2 == 0 {
                            (next() * 30.0) as u32
                        } else {
                            (next() * 1003.0) as u32
                        };
                        Sample::Fuse {
                            surfel,
                            offset: v,
                            normal: Vector3::new(v.x, v.y, -1.0),
                            color: [(k * 3) as u8, 0, 0],
                            quality: next() as f32,
                        }
                    })
                    .collect()
            })
            .collect();
        let bits = |m: &Model| {
            let f = |v: &[Vector3<f64>]| {
                v.iter()
                    .flat_map(|p| p.iter().map(|c| c.to_bits()).collect::<Vec<u64>>())
                    .collect::<Vec<u64>>()
            };
            (
                f(&m.canon),
                f(&m.normals),
                m.colors.clone(),
                m.color_quality
                    .iter()
                    .map(|q| q.to_bits())
                    .collect::<Vec<_>>(),
                m.weights.iter().map(|q| q.to_bits()).collect::<Vec<_>>(),
                m.seen.clone(),
                m.stability.iter().map(|q| q.to_bits()).collect::<Vec<_>>(),
            )
        };
        let mut want = Model::default();
        for i in 0..model.len() {
            want.push(
                model.canon[i],
                model.normals[i],
                model.colors[i],
                model.color_quality[i],
                0,
                Binding::EMPTY,
            );
            want.weights[i] = model.weights[i];
        }
        let fused = want.fuse_one_pass(&rows, 5, 16.0);
        for threads in [1, 3, 4, 8] {
            let mut got = Model::default();
            for i in 0..model.len() {
                got.push(
                    model.canon[i],
                    model.normals[i],
                    model.colors[i],
                    model.color_quality[i],
                    0,
                    Binding::EMPTY,
                );
                got.weights[i] = model.weights[i];
            }
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let n = pool.install(|| got.fuse(&rows, 5, 16.0));
            assert_eq!(n, fused, "{threads} threads: samples fused");
            assert!(
                bits(&got) == bits(&want),
                "{threads} threads: the model differs"
            );
        }
        assert!(fused > 1500 && want.seen.iter().filter(|&&s| s == 5).count() > 400);
    }
}
