//! Procrustes / Umeyama alignment of point sets, and RANSAC over it.
//!
//! Used by touch-point verification (the transform fitted to the touch pairs is
//! the seed paper's ground truth) and by the RGB-D feature method (3-D matches
//! from depth, many of them wrong, hence RANSAC).

use nalgebra::{Matrix3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{SeedableRng, rngs::StdRng, seq::index::sample};

use crate::pose::nearest_rotation_from_svd;
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
    check_finite(points_in_a, points_in_b)?;
    umeyama(points_in_a, points_in_b, weights)
}

fn check_finite(
    points_in_a: &[Point3<f64>],
    points_in_b: &[Point3<f64>],
) -> Result<(), CalibError> {
    if points_in_a
        .iter()
        .chain(points_in_b)
        .any(|p| !p.coords.iter().all(|v| v.is_finite()))
    {
        return Err(CalibError::NonFinite("point set".into()));
    }
    Ok(())
}

/// The weighted least-squares rigid fit of finite point sets of equal length.
fn umeyama(
    points_in_a: &[Point3<f64>],
    points_in_b: &[Point3<f64>],
    weights: Option<&[f64]>,
) -> Result<Iso3, CalibError> {
    let n = points_in_a.len();
    let w = |i: usize| weights.map_or(1.0, |w| w[i]);
    let (mut wsum, mut sa, mut sb) = (0.0, Vector3::zeros(), Vector3::zeros());
    for i in 0..n {
        let wi = w(i);
        wsum += wi;
        sa += points_in_a[i].coords * wi;
        sb += points_in_b[i].coords * wi;
    }
    if wsum <= 0.0 {
        return Err(CalibError::ZeroWeightSum);
    }
    let (ca, cb): (Vector3<f64>, Vector3<f64>) = (sa / wsum, sb / wsum);
    let mut h = Matrix3::zeros();
    for i in 0..n {
        h += w(i) * (points_in_a[i].coords - ca) * (points_in_b[i].coords - cb).transpose();
    }
    // Collinear or coincident points leave a rotation about their line free.
    let svd = h.svd(true, true);
    let mut s: Vec<f64> = svd.singular_values.iter().copied().collect();
    s.sort_by(|a, b| b.total_cmp(a));
    if s[0] <= 1e-18 || s[1] <= 1e-9 * s[0] {
        return Err(CalibError::DegeneratePoints(
            "points are coincident or collinear".into(),
        ));
    }
    // The rotation nearest `h`, from the same SVD.
    let r: UnitQuaternion<f64> = nearest_rotation_from_svd(&svd.u, &svd.v_t);
    let t = ca - r * cb;
    Ok(Iso3::from_parts(Translation3::from(t), r))
}

/// RANSAC settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacOptions {
    /// Inlier distance (m).
    pub threshold: f64,
    /// The most samples drawn.
    pub iterations: usize,
    /// Smallest consensus accepted.
    pub min_inliers: usize,
    pub seed: u64,
    /// Sampling stops once an all-inlier sample has been drawn with this
    /// probability, judged by the best consensus so far (the usual adaptive
    /// count `ln(1 - p) / ln(1 - w³)` for inlier share `w`); 1 draws all
    /// `iterations`.
    pub confidence: f64,
}

impl Default for RansacOptions {
    fn default() -> Self {
        RansacOptions {
            threshold: 0.005,
            iterations: 1000,
            min_inliers: 6,
            seed: 0,
            confidence: 0.9999,
        }
    }
}

/// Samples of three needed to draw one of inliers only with probability
/// `confidence`, when a share `w` of the pairs are inliers.
fn samples_needed(w: f64, confidence: f64, most: usize) -> usize {
    let all_inliers = w.clamp(0.0, 1.0).powi(3);
    if confidence >= 1.0 || all_inliers <= 0.0 {
        return most;
    }
    if all_inliers >= 1.0 {
        return 1;
    }
    let n = (1.0 - confidence).ln() / (1.0 - all_inliers).ln();
    if n.is_finite() {
        (n.ceil().max(1.0) as usize).min(most)
    } else {
        most
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
    check_finite(points_in_a, points_in_b)?;
    let mut rng = StdRng::seed_from_u64(options.seed);
    // Squared residuals under a model, through its rotation matrix (cheaper
    // per point than the quaternion).
    let residuals2 = |m: &Iso3| {
        let r = m.rotation.to_rotation_matrix().into_inner();
        let t = m.translation.vector;
        (0..n)
            .map(move |i| (points_in_a[i].coords - (r * points_in_b[i].coords + t)).norm_squared())
    };
    let threshold2 = options.threshold * options.threshold;
    // Which pairs are inliers under a model, and their squared residuals' sum.
    let count = |m: &Iso3| -> (Vec<bool>, f64) {
        residuals2(m).fold((Vec::with_capacity(n), 0.0), |(mut mask, sum), e| {
            let inlier = e <= threshold2;
            mask.push(inlier);
            (mask, if inlier { sum + e } else { sum })
        })
    };
    let consensus = |m: &Iso3| -> usize { residuals2(m).filter(|e| *e <= threshold2).count() };
    let mut best: Option<Iso3> = None;
    let mut best_n = 0;
    let mut needed = options.iterations;
    let mut drawn = 0;
    while drawn < needed {
        drawn += 1;
        let idx = sample(&mut rng, n, 3);
        let a: Vec<_> = idx.iter().map(|i| points_in_a[i]).collect();
        let b: Vec<_> = idx.iter().map(|i| points_in_b[i]).collect();
        let Ok(m) = umeyama(&a, &b, None) else {
            continue;
        };
        let k = consensus(&m);
        if k > best_n {
            best_n = k;
            best = Some(m);
            needed = samples_needed(k as f64 / n as f64, options.confidence, options.iterations);
        }
    }
    let Some(mut inliers) = best
        .filter(|_| best_n >= options.min_inliers)
        .map(|m| count(&m).0)
    else {
        return Err(CalibError::NoConsensus {
            best: best_n,
            total: n,
            need: options.min_inliers,
        });
    };
    // Refit on the consensus, then once more on the refit's consensus.
    let mut model = Iso3::identity();
    // The inliers' squared residuals under `model`, once known.
    let mut sse = None;
    for _ in 0..2 {
        let weights: Vec<f64> = inliers.iter().map(|&k| f64::from(u8::from(k))).collect();
        model = umeyama(points_in_a, points_in_b, Some(&weights))?;
        let (next, next_sse) = count(&model);
        if next.iter().filter(|v| **v).count() < options.min_inliers {
            break;
        }
        // The same consensus again: a refit on it gives the same model.
        let settled = next == inliers;
        inliers = next;
        if settled {
            sse = Some(next_sse);
            break;
        }
    }
    let k = inliers.iter().filter(|v| **v).count() as f64;
    let sse = sse.unwrap_or_else(|| {
        residuals2(&model)
            .zip(&inliers)
            .filter(|(_, k)| **k)
            .map(|(e, _)| e)
            .sum::<f64>()
    });
    let rms = (sse / k).sqrt();
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

    /// The adaptive count: one sample when all pairs agree, the textbook
    /// count for half of them (ln 0.01 / ln 0.875 = 34.5 at 99%), and the cap
    /// when nothing agrees or every sample is asked for.
    #[test]
    fn samples_needed_follows_the_inlier_share() {
        assert_eq!(samples_needed(1.0, 0.9999, 2000), 1);
        assert_eq!(samples_needed(0.5, 0.99, 2000), 35);
        assert_eq!(samples_needed(0.1, 0.9999, 2000), 2000);
        assert_eq!(samples_needed(0.0, 0.9999, 2000), 2000);
        assert_eq!(samples_needed(0.5, 1.0, 2000), 2000);
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
