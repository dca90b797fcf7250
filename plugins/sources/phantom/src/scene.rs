//! Procedural organs: a rest surface over a parameter plane (x, y in mm), its deformation in
//! time (heartbeat, breathing, a tool press) and the scope's trajectory.
//!
//! World frame = the left camera at t = 0 (OpenCV axes: x right, y down, z forward); tissue lies
//! ahead at positive z. All lengths in mm, times in s.

use misslam_framework::nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// Which organ.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Scene {
    /// A beating heart: a dome bulging toward the scope, pulsing along its normals.
    Heart,
    /// Liver and abdominal wall: a broad tilted surface moving with breathing.
    Liver,
    /// A kidney: a bean-shaped bulge.
    Kidney,
    /// Stomach: folded mucosa (rugae).
    Stomach,
}

/// Scope motion.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Trajectory {
    /// The scope does not move.
    Static,
    /// A slow sweep: lateral and vertical sinusoids with a small yaw and pitch.
    Sweep,
    /// The slow sweep plus a fast jerk (`fast_start_s`, `fast_duration_s`, `fast_amplitude_mm`).
    Fast,
}

/// Deformation and motion settings (all documented on the plugin's `Params`).
#[derive(Clone, Copy, Debug)]
pub struct Motion {
    /// Heartbeat peak displacement along the normal, mm.
    pub heartbeat_mm: f32,
    /// Heartbeat rate, Hz.
    pub heartbeat_hz: f32,
    /// Breathing peak displacement, mm.
    pub breathing_mm: f32,
    /// Breathing rate, Hz.
    pub breathing_hz: f32,
    /// Tool press depth, mm (0: none).
    pub tool_press_mm: f32,
    /// Tool press centre on the parameter plane, mm.
    pub tool_xy_mm: [f32; 2],
    /// Tool press radius (Gaussian sigma), mm.
    pub tool_radius_mm: f32,
    /// Tool press start and duration, s.
    pub tool_start_s: f32,
    /// Duration, s.
    pub tool_duration_s: f32,
    /// Scope motion.
    pub trajectory: Trajectory,
    /// Sweep amplitude, mm.
    pub sweep_mm: f32,
    /// Sweep period, s.
    pub sweep_period_s: f32,
    /// Fast segment start, s.
    pub fast_start_s: f32,
    /// Fast segment duration, s.
    pub fast_duration_s: f32,
    /// Fast segment amplitude, mm.
    pub fast_amplitude_mm: f32,
}

/// Depth of the rest surface at (x, y): the organ's shape, `distance` being its far plane.
pub fn rest_z(scene: Scene, x: f32, y: f32, distance: f32) -> f32 {
    let g = |x: f32, y: f32, sx: f32, sy: f32| {
        (-(x * x) / (2.0 * sx * sx) - (y * y) / (2.0 * sy * sy)).exp()
    };
    match scene {
        Scene::Heart => {
            distance - 24.0 * g(x, y, 24.0, 20.0) - 4.0 * g(x - 12.0, y + 8.0, 8.0, 10.0)
        }
        Scene::Liver => {
            distance - 12.0 * (x / 70.0).cos() + 0.12 * y - 3.0 * g(x + 20.0, y - 10.0, 15.0, 12.0)
        }
        Scene::Kidney => {
            let bend = y / 16.0 - 0.35 * (x / 28.0).powi(2);
            distance - 20.0 * (-(x / 28.0).powi(2) - bend * bend).exp()
        }
        Scene::Stomach => {
            distance - 9.0 * g(x, y, 35.0, 30.0) + 2.2 * (x / 5.5 + 0.6 * (y / 11.0).sin()).sin()
        }
    }
}

/// The rest point of parameter (x, y).
pub fn rest_point(scene: Scene, x: f32, y: f32, distance: f32) -> [f32; 3] {
    [x, y, rest_z(scene, x, y, distance)]
}

/// Unit normal of the rest surface (pointing toward the scope, -z mostly), by central differences.
pub fn rest_normal(scene: Scene, x: f32, y: f32, distance: f32) -> [f32; 3] {
    let h = 0.05;
    let dzdx = (rest_z(scene, x + h, y, distance) - rest_z(scene, x - h, y, distance)) / (2.0 * h);
    let dzdy = (rest_z(scene, x, y + h, distance) - rest_z(scene, x, y - h, distance)) / (2.0 * h);
    let n = Vector3::new(dzdx, dzdy, -1.0).normalize();
    [n.x, n.y, n.z]
}

/// Displacement at time `t` of the rest point of parameter (x, y) with rest normal `n`.
pub fn displacement(scene: Scene, m: &Motion, x: f32, y: f32, n: [f32; 3], t: f32) -> [f32; 3] {
    use std::f32::consts::TAU;
    let mut d = [0.0f32; 3];
    // Heartbeat: a contraction pulse along the normal, strongest at the apex of the dome.
    if m.heartbeat_mm != 0.0 {
        let phase = (TAU * m.heartbeat_hz * t).sin();
        let pulse = 0.5 - 0.5 * (TAU * m.heartbeat_hz * t).cos() + 0.15 * phase;
        let env = match scene {
            Scene::Heart => (-(x * x + y * y) / (2.0 * 30.0 * 30.0)).exp(),
            _ => (-(x * x + y * y) / (2.0 * 45.0 * 45.0)).exp(),
        };
        let a = m.heartbeat_mm * pulse * env;
        // Toward the scope: the normal points at it.
        for k in 0..3 {
            d[k] += a * n[k];
        }
        // A slight twist, as the ventricles wring.
        d[0] += -0.15 * a * y / 30.0;
        d[1] += 0.15 * a * x / 30.0;
    }
    // Breathing: the abdominal contents rise and slide together.
    if m.breathing_mm != 0.0 {
        let b = m.breathing_mm * (TAU * m.breathing_hz * t).sin();
        let env = 1.0 - 0.3 * ((x * x + y * y) / (80.0 * 80.0)).min(1.0);
        d[1] += 0.6 * b * env;
        d[2] -= 0.8 * b * env;
    }
    // Tool press: a Gaussian dent pushed away from the scope, ramped in and out.
    if m.tool_press_mm != 0.0
        && t >= m.tool_start_s
        && t <= m.tool_start_s + m.tool_duration_s
        && m.tool_duration_s > 0.0
    {
        let s = ((t - m.tool_start_s) / m.tool_duration_s * std::f32::consts::PI).sin();
        let (dx, dy) = (x - m.tool_xy_mm[0], y - m.tool_xy_mm[1]);
        let r2 = dx * dx + dy * dy;
        let w = (-r2 / (2.0 * m.tool_radius_mm * m.tool_radius_mm)).exp();
        for k in 0..3 {
            d[k] -= m.tool_press_mm * s * w * n[k];
        }
    }
    d
}

/// The scope's `world_from_camera` at time `t`.
pub fn scope_pose(m: &Motion, t: f32) -> Isometry3<f32> {
    use std::f32::consts::TAU;
    let (mut tx, mut ty, mut yaw, mut pitch) = (0.0, 0.0, 0.0, 0.0);
    if matches!(m.trajectory, Trajectory::Sweep | Trajectory::Fast) && m.sweep_period_s > 0.0 {
        let w = TAU / m.sweep_period_s;
        tx = m.sweep_mm * (w * t).sin();
        ty = 0.4 * m.sweep_mm * (0.6 * w * t).sin();
        yaw = 0.04 * (w * t).sin();
        pitch = 0.02 * (0.6 * w * t).cos() - 0.02;
    }
    if m.trajectory == Trajectory::Fast && m.fast_duration_s > 0.0 {
        let u = (t - m.fast_start_s) / m.fast_duration_s;
        if (0.0..=1.0).contains(&u) {
            // Out and back within the segment: a jerk the tracker must survive.
            let s = (u * std::f32::consts::PI).sin();
            tx += m.fast_amplitude_mm * s;
            ty -= 0.5 * m.fast_amplitude_mm * s;
            yaw += 0.15 * s;
        }
    }
    Isometry3::from_parts(
        Translation3::new(tx, ty, 0.0),
        UnitQuaternion::from_euler_angles(pitch, yaw, 0.0),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn still() -> Motion {
        Motion {
            heartbeat_mm: 0.0,
            heartbeat_hz: 1.2,
            breathing_mm: 0.0,
            breathing_hz: 0.25,
            tool_press_mm: 0.0,
            tool_xy_mm: [0.0, 0.0],
            tool_radius_mm: 5.0,
            tool_start_s: 0.0,
            tool_duration_s: 1.0,
            trajectory: Trajectory::Static,
            sweep_mm: 10.0,
            sweep_period_s: 8.0,
            fast_start_s: 2.0,
            fast_duration_s: 0.2,
            fast_amplitude_mm: 8.0,
        }
    }

    #[test]
    fn normals_face_the_scope() {
        for scene in [Scene::Heart, Scene::Liver, Scene::Kidney, Scene::Stomach] {
            for (x, y) in [(0.0, 0.0), (20.0, -10.0), (-30.0, 25.0)] {
                let n = rest_normal(scene, x, y, 90.0);
                assert!(n[2] < -0.3, "{scene:?} at ({x},{y}): {n:?}");
                assert!(((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) - 1.0).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn deformations_are_zero_when_switched_off_and_periodic_when_on() {
        let m = still();
        let n = rest_normal(Scene::Heart, 0.0, 0.0, 90.0);
        assert_eq!(displacement(Scene::Heart, &m, 3.0, 4.0, n, 0.7), [0.0; 3]);
        let beat = Motion {
            heartbeat_mm: 3.0,
            ..m
        };
        let period = 1.0 / beat.heartbeat_hz;
        let a = displacement(Scene::Heart, &beat, 0.0, 0.0, n, 0.3);
        let b = displacement(Scene::Heart, &beat, 0.0, 0.0, n, 0.3 + period);
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-4);
        }
        assert_eq!(
            displacement(Scene::Heart, &beat, 0.0, 0.0, n, 0.0),
            [0.0; 3],
            "rest at t = 0"
        );
        let press = Motion {
            tool_press_mm: 2.0,
            ..m
        };
        let d = displacement(Scene::Heart, &press, 0.0, 0.0, n, 0.5);
        let len = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        assert!(
            (len - 2.0).abs() < 1e-4,
            "full depth at the centre, mid-press: {len}"
        );
    }

    #[test]
    fn static_scope_stays_at_the_origin_and_fast_segment_jerks() {
        let m = still();
        assert_eq!(scope_pose(&m, 3.0), Isometry3::identity());
        let fast = Motion {
            trajectory: Trajectory::Fast,
            ..m
        };
        let mid = scope_pose(&fast, 2.1).translation.vector;
        let before = scope_pose(&fast, 1.9).translation.vector;
        assert!(
            (mid - before).norm() > 5.0,
            "the fast segment moves several mm in 0.2 s"
        );
    }
}
