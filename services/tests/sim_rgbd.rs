//! The RGB-D method live in the simulator: two simulated carts rendering the textured
//! boxes scene with a depth camera (colour and depth frames into iceoryx2), two
//! `agent run --sim` processes that detect SIFT features in each still frame, lift
//! them with the depth frame of the same number and publish them over zenoh, and
//! `coordinator run --method rgbd`. Checks against the scene's ground truth and its
//! touch pairs (the goal: touch error <= 5 mm; the seed's RGB-D method: 34.8).

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

fn dataset() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-rgbd-boxes-2x5")
}

#[test]
fn two_simulated_rgbd_carts_give_a_verified_rgbd_result() {
    let net = common::net();
    let dir = net.dir.path();
    let scene = dataset().join("scene.json");
    let result_file = dir.join("RESULT.json");
    let mut coordinator = common::Killed(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["run", "--method", "rgbd", "--robots", "robot1,robot2"])
            // What the simulated arms' DH errors amount to at the flange, as
            // offline (README): a common flange error moves every lifted
            // feature alike, and only this tells the covariance about it.
            .args([
                "--robot-accuracy-mm",
                "0.3",
                "--robot-accuracy-deg",
                "0.015",
            ])
            .arg("--zenoh")
            .arg(&net.coordinator_cfg)
            .arg("--state-dir")
            .arg(dir.join("coordinator-state"))
            .arg("--out")
            .arg(&result_file)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let mut agents = vec![];
    for robot in ["robot1", "robot2"] {
        let child = Command::new(env!("CARGO_BIN_EXE_agent"))
            .args(["run", "--quiet", "--robot", robot, "--sim"])
            .arg(&scene)
            .args(["--count", "8", "--features", "sift"])
            .arg("--zenoh")
            .arg(&net.agent_cfg)
            .arg("--state-dir")
            .arg(dir.join(format!("agent-{robot}")))
            .args(["--wait-result-s", "120"])
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        agents.push((robot, child));
    }
    for (robot, child) in agents {
        let out = child.wait_with_output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{robot} failed: {stderr}");
        assert!(
            !stderr.contains("no features"),
            "{robot}: a capture went without features: {stderr}"
        );
    }
    let result = common::wait_for_result(&result_file, &mut coordinator, Duration::from_secs(120));
    assert_eq!(result.method, "rgbd");
    for robot in ["robot1", "robot2"] {
        let used = result.captures.used.get(robot).copied().unwrap_or(0);
        assert!(used >= 5, "{robot}: only {used} captures in accepted pairs");
    }
    let (dt, da) = common::truth_error(&dataset(), &result);
    eprintln!(
        "live rgbd result: {:.3} mm / {:.4} deg from the truth",
        dt * 1e3,
        da.to_degrees()
    );
    // README: 0.63-0.86 mm, 0.008-0.046° in three runs; asserted within 1.5x
    // of the largest.
    assert!(dt < 1.3e-3 && da.to_degrees() < 0.07, "{dt} m, {da} rad");

    // Each view's fit, as the board methods carry it: every view the agents
    // published, those in accepted pairs with their reprojection RMS.
    let per = &result.captures.per_capture;
    assert_eq!(per.len(), 16, "{per:?}");
    for c in per {
        if let Some(rms) = c.rms_px {
            assert!(rms > 0.05 && rms < 3.0, "{} #{}: {rms} px", c.robot, c.row);
        }
    }
    let with_fit = per.iter().filter(|c| c.rms_px.is_some()).count();
    assert!(with_fit >= 10, "only {with_fit} views with a fit: {per:?}");

    // The scene's touches carry 0.2 mm of tip noise per pointer.
    let (printout, v) = common::verify(
        &result_file,
        &dataset().join("touch_points.csv"),
        &["--tip-sigma-mm", "0.2"],
    );
    eprintln!("{printout}");
    let mean_mm = v["touch_mean_mm"].as_f64().unwrap();
    // The goal is 5 mm; README: 0.73-0.80 mm in three runs, asserted
    // within 1.5x.
    assert!(mean_mm <= 1.2, "touch mean {mean_mm} mm");
    // The covariance is honest live too: the truth inside its 99.9% ellipsoid
    // (below 22.46 for 6 dof). README: Mahalanobis² 9.8-10.7 in four runs (the
    // error is mostly the arms' DH errors at the same views, so it changes little
    // between runs), asserted within 1.5x of the largest; before the live
    // hand-eyes carried the arms' systematic error, as offline, 25-34. The 25
    // touches inside the predicted 95% bound: 88-92% in those runs, asserted
    // within 1.5x (they share one calibration's error, so the fraction swings
    // with where that error falls).
    let truth = b2b_dataset::load_ground_truth(&dataset())
        .unwrap()
        .unwrap()
        .base1_from_base2
        .unwrap();
    let m2 = common::truth_m2(&result, "robot1", "robot2", &truth);
    let inside = v["within_predicted_p95"].as_f64().unwrap();
    eprintln!(
        "live rgbd: the truth at Mahalanobis² {m2:.2}; {:.0}% of touches inside the predicted 95% bound (p95 {:.2} mm)",
        inside * 100.0,
        result.predicted_touch_error_m.p95 * 1e3
    );
    assert!(m2 < common::CHI2_6_999, "the truth at Mahalanobis² {m2}");
    assert!(m2 < 1.5 * 10.7, "the truth at Mahalanobis² {m2}");
    assert!(inside >= 0.88 / 1.5, "only {:.0}% inside", inside * 100.0);
}
