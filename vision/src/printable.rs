//! Printable targets: every target kind as a vector page (SVG, exact physical size in
//! millimetres) and as a PNG at a given DPI, plus the multimarker file.
//!
//! Each target is first laid out as black rectangles on a white page (millimetres,
//! y down, origin at the page's top-left corner, [`Page`]); the SVG writes those
//! rectangles as they are, the PNG fills the pixels whose centres they cover (edges
//! rounded to the pixel grid, at most half a pixel). Marker bit patterns come from
//! OpenCV's `drawMarker` (one-cell black border), ChArUco marker places and ids from
//! OpenCV's own `CharucoBoard`, so what is printed is what the detectors expect
//! (including OpenCV 4.6's even-row ChArUco layout). Markers need a white quiet zone of
//! at least one of their cells around them (measured: a 100 mm AprilTag with 10 mm of
//! white on grey is not found); a smaller margin or grid separation is refused. (The
//! gaps between multimarker markers are not checked.) The PNG carries no DPI metadata:
//! print it at the DPI it was made for, with scaling off, or print the SVG.
//!
//! Page layouts (the target frame on the printed page):
//! - checkerboard: a white border of `margin` around `(cols+1)x(rows+1)` squares; the
//!   target origin is the inner corner at `(margin + square, margin + square)`, x to the
//!   right, y down (z into the page), the outer-corner square at the top left black;
//! - ChArUco / ArUco grid: OpenCV's board frame (x right, y down) offset by `margin`;
//! - single marker ([`marker_page`]): the marker centred, `margin` of white around it;
//! - multimarker: one page per face ([`crate::multimarker::MultimarkerConfig::faces`]),
//!   the face frame's x to the right and y up, the page's top-left corner at face
//!   coordinates `(x_min - margin, y_max + margin)` of the markers.

use std::path::{Path, PathBuf};

use opencv::core::Mat;
use opencv::prelude::*;

use crate::error::{CvContext, VisionError};
use crate::image::GrayImage;
use crate::markers::MarkerDictionary;
use crate::target::Target;

/// Largest page side, millimetres (a 2 m poster).
const MAX_PAGE_MM: f64 = 2000.0;
/// Largest PNG side, pixels.
const MAX_PNG_PX: f64 = 40_000.0;

/// Black rectangles on a white page, millimetres, y down.
#[derive(Debug, Clone, PartialEq)]
pub struct Page {
    /// A name for the page (`face0`, … for multimarker faces, empty otherwise).
    pub name: String,
    pub width_mm: f64,
    pub height_mm: f64,
    /// `(x, y, w, h)` of each black rectangle.
    pub rects: Vec<[f64; 4]>,
}

impl Page {
    /// The SVG document: `width`/`height` in millimetres, a `viewBox` in millimetres.
    pub fn svg(&self) -> String {
        let mut s = format!(
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n\
             <svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}mm\" height=\"{h}mm\" \
             viewBox=\"0 0 {w} {h}\" shape-rendering=\"crispEdges\">\n\
             <rect x=\"0\" y=\"0\" width=\"{w}\" height=\"{h}\" fill=\"#ffffff\"/>\n<g fill=\"#000000\">\n",
            w = num(self.width_mm),
            h = num(self.height_mm)
        );
        for [x, y, w, h] in &self.rects {
            s.push_str(&format!(
                "<rect x=\"{}\" y=\"{}\" width=\"{}\" height=\"{}\"/>\n",
                num(*x),
                num(*y),
                num(*w),
                num(*h)
            ));
        }
        s.push_str("</g>\n</svg>\n");
        s
    }

    /// The page rasterised at `dpi`: a pixel is black when its centre lies in a black
    /// rectangle.
    pub fn png(&self, dpi: f64) -> Result<GrayImage, VisionError> {
        if !(10.0..=4800.0).contains(&dpi) {
            return Err(VisionError::Printable(format!(
                "{dpi} DPI: need 10 to 4800"
            )));
        }
        let px_per_mm = dpi / 25.4;
        let (w, h) = (
            (self.width_mm * px_per_mm).round(),
            (self.height_mm * px_per_mm).round(),
        );
        if !(w >= 1.0 && h >= 1.0 && w <= MAX_PNG_PX && h <= MAX_PNG_PX) {
            return Err(VisionError::Printable(format!(
                "a {w}x{h} px image: need 1 to {MAX_PNG_PX} px per side (lower the DPI)"
            )));
        }
        let (w, h) = (w as usize, h as usize);
        let mut px = vec![255u8; w * h];
        // Pixel k's centre is at (k + 0.5) / px_per_mm: rect [a, b) covers pixels
        // round(a·ppm) .. round(b·ppm).
        let span = |a: f64, b: f64, n: usize| {
            let lo = (a * px_per_mm).round().clamp(0.0, n as f64) as usize;
            let hi = (b * px_per_mm).round().clamp(0.0, n as f64) as usize;
            lo..hi
        };
        for [x, y, rw, rh] in &self.rects {
            for v in span(*y, y + rh, h) {
                for u in span(*x, x + rw, w) {
                    px[v * w + u] = 0;
                }
            }
        }
        GrayImage::from_raw(w as u32, h as u32, &px)
    }
}

fn num(v: f64) -> String {
    let s = format!("{v:.4}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

fn check_len(what: &str, v: f64) -> Result<f64, VisionError> {
    if v.is_finite() && v >= 0.0 && v * 1e3 <= MAX_PAGE_MM {
        Ok(v * 1e3)
    } else {
        Err(VisionError::Printable(format!(
            "{what} {v} m: must be finite, not negative and under {} m",
            MAX_PAGE_MM / 1e3
        )))
    }
}

/// The black cells of marker `id` (one-cell border), merged along rows, as
/// rectangles of a `side_mm` marker with its top-left corner at `(x, y)`; `quiet_mm`
/// is the white around it, which must be at least one cell.
fn marker_rects(
    dict: &MarkerDictionary,
    id: usize,
    x: f64,
    y: f64,
    side_mm: f64,
    quiet_mm: f64,
    out: &mut Vec<[f64; 4]>,
) -> Result<(), VisionError> {
    if id >= dict.marker_count() {
        return Err(VisionError::InvalidTarget(format!(
            "marker id {id} is not in {} (ids 0..{})",
            dict.name(),
            dict.marker_count()
        )));
    }
    let cv = dict.opencv()?;
    let cells = (cv.marker_size() + 2) as usize;
    if quiet_mm < side_mm / cells as f64 - 1e-9 {
        return Err(VisionError::Printable(format!(
            "marker {id}: {quiet_mm} mm of white around it is less than one of its cells \
             ({:.2} mm); detectors need that quiet zone: increase the margin (or the separation)",
            side_mm / cells as f64
        )));
    }
    let mut m = Mat::default();
    opencv::aruco::draw_marker(&cv, id as i32, cells as i32, &mut m, 1).cv("drawMarker")?;
    let bits = m.data_bytes().cv("drawMarker data")?;
    if bits.len() != cells * cells {
        return Err(VisionError::Printable(format!(
            "drawMarker gave {} bytes for {cells}x{cells} cells",
            bits.len()
        )));
    }
    let cell = side_mm / cells as f64;
    for r in 0..cells {
        let mut c = 0;
        while c < cells {
            if bits[r * cells + c] < 128 {
                let start = c;
                while c < cells && bits[r * cells + c] < 128 {
                    c += 1;
                }
                out.push([
                    x + start as f64 * cell,
                    y + r as f64 * cell,
                    (c - start) as f64 * cell,
                    cell,
                ]);
            } else {
                c += 1;
            }
        }
    }
    Ok(())
}

/// A `w` x `h` mm page of `rects`, refused when larger than a poster.
fn page(w: f64, h: f64, rects: Vec<[f64; 4]>, name: String) -> Result<Page, VisionError> {
    if w > MAX_PAGE_MM || h > MAX_PAGE_MM {
        return Err(VisionError::Printable(format!(
            "a {w:.1} x {h:.1} mm page: more than {MAX_PAGE_MM} mm per side"
        )));
    }
    Ok(Page {
        name,
        width_mm: w,
        height_mm: h,
        rects,
    })
}

/// The page of one marker of `dictionary` (an OpenCV name), `marker_m` wide, centred
/// with `margin_m` of white around it (at least one of its cells).
pub fn marker_page(
    dictionary: &str,
    id: usize,
    marker_m: f64,
    margin_m: f64,
) -> Result<Page, VisionError> {
    let m = check_len("margin", margin_m)?;
    let dict = MarkerDictionary::parse(dictionary)?;
    let mk = check_len("marker size", marker_m)?;
    if mk <= 0.0 {
        return Err(VisionError::Printable(
            "marker size must be positive".into(),
        ));
    }
    let mut rects = Vec::new();
    marker_rects(&dict, id, m, m, mk, m, &mut rects)?;
    page(2.0 * m + mk, 2.0 * m + mk, rects, String::new())
}

/// Lays out the pages of a target with `margin_m` of white around it: one page, or
/// one per face of a multimarker set.
pub fn pages(target: &Target, margin_m: f64) -> Result<Vec<Page>, VisionError> {
    let m = check_len("margin", margin_m)?;
    let mut rects = Vec::new();
    match target {
        Target::Checkerboard(spec) => {
            spec.validate()?;
            let s = check_len("square size", spec.square_m)?;
            let (nc, nr) = (spec.cols + 1, spec.rows + 1);
            for b in 0..nr {
                for a in 0..nc {
                    if (a + b) % 2 == 0 {
                        rects.push([m + a as f64 * s, m + b as f64 * s, s, s]);
                    }
                }
            }
            Ok(vec![page(
                2.0 * m + nc as f64 * s,
                2.0 * m + nr as f64 * s,
                rects,
                String::new(),
            )?])
        }
        Target::Charuco(spec) => {
            let dict = spec.validate()?;
            let s = check_len("square size", spec.square_m)?;
            let mk = check_len("marker size", spec.marker_m)?;
            let [c, r] = spec.squares;
            for j in 0..r {
                for i in 0..c {
                    if (i + j) % 2 == 0 {
                        rects.push([m + i as f64 * s, m + j as f64 * s, s, s]);
                    }
                }
            }
            let board = spec.board(&dict)?;
            let ids = board.ids();
            for (quad, id) in board.obj_points().iter().zip(ids.iter()) {
                let q = quad.to_vec();
                let (x0, y0) = (f64::from(q[0].x) * 1e3, f64::from(q[0].y) * 1e3);
                // The first corner must be the top-left one (y down) for an upright marker.
                if q.iter()
                    .any(|p| f64::from(p.x) * 1e3 < x0 - 1e-3 || f64::from(p.y) * 1e3 < y0 - 1e-3)
                {
                    return Err(VisionError::Printable(
                        "OpenCV's ChArUco marker corners are not top-left first".into(),
                    ));
                }
                marker_rects(
                    &dict,
                    id as usize,
                    m + x0,
                    m + y0,
                    mk,
                    f64::INFINITY,
                    &mut rects,
                )?;
            }
            Ok(vec![page(
                2.0 * m + c as f64 * s,
                2.0 * m + r as f64 * s,
                rects,
                String::new(),
            )?])
        }
        Target::ArucoGrid(spec) => {
            let dict = spec.validate()?;
            let mk = check_len("marker size", spec.marker_m)?;
            let sep = check_len("separation", spec.separation_m)?;
            for k in 0..spec.marker_count() {
                let tl = spec.target_point(4 * k);
                marker_rects(
                    &dict,
                    spec.first_id + k,
                    m + tl.x * 1e3,
                    m + tl.y * 1e3,
                    mk,
                    if spec.marker_count() > 1 {
                        m.min(sep)
                    } else {
                        m
                    },
                    &mut rects,
                )?;
            }
            let [c, r] = spec.markers;
            let w = c as f64 * mk + (c - 1) as f64 * sep;
            let h = r as f64 * mk + (r - 1) as f64 * sep;
            Ok(vec![page(2.0 * m + w, 2.0 * m + h, rects, String::new())?])
        }
        Target::Multimarker { config, dictionary } => {
            let dict = *dictionary;
            config.check_dictionary(&dict)?;
            let mut out = Vec::new();
            for (f, face) in config.faces().iter().enumerate() {
                let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
                for (_, c, w) in &face.markers {
                    x0 = x0.min(c.x - w / 2.0);
                    x1 = x1.max(c.x + w / 2.0);
                    y0 = y0.min(c.y - w / 2.0);
                    y1 = y1.max(c.y + w / 2.0);
                }
                let mut rects = Vec::new();
                for (id, c, w) in &face.markers {
                    let x = m + (c.x - w / 2.0 - x0) * 1e3;
                    let y = m + (y1 - (c.y + w / 2.0)) * 1e3;
                    marker_rects(&dict, *id, x, y, w * 1e3, m, &mut rects)?;
                }
                out.push(page(
                    2.0 * m + (x1 - x0) * 1e3,
                    2.0 * m + (y1 - y0) * 1e3,
                    rects,
                    format!("face{f}"),
                )?);
            }
            Ok(out)
        }
    }
}

/// Writes `<stem>[-faceN].svg`, `<stem>[-faceN]-<dpi>dpi.png` and, for a multimarker
/// target, `<stem>.dat` into `dir`; returns the files written.
pub fn write_printable(
    target: &Target,
    dpi: f64,
    margin_m: f64,
    dir: &Path,
    stem: &str,
) -> Result<Vec<PathBuf>, VisionError> {
    let mut written = write_pages(&pages(target, margin_m)?, dpi, dir, stem)?;
    if let Target::Multimarker { config, .. } = target {
        let dat = dir.join(format!("{stem}.dat"));
        std::fs::write(&dat, config.to_dat()).map_err(|e| io_error(&dat, e))?;
        written.push(dat);
    }
    Ok(written)
}

fn io_error(path: &Path, source: std::io::Error) -> VisionError {
    VisionError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Writes each page as `<stem>[-<name>].svg` and `<stem>[-<name>]-<dpi>dpi.png` into
/// `dir` (a page's name is added when it has one); returns the files written.
pub fn write_pages(
    pages: &[Page],
    dpi: f64,
    dir: &Path,
    stem: &str,
) -> Result<Vec<PathBuf>, VisionError> {
    std::fs::create_dir_all(dir).map_err(|e| io_error(dir, e))?;
    let mut written = Vec::new();
    for p in pages {
        let base = if p.name.is_empty() {
            stem.to_string()
        } else {
            format!("{stem}-{}", p.name)
        };
        let svg = dir.join(format!("{base}.svg"));
        std::fs::write(&svg, p.svg()).map_err(|e| io_error(&svg, e))?;
        written.push(svg);
        let png = dir.join(format!("{base}-{}dpi.png", dpi.round()));
        let img = p.png(dpi)?;
        let path_str = png
            .to_str()
            .ok_or_else(|| VisionError::Printable(format!("{}: not UTF-8", png.display())))?;
        let ok = opencv::imgcodecs::imwrite(path_str, img.mat(), &opencv::core::Vector::new())
            .cv("imwrite")?;
        if !ok {
            return Err(VisionError::Printable(format!(
                "{}: imwrite failed",
                png.display()
            )));
        }
        written.push(png);
    }
    Ok(written)
}
