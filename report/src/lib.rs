//! The calibration report: one `index.html` with SVG plots that a person reads at
//! a glance.
//!
//! [`write_report`] takes [`ReportInputs`] and writes into a folder:
//!
//! | file | what | needs |
//! |---|---|---|
//! | `index.html` | the numbers (transform, sigma, predicted error, verify metrics, hand-eyes), the rejected captures and why, and the plots | RESULT.json |
//! | `residuals.svg` | reprojection RMS per capture, per robot; rejected captures as crosses | per-capture details |
//! | `residual_hist.svg` | distribution of the per-capture RMS, per robot | per-capture details |
//! | `touch_errors.svg` | each touch's error against its predicted 95% bound (or, with only `verify --json`, mean/RMS/max against the predicted mean and 95%) | a verify report or per-touch errors |
//! | `touch_hist.svg` | distribution of the touch errors with the predicted mean and 95% | per-touch errors |
//! | `view_sphere.svg` | where the cameras looked from: viewing directions in the target frame on an equal-area projection of the hemisphere | per-capture viewing directions |
//! | `rejections.svg` | rejected captures counted by reason | any rejection |
//! | `hand_eye_history_mm.svg`, `hand_eye_history_deg.svg` | each cart's hand-eye over time: how far (mm) and how much turned (deg) from that robot's first recorded hand-eye | the coordinator's history ([`HandEyeHistoryEntry`]) |
//!
//! The result's `warnings` (for example a camera mount that moved against the
//! cart's history) head the page in a red box.
//!
//! The inputs are designed to degrade: RESULT.json alone gives the numbers and the
//! rejection list; `verify --json` adds the touch summary; the hand-eye files
//! (`per_capture`), the capture messages and verify's per-touch errors add the
//! plots that need them; the coordinator's history adds the hand-eye plots. A plot
//! without its data is left out and the page says what would fill it. Everything is deterministic (no clock), so two reports of
//! the same inputs are byte-identical.
//!
//! `report/docs/screenshot.png` is the fixture report of `tests/screenshot.rs` as
//! headless Chromium draws it (half size).
//!
//! The SVG is hand-written ([`svg`]): the plots are simple and a plotting crate
//! would bring a font stack for text the browser draws anyway.
//!
//! The result's own files are this crate's too: RESULT.json's siblings in the
//! formats other tools read ([`formats`]: ROS YAML, OpenCV YAML, a ROS 2 launch
//! file, a URDF) and their writing all or nothing, with the refusals that come
//! before any work ([`write`]: a destination a file cannot replace, an output
//! over its own input).

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use b2b_protocol::messages::Capture;
use b2b_protocol::{CalibrationResult, HandEyeResult, Pose, ProtocolError, VerifyReport};
use nalgebra::{UnitQuaternion, Vector3};

pub mod formats;
pub mod svg;
pub mod write;

use svg::{Axes, GREEN, GREY, LEGEND_Y, PALETTE, RED, Svg, escape, legend};

/// Errors of this crate; each names the file or field at fault.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{path}: cannot read")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    /// serde_json's message carries the line and column.
    #[error("{path}: not a valid {what}")]
    Parse {
        path: PathBuf,
        what: &'static str,
        source: serde_json::Error,
    },
    #[error("{path}")]
    Invalid {
        path: PathBuf,
        source: ProtocolError,
    },
    #[error("{field}: {reason}")]
    Input { field: String, reason: String },
    #[error("{path}: cannot write")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    /// The result's transform is not one (passed on as it is: it names the field).
    #[error(transparent)]
    Transform(#[from] ProtocolError),
    #[error("cannot serialise the {what}")]
    Serialize {
        what: &'static str,
        #[source]
        source: serde_json::Error,
    },

    // Writing result files ([`write`]).
    #[error("cannot create {}", path.display())]
    CreateFolder {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A destination a file cannot replace: a directory, a pipe, a device.
    #[error(
        "{} is {kind}: it cannot be replaced by the output file; remove it or choose another path",
        path.display()
    )]
    NotReplaceable { path: PathBuf, kind: &'static str },
    /// [`write::write_together`] refused before writing anything.
    #[error(
        "nothing was written (the previous files, if any, are left as they were: {})",
        joined(files)
    )]
    NothingWritten {
        files: Vec<PathBuf>,
        #[source]
        source: Box<ReportError>,
    },
    #[error("cannot write {} (through {}); nothing was replaced", path.display(), temporary.display())]
    WriteThrough {
        path: PathBuf,
        temporary: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot keep {} while replacing it", path.display())]
    KeepPrevious {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot replace {}; nothing was replaced", path.display())]
    Replace {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An output path inside the dataset it is computed from.
    #[error(
        "{flag} {} is inside the dataset folder {} (resolved: {}): a result is never \
         written into the data it comes from; choose a path outside the dataset",
        path.display(),
        dataset.display(),
        resolved.display()
    )]
    OutputInsideDataset {
        flag: String,
        path: PathBuf,
        dataset: PathBuf,
        resolved: PathBuf,
    },
    /// An output path that is one of the inputs.
    #[error(
        "{flag} {} is the input {}: it would be overwritten; choose another path",
        path.display(),
        input.display()
    )]
    OutputIsInput {
        flag: String,
        path: PathBuf,
        input: PathBuf,
    },
}

/// Paths as one comma-separated list.
fn joined(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| p.display().to_string())
        .collect::<Vec<_>>()
        .join(", ")
}

fn bad(field: impl Into<String>, reason: impl Into<String>) -> ReportError {
    ReportError::Input {
        field: field.into(),
        reason: reason.into(),
    }
}

/// One capture as the report sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptureDetail {
    pub robot: String,
    /// The capture's number at its robot (the x axis of the residual plot).
    pub index: u64,
    /// Image file or other name.
    pub label: Option<String>,
    /// Reprojection RMS (px), when the capture was used.
    pub rms_px: Option<f64>,
    /// Corners the robust stage rejected.
    pub outlier_corners: Option<usize>,
    /// Unit vector from the target's origin to the camera, in the target frame.
    pub view_direction: Option<[f64; 3]>,
    /// Why it was not used.
    pub rejected: Option<String>,
}

impl CaptureDetail {
    /// From a capture message: its index, image, RMS, rejection, and the viewing
    /// direction from its `T_camera_target`.
    pub fn from_capture(robot: &str, capture: &Capture) -> Result<Self, ReportError> {
        let field = format!("capture {} of {robot}", capture.index);
        let (rms_px, view_direction) = match &capture.observation {
            Some(o) => {
                let camera_from_target = o
                    .camera_from_target
                    .to_isometry("T_camera_target")
                    .map_err(|e| bad(&field, e.to_string()))?;
                let camera_in_target = camera_from_target.inverse().translation.vector;
                let dir = camera_in_target
                    .try_normalize(1e-12)
                    .ok_or_else(|| bad(&field, "camera at the target's origin"))?;
                (Some(o.rms_px), Some([dir.x, dir.y, dir.z]))
            }
            None => (None, None),
        };
        Ok(CaptureDetail {
            robot: robot.to_owned(),
            index: capture.index,
            label: capture.image.clone(),
            rms_px,
            outlier_corners: None,
            view_direction,
            rejected: capture.rejected.clone(),
        })
    }
}

/// One verify touch.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TouchDetail {
    /// Row in `touch_points.csv`.
    pub row: usize,
    /// |tip1 - base1_from_base2 * tip2| (m).
    pub error_m: f64,
    /// The predicted 95% bound of this touch (m).
    pub bound95_m: f64,
}

/// One robot's hand-eye as the coordinator's history recorded it. Plain data:
/// the coordinator reads its database and passes the rows; this crate reads no
/// database.
#[derive(Debug, Clone, PartialEq)]
pub struct HandEyeHistoryEntry {
    pub robot: String,
    /// When it was recorded, Unix milliseconds (the plots' time axis).
    pub recorded_at_unix_ms: i64,
    /// The same time as people read it, e.g. `2025-06-01 12:00:03 UTC`.
    pub recorded_at: String,
    /// `T_flange_camera`.
    pub flange_from_camera: Pose,
}

/// Everything a report can show; only `result` is required.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportInputs {
    pub title: String,
    pub result: CalibrationResult,
    /// Where the result came from, shown on the page.
    pub result_source: Option<String>,
    pub verify: Option<VerifyReport>,
    pub verify_source: Option<String>,
    pub captures: Vec<CaptureDetail>,
    pub touches: Vec<TouchDetail>,
    /// Earlier (and this result's) hand-eyes of its robots, any order.
    pub hand_eye_history: Vec<HandEyeHistoryEntry>,
    /// Where the history came from, shown on the page.
    pub history_source: Option<String>,
}

fn read_json<T: serde::de::DeserializeOwned>(
    path: &Path,
    what: &'static str,
) -> Result<T, ReportError> {
    let text = std::fs::read_to_string(path).map_err(|source| ReportError::Read {
        path: path.to_owned(),
        source,
    })?;
    serde_json::from_str(&text).map_err(|source| ReportError::Parse {
        path: path.to_owned(),
        what,
        source,
    })
}

impl ReportInputs {
    /// A report of a result alone: its per-capture panels come from the result's
    /// own `captures.per_capture` (offline and live results carry it) and its
    /// rejected captures.
    pub fn new(result: CalibrationResult) -> Self {
        let mut captures: Vec<CaptureDetail> = result
            .captures
            .per_capture
            .iter()
            .map(|c| CaptureDetail {
                robot: c.robot.clone(),
                index: c.row as u64,
                label: c.image.clone(),
                rms_px: c.rms_px,
                outlier_corners: Some(c.outlier_corners),
                view_direction: Some(c.view_direction),
                rejected: result
                    .captures
                    .rejected
                    .iter()
                    .find(|r| r.robot == c.robot && r.row == Some(c.row))
                    .map(|r| r.reason.clone()),
            })
            .collect();
        if !captures.is_empty() {
            // Captures refused before the fit (no board found, ...) are in the
            // rejected list only.
            for r in &result.captures.rejected {
                let known = captures
                    .iter()
                    .any(|c| c.robot == r.robot && Some(c.index) == r.row.map(|x| x as u64));
                if !known {
                    captures.push(CaptureDetail {
                        robot: r.robot.clone(),
                        index: r.row.unwrap_or(0) as u64,
                        label: r.image.clone(),
                        rms_px: None,
                        outlier_corners: None,
                        view_direction: None,
                        rejected: Some(r.reason.clone()),
                    });
                }
            }
        }
        ReportInputs {
            title: "Base-to-base calibration".to_owned(),
            result,
            result_source: None,
            verify: None,
            verify_source: None,
            captures,
            touches: Vec::new(),
            hand_eye_history: Vec::new(),
            history_source: None,
        }
    }

    /// Loads RESULT.json and, optionally, the `verify --json` report.
    pub fn from_files(result: &Path, verify: Option<&Path>) -> Result<Self, ReportError> {
        let r: CalibrationResult = read_json(result, "RESULT.json (b2b-result/1)")?;
        r.validate().map_err(|source| ReportError::Invalid {
            path: result.to_owned(),
            source,
        })?;
        let mut inputs = ReportInputs::new(r);
        inputs.result_source = Some(result.display().to_string());
        if let Some(v) = verify {
            let report: VerifyReport = read_json(v, "verify report (verify --json)")?;
            check_verify(&report).map_err(|e| match e {
                ReportError::Input { field, reason } => {
                    bad(format!("{}: {field}", v.display()), reason)
                }
                other => other,
            })?;
            inputs.verify = Some(report);
            inputs.verify_source = Some(v.display().to_string());
        }
        Ok(inputs)
    }

    /// Adds a hand-eye result's per-capture residuals (merged by robot and image
    /// with details already present) and its rejections.
    pub fn add_hand_eye(&mut self, hand_eye: &HandEyeResult) {
        let robot = hand_eye.robot.clone();
        for (i, c) in hand_eye.per_capture.iter().enumerate() {
            let existing = self
                .captures
                .iter_mut()
                .find(|d| d.robot == robot && d.label.as_deref() == Some(c.image.as_str()));
            match existing {
                Some(d) => {
                    d.rms_px = c.rms_px;
                    d.outlier_corners = Some(c.outlier_corners);
                }
                None => self.captures.push(CaptureDetail {
                    robot: robot.clone(),
                    index: i as u64,
                    label: Some(c.image.clone()),
                    rms_px: c.rms_px,
                    outlier_corners: Some(c.outlier_corners),
                    view_direction: None,
                    rejected: None,
                }),
            }
        }
        for r in &hand_eye.captures.rejected {
            let known = self
                .result
                .captures
                .rejected
                .iter()
                .any(|k| k.robot == r.robot && k.image == r.image && k.row == r.row);
            if !known {
                self.result.captures.rejected.push(r.clone());
            }
        }
    }

    /// Loads a `HANDEYE.json` and adds it as [`ReportInputs::add_hand_eye`] does.
    pub fn add_hand_eye_file(&mut self, path: &Path) -> Result<(), ReportError> {
        let he: HandEyeResult = read_json(path, "HANDEYE.json (b2b-handeye/1)")?;
        for (i, c) in he.per_capture.iter().enumerate() {
            if let Some(r) = c.rms_px
                && !(r.is_finite() && r >= 0.0)
            {
                return Err(bad(
                    format!("{}: per_capture[{i}].rms_px", path.display()),
                    format!("{r} is not a non-negative number"),
                ));
            }
        }
        self.add_hand_eye(&he);
        Ok(())
    }

    /// Checks every number the report draws.
    pub fn validate(&self) -> Result<(), ReportError> {
        self.result
            .validate()
            .map_err(|e| bad("result", e.to_string()))?;
        if let Some(v) = &self.verify {
            check_verify(v)?;
        }
        for c in &self.captures {
            let field = || format!("capture {} of {}", c.index, c.robot);
            if let Some(r) = c.rms_px
                && !(r.is_finite() && r >= 0.0)
            {
                return Err(bad(
                    field(),
                    format!("rms_px {r} is not a non-negative number"),
                ));
            }
            if let Some(d) = c.view_direction {
                let n = Vector3::from(d).norm();
                if !(n.is_finite() && (n - 1.0).abs() < 1e-6) {
                    return Err(bad(
                        field(),
                        format!("view direction {d:?} is not a unit vector"),
                    ));
                }
            }
        }
        for h in &self.hand_eye_history {
            h.flange_from_camera
                .to_isometry("T_flange_camera")
                .map_err(|e| {
                    bad(
                        format!("hand-eye history of {} at {}", h.robot, h.recorded_at),
                        e.to_string(),
                    )
                })?;
        }
        for t in &self.touches {
            if !(t.error_m.is_finite()
                && t.error_m >= 0.0
                && t.bound95_m.is_finite()
                && t.bound95_m > 0.0)
            {
                return Err(bad(
                    format!("touch row {}", t.row),
                    format!("error {} m, bound {} m", t.error_m, t.bound95_m),
                ));
            }
        }
        Ok(())
    }

    fn robots(&self) -> Vec<String> {
        let mut set: BTreeSet<String> = self.result.hand_eye.keys().cloned().collect();
        set.extend(self.result.captures.used.keys().cloned());
        set.extend(self.captures.iter().map(|c| c.robot.clone()));
        set.extend(
            self.result
                .captures
                .rejected
                .iter()
                .map(|r| r.robot.clone()),
        );
        set.into_iter().collect()
    }

    /// Every rejected capture: the result's list and the details', once each.
    fn rejections(&self) -> Vec<(String, String, String)> {
        let mut out: Vec<(String, String, String)> = self
            .result
            .captures
            .rejected
            .iter()
            .map(|r| {
                let what = match (&r.image, r.row) {
                    (Some(i), Some(row)) => format!("{i} (row {row})"),
                    (Some(i), None) => i.clone(),
                    (None, Some(row)) => format!("row {row}"),
                    (None, None) => "-".to_owned(),
                };
                (r.robot.clone(), what, r.reason.clone())
            })
            .collect();
        for c in &self.captures {
            if let Some(reason) = &c.rejected {
                let dup = self
                    .result
                    .captures
                    .rejected
                    .iter()
                    .any(|r| r.robot == c.robot && r.image.is_some() && r.image == c.label);
                if !dup {
                    let what = c
                        .label
                        .clone()
                        .unwrap_or_else(|| format!("capture {}", c.index));
                    out.push((c.robot.clone(), what, reason.clone()));
                }
            }
        }
        out
    }
}

fn check_verify(v: &VerifyReport) -> Result<(), ReportError> {
    for (name, x) in [
        ("touch_mean_mm", v.touch_mean_mm),
        ("touch_rms_mm", v.touch_rms_mm),
        ("touch_max_mm", v.touch_max_mm),
        ("procrustes_linear_error_mm", v.procrustes_linear_error_mm),
        (
            "procrustes_angular_error_deg",
            v.procrustes_angular_error_deg,
        ),
        ("within_predicted_p95", v.within_predicted_p95),
    ] {
        if !x.is_finite() {
            return Err(bad(name, format!("{x} is not finite")));
        }
    }
    if !(0.0..=1.0).contains(&v.within_predicted_p95) {
        return Err(bad(
            "within_predicted_p95",
            format!("{} is not a fraction in [0, 1]", v.within_predicted_p95),
        ));
    }
    if let Some(c) = &v.bound_check {
        for (name, x) in [
            ("bound_check.offset_chi2", c.offset_chi2),
            ("bound_check.scatter_chi2", c.scatter_chi2),
            ("bound_check.offset_sigma_mm", c.offset_sigma_mm),
            ("bound_check.scatter_sigma_mm", c.scatter_sigma_mm),
        ] {
            if !(x.is_finite() && x >= 0.0) {
                return Err(bad(name, format!("{x} is not a finite number >= 0")));
            }
        }
        for (name, p) in [
            ("bound_check.offset_p", c.offset_p),
            ("bound_check.scatter_p", c.scatter_p),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(bad(name, format!("{p} is not a probability")));
            }
        }
    }
    Ok(())
}

/// The files a report consists of.
#[derive(Debug, Clone, PartialEq)]
pub struct ReportFiles {
    pub index: PathBuf,
    pub plots: Vec<PathBuf>,
}

const PLOT_W: f64 = 580.0;
const PLOT_H: f64 = 320.0;

fn colour_of(robots: &[String], robot: &str) -> &'static str {
    robots
        .iter()
        .position(|r| r == robot)
        .map_or(GREY, |i| PALETTE[i % PALETTE.len()])
}

fn robot_legend(robots: &[String]) -> Vec<(String, String)> {
    robots
        .iter()
        .map(|r| (colour_of(robots, r).to_owned(), r.clone()))
        .collect()
}

/// Per-capture RMS against the capture number, one series per robot.
fn plot_residuals(inputs: &ReportInputs, robots: &[String]) -> Option<String> {
    let with_rms: Vec<&CaptureDetail> = inputs
        .captures
        .iter()
        .filter(|c| c.rms_px.is_some())
        .collect();
    if with_rms.is_empty() {
        return None;
    }
    let max_rms = with_rms.iter().filter_map(|c| c.rms_px).fold(0.0, f64::max);
    let max_index = inputs.captures.iter().map(|c| c.index).max().unwrap_or(0) as f64;
    let mut svg = Svg::new(PLOT_W, PLOT_H);
    let axes = Axes::new(
        PLOT_W,
        PLOT_H,
        (0.0, max_index.max(1.0)),
        (0.0, max_rms * 1.1),
    );
    axes.draw(
        &mut svg,
        "Reprojection RMS per capture",
        "capture",
        "RMS (px)",
        true,
    );
    for robot in robots {
        let mut series: Vec<&CaptureDetail> = with_rms
            .iter()
            .copied()
            .filter(|c| &c.robot == robot)
            .collect();
        series.sort_by_key(|c| c.index);
        let colour = colour_of(robots, robot);
        let pts: Vec<(f64, f64)> = series
            .iter()
            .map(|c| (axes.x(c.index as f64), axes.y(c.rms_px.unwrap_or(0.0))))
            .collect();
        svg.polyline(&pts, colour, 1.2);
        for (c, (x, y)) in series.iter().zip(&pts) {
            let title = format!(
                "{robot} capture {}{}: {:.3} px{}",
                c.index,
                c.label
                    .as_ref()
                    .map_or(String::new(), |l| format!(" ({l})")),
                c.rms_px.unwrap_or(0.0),
                c.outlier_corners
                    .map_or(String::new(), |o| format!(", {o} outlier corners"))
            );
            svg.circle(*x, *y, 4.0, colour, Some(&title));
        }
    }
    let mut rejected_any = false;
    for c in inputs.captures.iter().filter(|c| c.rejected.is_some()) {
        rejected_any = true;
        let title = format!(
            "{} capture {} rejected: {}",
            c.robot,
            c.index,
            c.rejected.as_deref().unwrap_or("")
        );
        svg.cross(
            axes.x(c.index as f64),
            axes.y(0.0) - 6.0,
            5.0,
            RED,
            Some(&title),
        );
    }
    let mut entries = robot_legend(robots);
    if rejected_any {
        entries.push((RED.to_owned(), "rejected".to_owned()));
    }
    legend(&mut svg, PLOT_W - 16.0, LEGEND_Y, &entries);
    Some(svg.finish())
}

/// Counts `values` in `bins` equal bins over `[lo, hi]` (the end bins take what is outside).
fn histogram(values: &[f64], lo: f64, hi: f64, bins: usize) -> Vec<usize> {
    let mut counts = vec![0; bins];
    for v in values {
        let i = (((v - lo) / (hi - lo)) * bins as f64).floor().max(0.0) as usize;
        counts[i.min(bins - 1)] += 1;
    }
    counts
}

fn bin_count(n: usize) -> usize {
    ((n as f64).sqrt().round() as usize).clamp(5, 20)
}

/// Histogram of several series side by side in each bin, with optional
/// vertical marker lines (value, colour, label).
fn plot_histogram(
    title: &str,
    xlabel: &str,
    series: &[(String, &'static str, Vec<f64>)],
    markers: &[(f64, &'static str, String)],
    from_zero: bool,
) -> Option<String> {
    let n: usize = series.iter().map(|s| s.2.len()).sum();
    if n == 0 {
        return None;
    }
    let values = || {
        series
            .iter()
            .flat_map(|s| s.2.iter().copied())
            .chain(markers.iter().map(|m| m.0))
    };
    let max_v = values().fold(f64::NEG_INFINITY, f64::max);
    let min_v = if from_zero {
        0.0
    } else {
        values().fold(f64::INFINITY, f64::min)
    };
    let pad = 0.05 * (max_v - min_v);
    let (ticks, _) = svg::nice_ticks((min_v - pad).max(0.0), max_v + pad, 8);
    let lo = ticks[0];
    let hi = *ticks.last().unwrap_or(&(lo + 1.0));
    let bins = bin_count(n);
    let counts: Vec<Vec<usize>> = series
        .iter()
        .map(|s| histogram(&s.2, lo, hi, bins))
        .collect();
    let max_count = counts.iter().flatten().copied().max().unwrap_or(1);
    let mut svg = Svg::new(PLOT_W, PLOT_H);
    let axes = Axes::new(PLOT_W, PLOT_H, (lo, hi), (0.0, max_count as f64 * 1.1));
    axes.draw(&mut svg, title, xlabel, "count", false);
    let bin_w = (hi - lo) / bins as f64;
    let k = series.len().max(1) as f64;
    for (s, (name, colour, _)) in series.iter().enumerate() {
        for (b, &c) in counts[s].iter().enumerate() {
            if c == 0 {
                continue;
            }
            let (b0, b1) = (lo + b as f64 * bin_w, lo + (b + 1) as f64 * bin_w);
            let (x0, x1) = (axes.x(b0), axes.x(b1));
            let w = (x1 - x0 - 2.0) / k;
            let x = x0 + 1.0 + s as f64 * w;
            let y = axes.y(c as f64);
            let t = format!("{name}: {c} in [{b0:.3}, {b1:.3})");
            svg.rect(x, y, w, axes.y(0.0) - y, colour, Some(&t));
        }
    }
    let mut entries: Vec<(String, String)> = series
        .iter()
        .map(|(n, c, _)| (c.to_string(), n.clone()))
        .collect();
    for (v, colour, label) in markers {
        let x = axes.x(*v);
        svg.dashed(x, axes.top, x, axes.top + axes.height, colour, 2.0);
        entries.push((colour.to_string(), label.clone()));
    }
    legend(&mut svg, PLOT_W - 16.0, LEGEND_Y, &entries);
    Some(svg.finish())
}

/// Each touch's error against its predicted 95% bound, or, with only the verify
/// summary, its mean/RMS/max against the predicted mean and 95%.
fn plot_touch_errors(inputs: &ReportInputs) -> Option<String> {
    let pred = inputs.result.predicted_touch_error_m;
    let mut svg = Svg::new(PLOT_W, PLOT_H);
    if !inputs.touches.is_empty() {
        let mut touches = inputs.touches.clone();
        touches.sort_by_key(|t| t.row);
        let max = touches
            .iter()
            .map(|t| t.error_m.max(t.bound95_m))
            .fold(pred.p95, f64::max)
            * 1e3;
        let n = touches.len() as f64;
        let axes = Axes::new(PLOT_W, PLOT_H, (0.0, n), (0.0, max * 1.1));
        axes.draw(
            &mut svg,
            "Touch errors against the predicted 95% bound",
            "touch (in row order)",
            "error (mm)",
            true,
        );
        let slot = axes.width / n;
        for (i, t) in touches.iter().enumerate() {
            let x = axes.left + slot * i as f64;
            let over = t.error_m > t.bound95_m;
            let y = axes.y(t.error_m * 1e3);
            let title = format!(
                "row {}: {:.3} mm, bound {:.3} mm{}",
                t.row,
                t.error_m * 1e3,
                t.bound95_m * 1e3,
                if over { " (over)" } else { "" }
            );
            svg.rect(
                x + slot * 0.15,
                y,
                slot * 0.7,
                axes.y(0.0) - y,
                if over { RED } else { PALETTE[0] },
                Some(&title),
            );
            let yb = axes.y(t.bound95_m * 1e3);
            svg.line(x + slot * 0.05, yb, x + slot * 0.95, yb, "#111", 2.0);
        }
        let yp = axes.y(pred.p95 * 1e3);
        svg.dashed(axes.left, yp, axes.left + axes.width, yp, PALETTE[1], 2.0);
        let within = touches.iter().filter(|t| t.error_m <= t.bound95_m).count();
        legend(
            &mut svg,
            PLOT_W - 16.0,
            LEGEND_Y,
            &[
                (
                    PALETTE[0].to_owned(),
                    format!("inside ({within}/{})", touches.len()),
                ),
                (RED.to_owned(), "over".to_owned()),
                ("#111".to_owned(), "bound".to_owned()),
                (
                    PALETTE[1].to_owned(),
                    "result 95% (no tip noise)".to_owned(),
                ),
            ],
        );
        return Some(svg.finish());
    }
    let v = inputs.verify.as_ref()?;
    let bars = [
        ("mean", v.touch_mean_mm),
        ("RMS", v.touch_rms_mm),
        ("max", v.touch_max_mm),
        ("Procrustes", v.procrustes_linear_error_mm),
    ];
    let max = bars.iter().map(|b| b.1).fold(pred.p95 * 1e3, f64::max);
    let axes = Axes::new(PLOT_W, PLOT_H, (0.0, bars.len() as f64), (0.0, max * 1.1));
    axes.draw(
        &mut svg,
        &format!("Touch errors (n = {}) against the prediction", v.n),
        "",
        "error (mm)",
        true,
    );
    let slot = axes.width / bars.len() as f64;
    for (i, (name, val)) in bars.iter().enumerate() {
        let x = axes.left + slot * i as f64;
        let y = axes.y(*val);
        svg.rect(
            x + slot * 0.2,
            y,
            slot * 0.6,
            axes.y(0.0) - y,
            PALETTE[0],
            Some(&format!("{name}: {val:.3} mm")),
        );
        svg.text(
            x + slot / 2.0,
            axes.y(0.0) + 17.0,
            name,
            "middle",
            12.0,
            "#111",
        );
        svg.text(
            x + slot / 2.0,
            y - 4.0,
            &format!("{val:.3}"),
            "middle",
            11.0,
            "#111",
        );
    }
    let ym = axes.y(pred.mean * 1e3);
    let yp = axes.y(pred.p95 * 1e3);
    svg.dashed(axes.left, ym, axes.left + axes.width, ym, GREEN, 2.0);
    svg.dashed(axes.left, yp, axes.left + axes.width, yp, PALETTE[1], 2.0);
    legend(
        &mut svg,
        PLOT_W - 16.0,
        LEGEND_Y,
        &[
            (GREEN.to_owned(), "result mean".to_owned()),
            (
                PALETTE[1].to_owned(),
                "result 95% (no tip noise)".to_owned(),
            ),
        ],
    );
    Some(svg.finish())
}

/// Viewing directions on a Lambert azimuthal equal-area projection of the
/// hemisphere the cameras are in (the pole is the target's +z or -z, whichever
/// most cameras are on). Rings every 15 degrees of tilt from the pole.
fn plot_view_sphere(inputs: &ReportInputs, robots: &[String]) -> Option<String> {
    let dirs: Vec<(&CaptureDetail, Vector3<f64>)> = inputs
        .captures
        .iter()
        .filter_map(|c| c.view_direction.map(|d| (c, Vector3::from(d))))
        .collect();
    if dirs.is_empty() {
        return None;
    }
    let pole = if dirs.iter().filter(|(_, d)| d.z < 0.0).count() * 2 > dirs.len() {
        -1.0
    } else {
        1.0
    };
    let (w, h) = (PLOT_W, PLOT_H + 60.0);
    let mut svg = Svg::new(w, h);
    let (cx, cy) = (w / 2.0 - 40.0, h / 2.0 + 12.0);
    let radius = h / 2.0 - 34.0;
    // r(tilt) = 2 sin(tilt / 2), scaled so 90 degrees is the rim.
    let r_of = |tilt: f64| radius * (2.0 * (tilt / 2.0).sin()) / 2f64.sqrt();
    svg.text(
        16.0,
        20.0,
        &format!(
            "Pose coverage: directions to the cameras, target frame ({}z at the centre)",
            if pole > 0.0 { "+" } else { "-" }
        ),
        "start",
        14.0,
        "#111",
    );
    for deg in [15, 30, 45, 60, 75, 90] {
        let r = r_of((deg as f64).to_radians());
        svg.ring(cx, cy, r, if deg == 90 { "#333" } else { "#d0d0d0" });
        if deg % 30 == 0 {
            // Labels down the lower-right diagonal, clear of the axes.
            let d = r * std::f64::consts::FRAC_1_SQRT_2;
            svg.text(
                cx + d + 3.0,
                cy + d + 3.0,
                &format!("{deg}°"),
                "start",
                10.0,
                "#666",
            );
        }
    }
    svg.line(cx - radius, cy, cx + radius, cy, "#e4e4e4", 1.0);
    svg.line(cx, cy - radius, cx, cy + radius, "#e4e4e4", 1.0);
    svg.text(cx + radius + 4.0, cy + 14.0, "+x", "start", 11.0, "#333");
    svg.text(cx, cy - radius - 4.0, "+y", "middle", 11.0, "#333");
    let mut below = 0;
    for (c, d) in &dirs {
        let z = d.z * pole;
        let tilt = z.clamp(-1.0, 1.0).acos();
        if tilt > std::f64::consts::FRAC_PI_2 {
            below += 1;
        }
        let az = d.y.atan2(d.x);
        let r = r_of(tilt.min(std::f64::consts::FRAC_PI_2));
        let (x, y) = (cx + r * az.cos(), cy - r * az.sin());
        let title = format!(
            "{} capture {}: tilt {:.1}°, azimuth {:.1}°",
            c.robot,
            c.index,
            tilt.to_degrees(),
            az.to_degrees()
        );
        if c.rejected.is_some() {
            svg.cross(x, y, 4.0, GREY, Some(&title));
        } else {
            svg.circle(x, y, 5.0, colour_of(robots, &c.robot), Some(&title));
        }
    }
    // Tilt spread per robot: what a hand-eye needs is rotation diversity.
    let mut y = 56.0;
    for robot in robots {
        let tilts: Vec<f64> = dirs
            .iter()
            .filter(|(c, _)| &c.robot == robot && c.rejected.is_none())
            .map(|(_, d)| (d.z * pole).clamp(-1.0, 1.0).acos().to_degrees())
            .collect();
        if tilts.is_empty() {
            continue;
        }
        let lo = tilts.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = tilts.iter().copied().fold(0.0, f64::max);
        svg.rect(
            w - 170.0,
            y - 9.0,
            12.0,
            12.0,
            colour_of(robots, robot),
            None,
        );
        svg.text(w - 154.0, y + 1.0, robot, "start", 12.0, "#111");
        svg.text(
            w - 154.0,
            y + 17.0,
            &format!("{} views, tilt {lo:.0}-{hi:.0}°", tilts.len()),
            "start",
            11.0,
            "#444",
        );
        y += 40.0;
    }
    if below > 0 {
        svg.text(
            w - 170.0,
            y + 4.0,
            &format!("{below} behind the target (at the rim)"),
            "start",
            11.0,
            RED,
        );
    }
    Some(svg.finish())
}

/// Rejected captures counted by reason, horizontal bars.
fn plot_rejections(rejections: &[(String, String, String)], robots: &[String]) -> Option<String> {
    if rejections.is_empty() {
        return None;
    }
    let mut by_reason: BTreeMap<&str, BTreeMap<&str, usize>> = BTreeMap::new();
    for (robot, _, reason) in rejections {
        *by_reason
            .entry(reason.as_str())
            .or_default()
            .entry(robot.as_str())
            .or_default() += 1;
    }
    let mut reasons: Vec<(&str, usize, &BTreeMap<&str, usize>)> = by_reason
        .iter()
        .map(|(r, m)| (*r, m.values().sum(), m))
        .collect();
    reasons.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(b.0)));
    reasons.truncate(10);
    let row_h = 26.0;
    let h = 80.0 + row_h * reasons.len() as f64;
    let mut svg = Svg::new(PLOT_W, h);
    svg.text(
        16.0,
        20.0,
        "Rejected captures by reason",
        "start",
        14.0,
        "#111",
    );
    let max = reasons.iter().map(|r| r.1).max().unwrap_or(1) as f64;
    let (left, right) = (250.0, PLOT_W - 40.0);
    for (i, (reason, total, per_robot)) in reasons.iter().enumerate() {
        let y = 54.0 + row_h * i as f64;
        let label: String = if reason.chars().count() > 36 {
            reason.chars().take(35).chain(['…']).collect()
        } else {
            reason.to_string()
        };
        svg.text(left - 8.0, y + 14.0, &label, "end", 12.0, "#111");
        let mut x = left;
        for (robot, n) in per_robot.iter() {
            let w = (right - left) * *n as f64 / max;
            svg.rect(
                x,
                y + 2.0,
                w,
                row_h - 8.0,
                colour_of(robots, robot),
                Some(&format!("{robot}: {n} × {reason}")),
            );
            x += w;
        }
        svg.text(x + 4.0, y + 14.0, &total.to_string(), "start", 12.0, "#111");
    }
    legend(&mut svg, PLOT_W - 16.0, LEGEND_Y, &robot_legend(robots));
    Some(svg.finish())
}

/// One point of a robot's hand-eye over time: the entry, how far (mm) and how
/// much turned (deg) from that robot's first recorded hand-eye.
type DriftPoint<'a> = (&'a HandEyeHistoryEntry, f64, f64);

/// Each robot's history, oldest first, as offsets from its first hand-eye
/// (robots in colour order, then any others by id).
fn hand_eye_drift<'a>(
    inputs: &'a ReportInputs,
    robots: &[String],
) -> Vec<(String, Vec<DriftPoint<'a>>)> {
    let mut by_robot: BTreeMap<&str, Vec<&HandEyeHistoryEntry>> = BTreeMap::new();
    for h in &inputs.hand_eye_history {
        by_robot.entry(h.robot.as_str()).or_default().push(h);
    }
    let mut order: Vec<&str> = robots
        .iter()
        .map(String::as_str)
        .filter(|r| by_robot.contains_key(r))
        .collect();
    order.extend(by_robot.keys().filter(|r| !robots.iter().any(|x| x == *r)));
    order
        .into_iter()
        .map(|robot| {
            let mut entries = by_robot.remove(robot).unwrap_or_default();
            entries.sort_by_key(|h| h.recorded_at_unix_ms);
            // validate() has checked every pose.
            let pose =
                |h: &HandEyeHistoryEntry| h.flange_from_camera.to_isometry("T_flange_camera").ok();
            let first = entries.first().and_then(|h| pose(h));
            let points = entries
                .iter()
                .filter_map(|h| {
                    let (a, b) = (pose(h)?, first?);
                    let mm = (a.translation.vector - b.translation.vector).norm() * 1e3;
                    let deg = a.rotation.angle_to(&b.rotation).to_degrees();
                    Some((*h, mm, deg))
                })
                .collect();
            (robot.to_owned(), points)
        })
        .collect()
}

/// A time axis for Unix-ms instants: (unit name, seconds per unit) so the span
/// reads in round numbers.
fn time_unit(span_s: f64) -> (&'static str, f64) {
    if span_s <= 120.0 {
        ("seconds", 1.0)
    } else if span_s <= 2.0 * 3600.0 {
        ("minutes", 60.0)
    } else if span_s <= 48.0 * 3600.0 {
        ("hours", 3600.0)
    } else {
        ("days", 86_400.0)
    }
}

/// Each robot's hand-eye over record time: translation (`rotation` false, mm)
/// or rotation (deg) from its first recorded hand-eye.
fn plot_hand_eye_history(
    inputs: &ReportInputs,
    robots: &[String],
    rotation: bool,
) -> Option<String> {
    let drift = hand_eye_drift(inputs, robots);
    let all: Vec<&DriftPoint<'_>> = drift.iter().flat_map(|(_, p)| p).collect();
    let earliest = all.iter().min_by_key(|p| p.0.recorded_at_unix_ms)?.0;
    let latest = all.iter().map(|p| p.0.recorded_at_unix_ms).max()?;
    let span_s = (latest - earliest.recorded_at_unix_ms) as f64 / 1e3;
    let (unit, per) = time_unit(span_s);
    let x_of = |h: &HandEyeHistoryEntry| {
        (h.recorded_at_unix_ms - earliest.recorded_at_unix_ms) as f64 / 1e3 / per
    };
    let value = |p: &DriftPoint<'_>| if rotation { p.2 } else { p.1 };
    let max_v = all.iter().map(|p| value(p)).fold(0.0, f64::max);
    let y_max = if max_v > 0.0 {
        max_v * 1.15
    } else if rotation {
        0.01
    } else {
        0.1
    };
    let mut svg = Svg::new(PLOT_W, PLOT_H);
    let axes = Axes::new(
        PLOT_W,
        PLOT_H,
        (0.0, (span_s / per).max(1e-9)),
        (0.0, y_max),
    );
    let (title, ylabel, what) = if rotation {
        (
            "Hand-eye over time: rotation from the first",
            "rotation (°)",
            "°",
        )
    } else {
        (
            "Hand-eye over time: translation from the first",
            "translation (mm)",
            " mm",
        )
    };
    axes.draw(
        &mut svg,
        title,
        &format!("{unit} since {}", earliest.recorded_at),
        ylabel,
        false,
    );
    for (robot, points) in &drift {
        let colour = colour_of(robots, robot);
        let pts: Vec<(f64, f64)> = points
            .iter()
            .map(|p| (axes.x(x_of(p.0)), axes.y(value(p))))
            .collect();
        svg.polyline(&pts, colour, 1.2);
        let first = points.first().map_or("", |p| p.0.recorded_at.as_str());
        for (p, (x, y)) in points.iter().zip(&pts) {
            let title = format!(
                "{robot} {}: {:.3}{what} from its first hand-eye ({first})",
                p.0.recorded_at,
                value(p)
            );
            svg.circle(*x, *y, 4.0, colour, Some(&title));
        }
    }
    let entries: Vec<(String, String)> = drift
        .iter()
        .map(|(r, p)| {
            (
                colour_of(robots, r).to_owned(),
                format!("{r} ({})", p.len()),
            )
        })
        .collect();
    legend(&mut svg, PLOT_W - 16.0, LEGEND_Y, &entries);
    Some(svg.finish())
}

fn mm(v: f64) -> String {
    format!("{:.3}", v * 1e3)
}

/// The page's numbers: transform, sigma, prediction.
fn numbers_html(inputs: &ReportInputs) -> String {
    let r = &inputs.result;
    let mut h = String::new();
    let t = r.base1_from_base2.t;
    let q = r.base1_from_base2.q;
    let rot = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]));
    let (roll, pitch, yaw) = rot.euler_angles();
    let axis_angle = rot.scaled_axis();
    let sd: Vec<f64> = (0..6).map(|i| r.covariance[i][i].max(0.0).sqrt()).collect();
    let _ = write!(
        h,
        "<table class=\"num\"><tr><th></th><th>x</th><th>y</th><th>z</th></tr>\
         <tr><td>translation (mm)</td><td>{}</td><td>{}</td><td>{}</td></tr>\
         <tr><td>1&sigma; translation (mm)</td><td>{}</td><td>{}</td><td>{}</td></tr>\
         <tr><td>rotation roll / pitch / yaw (&deg;)</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td></tr>\
         <tr><td>rotation vector (&deg;)</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td></tr>\
         <tr><td>1&sigma; rotation (&deg;)</td><td>{:.4}</td><td>{:.4}</td><td>{:.4}</td></tr>\
         </table>\
         <p class=\"small\">quaternion x y z w: {:.8} {:.8} {:.8} {:.8}. Sigma is the square root of \
         the covariance diagonal over the left perturbation [rx ry rz tx ty tz].</p>",
        mm(t[0]),
        mm(t[1]),
        mm(t[2]),
        mm(sd[3]),
        mm(sd[4]),
        mm(sd[5]),
        roll.to_degrees(),
        pitch.to_degrees(),
        yaw.to_degrees(),
        axis_angle.x.to_degrees(),
        axis_angle.y.to_degrees(),
        axis_angle.z.to_degrees(),
        sd[0].to_degrees(),
        sd[1].to_degrees(),
        sd[2].to_degrees(),
        q[0],
        q[1],
        q[2],
        q[3],
    );
    h
}

fn hand_eye_html(inputs: &ReportInputs) -> String {
    let mut h = String::from(
        "<table class=\"num\"><tr><th>robot</th><th>T_flange_camera t (mm)</th>\
         <th>rotation vector (&deg;)</th><th>captures used</th></tr>",
    );
    for (robot, p) in &inputs.result.hand_eye {
        let q = p.q;
        let rot =
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(q[3], q[0], q[1], q[2]));
        let v = rot.scaled_axis();
        let used = inputs
            .result
            .captures
            .used
            .get(robot)
            .map_or("-".to_owned(), |n| n.to_string());
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{} {} {}</td><td>{:.3} {:.3} {:.3}</td><td>{used}</td></tr>",
            escape(robot),
            mm(p.t[0]),
            mm(p.t[1]),
            mm(p.t[2]),
            v.x.to_degrees(),
            v.y.to_degrees(),
            v.z.to_degrees(),
        );
    }
    h.push_str("</table>");
    if inputs.hand_eye_history.is_empty() {
        h.push_str(
            "<p class=\"small\">No hand-eye history given: <code>coordinator report</code> \
             plots each cart's hand-eye over time from the coordinator's state folder \
             (<code>--state-dir</code>).</p>",
        );
    } else {
        let mut robots: Vec<&str> = inputs
            .hand_eye_history
            .iter()
            .map(|e| e.robot.as_str())
            .collect();
        robots.sort_unstable();
        robots.dedup();
        let _ = write!(
            h,
            "<p class=\"small\">History: {} recorded hand-eyes of {}{}; plotted below.</p>",
            inputs.hand_eye_history.len(),
            escape(&robots.join(", ")),
            inputs
                .history_source
                .as_ref()
                .map_or(String::new(), |s| format!(" from {}", escape(s)))
        );
    }
    h
}

/// One verdict as a box: green PASS or red FAIL with its reasons.
fn one_verdict_html(what: &str, v: &b2b_protocol::Verdict) -> String {
    let (class, word) = if v.pass {
        ("verdict pass", "PASS")
    } else {
        ("verdict fail", "FAIL")
    };
    let mut h = format!(
        "<div class=\"{class}\"><h2>VERDICT: {word}</h2><p>{} against the tolerance of {} mm \
         (p95 touch error)</p>",
        escape(what),
        escape(&format!("{:.2}", v.tolerance_mm))
    );
    if !v.reasons.is_empty() {
        h.push_str("<ul>");
        for r in &v.reasons {
            let _ = write!(h, "<li>{}</li>", escape(r));
        }
        h.push_str("</ul>");
    }
    h.push_str("</div>\n");
    h
}

/// The verdicts (the result's, and the verification's when given), first on
/// the page, then what the checks found. A result of an older version has
/// no verdict: said so.
fn verdict_html(inputs: &ReportInputs) -> String {
    let mut h = match &inputs.result.verdict {
        Some(v) => one_verdict_html("The result", v),
        None => "<div class=\"verdict none\"><h2>VERDICT: none</h2><p>This result has no \
                 verdict (written by an older version): run coordinator calibrate or run \
                 again.</p></div>\n"
            .to_owned(),
    };
    if let Some(v) = inputs.verify.as_ref().and_then(|v| v.verdict.as_ref()) {
        h.push_str(&one_verdict_html("The touch-point verification", v));
    }
    if !inputs.result.findings.is_empty() {
        h.push_str("<div class=\"panel findings\"><h2>Findings</h2><ul>");
        for f in &inputs.result.findings {
            let _ = write!(
                h,
                "<li><b>{}{}</b>: {}</li>",
                escape(&f.kind),
                if f.fails { " (fails the verdict)" } else { "" },
                escape(&f.message)
            );
        }
        h.push_str("</ul></div>\n");
    }
    h
}

/// The result's warnings, in a red box at the top of the page.
fn warnings_html(inputs: &ReportInputs) -> String {
    if inputs.result.warnings.is_empty() {
        return String::new();
    }
    let mut h = String::from("<div class=\"alert\"><h2>Warnings</h2><ul>");
    for w in &inputs.result.warnings {
        let _ = write!(h, "<li>{}</li>", escape(w));
    }
    h.push_str("</ul></div>\n");
    h
}

fn verify_html(inputs: &ReportInputs) -> String {
    let pred = inputs.result.predicted_touch_error_m;
    let Some(v) = &inputs.verify else {
        return format!(
            "<p>No verify report: run <code>coordinator verify --json</code> and pass it with \
             <code>--verify</code>. Predicted touch error: mean {} mm, 95% {} mm.</p>",
            mm(pred.mean),
            mm(pred.p95)
        );
    };
    let share = v.within_predicted_p95 * 100.0;
    let class = if v.within_predicted_p95 >= 0.9 {
        "ok"
    } else {
        "warn"
    };
    // All touches at once against the result's error model (verify's
    // `bound_check`; absent in reports of older versions).
    let (check, check_note) = v.bound_check.as_ref().map_or_else(Default::default, |c| {
        let row = |what: &str, chi2: f64, dof: usize, p: f64, beyond: bool| {
            let class = if beyond { "warn" } else { "ok" };
            format!(
                "<tr><td>{what}</td><td class=\"{class}\">&chi;&sup2; {chi2:.1} on {dof} dof, \
                 p = {p:.2e}</td><td>p &ge; 0.005</td></tr>"
            )
        };
        let rows = row(
            "the result's offset against its covariance",
            c.offset_chi2,
            c.offset_dof,
            c.offset_p,
            c.offset_beyond_chance,
        ) + &row(
            "the touches' scatter against the tip noise",
            c.scatter_chi2,
            c.scatter_dof,
            c.scatter_p,
            c.scatter_beyond_chance,
        );
        let mut note = String::new();
        if c.offset_beyond_chance {
            note.push_str(&format!(
                " The result is off by more than its covariance allows: calibrate again with \
                 the arms' accuracy (these touches suggest about {:.2} mm).",
                c.offset_sigma_mm
            ));
        }
        if c.scatter_beyond_chance {
            note.push_str(&format!(
                " The touches scatter by about {:.3} mm per axis per arm beyond the tips' \
                 noise: noisier tips, or the arms' own error at the touch poses.",
                c.scatter_sigma_mm
            ));
        }
        (rows, note)
    });
    format!(
        "<table class=\"num\"><tr><th></th><th>measured</th><th>predicted by the result</th></tr>\
         <tr><td>touches</td><td>{}</td><td></td></tr>\
         <tr><td>mean error (mm)</td><td>{:.3}</td><td>{}</td></tr>\
         <tr><td>RMS error (mm)</td><td>{:.3}</td><td></td></tr>\
         <tr><td>95% of errors below (mm)</td><td></td><td>{}</td></tr>\
         <tr><td>max error (mm)</td><td>{:.3}</td><td></td></tr>\
         <tr><td>Procrustes linear (mm)</td><td>{:.3}</td><td></td></tr>\
         <tr><td>Procrustes angular (&deg;)</td><td>{:.4}</td><td></td></tr>\
         <tr><td>inside each touch's 95% bound</td><td class=\"{class}\">{share:.0}%</td><td>95%</td></tr>\
         {check}</table><p class=\"small\">The result's prediction covers the transform only; \
         each touch's bound in verify adds the pointer tips' noise.{check_note}</p>",
        v.n,
        v.touch_mean_mm,
        mm(pred.mean),
        v.touch_rms_mm,
        mm(pred.p95),
        v.touch_max_mm,
        v.procrustes_linear_error_mm,
        v.procrustes_angular_error_deg,
    )
}

fn rejections_html(rejections: &[(String, String, String)]) -> String {
    if rejections.is_empty() {
        return "<p>No capture was rejected.</p>".to_owned();
    }
    let mut h = String::from(
        "<table class=\"list\"><tr><th>robot</th><th>capture</th><th>reason</th></tr>",
    );
    for (robot, what, reason) in rejections {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td></tr>",
            escape(robot),
            escape(what),
            escape(reason)
        );
    }
    h.push_str("</table>");
    h
}

const CSS: &str = "body{font-family:'DejaVu Sans',Arial,sans-serif;margin:24px;color:#111;background:#f6f6f4}\
h1{font-size:24px;margin:0 0 4px}h2{font-size:18px;margin:0 0 10px}\
.src{color:#555;font-size:13px;margin-bottom:16px}\
.cards{display:flex;gap:12px;flex-wrap:wrap;margin-bottom:18px}\
.card{background:white;border:1px solid #ddd;border-radius:6px;padding:10px 14px;min-width:170px}\
.card .k{font-size:12px;color:#555}.card .v{font-size:22px;font-weight:bold}.card .s{font-size:12px;color:#555}\
.grid{display:grid;grid-template-columns:repeat(2,600px);gap:14px}\
.panel{background:white;border:1px solid #ddd;border-radius:6px;padding:10px}\
.panel img{display:block}.missing{color:#777;font-style:italic}\
table{border-collapse:collapse;font-size:13px}td,th{border-bottom:1px solid #e4e4e4;padding:3px 10px;text-align:right}\
td:first-child,th:first-child{text-align:left}table.list td{text-align:left}\
.small{font-size:12px;color:#555}.ok{color:#1d7a44;font-weight:bold}.warn{color:#b03a2e;font-weight:bold}\
code{background:#eee;padding:0 3px}\
.alert{background:#fdecea;border:2px solid #C0392B;border-radius:6px;padding:10px 14px;margin-bottom:18px;color:#7b1d14}\
.verdict{border-radius:6px;padding:10px 14px;margin-bottom:14px}.verdict h2{margin:0 0 4px 0}\
.verdict.pass{background:#eafaf1;border:2px solid #1E8449;color:#145a32}.verdict.fail{background:#fdecea;border:2px solid #C0392B;color:#7b1d14}\
.verdict.none{background:#f4f6f6;border:2px solid #7f8c8d}.findings{margin-bottom:14px}\
.alert h2{color:#C0392B}.alert li{font-size:15px;font-weight:bold;margin:4px 0}";

fn card(key: &str, value: &str, sub: &str) -> String {
    format!(
        "<div class=\"card\"><div class=\"k\">{}</div><div class=\"v\">{}</div><div class=\"s\">{}</div></div>",
        escape(key),
        escape(value),
        escape(sub)
    )
}

fn write_file(path: &Path, text: &str) -> Result<(), ReportError> {
    std::fs::write(path, text).map_err(|source| ReportError::Write {
        path: path.to_owned(),
        source,
    })
}

/// Writes `index.html` and its plots into `out_dir` (created if needed).
pub fn write_report(inputs: &ReportInputs, out_dir: &Path) -> Result<ReportFiles, ReportError> {
    inputs.validate()?;
    std::fs::create_dir_all(out_dir).map_err(|source| ReportError::Write {
        path: out_dir.to_owned(),
        source,
    })?;
    let robots = inputs.robots();
    let rejections = inputs.rejections();
    let r = &inputs.result;

    let rms_series: Vec<(String, &'static str, Vec<f64>)> = robots
        .iter()
        .map(|robot| {
            (
                robot.clone(),
                colour_of(&robots, robot),
                inputs
                    .captures
                    .iter()
                    .filter(|c| &c.robot == robot)
                    .filter_map(|c| c.rms_px)
                    .collect::<Vec<f64>>(),
            )
        })
        .filter(|s| !s.2.is_empty())
        .collect();
    let touch_series = vec![(
        "touches".to_owned(),
        PALETTE[0],
        inputs
            .touches
            .iter()
            .map(|t| t.error_m * 1e3)
            .collect::<Vec<_>>(),
    )];
    let pred = r.predicted_touch_error_m;
    let touch_markers = [
        (pred.mean * 1e3, GREEN, "result mean".to_owned()),
        (
            pred.p95 * 1e3,
            PALETTE[1],
            "result 95% (no tip noise)".to_owned(),
        ),
    ];

    let no_captures = "No per-capture details: this RESULT.json has no captures.per_capture \
                       (files written before it existed); give \
                       HANDEYE.json files with --hand-eye.";
    let plots: Vec<(&str, &str, Option<String>, &str)> = vec![
        (
            "residuals.svg",
            "Residuals per capture",
            plot_residuals(inputs, &robots),
            no_captures,
        ),
        (
            "residual_hist.svg",
            "Residual distribution",
            if rms_series.is_empty() {
                None
            } else {
                plot_histogram(
                    "Distribution of per-capture RMS",
                    "RMS (px)",
                    &rms_series,
                    &[],
                    false,
                )
            },
            no_captures,
        ),
        (
            "touch_errors.svg",
            "Touch errors against the prediction",
            plot_touch_errors(inputs),
            "No verify report: pass verify --json output with --verify.",
        ),
        (
            "touch_hist.svg",
            "Touch error distribution",
            if inputs.touches.is_empty() {
                None
            } else {
                plot_histogram(
                    "Distribution of touch errors",
                    "error (mm)",
                    &touch_series,
                    &touch_markers,
                    true,
                )
            },
            "No per-touch errors: the verify summary has only mean, RMS and max.",
        ),
        (
            "view_sphere.svg",
            "Pose coverage of the view sphere",
            plot_view_sphere(inputs, &robots),
            "No viewing directions: they come from the capture messages (T_camera_target).",
        ),
        (
            "rejections.svg",
            "Rejected captures",
            plot_rejections(&rejections, &robots),
            "No capture was rejected.",
        ),
        (
            "hand_eye_history_mm.svg",
            "Hand-eye over time: translation",
            plot_hand_eye_history(inputs, &robots, false),
            "",
        ),
        (
            "hand_eye_history_deg.svg",
            "Hand-eye over time: rotation",
            plot_hand_eye_history(inputs, &robots, true),
            "",
        ),
    ];

    let mut files = Vec::new();
    let mut panels = String::new();
    for (name, heading, svg, missing) in &plots {
        match svg {
            Some(svg) => {
                let path = out_dir.join(name);
                write_file(&path, svg)?;
                files.push(path);
                let _ = write!(
                    panels,
                    "<div class=\"panel\"><img src=\"{name}\" alt=\"{}\" width=\"580\"></div>",
                    escape(heading)
                );
            }
            // The rejection list at the bottom already says there were none; the
            // hand-eye panel says what the history plots need.
            None if *name == "rejections.svg" || name.starts_with("hand_eye_history") => {}
            None => {
                let _ = write!(
                    panels,
                    "<div class=\"panel\"><h2>{}</h2><p class=\"missing\">{}</p></div>",
                    escape(heading),
                    escape(missing)
                );
            }
        }
    }

    let t = r.base1_from_base2.t;
    let sd_t = (r.covariance[3][3] + r.covariance[4][4] + r.covariance[5][5])
        .max(0.0)
        .sqrt();
    let used: usize = r.captures.used.values().sum();
    let mut cards = String::new();
    cards.push_str(&card(
        "base1_from_base2 translation",
        &format!("{:.1} mm", Vector3::from(t).norm() * 1e3),
        &format!("{} {} {} mm", mm(t[0]), mm(t[1]), mm(t[2])),
    ));
    cards.push_str(&card(
        "translation 1σ (total)",
        &format!("{} mm", mm(sd_t)),
        &format!("method {}", r.method),
    ));
    cards.push_str(&card(
        "predicted touch error",
        &format!("{} mm", mm(pred.p95)),
        &format!("95%, transform only; mean {} mm", mm(pred.mean)),
    ));
    if let Some(v) = &inputs.verify {
        cards.push_str(&card(
            "measured touch error",
            &format!("{:.3} mm", v.touch_mean_mm),
            &format!(
                "mean of {}; {:.0}% inside the 95% bound",
                v.n,
                v.within_predicted_p95 * 100.0
            ),
        ));
    }
    cards.push_str(&card(
        "captures",
        &format!("{used} used"),
        &format!("{} rejected", rejections.len()),
    ));

    let sources = [
        inputs.result_source.as_ref().map(|s| format!("result {s}")),
        inputs.verify_source.as_ref().map(|s| format!("verify {s}")),
        inputs
            .history_source
            .as_ref()
            .map(|s| format!("history {s}")),
    ]
    .into_iter()
    .flatten()
    .collect::<Vec<_>>()
    .join(" · ");

    let html = format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
         <title>{title}</title><style>{CSS}</style></head><body>\n\
         <h1>{title}</h1>\n{verdict}<div class=\"src\">{sources}</div>\n\
         {warnings}\
         <div class=\"cards\">{cards}</div>\n\
         <div class=\"grid\">\n\
         <div class=\"panel\"><h2>base1_from_base2</h2>{numbers}</div>\n\
         <div class=\"panel\"><h2>Verification</h2>{verify}<h2 style=\"margin-top:14px\">Hand-eye</h2>{hand_eye}</div>\n\
         {panels}\n</div>\n\
         <div class=\"panel\" style=\"margin-top:14px;width:1186px\"><h2>Rejected captures</h2>{rejected}\
         <p class=\"small\">timings: detect {:.0} ms, solve {:.0} ms, total {:.0} ms</p></div>\n\
         </body></html>\n",
        r.timings_ms.detect,
        r.timings_ms.solve,
        r.timings_ms.total,
        title = escape(&inputs.title),
        sources = escape(&sources),
        verdict = verdict_html(inputs),
        warnings = warnings_html(inputs),
        numbers = numbers_html(inputs),
        verify = verify_html(inputs),
        hand_eye = hand_eye_html(inputs),
        rejected = rejections_html(&rejections),
    );
    let index = out_dir.join("index.html");
    write_file(&index, &html)?;
    Ok(ReportFiles {
        index,
        plots: files,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    use b2b_errors::assert_cause_once;

    #[test]
    fn every_wrapped_error_prints_its_cause_once() {
        let io = || std::io::Error::new(std::io::ErrorKind::NotFound, "missing for the test");
        let path = PathBuf::from("/out/RESULT.json");
        assert_cause_once(&ReportError::Read {
            path: path.clone(),
            source: io(),
        });
        assert_cause_once(&ReportError::Write {
            path: path.clone(),
            source: io(),
        });
        let source = serde_json::from_str::<serde_json::Value>("{ nope").unwrap_err();
        assert_cause_once(&ReportError::Parse {
            path: path.clone(),
            what: "result",
            source,
        });
        let source = ProtocolError::BadField {
            field: "method".into(),
            reason: "empty".into(),
        };
        assert_cause_once(&ReportError::Invalid { path, source });
        let source = serde_json::from_str::<serde_json::Value>("{ nope").unwrap_err();
        assert_cause_once(&ReportError::Serialize {
            what: "result",
            source,
        });
        assert_cause_once(&ReportError::CreateFolder {
            path: "out".into(),
            source: io(),
        });
        assert_cause_once(&ReportError::NothingWritten {
            files: vec!["a.json".into()],
            source: Box::new(ReportError::NotReplaceable {
                path: "b".into(),
                kind: "a directory",
            }),
        });
        assert_cause_once(&ReportError::WriteThrough {
            path: "a".into(),
            temporary: ".a.tmp".into(),
            source: io(),
        });
        assert_cause_once(&ReportError::KeepPrevious {
            path: "a".into(),
            source: io(),
        });
        assert_cause_once(&ReportError::Replace {
            path: "a".into(),
            source: io(),
        });
    }
}
