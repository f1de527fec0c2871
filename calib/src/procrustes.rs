//! Procrustes / Umeyama alignment of point sets, and RANSAC over it.
//!
//! Used by touch-point verification (the transform fitted to the touch pairs is
//! the seed paper's ground truth) and by the RGB-D feature method (3-D matches
//! from depth, many of them wrong, hence RANSAC).

use nalgebra::{Matrix3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{SeedableRng, rngs::StdRng, seq::index::sample};

use crate::pose::nearest_rotation;
use crate::{CalibError, Iso3};

/// Rigid fit `a_from_b` minimising `Σ |a_i - a_from_b * b_i|²` (Umeyama without
/// scale). Needs at least 3 points that are not collinear.
pub fn fit_rigid(
    points_in_a: &[Point3<f64>],
    points_in_b: &[Point3<f64>],
) -> Result<Iso3, CalibError> {
    fit_weighted(points_in_a, points_in_b, None)
}

/// As [`fit_rigid`], with a weight per pair.
pub fn fit_weighted(
    points_in_a: &[Point3<f64>],
    points_in_b: &[Point3<f64>],
    weights: Option<&[f64]>,
) -> Result<Iso3, CalibError> {
    let n = points_in_a.len();
    if n != points_in_b.len() {
        return Err(CalibError::MismatchedLengths {
            len_a: n,
            what_a: "points in a",
            len_b: points_in_b.len(),
            what_b: "in b",
        });
    }
    if n < 3 {
        return Err(CalibError::TooFewCaptures { got: n, need: 3 });
    }
    if points_in_a
        .iter()
        .chain(points_in_b)
        .any(|p| !p.coords.iter().all(|v| v.is_finite()))
    {
        return Err(CalibError::NonFinite("point set".into()));
    }
    let w = |i: usize| weights.map_or(1.0, |w| w[i]);
    let wsum: f64 = (0..n).map(w).sum();
    if wsum <= 0.0 {
        return Err(CalibError::ZeroWeightSum);
    }
    let ca: Vector3<f64> = (0..n)
        .map(|i| points_in_a[i].coords * w(i))
        .sum::<Vector3<f64>>()
        / wsum;
    let cb: Vector3<f64> = (0..n)
        .map(|i| points_in_b[i].coords * w(i))
        .sum::<Vector3<f64>>()
        / wsum;
    let mut h = Matrix3::zeros();
    for i in 0..n {
        h += w(i) * (points_in_a[i].coords - ca) * (points_in_b[i].coords - cb).transpose();
    }
    // Collinear or coincident points leave a rotation about their line free.
    let sv = h.svd(false, false).singular_values;
    let mut s: Vec<f64> = sv.iter().copied().collect();
    s.sort_by(|a, b| b.total_cmp(a));
    if s[0] <= 1e-18 || s[1] <= 1e-9 * s[0] {
        return Err(CalibError::DegeneratePoints(
            "points are coincident or collinear".into(),
        ));
    }
    let r: UnitQuaternion<f64> = nearest_rotation(&h);
    let t = ca - r * cb;
    Ok(Iso3::from_parts(Translation3::from(t), r))
}

/// RANSAC settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacOptions {
    /// Inlier distance (m).
    pub threshold: f64,
    pub iterations: usize,
    /// Smallest consensus accepted.
    pub min_inliers: usize,
    pub seed: u64,
}

impl Default for RansacOptions {
    fn default() -> Self {
        RansacOptions {
            threshold: 0.005,
            iterations: 1000,
            min_inliers: 6,
            seed: 0,
        }
    }
}

/// A RANSAC fit: the model refitted on all inliers, and which pairs they are.
#[derive(Debug, Clone, PartialEq)]
pub struct RansacFit {
    pub a_from_b: Iso3,
    pub inliers: Vec<bool>,
    pub rms: f64,
}

/// Robust rigid fit: minimal 3-point samples, the largest consensus, refitted.
/// Deterministic for a seed.
pub fn ransac_rigid(
    points_in_a: &[Point3<f64>],
    points_in_b: &[Point3<f64>],
    options: &RansacOptions,
) -> Result<RansacFit, CalibError> {
    let n = points_in_a.len();
    if n != points_in_b.len() {
        return Err(CalibError::MismatchedLengths {
            len_a: n,
            what_a: "points in a",
            len_b: points_in_b.len(),
            what_b: "in b",
        });
    }
    if n < 3.max(options.min_inliers) {
        return Err(CalibError::TooFewCaptures {
            got: n,
            need: 3.max(options.min_inliers),
        });
    }
    let mut rng = StdRng::seed_from_u64(options.seed);
    let count = |m: &Iso3| -> Vec<bool> {
        (0..n)
            .map(|i| (points_in_a[i] - m * points_in_b[i]).norm() <= options.threshold)
            .collect()
    };
    let mut best: Option<Vec<bool>> = None;
    let mut best_n = 0;
    for _ in 0..options.iterations {
        let idx = sample(&mut rng, n, 3);
        let a: Vec<_> = idx.iter().map(|i| points_in_a[i]).collect();
        let b: Vec<_> = idx.iter().map(|i| points_in_b[i]).collect();
        let Ok(m) = fit_rigid(&a, &b) else { continue };
        let inl = count(&m);
        let k = inl.iter().filter(|v| **v).count();
        if k > best_n {
            best_n = k;
            best = Some(inl);
        }
    }
    let Some(mut inliers) = best.filter(|_| best_n >= options.min_inliers) else {
        return Err(CalibError::NoConsensus {
            best: best_n,
            total: n,
            need: options.min_inliers,
        });
    };
    // Refit on the consensus, then once more on the refit's consensus.
    let mut model = Iso3::identity();
    for _ in 0..2 {
        let a: Vec<_> = (0..n)
            .filter(|i| inliers[*i])
            .map(|i| points_in_a[i])
            .collect();
        let b: Vec<_> = (0..n)
            .filter(|i| inliers[*i])
            .map(|i| points_in_b[i])
            .collect();
        model = fit_rigid(&a, &b)?;
        let next = count(&model);
        if next.iter().filter(|v| **v).count() < options.min_inliers {
            break;
        }
        inliers = next;
    }
    let k = inliers.iter().filter(|v| **v).count() as f64;
    let rms = ((0..n)
        .filter(|i| inliers[*i])
        .map(|i| (points_in_a[i] - model * points_in_b[i]).norm_squared())
        .sum::<f64>()
        / k)
        .sqrt();
    Ok(RansacFit {
        a_from_b: model,
        inliers,
        rms,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pose::pose_distance;
    use crate::synth::random_pose;
    use rand::Rng;

    fn cloud(rng: &mut StdRng, n: usize) -> Vec<Point3<f64>> {
        (0..n)
            .map(|_| {
                Point3::new(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                )
            })
            .collect()
    }

    #[test]
    fn exact_fit_recovers_transform() {
        let mut rng = StdRng::seed_from_u64(1);
        let truth = random_pose(&mut rng, 3.0, 1.0);
        let b = cloud(&mut rng, 10);
        let a: Vec<_> = b.iter().map(|p| truth * p).collect();
        let fit = fit_rigid(&a, &b).unwrap();
        let (dt, da) = pose_distance(&fit, &truth);
        assert!(dt < 1e-12 && da < 1e-12);
    }

    #[test]
    fn collinear_points_are_degenerate() {
        let b: Vec<_> = (0..5).map(|i| Point3::new(i as f64, 0.0, 0.0)).collect();
        let err = fit_rigid(&b, &b).unwrap_err();
        assert!(matches!(err, CalibError::DegeneratePoints(_)));
    }

    #[test]
    fn ransac_survives_40_percent_outliers() {
        let mut rng = StdRng::seed_from_u64(2);
        let truth = random_pose(&mut rng, 3.0, 1.0);
        let b = cloud(&mut rng, 100);
        let mut a: Vec<_> = b
            .iter()
            .map(|p| truth * p + Vector3::new(0.0005, -0.0005, 0.0))
            .collect();
        for p in a.iter_mut().take(40) {
            *p += Vector3::new(
                rng.random_range(-0.2..0.2),
                rng.random_range(-0.2..0.2),
                0.1,
            );
        }
        let fit = ransac_rigid(&a, &b, &RansacOptions::default()).unwrap();
        let (dt, da) = pose_distance(&fit.a_from_b, &truth);
        assert!(dt < 1e-3 && da < 1e-3, "{dt} {da}");
        assert_eq!(fit.inliers.iter().filter(|v| **v).count(), 60);
        // A plain fit is ruined by the same outliers.
        let (dt_plain, _) = pose_distance(&fit_rigid(&a, &b).unwrap(), &truth);
        assert!(dt_plain > 10.0 * dt);
    }

    #[test]
    fn ransac_reports_no_consensus() {
        let mut rng = StdRng::seed_from_u64(3);
        let a = cloud(&mut rng, 30);
        let b = cloud(&mut rng, 30);
        let opts = RansacOptions {
            threshold: 1e-4,
            min_inliers: 10,
            ..Default::default()
        };
        assert!(matches!(
            ransac_rigid(&a, &b, &opts).unwrap_err(),
            CalibError::NoConsensus { .. }
        ));
    }
}
