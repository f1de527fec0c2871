//! The drift watch during the operation: has a cart moved since it was
//! calibrated?
//!
//! After calibration the agents keep observing the target at a low rate. Each
//! observation of robot `r` puts the target in the reference base through the
//! result: `ref_from_base_r * base_r_from_flange * flange_from_camera_r *
//! camera_r_from_target`; the reference robot's own observation puts it there
//! directly. Their difference is the **innovation** of the pair, in target
//! coordinates (rotation `r`, and the shift of the target's centre `t`):
//! zero, up to noise and a constant misfit, while nothing moves; a cart that
//! moved by `δ` shifts it by `δ` seen at the target.
//!
//! [`PairWatch`] tests the innovations sequentially:
//!
//! 1. **Against the result.** The first [`DriftOptions::baseline`] innovations
//!    give the pair's constant misfit `b` (calibration error, and the arms'
//!    kinematic error at the watch poses) and the observation noise `S`
//!    (their sample covariance, floored). `b` is tested against the result's
//!    own covariance of the pair (mapped to the target) plus `S/n` and the
//!    kinematic allowance [`DriftOptions::pose_sigma_t_m`],
//!    [`DriftOptions::pose_sigma_r_rad`]: beyond χ²(6) at
//!    [`DriftOptions::result_chi2`] the watch alarms at once, since a cart that
//!    moved before the watch began looks exactly like this.
//! 2. **Sequentially (CUSUM).** Every later innovation's Mahalanobis distance
//!    `z = (d - b)ᵀ Σ⁻¹ (d - b)` from the misfit, `Σ = S (n+1)/n` with floors,
//!    is χ²(6) while nothing moves. The one-sided CUSUM
//!    `g = max(0, g + min(z, k + h/2) - k)` alarms when `g > h`. With `k` at 25
//!    (χ²(6) exceeds it once in 3,000) and `h` at 50, three observations in a
//!    row of a cart moved by 1 mm or 0.1° (z in the hundreds at the floors)
//!    alarm; the cap makes one wild observation (a heavy-tailed noise sample, a
//!    misdetection) unable to alarm alone.
//!
//! The floors (0.1 mm, 0.01°) keep a baseline that happened to be quiet from
//! making ordinary noise look like a move: they sit well below the 1 mm and
//! 0.1° the watch must catch, and above the noise of a still arm's
//! observations of a board at half a metre.

use nalgebra::{Matrix6, Point3, Vector6};

use crate::Iso3;

/// Settings of the drift watch (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriftOptions {
    /// Innovations that establish the misfit and the noise before the
    /// sequential test starts.
    pub baseline: usize,
    /// The CUSUM's reference value, subtracted from each `z`.
    pub k: f64,
    /// The CUSUM's alarm threshold.
    pub h: f64,
    /// Smallest per-axis standard deviation of the noise: translation, m.
    pub floor_t_m: f64,
    /// Smallest per-axis standard deviation of the noise: rotation, rad.
    pub floor_r_rad: f64,
    /// The limit of the misfit's χ²(6) against the result.
    pub result_chi2: f64,
    /// Per-axis allowance for the arms' kinematic error at the watch poses,
    /// which the result's covariance does not hold: translation, m.
    pub pose_sigma_t_m: f64,
    /// The same for rotation, rad.
    pub pose_sigma_r_rad: f64,
}

impl Default for DriftOptions {
    fn default() -> Self {
        DriftOptions {
            baseline: 20,
            k: 25.0,
            h: 50.0,
            floor_t_m: 0.1e-3,
            floor_r_rad: 0.01f64.to_radians(),
            // χ²(6) at 99.9%.
            result_chi2: 22.46,
            pose_sigma_t_m: 0.3e-3,
            pose_sigma_r_rad: 0.015f64.to_radians(),
        }
    }
}

/// The innovation of a pair in target coordinates: the rotation vector of
/// `target_a * target_b⁻¹` and the shift of the target's centre, with both
/// target poses given in the same (reference) base.
pub fn innovation(
    ref_from_target_a: &Iso3,
    ref_from_target_b: &Iso3,
    centre: &Point3<f64>,
) -> Vector6<f64> {
    let r = (ref_from_target_a.rotation * ref_from_target_b.rotation.inverse()).scaled_axis();
    let t = ref_from_target_a * centre - ref_from_target_b * centre;
    Vector6::new(r.x, r.y, r.z, t.x, t.y, t.z)
}

/// A covariance of a left perturbation `[r; t]` at the reference base's origin
/// seen at `point` (in the same base): the rotation stays, the point moves by
/// `t + r × p`.
pub fn covariance_at(cov: &Matrix6<f64>, point: &Point3<f64>) -> Matrix6<f64> {
    let mut j = Matrix6::identity();
    // t' = t + r × p = t - [p]× r.
    j.fixed_view_mut::<3, 3>(3, 0)
        .copy_from(&(-crate::pose::skew(&point.coords)));
    j * cov * j.transpose()
}

/// What one innovation did to the watch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum DriftEvent {
    /// Still establishing the baseline: `seen` of `needed`.
    Learning { seen: usize, needed: usize },
    /// The baseline is set; `chi2` is the misfit's χ²(6) against the result.
    Armed { chi2: f64, misfit: Vector6<f64> },
    /// Watching: this innovation's `z` and the CUSUM `g` after it.
    Watching { z: f64, g: f64 },
    /// A move: `shift` is the innovation's change from the baseline (rotation
    /// rad, translation m at the target); `against_result` when the baseline
    /// itself disagreed with the result.
    Alarm {
        z: f64,
        g: f64,
        shift: Vector6<f64>,
        against_result: bool,
    },
}

/// The drift watch of one pair (a robot against the reference).
#[derive(Debug, Clone)]
pub struct PairWatch {
    options: DriftOptions,
    /// The result's covariance of the pair, at the target.
    result_covariance: Matrix6<f64>,
    samples: Vec<Vector6<f64>>,
    misfit: Vector6<f64>,
    information: Matrix6<f64>,
    g: f64,
}

impl PairWatch {
    /// `result_covariance`: the result's covariance of the pair's left
    /// perturbation at the reference origin; `centre`: the target's centre in
    /// the reference base (where innovations are measured).
    pub fn new(
        options: DriftOptions,
        result_covariance: &Matrix6<f64>,
        centre: &Point3<f64>,
    ) -> Self {
        PairWatch {
            options,
            result_covariance: covariance_at(result_covariance, centre),
            samples: Vec::with_capacity(options.baseline),
            misfit: Vector6::zeros(),
            information: Matrix6::zeros(),
            g: 0.0,
        }
    }

    /// Whether the baseline is set.
    pub fn armed(&self) -> bool {
        self.samples.len() >= self.options.baseline
    }

    /// The CUSUM statistic now.
    pub fn cusum(&self) -> f64 {
        self.g
    }

    /// The constant misfit of the baseline.
    pub fn misfit(&self) -> Vector6<f64> {
        self.misfit
    }

    /// Tests one innovation ([`innovation`]). Non-finite input is ignored
    /// (returns the state unchanged, as `Learning` or `Watching`).
    pub fn update(&mut self, d: &Vector6<f64>) -> DriftEvent {
        let o = self.options;
        if !d.iter().all(|v| v.is_finite()) {
            return if self.armed() {
                DriftEvent::Watching { z: 0.0, g: self.g }
            } else {
                DriftEvent::Learning {
                    seen: self.samples.len(),
                    needed: o.baseline,
                }
            };
        }
        if !self.armed() {
            self.samples.push(*d);
            if !self.armed() {
                return DriftEvent::Learning {
                    seen: self.samples.len(),
                    needed: o.baseline,
                };
            }
            return self.arm();
        }
        let e = d - self.misfit;
        let z = (e.transpose() * self.information * e)[0];
        // Capped: no single observation can raise the alarm.
        self.g = (self.g + z.min(o.k + o.h / 2.0) - o.k).max(0.0);
        if self.g > o.h {
            DriftEvent::Alarm {
                z,
                g: self.g,
                shift: e,
                against_result: false,
            }
        } else {
            DriftEvent::Watching { z, g: self.g }
        }
    }

    fn arm(&mut self) -> DriftEvent {
        let o = self.options;
        let n = self.samples.len() as f64;
        let mean = self.samples.iter().sum::<Vector6<f64>>() / n;
        let mut s = Matrix6::zeros();
        for x in &self.samples {
            let e = x - mean;
            s += e * e.transpose();
        }
        s /= (n - 1.0).max(1.0);
        let floor = Vector6::new(
            o.floor_r_rad,
            o.floor_r_rad,
            o.floor_r_rad,
            o.floor_t_m,
            o.floor_t_m,
            o.floor_t_m,
        );
        let sigma = s * ((n + 1.0) / n) + Matrix6::from_diagonal(&floor.component_mul(&floor));
        self.information = sigma
            .try_inverse()
            .unwrap_or_else(|| Matrix6::from_diagonal(&floor.map(|f| 1.0 / (f * f))));
        self.misfit = mean;
        // Both arms' kinematic error at their watch poses.
        let (r2, t2) = (
            o.pose_sigma_r_rad * o.pose_sigma_r_rad,
            o.pose_sigma_t_m * o.pose_sigma_t_m,
        );
        let allowance = Matrix6::from_diagonal(&Vector6::new(r2, r2, r2, t2, t2, t2)) * 2.0;
        let against = self.result_covariance + sigma / n + allowance;
        let chi2 = against
            .try_inverse()
            .map_or(f64::INFINITY, |inv| (mean.transpose() * inv * mean)[0]);
        if chi2 > o.result_chi2 {
            DriftEvent::Alarm {
                z: chi2,
                g: self.g,
                shift: mean,
                against_result: true,
            }
        } else {
            DriftEvent::Armed { chi2, misfit: mean }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, StandardNormal, StudentT};

    /// Observation noise of a still arm seeing a board at half a metre: 0.03
    /// mm across, 0.1 mm in depth (z), 0.003° about each axis.
    fn noise_sd() -> Vector6<f64> {
        let r = 0.003f64.to_radians();
        Vector6::new(r, r, r, 0.03e-3, 0.03e-3, 0.1e-3)
    }

    enum Noise {
        Gaussian,
        /// Student-t with 4 degrees of freedom, scaled to the same variance.
        HeavyTailed,
        /// AR(1) with ρ = 0.9 (slowly varying), the same marginal variance.
        Correlated,
    }

    fn draw(rng: &mut StdRng, kind: &Noise, state: &mut Vector6<f64>) -> Vector6<f64> {
        draw_scaled(rng, kind, state, 1.0)
    }

    fn draw_scaled(
        rng: &mut StdRng,
        kind: &Noise,
        state: &mut Vector6<f64>,
        scale: f64,
    ) -> Vector6<f64> {
        let sd = noise_sd() * scale;
        match kind {
            Noise::Gaussian => Vector6::from_fn(|i, _| {
                let v: f64 = StandardNormal.sample(rng);
                v * sd[i]
            }),
            Noise::HeavyTailed => {
                let t = StudentT::new(4.0).unwrap();
                // Var of t(4) is 2.
                Vector6::from_fn(|i, _| t.sample(rng) / 2f64.sqrt() * sd[i])
            }
            Noise::Correlated => {
                let rho: f64 = 0.9;
                let fresh = Vector6::from_fn(|i, _| {
                    let v: f64 = StandardNormal.sample(rng);
                    v * sd[i] * (1.0 - rho * rho).sqrt()
                });
                *state = *state * rho + fresh;
                *state
            }
        }
    }

    fn watch() -> PairWatch {
        // A result uncertain by 0.2 mm and 0.01° per axis, target 0.5 m out.
        let r = 0.01f64.to_radians();
        let cov = Matrix6::from_diagonal(&Vector6::new(
            r * r,
            r * r,
            r * r,
            0.04e-6,
            0.04e-6,
            0.04e-6,
        ));
        PairWatch::new(DriftOptions::default(), &cov, &Point3::new(0.5, 0.0, 0.0))
    }

    /// A constant misfit the size of a calibration's error at the target.
    fn misfit() -> Vector6<f64> {
        Vector6::new(1e-4, -5e-5, 8e-5, 0.2e-3, -0.15e-3, 0.1e-3)
    }

    /// Observations at 5 Hz: 144,000 in 8 hours.
    const PER_8H: usize = 8 * 3600 * 5;

    /// False alarms over `hours` of watching (virtual time: observations are
    /// counted, not waited for), re-arming after each with a fresh baseline.
    fn false_alarms(kind: &Noise, scale: f64, hours: usize, seed: u64) -> usize {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut state = Vector6::zeros();
        let mut w = watch();
        let mut alarms = 0;
        for _ in 0..hours * PER_8H / 8 {
            let d = misfit() + draw_scaled(&mut rng, kind, &mut state, scale);
            if let DriftEvent::Alarm { .. } = w.update(&d) {
                alarms += 1;
                w = watch();
            }
        }
        alarms
    }

    /// The false-alarm rate under three noise models, only the first of which
    /// is the Gaussian the thresholds assume, at the noise of a still arm
    /// (below the floors) and at three times it (above them, where the
    /// baseline's own covariance decides): at most one per 8 hours of watching
    /// at 5 Hz, measured over 40 hours each (virtual time).
    #[test]
    fn false_alarms_stay_below_one_per_8_hours() {
        for scale in [1.0, 3.0] {
            for (name, kind) in [
                ("gaussian", Noise::Gaussian),
                ("student-t(4)", Noise::HeavyTailed),
                ("ar(1) 0.9", Noise::Correlated),
            ] {
                let alarms = false_alarms(&kind, scale, 40, 7);
                eprintln!("{name}, noise x{scale}: {alarms} false alarms in 40 h at 5 Hz");
                assert!(
                    alarms <= 5,
                    "{name} x{scale}: {alarms} false alarms in 40 h"
                );
            }
        }
    }

    /// A cart moved by 1 mm (in any direction) or turned by 0.1° about its
    /// base (seen at the target 0.5 m away) alarms within the 10 observations
    /// of 2 s at 5 Hz, every time.
    #[test]
    fn a_move_of_1_mm_or_a_turn_of_0_1_deg_alarms_within_2_s() {
        let mut rng = StdRng::seed_from_u64(11);
        let mut state = Vector6::zeros();
        let mut worst = 0;
        for trial in 0..200 {
            let mut w = watch();
            let dir = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
            // A turn about the base's vertical at the origin moves the target
            // (0.5 m out) by 0.9 mm sideways; a shift moves it by 1 mm.
            let step = if trial % 2 == 0 {
                Vector6::new(0.0, 0.0, 0.0, dir.x, dir.y, dir.z) * 1e-3
            } else {
                let r = Vector3::z() * 0.1f64.to_radians();
                let t = r.cross(&Vector3::new(0.5, 0.0, 0.0));
                Vector6::new(r.x, r.y, r.z, t.x, t.y, t.z)
            };
            for _ in 0..60 {
                let d = misfit() + draw(&mut rng, &Noise::Gaussian, &mut state);
                assert!(!matches!(w.update(&d), DriftEvent::Alarm { .. }));
            }
            let mut delay = None;
            for k in 1..=10 {
                let d = misfit() + step + draw(&mut rng, &Noise::Gaussian, &mut state);
                if let DriftEvent::Alarm { shift, .. } = w.update(&d) {
                    // The reported shift is the move, to within the noise.
                    assert!((shift - step).fixed_rows::<3>(3).norm() < 0.4e-3, "{shift}");
                    delay = Some(k);
                    break;
                }
            }
            let k = delay.unwrap_or_else(|| panic!("trial {trial}: no alarm within 10"));
            worst = worst.max(k);
        }
        eprintln!("worst delay: {worst} observations");
        // The cap lets one observation add at most h/2: three in a row are the
        // fewest that can alarm, and the README says three.
        assert!(worst <= 3, "worst delay {worst} observations");
    }

    /// A cart moved before the watch began: the baseline itself disagrees with
    /// the result, and the watch alarms as soon as it is set.
    #[test]
    fn a_move_before_the_watch_alarms_against_the_result() {
        let mut rng = StdRng::seed_from_u64(3);
        let mut state = Vector6::zeros();
        let mut w = watch();
        let moved = Vector6::new(0.0, 0.0, 0.0, 2e-3, 0.0, 0.0);
        let mut last = None;
        for _ in 0..DriftOptions::default().baseline {
            last =
                Some(w.update(&(misfit() + moved + draw(&mut rng, &Noise::Gaussian, &mut state))));
        }
        assert!(
            matches!(
                last,
                Some(DriftEvent::Alarm {
                    against_result: true,
                    ..
                })
            ),
            "{last:?}"
        );
        // Without the move, the same baseline is consistent with the result.
        let mut w = watch();
        for _ in 0..DriftOptions::default().baseline {
            last = Some(w.update(&(misfit() + draw(&mut rng, &Noise::Gaussian, &mut state))));
        }
        assert!(matches!(last, Some(DriftEvent::Armed { .. })), "{last:?}");
    }

    #[test]
    fn the_innovation_is_the_target_shift_and_turn() {
        let a = Iso3::translation(0.5, 0.0, 0.0);
        let c = Point3::new(0.1, 0.05, 0.0);
        let moved = Iso3::translation(0.0, 1e-3, 0.0) * a;
        let d = innovation(&moved, &a, &c);
        assert!((d - Vector6::new(0.0, 0.0, 0.0, 0.0, 1e-3, 0.0)).norm() < 1e-12);
        // A base turned about its origin moves the target by r × p.
        let r = Vector3::z() * 1e-3;
        let turned = Iso3::new(Vector3::zeros(), r) * a;
        let d = innovation(&turned, &a, &c);
        let p = (a * c).coords;
        let expected = r.cross(&p);
        // To first order in the turn.
        assert!((d.fixed_rows::<3>(3) - expected).norm() < 1e-6, "{d}");
        assert!((d.fixed_rows::<3>(0) - r).norm() < 1e-12);
    }

    #[test]
    fn non_finite_innovations_are_ignored() {
        let mut w = watch();
        let bad = Vector6::repeat(f64::NAN);
        assert!(matches!(
            w.update(&bad),
            DriftEvent::Learning { seen: 0, .. }
        ));
    }
}
