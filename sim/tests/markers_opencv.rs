//! The simulator's marker dictionaries and board layouts are OpenCV's, bit for bit.

use b2b_sim::markers::{Dictionary, Sheet, aruco_grid_sheet, charuco_sheet};
use b2b_vision::{CharucoSpec, render_charuco};
use opencv::aruco;
use opencv::core::{Mat, Size};
use opencv::prelude::*;

/// OpenCV's drawing of marker `id` at one pixel per cell: `(n + 2)²` grey levels.
fn opencv_marker(dict_index: i32, id: i32, cells: i32) -> Vec<u8> {
    let dict = aruco::get_predefined_dictionary_i32(dict_index).unwrap();
    let mut img = Mat::default();
    aruco::draw_marker(&dict, id, cells, &mut img, 1).unwrap();
    img.data_bytes().unwrap().to_vec()
}

/// Prints the code tables of `sim/src/markers/codes.rs` (run once, by hand).
#[test]
#[ignore = "generator: cargo test -p b2b-sim --test markers_opencv -- --ignored --nocapture"]
fn print_code_tables() {
    for (name, index, n, count) in [
        ("DICT_4X4", 2, 4, 250),
        ("DICT_5X5", 6, 5, 250),
        ("DICT_6X6", 10, 6, 250),
        ("DICT_APRILTAG_36H11", 20, 6, 587),
    ] {
        println!("pub(super) const {name}: [u64; {count}] = [");
        for id in 0..count {
            let px = opencv_marker(index, id, n + 2);
            let w = (n + 2) as usize;
            let mut code = 0u64;
            for r in 0..n as usize {
                for c in 0..n as usize {
                    code = (code << 1) | u64::from(px[(r + 1) * w + c + 1] > 127);
                }
            }
            println!("    {code:#x},");
        }
        println!("];");
    }
}

/// OpenCV's dictionary index (`PREDEFINED_DICTIONARY_NAME`) of each embedded name.
fn opencv_index(name: &str) -> i32 {
    match name {
        "DICT_4X4_50" => 0,
        "DICT_4X4_100" => 1,
        "DICT_4X4_250" => 2,
        "DICT_5X5_50" => 4,
        "DICT_5X5_100" => 5,
        "DICT_5X5_250" => 6,
        "DICT_6X6_50" => 8,
        "DICT_6X6_100" => 9,
        "DICT_6X6_250" => 10,
        "DICT_APRILTAG_36h11" => 20,
        other => panic!("no OpenCV index for {other}"),
    }
}

#[test]
fn every_embedded_marker_is_opencvs() {
    let mut checked = 0;
    for dict in Dictionary::all() {
        let index = opencv_index(dict.name());
        let cells = dict.bits() + 2;
        for id in 0..dict.count() {
            let ours = dict.marker_bitmap(id).unwrap();
            let theirs = opencv_marker(index, id as i32, cells as i32);
            assert_eq!(ours, theirs, "{} id {id}", dict.name());
            checked += 1;
        }
    }
    assert_eq!(
        checked,
        50 + 100 + 250 + 50 + 100 + 250 + 50 + 100 + 250 + 587
    );
}

/// `sheet.level` at the centre of every pixel of an image where `board point (x, y) =
/// ((u + 0.5 - offset) / px_per_m, ...)`, against OpenCV's drawing (white outside
/// `extent`). Returns the number of pixels that differ, after failing on any pixel
/// where OpenCV differs from the sheet at every point within `tolerance_px` of it
/// (OpenCV rounds the position of each marker it draws to whole pixels).
fn compare_sheet(
    sheet: &Sheet,
    img: &Mat,
    offset: f64,
    px_per_m: f64,
    extent: [f64; 2],
    tolerance_px: i32,
) -> usize {
    let (w, h) = (img.cols() as usize, img.rows() as usize);
    let px = img.data_bytes().unwrap();
    let ours = |u: f64, v: f64| {
        let x = (u + 0.5 - offset) / px_per_m;
        let y = (v + 0.5 - offset) / px_per_m;
        let inside = x > 0.0 && y > 0.0 && x < extent[0] && y < extent[1];
        if inside { sheet.level(x, y) } else { 255 }
    };
    let (mut differ, mut wrong) = (0, 0);
    for v in 0..h {
        for u in 0..w {
            let theirs = px[v * w + u];
            if ours(u as f64, v as f64) == theirs {
                continue;
            }
            differ += 1;
            let t = tolerance_px;
            let near = (-t..=t).any(|dv| {
                (-t..=t).any(|du| ours((u as i32 + du) as f64, (v as i32 + dv) as f64) == theirs)
            });
            if !near {
                wrong += 1;
            }
        }
    }
    assert_eq!(
        wrong,
        0,
        "{wrong} of {} pixels differ beyond {tolerance_px} px",
        w * h
    );
    differ
}

#[test]
fn charuco_sheet_is_opencvs_board() {
    let spec = CharucoSpec {
        squares: [7, 5],
        square_m: 0.04,
        marker_m: 0.028,
        dictionary: "DICT_5X5_100".into(),
    };
    // 2 mm per pixel: every edge of squares and marker cells falls between pixels.
    let pps = 20;
    let img = render_charuco(&spec, pps).unwrap();
    let sheet = charuco_sheet([7, 5], 0.04, 0.028, "DICT_5X5_100").unwrap();
    // OpenCV's CharucoBoard::draw places some markers one pixel off (rounding), so
    // edges may differ by a pixel; anything else is a layout or code error.
    let differ = compare_sheet(&sheet, img.mat(), pps as f64, 500.0, [0.28, 0.2], 1);
    assert!(differ < 25200 / 20, "{differ}");
    // A different dictionary or marker size is visibly different (the check can fail).
    let other = charuco_sheet([7, 5], 0.04, 0.028, "DICT_5X5_250").unwrap();
    assert_eq!(other.level(0.06, 0.02), sheet.level(0.06, 0.02));
    let shifted = charuco_sheet([7, 5], 0.04, 0.024, "DICT_5X5_100").unwrap();
    let r = std::panic::catch_unwind(|| {
        compare_sheet(&shifted, img.mat(), pps as f64, 500.0, [0.28, 0.2], 1)
    });
    assert!(r.is_err());
}

#[test]
fn aruco_grid_sheet_is_opencvs_grid_board() {
    // 4000 px/m: markers 200 px (cells 25 px), gaps 40 px, 100 px margins.
    let mut board = aruco::GridBoard::create(
        4,
        3,
        0.05,
        0.01,
        &aruco::get_predefined_dictionary_i32(10).unwrap(),
        3,
    )
    .unwrap();
    let mut img = Mat::default();
    board
        .draw(Size::new(920 + 200, 680 + 200), &mut img, 100, 1)
        .unwrap();
    let sheet = aruco_grid_sheet([4, 3], 0.05, 0.01, "DICT_6X6_250", 3).unwrap();
    assert_eq!(
        compare_sheet(&sheet, &img, 100.0, 4000.0, [0.23, 0.17], 0),
        0
    );
}
