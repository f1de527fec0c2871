//! Local image features for the RGB-D method: detection, description and matching.
//!
//! SIFT is the default ([`FeatureKind::Sift`]; SURF is not in Debian's OpenCV build),
//! AKAZE and ORB are options. Matches pass two tests: Lowe's ratio test (best distance
//! below `ratio` times the second best, 0.75 by default) and a cross-check (the match
//! is also the best one from the other image's side). What comes out are pixel pairs
//! with their descriptor distance and ratio; nothing of OpenCV crosses the API except
//! the descriptors kept inside [`Features`].
//!
//! [`load_depth`] reads the 16-bit depth PNGs aligned to the colour images.

use std::path::Path;

use nalgebra::Point2;
use opencv::core::{self, DMatch, KeyPoint, Mat, Vector};
use opencv::features2d::{self, AKAZE, BFMatcher, ORB, SIFT};
use opencv::imgcodecs;
use opencv::prelude::*;

use crate::error::{CvContext, VisionError};
use crate::image::GrayImage;

/// Which detector/descriptor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FeatureKind {
    /// SIFT (float descriptors, L2 distance). The default.
    #[default]
    Sift,
    /// AKAZE with MLDB binary descriptors (Hamming distance).
    Akaze,
    /// ORB (binary descriptors, Hamming distance).
    Orb,
}

impl FeatureKind {
    pub fn name(&self) -> &'static str {
        match self {
            FeatureKind::Sift => "sift",
            FeatureKind::Akaze => "akaze",
            FeatureKind::Orb => "orb",
        }
    }

    /// Parses `sift`, `akaze` or `orb`.
    pub fn parse(s: &str) -> Result<Self, VisionError> {
        match s.to_ascii_lowercase().as_str() {
            "sift" => Ok(FeatureKind::Sift),
            "akaze" => Ok(FeatureKind::Akaze),
            "orb" => Ok(FeatureKind::Orb),
            "surf" => Err(VisionError::InvalidSpec(
                "feature kind 'surf': this OpenCV build has no SURF (nonfree); use sift, akaze or orb"
                    .into(),
            )),
            _ => Err(VisionError::InvalidSpec(format!(
                "unknown feature kind '{s}': expected sift, akaze or orb"
            ))),
        }
    }

    fn norm(&self) -> i32 {
        match self {
            FeatureKind::Sift => core::NORM_L2,
            FeatureKind::Akaze | FeatureKind::Orb => core::NORM_HAMMING,
        }
    }
}

/// Detection and matching settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureOptions {
    pub kind: FeatureKind,
    /// Most features kept per image (by detector response); 0 = no limit.
    pub max_features: usize,
    /// Lowe's ratio: best distance < `ratio` × second best.
    pub ratio: f64,
    /// Keep only mutual best matches.
    pub cross_check: bool,
}

impl Default for FeatureOptions {
    fn default() -> Self {
        FeatureOptions {
            kind: FeatureKind::Sift,
            max_features: 4000,
            ratio: 0.75,
            cross_check: true,
        }
    }
}

/// The features of one image: keypoint positions (px, OpenCV convention), their
/// detector responses, and the descriptors (one row each).
#[derive(Debug)]
pub struct Features {
    pub kind: FeatureKind,
    pub pixels: Vec<Point2<f64>>,
    pub responses: Vec<f64>,
    descriptors: Mat,
}

impl Features {
    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// The descriptors as bytes for the wire: `(bytes per descriptor, rows)`.
    /// Binary descriptors (AKAZE, ORB) are bytes already; SIFT's are floats that
    /// OpenCV saturates to whole numbers 0..=255, so one byte each holds them
    /// exactly. A SIFT value that is not such a number is an error, never rounded.
    pub fn descriptor_bytes(&self) -> Result<(usize, Vec<u8>), VisionError> {
        let rows = self.descriptors.rows().max(0) as usize;
        if rows == 0 {
            return Ok((0, Vec::new()));
        }
        let cols = self.descriptors.cols().max(0) as usize;
        // A clone is continuous, whatever the original's layout.
        let mat = self.descriptors.try_clone().cv("Mat::clone")?;
        match self.kind {
            FeatureKind::Sift => {
                let data = mat.data_typed::<f32>().cv("Mat::data_typed")?;
                let mut out = Vec::with_capacity(data.len());
                for (i, v) in data.iter().enumerate() {
                    if !(v.fract() == 0.0 && (0.0..=255.0).contains(v)) {
                        return Err(VisionError::InvalidSpec(format!(
                            "SIFT descriptor {} value {} is {v}: not a whole number in 0..=255",
                            i / cols.max(1),
                            i % cols.max(1)
                        )));
                    }
                    out.push(*v as u8);
                }
                Ok((cols, out))
            }
            FeatureKind::Akaze | FeatureKind::Orb => {
                let data = mat.data_typed::<u8>().cv("Mat::data_typed")?;
                Ok((cols, data.to_vec()))
            }
        }
    }

    /// Features from their parts as [`Features::descriptor_bytes`] gives them
    /// (another process's, off the wire). Lengths must agree.
    pub fn from_parts(
        kind: FeatureKind,
        pixels: Vec<Point2<f64>>,
        responses: Vec<f64>,
        descriptor_len: usize,
        descriptors: &[u8],
    ) -> Result<Features, VisionError> {
        let n = pixels.len();
        if responses.len() != n {
            return Err(VisionError::InvalidSpec(format!(
                "{n} keypoints but {} responses",
                responses.len()
            )));
        }
        if descriptors.len() != n * descriptor_len || (n > 0 && descriptor_len == 0) {
            return Err(VisionError::InvalidSpec(format!(
                "{n} keypoints of {descriptor_len}-byte descriptors need {} bytes, got {}",
                n * descriptor_len,
                descriptors.len()
            )));
        }
        if let Some(i) = pixels
            .iter()
            .position(|p| !(p.x.is_finite() && p.y.is_finite()))
        {
            return Err(VisionError::InvalidSpec(format!(
                "keypoint {i} is not finite"
            )));
        }
        if n > 0 && kind == FeatureKind::Sift && descriptor_len != 128 {
            return Err(VisionError::InvalidSpec(format!(
                "sift descriptors have 128 values, got {descriptor_len}"
            )));
        }
        let descriptors = if n == 0 {
            Mat::default()
        } else {
            let (rows, cols) = (n as i32, descriptor_len as i32);
            match kind {
                FeatureKind::Sift => {
                    let floats: Vec<f32> = descriptors.iter().map(|b| f32::from(*b)).collect();
                    Mat::new_rows_cols_with_data(rows, cols, &floats)
                        .cv("Mat::from_slice")?
                        .try_clone()
                        .cv("Mat::clone")?
                }
                FeatureKind::Akaze | FeatureKind::Orb => {
                    Mat::new_rows_cols_with_data(rows, cols, descriptors)
                        .cv("Mat::from_slice")?
                        .try_clone()
                        .cv("Mat::clone")?
                }
            }
        };
        Ok(Features {
            kind,
            pixels,
            responses,
            descriptors,
        })
    }
}

/// One match: the pixel in each image, the descriptor distance, and the ratio of
/// best to second-best distance (0 when there was no second candidate).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureMatch {
    pub index1: usize,
    pub index2: usize,
    pub pixel1: Point2<f64>,
    pub pixel2: Point2<f64>,
    pub distance: f64,
    pub ratio: f64,
}

/// Detects and describes features in a grey image.
pub fn detect_features(img: &GrayImage, options: &FeatureOptions) -> Result<Features, VisionError> {
    let n = i32::try_from(options.max_features).unwrap_or(i32::MAX);
    let mut keypoints = Vector::<KeyPoint>::new();
    let mut descriptors = Mat::default();
    let mask = Mat::default();
    match options.kind {
        FeatureKind::Sift => {
            let mut d = SIFT::create(n, 3, 0.04, 10.0, 1.6).cv("SIFT::create")?;
            d.detect_and_compute(img.mat(), &mask, &mut keypoints, &mut descriptors, false)
                .cv("SIFT::detectAndCompute")?;
        }
        FeatureKind::Akaze => {
            let mut d = AKAZE::create_def().cv("AKAZE::create")?;
            d.detect_and_compute(img.mat(), &mask, &mut keypoints, &mut descriptors, false)
                .cv("AKAZE::detectAndCompute")?;
        }
        FeatureKind::Orb => {
            let n = if n == 0 { 4000 } else { n };
            let mut d = ORB::create(
                n,
                1.2,
                8,
                31,
                0,
                2,
                features2d::ORB_ScoreType::HARRIS_SCORE,
                31,
                20,
            )
            .cv("ORB::create")?;
            d.detect_and_compute(img.mat(), &mask, &mut keypoints, &mut descriptors, false)
                .cv("ORB::detectAndCompute")?;
        }
    }
    // AKAZE has no feature limit of its own: keep the strongest ones.
    let mut order: Vec<usize> = (0..keypoints.len()).collect();
    if options.max_features > 0 && order.len() > options.max_features {
        order.sort_by(|a, b| {
            let ra = keypoints.get(*a).map(|k| k.response()).unwrap_or(0.0);
            let rb = keypoints.get(*b).map(|k| k.response()).unwrap_or(0.0);
            rb.total_cmp(&ra)
        });
        order.truncate(options.max_features);
        order.sort_unstable();
        let mut kept = Mat::default();
        for &i in &order {
            let row = descriptors.row(i as i32).cv("Mat::row")?;
            kept.push_back(&row).cv("Mat::push_back")?;
        }
        descriptors = kept;
    }
    let mut pixels = Vec::with_capacity(order.len());
    let mut responses = Vec::with_capacity(order.len());
    for &i in &order {
        let k = keypoints.get(i).cv("keypoints")?;
        let p = k.pt();
        pixels.push(Point2::new(f64::from(p.x), f64::from(p.y)));
        responses.push(f64::from(k.response()));
    }
    Ok(Features {
        kind: options.kind,
        pixels,
        responses,
        descriptors,
    })
}

/// Two feature sets can be matched: the same kind, and a ratio in (0, 1].
fn check_matchable(
    a: &Features,
    b: &Features,
    options: &FeatureOptions,
) -> Result<(), VisionError> {
    if a.kind != b.kind {
        return Err(VisionError::InvalidSpec(format!(
            "cannot match {} features against {} features",
            a.kind.name(),
            b.kind.name()
        )));
    }
    if !(options.ratio > 0.0 && options.ratio <= 1.0) {
        return Err(VisionError::InvalidSpec(format!(
            "ratio {} must be in (0, 1]",
            options.ratio
        )));
    }
    Ok(())
}

/// The best and second-best candidate of every query row.
fn knn2(matcher: &BFMatcher, query: &Mat, train: &Mat) -> Result<Vec<Vector<DMatch>>, VisionError> {
    let mut out = Vector::<Vector<DMatch>>::new();
    matcher
        .knn_train_match(query, train, &mut out, 2, &Mat::default(), false)
        .cv("BFMatcher::knnMatch")?;
    Ok(out.into_iter().collect())
}

/// Matches two images' features: ratio test and (optionally) cross-check. Empty
/// feature sets give no matches, not an error.
pub fn match_features(
    a: &Features,
    b: &Features,
    options: &FeatureOptions,
) -> Result<Vec<FeatureMatch>, VisionError> {
    check_matchable(a, b, options)?;
    if a.is_empty() || b.is_empty() {
        return Ok(Vec::new());
    }
    let matcher = BFMatcher::new(a.kind.norm(), false).cv("BFMatcher::create")?;
    let forward = knn2(&matcher, &a.descriptors, &b.descriptors)?;
    let backward = if options.cross_check {
        Some(knn2(&matcher, &b.descriptors, &a.descriptors)?)
    } else {
        None
    };
    let mut out = Vec::new();
    for (qi, cands) in forward.iter().enumerate() {
        let Ok(best) = cands.get(0) else { continue };
        let ratio = match cands.get(1) {
            Ok(second) if second.distance > 0.0 => {
                f64::from(best.distance) / f64::from(second.distance)
            }
            Ok(_) => 1.0,
            Err(_) => 0.0,
        };
        if ratio >= options.ratio {
            continue;
        }
        let ti = best.train_idx as usize;
        if let Some(back) = &backward {
            let mutual = back
                .get(ti)
                .and_then(|c| c.get(0).ok())
                .is_some_and(|m| m.train_idx as usize == qi);
            if !mutual {
                continue;
            }
        }
        let (Some(p1), Some(p2)) = (a.pixels.get(qi), b.pixels.get(ti)) else {
            continue;
        };
        out.push(FeatureMatch {
            index1: qi,
            index2: ti,
            pixel1: *p1,
            pixel2: *p2,
            distance: f64::from(best.distance),
            ratio,
        });
    }
    Ok(out)
}

/// Matches `a`'s features against `b`'s comparing only the pairs that
/// `candidates` lists (`candidates[i]`: the indices of `b` that `a`'s feature
/// `i` may match), as where a prediction says each feature should be seen
/// again. The tests are [`match_features`]'s, taken among the candidates: the
/// ratio test against the second-best candidate (ratio 0 with a single
/// candidate) and the cross-check against the other features that list the
/// same one. Cost: one descriptor distance per listed pair, not one per pair
/// of features.
pub fn match_features_among(
    a: &Features,
    b: &Features,
    candidates: &[Vec<usize>],
    options: &FeatureOptions,
) -> Result<Vec<FeatureMatch>, VisionError> {
    check_matchable(a, b, options)?;
    if candidates.len() != a.len() {
        return Err(VisionError::InvalidSpec(format!(
            "{} candidate lists for {} features",
            candidates.len(),
            a.len()
        )));
    }
    if let Some((i, j)) = candidates
        .iter()
        .enumerate()
        .find_map(|(i, c)| c.iter().find(|j| **j >= b.len()).map(|j| (i, *j)))
    {
        return Err(VisionError::InvalidSpec(format!(
            "feature {i}'s candidate {j} is beyond the other set's {} features",
            b.len()
        )));
    }
    if a.is_empty() || b.is_empty() {
        return Ok(Vec::new());
    }
    let (da, db) = (a.descriptor_rows()?, b.descriptor_rows()?);
    // Per feature of `a`: best (distance, index of b) and second-best distance.
    let mut forward: Vec<Option<(f32, usize, f32)>> = vec![None; a.len()];
    // Per feature of `b`: the best feature of `a` that listed it.
    let mut backward: Vec<Option<(f32, usize)>> = vec![None; b.len()];
    for (i, list) in candidates.iter().enumerate() {
        for &j in list {
            let d = da.distance(i, &db, j);
            forward[i] = Some(match forward[i] {
                None => (d, j, f32::INFINITY),
                Some((best, _, _)) if d < best => (d, j, best),
                Some((best, bj, second)) => (best, bj, second.min(d)),
            });
            if backward[j].is_none_or(|(best, _)| d < best) {
                backward[j] = Some((d, i));
            }
        }
    }
    let mut out = Vec::new();
    for (i, f) in forward.iter().enumerate() {
        let Some((best, j, second)) = *f else {
            continue;
        };
        let ratio = if second.is_infinite() {
            0.0
        } else if second > 0.0 {
            f64::from(best) / f64::from(second)
        } else {
            1.0
        };
        if ratio >= options.ratio {
            continue;
        }
        if options.cross_check && backward[j].map(|(_, bi)| bi) != Some(i) {
            continue;
        }
        out.push(FeatureMatch {
            index1: i,
            index2: j,
            pixel1: a.pixels[i],
            pixel2: b.pixels[j],
            distance: f64::from(best),
            ratio,
        });
    }
    Ok(out)
}

/// A feature set's descriptors as rows of numbers, for distances computed here.
enum DescriptorRows<'a> {
    /// SIFT: L2 distance.
    Float {
        data: std::borrow::Cow<'a, [f32]>,
        cols: usize,
    },
    /// AKAZE, ORB: Hamming distance.
    Binary {
        data: std::borrow::Cow<'a, [u8]>,
        cols: usize,
    },
}

impl DescriptorRows<'_> {
    /// The distance (OpenCV's norm for the kind) between row `i` and `other`'s row `j`.
    fn distance(&self, i: usize, other: &DescriptorRows<'_>, j: usize) -> f32 {
        match (self, other) {
            (DescriptorRows::Float { data: a, cols }, DescriptorRows::Float { data: b, .. }) => {
                let (x, y) = (&a[i * cols..(i + 1) * cols], &b[j * cols..(j + 1) * cols]);
                // Eight running sums, so that the compiler can use vector lanes.
                let mut lanes = [0f32; 8];
                let (xc, yc) = (x.chunks_exact(8), y.chunks_exact(8));
                let tail: f32 = xc
                    .remainder()
                    .iter()
                    .zip(yc.remainder())
                    .map(|(p, q)| (p - q) * (p - q))
                    .sum();
                for (p, q) in xc.zip(yc) {
                    for k in 0..8 {
                        let d = p[k] - q[k];
                        lanes[k] += d * d;
                    }
                }
                (lanes.iter().sum::<f32>() + tail).sqrt()
            }
            (DescriptorRows::Binary { data: a, cols }, DescriptorRows::Binary { data: b, .. }) => {
                let (x, y) = (&a[i * cols..(i + 1) * cols], &b[j * cols..(j + 1) * cols]);
                x.iter()
                    .zip(y)
                    .map(|(p, q)| (p ^ q).count_ones())
                    .sum::<u32>() as f32
            }
            // Kinds are checked equal before any distance is taken.
            _ => f32::INFINITY,
        }
    }
}

impl Features {
    /// The descriptors as rows, borrowed where OpenCV's matrix is continuous.
    fn descriptor_rows(&self) -> Result<DescriptorRows<'_>, VisionError> {
        let cols = self.descriptors.cols().max(0) as usize;
        let rows = self.descriptors.rows().max(0) as usize;
        if rows != self.len() {
            return Err(VisionError::InvalidSpec(format!(
                "{} keypoints but {rows} descriptor rows",
                self.len()
            )));
        }
        Ok(match self.kind {
            FeatureKind::Sift => DescriptorRows::Float {
                data: match self.descriptors.data_typed::<f32>() {
                    Ok(d) => std::borrow::Cow::Borrowed(d),
                    Err(_) => std::borrow::Cow::Owned(
                        self.descriptors
                            .try_clone()
                            .cv("Mat::clone")?
                            .data_typed::<f32>()
                            .cv("Mat::data_typed")?
                            .to_vec(),
                    ),
                },
                cols,
            },
            FeatureKind::Akaze | FeatureKind::Orb => DescriptorRows::Binary {
                data: match self.descriptors.data_typed::<u8>() {
                    Ok(d) => std::borrow::Cow::Borrowed(d),
                    Err(_) => std::borrow::Cow::Owned(
                        self.descriptors
                            .try_clone()
                            .cv("Mat::clone")?
                            .data_typed::<u8>()
                            .cv("Mat::data_typed")?
                            .to_vec(),
                    ),
                },
                cols,
            },
        })
    }
}

/// Detects in both images and matches.
pub fn match_images(
    img1: &GrayImage,
    img2: &GrayImage,
    options: &FeatureOptions,
) -> Result<Vec<FeatureMatch>, VisionError> {
    let a = detect_features(img1, options)?;
    let b = detect_features(img2, options)?;
    match_features(&a, &b, options)
}

/// A 16-bit depth image in raw units (0 = no depth).
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u16>,
}

impl DepthImage {
    /// The raw value at an integer pixel; `None` outside the image.
    pub fn at(&self, u: i64, v: i64) -> Option<u16> {
        if u < 0 || v < 0 || u >= i64::from(self.width) || v >= i64::from(self.height) {
            return None;
        }
        self.data
            .get(v as usize * self.width as usize + u as usize)
            .copied()
    }
}

/// Reads a single-channel 16-bit depth PNG; 8-bit or colour files are refused, and
/// a header claiming more than [`crate::MAX_IMAGE_PIXELS`] is refused before decoding.
pub fn load_depth(path: &Path) -> Result<DepthImage, VisionError> {
    let bytes = std::fs::read(path).map_err(|source| VisionError::Io {
        path: path.to_owned(),
        source,
    })?;
    let name = path.display().to_string();
    if bytes.is_empty() {
        return Err(VisionError::CorruptImage {
            source_name: name,
            reason: "the file is empty".into(),
        });
    }
    if let Some(size) = crate::image::header_size(&bytes) {
        crate::image::check_stated_size(&name, size, None)?;
    }
    if let Some(png) = crate::image::decode_png(&bytes, &name)? {
        if png.channels != 1 || !png.sixteen_bit {
            return Err(VisionError::UnsupportedImage {
                source_name: name,
                what: format!(
                    "depth image must be 16-bit single-channel, got a {}-bit PNG with {} channel(s)",
                    if png.sixteen_bit { 16 } else { 8 },
                    png.channels
                ),
            });
        }
        let data = png
            .data
            .chunks_exact(2)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
            .collect();
        return Ok(DepthImage {
            width: png.width,
            height: png.height,
            data,
        });
    }
    let buf = Vector::<u8>::from_slice(&bytes);
    let mat = imgcodecs::imdecode(&buf, imgcodecs::IMREAD_UNCHANGED).map_err(|e| {
        VisionError::CorruptImage {
            source_name: name.clone(),
            reason: format!("decoder error: {}", e.message),
        }
    })?;
    if mat.empty() {
        return Err(VisionError::CorruptImage {
            source_name: name,
            reason: "no OpenCV decoder accepts these bytes".into(),
        });
    }
    if mat.typ() != core::CV_16UC1 {
        return Err(VisionError::UnsupportedImage {
            source_name: name,
            what: format!(
                "depth image must be 16-bit single-channel, got OpenCV depth code {} with {} channels",
                mat.depth(),
                mat.channels()
            ),
        });
    }
    let mat = if mat.is_continuous() {
        mat
    } else {
        mat.try_clone().cv("Mat::clone")?
    };
    let data = mat.data_typed::<u16>().cv("Mat::data_typed")?.to_vec();
    Ok(DepthImage {
        width: mat.cols() as u32,
        height: mat.rows() as u32,
        data,
    })
}
