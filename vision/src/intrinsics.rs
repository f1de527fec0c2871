//! Camera intrinsics from a set of board images (checkerboard or ChArUco).
//!
//! Every image is detected ([`crate::detect_checkerboard`] or
//! [`crate::detect_charuco`]); images where the board is not found or too few corners
//! are seen are rejected with the detector's reason. OpenCV's `calibrateCamera`
//! (Zhang's method + Levenberg–Marquardt, distortion `k1 k2 p1 p2 [k3]`) then fits
//! the rest; an image whose own reprojection RMS is an outlier
//! (above [`IntrinsicsOptions::outlier_factor`] × the median and above
//! [`IntrinsicsOptions::max_image_rms_px`]) is rejected and the fit repeated without it.
//!
//! ChArUco corners are predicted from the markers through a camera model, which is
//! not known yet: the first pass uses a guess (f = the image width, the principal
//! point at the centre), the second pass detects again with the first pass's
//! estimate and calibrates again.
//!
//! The result is the math core's [`CameraModel`]; `b2b_dataset::intrinsics_of`
//! turns it into the `camera` block of `dataset.json` (the one intrinsics type).

use std::path::Path;

use b2b_calib::camera::CameraModel;
use opencv::calib3d;
use opencv::core::{Mat, Point2f, Point3f, Size, TermCriteria, Vector};
use opencv::prelude::*;

use crate::checkerboard::BoardDetection;
use crate::error::{CvContext, VisionError, chain};
use crate::image::GrayImage;
use crate::target::Target;

/// Settings of [`calibrate_intrinsics`].
#[derive(Debug, Clone, PartialEq)]
pub struct IntrinsicsOptions {
    /// Fewest corners an image must give (ChArUco boards may be partly seen).
    pub min_corners: usize,
    /// Fewest usable images.
    pub min_images: usize,
    /// An image is an outlier when its RMS exceeds this factor times the median RMS…
    pub outlier_factor: f64,
    /// …and this many pixels.
    pub max_image_rms_px: f64,
    /// Fit k3 too (otherwise k3 = 0, OpenCV's `CALIB_FIX_K3`).
    pub fit_k3: bool,
}

impl Default for IntrinsicsOptions {
    fn default() -> Self {
        IntrinsicsOptions {
            min_corners: 8,
            min_images: 4,
            outlier_factor: 3.0,
            max_image_rms_px: 0.5,
            fit_k3: false,
        }
    }
}

/// What happened to one image.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageReport {
    pub name: String,
    /// Corners detected (0 when not found).
    pub corners: usize,
    /// Reprojection RMS in the final fit (px), for used images and for outliers
    /// (from the fit they were rejected in).
    pub rms_px: Option<f64>,
    /// Why the image was not used; `None` when it was.
    pub rejected: Option<String>,
}

/// The fitted camera and how each image fared.
#[derive(Debug, Clone, PartialEq)]
pub struct IntrinsicsResult {
    pub camera: CameraModel,
    /// Overall reprojection RMS of the used images (px).
    pub rms_px: f64,
    pub images: Vec<ImageReport>,
}

impl IntrinsicsResult {
    /// Number of images in the fit.
    pub fn used(&self) -> usize {
        self.images.iter().filter(|i| i.rejected.is_none()).count()
    }

    /// Distortion as written to `dataset.json`: `k1 k2 p1 p2 k3`.
    pub fn dist5(&self) -> [f64; 5] {
        let d = &self.camera.dist;
        [d[0], d[1], d[2], d[3], d[4]]
    }
}

/// How many detect-and-fit passes a target's images need: one for a checkerboard,
/// two for ChArUco (its corners are predicted through the camera); other kinds are
/// [`VisionError::IntrinsicsTarget`].
fn passes(target: &Target) -> Result<usize, VisionError> {
    match target {
        Target::Checkerboard(_) => Ok(1),
        Target::Charuco(_) => Ok(2),
        Target::ArucoGrid(_) | Target::Multimarker { .. } => Err(VisionError::IntrinsicsTarget {
            kind: target.kind(),
        }),
    }
}

/// Calibrates a camera from named images of one board (a checkerboard or a ChArUco
/// board; other kinds are [`VisionError::IntrinsicsTarget`]). All images must have
/// the same size. Fails (with the per-image reasons) when fewer than
/// [`IntrinsicsOptions::min_images`] images are usable.
pub fn calibrate_intrinsics(
    images: &[(String, GrayImage)],
    target: &Target,
    options: &IntrinsicsOptions,
) -> Result<IntrinsicsResult, VisionError> {
    let passes = passes(target)?;
    let Some((_, first)) = images.first() else {
        return Err(VisionError::Intrinsics("no images given".into()));
    };
    let (w, h) = (first.width(), first.height());
    if let Some((name, img)) = images
        .iter()
        .find(|(_, i)| i.width() != w || i.height() != h)
    {
        return Err(VisionError::Intrinsics(format!(
            "{name} is {}x{}, the first image is {w}x{h}: all images must come from one camera mode",
            img.width(),
            img.height()
        )));
    }
    let guess = CameraModel::new(
        w,
        h,
        [
            f64::from(w),
            f64::from(w),
            (f64::from(w) - 1.0) / 2.0,
            (f64::from(h) - 1.0) / 2.0,
        ],
        &[],
    )
    .map_err(|e| VisionError::Intrinsics(e.to_string()))?;
    let mut camera = guess;
    let mut result = None;
    for _ in 0..passes {
        let r = calibrate_pass(images, target, options, &camera)?;
        camera = r.camera.clone();
        result = Some(r);
    }
    result.ok_or_else(|| VisionError::Intrinsics("no pass ran".into()))
}

fn calibrate_pass(
    images: &[(String, GrayImage)],
    target: &Target,
    options: &IntrinsicsOptions,
    guess: &CameraModel,
) -> Result<IntrinsicsResult, VisionError> {
    let mut reports = Vec::with_capacity(images.len());
    let mut views: Vec<(usize, BoardDetection)> = Vec::new();
    for (k, (name, img)) in images.iter().enumerate() {
        let mut report = ImageReport {
            name: name.clone(),
            corners: 0,
            rms_px: None,
            rejected: None,
        };
        match target.detect_corners(img, guess) {
            Err(e) => report.rejected = Some(format!("board not found: {}", chain(&e))),
            Ok(det) => {
                report.corners = det.pixels.len();
                views.push((k, det));
            }
        }
        reports.push(report);
    }
    let terms = if options.fit_k3 {
        DistortionTerms::K1K2P1P2K3
    } else {
        DistortionTerms::K1K2P1P2
    };
    let settings = FitSettings {
        width: guess.width,
        height: guess.height,
        options,
        flags: terms.flags(),
        guess: None,
        stop: (100, 1e-12),
    };
    fit_views(views, reports, &settings)
}

/// How [`fit_views`] runs `calibrateCamera`.
struct FitSettings<'a> {
    width: u32,
    height: u32,
    options: &'a IntrinsicsOptions,
    /// `CALIB_*` flags of the distortion terms.
    flags: i32,
    /// The starting camera of a non-planar target (`CALIB_USE_INTRINSIC_GUESS`).
    guess: Option<&'a CameraModel>,
    /// Iterations and step size at which the LM stops.
    stop: (i32, f64),
}

/// Which distortion coefficients `calibrateCamera` fits; the others stay zero.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DistortionTerms {
    /// `k1` alone.
    K1,
    /// `k1, k2`.
    K1K2,
    /// `k1, k2, p1, p2` (k3 = 0, OpenCV's `CALIB_FIX_K3`).
    K1K2P1P2,
    /// `k1, k2, p1, p2, k3`.
    K1K2P1P2K3,
}

impl DistortionTerms {
    fn flags(self) -> i32 {
        match self {
            DistortionTerms::K1 => {
                calib3d::CALIB_FIX_K2 | calib3d::CALIB_FIX_K3 | calib3d::CALIB_ZERO_TANGENT_DIST
            }
            DistortionTerms::K1K2 => calib3d::CALIB_FIX_K3 | calib3d::CALIB_ZERO_TANGENT_DIST,
            DistortionTerms::K1K2P1P2 => calib3d::CALIB_FIX_K3,
            DistortionTerms::K1K2P1P2K3 => 0,
        }
    }

    /// The names of the fitted coefficients, e.g. `k1 k2 p1 p2`.
    pub fn names(self) -> &'static str {
        match self {
            DistortionTerms::K1 => "k1",
            DistortionTerms::K1K2 => "k1 k2",
            DistortionTerms::K1K2P1P2 => "k1 k2 p1 p2",
            DistortionTerms::K1K2P1P2K3 => "k1 k2 p1 p2 k3",
        }
    }
}

/// Calibrates a `width` x `height` camera from corners already detected, one named
/// view per image (checkerboard, ChArUco, ArUco grid or multimarker corners: any
/// [`BoardDetection`]), with the per-view outlier rejection of
/// [`calibrate_intrinsics`] and only the distortion `terms` fitted. Views with fewer
/// than [`IntrinsicsOptions::min_corners`] corners are rejected with the reason.
///
/// Views whose target points do not all lie on the target's z = 0 plane (a
/// non-planar multimarker set) cannot start from Zhang's closed form: they need
/// `guess` (OpenCV's `CALIB_USE_INTRINSIC_GUESS`), and a missing guess is an error.
/// A guess is used only for such views.
pub fn calibrate_from_detections(
    views: &[(String, BoardDetection)],
    width: u32,
    height: u32,
    options: &IntrinsicsOptions,
    terms: DistortionTerms,
    guess: Option<&CameraModel>,
) -> Result<IntrinsicsResult, VisionError> {
    if width == 0 || height == 0 {
        return Err(VisionError::Intrinsics(format!(
            "image size {width}x{height}: both sides must be positive"
        )));
    }
    let planar = views
        .iter()
        .all(|(_, d)| d.target_points.iter().all(|p| p.z == 0.0));
    let guess = if planar {
        None
    } else {
        Some(guess.ok_or_else(|| {
            VisionError::Intrinsics(
                "the target points are not on one z = 0 plane: calibrateCamera needs an initial camera guess"
                    .into(),
            )
        })?)
    };
    let reports = views
        .iter()
        .map(|(name, d)| ImageReport {
            name: name.clone(),
            corners: d.pixels.len(),
            rms_px: None,
            rejected: None,
        })
        .collect();
    let indexed = views.iter().cloned().map(|(_, d)| d).enumerate().collect();
    // OpenCV's own default stop (30 iterations or a step of machine epsilon): the
    // dense LM over all views' poses costs O(views³) per iteration, and a caller
    // that refines the camera further needs no more.
    let settings = FitSettings {
        width,
        height,
        options,
        flags: terms.flags(),
        guess,
        stop: (30, f64::EPSILON),
    };
    fit_views(indexed, reports, &settings)
}

/// The fit shared by [`calibrate_intrinsics`] and [`calibrate_from_detections`]:
/// drops views with too few corners, fits, rejects per-view outliers and fits again.
fn fit_views(
    views: Vec<(usize, BoardDetection)>,
    mut reports: Vec<ImageReport>,
    settings: &FitSettings<'_>,
) -> Result<IntrinsicsResult, VisionError> {
    let options = settings.options;
    let need = options.min_corners.max(4);
    let views: Vec<(usize, BoardDetection)> = views
        .into_iter()
        .filter(|(k, det)| {
            let ok = det.pixels.len() >= need;
            if !ok {
                reports[*k].rejected = Some(format!(
                    "too few corners: {} seen, need {need}",
                    det.pixels.len()
                ));
            }
            ok
        })
        .collect();
    let fit_once = |views: &[(usize, BoardDetection)], reports: &[ImageReport]| {
        run_calibration(views, reports, settings)
    };
    let mut fit = fit_once(&views, &reports)?;
    // Per-image outliers: drop them and fit again (once).
    let mut errors: Vec<f64> = fit.1.clone();
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let limit = (options.outlier_factor * median).max(options.max_image_rms_px);
    let mut kept = Vec::new();
    for ((k, det), e) in views.into_iter().zip(fit.1.iter()) {
        reports[k].rms_px = Some(*e);
        if *e > limit {
            reports[k].rejected = Some(format!(
                "per-image reprojection error {e:.3} px is an outlier (limit {limit:.3} px: \
                 {}x the median {median:.3} px, at least {} px)",
                options.outlier_factor, options.max_image_rms_px
            ));
        } else {
            kept.push((k, det));
        }
    }
    if kept.len() != fit.1.len() {
        fit = fit_once(&kept, &reports)?;
        for ((k, _), e) in kept.iter().zip(&fit.1) {
            reports[*k].rms_px = Some(*e);
        }
    }
    Ok(IntrinsicsResult {
        camera: fit.0,
        rms_px: fit.2,
        images: reports,
    })
}

/// `calibrateCamera` on the views; returns the camera, per-view RMS and overall RMS.
fn run_calibration(
    views: &[(usize, BoardDetection)],
    reports: &[ImageReport],
    settings: &FitSettings<'_>,
) -> Result<(CameraModel, Vec<f64>, f64), VisionError> {
    let (w, h, options, flags) = (
        settings.width,
        settings.height,
        settings.options,
        settings.flags,
    );
    let (max_iterations, eps) = settings.stop;
    if views.len() < options.min_images.max(3) {
        let reasons: Vec<String> = reports
            .iter()
            .filter_map(|r| r.rejected.as_ref().map(|why| format!("{}: {why}", r.name)))
            .collect();
        return Err(VisionError::Intrinsics(format!(
            "{} usable images, need {}; rejected: [{}]",
            views.len(),
            options.min_images.max(3),
            reasons.join("; ")
        )));
    }
    let object: Vector<Vector<Point3f>> = views
        .iter()
        .map(|(_, d)| {
            d.target_points
                .iter()
                .map(|p| Point3f::new(p.x as f32, p.y as f32, p.z as f32))
                .collect()
        })
        .collect();
    let image: Vector<Vector<Point2f>> = views
        .iter()
        .map(|(_, d)| {
            d.pixels
                .iter()
                .map(|p| Point2f::new(p.x as f32, p.y as f32))
                .collect()
        })
        .collect();
    let (mut k, mut dist, flags) = match settings.guess {
        Some(g) => {
            let k = Mat::from_slice_2d(&[[g.fx, 0.0, g.cx], [0.0, g.fy, g.cy], [0.0, 0.0, 1.0]])
                .cv("camera matrix")?;
            let d = Mat::from_slice_2d(&[&g.dist[..5]]).cv("distortion")?;
            (k, d, flags | calib3d::CALIB_USE_INTRINSIC_GUESS)
        }
        None => (Mat::default(), Mat::default(), flags),
    };
    let mut rvecs = Vector::<Mat>::new();
    let mut tvecs = Vector::<Mat>::new();
    let (mut sd_i, mut sd_e, mut per_view) = (Mat::default(), Mat::default(), Mat::default());
    let criteria = TermCriteria::new(
        opencv::core::TermCriteria_COUNT + opencv::core::TermCriteria_EPS,
        max_iterations,
        eps,
    )
    .cv("TermCriteria")?;
    let rms = calib3d::calibrate_camera_extended(
        &object,
        &image,
        Size::new(w as i32, h as i32),
        &mut k,
        &mut dist,
        &mut rvecs,
        &mut tvecs,
        &mut sd_i,
        &mut sd_e,
        &mut per_view,
        flags,
        criteria,
    )
    .cv("calibrateCamera")?;
    let kk = |r: i32, c: i32| -> Result<f64, VisionError> {
        k.at_2d::<f64>(r, c).copied().cv("camera matrix")
    };
    let d: Vec<f64> = dist.data_typed::<f64>().cv("distortion")?.to_vec();
    let mut d5 = [0.0; 5];
    for (o, v) in d5.iter_mut().zip(&d) {
        *o = *v;
    }
    let camera = CameraModel::new(w, h, [kk(0, 0)?, kk(1, 1)?, kk(0, 2)?, kk(1, 2)?], &d5)
        .map_err(|e| {
            VisionError::Intrinsics(format!("calibrateCamera gave an unusable camera: {e}"))
        })?;
    let per_view: Vec<f64> = per_view.data_typed::<f64>().cv("per-view errors")?.to_vec();
    if per_view.len() != views.len() || !rms.is_finite() {
        return Err(VisionError::Intrinsics(format!(
            "calibrateCamera returned {} per-view errors for {} views (RMS {rms})",
            per_view.len(),
            views.len()
        )));
    }
    Ok((camera, per_view, rms))
}

/// [`calibrate_intrinsics`] on every `.png`, `.jpg`, `.jpeg`, `.bmp` and `.tif(f)` file of
/// a folder (sorted by name); files that cannot be read are rejected images with the
/// reason, not a failure of the whole run.
pub fn calibrate_intrinsics_from_dir(
    dir: &Path,
    target: &Target,
    options: &IntrinsicsOptions,
) -> Result<IntrinsicsResult, VisionError> {
    passes(target)?;
    let entries = std::fs::read_dir(dir).map_err(|source| VisionError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut files: Vec<std::path::PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .map(|e| {
                    ["png", "jpg", "jpeg", "bmp", "tif", "tiff"]
                        .contains(&e.to_ascii_lowercase().as_str())
                })
                .unwrap_or(false)
        })
        .collect();
    files.sort();
    if files.is_empty() {
        return Err(VisionError::Intrinsics(format!(
            "{}: no image files (png, jpg, bmp, tif)",
            dir.display()
        )));
    }
    let mut images = Vec::new();
    let mut unreadable = Vec::new();
    for f in files {
        let name = f.display().to_string();
        match crate::load_gray(&f) {
            Ok(img) => images.push((name, img)),
            Err(e) => unreadable.push(ImageReport {
                name,
                corners: 0,
                rms_px: None,
                rejected: Some(format!("unreadable: {}", chain(&e))),
            }),
        }
    }
    // Images of another size than the majority's are rejected, not fatal.
    let mut sizes: Vec<(u32, u32)> = images
        .iter()
        .map(|(_, i)| (i.width(), i.height()))
        .collect();
    sizes.sort();
    let common = sizes
        .chunk_by(|a, b| a == b)
        .max_by_key(|c| c.len())
        .map(|c| c[0]);
    let (same, other): (Vec<_>, Vec<_>) = images
        .into_iter()
        .partition(|(_, i)| Some((i.width(), i.height())) == common);
    for (name, img) in other {
        let (cw, ch) = common.unwrap_or_default();
        unreadable.push(ImageReport {
            name,
            corners: 0,
            rms_px: None,
            rejected: Some(format!(
                "{}x{} image, most images are {cw}x{ch}",
                img.width(),
                img.height()
            )),
        });
    }
    if same.is_empty() {
        let reasons: Vec<String> = unreadable
            .iter()
            .map(|r| format!("{}: {}", r.name, r.rejected.as_deref().unwrap_or("")))
            .collect();
        return Err(VisionError::Intrinsics(format!(
            "{}: no readable images: {}",
            dir.display(),
            reasons.join("; ")
        )));
    }
    let mut result = calibrate_intrinsics(&same, target, options).map_err(|e| match e {
        VisionError::Intrinsics(msg) if !unreadable.is_empty() => VisionError::Intrinsics(format!(
            "{msg}; also not used: [{}]",
            unreadable
                .iter()
                .map(|r| format!("{}: {}", r.name, r.rejected.as_deref().unwrap_or("")))
                .collect::<Vec<_>>()
                .join("; ")
        )),
        other => other,
    })?;
    result.images.extend(unreadable);
    Ok(result)
}
