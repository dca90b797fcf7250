//! GPU code on whatever adapter exists: in CI, Mesa's software Vulkan (lavapipe). Where no
//! adapter exists the tests say so and pass, unless `MISSLAM_REQUIRE_GPU=1` (CI sets it, so a
//! missing driver fails CI instead of hiding).
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

mod common;

use std::sync::Arc;

use misslam::framework::gpu::{GpuProvider, GrayKernel};
use misslam::framework::{luma_bt601, Device, Image};

fn gpu() -> Option<Arc<misslam::framework::GpuContext>> {
    match GpuProvider::new().get() {
        Ok(ctx) => Some(ctx),
        Err(e) => {
            assert!(
                std::env::var_os("MISSLAM_REQUIRE_GPU").is_none(),
                "MISSLAM_REQUIRE_GPU is set but: {e}"
            );
            println!("skipped: {e}");
            None
        }
    }
}

/// Deterministic pseudo-random bytes (xorshift), so the test is seeded.
fn bytes(n: usize, mut s: u64) -> Vec<u8> {
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 24) as u8
        })
        .collect()
}

#[test]
fn gray_kernel_is_bit_exact_with_the_cpu_reference() {
    let Some(ctx) = gpu() else { return };
    println!(
        "adapter: {} ({:?})",
        ctx.adapter_info.name, ctx.adapter_info.device_type
    );
    let kernel = GrayKernel::new(&ctx);
    // Sizes that are not multiples of 4 pixels or of the workgroup exercise the tails.
    for (w, h) in [(1, 1), (3, 1), (7, 5), (640, 480), (721, 289)] {
        let rgb = bytes(w * h * 3, (w * 31 + h) as u64);
        let got = kernel.run(&ctx, &rgb).expect("kernel ran");
        let want: Vec<u8> = rgb
            .chunks_exact(3)
            .map(|p| luma_bt601(p[0], p[1], p[2]))
            .collect();
        assert_eq!(got.len(), want.len());
        let diff = got.iter().zip(&want).filter(|(a, b)| a != b).count();
        assert_eq!(
            diff, 0,
            "{w}x{h}: {diff} pixels differ (tolerance: bit-exact, integer arithmetic)"
        );
    }
    assert!(
        kernel.run(&ctx, &[1, 2]).is_err(),
        "a partial pixel is an error"
    );
}

#[test]
fn one_device_is_shared_and_auto_falls_back() {
    let provider = GpuProvider::new();
    assert!(
        provider.for_device(Device::Cpu, "n").unwrap().is_none(),
        "cpu never opens a device"
    );
    assert!(!provider.is_open());
    let Some(_) = gpu() else {
        // Without an adapter: `auto` falls back to the CPU, `gpu` is a clear error.
        assert!(provider.for_device(Device::Auto, "n").unwrap().is_none());
        let e = provider
            .for_device(Device::Gpu, "n")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("mesa-vulkan-drivers"), "{e}");
        return;
    };
    let a = provider.for_device(Device::Gpu, "a").unwrap().unwrap();
    let b = provider.for_device(Device::Auto, "b").unwrap().unwrap();
    assert!(Arc::ptr_eq(&a, &b), "every node gets the same device");
}

#[test]
fn gray_node_on_gpu_matches_cpu_node() {
    let Some(_) = gpu() else { return };
    let provider = GpuProvider::new();
    let build = |device| {
        let ctx = misslam::framework::BuildContext {
            node_id: "gray",
            graph_dir: std::path::Path::new("."),
            seed: 0,
            gpu: &provider,
        };
        misslam_image_gray::build(misslam_image_gray::Params { device }, &ctx).expect("built")
    };
    let img = Arc::new(Image::new(33, 17, 3, bytes(33 * 17 * 3, 9)).unwrap());
    let cpu = build(Device::Cpu).convert(&img).unwrap();
    let gpu = build(Device::Gpu).convert(&img).unwrap();
    assert_eq!(cpu.data, gpu.data);
    assert_eq!((gpu.width, gpu.height, gpu.channels), (33, 17, 1));
}
