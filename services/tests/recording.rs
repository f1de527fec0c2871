//! Rerun recordings written by real runs: an agent replaying the simulator's dataset
//! (no coordinator: it publishes everything, then gives up waiting for a result), an
//! offline calibration and a verification, each with `--rerun-save`. The recordings
//! are read back and must hold the entities the dashboards show.

mod common;
use common::state_beside;

use std::path::{Path, PathBuf};
use std::process::Command;

fn dataset() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12")
}

fn entities(rrd: &Path) -> Vec<String> {
    let summary = b2b_viz::summarize_rrd(rrd).unwrap_or_else(|e| panic!("{}: {e}", rrd.display()));
    summary.keys().cloned().collect()
}

fn has(entities: &[String], wanted: &str) -> bool {
    entities
        .iter()
        .any(|e| e.trim_start_matches('/') == wanted.trim_start_matches('/'))
}

#[test]
fn replay_calibration_and_verify_recordings_hold_the_dashboard_entities() {
    let dir = tempfile::tempdir().unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let cfg = dir.path().join("agent.json5");
    std::fs::write(
        &cfg,
        format!(
            r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#
        ),
    )
    .unwrap();
    let agent_rrd = dir.path().join("agent.rrd");
    let out = Command::new(env!("CARGO_BIN_EXE_agent"))
        .args(["run", "--quiet", "--robot", "robot1", "--replay"])
        .arg(dataset())
        .arg("--zenoh")
        .arg(&cfg)
        .arg("--state-dir")
        .arg(dir.path().join("agent-state"))
        .args(["--wait-result-s", "0", "--rerun-save"])
        .arg(&agent_rrd)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("no result from the coordinator"),
        "the agent should publish everything and then miss the coordinator: {stderr}"
    );
    let e = entities(&agent_rrd);
    for wanted in [
        paths_flange(),
        b2b_viz::paths::camera(b2b_viz::Base::One),
        b2b_viz::paths::detected(b2b_viz::Base::One),
        b2b_viz::paths::reprojected(b2b_viz::Base::One),
        b2b_viz::paths::rms(b2b_viz::Base::One),
    ] {
        assert!(
            has(&e, &wanted),
            "{wanted} missing from the agent's recording: {e:?}"
        );
    }

    let result = dir.path().join("RESULT.json");
    let calib_rrd = dir.path().join("calibrate.rrd");
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["calibrate", "--dataset"])
        .arg(dataset())
        .arg("--out")
        .arg(&result)
        .arg("--state-dir")
        .arg(state_beside(&result))
        .arg("--rerun-save")
        .arg(&calib_rrd)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let e = entities(&calib_rrd);
    for wanted in [
        b2b_viz::paths::base(b2b_viz::Base::One),
        b2b_viz::paths::base(b2b_viz::Base::Two),
        b2b_viz::paths::VERDICT.to_owned(),
    ] {
        assert!(
            has(&e, &wanted),
            "{wanted} missing from the calibration's recording: {e:?}"
        );
    }
    // Every capture of both robots, as the agents record theirs: its image, the
    // detected and reprojected corners, the RMS (issue 16: an offline recording
    // had nothing to see).
    let summary = b2b_viz::summarize_rrd(&calib_rrd).unwrap();
    let rows = |path: &str| {
        summary
            .iter()
            .find(|(k, _)| k.trim_start_matches('/') == path.trim_start_matches('/'))
            .map_or(0, |(_, v)| v.rows)
    };
    for base in [b2b_viz::Base::One, b2b_viz::Base::Two] {
        for path in [
            b2b_viz::paths::image(base),
            b2b_viz::paths::detected(base),
            b2b_viz::paths::reprojected(base),
            b2b_viz::paths::rms(base),
            b2b_viz::paths::flange(base),
        ] {
            assert_eq!(rows(&path), 12, "{path}: one row per capture");
        }
    }

    let verify_rrd = dir.path().join("verify.rrd");
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["verify", "--result"])
        .arg(&result)
        .arg("--touch-points")
        .arg(dataset().join("touch_points.csv"))
        .args(["--tip-sigma-mm", "0.3", "--rerun-save"])
        .arg(&verify_rrd)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let e = entities(&verify_rrd);
    assert!(
        has(&e, b2b_viz::paths::TOUCHES),
        "touches missing from verify's recording: {e:?}"
    );
    assert!(
        has(&e, b2b_viz::paths::VERDICT),
        "the verdict missing from verify's recording: {e:?}"
    );
}

fn paths_flange() -> String {
    b2b_viz::paths::flange(b2b_viz::Base::One)
}
