//! Choosing the estimator by the data's own evidence: cross-validation over
//! captures.
//!
//! No estimator is best on every arm. Inside a rendered world whose robot
//! errors have the shapes the noise model knows, the joint refinement sits near
//! the maximum-likelihood limit; on a real arm whose error is systematic, a
//! closed form sometimes cancels more of it. The user has no ground truth, and
//! neither does the estimator, but the captures are evidence: fit a candidate
//! without some of them and see how well it predicts the ones left out.
//!
//! [`cross_validate`]: every robot's captures are cut into [`FOLDS`] folds of
//! consecutive captures (a robot's captures are taken along a path, so a fold
//! is a region of the working volume and what is systematic there shows in it);
//! for each fold every [`CANDIDATES`] entry is fitted to the other folds of
//! every robot and predicts the held-out captures' corners
//! (`camera_from_target = (ref_from_base · base_from_flange · flange_from_camera)⁻¹
//! · ref_from_target`, projected by the candidate's camera). The candidate whose
//! held-out corners lie nearest (RMS px) is chosen. Park's closed form is
//! always a candidate, so the choice is never worse than Park on this evidence.
//!
//! The folds also give the bound its evidence ([`Selection::spread_scale`]):
//! the fits without each fold scatter about the full fit by what leaving those
//! captures out changes, `m / (n - m)` times the estimate's own covariance when
//! that covariance is right (`m` of `n` captures held out). The chosen
//! estimate's covariance is scaled to that scatter, down as well as up: a
//! model's covariance widened by checks for what it cannot model (see
//! [`crate::estimate`]) can be far wider than the error, and a bound four times
//! the error is no use to a surgeon.
//!
//! The scatter is evidence only where each fold's fit is far from the fewest
//! captures a hand-eye needs (three: two motions). Near that minimum the fits
//! without a fold are no longer linear in the captures and scatter far more
//! than the estimate errs: with Gaussian noise of the model's own shape, where
//! the model's covariance is right by construction (the error's mean χ² 6.3 on
//! 6 dof), folds keeping 3 captures per robot scatter 5.1x the covariance
//! (median over 30 problems), folds keeping 12 0.95x
//! (`calib/tests/spread_scale.rs` asserts both). The scale is applied only where
//! every fold's fit kept [`MIN_TRAINING_FOR_SCALE`] captures per robot; below,
//! the model's covariance stands and the scatter is reported, not applied.
//!
//! The folds cannot see an error common to all of a robot's captures, and the
//! candidates the held-out evidence cannot tell apart (within [`MARGIN`] of the
//! chosen one's figure) can still put the bases far apart: on a real Denso arm
//! split into its first and last 44 captures, the refinement's four noise
//! shapes predict the held-out corners within 1% of each other (1.646 to
//! 1.661 px) while their bases differ by millimetres. Which of them
//! is right the data do not say, so the estimate is their mean and the bound
//! holds their spread about it ([`Selection::agreement`]): with `δ_i` the mean
//! over the folds of each agreeing candidate's fit less the chosen one's (the
//! chosen one counted with `δ = 0`), the bases move by `δ̄ = Σ δ_i / (|S| + 1)`
//! and the covariance gains `Σ (δ_i - δ̄)(δ_i - δ̄)ᵀ / (|S| + 1)`. Choosing one
//! of candidates the evidence cannot rank is a draw; their mean is the estimate
//! whose expected error over the draw is least. Where the models agree (a
//! rendered world the noise model knows) both are a fraction of the
//! covariance; on that Denso split the mean is 11.9 mm from the truth and the
//! bound 1.09x the true p95 (`pipeline/tests/real_splits.rs`). Both are
//! applied where the scale is.

use nalgebra::{DMatrix, DVector};

use crate::base_to_base::{BasesEstimate, BasesInitial, evaluate_bases, refine_bases};
use crate::camera::CameraModel;
use crate::estimate::{
    BasesRun, RobotCaptures, common_mode, estimate_bases, kept, link_seeds, seed_robot,
};
use crate::handeye::{self, HandEyeMethod, RobotWorldMethod};
use crate::refine::{BoardCapture, NoiseFrame, NoiseModel, NoiseShape, RefineOptions, RobotNoise};
use crate::{CalibError, Iso3};

/// One way to estimate the bases.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Candidate {
    /// The joint reprojection refinement, the robots' pose noise estimated
    /// in this shape; `None`: in the shape the likelihood chooses per robot
    /// (BIC), the estimator's default.
    Refined(Option<NoiseShape>),
    /// A closed-form hand-eye per robot, then the board's pose in its base by
    /// least squares; the bases from the board poses.
    HandEye(HandEyeMethod),
    /// A closed-form robot-world hand-eye per robot.
    RobotWorld(RobotWorldMethod),
}

impl Candidate {
    /// The name in reports: `refined/<shape>` or the closed form's.
    pub fn name(&self) -> String {
        match self {
            Candidate::Refined(None) => "refined".to_owned(),
            Candidate::Refined(Some(shape)) => format!("refined/{}", shape_key(shape)),
            Candidate::HandEye(m) => m.name().to_owned(),
            Candidate::RobotWorld(m) => m.name().to_owned(),
        }
    }

    pub fn is_refined(&self) -> bool {
        matches!(self, Candidate::Refined(_))
    }
}

fn shape_key(shape: &NoiseShape) -> &'static str {
    match shape {
        NoiseShape::Isotropic(NoiseFrame::Base) => "base",
        NoiseShape::Isotropic(NoiseFrame::Flange) => "flange",
        NoiseShape::TwoCentres => "two-centres",
        NoiseShape::Given => "given",
    }
}

/// The candidates; the first is the default, which another must beat by
/// [`MARGIN`] to be chosen.
pub const CANDIDATES: [Candidate; 9] = [
    Candidate::Refined(None),
    Candidate::Refined(Some(NoiseShape::TwoCentres)),
    Candidate::Refined(Some(NoiseShape::Isotropic(NoiseFrame::Base))),
    Candidate::Refined(Some(NoiseShape::Isotropic(NoiseFrame::Flange))),
    Candidate::HandEye(HandEyeMethod::Park),
    Candidate::HandEye(HandEyeMethod::Tsai),
    Candidate::HandEye(HandEyeMethod::Daniilidis),
    Candidate::RobotWorld(RobotWorldMethod::Shah),
    Candidate::RobotWorld(RobotWorldMethod::Li),
];

/// How much nearer (relative) another candidate's held-out corners must lie
/// than the default's for it to be chosen: fold-to-fold noise moves candidates
/// that model the data alike by a percent or two (on the rendered sets the
/// refined shapes and Shah lie within 2% of each other), and the default is
/// the one the error study holds near the maximum-likelihood limit.
pub const MARGIN: f64 = 0.05;

/// Folds per robot.
pub const FOLDS: usize = 5;

/// Fewest captures per robot cross-validation runs on: every fold's fit keeps
/// at least three per robot.
pub const MIN_CAPTURES_TO_SELECT: usize = 4;

/// Fewest captures per robot every fold's fit must keep for the folds'
/// scatter to scale the covariance (see the module's documentation).
pub const MIN_TRAINING_FOR_SCALE: usize = 8;

/// A held-out corner that projects behind the camera counts as this far (px).
const BEHIND_CAMERA_PX: f64 = 1000.0;

/// A candidate's fit: what it needs to predict a capture.
#[derive(Debug, Clone)]
struct Model {
    /// Per robot, `ref_from_base` (the identity for the reference).
    bases: Vec<Iso3>,
    flange_from_camera: Vec<Iso3>,
    ref_from_target: Iso3,
    cameras: Vec<CameraModel>,
}

impl Model {
    fn from_estimate(e: &BasesEstimate) -> Model {
        Model {
            bases: (0..e.robots()).map(|r| e.base(r)).collect(),
            flange_from_camera: e.flange_from_camera.clone(),
            ref_from_target: e.ref_from_targets[0],
            cameras: e.cameras.clone(),
        }
    }

    /// Squared pixel errors summed over `capture`'s corners, and their count.
    fn predict(&self, robot: usize, capture: &BoardCapture) -> (f64, usize) {
        let camera_from_target =
            (self.bases[robot] * capture.base_from_flange * self.flange_from_camera[robot])
                .inverse()
                * self.ref_from_target;
        let sum = capture
            .target_points
            .iter()
            .zip(&capture.pixels)
            .map(|(p, uv)| {
                self.cameras[robot]
                    .project(&(camera_from_target * p))
                    .map_or(BEHIND_CAMERA_PX * BEHIND_CAMERA_PX, |q| {
                        (q - uv).norm_squared()
                    })
            })
            .sum();
        (sum, capture.pixels.len())
    }
}

/// One robot's captures with their PnP poses (owned), for a fold's fit.
type Owned = (Vec<BoardCapture>, Vec<Iso3>);

/// The closed form's bases: each robot's board pose, robot 0's the reference.
fn fit_closed(
    candidate: Candidate,
    robots: &[Owned],
    cameras: &[&CameraModel],
    options: &RefineOptions,
) -> Result<Model, CalibError> {
    let mut hand_eyes = Vec::with_capacity(robots.len());
    let mut boards = Vec::with_capacity(robots.len());
    for (caps, poses) in robots {
        let b: Vec<Iso3> = caps.iter().map(|c| c.base_from_flange).collect();
        let (x, w) = match candidate {
            Candidate::HandEye(m) => {
                let x = handeye::hand_eye_with(&b, poses, m, &options.motion)?;
                (x, handeye::base_from_target_given(&x, &b, poses)?)
            }
            Candidate::RobotWorld(m) => {
                let rw = handeye::robot_world_with(&b, poses, m, &options.motion)?;
                (rw.flange_from_camera, rw.base_from_target)
            }
            Candidate::Refined(_) => unreachable!("a refined candidate is no closed form"),
        };
        hand_eyes.push(x);
        boards.push(w);
    }
    Ok(Model {
        bases: boards.iter().map(|w| boards[0] * w.inverse()).collect(),
        flange_from_camera: hand_eyes,
        ref_from_target: boards[0],
        cameras: cameras.iter().map(|c| (*c).clone()).collect(),
    })
}

/// The seeds (Park with the gross-row screen) every refined candidate of a
/// fold starts from, and the captures they kept.
fn seeds(
    robots: &[Owned],
    cameras: &[&CameraModel],
    options: &RefineOptions,
) -> Result<(BasesInitial, Vec<Vec<BoardCapture>>), CalibError> {
    let seeds = robots
        .iter()
        .zip(cameras)
        .map(|((caps, poses), camera)| {
            seed_robot(
                &RobotCaptures {
                    camera,
                    captures: caps,
                    camera_from_target: poses,
                },
                1,
                options,
            )
        })
        .collect::<Result<Vec<_>, _>>()?;
    let initial = link_seeds(&seeds, 1)?;
    let kept_captures = robots
        .iter()
        .zip(&seeds)
        .map(|((caps, _), s)| kept(caps, &s.rejections))
        .collect();
    Ok((initial, kept_captures))
}

/// The options of a refined candidate: its shape, no spread (a fold's fit
/// needs the estimate only).
fn shape_options(options: &RefineOptions, shape: Option<NoiseShape>) -> RefineOptions {
    match shape {
        Some(shape) => RefineOptions {
            noise: NoiseModel::EstimatedShape(shape),
            ..options.clone()
        },
        None => options.clone(),
    }
}

fn fit_refined(
    shape: Option<NoiseShape>,
    initial: &BasesInitial,
    captures: &[Vec<BoardCapture>],
    cameras: &[&CameraModel],
    options: &RefineOptions,
) -> Result<BasesEstimate, CalibError> {
    let slices: Vec<&[BoardCapture]> = captures.iter().map(Vec::as_slice).collect();
    let opts = RefineOptions {
        widen_to_spread: false,
        ..shape_options(options, shape)
    };
    refine_bases(cameras, &slices, initial, &opts)
}

/// What cross-validation found.
#[derive(Debug, Clone)]
pub struct Selection {
    pub chosen: Candidate,
    /// Per candidate ([`CANDIDATES`] order): the RMS (px) of the held-out
    /// captures' corners about where its fits without them put them; `None`
    /// where a fold's fit failed.
    pub held_out_px: Vec<(Candidate, Option<f64>)>,
    pub folds: usize,
    /// Per candidate, per fold: the bases (robots 1..N) fitted without it.
    fold_bases: Vec<Vec<Option<Vec<Iso3>>>>,
    /// Per fold, the captures it held out (all robots).
    held: Vec<usize>,
    /// Captures in all.
    total: usize,
    /// The fewest captures a robot kept in a fold's fit.
    pub min_training: usize,
}

impl Selection {
    /// The held-out figure of `candidate`.
    pub fn held_out(&self, candidate: Candidate) -> Option<f64> {
        self.held_out_px
            .iter()
            .find(|(c, _)| *c == candidate)
            .and_then(|(_, v)| *v)
    }

    /// The factor that makes `covariance` (of the bases `ref_from_base`,
    /// robots 1..N, estimated by the chosen candidate on all captures) hold the
    /// folds' scatter: `Σ_k (n - m_k)/m_k · δ_kᵀ C⁻¹ δ_k / (K · dim)`, with
    /// `δ_k` the bases fitted without fold `k` less the full fit's. About 1
    /// when the covariance is right; `None` when a fold's fit failed or the
    /// covariance is singular.
    pub fn spread_scale(&self, ref_from_base: &[Iso3], covariance: &DMatrix<f64>) -> Option<f64> {
        let k = self
            .held_out_px
            .iter()
            .position(|(c, _)| *c == self.chosen)?;
        let dim = 6 * ref_from_base.len();
        if covariance.nrows() != dim {
            return None;
        }
        let chol = covariance.clone().cholesky()?;
        let mut sum = 0.0;
        for (fold, bases) in self.fold_bases[k].iter().enumerate() {
            let d = stacked_difference(bases.as_ref()?, ref_from_base);
            let m = self.held[fold] as f64;
            let w = (self.total as f64 - m) / m.max(1.0);
            sum += w * d.dot(&chol.solve(&d));
        }
        let s = sum / (self.fold_bases[k].len() * dim) as f64;
        s.is_finite().then_some(s)
    }

    /// The candidates whose held-out figure lies within [`MARGIN`] of the
    /// chosen one's (the chosen one excluded), their mean and their spread (see
    /// the module's documentation). With `δ_i` the mean over the folds of a
    /// candidate's bases less the chosen one's (stacked left differences,
    /// robots 1..N; the chosen one's `δ = 0`), the mean is
    /// `δ̄ = Σ δ_i / (|S| + 1)` and the spread about it
    /// `Σ (δ_i - δ̄)(δ_i - δ̄)ᵀ / (|S| + 1)`, the chosen one counted in both.
    /// `None` when the chosen candidate's fold fits are missing; a candidate
    /// whose fit failed on a fold is left out.
    pub fn agreement(&self) -> Option<Agreement> {
        let kc = CANDIDATES.iter().position(|c| *c == self.chosen)?;
        let chosen = self.held_out(self.chosen)?;
        let folds_of = |k: usize| -> Option<Vec<&Vec<Iso3>>> {
            self.fold_bases[k].iter().map(Option::as_ref).collect()
        };
        let chosen_folds = folds_of(kc)?;
        let dim = 6 * chosen_folds.first()?.len();
        let mut deltas = Vec::new();
        let mut members = Vec::new();
        for (k, (candidate, figure)) in self.held_out_px.iter().enumerate() {
            if k == kc || figure.is_none_or(|v| v > chosen * (1.0 + MARGIN)) {
                continue;
            }
            let Some(folds) = folds_of(k) else {
                continue;
            };
            deltas.push(
                folds
                    .iter()
                    .zip(&chosen_folds)
                    .map(|(bases, chosen_bases)| stacked_difference(bases, chosen_bases))
                    .fold(DVector::zeros(dim), |a, d| a + d)
                    / folds.len() as f64,
            );
            members.push(*candidate);
        }
        let n = (members.len() + 1) as f64;
        let mean = deltas.iter().fold(DVector::zeros(dim), |a, d| a + d) / n;
        // The chosen one's δ = 0 lies -δ̄ from the mean.
        let mut spread = &mean * mean.transpose();
        for d in &deltas {
            let e = d - &mean;
            spread += &e * e.transpose();
        }
        Some(Agreement {
            members,
            mean,
            spread: spread / n,
        })
    }
}

/// The candidates the held-out evidence cannot tell from the chosen one
/// ([`Selection::agreement`]).
#[derive(Debug, Clone)]
pub struct Agreement {
    pub members: Vec<Candidate>,
    /// Their bases' mean, the chosen one's included, less the chosen one's
    /// (stacked left perturbations, robots 1..N).
    pub mean: DVector<f64>,
    /// Their spread about that mean (a covariance of the bases).
    pub spread: DMatrix<f64>,
}

/// The left differences of `a` from `b`, robot by robot, stacked (6 rows per
/// robot of `b`).
fn stacked_difference(a: &[Iso3], b: &[Iso3]) -> DVector<f64> {
    let mut d = DVector::zeros(6 * b.len());
    for (r, (x, y)) in a.iter().zip(b).enumerate() {
        d.rows_mut(6 * r, 6)
            .copy_from(&crate::pose::left_difference(x, y));
    }
    d
}

/// Cross-validates [`CANDIDATES`] on the robots' captures; `None` when the
/// problem has several targets or a robot fewer than
/// [`MIN_CAPTURES_TO_SELECT`] captures.
pub fn cross_validate(
    robots: &[&RobotCaptures<'_>],
    options: &RefineOptions,
    folds: usize,
) -> Option<Selection> {
    cross_validate_with(robots, robots, options, folds)
}

/// [`cross_validate`] with the closed forms given their own cameras and
/// poses (`closed`: the same captures of the same robots, in the same order).
/// Where the intrinsics are estimated, the refinement refines them while a
/// closed form takes the PnP poses as they are: from the first estimate they
/// would handicap the closed forms against the refinement, so the caller gives
/// them the jointly refined cameras and the poses fitted with those
/// ([`estimate_bases_selected_with`]). Captures that differ are an error of
/// the caller's: `None`.
pub fn cross_validate_with(
    robots: &[&RobotCaptures<'_>],
    closed: &[&RobotCaptures<'_>],
    options: &RefineOptions,
    folds: usize,
) -> Option<Selection> {
    if closed.len() != robots.len()
        || closed.iter().zip(robots).any(|(c, r)| {
            c.captures.len() != r.captures.len() || c.camera_from_target.len() != r.captures.len()
        })
    {
        return None;
    }
    if robots.len() < 2
        || robots.iter().any(|r| {
            r.captures.len() < MIN_CAPTURES_TO_SELECT || r.captures.iter().any(|c| c.target != 0)
        })
    {
        return None;
    }
    let smallest = robots.iter().map(|r| r.captures.len()).min()?;
    let folds = folds.min(smallest).max(2);
    let cameras: Vec<&CameraModel> = robots.iter().map(|r| r.camera).collect();
    let closed_cameras: Vec<&CameraModel> = closed.iter().map(|r| r.camera).collect();
    // Consecutive captures per fold.
    let fold_of = |i: usize, n: usize| i * folds / n;
    let mut sums = vec![(0.0, 0usize, true); CANDIDATES.len()];
    let mut fold_bases = vec![Vec::with_capacity(folds); CANDIDATES.len()];
    let mut held = Vec::with_capacity(folds);
    let mut min_training = usize::MAX;
    for fold in 0..folds {
        let split = |r: &RobotCaptures<'_>, inside: bool| -> Owned {
            let n = r.captures.len();
            (0..n)
                .filter(|i| (fold_of(*i, n) == fold) != inside)
                .map(|i| (r.captures[i].clone(), r.camera_from_target[i]))
                .unzip()
        };
        let training: Vec<Owned> = robots.iter().map(|r| split(r, true)).collect();
        let closed_training: Vec<Owned> = closed.iter().map(|r| split(r, true)).collect();
        let test: Vec<Owned> = robots.iter().map(|r| split(r, false)).collect();
        held.push(test.iter().map(|t| t.0.len()).sum());
        min_training = training
            .iter()
            .map(|t| t.0.len())
            .min()
            .unwrap_or(0)
            .min(min_training);
        let seeded = seeds(&training, &cameras, options);
        for (k, candidate) in CANDIDATES.iter().enumerate() {
            let model = match candidate {
                Candidate::Refined(shape) => match &seeded {
                    Ok((initial, caps)) => fit_refined(*shape, initial, caps, &cameras, options)
                        .map(|e| Model::from_estimate(&e)),
                    Err(e) => Err(e.clone()),
                },
                _ => fit_closed(*candidate, &closed_training, &closed_cameras, options),
            };
            let Ok(model) = model else {
                sums[k].2 = false;
                fold_bases[k].push(None);
                continue;
            };
            for (r, (caps, _)) in test.iter().enumerate() {
                for c in caps {
                    let (s, n) = model.predict(r, c);
                    sums[k].0 += s;
                    sums[k].1 += n;
                }
            }
            fold_bases[k].push(Some(model.bases[1..].to_vec()));
        }
    }
    let held_out_px: Vec<(Candidate, Option<f64>)> = CANDIDATES
        .iter()
        .zip(&sums)
        .map(|(c, (s, n, ok))| (*c, (*ok && *n > 0).then(|| (s / *n as f64).sqrt())))
        .collect();
    let chosen = choose(&held_out_px)?;
    Some(Selection {
        chosen,
        held_out_px,
        folds,
        fold_bases,
        held,
        total: robots.iter().map(|r| r.captures.len()).sum(),
        min_training,
    })
}

/// The default ([`CANDIDATES`]' first) unless another candidate's held-out
/// figure is below it by more than [`MARGIN`]: then the best one. Never one
/// whose figure is above Park's.
fn choose(held_out: &[(Candidate, Option<f64>)]) -> Option<Candidate> {
    let best = held_out
        .iter()
        .filter_map(|(c, v)| v.map(|v| (*c, v)))
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    let park = held_out
        .iter()
        .find(|(c, _)| *c == Candidate::HandEye(HandEyeMethod::Park))
        .and_then(|(_, v)| *v);
    match held_out[0] {
        (default, Some(v)) if best.1 >= v * (1.0 - MARGIN) && park.is_none_or(|p| v <= p) => {
            Some(default)
        }
        _ => Some(best.0),
    }
}

/// The bases by the chosen estimator, with what chose it.
#[derive(Debug, Clone)]
pub struct SelectedRun {
    pub run: BasesRun,
    /// `None` when the problem was not cross-validated (several targets, too
    /// few captures, or a noise model given rather than estimated): `run` is
    /// then [`estimate_bases`]'s.
    pub selection: Option<Selection>,
    /// The factor the chosen estimate's covariance was scaled by to hold the
    /// folds' scatter ([`Selection::spread_scale`]); `None` where it was not
    /// applied.
    pub spread_scale: Option<f64>,
    /// The folds' scatter over what the chosen estimate's covariance predicts
    /// ([`Selection::spread_scale`]), applied or not: not where a fold's fit
    /// kept fewer than [`MIN_TRAINING_FOR_SCALE`] captures of a robot.
    pub fold_scatter: Option<f64>,
    /// The candidates the held-out evidence could not tell from the chosen
    /// one: the bases are their mean with the chosen one's, and their spread
    /// about it was added to the covariance ([`Selection::agreement`]); empty
    /// where none agreed or the spread was not applied (as the scale).
    pub agreeing: Vec<Candidate>,
}

/// The default estimator with the choice made by cross-validation: the
/// refinement in the shape that predicts held-out captures best, or a closed
/// form when one predicts them better; its covariance scaled to the folds'
/// scatter.
pub fn estimate_bases_selected(
    robots: &[&RobotCaptures<'_>],
    options: &RefineOptions,
) -> Result<SelectedRun, CalibError> {
    estimate_bases_selected_with(robots, robots, options)
}

/// [`estimate_bases_selected`] with the closed forms on their own cameras and
/// poses (see [`cross_validate_with`]); a closed form chosen is run on them.
pub fn estimate_bases_selected_with(
    robots: &[&RobotCaptures<'_>],
    closed: &[&RobotCaptures<'_>],
    options: &RefineOptions,
) -> Result<SelectedRun, CalibError> {
    let selection = match options.noise {
        NoiseModel::Estimated => cross_validate_with(robots, closed, options, FOLDS),
        _ => None,
    };
    let Some(selection) = selection else {
        return Ok(SelectedRun {
            run: estimate_bases(robots, options)?,
            selection: None,
            spread_scale: None,
            fold_scatter: None,
            agreeing: Vec::new(),
        });
    };
    // The configured systematic error shows in no scatter: it is added after
    // the scaling.
    let zero = RobotNoise {
        sigma_t_m: 0.0,
        sigma_r_rad: 0.0,
    };
    let inner = RefineOptions {
        systematic: zero,
        ..options.clone()
    };
    let mut run = match selection.chosen {
        Candidate::Refined(shape) => estimate_bases(robots, &shape_options(&inner, shape))?,
        form => closed_form_run(closed, form, &inner)?,
    };
    let fold_scatter =
        selection.spread_scale(&run.estimate.ref_from_base, &run.estimate.covariance);
    let spread_scale = fold_scatter.filter(|_| selection.min_training >= MIN_TRAINING_FOR_SCALE);
    let mut agreeing = Vec::new();
    if let Some(s) = spread_scale {
        run.estimate.covariance *= s;
        if let Some(agreement) = selection.agreement()
            && agreement.spread.shape() == run.estimate.covariance.shape()
        {
            // The data cannot say which of them is right: the estimate is their
            // mean, and its covariance holds their spread about it.
            for (r, base) in run.estimate.ref_from_base.iter_mut().enumerate() {
                let d =
                    nalgebra::Vector6::from_iterator(agreement.mean.rows(6 * r, 6).iter().copied());
                *base = crate::pose::perturb_left(&d, base);
            }
            run.estimate.covariance += agreement.spread;
            agreeing = agreement.members;
        }
    }
    let used: Vec<Vec<BoardCapture>> = robots
        .iter()
        .zip(&run.rejections)
        .map(|(r, rej)| kept(r.captures, rej))
        .collect();
    let used: Vec<&[BoardCapture]> = used.iter().map(Vec::as_slice).collect();
    run.estimate.covariance += common_mode(&run.estimate, &used, &options.systematic);
    Ok(SelectedRun {
        run,
        selection: Some(selection),
        spread_scale,
        fold_scatter,
        agreeing,
    })
}

/// A closed form on every capture, the joint problem evaluated there (its
/// covariance, noise and per-capture fit); nothing is left out.
fn closed_form_run(
    robots: &[&RobotCaptures<'_>],
    candidate: Candidate,
    options: &RefineOptions,
) -> Result<BasesRun, CalibError> {
    let owned: Vec<Owned> = robots
        .iter()
        .map(|r| (r.captures.to_vec(), r.camera_from_target.to_vec()))
        .collect();
    let cameras: Vec<&CameraModel> = robots.iter().map(|r| r.camera).collect();
    let model = fit_closed(candidate, &owned, &cameras, options)?;
    let initial = BasesInitial {
        flange_from_camera: model.flange_from_camera.clone(),
        ref_from_targets: vec![model.ref_from_target],
        ref_from_base: model.bases[1..].to_vec(),
    };
    let slices: Vec<&[BoardCapture]> = robots.iter().map(|r| r.captures).collect();
    let opts = RefineOptions {
        widen_to_spread: false,
        ..options.clone()
    };
    let mut estimate = evaluate_bases(&cameras, &slices, &initial, &opts)?;
    // The closed form's own poses and cameras (the evaluation moves nothing,
    // but its reference poses are the ones given).
    estimate.ref_from_base = initial.ref_from_base;
    Ok(BasesRun {
        rejections: robots
            .iter()
            .map(|r| vec![None; r.captures.len()])
            .collect(),
        splits: vec![None; robots.len() - 1],
        estimate,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn base(x: f64) -> Vec<Iso3> {
        vec![Iso3::from_parts(
            Translation3::new(1.0 + x, 0.5, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
        )]
    }

    /// Three candidates: the chosen one, one within the margin whose fold fits
    /// sit 2 mm and 4 mm along x from the chosen one's (mean 3 mm), and one
    /// beyond the margin whose fits are far off.
    fn selection() -> Selection {
        let figures = [1.0, 1.04, 1.2];
        let offsets = [[0.0, 0.0], [0.002, 0.004], [0.05, 0.05]];
        let mut held_out_px = Vec::new();
        let mut fold_bases = Vec::new();
        for (k, c) in CANDIDATES.iter().enumerate() {
            let (figure, bases) = match k {
                0..=2 => (
                    Some(figures[k]),
                    offsets[k].iter().map(|x| Some(base(*x))).collect(),
                ),
                _ => (None, vec![None, None]),
            };
            held_out_px.push((*c, figure));
            fold_bases.push(bases);
        }
        Selection {
            chosen: CANDIDATES[0],
            held_out_px,
            folds: 2,
            fold_bases,
            held: vec![10, 10],
            total: 20,
            min_training: 10,
        }
    }

    #[test]
    fn the_agreeing_candidates_mean_and_spread_about_it() {
        let a = selection().agreement().unwrap();
        assert_eq!(a.members, vec![CANDIDATES[1]]);
        // δ = 3 mm along x for the member, 0 for the chosen one: the mean is
        // 1.5 mm, the spread (1.5 mm)² along x and nothing else.
        assert!((a.mean[3] - 0.0015).abs() < 1e-12, "{}", a.mean);
        assert!(
            a.mean
                .iter()
                .enumerate()
                .all(|(i, v)| i == 3 || v.abs() < 1e-12)
        );
        assert!((a.spread[(3, 3)] - 0.0015f64.powi(2)).abs() < 1e-15);
        assert!((a.spread.sum() - a.spread[(3, 3)]).abs() < 1e-15);
    }

    #[test]
    fn no_agreeing_candidate_leaves_the_chosen_estimate() {
        let mut s = selection();
        s.held_out_px[1].1 = Some(1.2);
        let a = s.agreement().unwrap();
        assert!(a.members.is_empty());
        assert_eq!(a.mean.norm(), 0.0);
        assert_eq!(a.spread.norm(), 0.0);
    }
}
