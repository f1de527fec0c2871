//! Verification metrics: touch-point errors, the Procrustes comparison, predicted
//! errors from a covariance, and ISO 9283 pose accuracy and repeatability.
//!
//! The touch-point procedure is the seed paper's: each touch is one physical
//! point, touched by robot 1's pointer (known in `base1`) and robot 2's (known in
//! `base2`). Mapping robot 2's tip through the result and comparing gives the
//! touch error; fitting a rigid transform to the pairs alone gives an independent
//! "ground truth" transform to compare the result against.

use nalgebra::{Matrix3, Matrix3x6, Matrix6, Point3, SymmetricEigen, Vector3};
use rand::{SeedableRng, rngs::StdRng};

use crate::pose::{geodesic_angle, skew};
use crate::procrustes::fit_rigid;
use crate::synth::gauss;
use crate::{CalibError, Iso3};

/// The metrics of `coordinator verify`.
#[derive(Debug, Clone, PartialEq)]
pub struct TouchMetrics {
    pub n: usize,
    /// Per touch: |tip1 - base1_from_base2 * tip2| (m).
    pub errors_m: Vec<f64>,
    /// Per touch: the predicted 95% bound of that error at that point (m).
    pub bound95_m: Vec<f64>,
    pub mean_m: f64,
    pub rms_m: f64,
    pub max_m: f64,
    /// The transform fitted to the touches alone.
    pub procrustes_base1_from_base2: Iso3,
    pub procrustes_linear_m: f64,
    pub procrustes_angular_rad: f64,
    /// Fraction of touches whose error is within its predicted 95% bound.
    pub within_predicted_p95: f64,
}

/// The 3x3 covariance of a point `p_in_base1` mapped by a transform whose left
/// perturbation has covariance `cov` (δp = r × p + t).
pub fn point_covariance(cov: &Matrix6<f64>, p_in_base1: &Point3<f64>) -> Matrix3<f64> {
    let mut h = Matrix3x6::zeros();
    h.fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&(-skew(&p_in_base1.coords)));
    h.fixed_view_mut::<3, 3>(0, 3)
        .copy_from(&Matrix3::identity());
    h * cov * h.transpose()
}

/// Samples of |e| for e ~ N(0, c); deterministic for a seed.
fn norm_samples(c: &Matrix3<f64>, n: usize, rng: &mut StdRng) -> Vec<f64> {
    let eig = SymmetricEigen::new(*c);
    let sd = eig.eigenvalues.map(|v| v.max(0.0).sqrt());
    (0..n)
        .map(|_| {
            let z = Vector3::new(gauss(rng) * sd[0], gauss(rng) * sd[1], gauss(rng) * sd[2]);
            (eig.eigenvectors * z).norm()
        })
        .collect()
}

/// The median (the mean of the middle two for an even count; 0 for none). Sorts `v`.
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    v.sort_by(f64::total_cmp);
    let idx = ((v.len() - 1) as f64 * q).round() as usize;
    v[idx]
}

/// The predicted touch-point error over a set of points (m): the mean of |e| and
/// its 95th percentile, where at each point e ~ N(0, point covariance + 2 σ_tip² I)
/// (both pointers' tip noise). Monte Carlo with a fixed seed, so the numbers are
/// reproducible.
pub fn predicted_error(
    cov: &Matrix6<f64>,
    points_in_base1: &[Point3<f64>],
    tip_sigma_m: f64,
) -> (f64, f64) {
    let mut rng = StdRng::seed_from_u64(0x5eed);
    let mut all = Vec::new();
    for p in points_in_base1 {
        let c = point_covariance(cov, p) + Matrix3::identity() * (2.0 * tip_sigma_m * tip_sigma_m);
        all.extend(norm_samples(&c, 2000, &mut rng));
    }
    if all.is_empty() {
        return (0.0, 0.0);
    }
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    (mean, percentile(&mut all, 0.95))
}

/// Points of the shared workspace where touches are expected: a 0.3 m cube
/// centred on `centre_in_base1` (the board's centre), 5 x 5 x 5 points.
pub fn workspace_points(centre_in_base1: &Point3<f64>) -> Vec<Point3<f64>> {
    let mut pts = Vec::with_capacity(125);
    for i in 0..5 {
        for j in 0..5 {
            for k in 0..5 {
                let o = Vector3::new(i as f64, j as f64, k as f64) * 0.075 - Vector3::repeat(0.15);
                pts.push(centre_in_base1 + o);
            }
        }
    }
    pts
}

/// Checks a result against touch pairs `(tip1_in_base1, tip2_in_base2)`.
pub fn verify_touches(
    base1_from_base2: &Iso3,
    covariance: &Matrix6<f64>,
    touches: &[(Point3<f64>, Point3<f64>)],
    tip_sigma_m: f64,
) -> Result<TouchMetrics, CalibError> {
    if touches.len() < 3 {
        return Err(CalibError::TooFewTouches {
            got: touches.len(),
            need: 3,
        });
    }
    let tip1: Vec<_> = touches.iter().map(|t| t.0).collect();
    let tip2: Vec<_> = touches.iter().map(|t| t.1).collect();
    let errors_m: Vec<f64> = touches
        .iter()
        .map(|(a, b)| (a - base1_from_base2 * b).norm())
        .collect();
    if errors_m.iter().any(|e| !e.is_finite()) {
        return Err(CalibError::NonFinite("touch points".into()));
    }
    let mut rng = StdRng::seed_from_u64(0x70c4);
    let bound95_m: Vec<f64> = tip1
        .iter()
        .map(|p| {
            let c = point_covariance(covariance, p)
                + Matrix3::identity() * (2.0 * tip_sigma_m * tip_sigma_m);
            percentile(&mut norm_samples(&c, 4000, &mut rng), 0.95)
        })
        .collect();
    let n = touches.len();
    let fitted = fit_rigid(&tip1, &tip2)?;
    let within = errors_m
        .iter()
        .zip(&bound95_m)
        .filter(|(e, b)| e <= b)
        .count();
    Ok(TouchMetrics {
        n,
        mean_m: errors_m.iter().sum::<f64>() / n as f64,
        rms_m: (errors_m.iter().map(|e| e * e).sum::<f64>() / n as f64).sqrt(),
        max_m: errors_m.iter().copied().fold(0.0, f64::max),
        procrustes_linear_m: (fitted.translation.vector - base1_from_base2.translation.vector)
            .norm(),
        procrustes_angular_rad: geodesic_angle(&fitted.rotation, &base1_from_base2.rotation),
        procrustes_base1_from_base2: fitted,
        within_predicted_p95: within as f64 / n as f64,
        errors_m,
        bound95_m,
    })
}

/// ISO 9283 position accuracy and repeatability of one commanded position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Iso9283 {
    /// AP: distance from the barycentre of the attained positions to the command (m).
    pub accuracy_m: f64,
    /// RP = l̄ + 3 S_l, with l_j the distances of the attained positions to their barycentre (m).
    pub repeatability_m: f64,
    pub barycentre: Point3<f64>,
}

/// ISO 9283 AP and RP from n >= 2 attained positions of one command.
pub fn iso9283(commanded: &Point3<f64>, attained: &[Point3<f64>]) -> Result<Iso9283, CalibError> {
    let n = attained.len();
    if n < 2 {
        return Err(CalibError::TooFewTouches { got: n, need: 2 });
    }
    let bary = Point3::from(attained.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n as f64);
    let l: Vec<f64> = attained.iter().map(|p| (p - bary).norm()).collect();
    let lbar = l.iter().sum::<f64>() / n as f64;
    let s = (l.iter().map(|v| (v - lbar).powi(2)).sum::<f64>() / (n - 1) as f64).sqrt();
    Ok(Iso9283 {
        accuracy_m: (bary - commanded).norm(),
        repeatability_m: lbar + 3.0 * s,
        barycentre: bary,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::perturb_left;
    use crate::synth::random_pose;
    use nalgebra::Vector6;

    #[test]
    fn perfect_result_has_zero_touch_error() {
        let mut rng = StdRng::seed_from_u64(4);
        let truth = random_pose(&mut rng, 3.0, 1.0);
        let touches: Vec<_> = (0..25)
            .map(|i| {
                let p2 = Point3::new(
                    0.3 + 0.01 * i as f64,
                    (i % 5) as f64 * 0.05,
                    (i % 3) as f64 * 0.04,
                );
                (truth * p2, p2)
            })
            .collect();
        let m = verify_touches(&truth, &(Matrix6::identity() * 1e-10), &touches, 0.0).unwrap();
        assert!(
            m.mean_m < 1e-12 && m.procrustes_linear_m < 1e-9 && m.procrustes_angular_rad < 1e-9
        );
        assert_eq!(m.within_predicted_p95, 1.0);
    }

    #[test]
    fn errors_are_measured_in_base1() {
        let truth = Iso3::identity();
        let wrong = perturb_left(&Vector6::new(0.0, 0.0, 0.0, 0.002, 0.0, 0.0), &truth);
        let touches: Vec<_> = (0..10)
            .map(|i| {
                (
                    Point3::new(i as f64 * 0.1, (i * i) as f64 * 0.01, 0.0),
                    Point3::new(i as f64 * 0.1, (i * i) as f64 * 0.01, 0.0),
                )
            })
            .collect();
        let m = verify_touches(&wrong, &(Matrix6::identity() * 1e-12), &touches, 0.0).unwrap();
        assert!((m.mean_m - 0.002).abs() < 1e-12);
        assert!((m.procrustes_linear_m - 0.002).abs() < 1e-9);
        assert_eq!(m.within_predicted_p95, 0.0);
    }

    #[test]
    fn predicted_p95_covers_95_percent_of_sampled_errors() {
        // An isotropic 1 mm translation covariance: |e| is Maxwell distributed,
        // whose 95th percentile is 2.795 sigma.
        let cov = Matrix6::from_diagonal(&Vector6::new(0.0, 0.0, 0.0, 1e-6, 1e-6, 1e-6));
        let (mean, p95) = predicted_error(&cov, &[Point3::origin()], 0.0);
        assert!((p95 - 2.795e-3).abs() < 0.1e-3, "{p95}");
        assert!((mean - 1.596e-3).abs() < 0.05e-3, "{mean}");
    }

    #[test]
    fn iso9283_matches_hand_computation() {
        let c = Point3::origin();
        let att = [Point3::new(0.001, 0.0, 0.0), Point3::new(0.003, 0.0, 0.0)];
        let r = iso9283(&c, &att).unwrap();
        assert!((r.accuracy_m - 0.002).abs() < 1e-15);
        // l = [0.001, 0.001], S = 0 -> RP = 0.001
        assert!((r.repeatability_m - 0.001).abs() < 1e-15);
        assert!(iso9283(&c, &att[..1]).is_err());
    }

    #[test]
    fn too_few_touches_is_an_error() {
        let t = vec![(Point3::origin(), Point3::origin()); 2];
        let e = verify_touches(&Iso3::identity(), &Matrix6::zeros(), &t, 0.0).unwrap_err();
        // Worded as touches, not captures.
        assert_eq!(e.to_string(), "too few touch pairs: 2, need at least 3");
    }
}
