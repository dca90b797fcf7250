//! SGM on constructed cases with exact expectations.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

use misslam_depth_sgm::sgm::{
    census, census_with, median3, path_step, remove_speckles, sgm, Scratch, SgmParams,
};
use misslam_depth_sgm::simd::Level;
use misslam_depth_sgm::synthetic::right_view;

/// The lane code levels, widest first.
const LEVELS: [Level; 3] = [Level::Avx512, Level::Avx2, Level::Portable];

/// Held by every test that caps the lane code (a process-wide setting), so that each checks
/// the level it names while the tests run in parallel.
static LEVEL_LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn level_lock() -> std::sync::MutexGuard<'static, ()> {
    LEVEL_LOCK
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Caps the kernels at `level` and returns the level they run at (lower where the CPU lacks
/// it: said, so a run on such a CPU shows what it did not check).
fn run_at(level: Level) -> Level {
    misslam_depth_sgm::simd::cap(level);
    let got = misslam_depth_sgm::simd::level();
    if got < level {
        eprintln!("this CPU lacks {level:?}: checked at {got:?} instead");
    }
    got
}

/// Deterministic random dots.
fn dots(w: usize, h: usize, seed: u64) -> Vec<u8> {
    let mut s = seed;
    (0..w * h)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 56) as u8
        })
        .collect()
}

#[test]
fn census_bits_follow_the_window_order() {
    // 3x3 window around the centre (value 5): neighbours row by row, bit set when darker.
    let img = [1, 9, 5, 5, 5, 2, 7, 0, 6];
    let mut out = Vec::new();
    census(&img, 3, 3, 3, 3, &mut out);
    // Order: (-1,-1)=1 darker, (0,-1)=9, (1,-1)=5, (-1,0)=5, (1,0)=2 darker, (-1,1)=7, (0,1)=0 darker, (1,1)=6.
    assert_eq!(out[4], 0b1000_1010);
}

#[test]
fn census_matches_the_reference_for_every_window_shape_on_both_code_paths() {
    use misslam_depth_sgm::reference::census_reference;
    let _level = level_lock();
    // Widths around the 32- and 64-pixel blocks; windows from 8 to 64 comparisons (13x5 and
    // 5x13 fill all 64 bits), including extreme gray levels at the borders.
    // One pad buffer across every size and window, as a `Scratch` keeps it between frames.
    let mut pad = vec![0u8; 5];
    for (w, h) in [(70, 9), (31, 14), (96, 5), (1, 3)] {
        let mut img = dots(w, h, (w * h) as u64);
        img[0] = 255;
        img[w * h - 1] = 0;
        for (cw, ch) in [(3, 3), (5, 5), (9, 7), (7, 9), (13, 5), (5, 13)] {
            let want = census_reference(&img, w, h, cw, ch);
            for portable in [false, true] {
                misslam_depth_sgm::simd::force_portable(portable);
                let mut got = vec![7u64; 3];
                census(&img, w, h, cw, ch, &mut got);
                let mut reused = vec![9u64; 2];
                census_with(&img, w, h, cw, ch, &mut pad, &mut reused);
                misslam_depth_sgm::simd::force_portable(false);
                assert_eq!(got, want, "{w}x{h}, window {cw}x{ch}, portable {portable}");
                assert_eq!(
                    reused, want,
                    "reused pad: {w}x{h}, window {cw}x{ch}, portable {portable}"
                );
            }
        }
    }
}

#[test]
fn path_step_is_the_recurrence() {
    let cost = [4u8, 1, 7, 3];
    let prev = [10u16, 2, 9, 30];
    let mut out = [0u16; 4];
    path_step(&cost, &prev, 3, 20, &mut out);
    // min(prev) = 2. d0: min(10, 2+3, 22) - 2 = 3 -> 7; d1: min(2, ...) - 2 = 0 -> 1;
    // d2: min(9, 2+3, 30+3, 22) - 2 = 3 -> 10; d3: min(30, 9+3, 22) - 2 = 10 -> 13.
    assert_eq!(out, [7, 1, 10, 13]);
}

#[test]
fn constant_disparity_is_recovered_exactly() {
    let (w, h) = (96, 64);
    let left = dots(w, h, 3);
    let right = right_view(&left, w, h, |_, _| 7, dots(w, h, 99));
    let p = SgmParams {
        max_disparity: 16,
        census_width: 5,
        census_height: 5,
        ..SgmParams::default()
    };
    let d = sgm(&left, &right, w, h, None, &p, &mut Scratch::default()).unwrap();
    let inner: Vec<f32> = (4..h - 4)
        .flat_map(|y| (20..w - 4).map(move |x| (x, y)))
        .map(|(x, y)| d[y * w + x])
        .collect();
    let exact = inner.iter().filter(|v| (**v - 7.0).abs() < 0.05).count();
    assert!(
        exact as f64 > 0.98 * inner.len() as f64,
        "{exact} of {}",
        inner.len()
    );
}

#[test]
fn left_right_check_invalidates_the_occluded_strip() {
    let (w, h) = (120, 60);
    let left = dots(w, h, 5);
    // Background at disparity 4, a square in front at 14 (x 50..80, y 15..45).
    let fg = |x: usize, y: usize| (50..80).contains(&x) && (15..45).contains(&y);
    let right = right_view(
        &left,
        w,
        h,
        |x, y| if fg(x, y) { 14 } else { 4 },
        dots(w, h, 77),
    );
    let p = SgmParams {
        max_disparity: 24,
        census_width: 5,
        census_height: 5,
        speckle_window: 0,
        median: false,
        ..SgmParams::default()
    };
    let d = sgm(&left, &right, w, h, None, &p, &mut Scratch::default()).unwrap();
    // Left of the square, background pixels x in 40..50 are hidden in the right image (the
    // square covers right-image columns 36..66): they must not carry a disparity.
    let y = 30;
    let occluded = (41..49).filter(|&x| d[y * w + x].is_finite()).count();
    assert!(
        occluded <= 1,
        "{occluded} occluded pixels kept: {:?}",
        &d[y * w + 38..y * w + 52]
    );
    assert!(
        (d[y * w + 65] - 14.0).abs() < 0.2,
        "square: {}",
        d[y * w + 65]
    );
    assert!(
        (d[y * w + 100] - 4.0).abs() < 0.2,
        "background: {}",
        d[y * w + 100]
    );
    // Without the check the strip is filled (wrongly).
    let p = SgmParams {
        lr_check: false,
        ..p
    };
    let d = sgm(&left, &right, w, h, None, &p, &mut Scratch::default()).unwrap();
    assert!((41..49).filter(|&x| d[y * w + x].is_finite()).count() >= 6);
}

#[test]
fn speckles_and_median() {
    let (w, h) = (6, 5);
    let mut d = vec![5.0f32; w * h];
    d[2 * w + 2] = 20.0; // an isolated pixel of another depth
    d[0] = f32::NAN;
    remove_speckles(&mut d, w, h, 2, 1.0);
    assert!(d[2 * w + 2].is_nan(), "a region of one pixel is removed");
    assert_eq!(d.iter().filter(|v| v.is_finite()).count(), w * h - 2);
    let mut m = vec![1.0f32; 9];
    m[4] = 9.0;
    m[0] = f32::NAN;
    let out = median3(&m, 3, 3);
    assert_eq!(out[4], 1.0, "the outlier goes");
    assert!(out[0].is_nan(), "invalid stays invalid");
}

#[test]
fn masked_pixels_get_no_disparity_and_bad_parameters_are_named() {
    let (w, h) = (40, 20);
    let left = dots(w, h, 1);
    let right = right_view(&left, w, h, |_, _| 3, dots(w, h, 2));
    let mut mask = vec![1u8; w * h];
    mask[10 * w + 20] = 0;
    let p = SgmParams {
        max_disparity: 8,
        census_width: 5,
        census_height: 5,
        ..SgmParams::default()
    };
    let d = sgm(
        &left,
        &right,
        w,
        h,
        Some(&mask),
        &p,
        &mut Scratch::default(),
    )
    .unwrap();
    assert!(d[10 * w + 20].is_nan());
    let bad = SgmParams { p2: 5, p1: 10, ..p };
    assert_eq!(
        bad.validate().unwrap_err(),
        "`p2` (5) must exceed `p1` (10)"
    );
    let bad = SgmParams {
        census_width: 11,
        census_height: 7,
        ..p
    };
    assert!(bad
        .validate()
        .unwrap_err()
        .contains("more than 64 comparisons"));
}

/// Runs `f` on a rayon pool of `threads` threads.
fn on_threads<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> T {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
        .install(f)
}

/// Bitwise equality of two disparity images (NaN equal to NaN).
fn same(a: &[f32], b: &[f32]) -> usize {
    a.iter()
        .zip(b)
        .filter(|(x, y)| x.to_bits() != y.to_bits() && !(x.is_nan() && y.is_nan()))
        .count()
}

#[test]
fn the_fast_path_gives_exactly_the_reference_output() {
    use misslam_depth_sgm::reference::{census_reference, sgm_reference};
    // A slanted scene with texture, occlusions and a border; sizes not multiples of 16 or 64.
    let (w, h) = (83, 37);
    let left = dots(w, h, 11);
    let right = right_view(&left, w, h, |x, y| 3 + (x + 2 * y) / 20, dots(w, h, 12));
    let mut mask = vec![1u8; w * h];
    mask[..w * 2].fill(0);
    let cases = [
        SgmParams::default(),
        SgmParams {
            paths: 4,
            max_disparity: 13,
            census_width: 5,
            census_height: 5,
            ..SgmParams::default()
        },
        SgmParams {
            p2_adaptive: true,
            p2: 300,
            max_disparity: 20,
            min_disparity: -3,
            subpixel: false,
            uniqueness_pct: 15,
            ..SgmParams::default()
        },
        SgmParams {
            min_disparity: 4,
            max_disparity: 33,
            census_width: 7,
            census_height: 9,
            lr_check: false,
            median: false,
            speckle_window: 0,
            ..SgmParams::default()
        },
        SgmParams {
            max_disparity: 2,
            census_width: 3,
            census_height: 3,
            uniqueness_pct: 0,
            ..SgmParams::default()
        },
        // u8 lanes (C_max + P2 <= 255) with a negative range start, adaptive P2 and 4 paths.
        SgmParams {
            min_disparity: -5,
            max_disparity: 40,
            p2_adaptive: true,
            paths: 4,
            ..SgmParams::default()
        },
        // The largest P2 that still fits u8 lanes (62 + 193 = 255), with a strong margin;
        // D' = 96, not a multiple of the 64 u8 lanes of an AVX-512 register.
        SgmParams {
            p2: 193,
            max_disparity: 70,
            uniqueness_pct: 30,
            ..SgmParams::default()
        },
        // i16 lanes with D' = 48, not a multiple of the 32 i16 lanes of an AVX-512 register
        // (the AVX2 selection then runs at the AVX-512 level).
        SgmParams {
            p2: 300,
            max_disparity: 40,
            ..SgmParams::default()
        },
    ];
    for (i, p) in cases.iter().enumerate() {
        let (cw, ch) = (p.census_width as usize, p.census_height as usize);
        let want_census = census_reference(&left, w, h, cw, ch);
        let m = (i % 2 == 1).then_some(mask.as_slice());
        let want = sgm_reference(&left, &right, w, h, m, p).unwrap();
        assert!(
            want.iter().filter(|v| v.is_finite()).count() > w * h / 3,
            "case {i} is dense enough to mean something"
        );
        // The AVX-512 and AVX2 kernels (where the CPU has them) and the portable ones.
        let _level = level_lock();
        for level in LEVELS {
            let level = run_at(level);
            let mut c = Vec::new();
            census(&left, w, h, cw, ch, &mut c);
            assert_eq!(c, want_census, "census, case {i}, {level:?}");
            for threads in [1, 2] {
                let got = on_threads(threads, || {
                    let mut s = Scratch::default();
                    // Twice with one scratch: buffers reused across frames must not leak state.
                    sgm(&right, &left, w, h, None, p, &mut s).unwrap();
                    sgm(&left, &right, w, h, m, p, &mut s).unwrap()
                });
                assert_eq!(
                    same(&got, &want),
                    0,
                    "case {i}, {threads} threads, {level:?}"
                );
            }
        }
        misslam_depth_sgm::simd::uncap();
    }
}

#[test]
fn an_empty_image_is_refused_and_a_tiny_one_matched_not_a_panic() {
    for (w, h) in [(0, 5), (7, 0), (0, 0)] {
        let e = sgm(
            &[],
            &[],
            w,
            h,
            None,
            &SgmParams::default(),
            &mut Scratch::default(),
        )
        .unwrap_err();
        assert!(e.contains(&format!("{w}x{h}")), "{e}");
    }
    // Narrower than the disparity range and the census window, at every level.
    let _level = level_lock();
    for (w, h) in [(1, 1), (3, 2), (16, 1), (1, 16), (5, 3)] {
        let img = dots(w, h, 3);
        for level in LEVELS {
            run_at(level);
            let d = sgm(
                &img,
                &img,
                w,
                h,
                None,
                &SgmParams::default(),
                &mut Scratch::default(),
            );
            misslam_depth_sgm::simd::uncap();
            assert_eq!(d.unwrap().len(), w * h, "{w}x{h}");
        }
    }
}

#[test]
fn p2_beyond_the_lane_bound_a_huge_uniqueness_and_a_wrong_mask_are_refused() {
    let p = SgmParams {
        p2: 5000,
        ..SgmParams::default()
    };
    let e = p.validate().unwrap_err();
    assert!(e.contains("`p2`"), "{e}");
    let p = SgmParams {
        uniqueness_pct: 5000,
        ..SgmParams::default()
    };
    let e = p.validate().unwrap_err();
    assert!(e.contains("`uniqueness_pct`"), "{e}");
    let img = vec![0u8; 40 * 30];
    let e = sgm(
        &img,
        &img,
        40,
        30,
        Some(&[1u8; 10]),
        &SgmParams::default(),
        &mut Scratch::default(),
    )
    .unwrap_err();
    assert!(e.contains("mask"), "{e}");
}

#[test]
fn two_threads_hand_rows_over_and_give_the_one_thread_output() {
    // Large enough that the two passes meet in the middle while both run; repeated, so
    // different interleavings of the row hand-over occur.
    let (w, h) = (240, 160);
    let left = dots(w, h, 21);
    let right = right_view(&left, w, h, |x, y| 4 + (x + 3 * y) / 40, dots(w, h, 22));
    for p in [
        SgmParams::default(),
        SgmParams {
            p2: 400,
            max_disparity: 48,
            ..SgmParams::default()
        },
    ] {
        let one = on_threads(1, || {
            sgm(&left, &right, w, h, None, &p, &mut Scratch::default()).unwrap()
        });
        let mut s = Scratch::default();
        for run in 0..6 {
            let two = on_threads(2, || sgm(&left, &right, w, h, None, &p, &mut s).unwrap());
            assert_eq!(same(&two, &one), 0, "run {run}, p2 {}", p.p2);
        }
    }
}
