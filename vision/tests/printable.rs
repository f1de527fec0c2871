//! Printable targets: the PNG of every kind is found by its own detector with the
//! layout it was drawn with, and the SVG has the exact physical size.

use b2b_calib::camera::CameraModel;
use b2b_vision::multimarker::{MultimarkerConfig, detect_multimarker};
use b2b_vision::printable::{marker_page, pages, write_printable};
use b2b_vision::{
    ArucoGridSpec, CharucoSpec, CheckerboardSpec, GrayImage, MarkerDictionary, Target, VisionError,
    detect_aruco_grid, detect_charuco, detect_checkerboard, detect_marker,
};
use nalgebra::Point2;

const DPI: f64 = 150.0;
const MARGIN: f64 = 0.01;

fn ppm() -> f64 {
    DPI / 25.4
}

/// The page pixel (centre convention) of a point `mm` from the page's top-left, as
/// the PNG draws it: edges rounded to the nearest pixel boundary.
fn px(x_mm: f64, y_mm: f64) -> Point2<f64> {
    Point2::new((x_mm * ppm()).round() - 0.5, (y_mm * ppm()).round() - 0.5)
}

/// Detected corners must land on the drawn (pixel-rounded) corners.
const TOL_PX: f64 = 0.15;

/// A pinhole that sees the page frontally at the PNG's scale.
fn page_camera(img: &GrayImage) -> CameraModel {
    CameraModel::new(
        img.width(),
        img.height(),
        [
            5000.0,
            5000.0,
            img.width() as f64 / 2.0,
            img.height() as f64 / 2.0,
        ],
        &[],
    )
    .unwrap()
}

fn svg_size(svg: &str) -> (f64, f64) {
    let attr = |name: &str| -> f64 {
        let key = format!(" {name}=\"");
        let start = svg.find(&key).unwrap() + key.len();
        let end = start + svg[start..].find("mm\"").unwrap();
        svg[start..end].parse().unwrap()
    };
    (attr("width"), attr("height"))
}

fn max_error(found: &[Point2<f64>], expected: &[Point2<f64>]) -> f64 {
    assert_eq!(found.len(), expected.len());
    found
        .iter()
        .zip(expected)
        .map(|(a, b)| (a - b).norm())
        .fold(0.0, f64::max)
}

#[test]
fn checkerboard_page_is_detected_with_its_layout_and_svg_size() {
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.025,
    };
    let page = &pages(&Target::Checkerboard(spec), MARGIN).unwrap()[0];
    assert_eq!(svg_size(&page.svg()), (270.0, 195.0));
    let img = page.png(DPI).unwrap();
    assert_eq!(
        (img.width(), img.height()),
        (
            (270.0 * ppm()).round() as u32,
            (195.0 * ppm()).round() as u32
        )
    );
    let det = detect_checkerboard(&img, &spec).unwrap();
    let expected: Vec<_> = det
        .corner_ids
        .iter()
        .map(|&k| {
            px(
                10.0 + 25.0 * ((k % 9) as f64 + 1.0),
                10.0 + 25.0 * ((k / 9) as f64 + 1.0),
            )
        })
        .collect();
    let e = max_error(&det.pixels, &expected);
    eprintln!("checkerboard page: max corner error {e:.3} px");
    assert!(e < TOL_PX, "{e}");
}

#[test]
fn charuco_grid_and_marker_pages_are_detected_with_their_layout() {
    let charuco = CharucoSpec {
        squares: [7, 5],
        square_m: 0.04,
        marker_m: 0.028,
        dictionary: "DICT_5X5_100".into(),
    };
    let page = &pages(&Target::Charuco(charuco.clone()), MARGIN).unwrap()[0];
    assert_eq!(svg_size(&page.svg()), (300.0, 220.0));
    let img = page.png(DPI).unwrap();
    let det = detect_charuco(&img, &charuco, &page_camera(&img)).unwrap();
    assert_eq!(det.corner_ids.len(), charuco.corner_count());
    let expected: Vec<_> = det
        .target_points
        .iter()
        .map(|p| px(10.0 + p.x * 1e3, 10.0 + p.y * 1e3))
        .collect();
    let e = max_error(&det.pixels, &expected);
    eprintln!("charuco page: max corner error {e:.3} px");
    assert!(e < TOL_PX, "{e}");

    let grid = ArucoGridSpec {
        markers: [4, 3],
        marker_m: 0.05,
        separation_m: 0.01,
        dictionary: "DICT_6X6_250".into(),
        first_id: 3,
    };
    let page = &pages(&Target::ArucoGrid(grid.clone()), MARGIN).unwrap()[0];
    assert_eq!(svg_size(&page.svg()), (250.0, 190.0));
    let img = page.png(DPI).unwrap();
    let det = detect_aruco_grid(&img, &grid).unwrap();
    assert_eq!(det.corner_ids.len(), 48);
    let expected: Vec<_> = det
        .target_points
        .iter()
        .map(|p| px(10.0 + p.x * 1e3, 10.0 + p.y * 1e3))
        .collect();
    let e = max_error(&det.pixels, &expected);
    eprintln!("aruco grid page: max corner error {e:.3} px");
    assert!(e < TOL_PX, "{e}");

    let page = &marker_page("DICT_APRILTAG_36h11", 7, 0.06, MARGIN).unwrap();
    assert_eq!(svg_size(&page.svg()), (80.0, 80.0));
    let img = page.png(DPI).unwrap();
    let det = detect_marker(&img, "DICT_APRILTAG_36h11", 7, 0.06).unwrap();
    // Top-left, top-right, bottom-right, bottom-left.
    let expected = [
        px(10.0, 10.0),
        px(70.0, 10.0),
        px(70.0, 70.0),
        px(10.0, 70.0),
    ];
    let e = max_error(&det.pixels, &expected);
    assert!(e < TOL_PX, "{e}");
    assert!(matches!(
        detect_marker(&img, "DICT_APRILTAG_36h11", 8, 0.06),
        Err(VisionError::MarkersNotFound { .. })
    ));
}

#[test]
fn multimarker_pages_and_file_are_written_and_detected() {
    let dir = tempfile::tempdir().unwrap();
    for (stem, config, dictionary, n_pages) in [
        ("grid", MultimarkerConfig::grid_4x3(), "DICT_4X4_50", 1),
        (
            "corner",
            MultimarkerConfig::three_face_corner(),
            "DICT_APRILTAG_36h11",
            3,
        ),
    ] {
        let target = Target::Multimarker {
            config: config.clone(),
            dictionary: MarkerDictionary::parse(dictionary).unwrap(),
        };
        let files = write_printable(&target, DPI, MARGIN, dir.path(), stem).unwrap();
        assert_eq!(files.len(), 2 * n_pages + 1, "{files:?}");
        let back = MultimarkerConfig::load(&dir.path().join(format!("{stem}.dat"))).unwrap();
        assert_eq!(back.markers.len(), 12);
        let dict = MarkerDictionary::parse(dictionary).unwrap();
        let mut seen = Vec::new();
        for (face, page) in config.faces().iter().zip(pages(&target, MARGIN).unwrap()) {
            let x0 = face
                .markers
                .iter()
                .map(|(_, c, w)| c.x - w / 2.0)
                .fold(f64::MAX, f64::min);
            let y1 = face
                .markers
                .iter()
                .map(|(_, c, w)| c.y + w / 2.0)
                .fold(f64::MIN, f64::max);
            let w = face
                .markers
                .iter()
                .map(|(_, c, w)| c.x + w / 2.0)
                .fold(f64::MIN, f64::max)
                - x0;
            let h = y1
                - face
                    .markers
                    .iter()
                    .map(|(_, c, w)| c.y - w / 2.0)
                    .fold(f64::MAX, f64::min);
            let (sw, sh) = svg_size(&page.svg());
            assert!((sw - (w * 1e3 + 20.0)).abs() < 1e-9 && (sh - (h * 1e3 + 20.0)).abs() < 1e-9);
            let png = opencv::imgcodecs::imread(
                files
                    .iter()
                    .find(|f| {
                        f.to_str().unwrap().ends_with(&format!("{}dpi.png", DPI))
                            && (n_pages == 1 || f.to_str().unwrap().contains(&page.name))
                    })
                    .unwrap()
                    .to_str()
                    .unwrap(),
                opencv::imgcodecs::IMREAD_GRAYSCALE,
            )
            .unwrap();
            let img = GrayImage::from_mat(png).unwrap();
            let det = detect_multimarker(&img, &config, &dict, &page_camera(&img)).unwrap();
            let ids: Vec<usize> = face.markers.iter().map(|(id, ..)| *id).collect();
            let mut sorted = ids.clone();
            sorted.sort();
            assert_eq!(det.markers, sorted, "{stem} {}", page.name);
            // Corner pixels: face (x, y) -> page mm (margin + x - x0, margin + y1 - y).
            for (k, uv) in det.detection.corner_ids.iter().zip(&det.detection.pixels) {
                let (id, c) = (k / 4, k % 4);
                let m = config.marker(id).unwrap();
                let p = face.set_from_face.inverse() * m.corners()[c];
                let e = (uv - px(10.0 + (p.x - x0) * 1e3, 10.0 + (y1 - p.y) * 1e3)).norm();
                assert!(e < TOL_PX, "{stem} marker {id} corner {c}: {e} px");
            }
            seen.extend(ids);
        }
        seen.sort();
        assert_eq!(seen, (0..12).collect::<Vec<_>>());
    }
}

#[test]
fn bad_printing_requests_are_refused() {
    let spec = CheckerboardSpec {
        cols: 9,
        rows: 6,
        square_m: 0.025,
    };
    let page = &pages(&Target::Checkerboard(spec), MARGIN).unwrap()[0];
    for dpi in [0.0, -5.0, f64::NAN, 1e6] {
        assert!(
            matches!(page.png(dpi), Err(VisionError::Printable(_))),
            "{dpi}"
        );
    }
    let huge = CheckerboardSpec {
        cols: 99,
        rows: 100,
        square_m: 0.1,
    };
    assert!(pages(&Target::Checkerboard(huge), MARGIN).is_err());
    assert!(pages(&Target::Checkerboard(spec), -0.01).is_err());
    assert!(matches!(
        marker_page("DICT_4X4_50", 50, 0.05, MARGIN),
        Err(VisionError::InvalidTarget(_))
    ));
    assert!(matches!(
        marker_page("DICT_9X9_1", 0, 0.05, MARGIN),
        Err(VisionError::UnknownDictionary(_))
    ));
    // Less white around a marker than one of its cells (12.5 mm here).
    let tight = |margin_m| marker_page("DICT_APRILTAG_36h11", 0, 0.1, margin_m);
    let err = tight(0.01).unwrap_err();
    assert!(err.to_string().contains("quiet zone"), "{err}");
    assert!(tight(0.0125).is_ok());
    let readonly = std::path::Path::new("/proc/nonexistent-dir");
    assert!(write_printable(&Target::Checkerboard(spec), DPI, MARGIN, readonly, "x").is_err());
}
