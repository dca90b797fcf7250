//! The `misslam bench` subcommands end to end: each writes what it measured and names bad input.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

mod common;

use common::misslam;

#[test]
fn runtime_overhead_bench_writes_its_rows() {
    let dir = common::tmp_dir("bench");
    let json = dir.join("overhead.json");
    let out = misslam()
        .args([
            "bench",
            "runtime-overhead",
            "--nodes",
            "3",
            "--frames",
            "20",
            "--out",
        ])
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rows: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 4);
    let pipelines: Vec<u64> = rows
        .iter()
        .map(|r| r["pipeline"].as_u64().unwrap())
        .collect();
    assert_eq!(pipelines, [1, 1, 1, 4]);
    for r in rows {
        assert_eq!(r["nodes"], 3);
        assert_eq!(r["frames"], 20);
        assert!(r["per_node_us"].as_f64().unwrap() > 0.0);
    }
}

#[test]
fn sgm_bench_reports_its_stages_and_names_a_pair_that_does_not_fit() {
    let dir = common::tmp_dir("bench-sgm");
    let json = dir.join("sgm.json");
    let out = misslam()
        .args([
            "bench", "sgm", "--width", "96", "--height", "40", "--repeat", "1", "--out",
        ])
        .arg(&json)
        .env_remove("MISSLAM_SIMD")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(
        (r["width"].as_u64(), r["height"].as_u64()),
        (Some(96), Some(40))
    );
    assert_eq!(r["runs"], 1);
    // The random-dot pair is textured everywhere: most pixels get a disparity.
    assert!(r["density_pct"].as_f64().unwrap() > 60.0, "{r}");
    let s = &r["stages_ms"];
    let stage = |k: &str| s[k].as_f64().unwrap();
    let parts = stage("census_ms") + stage("forward_ms") + stage("backward_select_ms");
    for k in ["census_ms", "forward_ms", "backward_select_ms", "finish_ms"] {
        assert!(stage(k) >= 0.0, "{k}: {s}");
    }
    // The stages are disjoint parts of the call (one timed run: its medians are its times).
    assert!(
        parts + stage("finish_ms") <= stage("total_ms") * 1.001 + 1e-3,
        "{s}"
    );
    // The lane code it ran at: the widest this CPU has unless capped.
    let widest = format!("{:?}", misslam_depth_sgm::simd::supported());
    assert_eq!(r["lanes"].as_str(), Some(widest.as_str()), "{r}");
    let capped = misslam()
        .args([
            "bench", "sgm", "--width", "40", "--height", "20", "--repeat", "1",
        ])
        .args(["--lanes", "portable"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&capped.stdout);
    assert!(text.contains("Portable lanes"), "{text}");
    // MISSLAM_SIMD caps a whole run; a wrong value is said and ignored.
    let small = [
        "bench", "sgm", "--width", "40", "--height", "20", "--repeat", "1",
    ];
    let env = misslam()
        .args(small)
        .env("MISSLAM_SIMD", "portable")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&env.stdout);
    assert!(text.contains("Portable lanes"), "{text}");
    let env = misslam()
        .args(small)
        .env("MISSLAM_SIMD", "sse9")
        .output()
        .unwrap();
    let (text, err) = (
        String::from_utf8_lossy(&env.stdout),
        String::from_utf8_lossy(&env.stderr),
    );
    assert!(
        env.status.success() && text.contains(&format!("{widest} lanes")),
        "{text}"
    );
    assert!(
        err.contains("MISSLAM_SIMD: `sse9` is not one of avx512, avx2, portable; ignored"),
        "{err}"
    );
    let wrong = misslam()
        .args(["bench", "sgm", "--lanes", "sse9"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&wrong.stderr);
    assert!(
        !wrong.status.success() && err.contains("`sse9` is not one of avx512, avx2, portable"),
        "{err}"
    );

    let left = dir.join("l.png");
    let right = dir.join("r.png");
    image::GrayImage::new(32, 20).save(&left).unwrap();
    image::GrayImage::new(30, 20).save(&right).unwrap();
    let bad = misslam()
        .args(["bench", "sgm", "--left"])
        .arg(&left)
        .arg("--right")
        .arg(&right)
        .output()
        .unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("l.png is 32x20 but") && err.contains("r.png is 30x20"),
        "{err}"
    );
}

#[test]
fn features_bench_matches_an_image_to_itself_and_names_a_bad_threshold() {
    let dir = common::tmp_dir("bench-features");
    // Random 4x4 blocks on the left half, a faint gradient on the right (weak texture, where
    // only the low-threshold retry finds corners).
    let (w, h) = (160u32, 120u32);
    let img = image::GrayImage::from_fn(w, h, |x, y| {
        if x < w / 2 {
            let cell = (x / 4) * 131 + (y / 4) * 71;
            image::Luma([((cell.wrapping_mul(2_654_435_761) >> 24) & 0xff) as u8])
        } else {
            let v = 100 + ((x + y) % 9) as u8 + if (x / 7 + y / 5) % 2 == 0 { 9 } else { 0 };
            image::Luma([v])
        }
    });
    let path = dir.join("a.png");
    img.save(&path).unwrap();
    let run = |extra: &[&str]| {
        let json = dir.join("f.json");
        let out = misslam()
            .args([
                "bench",
                "features",
                "--repeat",
                "1",
                "--n-features",
                "300",
                "--image",
            ])
            .arg(&path)
            .arg("--image2")
            .arg(&path)
            .args(extra)
            .arg("--out")
            .arg(&json)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr).to_string();
        let v = out.status.success().then(|| {
            serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(&json).unwrap())
                .unwrap()
        });
        (v, err)
    };
    let (with_retry, err) = run(&["--distribution", "none"]);
    let with_retry = with_retry.unwrap_or_else(|| panic!("{err}"));
    let (opencv_rule, err) = run(&["--distribution", "none", "--min-fast-threshold", "0"]);
    let opencv_rule = opencv_rule.unwrap_or_else(|| panic!("{err}"));
    let n = |v: &serde_json::Value| v["keypoints"].as_u64().unwrap();
    assert!(n(&opencv_rule) > 20, "{opencv_rule}");
    // The retry adds corners on the weakly textured half.
    assert!(
        n(&with_retry) > n(&opencv_rule),
        "{} vs {}",
        n(&with_retry),
        n(&opencv_rule)
    );
    // An image against itself: every match is a keypoint with itself.
    let matches = opencv_rule["matches"].as_array().unwrap();
    assert!(matches.len() > 20, "{opencv_rule}");
    for m in matches {
        let m: Vec<f64> = m
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert!(
            (m[0] - m[2]).abs() < 1e-6 && (m[1] - m[3]).abs() < 1e-6,
            "{m:?}"
        );
    }
    let (bad, err) = run(&["--min-fast-threshold", "30"]);
    assert!(bad.is_none());
    assert!(err.contains("min_fast_threshold"), "{err}");
}

#[test]
fn bilateral_bench_filters_the_map_as_post_processing_does() {
    // A 40x30 slope with noise and a hole: the bench's output is the node's filter to the bit,
    // its JSON says what ran, and bad input is named.
    let dir = common::tmp_dir("bench-bilateral");
    let (w, h) = (40u32, 30u32);
    let mut s = 3u32;
    let data: Vec<f32> = (0..w * h)
        .map(|i| {
            s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let (x, y) = (i % w, i / w);
            if (10..14).contains(&x) && (5..9).contains(&y) {
                f32::NAN
            } else {
                70.0 + 0.2 * x as f32 + (s >> 9) as f32 / (1u32 << 23) as f32
            }
        })
        .collect();
    let map = misslam::framework::FloatMap {
        width: w,
        height: h,
        data: data.clone(),
    };
    let (src, out, json) = (dir.join("d.pfm"), dir.join("f.pfm"), dir.join("f.json"));
    misslam::framework::pfm::write_pfm(&src, &map).unwrap();
    let run = misslam()
        .args([
            "bench",
            "bilateral",
            "--repeat",
            "2",
            "--sigma-mm",
            "1.0",
            "--depth",
        ])
        .arg(&src)
        .arg("--out")
        .arg(&out)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let got = misslam::framework::pfm::read_pfm(&out).unwrap();
    let want =
        misslam_depth_postprocess::maps::bilateral(&data, w as usize, h as usize, 3, 2.0, 1.0);
    assert_eq!((got.width, got.height), (w, h));
    for (i, (g, e)) in got.data.iter().zip(&want).enumerate() {
        assert_eq!(g.to_bits(), e.to_bits(), "pixel {i}");
    }
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(
        (r["width"].as_u64(), r["runs"].as_u64()),
        (Some(40), Some(2))
    );
    assert_eq!(r["sigma_mm"].as_f64(), Some(1.0));
    let valid = r["valid_pct"].as_f64().unwrap();
    assert!(
        (valid - 100.0 * (1200.0 - 16.0) / 1200.0).abs() < 1e-9,
        "{r}"
    );
    // A missing map and a bad sigma are named.
    let err = |args: &[&str]| {
        let o = misslam().args(args).output().unwrap();
        assert!(!o.status.success());
        String::from_utf8_lossy(&o.stderr).to_string()
    };
    let missing = dir.join("none.pfm");
    let e = err(&["bench", "bilateral", "--depth", missing.to_str().unwrap()]);
    assert!(e.contains("none.pfm"), "{e}");
    let e = err(&[
        "bench",
        "bilateral",
        "--sigma-mm=0",
        "--depth",
        src.to_str().unwrap(),
    ]);
    assert!(
        e.contains("--sigma-mm") && e.contains("smooth_sigma_mm"),
        "{e}"
    );
}
