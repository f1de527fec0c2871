//! The drift watch end to end: two simulated carts (each its own process,
//! started by its agent), `agent watch` on both, and `coordinator watch`, zenoh
//! peers on loopback. The carts stand still for a while (no alarm), then one is
//! bumped by 1 mm through the cart's command folder; the coordinator must raise
//! the alarm on `b2b/coordinator/alarm` and stderr after the bump (the delay is
//! printed; the number of observations it takes is the in-process tests') and
//! exit with status 3 (`--until-alarm`). The same through the scene's depth
//! features (`agent watch --observe features` on the textured RGB-D scene),
//! where each cart is watched against the scene rather than the target.
//! These are smoke tests of the wiring: what the watch decides (a 0.1° turn
//! alarms, still carts do not, how many observations it takes) is tested in
//! process on a virtual clock (`calib/src/drift.rs`, `watch/`).

mod common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use b2b_protocol::messages::{DriftAlarm, Envelope, alarm_key};
use b2b_services::bus::{Bus, Role, ZenohBus};
use common::{Killed, net};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The committed two-robot set: the simulated carts of its scene, with the
/// same seed, are the arms that recorded it.
fn dataset() -> PathBuf {
    root().join("datasets/sim-checkerboard-2x12")
}

/// The committed RGB-D set: boxes on a table beside the board, and depth.
fn rgbd_dataset() -> PathBuf {
    root().join("datasets/sim-rgbd-boxes-2x5")
}

fn sim_cart() -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_agent"))
        .with_file_name(format!("b2b-sim-cart{}", std::env::consts::EXE_SUFFIX))
}

/// Lines of a child's stderr, each with the time it was read.
fn lines_of(child: &mut std::process::Child) -> mpsc::Receiver<(Instant, String)> {
    let (tx, rx) = mpsc::channel();
    let err = child.stderr.take().expect("stderr piped");
    std::thread::spawn(move || {
        for line in BufReader::new(err).lines() {
            let Ok(line) = line else { break };
            if tx.send((Instant::now(), line)).is_err() {
                break;
            }
        }
    });
    rx
}

/// Waits for a line containing `needle`; every line read goes to `seen`.
fn wait_for(
    rx: &mpsc::Receiver<(Instant, String)>,
    needle: &str,
    limit: Duration,
    seen: &mut Vec<String>,
) -> Option<Instant> {
    let deadline = Instant::now() + limit;
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        match rx.recv_timeout(left) {
            Ok((at, line)) => {
                let hit = line.contains(needle);
                seen.push(line);
                if hit {
                    return Some(at);
                }
            }
            Err(mpsc::RecvTimeoutError::Timeout) => return None,
            Err(mpsc::RecvTimeoutError::Disconnected) => return None,
        }
    }
    None
}

/// A cart shifted by 1 mm.
#[test]
fn a_cart_shifted_by_1_mm_alarms_and_still_carts_do_not() {
    let a = bumped(&dataset(), "target", &["--t-mm", "1,0,0"]);
    // The base moved 1 mm: the target, seen through robot 2, by about as much.
    assert!((0.5e-3..1.5e-3).contains(&a.shift_m), "{a:?}");
}

/// Where no target is left in view: each agent publishes the scene's features
/// lifted with its depth frame (`--observe features`, the board's detection
/// switched off), and each cart is watched against the scene itself.
#[test]
fn a_cart_shifted_by_1_mm_alarms_through_the_scene_features() {
    let a = bumped(&rgbd_dataset(), "features", &["--t-mm", "1,0,0"]);
    // The scene's centre, seen from robot 2's moved base, moves by about as much.
    assert!((0.5e-3..1.5e-3).contains(&a.shift_m), "{a:?}");
}

/// One cell at a time: four carts rendering at once on a 2-core machine
/// would time the machine, not the watch.
static ONE_CELL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// `set`'s scene rendered faster, written into `dir`: one sample per pixel
/// over its textures, and its cameras' resolution divided by `divide`.
fn fast_scene(set: &Path, dir: &Path, divide: u32) -> PathBuf {
    let mut json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(set.join("scene.json")).unwrap()).unwrap();
    json["texture_samples"] = serde_json::json!(1);
    for robot in json["robots"].as_array_mut().unwrap() {
        let c = &mut robot["camera"];
        for k in ["width", "height"] {
            c[k] = serde_json::json!(c[k].as_u64().unwrap() / u64::from(divide));
        }
        for k in ["fx", "fy", "cx", "cy"] {
            c[k] = serde_json::json!(c[k].as_f64().unwrap() / f64::from(divide));
        }
    }
    let scene = dir.join("scene.json");
    std::fs::write(&scene, json.to_string()).unwrap();
    scene
}

/// Starts `coordinator watch --until-alarm` on `result`: the process and its
/// stderr's lines.
fn start_watch(net: &common::Net, result: &Path) -> (Killed, mpsc::Receiver<(Instant, String)>) {
    let mut coordinator = Killed(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["watch", "--until-alarm", "--result"])
            .arg(result)
            .arg("--zenoh")
            .arg(&net.coordinator_cfg)
            .arg("--state-dir")
            .arg(net.dir.path().join("coordinator-state"))
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let lines = lines_of(&mut coordinator.0);
    (coordinator, lines)
}

/// Waits for a line with `armed` (robot 2 armed), then `quiet_s` seconds
/// without an alarm; if `take_target`, takes the target away (`b2b-sim-cart
/// take-target`) and waits `quiet_s` more without an alarm; bumps robot 2's
/// cart by `bump` through `control`, and waits for the alarm: when the bump
/// and the alarm came, and every line seen.
fn quiet_then_bumped(
    lines: &mpsc::Receiver<(Instant, String)>,
    control: &Path,
    bump: &[&str],
    quiet_s: u64,
    armed: &str,
    take_target: bool,
) -> (Instant, Instant, Vec<String>) {
    let mut seen = Vec::new();
    let armed = wait_for(lines, armed, Duration::from_secs(150), &mut seen);
    assert!(armed.is_some(), "never armed: {seen:#?}");
    let quiet = wait_for(lines, "ALARM", Duration::from_secs(quiet_s), &mut seen);
    assert!(quiet.is_none(), "a false alarm: {seen:#?}");
    // A command to the simulated carts of `control`.
    let command = |args: &[&str]| {
        let out = Command::new(sim_cart())
            .args(args)
            .arg("--control")
            .arg(control)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    };
    if take_target {
        // Carrying the board off alone must not alarm: the scene loses the
        // board's features, not its place.
        command(&["take-target"]);
        let quiet = wait_for(lines, "ALARM", Duration::from_secs(quiet_s), &mut seen);
        assert!(
            quiet.is_none(),
            "a false alarm as the target was taken: {seen:#?}"
        );
    }
    let bumped = Instant::now();
    command(&[&["bump", "--robot", "robot2"], bump].concat());
    let alarm_at = wait_for(lines, "ALARM", Duration::from_secs(30), &mut seen)
        .unwrap_or_else(|| panic!("no alarm after the bump: {seen:#?}"));
    (bumped, alarm_at, seen)
}

/// Calibrates on `set`, watches its still carts for 10 s (no alarm) with
/// `agent watch --observe OBSERVE`, bumps robot 2 by `bump` (`b2b-sim-cart
/// bump` flags) and returns the alarm, as it came on stderr
/// and on the bus.
fn bumped(set: &Path, observe: &str, bump: &[&str]) -> DriftAlarm {
    let _cell = ONE_CELL.lock().unwrap_or_else(|e| e.into_inner());
    let net = net();
    let dir = net.dir.path();
    let result = dir.join("RESULT.json");
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(["calibrate", "--dataset"])
        .arg(set)
        .arg("--out")
        .arg(&result)
        .arg("--state-dir")
        .arg(dir.join("coordinator-state"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let control = dir.join("control");
    std::fs::create_dir_all(&control).unwrap();

    let (mut coordinator, lines) = start_watch(&net, &result);
    // The test's own zenoh session, as any other process on the platform.
    let bus = ZenohBus::open(Some(&net.agent_cfg), Role::Agent).unwrap();
    let alarms = bus.subscribe(&alarm_key()).unwrap();
    let scene = if observe == "features" {
        // Two carts render the textured scene at about one frame a second
        // each here (424x240, 13 samples per pixel over its textures), far
        // below the watch's 5 Hz and a camera's rate: at half the resolution
        // and one sample they keep up with it. The watch's timing is under
        // test, not the renderer's.
        fast_scene(set, dir, 2)
    } else {
        set.join("scene.json")
    };
    let _agents: Vec<Killed> = ["robot1", "robot2"]
        .into_iter()
        .map(|robot| {
            Killed(
                Command::new(env!("CARGO_BIN_EXE_agent"))
                    .args([
                        "watch",
                        "--robot",
                        robot,
                        "--hz",
                        "5",
                        "--duration-s",
                        "240",
                        "--observe",
                        observe,
                    ])
                    .arg("--sim")
                    .arg(&scene)
                    .arg("--sim-control")
                    .arg(&control)
                    .arg("--zenoh")
                    .arg(&net.agent_cfg)
                    .arg("--state-dir")
                    .arg(dir.join(format!("agent-state-{robot}")))
                    // The setup each agent derives for its cart goes in here: the
                    // agents are killed at the end, before they could remove it.
                    .env("TMPDIR", dir)
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .spawn()
                    .unwrap(),
            )
        })
        .collect();

    // Still carts: no alarm for 10 s of watching.
    let (bumped, alarm_at, seen) =
        quiet_then_bumped(&lines, &control, bump, 10, "robot2: armed", false);
    // Observations were tested meanwhile (a summary every 5 s).
    assert!(
        seen.iter().any(|l| l.starts_with("robot2: watching")),
        "no observation tested: {seen:#?}"
    );
    let delay = alarm_at.duration_since(bumped);
    let status = coordinator.0.wait().unwrap();
    let alarm_line = seen.iter().find(|l| l.contains("ALARM")).cloned().unwrap();
    // What the coordinator said as it ended.
    let mut last = Vec::new();
    while let Ok((_, line)) = lines.recv_timeout(Duration::from_secs(5)) {
        last.push(line);
    }
    if observe == "features" {
        // Every scene frame after each robot's first comparison was matched
        // near its prediction: the still carts' and the bumped one's.
        let matching = last
            .iter()
            .find(|l| l.starts_with("robot2: scene frames matched"))
            .unwrap_or_else(|| panic!("no scene matching summary: {last:#?}"));
        eprintln!("{matching}");
        let count = |after: &str, until: char| -> u64 {
            matching
                .split(after)
                .nth(1)
                .and_then(|r| r.split(until).next())
                .and_then(|n| n.parse().ok())
                .unwrap_or_else(|| panic!("{matching}"))
        };
        let (near, brute) = (count("prediction ", ','), count("brute force ", ' '));
        assert!(near >= 20 && brute >= 1 && brute * 10 <= near, "{matching}");
    }
    for line in seen
        .iter()
        .filter(|l| l.contains("armed") || l.contains("in the last 5 s"))
    {
        eprintln!("{line}");
    }
    eprintln!(
        "bumped robot2 ({}): alarm after {:.2} s: {alarm_line}",
        bump.join(" "),
        delay.as_secs_f64()
    );
    assert_eq!(status.code(), Some(3), "{seen:#?}");
    assert!(alarm_line.contains("robot2"), "{alarm_line}");
    // The delay is printed, not bounded: five processes rendering and matching on
    // two shared cores stretch any wall-clock figure. How many observations the
    // alarm takes is asserted in process, on the watch's own clock
    // (`cargo test -p b2b-watch`: within three observations).
    let _ = delay;
    // The same alarm on the bus, with the size of the move.
    let msg = alarms
        .recv_timeout(Duration::from_secs(5))
        .unwrap()
        .expect("no alarm on b2b/coordinator/alarm");
    let envelope: Envelope<DriftAlarm> = serde_json::from_slice(&msg.payload).unwrap();
    let a = envelope.body;
    let against = if observe == "features" {
        "scene"
    } else {
        "robot1"
    };
    assert_eq!(
        (a.robot.as_str(), a.reference.as_str()),
        ("robot2", against)
    );
    assert!(!a.against_result, "{a:?}");
    a
}

/// `agent auto --watch-hz`: the automatic routine calibrates both carts with
/// the board, and each agent then stays to watch without being started again
/// (`--watch-observe auto`: the target and the scene's features). The board
/// is still in view, so each scene reference is taken with it; then the
/// board is carried off (no alarm for 5 s), and robot 2's cart bumped by
/// 1 mm: the alarm comes against the scene. (A bump at the very moment the
/// board goes is the `Watcher`'s unit test `a_cart_bumped_as_the_target_is_taken_away`.)
#[test]
fn the_automatic_routine_stays_to_watch_the_scene_and_a_bump_alarms() {
    let _cell = ONE_CELL.lock().unwrap_or_else(|e| e.into_inner());
    let net = net();
    let dir = net.dir.path();
    let result = dir.join("RESULT.json");
    let control = dir.join("control");
    std::fs::create_dir_all(&control).unwrap();
    // The board is detected at the scene's own resolution; one texture
    // sample keeps the watch's frames coming at its rate.
    let scene = fast_scene(&rgbd_dataset(), dir, 1);
    let mut run = Killed(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["run", "--robots", "robot1,robot2", "--method", "board"])
            .args(["--robot-sigma-mm", "0.3", "--robot-sigma-deg", "0.015"])
            .arg("--zenoh")
            .arg(&net.coordinator_cfg)
            .arg("--state-dir")
            .arg(dir.join("coordinator-state"))
            .arg("--out")
            .arg(&result)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let mut agents = Vec::new();
    for robot in ["robot1", "robot2"] {
        let mut agent = Killed(
            Command::new(env!("CARGO_BIN_EXE_agent"))
                .args(["auto", "--quiet", "--robot", robot])
                .args(["--count", "12", "--min-good", "8"])
                .args(["--robot-sigma-mm", "0.3", "--robot-sigma-deg", "0.015"])
                .args(["--watch-hz", "5", "--watch-observe", "auto"])
                .args(["--wait-result-s", "300"])
                .arg("--sim")
                .arg(&scene)
                .arg("--sim-control")
                .arg(&control)
                .arg("--zenoh")
                .arg(&net.agent_cfg)
                .arg("--state-dir")
                .arg(dir.join(format!("agent-state-{robot}")))
                .env("TMPDIR", dir)
                .stdout(Stdio::null())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap(),
        );
        let lines = lines_of(&mut agent.0);
        agents.push((robot, agent, lines));
    }
    let calibrated = common::wait_for_result(&result, &mut run, Duration::from_secs(400));
    for robot in ["robot1", "robot2"] {
        assert!(
            calibrated.captures.used.get(robot).copied().unwrap_or(0) >= 8,
            "{robot}: {:?}",
            calibrated.captures
        );
    }
    for (robot, _, lines) in &agents {
        let mut seen = Vec::new();
        let staying = wait_for(
            lines,
            "watching for drift",
            Duration::from_secs(60),
            &mut seen,
        );
        assert!(
            staying.is_some(),
            "{robot} did not stay to watch: {seen:#?}"
        );
    }

    let (mut coordinator, lines) = start_watch(&net, &result);
    let (bumped, alarm_at, seen) = quiet_then_bumped(
        &lines,
        &control,
        &["--t-mm", "1,0,0"],
        5,
        "robot2: armed on the scene's features",
        true,
    );
    for robot in ["robot1", "robot2"] {
        assert!(
            seen.iter()
                .any(|l| l.starts_with(&format!("{robot}: frame"))
                    && l.contains("is the scene's reference")
                    && l.contains("taken with the target in view")),
            "{robot}'s scene reference was not taken with the target: {seen:#?}"
        );
    }
    assert!(
        seen.iter()
            .any(|l| l.starts_with("robot2: armed; its misfit against the result")),
        "robot 2's target was not tested against the result: {seen:#?}"
    );
    let status = coordinator.0.wait().unwrap();
    assert_eq!(status.code(), Some(3), "{seen:#?}");
    let line = seen.iter().find(|l| l.contains("ALARM")).unwrap();
    let delay = alarm_at.duration_since(bumped);
    eprintln!(
        "after the automatic routine, the board carried off, then robot 2 bumped: alarm after {:.2} s: {line}",
        delay.as_secs_f64()
    );
    assert!(line.contains("robot2") && line.contains("scene"), "{line}");
    let shifted_mm: f64 = line
        .split("shifted ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("no shift in {line}"));
    assert!((0.62..1.5).contains(&shifted_mm), "{line}");
    // No bound on the delay here: two carts rendering at the scene's full
    // resolution (the board must be detected) give each agent one to two
    // frames a second on this machine, not the watch's 5 Hz, and the CUSUM
    // needs three. The 2 s bound is held at 5 Hz by the tests above.
    let rate = seen
        .iter()
        .rev()
        .find(|l| l.starts_with("robot2: watching against the scene"))
        .cloned()
        .unwrap_or_default();
    eprintln!("robot 2's rate: {rate}");
}
