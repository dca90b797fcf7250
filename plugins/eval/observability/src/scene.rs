//! The simulated world of the study: a planar cross-section of an organ whose wall points
//! (features) move periodically, a scope that stays still for a while and then moves inside it,
//! its odometry and its observations of the features.

use misslam_framework::nalgebra::{Matrix2, Vector2};

/// A planar pose: position (mm) and heading (rad).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Pose2 {
    /// Position x, mm.
    pub x: f64,
    /// Position y, mm.
    pub y: f64,
    /// Heading, rad.
    pub th: f64,
}

/// The rotation by `th`.
pub fn rot(th: f64) -> Matrix2<f64> {
    let (s, c) = th.sin_cos();
    Matrix2::new(c, -s, s, c)
}

/// `a` wrapped into (-pi, pi].
pub fn wrap(a: f64) -> f64 {
    let t = std::f64::consts::TAU;
    let w = a - t * (a / t).round();
    if w <= -std::f64::consts::PI {
        w + t
    } else {
        w
    }
}

impl Pose2 {
    /// The position.
    pub fn p(&self) -> Vector2<f64> {
        Vector2::new(self.x, self.y)
    }

    /// `self` then `d` (d in `self`'s frame).
    pub fn compose(&self, d: &Pose2) -> Pose2 {
        let p = self.p() + rot(self.th) * d.p();
        Pose2 {
            x: p.x,
            y: p.y,
            th: wrap(self.th + d.th),
        }
    }

    /// The motion from `self` to `b`, in `self`'s frame.
    pub fn between(&self, b: &Pose2) -> Pose2 {
        let p = rot(self.th).transpose() * (b.p() - self.p());
        Pose2 {
            x: p.x,
            y: p.y,
            th: wrap(b.th - self.th),
        }
    }

    /// A world point in this pose's frame.
    pub fn to_local(&self, f: &Vector2<f64>) -> Vector2<f64> {
        rot(self.th).transpose() * (f - self.p())
    }
}

/// The organs of the thesis's simulations, each a cross-section with its own periodic motion.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Organ {
    /// An ellipse of 32 x 28 mm beating every 10 steps (1 Hz at 10 frames a second): a radial
    /// contraction of 3 mm with a twist of 0.8 mm and a second harmonic of 1 mm.
    Heart,
    /// An ellipse of 50 x 32 mm with a peristaltic wave of 2.5 mm travelling around it (two
    /// wavelengths per turn) every 16 steps.
    Stomach,
    /// An ellipse of 60 x 38 mm off the origin, breathing every 20 steps: a translation of 4 x
    /// 1.5 mm and a radial swell of 1 mm.
    Liver,
    /// A circle of 45 mm breathing every 20 steps: a radial swell of 5 mm with a second harmonic
    /// of 1.5 mm.
    Lung,
}

impl Organ {
    /// Every organ, in the study's order.
    pub const ALL: [Organ; 4] = [Organ::Heart, Organ::Stomach, Organ::Liver, Organ::Lung];

    /// Its name in the CLI and the JSON.
    pub fn name(self) -> &'static str {
        match self {
            Organ::Heart => "heart",
            Organ::Stomach => "stomach",
            Organ::Liver => "liver",
            Organ::Lung => "lung",
        }
    }

    /// The organ called `s`; the error lists the names.
    pub fn parse(s: &str) -> Result<Organ, String> {
        Organ::ALL
            .into_iter()
            .find(|o| o.name() == s)
            .ok_or_else(|| {
                format!("unknown organ `{s}`: expected one of heart, stomach, liver, lung")
            })
    }

    /// Angular frequencies of its motion, rad per step.
    pub fn omegas(self) -> Vec<f64> {
        let w = |period: f64| std::f64::consts::TAU / period;
        match self {
            Organ::Heart => vec![w(10.0), 2.0 * w(10.0)],
            Organ::Stomach => vec![w(16.0)],
            Organ::Liver => vec![w(20.0)],
            Organ::Lung => vec![w(20.0), 2.0 * w(20.0)],
        }
    }

    /// Rest position of the wall at angle `phi`, its outward normal and its tangent.
    fn wall(self, phi: f64) -> (Vector2<f64>, Vector2<f64>, Vector2<f64>) {
        let (a, b, c) = match self {
            Organ::Heart => (32.0, 28.0, Vector2::zeros()),
            Organ::Stomach => (50.0, 32.0, Vector2::zeros()),
            Organ::Liver => (60.0, 38.0, Vector2::new(12.0, -4.0)),
            Organ::Lung => (45.0, 45.0, Vector2::zeros()),
        };
        let (s, co) = phi.sin_cos();
        let g = c + Vector2::new(a * co, b * s);
        let n = Vector2::new(co / a, s / b).normalize();
        let t = Vector2::new(-n.y, n.x);
        (g, n, t)
    }

    /// Cosine and sine coefficients (each a 2D displacement, mm) of each frequency for the wall
    /// point at angle `phi`: f(n) = g + sum_h (alpha_h cos(w_h n) + beta_h sin(w_h n)).
    fn coefficients(self, phi: f64) -> Vec<(Vector2<f64>, Vector2<f64>)> {
        let (_, n, t) = self.wall(phi);
        match self {
            Organ::Heart => vec![
                (-3.0 * n, 0.8 * t),
                (-phi.cos().abs() * n, Vector2::zeros()),
            ],
            Organ::Stomach => vec![(2.5 * (2.0 * phi).cos() * n, 2.5 * (2.0 * phi).sin() * n)],
            Organ::Liver => vec![(Vector2::new(4.0, 1.5) + 1.0 * n, Vector2::zeros())],
            Organ::Lung => vec![(5.0 * n, Vector2::zeros()), (1.5 * n, Vector2::zeros())],
        }
    }
}

/// What the simulation draws.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SceneParams {
    /// The organ.
    pub organ: Organ,
    /// Wall points (features), evenly spread in angle.
    pub features: usize,
    /// Steps in all.
    pub steps: usize,
    /// Initial steps with the scope still (the thesis's E_ini period); the scope moves after.
    pub static_steps: usize,
    /// Standard deviation of each coordinate of an observed feature (in the scope's frame), mm.
    pub obs_sigma_mm: f64,
    /// Standard deviation of each coordinate of the odometry's translation per step, mm.
    pub odo_sigma_mm: f64,
    /// Standard deviation of the odometry's rotation per step, degrees.
    pub odo_sigma_deg: f64,
    /// Radius of the scope's loop inside the organ, mm.
    pub path_radius_mm: f64,
    /// Seed of the noise.
    pub seed: u64,
}

impl SceneParams {
    /// The defaults for an organ: 16 features, 72 steps of which 24 still (at least a period of
    /// every organ's motion, so that the recurrence can be fitted), 0.3 mm observation
    /// noise, odometry 0.3 mm and 0.5 degrees per step, a loop of 8 mm.
    pub fn new(organ: Organ) -> Self {
        SceneParams {
            organ,
            features: 16,
            steps: 72,
            static_steps: 24,
            obs_sigma_mm: 0.3,
            odo_sigma_mm: 0.3,
            odo_sigma_deg: 0.5,
            path_radius_mm: 8.0,
            seed: 1,
        }
    }

    /// The parameter that cannot be simulated, named.
    pub fn validate(&self) -> Result<(), String> {
        if self.features < 4 {
            return Err(format!("`features` is {}: at least 4", self.features));
        }
        if self.static_steps < 2 {
            return Err(format!(
                "`static_steps` is {}: at least 2 (the recurrence is fitted there)",
                self.static_steps
            ));
        }
        if self.steps <= self.static_steps {
            return Err(format!(
                "`steps` ({}) must exceed `static_steps` ({}): the scope must move",
                self.steps, self.static_steps
            ));
        }
        for (name, v) in [
            ("obs_sigma_mm", self.obs_sigma_mm),
            ("odo_sigma_mm", self.odo_sigma_mm),
            ("odo_sigma_deg", self.odo_sigma_deg),
            ("path_radius_mm", self.path_radius_mm),
        ] {
            if !v.is_finite() || v < 0.0 {
                return Err(format!("`{name}` is {v}: a finite value >= 0"));
            }
        }
        Ok(())
    }
}

/// One simulated run: the truth and what the scope measures.
#[derive(Clone, Debug)]
pub struct Scene {
    /// The parameters it was drawn with.
    pub params: SceneParams,
    /// Rest positions of the features, mm.
    pub rest: Vec<Vector2<f64>>,
    /// True feature positions, `truth[n][j]`, mm.
    pub truth: Vec<Vec<Vector2<f64>>>,
    /// True scope poses, one per step.
    pub poses: Vec<Pose2>,
    /// Measured motion from step n - 1 to n, in the frame of n - 1 (`odometry[0]` is unused).
    pub odometry: Vec<Pose2>,
    /// Every feature seen from every step, in the scope's frame, `observations[n][j]`, mm.
    pub observations: Vec<Vec<Vector2<f64>>>,
}

/// A seeded normal sampler (xorshift and Box-Muller), so runs repeat.
pub struct Noise(u64);

impl Noise {
    /// From a seed.
    pub fn new(seed: u64) -> Self {
        Noise(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1)
    }

    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// A standard normal sample.
    pub fn normal(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

impl Scene {
    /// Draws a run.
    pub fn simulate(params: &SceneParams) -> Result<Scene, String> {
        params.validate()?;
        let o = params.organ;
        let m = params.features;
        let omegas = o.omegas();
        let phis: Vec<f64> = (0..m)
            .map(|j| std::f64::consts::TAU * j as f64 / m as f64)
            .collect();
        let rest: Vec<_> = phis.iter().map(|&p| o.wall(p).0).collect();
        let coeffs: Vec<_> = phis.iter().map(|&p| o.coefficients(p)).collect();
        let truth: Vec<Vec<_>> = (0..params.steps)
            .map(|n| {
                (0..m)
                    .map(|j| {
                        let mut f = rest[j];
                        for (h, (a, b)) in coeffs[j].iter().enumerate() {
                            let (s, c) = (omegas[h] * n as f64).sin_cos();
                            f += a * c + b * s;
                        }
                        f
                    })
                    .collect()
            })
            .collect();
        // Still at the origin facing +x, then a loop of the given radius while the heading
        // swings by 0.6 rad.
        let r = params.path_radius_mm;
        let moving = (params.steps - params.static_steps) as f64;
        let poses: Vec<Pose2> = (0..params.steps)
            .map(|n| {
                if n < params.static_steps {
                    return Pose2::default();
                }
                let s = std::f64::consts::TAU * (n - params.static_steps + 1) as f64 / moving;
                Pose2 {
                    x: r * s.sin(),
                    y: r * (1.0 - s.cos()),
                    th: 0.6 * s.sin(),
                }
            })
            .collect();
        let mut noise = Noise::new(params.seed);
        let odo_rad = params.odo_sigma_deg.to_radians();
        let mut odometry = vec![Pose2::default()];
        for n in 1..params.steps {
            let d = poses[n - 1].between(&poses[n]);
            odometry.push(Pose2 {
                x: d.x + params.odo_sigma_mm * noise.normal(),
                y: d.y + params.odo_sigma_mm * noise.normal(),
                th: d.th + odo_rad * noise.normal(),
            });
        }
        let observations = (0..params.steps)
            .map(|n| {
                truth[n]
                    .iter()
                    .map(|f| {
                        poses[n].to_local(f)
                            + params.obs_sigma_mm * Vector2::new(noise.normal(), noise.normal())
                    })
                    .collect()
            })
            .collect();
        Ok(Scene {
            params: params.clone(),
            rest,
            truth,
            poses,
            odometry,
            observations,
        })
    }

    /// The true recurrence's coefficients: f(n) = sum_{i=1..t} c_i f(n - i) holds exactly for
    /// every feature, with t = 2H + 1 for H frequencies (the characteristic polynomial
    /// (z - 1) prod_h (z^2 - 2 cos(w_h) z + 1)).
    pub fn true_recurrence(&self) -> Vec<f64> {
        let mut poly = vec![1.0, -1.0]; // z - 1, highest power first
        for w in self.params.organ.omegas() {
            let q = [1.0, -2.0 * w.cos(), 1.0];
            let mut next = vec![0.0; poly.len() + 2];
            for (i, a) in poly.iter().enumerate() {
                for (k, b) in q.iter().enumerate() {
                    next[i + k] += a * b;
                }
            }
            poly = next;
        }
        // z^t - c_1 z^(t-1) - ... - c_t: c_i = -poly[i].
        poly[1..].iter().map(|a| -a).collect()
    }
}
