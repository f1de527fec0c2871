//! `coordinator history` and the history behind it, as operators meet them: two
//! calibrations listed, a moved camera mount flagged in the printout, RESULT.json
//! and the report, a corrupt, locked or newer database that costs the history but
//! never the result, and readers beside a writer.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use b2b_protocol::CalibrationResult;
use b2b_services::history::{self, DB_FILE, MOUNT_WARNING};
use common::copy_dir;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

fn coordinator() -> Command {
    Command::new(env!("CARGO_BIN_EXE_coordinator"))
}

fn committed_dataset() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12")
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// `coordinator calibrate` of `dataset` into `out`, recording in `state`.
fn calibrate(dataset: &Path, state: &Path, out: &Path) -> Output {
    let output = coordinator()
        .args(["calibrate", "--dataset"])
        .arg(dataset)
        .arg("--state-dir")
        .arg(state)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(
        !text(&output.stderr).contains("panicked"),
        "{}",
        text(&output.stderr)
    );
    output
}

fn succeeded(output: &Output) -> (String, String) {
    let (stdout, stderr) = (text(&output.stdout), text(&output.stderr));
    assert!(
        output.status.success(),
        "stdout: {stdout}\nstderr: {stderr}"
    );
    (stdout, stderr)
}

/// `coordinator history --state-dir STATE ARGS...`.
fn history_cmd(state: &Path, args: &[&str]) -> Output {
    coordinator()
        .arg("history")
        .arg("--state-dir")
        .arg(state)
        .args(args)
        .output()
        .unwrap()
}

fn history_json(state: &Path, args: &[&str]) -> serde_json::Value {
    let mut all = vec!["--json"];
    all.extend_from_slice(args);
    let (stdout, _) = succeeded(&history_cmd(state, &all));
    serde_json::from_str(&stdout).unwrap_or_else(|e| panic!("{e}: {stdout}"))
}

fn read_result(path: &Path) -> CalibrationResult {
    let r: CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    r.validate().unwrap();
    r
}

/// The number just before `unit` (e.g. " deg") in `text`.
fn number_before(text: &str, unit: &str) -> f64 {
    let head = &text[..text
        .find(unit)
        .unwrap_or_else(|| panic!("{unit} in {text}"))];
    let start = head
        .rfind(|c: char| !(c.is_ascii_digit() || c == '.'))
        .map_or(0, |i| i + 1);
    head[start..].parse().unwrap()
}

/// Rewrites a robot's `T_base_flange` rows as `T_base_flange * inverse(D)`: to
/// the estimator (the images unchanged) exactly a camera mount moved by `D`,
/// whose hand-eye is `D * T_flange_camera`.
fn move_mount(dataset: &Path, robot: &str, flange_from_moved_flange: &Isometry3<f64>) {
    let csv = dataset.join(robot).join("captures.csv");
    let original = std::fs::read_to_string(&csv).unwrap();
    let mut lines = original.lines();
    let header = lines.next().unwrap();
    let columns: Vec<&str> = header.split(',').collect();
    let at = |name: &str| columns.iter().position(|c| *c == name).unwrap();
    let (tx, qx) = (at("tx"), at("qx"));
    let mut out = vec![header.to_owned()];
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let mut fields: Vec<String> = line.split(',').map(str::to_owned).collect();
        let v = |i: usize| -> f64 { fields[i].parse().unwrap() };
        let base_from_flange = Isometry3::from_parts(
            Translation3::new(v(tx), v(tx + 1), v(tx + 2)),
            UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                v(qx + 3),
                v(qx),
                v(qx + 1),
                v(qx + 2),
            )),
        );
        let moved = base_from_flange * flange_from_moved_flange.inverse();
        let t = moved.translation.vector;
        let q = moved.rotation.coords;
        for (i, value) in [t.x, t.y, t.z].iter().enumerate() {
            fields[tx + i] = format!("{value:?}");
        }
        for (i, value) in [q.x, q.y, q.z, q.w].iter().enumerate() {
            fields[qx + i] = format!("{value:?}");
        }
        out.push(fields.join(","));
    }
    std::fs::write(&csv, out.join("\n") + "\n").unwrap();
}

#[test]
fn two_calibrations_of_one_dataset_are_listed_with_two_hand_eyes_per_robot() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    // Nothing recorded yet: said, and not an error.
    let out = history_cmd(&state, &[]);
    let (stdout, _) = succeeded(&out);
    assert!(stdout.contains("no results or hand-eyes"), "{stdout}");
    assert_eq!(history_json(&state, &[])["results"], serde_json::json!([]));

    let ds = committed_dataset();
    let outs = [
        tmp.path().join("a/RESULT.json"),
        tmp.path().join("b/RESULT.json"),
    ];
    for out in &outs {
        let (stdout, stderr) = succeeded(&calibrate(&ds, &state, out));
        // The same data twice: the same mount.
        assert!(!stdout.contains(MOUNT_WARNING), "{stdout}");
        assert!(!stderr.contains("history"), "{stderr}");
        assert!(read_result(out).warnings.is_empty());
    }
    assert!(state.join(DB_FILE).exists());

    let (stdout, _) = succeeded(&history_cmd(&state, &[]));
    assert!(stdout.contains(": 2 results"), "{stdout}");
    assert!(stdout.contains("hand-eyes of robot1: 2"), "{stdout}");
    assert!(stdout.contains("hand-eyes of robot2: 2"), "{stdout}");
    for out in &outs {
        let absolute = std::path::absolute(out).unwrap();
        assert!(stdout.contains(&absolute.display().to_string()), "{stdout}");
    }
    assert!(
        stdout.contains("calibrate board  robots robot1, robot2"),
        "{stdout}"
    );

    let all = history_json(&state, &[]);
    assert_eq!(all["schema_version"], history::SCHEMA_VERSION);
    assert_eq!(all["hand_eyes"].as_object().unwrap().len(), 2);
    let listing = history_json(&state, &["--robot", "robot2"]);
    let results = listing["results"].as_array().unwrap();
    assert_eq!(results.len(), 2);
    assert_eq!(
        results[0]["robots"],
        serde_json::json!(["robot1", "robot2"])
    );
    assert_eq!(results[0]["method"], "board");
    let first = read_result(&outs[0]);
    assert_eq!(
        results[0]["T_base1_base2"]["t"],
        serde_json::json!(first.base1_from_base2.t)
    );
    assert_eq!(
        results[0]["predicted_touch_error_m"]["p95"],
        serde_json::json!(first.predicted_touch_error_m.p95)
    );
    let hand_eyes = listing["hand_eyes"].as_object().unwrap();
    assert_eq!(hand_eyes.keys().collect::<Vec<_>>(), ["robot2"]);
    let robot2 = hand_eyes["robot2"].as_array().unwrap();
    assert_eq!(robot2.len(), 2);
    assert!(robot2.iter().all(|h| h["has_covariance"] == true));
    assert!(robot2[0]["recorded_at_unix_ms"].as_i64() <= robot2[1]["recorded_at_unix_ms"].as_i64());
    // A robot the history has never seen: nothing, said.
    let (stdout, _) = succeeded(&history_cmd(&state, &["--robot", "robot7"]));
    assert!(
        stdout.contains("no results or hand-eyes of robot7"),
        "{stdout}"
    );
    // Not a robot id at all: refused, not a panic.
    let out = history_cmd(&state, &["--robot", "robot 1;"]);
    assert!(!out.status.success());
    assert!(
        text(&out.stderr).contains("is not a robot id"),
        "{}",
        text(&out.stderr)
    );
}

/// The same two carts calibrated on another day, from other captures (the
/// three-robot set: the same arms and mounts, other viewpoints, 320x240
/// images): their hand-eyes differ by about 0.1 mm, which both covariances
/// explain, so nothing is flagged; the third cart, new to the history, is
/// recorded without a check.
#[test]
fn the_same_mounts_from_other_captures_are_not_flagged() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    let first = tmp.path().join("a/RESULT.json");
    succeeded(&calibrate(&committed_dataset(), &state, &first));
    let second = tmp.path().join("b/RESULT.json");
    let other = committed_dataset().with_file_name("sim-checkerboard-3x12");
    let (stdout, stderr) = succeeded(&calibrate(&other, &state, &second));
    let r = read_result(&second);
    assert!(r.warnings.is_empty(), "{:?}", r.warnings);
    assert!(!stdout.contains("mount moved"), "{stdout}\n{stderr}");
    let listing = history_json(&state, &["--robot", "robot3"]);
    assert!(listing.to_string().contains("robot3"), "{listing}");
}

#[test]
fn a_moved_camera_mount_is_flagged_in_the_printout_the_result_and_the_report() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    let moved_ds = tmp.path().join("moved");
    copy_dir(&committed_dataset(), &moved_ds);
    // The mount moved by 3 mm and turned 1 degree on robot2's flange.
    let d = Isometry3::new(
        Vector3::new(0.003, 0.0, 0.0),
        Vector3::new(0.0, 0.0, 1f64.to_radians()),
    );
    move_mount(&moved_ds, "robot2", &d);

    let before = tmp.path().join("before/RESULT.json");
    let (stdout, _) = succeeded(&calibrate(&committed_dataset(), &state, &before));
    // The first calibration of a fresh state folder has nothing to compare with.
    assert!(!stdout.contains(MOUNT_WARNING), "{stdout}");
    assert!(read_result(&before).warnings.is_empty());

    let after = tmp.path().join("after/RESULT.json");
    let (stdout, _) = succeeded(&calibrate(&moved_ds, &state, &after));
    let printed: Vec<&str> = stdout
        .lines()
        .filter(|l| l.contains(MOUNT_WARNING))
        .collect();
    assert_eq!(printed.len(), 1, "{stdout}");
    assert!(printed[0].starts_with("WARNING: "), "{stdout}");
    let result = read_result(&after);
    assert_eq!(result.warnings.len(), 1, "{:?}", result.warnings);
    let w = &result.warnings[0];
    assert!(printed[0].ends_with(w.as_str()));
    // Robot2 only, with how far, the chi-square against its limit, and when the
    // earlier hand-eye was recorded.
    assert!(
        w.contains("robot2's hand-eye") && !w.contains("robot1"),
        "{w}"
    );
    let earlier = history_json(&state, &["--robot", "robot2"])["hand_eyes"]["robot2"][0]
        ["recorded_at_unix_ms"]
        .as_i64()
        .unwrap();
    assert!(w.contains(&history::format_utc(earlier)), "{w}");
    assert!((number_before(w, " deg") - 1.0).abs() < 0.05, "{w}");
    let x = read_result(&before).hand_eye["robot2"]
        .to_isometry("hand_eye")
        .unwrap();
    let (expected_m, _) = b2b_calib::pose::pose_distance(&(d * x), &x);
    assert!(
        (number_before(w, " mm") - expected_m * 1e3).abs() < 0.1,
        "{w}: expected {:.2} mm",
        expected_m * 1e3
    );
    let chi2 = number_before(w, " > 22.46");
    assert!(chi2 > 22.46, "{w}");

    // The report heads its page with it and plots both hand-eyes of each robot.
    let report = tmp.path().join("report");
    let out = coordinator()
        .args(["report", "--result"])
        .arg(&after)
        .arg("--state-dir")
        .arg(&state)
        .arg("--out")
        .arg(&report)
        .output()
        .unwrap();
    succeeded(&out);
    let html = std::fs::read_to_string(report.join("index.html")).unwrap();
    assert!(html.contains(MOUNT_WARNING) && html.contains("class=\"alert\""));
    assert!(
        html.contains("History: 4 recorded hand-eyes of robot1, robot2"),
        "{html}"
    );
    let mm = std::fs::read_to_string(report.join("hand_eye_history_mm.svg")).unwrap();
    assert!(
        mm.contains("robot2 (2)") && mm.contains("robot1 (2)"),
        "{mm}"
    );

    // The history keeps the warning with its result.
    let listing = history_json(&state, &[]);
    assert_eq!(listing["results"][1]["warnings"][0], w.as_str());
    assert!(listing["results"][0].get("warnings").is_none());
}

#[test]
fn a_corrupt_database_costs_the_history_never_the_result() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    std::fs::create_dir_all(&state).unwrap();
    let db = state.join(DB_FILE);
    let garbage: Vec<u8> = (0..8192u32).map(|i| (i * 7919 % 251) as u8).collect();
    std::fs::write(&db, &garbage).unwrap();

    let out_file = tmp.path().join("out/RESULT.json");
    let (_, stderr) = succeeded(&calibrate(&committed_dataset(), &state, &out_file));
    read_result(&out_file);
    let named = db.display().to_string();
    assert!(
        stderr.contains(&named) && stderr.contains("corrupt"),
        "{stderr}"
    );
    assert!(
        stderr.contains("the result WAS written")
            && stderr.contains(
                &std::path::absolute(&out_file)
                    .unwrap()
                    .display()
                    .to_string()
            ),
        "{stderr}"
    );
    // Left as it was: nobody's data is overwritten.
    assert_eq!(std::fs::read(&db).unwrap(), garbage);

    let out = history_cmd(&state, &[]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success(), "{}", text(&out.stdout));
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        stderr.contains(&named) && stderr.contains("corrupt"),
        "{stderr}"
    );

    // The report is still written, without the history.
    let report = tmp.path().join("report");
    let out = coordinator()
        .args(["report", "--result"])
        .arg(&out_file)
        .arg("--state-dir")
        .arg(&state)
        .arg("--out")
        .arg(&report)
        .output()
        .unwrap();
    let (_, stderr) = succeeded(&out);
    assert!(
        stderr.contains(&named) && stderr.contains("corrupt"),
        "{stderr}"
    );
    assert!(report.join("index.html").exists());
}

/// A state folder whose history holds one result (the report's fixture).
fn history_with_one_result(state: &Path) -> PathBuf {
    let text = include_str!("../../report/tests/fixtures/RESULT.json");
    let result: CalibrationResult = serde_json::from_str(text).unwrap();
    let db = state.join(DB_FILE);
    history::record(
        &db,
        &history::Record {
            recorded_at_unix_ms: 1_700_000_000_000,
            command: "calibrate",
            result: &result,
            result_file: Path::new("/earlier/RESULT.json"),
            robots: &["robot1".to_owned(), "robot2".to_owned()],
        },
    )
    .unwrap();
    db
}

fn count_results(db: &Path) -> i64 {
    let conn = rusqlite::Connection::open(db).unwrap();
    conn.query_row("SELECT count(*) FROM results", [], |r| r.get(0))
        .unwrap()
}

#[test]
fn a_locked_database_costs_the_history_never_the_result() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    let db = history_with_one_result(&state);
    let lock = rusqlite::Connection::open(&db).unwrap();
    lock.execute_batch("BEGIN EXCLUSIVE").unwrap();
    let out_file = tmp.path().join("out/RESULT.json");
    let output = calibrate(&committed_dataset(), &state, &out_file);
    lock.execute_batch("ROLLBACK").unwrap();
    drop(lock);
    let (_, stderr) = succeeded(&output);
    read_result(&out_file);
    assert!(
        stderr.contains(&db.display().to_string())
            && stderr.contains("locked by another process")
            && stderr.contains("the result WAS written"),
        "{stderr}"
    );
    assert_eq!(count_results(&db), 1, "nothing recorded under the lock");
}

#[test]
fn a_newer_schema_is_refused_by_its_version_and_left_alone() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    let db = history_with_one_result(&state);
    let newer = history::SCHEMA_VERSION + 1;
    rusqlite::Connection::open(&db)
        .unwrap()
        .pragma_update(None, "user_version", newer)
        .unwrap();
    let expected = format!("schema version {newer} is newer than this coordinator's");

    let out = history_cmd(&state, &[]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains(&expected) && stderr.contains(&db.display().to_string()),
        "{stderr}"
    );

    let out_file = tmp.path().join("out/RESULT.json");
    let (_, stderr) = succeeded(&calibrate(&committed_dataset(), &state, &out_file));
    read_result(&out_file);
    assert!(stderr.contains(&expected), "{stderr}");
    let conn = rusqlite::Connection::open(&db).unwrap();
    let version: i64 = conn
        .query_row("PRAGMA user_version", [], |r| r.get(0))
        .unwrap();
    assert_eq!(version, newer);
    assert_eq!(count_results(&db), 1);
}

#[test]
fn readers_succeed_while_another_process_writes() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    let db = history_with_one_result(&state);
    let text_result = include_str!("../../report/tests/fixtures/RESULT.json");
    let result: CalibrationResult = serde_json::from_str(text_result).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    // The writer: one result per transaction until the readers are done.
    let writer = {
        let (stop, db) = (Arc::clone(&stop), db.clone());
        std::thread::spawn(move || {
            let mut h = history::History::open(&db).unwrap();
            let robots = ["robot1".to_owned(), "robot2".to_owned()];
            let mut written = 0;
            while !stop.load(Ordering::SeqCst) || written < 50 {
                h.record(&history::Record {
                    recorded_at_unix_ms: 1_700_000_000_000 + written,
                    command: "run",
                    result: &result,
                    result_file: Path::new("/live/RESULT.json"),
                    robots: &robots,
                })
                .unwrap();
                written += 1;
            }
            written
        })
    };
    // Two readers at once, each a process listing the history five times.
    let readers: Vec<_> = (0..2)
        .map(|_| {
            let state = state.clone();
            std::thread::spawn(move || {
                (0..5)
                    .map(|_| {
                        history_json(&state, &["--robot", "robot2"])["results"]
                            .as_array()
                            .unwrap()
                            .len()
                    })
                    .collect::<Vec<usize>>()
            })
        })
        .collect();
    let seen: Vec<Vec<usize>> = readers.into_iter().map(|r| r.join().unwrap()).collect();
    stop.store(true, Ordering::SeqCst);
    let written = writer.join().unwrap();
    for counts in &seen {
        // Each listing a consistent snapshot: never fewer than before, never
        // more than were written.
        assert!(counts.windows(2).all(|w| w[0] <= w[1]), "{seen:?}");
        assert!(counts.iter().all(|n| *n >= 1 && *n <= 1 + written as usize));
    }
    assert_eq!(count_results(&db), 1 + written);
}

#[test]
fn a_listing_cut_short_by_its_reader_is_not_a_panic() {
    let tmp = tempfile::tempdir().unwrap();
    let state = tmp.path().join("state");
    let db = history_with_one_result(&state);
    let result: CalibrationResult =
        serde_json::from_str(include_str!("../../report/tests/fixtures/RESULT.json")).unwrap();
    let mut h = history::History::open(&db).unwrap();
    let robots = ["robot1".to_owned(), "robot2".to_owned()];
    for i in 0..1000 {
        h.record(&history::Record {
            recorded_at_unix_ms: 1_700_000_000_000 + i,
            command: "run",
            result: &result,
            result_file: Path::new("/live/RESULT.json"),
            robots: &robots,
        })
        .unwrap();
    }
    for args in [&[][..], &["--json"][..]] {
        // `history | head -c 100`: far more than a pipe holds, read 100 bytes.
        let mut child = coordinator()
            .arg("history")
            .arg("--state-dir")
            .arg(&state)
            .args(args)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut head = [0u8; 100];
        std::io::Read::read_exact(child.stdout.as_mut().unwrap(), &mut head).unwrap();
        drop(child.stdout.take());
        let out = child.wait_with_output().unwrap();
        let stderr = text(&out.stderr);
        assert!(out.status.success(), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    }
}
