//! Scaffolding shared by the multi-process tests: loopback zenoh configurations on
//! a free port, and child processes killed when a test ends.

#![allow(dead_code)]

use std::net::TcpListener;
use std::path::PathBuf;

/// A coordinator state folder beside a result file, so that a test's history
/// database lives in its own temporary folder, never in the checkout.
pub fn state_beside(result: &std::path::Path) -> PathBuf {
    result
        .parent()
        .unwrap_or_else(|| std::path::Path::new("."))
        .join("coordinator-state")
}

pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A temporary folder with a coordinator configuration listening on a free
/// loopback port and an agent configuration connecting to it (multicast off).
pub struct Net {
    pub dir: tempfile::TempDir,
    pub coordinator_cfg: PathBuf,
    pub agent_cfg: PathBuf,
}

pub fn net() -> Net {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let coordinator_cfg = dir.path().join("coordinator.json5");
    let agent_cfg = dir.path().join("agent.json5");
    std::fs::write(
        &coordinator_cfg,
        format!(
            r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#
        ),
    )
    .unwrap();
    std::fs::write(
        &agent_cfg,
        format!(
            r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:0"] }}, connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#
        ),
    )
    .unwrap();
    Net {
        dir,
        coordinator_cfg,
        agent_cfg,
    }
}

/// Copies a folder with everything in it (a dataset reads only files inside
/// its own folder, so a variant of one is a copy, not symlinks).
pub fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &dest);
        } else {
            std::fs::copy(e.path(), &dest).unwrap();
        }
    }
}

/// A child process killed (and reaped) when dropped.
pub struct Killed(pub std::process::Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Runs `coordinator verify` on a result against touch pairs (plus `extra`
/// arguments); asserts it succeeded and returns its printout and its JSON report.
pub fn verify(
    result: &std::path::Path,
    touch_points: &std::path::Path,
    extra: &[&str],
) -> (String, serde_json::Value) {
    let json = result.with_file_name("VERIFY.json");
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["verify", "--result"])
        .arg(result)
        .arg("--touch-points")
        .arg(touch_points)
        .arg("--json")
        .arg(&json)
        .args(extra)
        .output()
        .unwrap();
    // Exit 4 is a finished verify whose verdict is FAIL (its own tests are in
    // cli.rs); the callers here check the figures.
    assert!(
        out.status.success() || out.status.code() == Some(4),
        "coordinator verify failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    (String::from_utf8_lossy(&out.stdout).into_owned(), report)
}

/// Waits for the coordinator to write `result_file` (within `limit`), lets the
/// process end, and reads the result.
pub fn wait_for_result(
    result_file: &std::path::Path,
    coordinator: &mut Killed,
    limit: std::time::Duration,
) -> b2b_protocol::CalibrationResult {
    let deadline = std::time::Instant::now() + limit;
    while !result_file.exists() {
        assert!(std::time::Instant::now() < deadline, "no RESULT.json");
        std::thread::sleep(std::time::Duration::from_millis(200));
    }
    let _ = coordinator.0.wait();
    serde_json::from_str(&std::fs::read_to_string(result_file).unwrap()).unwrap()
}

/// A result's distance from the dataset's ground truth: translation (m) and
/// rotation angle (rad).
pub fn truth_error(
    dataset: &std::path::Path,
    result: &b2b_protocol::CalibrationResult,
) -> (f64, f64) {
    let truth = b2b_dataset::load_ground_truth(dataset)
        .unwrap()
        .unwrap()
        .base1_from_base2
        .unwrap();
    let est = result.base1_from_base2.to_isometry("result").unwrap();
    let d = truth.inverse() * est;
    (d.translation.vector.norm(), d.rotation.angle())
}

/// `coordinator calibrate --method METHOD` on a dataset: the offline result the
/// live runs must equal.
pub fn offline_result_of(
    dir: &std::path::Path,
    dataset: &std::path::Path,
    method: &str,
) -> b2b_protocol::CalibrationResult {
    let out = dir.join("OFFLINE.json");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["calibrate", "--method", method, "--dataset"])
        .arg(dataset)
        .arg("--out")
        .arg(&out)
        .arg("--state-dir")
        .arg(state_beside(&out))
        .stdout(std::process::Stdio::null())
        .status()
        .unwrap();
    // Exit 4: written, with a FAIL verdict (the verdict's own tests are in cli.rs).
    assert!(status.success() || status.code() == Some(4), "{status}");
    serde_json::from_str(&std::fs::read_to_string(out).unwrap()).unwrap()
}

/// The same pose to 1e-9 and the same captures used.
pub fn assert_same(
    live: &b2b_protocol::CalibrationResult,
    offline: &b2b_protocol::CalibrationResult,
) {
    for i in 0..3 {
        assert!(
            (live.base1_from_base2.t[i] - offline.base1_from_base2.t[i]).abs() < 1e-9,
            "{live:?} vs {offline:?}"
        );
    }
    for i in 0..4 {
        assert!((live.base1_from_base2.q[i] - offline.base1_from_base2.q[i]).abs() < 1e-9);
    }
    assert_eq!(live.captures.used, offline.captures.used);
}

/// The cell setup the simulated cart's binary derives for `robot` of `scene`
/// (`b2b-sim-cart setup`, beside the agent binary), written into `dir`.
#[allow(dead_code)]
pub fn sim_setup(
    scene: &std::path::Path,
    robot: &str,
    dir: &std::path::Path,
) -> b2b_services::setup::CellSetup {
    let cart = std::path::Path::new(env!("CARGO_BIN_EXE_agent"))
        .with_file_name(format!("b2b-sim-cart{}", std::env::consts::EXE_SUFFIX));
    let file = b2b_services::sim_cart::derive_setup(&cart, scene, robot, dir)
        .unwrap_or_else(|e| panic!("{e:#}"));
    b2b_services::setup::CellSetup::load(&file).unwrap()
}

/// The truth's Mahalanobis² under the covariance the result gives the pair
/// `a`, `b` (robot ids), with `a_from_b` the true transform.
pub fn truth_m2(
    result: &b2b_protocol::CalibrationResult,
    a: &str,
    b: &str,
    a_from_b: &nalgebra::Isometry3<f64>,
) -> f64 {
    let (est, cov) = b2b_pipeline::pair_transform(result, a, b).unwrap();
    b2b_calib::refine::mahalanobis2(&b2b_calib::pose::left_difference(&est, a_from_b), &cov)
        .unwrap()
}

/// The 99.9% point of chi-square with 6 dof: an honest covariance puts the
/// truth beyond it one run in a thousand, one too small by 1.5x in sigma one
/// run in eight.
pub const CHI2_6_999: f64 = 22.46;
