//! `misslam bench phantom`: render speed of the phantom per scene and image size.

use std::time::Instant;

use serde::Serialize;

/// One phantom configuration's render speed.
#[derive(Debug, Serialize)]
pub struct PhantomRow {
    /// Scene.
    pub scene: String,
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Frames rendered.
    pub frames: u64,
    /// Mean wall time per frame (both views and all GT), ms.
    pub ms_per_frame: f64,
    /// Frames per second.
    pub fps: f64,
}

/// Renders `frames` frames of every scene at 640x480 and 360x288 and times them.
pub fn phantom(frames: u64) -> Result<Vec<PhantomRow>, String> {
    use misslam_source_phantom::scene::Scene;
    let mut rows = Vec::new();
    for (w, h, f) in [(640u32, 480u32, 700.0), (360, 288, 394.0)] {
        for scene in [Scene::Heart, Scene::Liver, Scene::Kidney, Scene::Stomach] {
            let p = misslam_source_phantom::Params {
                scene,
                width: w,
                height: h,
                focal_px: f,
                frames,
                ..Default::default()
            };
            let mut ph = misslam_source_phantom::Phantom::new(p, 0)?;
            let t = Instant::now();
            for i in 0..frames {
                std::hint::black_box(ph.render(i));
            }
            let ms = t.elapsed().as_secs_f64() * 1e3 / frames.max(1) as f64;
            rows.push(PhantomRow {
                scene: format!("{scene:?}").to_lowercase(),
                width: w,
                height: h,
                frames,
                ms_per_frame: ms,
                fps: 1e3 / ms,
            });
        }
    }
    Ok(rows)
}
