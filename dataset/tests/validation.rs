//! One test per validation rule: each breaks the valid fixture in one way and checks the
//! error variant and that the message names the file and the row or field.

mod common;

use std::fs;

use b2b_dataset::{DatasetError as E, load_ground_truth, load_reference};
use common::{Fixture, assert_message};

const C1: &str = "robot1/captures.csv";
const C2: &str = "robot2/captures.csv";
const M: &str = "dataset.json";
const T: &str = "touch_points.csv";
const ROW2_C1: &str = "images/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0";

fn row2(fx: &Fixture, replacement: &str) {
    fx.edit(C1, ROW2_C1, replacement);
}

#[test]
fn the_fixture_is_valid() {
    let fx = Fixture::new();
    let ds = fx.load().expect("fixture loads");
    assert_eq!(ds.robots.len(), 2);
    assert_eq!(ds.robots[0].captures.len(), 2);
    assert_eq!(ds.robots[1].captures.len(), 2);
    assert!(ds.robots[1].captures[0].image.is_none());
    assert!(ds.robots[1].captures[0].camera_from_target.is_some());
    assert!(ds.robots[1].captures[1].camera_from_target.is_none());
    assert_eq!(ds.touch_points.as_ref().map(Vec::len), Some(2));
    let c = &ds.robots[0].captures[0];
    assert_eq!(
        ds.image_path("robot1", c),
        Some(fx.path("robot1/images/000.png"))
    );
    assert_eq!(
        ds.depth_path("robot1", c),
        Some(fx.path("robot1/depth/000.png"))
    );
}

// --- files -------------------------------------------------------------------------

#[test]
fn missing_dataset_json() {
    let fx = Fixture::new();
    fs::remove_file(fx.path(M)).unwrap();
    let e = fx.load_err(M, &["not found"]);
    assert!(matches!(e, E::MissingFile { .. }), "{e}");
}

#[test]
fn missing_captures_csv() {
    let fx = Fixture::new();
    fs::remove_file(fx.path(C2)).unwrap();
    let e = fx.load_err(C2, &["not found"]);
    assert!(matches!(e, E::MissingFile { .. }), "{e}");
}

#[test]
fn unreadable_dataset_json() {
    let fx = Fixture::new();
    fs::remove_file(fx.path(M)).unwrap();
    fs::create_dir(fx.path(M)).unwrap();
    let e = fx.load_err(M, &["is a directory, not a regular file"]);
    assert!(matches!(e, E::NotARegularFile { .. }), "{e}");
}

#[test]
fn invalid_json_reports_line_and_column() {
    let fx = Fixture::new();
    fx.edit(M, "\"name\": \"fixture\",", "\"name\": \"fixture\"");
    let e = fx.load_err(M, &["line 4, column"]);
    assert!(matches!(e, E::Json { line: 4, .. }), "{e}");
}

#[test]
fn json_of_the_wrong_type_reports_line() {
    let fx = Fixture::new();
    fx.edit(M, "\"width\": 1280", "\"width\": \"1280\"");
    let e = fx.load_err(M, &["line 11", "field `robots[0].camera.width`"]);
    assert!(matches!(e, E::Json { .. }), "{e}");
}

#[test]
fn wrong_format() {
    let fx = Fixture::new();
    fx.edit(M, "b2b-dataset/1", "b2b-dataset/2");
    let e = fx.load_err(M, &["field `format`", "b2b-dataset/2"]);
    assert!(matches!(e, E::WrongFormat { .. }), "{e}");
}

const TARGET_LINE: &str =
    r#""target": { "kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.025 },"#;

fn with_targets(fx: &Fixture, targets: &str) {
    fx.edit(
        M,
        TARGET_LINE,
        &format!("{TARGET_LINE}\n  \"targets\": {targets},"),
    );
}

#[test]
fn further_targets_and_the_target_column_are_read() {
    let fx = Fixture::new();
    with_targets(
        &fx,
        r#"{ "side": { "kind": "checkerboard", "inner_corners": [7, 5], "square_m": 0.03 } }"#,
    );
    fx.edit(C1, "tx,ty,tz,qx,qy,qz,qw", "tx,ty,tz,qx,qy,qz,qw,target");
    let text = fs::read_to_string(fx.path(C1)).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    lines[1].push(',');
    lines[2].push_str(",side");
    fx.write(C1, &(lines.join("\n") + "\n"));
    let ds = fx.load().expect("loads");
    assert_eq!(ds.manifest.targets.len(), 1);
    let caps = &ds.robots[0].captures;
    assert_eq!(caps[0].target, None);
    assert_eq!(caps[1].target.as_deref(), Some("side"));
    assert_eq!(
        (ds.target_index(&caps[0]), ds.target_index(&caps[1])),
        (0, 1)
    );
}

#[test]
fn a_further_target_of_unknown_kind_is_named() {
    let fx = Fixture::new();
    with_targets(&fx, r#"{ "side": { "kind": "dartboard" } }"#);
    let e = fx.load_err(M, &["field `targets.side.kind`", "dartboard"]);
    assert!(matches!(e, E::UnknownTargetKind { .. }), "{e}");
}

#[test]
fn a_further_target_with_a_bad_size_is_named() {
    let fx = Fixture::new();
    with_targets(
        &fx,
        r#"{ "side": { "kind": "checkerboard", "inner_corners": [9, 6], "square_m": -1 } }"#,
    );
    let e = fx.load_err(M, &["field `targets.side.square_m`", "positive"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
}

#[test]
fn a_capture_of_an_unlisted_target_is_refused() {
    let fx = Fixture::new();
    fx.edit(C1, "tx,ty,tz,qx,qy,qz,qw", "tx,ty,tz,qx,qy,qz,qw,target");
    let text = fs::read_to_string(fx.path(C1)).unwrap();
    let mut lines: Vec<String> = text.lines().map(str::to_owned).collect();
    lines[1].push_str(",side");
    lines[2].push(',');
    fx.write(C1, &(lines.join("\n") + "\n"));
    let e = fx.load_err(C1, &["row 1", "field `target`", "`side`", "lists none"]);
    assert!(matches!(e, E::UnknownTarget { .. }), "{e}");
}

// --- captures.csv header and cells ---------------------------------------------------

#[test]
fn header_missing_column() {
    let fx = Fixture::new();
    fx.write(C1, "image,depth,tx,ty,qx,qy,qz,qw\n");
    let e = fx.load_err(C1, &["line 1", "field `tz`", "missing"]);
    assert!(matches!(e, E::BadHeader { .. }), "{e}");
}

#[test]
fn header_misnamed_column() {
    let fx = Fixture::new();
    fx.edit(C1, "tx,ty,tz", "x,ty,tz");
    let e = fx.load_err(C1, &["line 1", "field `x`", "unknown column"]);
    assert!(matches!(e, E::BadHeader { .. }), "{e}");
}

#[test]
fn header_incomplete_camera_pose_block() {
    let fx = Fixture::new();
    fx.write(
        C2,
        "image,depth,tx,ty,tz,qx,qy,qz,qw,ctx,cty,ctz,cqx,cqy,cqz\n",
    );
    let e = fx.load_err(C2, &["line 1", "field `cqw`", "block of 7"]);
    assert!(matches!(e, E::BadHeader { .. }), "{e}");
}

#[test]
fn wrong_number_of_fields() {
    let fx = Fixture::new();
    row2(&fx, "images/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0,");
    let e = fx.load_err(C1, &["row 2 (line 3)", "10 fields", "header has 9"]);
    assert!(
        matches!(
            e,
            E::FieldCount {
                expected: 9,
                found: 10,
                ..
            }
        ),
        "{e}"
    );
}

#[test]
fn unparsable_number() {
    let fx = Fixture::new();
    row2(&fx, "images/001.png,,0.5,-0.1O,0.6,0.0,0.0,0.0,1.0");
    let e = fx.load_err(C1, &["row 2 (line 3)", "field `ty`", "`-0.1O`"]);
    assert!(matches!(e, E::BadNumber { .. }), "{e}");
}

#[test]
fn empty_number() {
    let fx = Fixture::new();
    row2(&fx, "images/001.png,,0.5,-0.1,0.6,0.0,0.0,,1.0");
    let e = fx.load_err(C1, &["row 2 (line 3)", "field `qz`", "empty"]);
    assert!(matches!(e, E::BadNumber { .. }), "{e}");
}

#[test]
fn non_finite_numbers() {
    for bad in ["NaN", "inf", "-infinity"] {
        let fx = Fixture::new();
        row2(
            &fx,
            &format!("images/001.png,,0.5,-0.1,{bad},0.0,0.0,0.0,1.0"),
        );
        let e = fx.load_err(C1, &["row 2 (line 3)", "field `tz`", "not finite"]);
        assert!(matches!(e, E::NonFinite { .. }), "{e}");
    }
}

#[test]
fn quaternion_far_from_unit() {
    let fx = Fixture::new();
    row2(&fx, "images/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.01");
    let e = fx.load_err(C1, &["row 2 (line 3)", "field `qx..qw`", "norm"]);
    assert!(matches!(e, E::NotUnitQuaternion { .. }), "{e}");
}

#[test]
fn zero_quaternion_is_rejected() {
    // E.g. a column of zeros left by a recorder that never got a pose.
    let fx = Fixture::new();
    row2(&fx, "images/001.png,,0.5,-0.1,0.6,0,0,0,0");
    let e = fx.load_err(C1, &["row 2", "qx..qw"]);
    assert!(matches!(e, E::NotUnitQuaternion { .. }), "{e}");
}

#[test]
fn quaternion_near_unit_is_normalised() {
    let fx = Fixture::new();
    row2(&fx, "images/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0009");
    let ds = fx.load().unwrap();
    let q = ds.robots[0].captures[1].base_from_flange.rotation;
    assert_eq!(q.quaternion().w, 1.0);
}

#[test]
fn translation_in_millimetres() {
    let fx = Fixture::new();
    row2(&fx, "images/001.png,,512.0,-103.0,644.0,0.0,0.0,0.0,1.0");
    let e = fx.load_err(
        C1,
        &[
            "row 2 (line 3)",
            "field `tx`",
            "looks like millimetres",
            "metres",
        ],
    );
    assert!(matches!(e, E::LooksLikeMillimetres { .. }), "{e}");
}

#[test]
fn camera_pose_in_millimetres() {
    let fx = Fixture::new();
    fx.edit(C2, "0.01,0.02,0.7,", "0.01,0.02,700,");
    let e = fx.load_err(C2, &["row 1 (line 2)", "field `ctz`", "millimetres"]);
    assert!(matches!(e, E::LooksLikeMillimetres { .. }), "{e}");
}

#[test]
fn duplicate_image() {
    let fx = Fixture::new();
    row2(&fx, "images/000.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0");
    let e = fx.load_err(
        C1,
        &["row 2 (line 3)", "field `image`", "already used by row 1"],
    );
    assert!(matches!(e, E::DuplicateImage { first_row: 1, .. }), "{e}");
}

#[test]
fn missing_image_file() {
    let fx = Fixture::new();
    fs::remove_file(fx.path("robot1/images/001.png")).unwrap();
    let e = fx.load_err(C1, &["row 2 (line 3)", "field `image`", "does not exist"]);
    assert!(matches!(e, E::MissingImage { .. }), "{e}");
    assert!(
        e.to_string()
            .contains(&fx.path("robot1/images/001.png").display().to_string())
    );
}

#[test]
fn row_without_image_or_board_pose() {
    let fx = Fixture::new();
    fx.edit(C2, "images/a.jpg,,", ",,");
    let e = fx.load_err(C2, &["row 2 (line 3)", "neither an image nor"]);
    assert!(matches!(e, E::NoObservation { .. }), "{e}");
}

#[test]
fn row_without_image_and_no_pose_columns() {
    let fx = Fixture::new();
    row2(&fx, ",,0.5,-0.1,0.6,0.0,0.0,0.0,1.0");
    let e = fx.load_err(C1, &["row 2 (line 3)", "neither an image nor"]);
    assert!(matches!(e, E::NoObservation { .. }), "{e}");
}

#[test]
fn partly_filled_board_pose() {
    let fx = Fixture::new();
    fx.edit(C2, "0.01,0.02,0.7,0,0,0,1", "0.01,0.02,0.7,0,0,0,");
    let e = fx.load_err(C2, &["row 1 (line 2)", "field `cqw`", "partly empty"]);
    assert!(matches!(e, E::PartialCameraPose { .. }), "{e}");
}

#[test]
fn absolute_image_path() {
    let fx = Fixture::new();
    row2(&fx, "/tmp/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0");
    let e = fx.load_err(C1, &["row 2 (line 3)", "field `image`", "absolute"]);
    assert!(matches!(e, E::BadPath { .. }), "{e}");
}

// --- depth ---------------------------------------------------------------------------

#[test]
fn missing_depth_file() {
    let fx = Fixture::new();
    fs::remove_file(fx.path("robot1/depth/000.png")).unwrap();
    let e = fx.load_err(C1, &["row 1 (line 2)", "field `depth`", "does not exist"]);
    assert!(matches!(e, E::MissingDepth { .. }), "{e}");
}

#[test]
fn depth_without_depth_unit() {
    let fx = Fixture::new();
    fx.edit(M, ",\n      \"depth_unit_m\": 0.001", "");
    let e = fx.load_err(
        C1,
        &["row 1 (line 2)", "field `depth`", "depth_unit_m", "robot1"],
    );
    assert!(matches!(e, E::DepthWithoutUnit { .. }), "{e}");
}

#[test]
fn non_positive_depth_unit() {
    let fx = Fixture::new();
    fx.edit(M, "\"depth_unit_m\": 0.001", "\"depth_unit_m\": 0");
    let e = fx.load_err(M, &["field `robots[0].depth_unit_m`"]);
    assert!(matches!(e, E::InvalidManifest { .. }), "{e}");
}

// --- robots --------------------------------------------------------------------------

#[test]
fn robot_without_folder() {
    let fx = Fixture::new();
    fs::remove_dir_all(fx.path("robot2")).unwrap();
    let e = fx.load_err(M, &["field `robots[1].id`", "robot2", "does not exist"]);
    assert!(matches!(e, E::MissingRobotFolder { .. }), "{e}");
}

#[test]
fn extra_folders_are_fine() {
    let fx = Fixture::new();
    fx.write("robot3/captures.csv", "garbage");
    fx.write("original/notes.txt", "anything");
    fx.load().expect("extra folders are allowed");
}

#[test]
fn duplicate_robot_id() {
    let fx = Fixture::new();
    fx.edit(M, "{ \"id\": \"robot2\" }", "{ \"id\": \"robot1\" }");
    let e = fx.load_err(M, &["field `robots[1].id`", "listed twice"]);
    assert!(matches!(e, E::DuplicateRobot { first: 0, .. }), "{e}");
}

#[test]
fn robot_id_that_is_not_a_folder_name() {
    let fx = Fixture::new();
    fx.edit(M, "{ \"id\": \"robot2\" }", "{ \"id\": \"../robot2\" }");
    let e = fx.load_err(M, &["field `robots[1].id`", "path separator"]);
    assert!(matches!(e, E::InvalidManifest { .. }), "{e}");
}

#[test]
fn no_robots() {
    let fx = Fixture::new();
    let manifest = r#"{"format": "b2b-dataset/1", "name": "x",
        "target": {"kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.02},
        "robots": []}"#;
    fx.write(M, manifest);
    let e = fx.load_err(M, &["field `robots`", "no robots"]);
    assert!(matches!(e, E::InvalidManifest { .. }), "{e}");
}

// --- target --------------------------------------------------------------------------

fn with_target(target: &str) -> Fixture {
    let fx = Fixture::new();
    fx.edit(
        M,
        r#"{ "kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.025 }"#,
        target,
    );
    fx
}

#[test]
fn target_non_positive_square() {
    for bad in ["0", "-0.025"] {
        let fx = with_target(&format!(
            r#"{{ "kind": "checkerboard", "inner_corners": [9, 6], "square_m": {bad} }}"#
        ));
        let e = fx.load_err(M, &["field `target.square_m`", "positive"]);
        assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
    }
}

#[test]
fn target_too_few_inner_corners() {
    let fx =
        with_target(r#"{ "kind": "checkerboard", "inner_corners": [9, 1], "square_m": 0.02 }"#);
    let e = fx.load_err(M, &["field `target.inner_corners[1]`", "at least 2"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
}

#[test]
fn charuco_marker_not_smaller_than_square() {
    let fx = with_target(
        r#"{ "kind": "charuco", "squares": [5, 7], "square_m": 0.03, "marker_m": 0.03, "dictionary": "DICT_5X5_100" }"#,
    );
    let e = fx.load_err(M, &["field `target.marker_m`", "not smaller than square_m"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
}

#[test]
fn charuco_unknown_dictionary() {
    let fx = with_target(
        r#"{ "kind": "charuco", "squares": [5, 7], "square_m": 0.03, "marker_m": 0.02, "dictionary": "DICT_5x5_100" }"#,
    );
    let e = fx.load_err(M, &["field `target.dictionary`", "DICT_5x5_100"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
}

#[test]
fn aruco_grid_non_positive_separation() {
    let fx = with_target(
        r#"{ "kind": "aruco_grid", "markers": [4, 3], "marker_m": 0.04, "separation_m": 0.0, "dictionary": "DICT_6X6_250", "first_id": 0 }"#,
    );
    let e = fx.load_err(M, &["field `target.separation_m`", "positive"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
}

#[test]
fn aruco_grid_ids_beyond_dictionary() {
    let fx = with_target(
        r#"{ "kind": "aruco_grid", "markers": [4, 3], "marker_m": 0.04, "separation_m": 0.01, "dictionary": "DICT_4X4_50", "first_id": 40 }"#,
    );
    let e = fx.load_err(M, &["field `target.dictionary`", "has 50"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
}

#[test]
fn multimarker_config_must_exist() {
    let fx = with_target(
        r#"{ "kind": "multimarker", "config": "target/multi.dat", "dictionary": "ARTOOLKIT" }"#,
    );
    let e = fx.load_err(M, &["field `target.config`", "does not exist"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");
    fx.write("target/multi.dat", "# 0 markers\n0\n");
    let ds = fx.load().expect("config now exists");
    assert_eq!(
        ds.multimarker_config_path(),
        Some(fx.path("target/multi.dat"))
    );
}

#[test]
fn unknown_target_kind() {
    let fx = with_target(r#"{ "kind": "circles_grid", "size": [4, 11] }"#);
    let e = fx.load_err(M, &["field `target.kind`", "circles_grid"]);
    assert!(matches!(e, E::UnknownTargetKind { .. }), "{e}");
}

#[test]
fn target_missing_parameter() {
    let fx = with_target(r#"{ "kind": "charuco", "squares": [5, 7], "square_m": 0.03 }"#);
    let e = fx.load_err(M, &["marker_m"]);
    assert!(matches!(e, E::Json { .. }), "{e}");
}

// --- camera --------------------------------------------------------------------------

#[test]
fn camera_non_positive_focal_length() {
    let fx = Fixture::new();
    fx.edit(M, "\"fy\": 910.0", "\"fy\": -910.0");
    let e = fx.load_err(M, &["field `robots[0].camera.fy`", "positive"]);
    assert!(matches!(e, E::InvalidCamera { .. }), "{e}");
}

#[test]
fn camera_zero_size() {
    let fx = Fixture::new();
    fx.edit(M, "\"height\": 720", "\"height\": 0");
    let e = fx.load_err(M, &["field `robots[0].camera.height`"]);
    assert!(matches!(e, E::InvalidCamera { .. }), "{e}");
}

#[test]
fn camera_distortion_length() {
    for dist in [
        "[0.0, 0.0, 0.0]",
        "[0,0,0,0,0,0,0,0,0,0,0,0,0,0,0]",
        "[0,0,0,0,0,0]",
    ] {
        let fx = Fixture::new();
        fx.edit(M, "[0.0, 0.0, 0.0, 0.0, 0.0]", dist);
        let e = fx.load_err(M, &["field `robots[0].camera.dist`", "4, 5, 8, 12 or 14"]);
        assert!(matches!(e, E::InvalidCamera { .. }), "{e}");
    }
}

// --- touch_points.csv ----------------------------------------------------------------

#[test]
fn touch_points_bad_header() {
    let fx = Fixture::new();
    fx.edit(T, "x1,y1,z1,x2,y2,z2", "x1,y1,z1,x2,y2");
    let e = fx.load_err(T, &["line 1", "field `z2`", "missing"]);
    assert!(matches!(e, E::BadHeader { .. }), "{e}");
}

#[test]
fn touch_points_non_finite() {
    let fx = Fixture::new();
    fx.edit(T, "0.5,0.0,0.1,", "0.5,nan,0.1,");
    let e = fx.load_err(T, &["row 2 (line 3)", "field `y1`", "not finite"]);
    assert!(matches!(e, E::NonFinite { .. }), "{e}");
}

#[test]
fn touch_points_in_millimetres() {
    let fx = Fixture::new();
    fx.edit(T, "0.3,-0.2,0.1", "300,-200,100");
    let e = fx.load_err(T, &["row 2 (line 3)", "field `x2`", "millimetres"]);
    assert!(matches!(e, E::LooksLikeMillimetres { .. }), "{e}");
}

#[test]
fn touch_points_field_count() {
    let fx = Fixture::new();
    fx.edit(T, "0.5,0.0,0.1,0.3,-0.2,0.1", "0.5,0.0,0.1,0.3,-0.2");
    let e = fx.load_err(T, &["row 2 (line 3)", "5 fields"]);
    assert!(matches!(e, E::FieldCount { .. }), "{e}");
}

#[test]
fn touch_points_need_two_robots() {
    let fx = Fixture::new();
    fx.edit(M, ",\n    { \"id\": \"robot2\" }", "");
    let e = fx.load_err(T, &["1 robot"]);
    assert!(
        matches!(e, E::TouchPointsNeedTwoRobots { robots: 1, .. }),
        "{e}"
    );
}

// --- ground truth and reference --------------------------------------------------------

#[test]
fn loading_never_reads_ground_truth_or_reference() {
    let fx = Fixture::new();
    fx.write("ground_truth.json", "{ this is not JSON");
    fx.write("reference.json", "{ neither is this");
    fx.load()
        .expect("Dataset::load must not read ground_truth.json or reference.json");
    assert!(matches!(load_ground_truth(fx.root()), Err(E::Json { .. })));
    assert!(matches!(load_reference(fx.root()), Err(E::Json { .. })));
}

#[test]
fn absent_ground_truth_and_reference_are_none() {
    let fx = Fixture::new();
    assert!(load_ground_truth(fx.root()).unwrap().is_none());
    assert!(load_reference(fx.root()).unwrap().is_none());
}

#[test]
fn ground_truth_unknown_robot() {
    let fx = Fixture::new();
    fx.write(
        "ground_truth.json",
        r#"{"T_flange_camera": {"robot_1": {"t": [0, 0, 0.1], "q": [0, 0, 0, 1]}}}"#,
    );
    let e = load_ground_truth(fx.root()).unwrap_err();
    assert_message(
        &e,
        &fx.path("ground_truth.json"),
        &["field `T_flange_camera.robot_1`"],
    );
    assert!(matches!(e, E::UnknownRobot { .. }), "{e}");
}

#[test]
fn ground_truth_bad_pose() {
    let fx = Fixture::new();
    fx.write(
        "ground_truth.json",
        r#"{"T_base1_base2": {"t": [0, 0, 0.1], "q": [0, 0, 0, 2]}}"#,
    );
    let e = load_ground_truth(fx.root()).unwrap_err();
    assert_message(
        &e,
        &fx.path("ground_truth.json"),
        &["field `T_base1_base2.q`"],
    );
    assert!(matches!(e, E::NotUnitQuaternion { .. }), "{e}");

    fx.write(
        "ground_truth.json",
        r#"{"T_base1_base2": {"t": [1200, 0, 0.1], "q": [0, 0, 0, 1]}}"#,
    );
    let e = load_ground_truth(fx.root()).unwrap_err();
    assert_message(
        &e,
        &fx.path("ground_truth.json"),
        &["field `T_base1_base2.t[0]`", "millimetres"],
    );
    assert!(matches!(e, E::LooksLikeMillimetres { .. }), "{e}");
}

#[test]
fn ground_truth_bad_base_key() {
    let fx = Fixture::new();
    let pose = r#"{"t": [0, 0, 0.1], "q": [0, 0, 0, 1]}"#;
    for (key, part) in [
        ("T_base1_baseX", "unknown key `T_base1_baseX`"),
        ("T_base1_base03", "unknown key `T_base1_base03`"),
        ("T_base1_base1", "names robot 1"),
        ("T_base1_base0", "names robot 0"),
        ("T_base1_base3", "lists 2 robot(s)"),
    ] {
        for name in ["ground_truth.json", "reference.json"] {
            fx.write(name, &format!(r#"{{"source": "x", "{key}": {pose}}}"#));
            let e = if name == "ground_truth.json" {
                load_ground_truth(fx.root()).unwrap_err()
            } else {
                load_reference(fx.root()).unwrap_err()
            };
            assert_message(&e, &fx.path(name), &[&format!("field `{key}`"), part]);
            assert!(matches!(e, E::UnknownBaseKey { .. }), "{e}");
        }
    }
    // Other keys are still ignored; a further robot's pose is checked like any pose.
    fx.write("ground_truth.json", r#"{"comment": "from a newer writer"}"#);
    load_ground_truth(fx.root()).unwrap().unwrap();
    fx.edit(
        M,
        "{ \"id\": \"robot2\" }",
        "{ \"id\": \"robot2\" }, { \"id\": \"robot3\" }",
    );
    fx.write("robot3/captures.csv", CAPTURES1_POSES_ONLY);
    fx.write(
        "ground_truth.json",
        r#"{"T_base1_base3": {"t": [0, 0, 0.1], "q": [0, 0, 0, 2]}}"#,
    );
    let e = load_ground_truth(fx.root()).unwrap_err();
    assert_message(
        &e,
        &fx.path("ground_truth.json"),
        &["field `T_base1_base3.q`"],
    );
    assert!(matches!(e, E::NotUnitQuaternion { .. }), "{e}");
    fx.write(
        "ground_truth.json",
        r#"{"T_base1_base3": {"t": [0.5, 1, 0], "q": [0, 0, 0, 1]}}"#,
    );
    let gt = load_ground_truth(fx.root()).unwrap().unwrap();
    assert_eq!(
        gt.base1_from_base(3).unwrap().translation.vector,
        nalgebra::Vector3::new(0.5, 1.0, 0.0)
    );
    assert_eq!(gt.base1_from_base(2), None);
}

const CAPTURES1_POSES_ONLY: &str = "image,depth,tx,ty,tz,qx,qy,qz,qw,ctx,cty,ctz,cqx,cqy,cqz,cqw
,,0.4,0.2,0.5,0,0,0,1,0.01,0.02,0.7,0,0,0,1
";

#[test]
fn pair_touch_files_are_checked_like_touch_points() {
    let fx = Fixture::new();
    fx.edit(
        M,
        "{ \"id\": \"robot2\" }",
        "{ \"id\": \"robot2\" }, { \"id\": \"robot_3\" }",
    );
    fx.write("robot_3/captures.csv", CAPTURES1_POSES_ONLY);
    let pair = "touch_points_robot2_robot_3.csv";
    fx.write(pair, "x1,y1,z1,x2,y2,z2\n0.5,0.0,0.1,0.3,-0.2,0.1\n");
    // A file of robots not in the manifest is not part of the dataset.
    fx.write("touch_points_robot2_robot9.csv", "not, even, CSV");
    let ds = fx.load().unwrap();
    assert_eq!(ds.pair_touch_points.len(), 1);
    assert_eq!(
        ds.touches_between("robot2", "robot_3").map(<[_]>::len),
        Some(1)
    );
    assert_eq!(
        ds.touches_between("robot1", "robot2").map(<[_]>::len),
        Some(2)
    );
    assert_eq!(ds.touches_between("robot_3", "robot2"), None);

    fx.write(pair, "x1,y1,z1,x2,y2,z2\n0.5,0.0,0.1,300,-0.2,0.1\n");
    let e = fx.load_err(pair, &["row 1 (line 2)", "field `x2`", "millimetres"]);
    assert!(matches!(e, E::LooksLikeMillimetres { .. }), "{e}");

    // `robot2` + `x_robot_3` and `robot2_x` + `robot_3` share one file name.
    let fx = Fixture::new();
    fx.edit(
        M,
        "{ \"id\": \"robot2\" }",
        "{ \"id\": \"robot2\" }, { \"id\": \"x_robot_3\" }, { \"id\": \"robot2_x\" }, { \"id\": \"robot_3\" }",
    );
    for id in ["x_robot_3", "robot2_x", "robot_3"] {
        fx.write(&format!("{id}/captures.csv"), CAPTURES1_POSES_ONLY);
    }
    let name = "touch_points_robot2_x_robot_3.csv";
    fx.write(name, "x1,y1,z1,x2,y2,z2\n");
    let e = fx.load_err(
        name,
        &["`robot2` with `x_robot_3`", "`robot2_x` with `robot_3`"],
    );
    assert!(matches!(e, E::AmbiguousTouchFile { .. }), "{e}");
}

#[test]
fn reference_needs_source() {
    let fx = Fixture::new();
    fx.write(
        "reference.json",
        r#"{"T_base1_base2": {"t": [0, 0, 0.1], "q": [0, 0, 0, 1]}}"#,
    );
    let e = load_reference(fx.root()).unwrap_err();
    assert_message(&e, &fx.path("reference.json"), &["field `source`"]);
    assert!(matches!(e, E::InvalidManifest { .. }), "{e}");
}

// --- other CSV-level problems ------------------------------------------------------------

#[test]
fn invalid_utf8_in_captures() {
    let fx = Fixture::new();
    let mut bytes = fs::read(fx.path(C1)).unwrap();
    bytes.extend_from_slice(b"images/\xff.png,,0,0,0,0,0,0,1\n");
    fs::write(fx.path(C1), bytes).unwrap();
    let e = fx.load_err(C1, &["line 4", "UTF-8"]);
    assert!(matches!(e, E::Csv { .. }), "{e}");
}

#[test]
fn empty_captures_file() {
    let fx = Fixture::new();
    fx.write(C1, "");
    let e = fx.load_err(C1, &["line 1", "no header"]);
    assert!(matches!(e, E::BadHeader { .. }), "{e}");
}

// --- files stay inside the dataset folder ------------------------------------------------

/// A file outside the dataset, which a symlink inside it points at.
fn outside_file(name: &str) -> (tempfile::TempDir, std::path::PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join(name);
    fs::write(&file, "root:x:0:0:root:/root:/bin/bash\n").unwrap();
    (dir, file)
}

fn symlink(to: &std::path::Path, at: &std::path::Path) {
    let _ = fs::remove_file(at);
    fs::create_dir_all(at.parent().unwrap()).unwrap();
    std::os::unix::fs::symlink(to, at).unwrap();
}

#[test]
fn image_paths_that_climb_out_are_refused() {
    let fx = Fixture::new();
    row2(&fx, "../../outside/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0");
    let e = fx.load_err(C1, &["row 2 (line 3)", "field `image`", "`..`"]);
    assert!(matches!(e, E::BadPath { .. }), "{e}");
    // `..` that stays inside the dataset (a folder of images beside the robots')
    // is read.
    fx.write("shared/001.png", "not really an image");
    row2_back(&fx, "../shared/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0");
    fx.load().expect("`..` inside the dataset");
    row2_back(
        &fx,
        "images/../../../x/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0",
    );
    let e = fx.load_err(C1, &["row 2 (line 3)", "`..`"]);
    assert!(matches!(e, E::BadPath { .. }), "{e}");
}

fn row2_back(fx: &Fixture, replacement: &str) {
    let text = fs::read_to_string(fx.path(C1)).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    let mut out: Vec<&str> = lines[..2].to_vec();
    out.push(replacement);
    out.extend(&lines[3..]);
    fx.write(C1, &(out.join("\n") + "\n"));
}

#[test]
fn images_symlinked_out_of_the_dataset_are_refused_and_inside_ones_read() {
    let fx = Fixture::new();
    // A symlink to another file of the dataset is fine.
    symlink(
        &fx.path("robot2/images/a.jpg"),
        &fx.path("robot1/images/001.png"),
    );
    fx.load().expect("a symlink inside the dataset");
    let (_keep, secret) = outside_file("passwd.png");
    symlink(&secret, &fx.path("robot1/images/001.png"));
    let e = fx.load_err(
        C1,
        &[
            "row 2 (line 3)",
            "field `image`",
            "outside the dataset folder",
        ],
    );
    assert!(matches!(e, E::OutsideDataset { .. }), "{e}");
    assert!(!e.to_string().contains("root:x"), "{e}");
    // The same for a depth image.
    let fx = Fixture::new();
    symlink(&secret, &fx.path("robot1/depth/000.png"));
    let e = fx.load_err(C1, &["row 1 (line 2)", "field `depth`", "outside"]);
    assert!(matches!(e, E::OutsideDataset { .. }), "{e}");
}

#[test]
fn robot_folders_captures_and_touch_files_symlinked_out_are_refused() {
    let outside = tempfile::tempdir().unwrap();
    // A robot folder elsewhere, valid in itself.
    let fx = Fixture::new();
    fs::rename(fx.path("robot2"), outside.path().join("robot2")).unwrap();
    symlink(&outside.path().join("robot2"), &fx.path("robot2"));
    let e = fx.load_err(M, &["field `robots[1].id`", "outside the dataset folder"]);
    assert!(matches!(e, E::OutsideDataset { .. }), "{e}");

    let fx = Fixture::new();
    let elsewhere = outside.path().join("captures.csv");
    fs::copy(fx.path(C1), &elsewhere).unwrap();
    symlink(&elsewhere, &fx.path(C1));
    let e = fx.load_err(C1, &["outside the dataset folder"]);
    assert!(matches!(e, E::OutsideDataset { .. }), "{e}");

    let fx = Fixture::new();
    let elsewhere = outside.path().join("touch_points.csv");
    fs::copy(fx.path(T), &elsewhere).unwrap();
    symlink(&elsewhere, &fx.path(T));
    let e = fx.load_err(T, &["outside the dataset folder"]);
    assert!(matches!(e, E::OutsideDataset { .. }), "{e}");
}

#[test]
fn a_multimarker_file_outside_the_dataset_is_refused() {
    let fx = with_target(
        r#"{ "kind": "multimarker", "config": "../passwd.dat", "dictionary": "ARTOOLKIT" }"#,
    );
    let e = fx.load_err(M, &["field `target.config`", "`..`"]);
    assert!(matches!(e, E::InvalidTarget { .. }), "{e}");

    let fx = with_target(
        r#"{ "kind": "multimarker", "config": "target/multi.dat", "dictionary": "ARTOOLKIT" }"#,
    );
    let (_keep, secret) = outside_file("passwd.dat");
    symlink(&secret, &fx.path("target/multi.dat"));
    let e = fx.load_err(M, &["field `target.config`", "outside the dataset folder"]);
    assert!(matches!(e, E::OutsideDataset { .. }), "{e}");
}

#[test]
fn errors_quote_at_most_a_short_excerpt_of_a_file() {
    let fx = Fixture::new();
    let long = "root:x:0:0:root:/root:/bin/bash:and-a-lot-more-of-the-file";
    fx.edit(C1, "image,depth", &format!("{long},depth"));
    let e = fx.load_err(C1, &["unknown column", "root:x:0:0:root"]);
    assert!(!e.to_string().contains("/bin/bash"), "{e}");
    let fx = Fixture::new();
    row2(
        &fx,
        &format!("images/001.png,,{long},-0.1,0.6,0.0,0.0,0.0,1.0"),
    );
    let e = fx.load_err(C1, &["row 2", "root:x:0:0:root"]);
    assert!(!e.to_string().contains("and-a-lot-more"), "{e}");
}
