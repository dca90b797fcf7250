//! How the GPU SGM kernels are laid out for a configuration and an adapter ([`Layout`]): the
//! invocations per path, the paths per workgroup, the bytes per stored cost, per-direction
//! volumes or one volume of sums (and its atomics), the exchange by subgroups or workgroup
//! memory; and the specialisation of the kernels' constants by text ([`specialise`]).

use crate::sgm::{GpuExchange, GpuVolumes, SgmParams};

/// How the aggregation kernel is specialised for a disparity count and cost bound.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(crate) struct Layout {
    /// Invocations per path (a multiple of 4), four disparities each.
    pub(crate) threads: u32,
    /// Paths per workgroup.
    pub(crate) paths: u32,
    /// Bytes per stored L (1 or 2).
    pub(crate) bytes: u32,
    /// One volume of sums instead of a volume per direction.
    pub(crate) summed: bool,
    /// Subgroup lanes per path (a power of two, at least `threads`) when the invocations
    /// exchange by subgroup shuffles; 0 when through workgroup memory.
    pub(crate) lanes: u32,
    /// The sums added by one 64-bit atomic per four disparities instead of two 32-bit ones.
    pub(crate) atomics64: bool,
    /// Invocations of the selection's workgroup (one row): a pixel each where the adapter's
    /// workgroups allow ([`select_threads`]).
    pub(crate) select_threads: u32,
}

impl Layout {
    pub(crate) fn of(p: &SgmParams) -> Layout {
        let threads = 4 * p.max_disparity.div_ceil(16);
        // About 64 invocations per workgroup: few enough workgroups to be resident at once.
        let paths = (64 / threads).max(1);
        // L <= C + P2 on every path (see the aggregation kernel); P2 adapted to the intensity
        // step never exceeds max(P2, P1 + 1).
        let max_cost = (p.census_width * p.census_height - 1).max(u32::from(p.unknown_cost()));
        let p2 = if p.p2_adaptive {
            u32::from(p.p2).max(u32::from(p.p1) + 1)
        } else {
            u32::from(p.p2)
        };
        let bytes = if max_cost + p2 <= 255 { 1 } else { 2 };
        Layout {
            threads,
            paths,
            bytes,
            summed: false,
            lanes: 0,
            atomics64: false,
            select_threads: SELECT_THREADS_MIN,
        }
    }

    /// This layout with the exchange `gpu_exchange` asks for, on an adapter whose subgroups
    /// all have `subgroup` lanes (`None`: no subgroups, or of varying size). A path takes the
    /// next power of two of `threads` lanes of one subgroup, so it must fit one; a workgroup
    /// is a whole number of subgroups, of at least 64 invocations.
    pub(crate) fn exchanged(
        self,
        choice: GpuExchange,
        subgroup: Option<u32>,
    ) -> Result<Layout, String> {
        let lanes = self.threads.next_power_of_two();
        match (choice, subgroup.filter(|&s| lanes <= s)) {
            (GpuExchange::Workgroup, _) | (GpuExchange::Auto, None) => Ok(self),
            (_, Some(s)) => Ok(Layout {
                lanes,
                paths: s.max(64) / lanes,
                ..self
            }),
            (GpuExchange::Subgroup, None) => Err(match subgroup {
                Some(s) => format!(
                    "gpu_exchange = \"subgroup\": a path's {lanes} lanes ({} disparities) do not fit the adapter's subgroups of {s}: use \"auto\" or \"workgroup\"",
                    4 * self.threads
                ),
                None => "gpu_exchange = \"subgroup\": the adapter has no subgroups, or not of one size: use \"auto\" or \"workgroup\"".to_owned(),
            }),
        }
    }

    /// Disparities per pixel in a volume.
    pub(crate) fn dp(&self) -> u32 {
        4 * self.threads
    }

    /// Bytes of the aggregated costs of a `w` x `h` image over `dirs` directions: one volume
    /// per direction, or one of u16 sums.
    pub(crate) fn volumes_bytes(&self, w: usize, h: usize, dirs: usize) -> u64 {
        let px = (w * h) as u64;
        if self.summed {
            px * u64::from(self.dp()) * 2
        } else {
            px * u64::from(self.dp() * self.bytes) * dirs as u64
        }
    }

    /// The layout for these parameters on adapter `a`: per direction or summed, as
    /// `gpu_volumes` asks and the adapter allows (`auto`: summed on a discrete GPU, where it is
    /// the faster, or where a volume per direction does not fit; else per direction); exchanging
    /// by subgroups or workgroup memory, as `gpu_exchange` asks and the subgroups allow.
    pub(crate) fn choose(
        p: &SgmParams,
        (w, h, dirs): (usize, usize, usize),
        a: Adapter,
    ) -> Result<Layout, String> {
        let max = a.max_buffer;
        let per_direction = Layout::of(p);
        let summed = Layout {
            summed: true,
            atomics64: a.int64_atomics,
            ..per_direction
        };
        let layout = match p.gpu_volumes {
            GpuVolumes::PerDirection => per_direction,
            GpuVolumes::Summed => summed,
            GpuVolumes::Auto if !a.discrete && per_direction.volumes_bytes(w, h, dirs) <= max => {
                per_direction
            }
            GpuVolumes::Auto => summed,
        };
        let layout = Layout {
            select_threads: select_threads(w, a.max_workgroup),
            ..layout.exchanged(p.gpu_exchange, a.subgroup)?
        };
        let need = layout.volumes_bytes(w, h, dirs);
        if need > max {
            return Err(format!(
                "the path costs of {w}x{h}x{} over {dirs} directions need {need} bytes {}, beyond the GPU's storage buffer limit of {max} bytes: use device = \"cpu\", fewer disparities{}",
                p.max_disparity,
                if layout.summed { "even summed" } else { "with a volume per direction" },
                if layout.summed { "" } else { " or gpu_volumes = \"summed\" (or \"auto\")" },
            ));
        }
        Ok(layout)
    }

    /// How the selection kernel reads the costs: (bytes per entry, volumes).
    pub(crate) fn selected(&self, dirs: u32) -> (u32, u32) {
        if self.summed {
            (2, 1)
        } else {
            (self.bytes, dirs)
        }
    }
}

/// Pixels on path `path` of direction (dx, dy) in a `w` x `h` image: the path starts where its
/// predecessor would leave the image and walks to the opposite border (the kernels' `start` and
/// `length` in `sgm_paths.wgsl`). Rows: one path per row; columns: one per column; diagonals:
/// one per column of the first row of their direction, then one per row below (or above) it.
pub(crate) fn path_length(w: u32, h: u32, (dx, dy): (isize, isize), path: u32) -> u32 {
    let (w, h, p) = (i64::from(w), i64::from(h), i64::from(path));
    let x0 = if dx > 0 { 0 } else { w - 1 };
    let y0 = if dy > 0 { 0 } else { h - 1 };
    let (x, y) = if dy == 0 {
        (x0, p)
    } else if p < w {
        (p, y0)
    } else {
        let k = p - w + 1;
        (x0, if dy > 0 { y0 + k } else { y0 - k })
    };
    let mut n = i64::MAX;
    match dx.signum() {
        1 => n = n.min(w - x),
        -1 => n = n.min(x + 1),
        _ => {}
    }
    match dy.signum() {
        1 => n = n.min(h - y),
        -1 => n = n.min(y + 1),
        _ => {}
    }
    n.max(0) as u32
}

/// Bits of a [`workgroup_order`] entry that hold the block (`sgm_paths.wgsl`'s
/// `workgroup_paths` splits it the same way).
pub(crate) const ORDER_BLOCK_BITS: u32 = 29;

/// Paths of direction (dx, dy) in a `w` x `h` image.
pub(crate) fn paths_of(w: u32, h: u32, (dx, dy): (isize, isize)) -> u32 {
    if dy == 0 {
        h
    } else if dx == 0 {
        w
    } else {
        w + h - 1
    }
}

/// The aggregation's workgroups in dispatch order: entry g is what workgroup g walks, its
/// direction's index in `dirs` (the high 3 bits) and its block of `per_group` consecutive paths
/// (the low [`ORDER_BLOCK_BITS`]). The blocks of every direction are sorted by their longest
/// path, longest first (ties in direction and path order): the aggregation's time is set by its
/// longest paths (640 steps along a 640x480 row), and in index order some of them started only
/// once a wave of short diagonals had finished (on an H100 with 64 disparities the aggregation
/// took 0.445 ms in index order, 0.379 in this one). The order changes when each path runs, not
/// what it computes.
pub(crate) fn workgroup_order(w: u32, h: u32, dirs: &[(isize, isize)], per_group: u32) -> Vec<u32> {
    let mut blocks: Vec<(u32, u32)> = Vec::new();
    for (r, &dir) in dirs.iter().enumerate() {
        let paths = paths_of(w, h, dir);
        for b in 0..paths.div_ceil(per_group) {
            let first = b * per_group;
            let longest = (first..(first + per_group).min(paths))
                .map(|path| path_length(w, h, dir, path))
                .max()
                .unwrap_or(0);
            blocks.push((longest, ((r as u32) << ORDER_BLOCK_BITS) | b));
        }
    }
    // Stable: equal lengths keep direction and path order.
    blocks.sort_by_key(|&(longest, _)| std::cmp::Reverse(longest));
    blocks.into_iter().map(|(_, e)| e).collect()
}

/// The fewest invocations of a selection workgroup.
const SELECT_THREADS_MIN: u32 = 64;

/// Invocations of the selection's workgroup for rows of `w` pixels: one per pixel, in whole
/// subgroups of 32, within the adapter's largest workgroup `max_workgroup` (1024 on an H100;
/// wider rows loop). A pixel's disparities are a serial chain of minima, so the kernel is bound
/// by latency: on an H100 (640x480, 128 disparities) the selection took 0.108 ms with 256
/// invocations a row, 0.091 with 512 and 0.079 with 1024.
pub(crate) fn select_threads(w: usize, max_workgroup: u32) -> u32 {
    let per_pixel = (w as u32).div_ceil(32) * 32;
    per_pixel.min(max_workgroup).max(SELECT_THREADS_MIN)
}

/// What the layout's choice knows of the adapter.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Adapter {
    /// The largest storage buffer binding, bytes.
    pub(crate) max_buffer: u64,
    /// The size of its subgroups, where it has them and they all have one size.
    pub(crate) subgroup: Option<u32>,
    /// A discrete GPU. On an H100 (640x480, 128 disparities, 8 paths, subgroup exchange) the
    /// summed costs took 0.74 ms to aggregate and 0.12 to select, a volume per direction 0.54
    /// and 0.51; on Mesa's lavapipe (320x240, 64 disparities) the per-direction volumes were
    /// the faster, 228 against 291 ms a pair.
    pub(crate) discrete: bool,
    /// 64-bit atomics in storage buffers (and not switched off: [`SgmGpu::set_int64_atomics`]).
    pub(crate) int64_atomics: bool,
    /// The largest one-dimensional workgroup (invocations).
    pub(crate) max_workgroup: u32,
}

/// Replaces the value of each `const NAME: u32 = ...;` line of a kernel.
pub(crate) fn specialise(src: &str, values: &[(&str, u32)]) -> Result<String, String> {
    let mut out = String::with_capacity(src.len());
    let mut found = vec![false; values.len()];
    for line in src.lines() {
        let mut replaced = false;
        for (k, (name, value)) in values.iter().enumerate() {
            if line.starts_with(&format!("const {name}: u32 = ")) {
                out.push_str(&format!("const {name}: u32 = {value}u;"));
                found[k] = true;
                replaced = true;
            }
        }
        if !replaced {
            out.push_str(line);
        }
        out.push('\n');
    }
    match values.iter().zip(&found).find(|(_, &f)| !f) {
        Some(((name, _), _)) => Err(format!(
            "the SGM kernel has no line `const {name}: u32 = ...;` to specialise"
        )),
        None => Ok(out),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::{AGGREGATE_SUBGROUP_WGSL, AGGREGATE_WGSL, PATHS_WGSL, SELECT_WGSL, SUMS_WGSL};
    use misslam_framework::gpu::wgsl_with_uses;

    #[test]
    fn specialise_replaces_every_constant_and_names_a_missing_one() {
        let uses = [("sgm_paths.wgsl", PATHS_WGSL), ("sgm_sums.wgsl", SUMS_WGSL)];
        for kernel in [AGGREGATE_WGSL, AGGREGATE_SUBGROUP_WGSL] {
            let src = specialise(
                &wgsl_with_uses(kernel, &uses).unwrap(),
                &[("THREADS", 36), ("PATHS", 1), ("BYTES", 2)],
            )
            .expect("the aggregation kernels have the constants");
            assert!(src.contains("const THREADS: u32 = 36u;"));
            assert!(src.contains("const BYTES: u32 = 2u;"));
        }
        let sel = specialise(SELECT_WGSL, &[("BYTES", 1), ("DIRS", 4), ("THREADS", 64)]).unwrap();
        assert!(sel.contains("const DIRS: u32 = 4u;"));
        let err = specialise(SELECT_WGSL, &[("PER", 4)]).unwrap_err();
        assert!(err.contains("PER"), "{err}");
    }

    #[test]
    fn the_costs_are_summed_only_where_a_volume_per_direction_does_not_fit() {
        let p = SgmParams {
            max_disparity: 128,
            ..SgmParams::default()
        };
        // 640x480, 128 disparities, 8 paths: 315 MB per direction, 79 MB summed.
        let per_direction = 640 * 480 * 128 * 8;
        let summed = 640 * 480 * 128 * 2;
        let cpu = |max_buffer: u64| Adapter {
            max_buffer,
            subgroup: None,
            discrete: false,
            int64_atomics: false,
            max_workgroup: 256,
        };
        let auto = |max: u64| Layout::choose(&p, (640, 480, 8), cpu(max));
        assert!(!auto(per_direction).unwrap().summed, "fits: per direction");
        assert!(
            auto(per_direction - 1).unwrap().summed,
            "Mesa's 128 MiB: summed"
        );
        let err = auto(summed - 1).unwrap_err();
        assert!(err.contains("even summed"), "{err}");
        let forced = |v: GpuVolumes, max: u64| {
            Layout::choose(
                &SgmParams {
                    gpu_volumes: v,
                    ..p
                },
                (640, 480, 8),
                cpu(max),
            )
        };
        assert!(forced(GpuVolumes::Summed, u64::MAX).unwrap().summed);
        let err = forced(GpuVolumes::PerDirection, per_direction - 1).unwrap_err();
        assert!(err.contains("gpu_volumes"), "{err}");
        // u16 costs take two bytes per direction; the sums stay two bytes.
        let wide = SgmParams { p2: 1000, ..p };
        let l = Layout::choose(&wide, (640, 480, 8), cpu(u64::MAX)).unwrap();
        // A discrete GPU sums them whatever fits.
        let gpu = Adapter {
            discrete: true,
            ..cpu(u64::MAX)
        };
        let g = Layout::choose(&p, (640, 480, 8), gpu).unwrap();
        assert!(g.summed && !g.atomics64);
        // With 64-bit atomics the sums take them; a volume per direction has no sums.
        let wide_atomics = Adapter {
            int64_atomics: true,
            ..gpu
        };
        assert!(
            Layout::choose(&p, (640, 480, 8), wide_atomics)
                .unwrap()
                .atomics64
        );
        let per = SgmParams {
            gpu_volumes: GpuVolumes::PerDirection,
            ..p
        };
        assert!(
            !Layout::choose(&per, (640, 480, 8), wide_atomics)
                .unwrap()
                .atomics64
        );
        assert_eq!(l.volumes_bytes(640, 480, 8), 2 * per_direction);
        assert_eq!(
            Layout { summed: true, ..l }.volumes_bytes(640, 480, 8),
            summed
        );
    }

    #[test]
    fn byte_costs_only_when_cost_plus_p2_fits_a_byte() {
        let p = SgmParams::default();
        let l = Layout::of(&p);
        assert_eq!((l.threads, l.paths, l.bytes, l.dp()), (16, 4, 1, 64));
        let q = SgmParams {
            p2: 255 - 62 + 1,
            max_disparity: 150,
            ..p
        };
        let l = Layout::of(&q);
        assert_eq!((l.threads, l.paths, l.bytes), (40, 1, 2));
    }

    #[test]
    fn paths_cover_every_pixel_once_per_direction_and_the_order_puts_the_longest_first() {
        use crate::reference::{DIRS, DIRS4};
        for (w, h) in [(7u32, 5u32), (5, 7), (1, 4), (6, 1), (64, 48)] {
            for &(dx, dy) in &DIRS {
                // The paths found from the pixels: each starts where its predecessor is outside
                // the image, and walks until it leaves; their lengths cover every pixel once.
                let inside = |x: i64, y: i64| x >= 0 && y >= 0 && x < w as i64 && y < h as i64;
                let mut walked = Vec::new();
                for y in 0..h as i64 {
                    for x in 0..w as i64 {
                        if !inside(x - dx as i64, y - dy as i64) {
                            let mut n = 0;
                            while inside(x + n * dx as i64, y + n * dy as i64) {
                                n += 1;
                            }
                            walked.push(n as u32);
                        }
                    }
                }
                let mut lengths: Vec<u32> = (0..paths_of(w, h, (dx, dy)))
                    .map(|path| path_length(w, h, (dx, dy), path))
                    .collect();
                assert_eq!(lengths.iter().sum::<u32>(), w * h, "{w}x{h} ({dx}, {dy})");
                lengths.sort_unstable();
                walked.sort_unstable();
                assert_eq!(lengths, walked, "{w}x{h} ({dx}, {dy})");
            }
            for (dirs, per) in [(&DIRS[..], 2u32), (&DIRS4[..], 1), (&DIRS[..], 8)] {
                let order = workgroup_order(w, h, dirs, per);
                // Every block of every direction once.
                let mut want: Vec<u32> = Vec::new();
                for (r, &d) in dirs.iter().enumerate() {
                    let blocks = paths_of(w, h, d).div_ceil(per);
                    want.extend((0..blocks).map(|b| ((r as u32) << ORDER_BLOCK_BITS) | b));
                }
                let mut got = order.clone();
                got.sort_unstable();
                want.sort_unstable();
                assert_eq!(got, want);
                // Longest first.
                let longest = |e: u32| {
                    let d = dirs[(e >> ORDER_BLOCK_BITS) as usize];
                    let first = (e & ((1 << ORDER_BLOCK_BITS) - 1)) * per;
                    (first..(first + per).min(paths_of(w, h, d)))
                        .map(|p| path_length(w, h, d, p))
                        .max()
                        .unwrap()
                };
                assert!(order.windows(2).all(|p| longest(p[0]) >= longest(p[1])));
            }
        }
        // 640x480: the rows' paths (640 pixels) come first, all 480 of each direction.
        let order = workgroup_order(640, 480, &DIRS, 2);
        assert!(order[..480]
            .iter()
            .all(|&e| matches!(e >> ORDER_BLOCK_BITS, 0 | 4)));
        assert_eq!(order[480] >> ORDER_BLOCK_BITS, 1);
    }

    #[test]
    fn the_selection_takes_a_pixel_per_invocation_within_the_adapter_limit() {
        assert_eq!(select_threads(640, 1024), 640);
        assert_eq!(select_threads(641, 1024), 672);
        assert_eq!(select_threads(1920, 1024), 1024);
        assert_eq!(select_threads(640, 256), 256);
        assert_eq!(select_threads(20, 1024), SELECT_THREADS_MIN);
        let p = SgmParams::default();
        let a = Adapter {
            max_buffer: u64::MAX,
            subgroup: Some(32),
            discrete: true,
            int64_atomics: true,
            max_workgroup: 1024,
        };
        let l = Layout::choose(&p, (640, 480, 8), a).unwrap();
        assert_eq!(l.select_threads, 640);
    }

    #[test]
    fn subgroups_exchange_where_a_path_fits_one() {
        let p = |d: u32, exchange: GpuExchange| SgmParams {
            max_disparity: d,
            gpu_exchange: exchange,
            ..SgmParams::default()
        };
        let choose = |q: &SgmParams, subgroup| {
            let a = Adapter {
                max_buffer: u64::MAX,
                subgroup,
                discrete: false,
                int64_atomics: false,
                max_workgroup: 1024,
            };
            Layout::choose(q, (64, 48, 8), a)
        };
        // 128 disparities: 32 invocations, one NVIDIA subgroup, two paths a workgroup.
        let l = choose(&p(128, GpuExchange::Auto), Some(32)).unwrap();
        assert_eq!((l.threads, l.lanes, l.paths), (32, 32, 2));
        // 96: 24 invocations in 32 lanes (the last 8 hold padding); the volume keeps 96.
        let l = choose(&p(96, GpuExchange::Auto), Some(32)).unwrap();
        assert_eq!((l.threads, l.lanes, l.paths, l.dp()), (24, 32, 2, 96));
        // 32 disparities on subgroups of 8 (lavapipe on AVX2): 8 paths of 8 lanes.
        let l = choose(&p(32, GpuExchange::Auto), Some(8)).unwrap();
        assert_eq!((l.threads, l.lanes, l.paths), (8, 8, 8));
        // Subgroups of 64: a workgroup is one subgroup.
        let l = choose(&p(64, GpuExchange::Auto), Some(64)).unwrap();
        assert_eq!((l.lanes, l.paths), (16, 4));
        // Too small, absent or of varying size: workgroup memory, or an error when forced.
        for sub in [Some(16), None] {
            let l = choose(&p(128, GpuExchange::Auto), sub).unwrap();
            assert_eq!((l.lanes, l.paths), (0, 2));
            let err = choose(&p(128, GpuExchange::Subgroup), sub).unwrap_err();
            assert!(err.contains("gpu_exchange"), "{err}");
        }
        let l = choose(&p(128, GpuExchange::Workgroup), Some(32)).unwrap();
        assert_eq!(l.lanes, 0);
    }
}
