//! The calibration pipeline: from captures to results.
//!
//! The agent and the coordinator are thin binaries; what they compute lives here so
//! that an offline run on a dataset (`coordinator calibrate`, `agent handeye`) and
//! the live services go through the same code. The stages:
//!
//! 1. [`observe_robot`]: per capture, detect the target (vision crate: checkerboard,
//!    ChArUco, ArUco grid or multimarker, the one [`b2b_vision::Target`] made from
//!    `dataset.json` by [`target_from_manifest`]), fit its pose, and pair the
//!    corners seen (3-D target points + pixels) with the flange pose; failures
//!    become rejected captures with a reason, never silent drops. A checkerboard that
//!    looks the same turned (odd x odd squares, square boards) gets each capture's
//!    labelling from the robot's motion ([`observe_robot`], see "Symmetric targets").
//! 2. [`hand_eye`]: a closed form (Tsai, Park, Horaud, Andreff, Daniilidis, Shah, Li)
//!    or the joint reprojection refinement seeded by Park.
//! 3. [`base_to_base`]: both robots' refinements, then the joint problem over both
//!    (`base1_from_base2` with covariance and a predicted touch error). The `board`
//!    and `multimarker` methods are this same problem (the refinement projects 3-D
//!    target points and does not assume a plane); each needs its kind of target.
//! 4. [`verify`]: the touch-point check of a result.
//!
//! # Symmetric targets
//!
//! A checkerboard with `cols + rows` even (8x6 inner corners = 9x7 squares) looks the
//! same turned by 180° about its centre, a square one possibly also by 90°, so one image
//! cannot say which corner is which. The rule:
//!
//! - **Within one robot the motion decides.** [`observe_robot`] detects every capture
//!   in some labelling and then chooses each capture's labelling so that the camera's
//!   motion between captures has the same rotation angle and screw translation as the
//!   flange's (the hand-eye invariants, `b2b_calib::symmetry::resolve_labelling`); the
//!   first capture keeps the detector's labelling. A capture whose labelling the motion
//!   cannot decide (its alternatives fit about as well, e.g. it is turned by 90° about
//!   the board normal from the others, or its board pose is bad) is rejected with that
//!   reason while at least 3 captures and two thirds of them are decided; otherwise the
//!   robot is refused with [`PipelineError::SymmetricLabellingUndecided`] naming the
//!   captures.
//! - **Between two robots only gravity can decide.** Relabelling all of robot 2's
//!   captures turns `base1_from_base2` about the board normal and leaves every residual
//!   the same. The service assumes both bases stand upright (base z = up, the carts on
//!   the floor), so "up" seen from the board must agree for both robots; that decides
//!   the turn when the board is tilted out of the horizontal (a half-turn moves "up" by
//!   twice the tilt; decided when one turn agrees within 5° and the others are at least
//!   10° further, i.e. from about 10° of tilt). A board lying flat cannot be decided:
//!   [`base_to_base`] refuses with [`PipelineError::SymmetricTargetBetweenRobots`] and
//!   suggests an asymmetric board (9x6 inner corners = 10x7 squares) or ChArUco. A
//!   wrong guess would move the result by a turn of the whole board, far beyond any
//!   stated uncertainty, so the service does not guess.
//! - The live agent publishes each capture as it is taken and cannot relabel it later,
//!   so [`observe_capture`] keeps refusing symmetric boards (the vision crate's
//!   [`VisionError::AmbiguousOrientation`]).

pub mod causes;
pub mod depth_checks;
pub mod progress;
pub mod rgbd;
mod select;

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::Instant;

use b2b_calib::camera::CameraModel;
use b2b_calib::estimate::{Rejection, RobotCaptures, SplitCheck, estimate_hand_eye};
use b2b_calib::handeye::{self, HandEyeMethod, RobotWorldMethod};
use b2b_calib::metrics::{TouchMetrics, predicted_error, verify_touches, workspace_points};
use b2b_calib::refine::{BoardCapture, HandEyeEstimate, RefineOptions, evaluate_hand_eye};
use b2b_calib::sanity::{SanityOptions, SanityReport, check_pose_pairs};
use b2b_calib::symmetry::{
    GravityOptions, LabellingOptions, TargetSymmetry, resolve_between_robots, resolve_labelling,
};
use b2b_calib::{CalibError, Iso3};
use b2b_dataset::{Dataset, DatasetError, TouchPair};
use b2b_protocol::{
    CalibrationResult, CaptureResidual, CaptureSummary, HANDEYE_FORMAT, HandEyeResult, Pose,
    PredictedError, RESULT_FORMAT, RejectedCapture, Timings, VerifyReport,
};
use b2b_vision::{
    ArucoGridSpec, BoardDetection, CharucoSpec, CheckerboardSpec, DistortionTerms, GrayImage,
    IntrinsicsOptions, MarkerDictionary, MultimarkerConfig, Target, VisionError,
};
use nalgebra::{Matrix6, Point3};

/// Everything that can stop the pipeline, with where it happened.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    #[error("robot {robot}")]
    Calib { robot: String, source: CalibError },
    #[error(transparent)]
    Vision(#[from] VisionError),
    #[error("{0}")]
    Unsupported(String),
    /// Robots that no chain of shared targets links to the reference robot.
    #[error(
        "{} cannot be placed in {reference}'s base: no target they see is seen by {reference} \
         or by a robot linked to it (each target links the robots that see it; \
         a robot that sees targets of both groups joins them)",
        cut_off.join(", ")
    )]
    Disconnected {
        reference: String,
        cut_off: Vec<String>,
    },
    /// The pre-fit checks found that one robot's flange poses and board poses do
    /// not belong together ([`b2b_calib::sanity`]): quaternion order, units, rows.
    #[error("{captures}: robot {robot}: {problem}")]
    CapturesInconsistent {
        robot: String,
        /// The capture list at fault (`.../captures.csv`, or where the captures came from).
        captures: String,
        problem: CalibError,
    },
    /// One robot's flange poses fit far better inverted: written as
    /// `T_flange_base` where `T_base_flange` belongs ([`causes::check_inverted_poses`]).
    #[error(
        "{captures}: {robot}'s poses look inverted (T_flange_base instead of T_base_flange): \
         {evidence}. Write each row as the flange's pose in the base (or, if the camera stands \
         still and the target rides on the flange, this is eye-to-hand data, which the service \
         does not calibrate)"
    )]
    PosesInverted {
        robot: String,
        /// The capture list at fault.
        captures: String,
        /// The screw axes' fit as given and inverted.
        evidence: String,
    },
    /// RGB-D: a robot's depth images do not lift its colour features to points
    /// that move as the robot moved ([`depth_checks::DepthCheck::mismatch`]).
    #[error(
        "{robot}'s depth images do not match its colour images: {evidence}. A depth folder of \
         another camera or robot{}? Give each robot its own depth images, aligned to its colour \
         images",
        .depth_folder.as_ref().map(|f| format!(" ({} holds them)", f.display())).unwrap_or_default()
    )]
    DepthNotOfColour {
        robot: String,
        /// The folder the depth images came from, when they came from files.
        depth_folder: Option<PathBuf>,
        /// The registrations of its views' depth against its motion.
        evidence: String,
    },
    /// RGB-D: a robot's depth at another scale than its motion
    /// ([`causes::is_depth_scaled`]).
    #[error(
        "{robot}'s depth measures {scale:.3} ± {scale_sigma:.4} of the robot's motion ({evidence}): \
         its depth unit or depth scale is wrong{}",
        .unit.as_ref().map(|(manifest, unit)| format!(
            " ({} gives depth_unit_m {unit}; the motion fits {:.6})",
            manifest.display(),
            unit / scale
        )).unwrap_or_default()
    )]
    DepthScale {
        robot: String,
        scale: f64,
        scale_sigma: f64,
        /// The pairs and residuals the scale comes from.
        evidence: String,
        /// The manifest and the depth unit it gives, when from a dataset.
        unit: Option<(PathBuf, f64)>,
    },
    /// RGB-D: a robot's depth, read with the dataset's unit, lies outside the
    /// working range, so its features lift to nothing (a depth unit slip).
    #[error(
        "{}: {robot}'s depth images give a median depth of {median_m:.3} m with depth_unit_m \
         {unit_m} ({files} images), outside the working range {min_m}-{max_m} m: only \
         {lifted} of its {keypoints} features lift to a point. Its depth unit is wrong? (with \
         depth_unit_m 0.001, the RealSense default, the median would be {:.3} m)",
        manifest.display(),
        median_m / unit_m * 0.001
    )]
    DepthOutOfRange {
        robot: String,
        manifest: PathBuf,
        unit_m: f64,
        median_m: f64,
        files: usize,
        lifted: usize,
        keypoints: usize,
        min_m: f64,
        max_m: f64,
    },
    /// A multimarker file whose widths look like metres ([`causes::check_multimarker_units`]).
    #[error(
        "{}: marker {marker} (entry at line {line}) is {width_mm:.3} mm wide ({count} marker(s) \
         under 1 mm): the widths look like metres; the file gives widths and translations in \
         millimetres",
        file.display()
    )]
    MarkerUnits {
        file: PathBuf,
        marker: usize,
        line: usize,
        width_mm: f64,
        count: usize,
    },
    /// A robot without a `camera` block, in a command that cannot estimate one.
    #[error(
        "robot '{robot}' has no camera intrinsics in {}: this command needs them given \
         (`coordinator calibrate --method board|multimarker` and `agent handeye` estimate \
         them from the captures' images)",
        manifest.display()
    )]
    NoIntrinsics { robot: String, manifest: PathBuf },
    /// A robot without a `camera` block whose captures do not allow estimating one.
    #[error("robot '{robot}': cannot estimate the camera intrinsics from its captures: {reason}")]
    IntrinsicsEstimation { robot: String, reason: String },
    /// A robot id that the dataset's manifest does not list.
    #[error("robot '{robot}' is not in {}", manifest.display())]
    UnknownRobot { robot: String, manifest: PathBuf },
    /// The manifest's target cannot be detected as described (sizes, dictionary, the
    /// multimarker file).
    #[error("{}: target", manifest.display())]
    InvalidTarget {
        manifest: PathBuf,
        #[source]
        source: VisionError,
    },
    /// No camera could be guessed from an image's size to start the intrinsics fit.
    #[error("{width}x{height} image: no initial camera for the intrinsics fit")]
    CameraGuess {
        width: u32,
        height: u32,
        #[source]
        source: CalibError,
    },
    /// A base-to-base method whose target kind the dataset does not have.
    #[error(
        "{}: method {method} needs {needs}; this dataset's target is {found}: use --method {instead}",
        manifest.display()
    )]
    MethodTargetMismatch {
        manifest: PathBuf,
        method: &'static str,
        /// What the method needs, e.g. `a multimarker target`.
        needs: &'static str,
        /// What the dataset has, e.g. `'charuco'`.
        found: String,
        /// The method that fits the dataset's target.
        instead: &'static str,
    },
    /// Base-to-base on a dataset with fewer than two robots, or the RGB-D
    /// method on one with other than two.
    #[error(
        "{}: base-to-base {what}, the manifest lists {robots}",
        manifest.display()
    )]
    NotTwoRobots {
        manifest: PathBuf,
        robots: usize,
        /// What the method needs, e.g. `needs at least two robots`.
        what: &'static str,
    },
    /// A robot with fewer usable captures than any fit needs: the robot alone
    /// is named, with the reasons its captures were rejected, most frequent
    /// first (the root cause, e.g. every image black or the wrong dictionary).
    #[error(
        "robot {robot}: too few captures: {used}, need at least {need}; {rejected} of its {total} \
         captures rejected{}",
        if reasons.is_empty() { String::new() } else { format!(": {reasons}") }
    )]
    TooFewUsableCaptures {
        robot: String,
        used: usize,
        need: usize,
        total: usize,
        rejected: usize,
        /// The top reasons with their counts, e.g. `12 x no checkerboard found
        /// (e.g. images/001.png)`.
        reasons: String,
    },
    /// Touches that cannot verify a result (too few, not finite): the touch
    /// file is at fault, not the result (the caller names the file).
    #[error("touch points")]
    Touches {
        #[source]
        source: CalibError,
    },
    /// `verify --pair` for robots the result holds no transform between.
    #[error("the result holds no transform between robots {a} and {b}: {why}")]
    NoPair { a: String, b: String, why: String },
    /// A result file (or message) that does not validate.
    #[error("result")]
    InvalidResult {
        #[source]
        source: b2b_protocol::ProtocolError,
    },
    /// RGB-D: a robot whose manifest entry has no depth unit.
    #[error(
        "{}: robot '{robot}' has no depth_unit_m: method rgbd needs depth images",
        manifest.display()
    )]
    NoDepthUnit { robot: String, manifest: PathBuf },
    /// RGB-D: a capture without both its colour and its depth image.
    #[error("rgbd needs both a colour and a depth image")]
    NoDepthImage,
    /// RGB-D: a depth image of another size than the colour camera's; `depth_file`
    /// is the depth image when it came from a file.
    #[error(
        "{}depth image is {depth_width}x{depth_height}, the colour camera \
         {colour_width}x{colour_height} (depth must be aligned to colour)",
        .depth_file.as_ref().map(|f| format!("{}: ", f.display())).unwrap_or_default()
    )]
    DepthNotAligned {
        depth_file: Option<PathBuf>,
        depth_width: u32,
        depth_height: u32,
        colour_width: u32,
        colour_height: u32,
    },
    /// RGB-D: a feature set whose keypoints and 3-D points are not paired one to one.
    #[error("features of row {row}: {keypoints} keypoints but {points} points")]
    FeatureCountMismatch {
        row: usize,
        keypoints: usize,
        points: usize,
    },
    /// RGB-D: an image pair with too few matches that have depth at both ends.
    #[error("{matches} matches with valid depth at both ends, need at least {need}")]
    TooFewDepthMatches { matches: usize, need: usize },
    /// RGB-D: RANSAC found no rigid motion that enough matches agree with.
    #[error(
        "RANSAC: best consensus {best} of {total} matches within {threshold_mm:.1} mm, need {need}"
    )]
    NoRansacConsensus {
        best: usize,
        total: usize,
        threshold_mm: f64,
        need: usize,
    },
    /// RGB-D: fewer RANSAC inliers than needed after the final fit.
    #[error("{inliers} RANSAC inliers, need at least {need}")]
    TooFewRansacInliers { inliers: usize, need: usize },
    /// RGB-D: the pair estimates and their view labels differ in number.
    #[error("rgbd: {estimates} pair estimates but {labels} view labels")]
    PairLabelsMismatch { estimates: usize, labels: usize },
    /// RGB-D: nothing to combine.
    #[error("rgbd: no image pair gave an estimate")]
    NoPairEstimate,
    /// RGB-D: the screening left no pair.
    #[error("rgbd: every pair was rejected as an outlier")]
    AllPairsOutliers,
    /// RGB-D: no image pair of the two robots had enough inliers; `reasons` says why
    /// per pair ("rows 3/5: ...").
    #[error(
        "rgbd: no image pair has {min_inliers} inliers ({pairs} pairs tried, {views1} views of \
         {robot1}, {views2} of {robot2}){}{}",
        if reasons.is_empty() { "" } else { ": " },
        reasons.join("; ")
    )]
    NoPairWithInliers {
        min_inliers: usize,
        pairs: usize,
        robot1: String,
        views1: usize,
        robot2: String,
        views2: usize,
        reasons: Vec<String>,
    },
    /// A symmetric target whose labelling the robot's motion could not decide for too
    /// many captures (see the crate docs, "Symmetric targets").
    #[error(
        "robot {robot}: the {target} looks the same turned about its centre, and the robot's \
         motion cannot decide its labelling in {}: {reason}; use an asymmetric board (9x6 \
         inner corners = 10x7 squares) or a ChArUco board, or capture from more varied poses",
        .captures.join(", ")
    )]
    SymmetricLabellingUndecided {
        robot: String,
        target: String,
        captures: Vec<String>,
        reason: String,
    },
    /// Two robots saw a symmetric target and nothing physical decides how robot 2's
    /// labelling relates to robot 1's (see the crate docs, "Symmetric targets").
    #[error(
        "the {target} looks the same turned about its normal, so robot {robot2}'s captures \
         can be labelled {turns} relative to robot {robot1}'s and base1_from_base2 would turn \
         with them; motion cannot decide this between two robots and gravity (both bases \
         upright) cannot either: {reason}. Use an asymmetric board (cols + rows odd, e.g. 9x6 \
         inner corners = 10x7 squares) or a ChArUco board, or tilt the board at least 15° \
         out of the horizontal"
    )]
    SymmetricTargetBetweenRobots {
        target: String,
        robot1: String,
        robot2: String,
        turns: String,
        reason: String,
    },
}

/// An error and its causes on one line, "a: b: c", for a reason kept as text (a
/// rejected capture's reason, a status message).
pub use b2b_errors::chain as error_chain;

fn unknown_robot(ds: &Dataset, robot: &str) -> PipelineError {
    PipelineError::UnknownRobot {
        robot: robot.to_owned(),
        manifest: ds.root.join("dataset.json"),
    }
}

pub(crate) fn not_two_robots(ds: &Dataset) -> PipelineError {
    PipelineError::NotTwoRobots {
        manifest: ds.root.join("dataset.json"),
        robots: ds.manifest.robots.len(),
        what: "needs at least two robots",
    }
}

/// The RGB-D method pairs images of two robots.
pub(crate) fn rgbd_not_two_robots(ds: &Dataset) -> PipelineError {
    PipelineError::NotTwoRobots {
        manifest: ds.root.join("dataset.json"),
        robots: ds.manifest.robots.len(),
        what: "by the rgbd method needs exactly two robots (use the board or multimarker method for more)",
    }
}

fn calib(robot: &str) -> impl FnOnce(CalibError) -> PipelineError + '_ {
    move |source| PipelineError::Calib {
        robot: robot.to_owned(),
        source,
    }
}

/// How a hand-eye is computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HandEyeChoice {
    ClosedForm(HandEyeMethod),
    RobotWorld(RobotWorldMethod),
    /// The joint reprojection refinement (the default).
    Refined,
}

impl FromStr for HandEyeChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        if s == "refined" {
            return Ok(HandEyeChoice::Refined);
        }
        if let Ok(m) = s.parse::<HandEyeMethod>() {
            return Ok(HandEyeChoice::ClosedForm(m));
        }
        if let Ok(m) = s.parse::<RobotWorldMethod>() {
            return Ok(HandEyeChoice::RobotWorld(m));
        }
        Err(format!(
            "unknown hand-eye method '{s}': expected one of tsai, park, horaud, andreff, daniilidis, shah, li, refined"
        ))
    }
}

impl HandEyeChoice {
    pub fn name(&self) -> String {
        match self {
            HandEyeChoice::ClosedForm(m) => m.name().to_owned(),
            HandEyeChoice::RobotWorld(m) => m.name().to_owned(),
            HandEyeChoice::Refined => "refined".to_owned(),
        }
    }
}

/// One usable capture.
#[derive(Debug, Clone)]
pub struct Observation {
    pub row: usize,
    pub image: Option<String>,
    pub camera_from_target: Iso3,
    /// Flange pose and the corners, as the refinement takes them.
    pub board: BoardCapture,
    pub pnp_rms_px: f64,
    /// Per-corner residual of the board pose (px).
    pub residuals_px: Vec<f64>,
}

/// One robot's usable captures and the rejected ones.
#[derive(Debug, Clone)]
pub struct RobotObservations {
    pub robot: String,
    /// The dataset's camera, or the initial estimate when it had none.
    pub camera: CameraModel,
    pub observations: Vec<Observation>,
    pub rejected: Vec<RejectedCapture>,
    pub detect_ms: f64,
    /// `Some` when the dataset gave no intrinsics and `camera` was estimated from
    /// these captures' images; the hand-eye and base-to-base fits then refine it
    /// jointly (see [`observe_robot`]).
    pub estimated_intrinsics: Option<EstimatedIntrinsics>,
}

/// How a robot's intrinsics were estimated from its own captures.
#[derive(Debug, Clone, PartialEq)]
pub struct EstimatedIntrinsics {
    /// The distortion terms of the initial fit (the others started at zero).
    pub terms: DistortionTerms,
    /// Images in the initial fit.
    pub images_used: usize,
    /// Reprojection RMS of the initial fit (px).
    pub rms_px: f64,
    /// Time the initial fit took (ms), included in `detect_ms`.
    pub fit_ms: f64,
}

/// The `camera` block of a robot; `None` when the dataset leaves it out.
fn camera_of(ds: &Dataset, robot: &str) -> Result<Option<CameraModel>, PipelineError> {
    let m = ds
        .robot_manifest(robot)
        .ok_or_else(|| unknown_robot(ds, robot))?;
    m.camera
        .as_ref()
        .map(|c| b2b_dataset::camera_model(c).map_err(calib(robot)))
        .transpose()
}

/// The target of a dataset ([`Dataset::manifest`]'s `target`); a multimarker file
/// is read from the dataset folder.
pub fn target_of(ds: &Dataset) -> Result<Target, PipelineError> {
    target_from_manifest(&ds.manifest.target, &ds.root.join("dataset.json"))
}

/// Every target of a dataset, in [`Dataset::all_targets`] order (the manifest's
/// `target` first).
pub fn targets_of(ds: &Dataset) -> Result<Vec<Target>, PipelineError> {
    let manifest = ds.root.join("dataset.json");
    ds.all_targets()
        .into_iter()
        .map(|(_, t)| target_from_manifest(t, &manifest))
        .collect()
}

/// A target as `dataset.json` describes it (the same JSON in a live agent's setup
/// file, or the block `b2b-vision-tool` prints), read from `manifest`: the sizes
/// validated, a multimarker file read (its relative path taken from the folder of
/// `manifest`, which errors also name) and checked against its dictionary and for
/// millimetres given as metres.
pub fn target_from_manifest(
    target: &b2b_dataset::Target,
    manifest: &Path,
) -> Result<Target, PipelineError> {
    use b2b_dataset::Target as File;
    let root = manifest.parent().unwrap_or(Path::new("."));
    let bad = |source: VisionError| PipelineError::InvalidTarget {
        manifest: manifest.to_owned(),
        source,
    };
    let spec = match target {
        File::Checkerboard {
            inner_corners,
            square_m,
        } => {
            let spec = CheckerboardSpec {
                cols: inner_corners[0] as usize,
                rows: inner_corners[1] as usize,
                square_m: *square_m,
            };
            spec.validate().map_err(bad)?;
            Target::Checkerboard(spec)
        }
        File::Charuco {
            squares,
            square_m,
            marker_m,
            dictionary,
        } => {
            let spec = CharucoSpec {
                squares: [squares[0] as usize, squares[1] as usize],
                square_m: *square_m,
                marker_m: *marker_m,
                dictionary: dictionary.clone(),
            };
            spec.validate().map_err(bad)?;
            Target::Charuco(spec)
        }
        File::ArucoGrid {
            markers,
            marker_m,
            separation_m,
            dictionary,
            first_id,
        } => {
            let spec = ArucoGridSpec {
                markers: [markers[0] as usize, markers[1] as usize],
                marker_m: *marker_m,
                separation_m: *separation_m,
                dictionary: dictionary.clone(),
                first_id: *first_id as usize,
            };
            spec.validate().map_err(bad)?;
            Target::ArucoGrid(spec)
        }
        File::Multimarker { config, dictionary } => {
            let dictionary = MarkerDictionary::parse(dictionary).map_err(bad)?;
            let path = if config.is_absolute() {
                config.clone()
            } else {
                root.join(config)
            };
            let config = MultimarkerConfig::load(&path)?;
            config.check_dictionary(&dictionary)?;
            causes::check_multimarker_units(&config, &path)?;
            Target::Multimarker { config, dictionary }
        }
    };
    Ok(spec)
}

/// What the detector needs to know about one robot of a dataset.
#[derive(Debug, Clone)]
pub struct RobotSetup {
    pub robot: String,
    pub camera: CameraModel,
    /// The dataset's `target`.
    pub target: Target,
    board_points: Vec<Point3<f64>>,
    /// The dataset's further `targets` and their points, in
    /// [`Dataset::all_targets`] order after the first.
    others: Vec<(Target, Vec<Point3<f64>>)>,
}

impl RobotSetup {
    /// The camera and target of `robot` in a dataset; a robot without intrinsics is
    /// [`PipelineError::NoIntrinsics`] (only [`observe_robot`] estimates them).
    pub fn from_dataset(ds: &Dataset, robot: &str) -> Result<Self, PipelineError> {
        let camera = camera_of(ds, robot)?.ok_or_else(|| PipelineError::NoIntrinsics {
            robot: robot.to_owned(),
            manifest: ds.root.join("dataset.json"),
        })?;
        let mut targets = targets_of(ds)?.into_iter();
        let target = targets
            .next()
            .ok_or_else(|| PipelineError::Unsupported("a dataset without a target".into()))?;
        let board_points = target.all_points();
        Ok(RobotSetup {
            robot: robot.to_owned(),
            camera,
            target,
            board_points,
            others: targets
                .map(|t| {
                    let points = t.all_points();
                    (t, points)
                })
                .collect(),
        })
    }

    /// Target `index` ([`Dataset::target_index`]) and its points.
    pub fn target_at(&self, index: usize) -> (&Target, &[Point3<f64>]) {
        match index.checked_sub(1).and_then(|k| self.others.get(k)) {
            Some((t, points)) => (t, points),
            None => (&self.target, &self.board_points),
        }
    }
}

/// Detects the target in one capture and fits its pose, or says why not. Rows
/// that give `T_camera_target` directly (pose-only rows) become the target's
/// points projected by that pose, so the refinement sees the same kind of data.
///
/// A symmetric checkerboard is rejected here (one capture cannot fix its labelling);
/// [`observe_robot`] decides it over all of a robot's captures.
pub fn observe_capture(
    ds: &Dataset,
    setup: &RobotSetup,
    cap: &b2b_dataset::Capture,
) -> Result<Observation, RejectedCapture> {
    observe_capture_impl(ds, setup, cap, false)
}

fn observe_capture_impl(
    ds: &Dataset,
    setup: &RobotSetup,
    cap: &b2b_dataset::Capture,
    up_to_symmetry: bool,
) -> Result<Observation, RejectedCapture> {
    let robot = setup.robot.as_str();
    let image = cap.image.as_ref().map(|p| p.display().to_string());
    let reject = |reason: String| RejectedCapture {
        robot: robot.to_owned(),
        image: image.clone(),
        row: Some(cap.row),
        reason,
    };
    let target_index = ds.target_index(cap);
    let (target, board_points) = setup.target_at(target_index);
    if let (None, Some(camera_from_target)) = (&cap.image, cap.camera_from_target) {
        let pixels: Vec<_> = board_points
            .iter()
            .filter_map(|p| setup.camera.project(&(camera_from_target * p)))
            .collect();
        if pixels.len() != board_points.len() {
            return Err(reject(
                "target behind the camera in the given T_camera_target".into(),
            ));
        }
        return Ok(Observation {
            row: cap.row,
            image,
            camera_from_target,
            board: BoardCapture {
                base_from_flange: cap.base_from_flange,
                target_points: board_points.to_vec(),
                pixels,
                target: target_index,
            },
            pnp_rms_px: 0.0,
            residuals_px: vec![0.0; board_points.len()],
        });
    }
    let Some(path) = ds.image_path(robot, cap) else {
        return Err(reject(
            "row has neither an image nor T_camera_target".into(),
        ));
    };
    b2b_vision::load_gray_sized(&path, setup.camera.width, setup.camera.height)
        .and_then(|img| {
            observe(
                &img,
                &setup.camera,
                target,
                cap.base_from_flange,
                up_to_symmetry,
            )
        })
        .map(|mut o| {
            o.board.target = target_index;
            Observation {
                row: cap.row,
                image: image.clone(),
                ..o
            }
        })
        .map_err(|e| reject(error_chain(&e)))
}

/// One image of the target from a flange pose: the detection and its pose fit
/// as the observation every estimator takes. The offline path (each capture of
/// a dataset) and the live agent (each still frame) both observe through this.
/// `row` is 0 and `image` `None`: the caller names the capture. With
/// `up_to_symmetry`, a symmetric target comes back in one of the labellings of
/// [`Target::symmetry`], which the caller resolves.
pub fn observe(
    img: &b2b_vision::GrayImage,
    camera: &CameraModel,
    target: &Target,
    base_from_flange: Iso3,
    up_to_symmetry: bool,
) -> Result<Observation, VisionError> {
    let (detection, pose) = if up_to_symmetry {
        target.detect_up_to_symmetry(img, camera)?
    } else {
        target.detect(img, camera)?
    };
    Ok(Observation {
        row: 0,
        image: None,
        camera_from_target: pose.camera_from_target,
        board: BoardCapture {
            base_from_flange,
            target_points: detection.target_points,
            pixels: detection.pixels,
            target: 0,
        },
        pnp_rms_px: pose.rms_px,
        residuals_px: pose.residuals_px,
    })
}

/// Detects the board in every capture of one robot and fits its pose; failures
/// become rejected captures with a reason, never silent drops. A symmetric target's
/// labelling is chosen per capture from the robot's motion (crate docs, "Symmetric
/// targets"), the first capture keeping the detector's.
///
/// A robot without a `camera` block in `dataset.json` gets one estimated from
/// these same captures (see [`observe_uncalibrated`]); the result says so in
/// [`RobotObservations::estimated_intrinsics`].
pub fn observe_robot(ds: &Dataset, robot: &str) -> Result<RobotObservations, PipelineError> {
    let start = Instant::now();
    let captures = ds.root.join(robot).join(b2b_dataset::CAPTURES_FILE);
    if camera_of(ds, robot)?.is_none() {
        if let Some(cap) = ds
            .robot(robot)
            .and_then(|d| d.captures.iter().find(|c| c.target.is_some()))
        {
            return Err(PipelineError::Unsupported(format!(
                "{robot} has no intrinsics in dataset.json and row {} of its captures.csv sees \
                 target `{}`: intrinsics are estimated from the captures of the dataset's `target` \
                 only; give this robot's `camera` block",
                cap.row,
                cap.target.as_deref().unwrap_or_default()
            )));
        }
        let obs = observe_uncalibrated(ds, robot, target_of(ds)?, start)?;
        return screen_observations(&obs, &captures.display().to_string()).map(|(o, _)| o);
    }
    let setup = RobotSetup::from_dataset(ds, robot)?;
    let data = ds.robot(robot).ok_or_else(|| unknown_robot(ds, robot))?;
    check_image_sizes(ds, robot, &setup.camera)?;
    let mut observations = Vec::new();
    let mut rejected = Vec::new();
    let stage = progress::Stage::new(
        &format!("{robot}: detecting the target"),
        data.captures.len(),
    );
    for cap in &data.captures {
        match observe_capture_impl(ds, &setup, cap, true) {
            Ok(o) => observations.push(o),
            Err(r) => {
                tracing::warn!(robot, row = cap.row, "capture rejected: {}", r.reason);
                rejected.push(r);
            }
        }
        stage.step();
    }
    drop(stage);
    // A symmetric target's labelling is resolved over the robot's views of
    // that target.
    let targets = 1 + setup.others.len();
    let mut resolved = Vec::with_capacity(observations.len());
    for t in 0..targets {
        let (spec, _) = setup.target_at(t);
        let (mine, rest): (Vec<Observation>, Vec<Observation>) =
            observations.into_iter().partition(|o| o.board.target == t);
        observations = rest;
        let symmetry = spec.symmetry();
        if symmetry.is_trivial() || mine.is_empty() {
            resolved.extend(mine);
            continue;
        }
        resolved.extend(resolve_symmetric_labelling(
            robot,
            &spec.describe(),
            &symmetry,
            mine,
            &mut rejected,
        )?);
    }
    resolved.sort_by_key(|o| o.row);
    let observations = resolved;
    let obs = RobotObservations {
        robot: robot.to_owned(),
        camera: setup.camera,
        observations,
        rejected,
        detect_ms: start.elapsed().as_secs_f64() * 1e3,
        estimated_intrinsics: None,
    };
    screen_observations(&obs, &captures.display().to_string()).map(|(o, _)| o)
}

/// Checks every colour and depth image of one robot against its camera intrinsics'
/// width and height (and the pixel cap) from the file headers, before anything is
/// decoded. A mismatch is an error for the whole data set: the intrinsics do not
/// belong to these images.
pub fn check_image_sizes(
    ds: &Dataset,
    robot: &str,
    camera: &CameraModel,
) -> Result<(), PipelineError> {
    let Some(data) = ds.robot(robot) else {
        return Ok(());
    };
    for cap in &data.captures {
        for path in [ds.image_path(robot, cap), ds.depth_path(robot, cap)]
            .into_iter()
            .flatten()
        {
            b2b_vision::check_image_file(&path, camera.width, camera.height)?;
        }
    }
    Ok(())
}

/// Fewest usable captures of one robot for any fit (hand-eye or base-to-base).
pub const MIN_USABLE_CAPTURES: usize = 3;

/// How many distinct reasons [`rejection_summary`] lists.
const TOP_REASONS: usize = 3;

/// The most frequent rejection reasons of `rejected`, with their counts and an
/// example capture: `12 x no checkerboard found (e.g. row 1, images/001.png);
/// 2 x ...`. Reasons that differ only in their numbers or in the image's own
/// path count as one.
pub fn rejection_summary(rejected: &[RejectedCapture]) -> String {
    let key = |r: &RejectedCapture| {
        let mut text = r.reason.clone();
        if let Some(image) = &r.image {
            text = text.replace(image.as_str(), "");
        }
        let mut out = String::with_capacity(text.len());
        let mut in_number = false;
        for c in text.chars() {
            if c.is_ascii_digit() || (in_number && c == '.') {
                if !in_number {
                    out.push('#');
                }
                in_number = true;
            } else {
                in_number = false;
                out.push(c);
            }
        }
        out
    };
    // At most this many distinct reasons are told apart (the rest are "other").
    const MAX_GROUPS: usize = 1000;
    let mut groups: Vec<(String, usize, &RejectedCapture)> = vec![];
    let mut other = 0;
    for r in rejected {
        let k = key(r);
        if let Some(g) = groups.iter_mut().find(|g| g.0 == k) {
            g.1 += 1;
        } else if groups.len() < MAX_GROUPS {
            groups.push((k, 1, r));
        } else {
            other += 1;
        }
    }
    // Most frequent first; ties in the order first seen.
    groups.sort_by_key(|g| std::cmp::Reverse(g.1));
    let mut parts: Vec<String> = groups
        .iter()
        .take(TOP_REASONS)
        .map(|(_, n, r)| {
            let example = match (r.row, &r.image) {
                (Some(row), Some(image)) => format!(" (e.g. row {row}, {image})"),
                (Some(row), None) => format!(" (e.g. row {row})"),
                (None, Some(image)) => format!(" (e.g. {image})"),
                (None, None) => String::new(),
            };
            format!("{n} x {}{example}", r.reason)
        })
        .collect();
    let rest: usize = other + groups.iter().skip(TOP_REASONS).map(|g| g.1).sum::<usize>();
    if rest > 0 {
        parts.push(format!("{rest} for other reasons"));
    }
    parts.join("; ")
}

/// Refuses a robot with fewer than [`MIN_USABLE_CAPTURES`] usable captures,
/// naming it alone and why its captures were rejected.
pub fn check_enough_captures(obs: &RobotObservations) -> Result<(), PipelineError> {
    let used = obs.observations.len();
    if used >= MIN_USABLE_CAPTURES {
        return Ok(());
    }
    Err(PipelineError::TooFewUsableCaptures {
        robot: obs.robot.clone(),
        used,
        need: MIN_USABLE_CAPTURES,
        total: used + obs.rejected.len(),
        rejected: obs.rejected.len(),
        reasons: rejection_summary(&obs.rejected),
    })
}

/// Runs the pre-fit consistency checks ([`b2b_calib::sanity::check_pose_pairs`]) on
/// one robot's observations. A data-set-wide disagreement (quaternion order, a unit
/// error, flange and board poses that do not belong together) is an error naming
/// `captures` (the capture list, for the message); captures that disagree with most
/// others are moved to the rejected list with the reason, and the rest returned.
pub fn screen_observations(
    obs: &RobotObservations,
    captures: &str,
) -> Result<(RobotObservations, SanityReport), PipelineError> {
    // Motions pair captures of one target: each target's captures are checked
    // alone. The report is that of the target seen most.
    let mut targets: Vec<usize> = obs.observations.iter().map(|o| o.board.target).collect();
    targets.sort_unstable();
    targets.dedup();
    if targets.is_empty() {
        targets.push(0);
    }
    let mut report: Option<SanityReport> = None;
    let mut suspects: Vec<(usize, String)> = Vec::new();
    for t in targets {
        let group: Vec<usize> = (0..obs.observations.len())
            .filter(|k| obs.observations[*k].board.target == t)
            .collect();
        let base_from_flange: Vec<Iso3> = group
            .iter()
            .map(|k| obs.observations[*k].board.base_from_flange)
            .collect();
        let camera_from_target: Vec<Iso3> = group
            .iter()
            .map(|k| obs.observations[*k].camera_from_target)
            .collect();
        let checked = check_pose_pairs(
            &base_from_flange,
            &camera_from_target,
            &SanityOptions::default(),
        )
        .map_err(|problem| PipelineError::CapturesInconsistent {
            robot: obs.robot.clone(),
            captures: captures.to_owned(),
            problem,
        })?;
        suspects.extend(
            checked
                .suspects
                .iter()
                .map(|s| (group[s.index], s.reason.clone())),
        );
        if report
            .as_ref()
            .is_none_or(|r| checked.captures > r.captures)
        {
            report = Some(checked);
        }
    }
    let report = report.unwrap_or_else(|| unreachable!("at least one target is checked"));
    causes::check_inverted_poses(obs, captures)?;
    let mut out = obs.clone();
    if !suspects.is_empty() {
        out.observations = obs
            .observations
            .iter()
            .enumerate()
            .filter(|(k, _)| !suspects.iter().any(|(i, _)| i == k))
            .map(|(_, o)| o.clone())
            .collect();
        suspects.sort_by_key(|(i, _)| *i);
        for (index, reason) in &suspects {
            let o = &obs.observations[*index];
            tracing::warn!(
                robot = obs.robot.as_str(),
                row = o.row,
                "capture rejected: {reason}"
            );
            out.rejected.push(RejectedCapture {
                robot: obs.robot.clone(),
                image: o.image.clone(),
                row: Some(o.row),
                reason: reason.clone(),
            });
        }
    }
    Ok((out, report))
}

/// The starting camera of the detection before any intrinsics are known: focal
/// length = the image width (a 53° horizontal field of view, between a RealSense
/// colour camera's 69° and a narrow lens), principal point at the centre, no
/// distortion.
pub fn guess_camera(width: u32, height: u32) -> Result<CameraModel, PipelineError> {
    let (w, h) = (f64::from(width), f64::from(height));
    CameraModel::new(width, height, [w, w, (w - 1.0) / 2.0, (h - 1.0) / 2.0], &[]).map_err(
        |source| PipelineError::CameraGuess {
            width,
            height,
            source,
        },
    )
}

/// The most views the initial intrinsics fit takes (spread over the captures in
/// order). OpenCV's `calibrateCamera` solves for every view's pose with the camera
/// in one dense Levenberg–Marquardt problem, so an iteration costs O(views³):
/// 30 views of 54 corners took 0.5 s here, 12 views 65-110 ms, 8 views 40 ms (and
/// 8 suffice for `k1 k2 p1 p2`, [`initial_distortion_terms`]). The joint refinement
/// then fits the camera to every capture.
pub const MAX_INITIAL_VIEWS: usize = 8;

/// The distortion terms the initial intrinsics fit estimates from `views` images
/// of the target (the rest start at zero).
///
/// - `k3` is never fitted at first: the r⁶ term only differs from `k1`, `k2` near
///   the image corners, which a board seen from a robot's working distances seldom
///   reaches, so `k3` is nearly collinear with `k2` and absorbs noise (OpenCV's own
///   advice for non-fisheye lenses; RealSense colour lenses are mild, their factory
///   intrinsics often carry no distortion at all).
/// - `p1`, `p2` (decentring) trade off against the principal point: a shift of
///   `cx` and a tangential term move the corners near the centre alike, and only
///   views tilted in several directions separate them. From 8 views on (ViSP's
///   Franka set has 8) they are fitted; below, they start at zero.
/// - `k2` needs corners over a range of radii from several views: from 5 views;
///   with 4 (the fewest accepted) only `k1`. And it needs corners far from the
///   centre: over radii up to less than [`MIN_REACH_FOR_K2`] of the image's
///   half-diagonal (`reach`, [`corner_reach`]: a board far away or small), the
///   r⁴ term is hardly distinguishable from `k1`'s r² and took values that bent
///   the image's corners by tens of pixels: then only `k1` (and `p1 p2`) at
///   first, and the joint refinement's prior holds `k2` at that start.
///
/// This is only the start. The joint refinement that follows
/// ([`RefineOptions::refine_intrinsics`]) estimates all nine intrinsics
/// (`fx, fy, cx, cy, k1, k2, p1, p2, k3`) together with the hand-eye (and
/// base-to-base): it constrains the camera far more than `calibrateCamera`
/// does (one hand-eye instead of six pose unknowns per view). `k2` and `k3`
/// carry a prior ([`b2b_calib::refine::DISTORTION_PRIOR_PX`]: 10 px at the
/// image's farthest corner, one sigma) that holds them where no corner was
/// seen: a board seen only near the image's centre cannot tell them from `k1`,
/// and unheld they moved the image's corners by hundreds of pixels (a board 2 m
/// away: 351 and 1507 px; `cargo test -p b2b-pipeline --test symmetric far_`).
/// The intrinsics' uncertainty is in the poses' covariance (without the prior's
/// information: the covariance does not lean on it).
pub fn initial_distortion_terms(views: usize, reach: f64) -> DistortionTerms {
    match views {
        0..=4 => DistortionTerms::K1,
        _ if reach < MIN_REACH_FOR_K2 => DistortionTerms::K1,
        5..=7 => DistortionTerms::K1K2,
        _ => DistortionTerms::K1K2P1P2,
    }
}

/// The least `reach` ([`corner_reach`]) from which the initial intrinsics fit
/// estimates `k2` ([`initial_distortion_terms`]).
pub const MIN_REACH_FOR_K2: f64 = 0.5;

/// How far from the image's centre the views' corners reach: the farthest
/// corner's distance over the image's half-diagonal (1 at the image's corners).
pub fn corner_reach(views: &[(String, BoardDetection)], width: u32, height: u32) -> f64 {
    let (cx, cy) = (f64::from(width) / 2.0, f64::from(height) / 2.0);
    let half_diagonal = cx.hypot(cy).max(1.0);
    views
        .iter()
        .flat_map(|(_, det)| &det.pixels)
        .map(|p| (p.x - cx).hypot(p.y - cy) / half_diagonal)
        .filter(|r| r.is_finite())
        .fold(0.0, f64::max)
}

/// The initial intrinsics fit to corners already detected (OpenCV's
/// `calibrateCamera`, [`b2b_vision::calibrate_from_detections`], with
/// [`initial_distortion_terms`]): views with too few corners are left out, and at
/// most [`MAX_INITIAL_VIEWS`] are taken, spread over the views in order. `guess`
/// gives the image size, and the start for a non-planar target.
pub(crate) fn initial_intrinsics(
    views: Vec<(String, BoardDetection)>,
    guess: &CameraModel,
) -> Result<(CameraModel, EstimatedIntrinsics), String> {
    let fit_start = Instant::now();
    let options = IntrinsicsOptions::default();
    let usable: Vec<(String, BoardDetection)> = views
        .into_iter()
        .filter(|(_, det)| det.pixels.len() >= options.min_corners)
        .collect();
    let n = usable.len();
    let views: Vec<(String, BoardDetection)> = if n > MAX_INITIAL_VIEWS {
        (0..MAX_INITIAL_VIEWS)
            .map(|k| usable[k * (n - 1) / (MAX_INITIAL_VIEWS - 1)].clone())
            .collect()
    } else {
        usable
    };
    let terms =
        initial_distortion_terms(views.len(), corner_reach(&views, guess.width, guess.height));
    let fit = b2b_vision::calibrate_from_detections(
        &views,
        guess.width,
        guess.height,
        &options,
        terms,
        Some(guess),
    )
    .map_err(|e| error_chain(&e))?;
    let estimated = EstimatedIntrinsics {
        terms,
        images_used: fit.used(),
        rms_px: fit.rms_px,
        fit_ms: fit_start.elapsed().as_secs_f64() * 1e3,
    };
    Ok((fit.camera, estimated))
}

/// Fewest observations [`estimate_intrinsics_from_observations`] fits a camera
/// to: Zhang's closed form needs three views of a plane, and a fourth and fifth
/// keep one badly conditioned view from deciding the focal length.
pub const MIN_VIEWS_FOR_INTRINSICS: usize = 5;

/// A robot's observations when its camera gave no intrinsics: the camera fitted
/// to the observations' own corners, as [`observe_robot`] fits it for a dataset
/// without a `camera` block ([`initial_intrinsics`]), and every observation's pose
/// fitted again with it (an observation whose pose then fails is rejected with
/// the reason). The result is marked estimated, so that [`hand_eye`] and the
/// base-to-base fits refine the intrinsics jointly and carry their uncertainty.
///
/// This is the live path: an agent whose frames carry no intrinsics detects with
/// a provisional camera ([`guess_camera`], then its own estimates) and says so on
/// every capture; the coordinator fits the camera again from all of them. The
/// pixels and the target points (labelled already) are all it needs, so the
/// provisional camera's poses do not matter. `obs.camera` gives the image size and
/// the start for a non-planar target.
pub fn estimate_intrinsics_from_observations(
    obs: RobotObservations,
) -> Result<RobotObservations, PipelineError> {
    let robot = obs.robot.clone();
    let estimation = |reason: String| PipelineError::IntrinsicsEstimation {
        robot: robot.clone(),
        reason,
    };
    if obs.observations.len() < MIN_VIEWS_FOR_INTRINSICS {
        return Err(estimation(format!(
            "{} captures see the target; estimating the intrinsics takes at least \
             {MIN_VIEWS_FOR_INTRINSICS}",
            obs.observations.len()
        )));
    }
    let views = obs
        .observations
        .iter()
        .map(|o| (capture_name(o), published_detection(o)))
        .collect();
    let (camera, estimated) = initial_intrinsics(views, &obs.camera).map_err(estimation)?;
    let detect_ms = obs.detect_ms + estimated.fit_ms;
    let refitted = refit_poses(obs, camera, "the intrinsics estimated from the captures");
    Ok(RobotObservations {
        detect_ms,
        estimated_intrinsics: Some(estimated),
        ..refitted
    })
}

/// An observation's corners as a detection (labelled already: as published).
pub(crate) fn published_detection(o: &Observation) -> BoardDetection {
    BoardDetection {
        target_points: o.board.target_points.clone(),
        corner_ids: (0..o.board.pixels.len()).collect(),
        pixels: o.board.pixels.clone(),
        method: b2b_vision::checkerboard::CornerMethod::Published,
        refined: true,
    }
}

/// An observation's pose fitted to its corners with `camera`: a planar target
/// by IPPE + LM, another by the multimarker pose.
fn pose_with(
    o: &Observation,
    camera: &CameraModel,
) -> Result<b2b_vision::PoseEstimate, VisionError> {
    let det = published_detection(o);
    if det.target_points.iter().all(|p| p.z == 0.0) {
        b2b_vision::board_pose(&det, camera)
    } else {
        b2b_vision::multimarker_pose(&det.target_points, &det.pixels, camera).map(|(pose, _)| pose)
    }
}

/// The observations with `camera`: every pose fitted again to its corners with
/// it (a planar target by IPPE + LM, another by the multimarker pose). An
/// observation whose pose then fails is rejected with the reason, naming the
/// camera as `which`. What an agent with a provisional camera publishes is
/// `refit_poses(observations, guess, …)`.
pub fn refit_poses(obs: RobotObservations, camera: CameraModel, which: &str) -> RobotObservations {
    let mut observations = Vec::with_capacity(obs.observations.len());
    let mut rejected = obs.rejected;
    for o in obs.observations {
        match pose_with(&o, &camera) {
            Ok(pose) => observations.push(Observation {
                camera_from_target: pose.camera_from_target,
                pnp_rms_px: pose.rms_px,
                residuals_px: pose.residuals_px,
                ..o
            }),
            Err(e) => rejected.push(RejectedCapture {
                robot: obs.robot.clone(),
                image: o.image.clone(),
                row: Some(o.row),
                reason: format!("no pose with {which}: {}", error_chain(&e)),
            }),
        }
    }
    rejected.sort_by_key(|r| r.row);
    RobotObservations {
        camera,
        observations,
        rejected,
        ..obs
    }
}

/// [`observe_robot`] for a robot whose dataset gives no intrinsics: detect the
/// target's corners in every image without a camera model (a guess where the
/// detector wants one, [`guess_camera`]), fit the intrinsics to those corners
/// (OpenCV's `calibrateCamera`, [`b2b_vision::calibrate_from_detections`], with
/// [`initial_distortion_terms`]), then fit each capture's pose with that camera.
/// ChArUco corners, which the detector predicts through the camera, are detected
/// again with the estimate before the poses. Pose-only rows (`T_camera_target`
/// without an image) are rejected: their pixels would have to be made with the
/// very intrinsics that are missing.
fn observe_uncalibrated(
    ds: &Dataset,
    robot: &str,
    target: Target,
    start: Instant,
) -> Result<RobotObservations, PipelineError> {
    let data = ds.robot(robot).ok_or_else(|| unknown_robot(ds, robot))?;
    let estimation = |reason: String| PipelineError::IntrinsicsEstimation {
        robot: robot.to_owned(),
        reason,
    };
    let redetect = matches!(target, Target::Charuco(_));
    let mut rejected = Vec::new();
    let mut found: Vec<(&b2b_dataset::Capture, Option<GrayImage>, BoardDetection)> = Vec::new();
    let mut guess: Option<CameraModel> = None;
    let stage = progress::Stage::new(
        &format!("{robot}: detecting the target (no intrinsics given)"),
        data.captures.len(),
    );
    for cap in &data.captures {
        stage.step();
        let image = cap.image.as_ref().map(|p| p.display().to_string());
        let mut reject = |reason: String| {
            tracing::warn!(robot, row = cap.row, "capture rejected: {reason}");
            rejected.push(RejectedCapture {
                robot: robot.to_owned(),
                image: image.clone(),
                row: Some(cap.row),
                reason,
            });
        };
        let Some(path) = ds.image_path(robot, cap) else {
            reject(if cap.camera_from_target.is_some() {
                "row gives T_camera_target but no image: without intrinsics in dataset.json \
                 it cannot become pixels"
                    .into()
            } else {
                "row has neither an image nor T_camera_target".into()
            });
            continue;
        };
        let img = match b2b_vision::load_gray(&path) {
            Ok(img) => img,
            Err(e) => {
                reject(error_chain(&e));
                continue;
            }
        };
        let g = match &guess {
            Some(g) => g.clone(),
            None => {
                let g = guess_camera(img.width(), img.height())?;
                guess = Some(g.clone());
                g
            }
        };
        if (g.width, g.height) != (img.width(), img.height()) {
            reject(format!(
                "{}x{} image, the first image of robot '{robot}' is {}x{}: intrinsics are \
                 estimated for one camera mode",
                img.width(),
                img.height(),
                g.width,
                g.height
            ));
            continue;
        }
        // A symmetric board's labelling does not matter to the intrinsics (each
        // view has its own pose); it is chosen from the robot's motion below.
        match target.detect_corners_up_to_symmetry(&img, &g) {
            Ok(det) => found.push((cap, redetect.then_some(img), det)),
            Err(e) => reject(error_chain(&e)),
        }
    }
    let Some(guess) = guess else {
        return Err(estimation(format!(
            "none of its {} captures has a readable image",
            data.captures.len()
        )));
    };
    let usable: Vec<(String, BoardDetection)> = found
        .iter()
        .map(|(cap, _, det)| {
            let name = cap
                .image
                .as_ref()
                .map_or_else(|| format!("row {}", cap.row), |p| p.display().to_string());
            (name, det.clone())
        })
        .collect();
    let (camera, estimated) = initial_intrinsics(usable, &guess).map_err(estimation)?;
    tracing::info!(
        robot,
        fx = camera.fx,
        fy = camera.fy,
        cx = camera.cx,
        cy = camera.cy,
        dist = ?&camera.dist[..5],
        images = estimated.images_used,
        rms_px = estimated.rms_px,
        terms = estimated.terms.names(),
        "no intrinsics in dataset.json: initial camera fitted to the captures' corners"
    );
    let mut observations = Vec::new();
    for (cap, img, det) in found {
        let image = cap.image.as_ref().map(|p| p.display().to_string());
        let det = match img {
            Some(img) => target.detect_corners(&img, &camera),
            None => Ok(det),
        };
        match det.and_then(|det| target.pose(&det, &camera).map(|pose| (det, pose))) {
            Ok((det, pose)) => observations.push(Observation {
                row: cap.row,
                image,
                camera_from_target: pose.camera_from_target,
                board: BoardCapture {
                    base_from_flange: cap.base_from_flange,
                    target_points: det.target_points,
                    pixels: det.pixels,
                    target: 0,
                },
                pnp_rms_px: pose.rms_px,
                residuals_px: pose.residuals_px,
            }),
            Err(e) => {
                let reason = error_chain(&e);
                tracing::warn!(robot, row = cap.row, "capture rejected: {reason}");
                rejected.push(RejectedCapture {
                    robot: robot.to_owned(),
                    image,
                    row: Some(cap.row),
                    reason,
                });
            }
        }
    }
    let symmetry = target.symmetry();
    if !symmetry.is_trivial() {
        observations = resolve_symmetric_labelling(
            robot,
            &target.describe(),
            &symmetry,
            observations,
            &mut rejected,
        )?;
    }
    rejected.sort_by_key(|r| r.row);
    Ok(RobotObservations {
        robot: robot.to_owned(),
        camera,
        observations,
        rejected,
        detect_ms: start.elapsed().as_secs_f64() * 1e3,
        estimated_intrinsics: Some(estimated),
    })
}

/// `options` for fitting `robots`' observations: intrinsics refined too when asked
/// or when any of them was estimated from the images (the engine refines every
/// camera of a problem or none).
fn options_for(options: &RefineOptions, robots: &[&RobotObservations]) -> RefineOptions {
    RefineOptions {
        refine_intrinsics: options.refine_intrinsics
            || robots.iter().any(|o| o.estimated_intrinsics.is_some()),
        ..options.clone()
    }
}

/// At least this many captures must be decided, and at least two thirds of them, before
/// undecided captures of a symmetric target are rejected rather than the robot refused.
const MIN_DECIDED_CAPTURES: usize = 3;

pub(crate) fn capture_name(o: &Observation) -> String {
    match &o.image {
        Some(image) => format!("row {} ({image})", o.row),
        None => format!("row {}", o.row),
    }
}

/// Chooses each observation's labelling of a symmetric target from the robot's motion
/// and relabels it (pose and target points; the pixels stay); see the crate docs.
fn resolve_symmetric_labelling(
    robot: &str,
    target: &str,
    symmetry: &TargetSymmetry,
    observations: Vec<Observation>,
    rejected: &mut Vec<RejectedCapture>,
) -> Result<Vec<Observation>, PipelineError> {
    let options = LabellingOptions::default();
    let base_from_flange: Vec<Iso3> = observations
        .iter()
        .map(|o| o.board.base_from_flange)
        .collect();
    let camera_from_target: Vec<Iso3> = observations.iter().map(|o| o.camera_from_target).collect();
    let resolution = resolve_labelling(&base_from_flange, &camera_from_target, symmetry, &options)
        .map_err(calib(robot))?;
    let undecided = resolution.undecided();
    let total = observations.len();
    let decided = total - undecided.len();
    let name = |k: Option<usize>| {
        k.map_or("none", |k| symmetry.elements()[k].name.as_str())
            .to_owned()
    };
    let why = |v: usize| {
        let view = &resolution.views[v];
        format!(
            "its motion to the other captures fits the labelling '{}' and the labelling '{}' \
             about equally (they differ by {:.1}, need {:.0}; {} of {} pairs decisive): a capture \
             turned about the board normal by 90° from the others, or a bad board pose",
            name(Some(view.element)),
            name(view.runner_up),
            view.margin,
            options.min_margin,
            view.decisive_pairs,
            total - 1
        )
    };
    if !undecided.is_empty() && (decided < MIN_DECIDED_CAPTURES || 3 * decided < 2 * total) {
        return Err(PipelineError::SymmetricLabellingUndecided {
            robot: robot.to_owned(),
            target: target.to_owned(),
            captures: undecided
                .iter()
                .map(|&v| capture_name(&observations[v]))
                .collect(),
            reason: format!(
                "{decided} of {total} captures decided (need {MIN_DECIDED_CAPTURES} and two thirds); {}",
                why(undecided[0])
            ),
        });
    }
    let mut kept = Vec::with_capacity(decided);
    for (v, mut o) in observations.into_iter().enumerate() {
        let view = &resolution.views[v];
        if !view.decided {
            let r = RejectedCapture {
                robot: robot.to_owned(),
                image: o.image.clone(),
                row: Some(o.row),
                reason: format!("labelling of the symmetric {target} undecided: {}", why(v)),
            };
            tracing::warn!(robot, row = o.row, "capture rejected: {}", r.reason);
            rejected.push(r);
            continue;
        }
        tracing::debug!(
            robot,
            row = o.row,
            margin = view.margin,
            "symmetric target labelled by '{}'",
            name(Some(view.element))
        );
        o.camera_from_target = symmetry.relabel_pose(&o.camera_from_target, view.element);
        o.board.target_points = symmetry.relabel_points(&o.board.target_points, view.element);
        kept.push(o);
    }
    Ok(kept)
}

/// Makes robot 2's labelling of a symmetric target agree with robot 1's by gravity
/// (both bases upright), or refuses; see the crate docs, "Symmetric targets".
fn align_symmetric_between_robots(
    target: &Target,
    symmetry: &TargetSymmetry,
    obs1: &RobotObservations,
    obs2: &mut RobotObservations,
) -> Result<(), PipelineError> {
    let base_from_target = |obs: &RobotObservations| -> Result<Iso3, PipelineError> {
        let b: Vec<Iso3> = obs
            .observations
            .iter()
            .map(|o| o.board.base_from_flange)
            .collect();
        let c: Vec<Iso3> = obs
            .observations
            .iter()
            .map(|o| o.camera_from_target)
            .collect();
        let x = handeye::hand_eye(&b, &c, HandEyeMethod::Park).map_err(calib(&obs.robot))?;
        handeye::base_from_target_given(&x, &b, &c).map_err(calib(&obs.robot))
    };
    let w1 = base_from_target(obs1)?;
    let w2 = base_from_target(obs2)?;
    let options = GravityOptions::default();
    let between = resolve_between_robots(&w1, &w2, symmetry, &options);
    let Some(k) = between.element else {
        let angles: Vec<String> = symmetry
            .elements()
            .iter()
            .zip(&between.up_angles)
            .map(|(e, a)| format!("{} {:.1}°", e.name, a.to_degrees()))
            .collect();
        return Err(PipelineError::SymmetricTargetBetweenRobots {
            target: target.describe(),
            robot1: obs1.robot.clone(),
            robot2: obs2.robot.clone(),
            turns: format!("{} ways", symmetry.len()),
            reason: format!(
                "the board is tilted {:.1}° out of the horizontal, and the bases' up directions \
                 seen from the board are apart by {} for the possible labellings (need one \
                 within {:.0}° and the others {:.0}° further)",
                between.board_tilt_rad.to_degrees(),
                angles.join(", "),
                options.max_up_disagreement_rad.to_degrees(),
                options.min_up_separation_rad.to_degrees()
            ),
        });
    };
    tracing::info!(
        robot = obs2.robot,
        tilt_deg = between.board_tilt_rad.to_degrees(),
        "symmetric target: robot 2 labelled by '{}' (gravity)",
        symmetry.elements()[k].name
    );
    for o in &mut obs2.observations {
        o.camera_from_target = symmetry.relabel_pose(&o.camera_from_target, k);
        o.board.target_points = symmetry.relabel_points(&o.board.target_points, k);
    }
    Ok(())
}

fn covariance6(m: &Matrix6<f64>) -> [[f64; 6]; 6] {
    let s = (m + m.transpose()) * 0.5;
    let mut out = [[0.0; 6]; 6];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = s[(i, j)];
        }
    }
    out
}

/// A hand-eye estimate of one robot, with the method that made it.
#[derive(Debug, Clone)]
pub struct HandEyeRun {
    pub estimate: HandEyeEstimate,
    pub result: HandEyeResult,
    /// The split-half check of the refined method (`None` for a closed form, or
    /// too few captures to split); its covariance is already widened by it.
    pub split: Option<SplitCheck>,
}

impl HandEyeRun {
    /// The warning an operator needs when the check saw a systematic robot error.
    pub fn systematic_warning(&self) -> Option<String> {
        self.split.filter(SplitCheck::beyond_chance).map(|s| {
            systematic_message(
                &format!("robot {}'s T_flange_camera", self.result.robot),
                &s,
            )
        })
    }
}

/// Computes one robot's hand-eye by the chosen method. Closed forms are reported
/// with the covariance of the reprojection problem evaluated at their estimate.
///
/// When the robot's intrinsics were estimated from its images
/// ([`RobotObservations::estimated_intrinsics`]) they are refined with the
/// hand-eye (`refine_intrinsics` is switched on for this fit), so the covariance
/// includes their uncertainty; the refined camera is
/// [`HandEyeEstimate::camera`](b2b_calib::refine::HandEyeEstimate).
pub fn hand_eye(
    obs: &RobotObservations,
    choice: HandEyeChoice,
    options: &RefineOptions,
) -> Result<HandEyeRun, PipelineError> {
    hand_eye_with(obs, choice, &options_for(options, &[obs]))
}

/// [`hand_eye`] with `options` as given (intrinsics refined only when they say so).
fn hand_eye_with(
    obs: &RobotObservations,
    choice: HandEyeChoice,
    options: &RefineOptions,
) -> Result<HandEyeRun, PipelineError> {
    let start = Instant::now();
    let (obs, _) = screen_observations(obs, &format!("captures of robot {}", obs.robot))?;
    check_enough_captures(&obs)?;
    let obs = &obs;
    let robot = obs.robot.as_str();
    let base_from_flange: Vec<Iso3> = obs
        .observations
        .iter()
        .map(|o| o.board.base_from_flange)
        .collect();
    let camera_from_target: Vec<Iso3> = obs
        .observations
        .iter()
        .map(|o| o.camera_from_target)
        .collect();
    let boards: Vec<BoardCapture> = obs.observations.iter().map(|o| o.board.clone()).collect();
    let mut rejections: Vec<Option<Rejection>> = vec![None; boards.len()];
    let mut split = None;
    let estimate = match choice {
        HandEyeChoice::ClosedForm(m) => {
            let x = handeye::hand_eye(&base_from_flange, &camera_from_target, m)
                .map_err(calib(robot))?;
            let w = handeye::base_from_target_given(&x, &base_from_flange, &camera_from_target)
                .map_err(calib(robot))?;
            evaluate_hand_eye(&obs.camera, &boards, (x, w), options).map_err(calib(robot))?
        }
        HandEyeChoice::RobotWorld(m) => {
            let rw = handeye::robot_world(&base_from_flange, &camera_from_target, m)
                .map_err(calib(robot))?;
            evaluate_hand_eye(
                &obs.camera,
                &boards,
                (rw.flange_from_camera, rw.base_from_target),
                options,
            )
            .map_err(calib(robot))?
        }
        HandEyeChoice::Refined => {
            let run = estimate_hand_eye(
                &RobotCaptures {
                    camera: &obs.camera,
                    captures: &boards,
                    camera_from_target: &camera_from_target,
                },
                options,
            )
            .map_err(calib(robot))?;
            // Not logged here: a live agent recomputes its hand-eye with every
            // capture; `agent handeye` prints it once (HandEyeRun::systematic_warning).
            split = run.split;
            rejections = run.rejections;
            run.estimate
        }
    };
    let solve_ms = start.elapsed().as_secs_f64() * 1e3;
    if options.refine_intrinsics {
        let c = &estimate.camera;
        tracing::info!(
            robot,
            estimated = obs.estimated_intrinsics.is_some(),
            fx = c.fx,
            fy = c.fy,
            cx = c.cx,
            cy = c.cy,
            dist = ?&c.dist[..5],
            "camera intrinsics refined with the hand-eye"
        );
    }
    let result = HandEyeResult {
        format: HANDEYE_FORMAT.to_owned(),
        robot: robot.to_owned(),
        method: choice.name(),
        flange_from_camera: Pose::from_isometry(&estimate.flange_from_camera),
        covariance: covariance6(&estimate.flange_from_camera_covariance),
        base_from_target: Some(Pose::from_isometry(&estimate.base_from_target)),
        reprojection_rms_px: estimate.rms_px,
        per_capture: observation_fits(obs, &rejections, &estimate.per_capture)
            .map(|(o, rms_px, outlier_corners)| CaptureResidual {
                image: o.image.clone().unwrap_or_else(|| format!("row {}", o.row)),
                rms_px,
                outlier_corners,
            })
            .collect(),
        captures: {
            let (used, rejected) = after_fit(obs, &rejections);
            CaptureSummary {
                used: [(robot.to_owned(), used)].into_iter().collect(),
                rejected,
                per_capture: Vec::new(),
            }
        },
        timings_ms: Timings {
            detect: obs.detect_ms,
            solve: solve_ms,
            total: obs.detect_ms + solve_ms,
        },
    };
    Ok(HandEyeRun {
        estimate,
        result,
        split,
    })
}

/// Which method computes `base1_from_base2`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum B2bMethod {
    Board,
    Multimarker,
    Rgbd,
}

impl FromStr for B2bMethod {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "board" => Ok(B2bMethod::Board),
            "multimarker" => Ok(B2bMethod::Multimarker),
            "rgbd" => Ok(B2bMethod::Rgbd),
            _ => Err(format!(
                "unknown method '{s}': expected board, multimarker or rgbd"
            )),
        }
    }
}

impl B2bMethod {
    /// The name used on the command line and in results.
    pub fn name(&self) -> &'static str {
        match self {
            B2bMethod::Board => "board",
            B2bMethod::Multimarker => "multimarker",
            B2bMethod::Rgbd => "rgbd",
        }
    }

    /// The default for a dataset's target kind (shared/interfaces.md).
    pub fn default_for(target: &b2b_dataset::Target) -> B2bMethod {
        match target {
            b2b_dataset::Target::Multimarker { .. } => B2bMethod::Multimarker,
            _ => B2bMethod::Board,
        }
    }
}

/// A robot's camera as a calibration used it.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotCamera {
    pub robot: String,
    /// After the joint fit: the dataset's own unless intrinsics were refined.
    pub camera: CameraModel,
    /// Whether the joint fit refined the intrinsics.
    pub refined: bool,
    /// `Some` when the dataset gave none and they were estimated from the images.
    pub estimated: Option<EstimatedIntrinsics>,
    /// The robot's pose error as the joint fit found it in the residuals
    /// (`None` where no joint fit was made).
    pub pose_error: Option<b2b_calib::refine::FittedNoise>,
}

impl RobotCamera {
    /// One line for the console: the camera and where it came from.
    pub fn describe(&self) -> String {
        let c = &self.camera;
        let d = &c.dist;
        let origin = match (&self.estimated, self.refined) {
            (Some(e), refined) => format!(
                "ESTIMATED from {} images (no intrinsics given; initial fit of {} at {:.3} px{})",
                e.images_used,
                e.terms.names(),
                e.rms_px,
                if refined {
                    ", then refined jointly"
                } else {
                    ", not refined further"
                }
            ),
            (None, true) => "given, refined jointly (--refine-intrinsics)".to_owned(),
            (None, false) => "given".to_owned(),
        };
        format!(
            "camera {}: fx {:.2} fy {:.2} cx {:.2} cy {:.2} dist [{:.5}, {:.5}, {:.5}, {:.5}, {:.5}]: {origin}",
            self.robot, c.fx, c.fy, c.cx, c.cy, d[0], d[1], d[2], d[3], d[4]
        )
    }
}

/// A base-to-base result and the cameras it was computed with.
#[derive(Debug, Clone)]
pub struct CalibrationRun {
    pub result: CalibrationResult,
    /// Per robot, in the dataset's order (empty for the RGB-D method, which uses
    /// the dataset's intrinsics as given).
    pub cameras: Vec<RobotCamera>,
    /// What was seen in each robot's captures, in the dataset's order (the
    /// target's detections and the captures rejected before the fit; empty for
    /// the RGB-D method), for recordings and reports.
    pub observations: Vec<RobotObservations>,
    /// How far the covariance had to be widened to hold the captures' own
    /// spread (`None` for the RGB-D method, which has no such check).
    pub spread: Option<SpreadCheck>,
}

/// A joint fit's result, its cameras, and how far its covariance had to be
/// widened.
#[derive(Debug, Clone)]
pub struct JointFit {
    pub result: CalibrationResult,
    /// Per robot, in the observations' order.
    pub cameras: Vec<RobotCamera>,
    pub spread: SpreadCheck,
}

/// The largest factor the covariance of the bases was widened by to hold the
/// captures' leave-one-out spread (the capture-clustered jackknife; see
/// `b2b_calib::refine`), and what chance alone would give.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpreadCheck {
    /// On a variance, at least 1 (1: the noise model's covariance held it).
    pub factor: f64,
    /// The captures the fit used, over all robots.
    pub captures: usize,
    /// The covariance's dimension (6 per base after the reference).
    pub dims: usize,
}

impl SpreadCheck {
    /// The widening, in standard deviation.
    pub fn sigma_factor(&self) -> f64 {
        self.factor.max(1.0).sqrt()
    }

    /// About the largest widening (in standard deviation) the spread of
    /// `captures` draws gives by chance when the noise model is right: the
    /// edge of the sample covariance's eigenvalues (Marchenko-Pastur),
    /// `1 + sqrt(dims / (captures - 1))`. At 12-30 captures it is about the
    /// 90th percentile of the widening of equally informative captures (a
    /// Monte-Carlo test checks it): one well-modelled calibration in ten reads
    /// "beyond chance".
    pub fn chance(&self) -> f64 {
        1.0 + (self.dims as f64 / (self.captures.max(2) - 1) as f64).sqrt()
    }

    /// Whether the widening is beyond chance: the robots' errors have a shape
    /// the noise model does not express, or a few captures carry much of the
    /// fit (a capture-clustered jackknife overstates the spread then; a set
    /// of heavily occluded views rendered with noise of the model's own shape
    /// shows 2.7x).
    pub fn beyond_chance(&self) -> bool {
        self.sigma_factor() > self.chance()
    }

    /// One line for an operator.
    pub fn describe(&self) -> String {
        let (s, c, n) = (self.sigma_factor(), self.chance(), self.captures);
        if self.beyond_chance() {
            format!(
                "covariance widened by up to {s:.2}x in σ to hold the captures' own spread, beyond the about {c:.2}x chance gives with {n} equally informative captures: the robots' errors have a shape the noise model does not express, or a few captures carry much of the fit; the reported uncertainty includes the spread either way"
            )
        } else {
            format!(
                "covariance: the captures' own spread fits the noise model (widened by up to {s:.2}x in σ; chance gives up to about {c:.2}x with {n} captures)"
            )
        }
    }
}

/// The offline base-to-base calibration of a two-robot dataset.
pub fn base_to_base(
    ds: &Dataset,
    method: B2bMethod,
    options: &RefineOptions,
) -> Result<CalibrationResult, PipelineError> {
    base_to_base_run(ds, method, options).map(|r| r.result)
}

/// [`base_to_base`] with the cameras used. Robots without intrinsics in the
/// dataset get them estimated from their images and refined jointly (board and
/// multimarker methods; the RGB-D method needs them given).
pub fn base_to_base_run(
    ds: &Dataset,
    method: B2bMethod,
    options: &RefineOptions,
) -> Result<CalibrationRun, PipelineError> {
    let start = Instant::now();
    let target = target_of(ds)?;
    match (method, target.is_board()) {
        (B2bMethod::Board, true) | (B2bMethod::Multimarker, false) => {}
        (B2bMethod::Board, false) => {
            return Err(PipelineError::MethodTargetMismatch {
                manifest: ds.root.join("dataset.json"),
                method: "board",
                needs: "a board target (checkerboard, charuco, aruco_grid)",
                found: "a multimarker set".into(),
                instead: "multimarker",
            });
        }
        (B2bMethod::Multimarker, true) => {
            return Err(PipelineError::MethodTargetMismatch {
                manifest: ds.root.join("dataset.json"),
                method: "multimarker",
                needs: "a multimarker target",
                found: format!("'{}'", ds.manifest.target.kind()),
                instead: "board",
            });
        }
        (B2bMethod::Rgbd, _) => {
            for r in &ds.manifest.robots {
                if r.camera.is_none() {
                    return Err(PipelineError::NoIntrinsics {
                        robot: r.id.clone(),
                        manifest: ds.root.join("dataset.json"),
                    });
                }
            }
            return rgbd::rgbd_base_to_base(ds, options, &rgbd::RgbdOptions::default()).map(|r| {
                CalibrationRun {
                    result: r.result,
                    cameras: Vec::new(),
                    observations: Vec::new(),
                    spread: None,
                }
            });
        }
    }
    if ds.manifest.robots.len() < 2 {
        return Err(not_two_robots(ds));
    }
    let mut observed = ds
        .manifest
        .robots
        .iter()
        .map(|r| observe_robot(ds, &r.id))
        .collect::<Result<Vec<_>, _>>()?;
    let symmetry = target.symmetry();
    if !symmetry.is_trivial() {
        let (first, others) = observed.split_at_mut(1);
        for other in others {
            align_symmetric_between_robots(&target, &symmetry, &first[0], other)?;
        }
    }
    let board_centre = target.centre();
    let robots: Vec<&RobotObservations> = observed.iter().collect();
    let JointFit {
        mut result,
        cameras,
        spread,
    } = bases_and_cameras_from_observations(&robots, &board_centre, options, method)?;
    result.timings_ms.total = start.elapsed().as_secs_f64() * 1e3;
    for c in &cameras {
        if c.estimated.is_some() {
            tracing::info!("{}", c.describe());
        }
    }
    Ok(CalibrationRun {
        result,
        cameras,
        observations: observed,
        spread: Some(spread),
    })
}

/// Base-to-base from both robots' observations (offline or received live), by the
/// board method. `board_centre` (in the target frame) centres the workspace over which
/// the touch error is predicted.
pub fn base_to_base_from_observations(
    robots: [&RobotObservations; 2],
    board_centre: &Point3<f64>,
    options: &RefineOptions,
) -> Result<CalibrationResult, PipelineError> {
    base_to_base_from_observations_with(&robots, board_centre, options, B2bMethod::Board)
}

/// [`base_to_base_from_observations`] recording `method` in the result. The board
/// and multimarker methods are the same joint reprojection problem: the
/// observations carry each capture's 3-D target points (board corners, or the
/// corners of every marker seen, planar or not) and pixels, and the refinement
/// projects them through `T_camera_target` without assuming a plane.
///
/// With more than two robots (the first is the reference) every base is solved
/// in one problem; see [`CalibrationResult::bases`].
pub fn base_to_base_from_observations_with(
    robots: &[&RobotObservations],
    board_centre: &Point3<f64>,
    options: &RefineOptions,
    method: B2bMethod,
) -> Result<CalibrationResult, PipelineError> {
    bases_and_cameras_from_observations(robots, board_centre, options, method).map(|f| f.result)
}

/// Every robot's base in the first robot's, as one problem over all their
/// observations of one target, with every camera and robot pose error after
/// the joint fit (in `robots`' order) and its [`SpreadCheck`].
/// Intrinsics estimated from the images are refined in the joint fit
/// ([`options_for`]); the closed-form seeds use the initial cameras. With more
/// than two robots the result also holds `reference`, every base and every
/// pair without the reference. [`base_to_base_from_observations_with`] keeps
/// the result only.
pub fn bases_and_cameras_from_observations(
    robots: &[&RobotObservations],
    board_centre: &Point3<f64>,
    options: &RefineOptions,
    method: B2bMethod,
) -> Result<JointFit, PipelineError> {
    let options = &options_for(options, robots);
    if method == B2bMethod::Rgbd {
        return Err(PipelineError::Unsupported(
            "method rgbd needs the images and depth of a dataset (coordinator calibrate --method rgbd); captures on the bus carry neither".into(),
        ));
    }
    let solve_start = Instant::now();
    let mut screened = robots
        .iter()
        .map(|o| screen_observations(o, &format!("captures of robot {}", o.robot)).map(|s| s.0))
        .collect::<Result<Vec<_>, _>>()?;
    // A robot without enough usable captures is named alone, with why, before
    // the joint problem (which would call it unplaced, or blame every robot).
    for o in &screened {
        check_enough_captures(o)?;
    }
    // The targets no robot saw are left out of the problem (a dataset may list
    // more than one operation uses): the others are numbered densely.
    let mut seen_targets: Vec<usize> = screened
        .iter()
        .flat_map(|o| o.observations.iter().map(|o| o.board.target))
        .collect();
    seen_targets.sort_unstable();
    seen_targets.dedup();
    for o in screened.iter_mut().flat_map(|o| o.observations.iter_mut()) {
        o.board.target = seen_targets
            .binary_search(&o.board.target)
            .unwrap_or_else(|_| unreachable!("every seen target is listed"));
    }
    let main_target_seen = seen_targets.first() == Some(&0);
    let inputs: Vec<(Vec<BoardCapture>, Vec<Iso3>)> = screened
        .iter()
        .map(|o| {
            (
                o.observations.iter().map(|x| x.board.clone()).collect(),
                o.observations
                    .iter()
                    .map(|x| x.camera_from_target)
                    .collect(),
            )
        })
        .collect();
    let captures: Vec<RobotCaptures<'_>> = screened
        .iter()
        .zip(&inputs)
        .map(|(o, (board, poses))| RobotCaptures {
            camera: &o.camera,
            captures: board,
            camera_from_target: poses,
        })
        .collect();
    let ids: Vec<&str> = screened.iter().map(|o| o.robot.as_str()).collect();
    let all = ids.join("+");
    let capture_refs: Vec<&RobotCaptures<'_>> = captures.iter().collect();
    // The model selection's closed forms take the PnP poses as they are; where
    // the intrinsics were estimated from the captures, those come from the first
    // estimate, while the refinement refines the cameras. So the closed forms get
    // the cameras the default fit refines and the poses fitted with them.
    let closed_inputs = closed_form_inputs(&screened, &capture_refs, options);
    let closed_captures: Vec<RobotCaptures<'_>> = match &closed_inputs {
        Some(inputs) => captures
            .iter()
            .zip(inputs)
            .map(|(c, (camera, poses))| RobotCaptures {
                camera,
                captures: c.captures,
                camera_from_target: poses,
            })
            .collect(),
        None => captures.clone(),
    };
    let closed_refs: Vec<&RobotCaptures<'_>> = closed_captures.iter().collect();
    let selected =
        b2b_calib::select::estimate_bases_selected_with(&capture_refs, &closed_refs, options)
            .map_err(|e| match e {
                CalibError::Disconnected { cut_off } => PipelineError::Disconnected {
                    reference: ids[0].to_owned(),
                    cut_off: cut_off.iter().map(|r| ids[*r].to_owned()).collect(),
                },
                e => calib(&all)(e),
            })?;
    let model_selection = select::model_selection(&selected);
    let run = selected.run;
    for (k, split) in run.splits.iter().enumerate() {
        if let Some(split) = split.filter(SplitCheck::beyond_chance) {
            let what = if k == 0 {
                "base1_from_base2".to_owned()
            } else {
                format!("the base of {} in {}'s", ids[k + 1], ids[0])
            };
            warn_systematic(&what, &split);
        }
    }
    let joint = &run.estimate;
    let centres_in_ref = target_centres_in_ref(
        &screened,
        &joint.ref_from_targets,
        main_target_seen.then_some(board_centre),
    );
    let seen: Vec<Vec<usize>> = screened
        .iter()
        .map(|o| {
            let mut t: Vec<usize> = o.observations.iter().map(|o| o.board.target).collect();
            t.sort_unstable();
            t.dedup();
            t
        })
        .collect();
    // The predicted touch error of robot b's base in robot a's, over the
    // workspace about the target both see (in a's base); with several targets
    // and none shared, about the middle of the targets either sees.
    let pair = |a: usize, b: usize| {
        let (a_from_b, cov) = joint.pair(a, b);
        let shared: Vec<usize> = seen[a]
            .iter()
            .copied()
            .filter(|t| seen[b].contains(t))
            .collect();
        let around = if shared.is_empty() {
            let mut either = seen[a].clone();
            either.extend(&seen[b]);
            either.sort_unstable();
            either.dedup();
            either
        } else {
            shared
        };
        let centre_in_ref = around
            .iter()
            .fold(Point3::origin(), |acc, t| acc + centres_in_ref[*t].coords)
            / around.len().max(1) as f64;
        let centre = joint.base(a).inverse() * centre_in_ref;
        let (mean, p95) = predicted_error(&cov, &workspace_points(&centre), 0.0);
        (a_from_b, cov, PredictedError { mean, p95 })
    };
    let (base1_from_base2, covariance, predicted) = pair(0, 1);
    let n = screened.len();
    let (bases, pairs) = if n > 2 {
        let bases = (1..n)
            .map(|r| {
                let (t, cov, predicted) = pair(0, r);
                (
                    ids[r].to_owned(),
                    b2b_protocol::BaseResult {
                        ref_from_base: Pose::from_isometry(&t),
                        covariance: covariance6(&cov),
                        predicted_touch_error_m: predicted,
                    },
                )
            })
            .collect();
        let pairs = (1..n)
            .flat_map(|a| (a + 1..n).map(move |b| (a, b)))
            .map(|(a, b)| {
                let (t, cov, predicted) = pair(a, b);
                b2b_protocol::PairResult {
                    a: ids[a].to_owned(),
                    b: ids[b].to_owned(),
                    a_from_b: Pose::from_isometry(&t),
                    covariance: covariance6(&cov),
                    predicted_touch_error_m: predicted,
                }
            })
            .collect();
        (bases, pairs)
    } else {
        (Default::default(), Vec::new())
    };
    let solve_ms = solve_start.elapsed().as_secs_f64() * 1e3;
    let mut used = std::collections::BTreeMap::new();
    let mut rejected = Vec::new();
    for (o, r) in screened.iter().zip(&run.rejections) {
        let (count, out) = after_fit(o, r);
        used.insert(o.robot.clone(), count);
        rejected.extend(out);
    }
    let detect_ms: f64 = screened.iter().map(|o| o.detect_ms).sum();
    let result = CalibrationResult {
        format: RESULT_FORMAT.to_owned(),
        method: method.name().to_owned(),
        base1_from_base2: Pose::from_isometry(&base1_from_base2),
        covariance: covariance6(&covariance),
        predicted_touch_error_m: predicted,
        hand_eye: screened
            .iter()
            .zip(&joint.flange_from_camera)
            .map(|(o, x)| (o.robot.clone(), Pose::from_isometry(x)))
            .collect(),
        captures: CaptureSummary {
            used,
            rejected,
            per_capture: screened
                .iter()
                .zip(&run.rejections)
                .zip(&joint.per_capture)
                .flat_map(|((o, r), fit)| capture_fits(o, r, fit))
                .collect(),
        },
        timings_ms: Timings {
            detect: detect_ms,
            solve: solve_ms,
            total: detect_ms + solve_ms,
        },
        reference: Some(ids[0].to_owned()),
        bases,
        pairs,
        hand_eye_covariance: screened
            .iter()
            .zip(&joint.flange_from_camera_covariance)
            .map(|(o, c)| (o.robot.clone(), covariance6(c)))
            .collect(),
        warnings: Vec::new(),
        findings: Vec::new(),
        verdict: None,
        model_selection,
    };
    let spread = SpreadCheck {
        factor: run.estimate.spread_factor,
        captures: result.captures.used.values().sum(),
        dims: run.estimate.covariance.nrows(),
    };
    let mut result = result;
    result.findings.extend(causes::intrinsics_findings(robots));
    result
        .findings
        .extend(screened.iter().flat_map(causes::robot_findings));
    result.findings.extend(causes::spread_finding(&spread));
    let cameras = robots
        .iter()
        .zip(run.estimate.cameras)
        .zip(run.estimate.noise)
        .map(|((o, camera), noise)| RobotCamera {
            robot: o.robot.clone(),
            camera,
            refined: options.refine_intrinsics,
            estimated: o.estimated_intrinsics.clone(),
            pose_error: Some(noise),
        })
        .collect();
    Ok(JointFit {
        result,
        cameras,
        spread,
    })
}

/// Per robot, the camera and poses the model selection's closed forms take
/// when some robot's intrinsics were estimated from its captures: that robot's
/// camera as the default fit refines it, each capture's pose fitted again with
/// it (the first pose where that fit fails); the others' as they are. `None`
/// when no intrinsics were estimated, the noise model is given (no selection
/// then) or the default fit fails (the selection runs as before).
fn closed_form_inputs(
    screened: &[RobotObservations],
    captures: &[&RobotCaptures<'_>],
    options: &RefineOptions,
) -> Option<Vec<(CameraModel, Vec<Iso3>)>> {
    if !screened.iter().any(|o| o.estimated_intrinsics.is_some())
        || options.noise != b2b_calib::refine::NoiseModel::Estimated
    {
        return None;
    }
    let first = b2b_calib::estimate::estimate_bases(captures, options).ok()?;
    Some(
        screened
            .iter()
            .zip(captures)
            .zip(first.estimate.cameras)
            .map(|((o, c), refined)| {
                if o.estimated_intrinsics.is_none() {
                    return (c.camera.clone(), c.camera_from_target.to_vec());
                }
                let poses = o
                    .observations
                    .iter()
                    .zip(c.camera_from_target)
                    .map(|(x, first_pose)| {
                        pose_with(x, &refined).map_or(*first_pose, |p| p.camera_from_target)
                    })
                    .collect();
                (refined, poses)
            })
            .collect(),
    )
}

/// Each target's centre in the reference base: the main target's is
/// `board_centre` (the target model's; given when target 0 is the main
/// target), a further target's the mean of its corners seen.
fn target_centres_in_ref(
    robots: &[RobotObservations],
    ref_from_targets: &[Iso3],
    board_centre: Option<&Point3<f64>>,
) -> Vec<Point3<f64>> {
    ref_from_targets
        .iter()
        .enumerate()
        .map(|(t, ref_from_target)| {
            if let (0, Some(centre)) = (t, board_centre) {
                return ref_from_target * centre;
            }
            let seen = robots
                .iter()
                .flat_map(|o| o.observations.iter())
                .map(|o| &o.board)
                .filter(|b| b.target == t);
            ref_from_target * b2b_calib::estimate::target_centre(seen)
        })
        .collect()
}

/// Each observation with its fit: the RMS of its inlier corners (`None` when it
/// was left out before the fit or has none) and its outlier corners. The fit's
/// entries run over the captures the seed's screen kept; one rejected there as
/// a gross row counts every corner as an outlier. Both result files report it.
fn observation_fits<'a>(
    obs: &'a RobotObservations,
    rejections: &'a [Option<Rejection>],
    fit: &'a [(f64, usize)],
) -> impl Iterator<Item = (&'a Observation, Option<f64>, usize)> + 'a {
    let mut fit = fit.iter();
    obs.observations.iter().zip(rejections).map(move |(o, r)| {
        let (rms_px, outliers) = match r {
            Some(Rejection::Gross { .. }) => (f64::NAN, o.board.pixels.len()),
            _ => fit.next().copied().unwrap_or((f64::NAN, 0)),
        };
        (o, rms_px.is_finite().then_some(rms_px), outliers)
    })
}

/// Each observation's fit for `RESULT.json` ([`observation_fits`]) with the
/// direction it was seen from.
fn capture_fits(
    obs: &RobotObservations,
    rejections: &[Option<Rejection>],
    fit: &[(f64, usize)],
) -> Vec<b2b_protocol::CaptureFit> {
    observation_fits(obs, rejections, fit)
        .map(|(o, rms_px, outlier_corners)| {
            let camera_in_target = o.camera_from_target.inverse().translation.vector;
            let d = camera_in_target
                .try_normalize(1e-12)
                .unwrap_or_else(nalgebra::Vector3::z);
            b2b_protocol::CaptureFit {
                robot: obs.robot.clone(),
                row: o.row,
                image: o.image.clone(),
                rms_px,
                outlier_corners,
                view_direction: [d.x, d.y, d.z],
            }
        })
        .collect()
}

/// The captures a fit used, and every rejected one with its reason: those
/// observation refused before the fit, then those the fit left out.
fn after_fit(
    obs: &RobotObservations,
    rejections: &[Option<Rejection>],
) -> (usize, Vec<RejectedCapture>) {
    let mut rejected = obs.rejected.clone();
    for (o, r) in obs.observations.iter().zip(rejections) {
        if let Some(r) = r {
            tracing::warn!(robot = %obs.robot, row = o.row, image = ?o.image, "capture left out: {r}");
            rejected.push(RejectedCapture {
                robot: obs.robot.clone(),
                image: o.image.clone(),
                row: Some(o.row),
                reason: r.to_string(),
            });
        }
    }
    let used = rejections.iter().filter(|r| r.is_none()).count();
    (used, rejected)
}

/// Checks a result against touch pairs of its first two robots; `tip_sigma_m`
/// is each pointer's tip noise.
pub fn verify(
    result: &CalibrationResult,
    touches: &[TouchPair],
    tip_sigma_m: f64,
) -> Result<(VerifyReport, TouchMetrics), PipelineError> {
    verify_pair(result, None, touches, tip_sigma_m)
}

/// Robot `b`'s base in robot `a`'s as a result gives it, with the covariance of
/// its left perturbation (in `a`'s base): the first two robots' fields, a base
/// in `bases`, a pair in `pairs`, or one of those inverted.
pub fn pair_transform(
    result: &CalibrationResult,
    a: &str,
    b: &str,
) -> Result<(Iso3, Matrix6<f64>), PipelineError> {
    let no = |why: String| PipelineError::NoPair {
        a: a.to_owned(),
        b: b.to_owned(),
        why,
    };
    let invalid = |source| PipelineError::InvalidResult { source };
    let robots: Vec<&str> = result.hand_eye.keys().map(String::as_str).collect();
    for r in [a, b] {
        if !robots.contains(&r) {
            return Err(no(format!(
                "it has no robot '{r}' (its robots: {})",
                robots.join(", ")
            )));
        }
    }
    if a == b {
        return Err(no("a pair needs two different robots".into()));
    }
    let Some(reference) = result.reference.as_deref() else {
        return Err(no(
            "it does not name its reference robot (written by an older version); \
             without --pair it checks T_base1_base2"
                .into(),
        ));
    };
    let cov = |c: &b2b_protocol::Covariance6| Matrix6::from_fn(|i, j| c[i][j]);
    // `x_from_y` and its covariance, as stored, for the (x, y) the file holds.
    let stored = |x: &str, y: &str| -> Result<Option<(Iso3, Matrix6<f64>)>, PipelineError> {
        if x == reference {
            if let Some(base) = result.bases.get(y) {
                let t = base
                    .ref_from_base
                    .to_isometry(&format!("bases.{y}.T_ref_base"))
                    .map_err(invalid)?;
                return Ok(Some((t, cov(&base.covariance))));
            }
            if result.bases.is_empty() && robots.len() == 2 {
                let t = result
                    .base1_from_base2
                    .to_isometry("T_base1_base2")
                    .map_err(invalid)?;
                return Ok(Some((t, cov(&result.covariance))));
            }
            return Ok(None);
        }
        for (i, p) in result.pairs.iter().enumerate() {
            if p.a == x && p.b == y {
                let t = p
                    .a_from_b
                    .to_isometry(&format!("pairs[{i}].T_a_b"))
                    .map_err(invalid)?;
                return Ok(Some((t, cov(&p.covariance))));
            }
        }
        Ok(None)
    };
    if let Some(found) = stored(a, b)? {
        return Ok(found);
    }
    if let Some((b_from_a, c)) = stored(b, a)? {
        // T⁻¹ with T' = exp(δ) T: T'⁻¹ = exp(-Ad(T⁻¹) δ) T⁻¹.
        let a_from_b = b_from_a.inverse();
        let ad = b2b_calib::pose::adjoint(&a_from_b);
        let c = ad * c * ad.transpose();
        return Ok((a_from_b, (c + c.transpose()) * 0.5));
    }
    Err(no(format!(
        "it holds {} (reference {reference})",
        if result.pairs.is_empty() {
            "only the bases in the reference's base".to_owned()
        } else {
            "the bases and the pairs without the reference, but not this one".to_owned()
        }
    )))
}

/// Checks a result against touch pairs of robots `pair = (a, b)` (columns 1-3
/// in `a`'s base, 4-6 in `b`'s); `None` checks the first two robots'
/// `T_base1_base2`.
pub fn verify_pair(
    result: &CalibrationResult,
    pair: Option<(&str, &str)>,
    touches: &[TouchPair],
    tip_sigma_m: f64,
) -> Result<(VerifyReport, TouchMetrics), PipelineError> {
    result
        .validate()
        .map_err(|source| PipelineError::InvalidResult { source })?;
    let (a_from_b, cov) = match pair {
        Some((a, b)) => pair_transform(result, a, b)?,
        None => (
            result
                .base1_from_base2
                .to_isometry("T_base1_base2")
                .map_err(|source| PipelineError::InvalidResult { source })?,
            Matrix6::from_fn(|i, j| result.covariance[i][j]),
        ),
    };
    let pairs: Vec<_> = touches
        .iter()
        .map(|t| (t.tip1_in_base1, t.tip2_in_base2))
        .collect();
    let m = verify_touches(&a_from_b, &cov, &pairs, tip_sigma_m)
        .map_err(|source| PipelineError::Touches { source })?;
    let names = match pair {
        Some((a, b)) => [a.to_owned(), b.to_owned()],
        None => {
            let mut ids = result.hand_eye.keys().cloned();
            let first = result.reference.clone().or_else(|| ids.next());
            let first = first.unwrap_or_else(|| "robot 1".into());
            let second = result
                .hand_eye
                .keys()
                .find(|k| **k != first)
                .cloned()
                .unwrap_or_else(|| "robot 2".into());
            [first, second]
        }
    };
    let findings = causes::swapped_robots(&a_from_b, &pairs, &m, [&names[0], &names[1]])
        .into_iter()
        .collect();
    Ok((
        VerifyReport {
            n: m.n,
            touch_mean_mm: m.mean_m * 1e3,
            touch_rms_mm: m.rms_m * 1e3,
            touch_max_mm: m.max_m * 1e3,
            procrustes_linear_error_mm: m.procrustes_linear_m * 1e3,
            procrustes_angular_error_deg: m.procrustes_angular_rad.to_degrees(),
            within_predicted_p95: m.within_predicted_p95,
            iso9283: repeated_locations(&a_from_b, touches)?,
            bound_check: Some(touch_bound_check(&m.bound_check)),
            verdict: None,
            findings,
        },
        m,
    ))
}

/// The touch check as `verify --json` writes it.
fn touch_bound_check(b: &b2b_calib::metrics::BoundCheck) -> b2b_protocol::TouchBoundCheck {
    b2b_protocol::TouchBoundCheck {
        offset_chi2: b.offset.chi2,
        offset_dof: b.offset.dof,
        offset_p: b.offset.p_value,
        scatter_chi2: b.scatter.chi2,
        scatter_dof: b.scatter.dof,
        scatter_p: b.scatter.p_value,
        offset_beyond_chance: b.offset.beyond_chance(),
        scatter_beyond_chance: b.scatter.beyond_chance(),
        offset_sigma_mm: b.offset_sigma_m * 1e3,
        scatter_sigma_mm: b.scatter_sigma_m * 1e3,
    }
}

/// ISO 9283 AP and RP per location touched at least twice, in the order the
/// locations first appear: robot 2's touches mapped into `base1` by the result are
/// the attained positions, robot 1's mean touch of the location the commanded one.
fn repeated_locations(
    base1_from_base2: &Iso3,
    touches: &[TouchPair],
) -> Result<Vec<b2b_protocol::LocationIso9283>, PipelineError> {
    // Grouped in one pass (a file of many locations stays linear).
    let mut index: std::collections::HashMap<&str, usize> = std::collections::HashMap::new();
    let mut groups: Vec<(&str, Vec<&TouchPair>)> = vec![];
    for t in touches {
        if let Some(l) = t.location.as_deref() {
            let k = *index.entry(l).or_insert_with(|| {
                groups.push((l, vec![]));
                groups.len() - 1
            });
            groups[k].1.push(t);
        }
    }
    let mut out = vec![];
    for (location, group) in groups {
        if group.len() < 2 {
            continue;
        }
        let n = group.len() as f64;
        let commanded = Point3::from(
            group
                .iter()
                .map(|t| t.tip1_in_base1.coords)
                .sum::<nalgebra::Vector3<f64>>()
                / n,
        );
        let attained: Vec<Point3<f64>> = group
            .iter()
            .map(|t| base1_from_base2 * t.tip2_in_base2)
            .collect();
        let iso = b2b_calib::metrics::iso9283(&commanded, &attained)
            .map_err(|source| PipelineError::Touches { source })?;
        out.push(b2b_protocol::LocationIso9283 {
            location: location.to_owned(),
            n: group.len(),
            accuracy_mm: iso.accuracy_m * 1e3,
            repeatability_mm: iso.repeatability_m * 1e3,
        });
    }
    Ok(out)
}

/// Loads a dataset, naming the folder in the error.
pub fn load_dataset(dir: &Path) -> Result<Dataset, PipelineError> {
    Ok(Dataset::load(dir)?)
}

/// What an operator is told when the split-half check found the captures on
/// opposite sides of the board disagreeing beyond their noise: the size of the
/// gap and what to do (the covariance already includes the gap, not the common
/// part).
fn systematic_message(what: &str, split: &SplitCheck) -> String {
    let d = split.difference;
    format!(
        "the captures on opposite sides of the board give {what} {:.2} mm / {:.3}° apart, \
         beyond their noise (chi-square {:.0} on 6 dof): a systematic robot error (kinematic \
         parameters, a sagging base or mount); the bound includes the disagreement, but not \
         the part common to all captures: give the arms' absolute accuracy \
         (--robot-accuracy-mm, --robot-accuracy-deg) and check with touch points",
        d.fixed_rows::<3>(3).norm() * 1e3,
        d.fixed_rows::<3>(0).norm().to_degrees(),
        split.chi2
    )
}

fn warn_systematic(what: &str, split: &SplitCheck) {
    tracing::warn!("{}", systematic_message(what, split));
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ISO 9283 per repeated location, against values worked by hand: robot 1
    /// touches p four times; robot 2's touches, mapped through a known transform,
    /// land at p + (1, 0, 0), p + (3, 0, 0), p + (2, 1, 0), p + (2, -1, 0) mm. The
    /// barycentre is p + (2, 0, 0) mm (AP 2 mm); the distances to it are all 1 mm
    /// (RP = 1 + 3 * 0 = 1 mm). A location touched once gives nothing.
    #[test]
    fn repeated_locations_give_iso_9283_ap_and_rp() {
        let b1_from_b2 = Iso3::new(
            nalgebra::Vector3::new(1.0, 0.1, 0.0),
            nalgebra::Vector3::new(0.0, 0.0, 3.0),
        );
        let p = Point3::new(0.5, 0.2, 0.1);
        let mm = |x: f64, y: f64| nalgebra::Vector3::new(x, y, 0.0) * 1e-3;
        let mut touches: Vec<TouchPair> = [mm(1.0, 0.0), mm(3.0, 0.0), mm(2.0, 1.0), mm(2.0, -1.0)]
            .iter()
            .enumerate()
            .map(|(k, d)| TouchPair {
                row: k + 1,
                location: Some("A".into()),
                tip1_in_base1: p,
                tip2_in_base2: b1_from_b2.inverse() * (p + d),
            })
            .collect();
        touches.push(TouchPair {
            row: 5,
            location: Some("B".into()),
            tip1_in_base1: p,
            tip2_in_base2: b1_from_b2.inverse() * p,
        });
        let iso = repeated_locations(&b1_from_b2, &touches).unwrap();
        assert_eq!(iso.len(), 1);
        assert_eq!((iso[0].location.as_str(), iso[0].n), ("A", 4));
        assert!((iso[0].accuracy_mm - 2.0).abs() < 1e-9, "{iso:?}");
        assert!((iso[0].repeatability_mm - 1.0).abs() < 1e-9, "{iso:?}");
    }

    /// Rejections grouped by reason (numbers and the image's own path aside),
    /// most frequent first, with counts and an example; the rest counted.
    #[test]
    fn rejection_summary_counts_the_top_reasons() {
        let r = |row: usize, reason: &str| RejectedCapture {
            robot: "robot2".into(),
            image: Some(format!("images/{row:03}.png")),
            row: Some(row),
            reason: reason.into(),
        };
        let mut rejected: Vec<RejectedCapture> = (1..=9)
            .map(|k| {
                r(
                    k,
                    &format!("/d/robot2/images/{k:03}.png: no checkerboard found"),
                )
            })
            .collect();
        rejected.push(r(10, "PnP residual 7.2 px"));
        rejected.push(r(11, "PnP residual 9.8 px"));
        rejected.push(r(12, "a"));
        rejected.push(r(13, "b"));
        let s = rejection_summary(&rejected);
        assert!(
            s.starts_with("9 x /d/robot2/images/001.png: no checkerboard found (e.g. row 1, images/001.png); 2 x PnP residual 7.2 px (e.g. row 10"),
            "{s}"
        );
        assert!(
            s.ends_with("; 1 x a (e.g. row 12, images/012.png); 1 for other reasons"),
            "{s}"
        );
        let obs = RobotObservations {
            robot: "robot2".into(),
            camera: CameraModel::new(640, 480, [600.0, 600.0, 320.0, 240.0], &[]).unwrap(),
            observations: vec![],
            rejected,
            detect_ms: 0.0,
            estimated_intrinsics: None,
        };
        let e = check_enough_captures(&obs).unwrap_err().to_string();
        assert!(
            e.starts_with("robot robot2: too few captures: 0, need at least 3; 13 of its 13 captures rejected: 9 x "),
            "{e}"
        );
    }

    /// The review's example: "too few captures: 0, need at least 3" was printed twice,
    /// once in the message and once as its source.
    #[test]
    fn too_few_captures_prints_its_cause_once() {
        let e = PipelineError::Calib {
            robot: "robot1".into(),
            source: CalibError::TooFewCaptures { got: 0, need: 3 },
        };
        let chain = error_chain(&e);
        assert_eq!(chain, "robot robot1: too few captures: 0, need at least 3");
        assert_eq!(chain.matches("too few captures").count(), 1, "{chain}");
    }

    /// Every variant that wraps an error: its message leaves the source out, and the
    /// chain names the cause once.
    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "missing for the test");
        let wrapped = [
            PipelineError::Calib {
                robot: "robot2".into(),
                source: CalibError::NonFinite("base_from_flange[3]".into()),
            },
            PipelineError::Vision(VisionError::Io {
                path: "/d/robot1/images/000.png".into(),
                source: io,
            }),
        ];
        for e in wrapped {
            let mut causes = Vec::new();
            let mut next = std::error::Error::source(&e);
            while let Some(c) = next {
                causes.push(c.to_string());
                next = c.source();
            }
            let cause = causes.last().expect("a wrapped error has a cause");
            let chain = error_chain(&e);
            assert_eq!(chain.matches(cause.as_str()).count(), 1, "{chain}");
        }
    }

    #[test]
    fn the_spread_check_says_whether_chance_explains_the_widening() {
        let check = |factor: f64, captures: usize, dims: usize| SpreadCheck {
            factor,
            captures,
            dims,
        };
        // 2 x 12 captures, one base: chance gives up to 1 + sqrt(6/23) in σ.
        let c = check(1.145, 24, 6);
        assert!((c.chance() - (1.0 + (6.0f64 / 23.0).sqrt())).abs() < 1e-12);
        assert!((c.sigma_factor() - 1.145f64.sqrt()).abs() < 1e-12);
        assert!(!c.beyond_chance());
        let line = c.describe();
        assert!(
            line.contains("fits the noise model")
                && line.contains("1.07x")
                && line.contains("1.51x"),
            "{line}"
        );
        // Four times the variance is beyond chance with 60 captures, not with 6.
        let wide = check(4.0, 60, 6);
        assert!(wide.beyond_chance());
        let line = wide.describe();
        assert!(
            line.contains("2.00x")
                && line.contains("a shape the noise model does not express")
                && line.contains("a few captures carry much of the fit"),
            "{line}"
        );
        assert!(!check(4.0, 6, 6).beyond_chance());
        // Below 1 is no widening; too few captures do not divide by zero.
        assert_eq!(check(0.5, 1, 6).sigma_factor(), 1.0);
        assert!(check(1.0, 1, 6).chance().is_finite());
    }

    /// The chance edge when the noise model is right and the captures are
    /// equally informative: each capture an independent draw, the estimate
    /// their mean, its covariance the model's, widened by the engine's own
    /// `widen_to_spread` to the captures' jackknife spread. The edge is about
    /// the 90th percentile of the widening (measured: 10.2-10.9% beyond it over
    /// 4,000 draws each; Marchenko-Pastur's asymptotic edge, at these few
    /// captures), so "beyond chance" comes about once in ten calibrations of a
    /// well-modelled rig.
    #[test]
    fn the_chance_edge_is_about_the_90th_percentile_of_a_well_modelled_spread() {
        use nalgebra::{DMatrix, DVector};
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let mut rng = rand::rngs::StdRng::seed_from_u64(23);
        let mut normal = move || -> f64 { StandardNormal.sample(&mut rng) };
        for (dims, captures) in [(6, 12), (6, 24), (6, 30), (12, 24)] {
            let draws = 4000;
            let mut beyond = 0;
            for _ in 0..draws {
                let x: Vec<DVector<f64>> = (0..captures)
                    .map(|_| DVector::from_fn(dims, |_, _| normal()))
                    .collect();
                let n = captures as f64;
                let sum: DVector<f64> = x.iter().fold(DVector::zeros(dims), |s, v| s + v);
                // Leave-one-out estimates and their spread (the capture-clustered jackknife).
                let loo: Vec<DVector<f64>> = x.iter().map(|v| (&sum - v) / (n - 1.0)).collect();
                let mean = loo.iter().fold(DVector::zeros(dims), |s, v| s + v) / n;
                let spread = loo.iter().fold(DMatrix::zeros(dims, dims), |s, v| {
                    s + (v - &mean) * (v - &mean).transpose()
                }) * ((n - 1.0) / n);
                let mut covariance = DMatrix::identity(dims, dims) / n;
                let factor = b2b_calib::refine::widen_to_spread(&mut covariance, &spread);
                let check = SpreadCheck {
                    factor,
                    captures,
                    dims,
                };
                if check.beyond_chance() {
                    beyond += 1;
                }
            }
            let share = beyond as f64 / draws as f64;
            eprintln!(
                "{dims} dims, {captures} captures: {:.1}% beyond the chance edge",
                100.0 * share
            );
            assert!(
                (0.067..0.15).contains(&share),
                "{dims} dims, {captures} captures: {share}"
            );
        }
    }
}
