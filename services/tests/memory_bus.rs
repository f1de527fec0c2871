//! The agent and coordinator loops without processes or sockets: two agents
//! replaying the simulator's two-robot dataset and a coordinator, as threads of
//! one process on the in-process bus. Their result equals the offline
//! `calibrate`, as it does over zenoh between processes (`tests/live.rs`): the
//! loops depend on the [`Bus`] trait, not on the transport.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use b2b_calib::refine::RefineOptions;
use b2b_protocol::messages::{COORDINATOR, result_key};
use b2b_services::agent::{AgentOptions, ReplaySource, run_agent_on};
use b2b_services::bus::{Bus, MemoryBus};
use b2b_services::coordinator::{RunOptions, run_on};

fn dataset() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12")
}

/// `coordinator run` for two robots, its journal in `state_dir`.
fn coordinator_options(state_dir: &Path, order: Option<Vec<String>>) -> RunOptions {
    RunOptions {
        zenoh: None,
        state_dir: state_dir.to_owned(),
        robots: 2,
        order,
        refine: RefineOptions::default(),
        method: b2b_pipeline::B2bMethod::Board,
        rgbd: b2b_pipeline::rgbd::RgbdOptions::default(),
    }
}

/// An agent replaying `robot`'s captures at once, then waiting for the result.
fn replay_agent(
    bus: Arc<dyn Bus>,
    robot: &str,
    state_dir: &Path,
    wait_result: Duration,
    stop: &AtomicBool,
) -> anyhow::Result<Option<b2b_protocol::CalibrationResult>> {
    let opts = AgentOptions {
        robot: robot.into(),
        zenoh: None,
        state_dir: state_dir.to_owned(),
        pace: Duration::ZERO,
        wait_result,
        progress: false,
        refine: RefineOptions::default(),
        rerun: Arc::new(b2b_viz::Recorder::disabled()),
    };
    let mut source = ReplaySource::open(&dataset(), robot)?;
    run_agent_on(bus, &opts, &mut source, stop)
}

#[test]
fn agents_and_coordinator_on_the_in_process_bus_give_the_offline_result() {
    let dir = tempfile::tempdir().unwrap();
    let bus = Arc::new(MemoryBus::new());
    let results = bus.subscribe(&result_key()).unwrap();
    // A watchdog: if the loops stall, stop them so that the test fails
    // instead of hanging.
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs(180));
            stop.store(true, Ordering::SeqCst);
        });
    }
    let stop = &*stop;
    let (coordinator, agents) = std::thread::scope(|s| {
        let coordinator = s.spawn(|| {
            let opts = coordinator_options(&dir.path().join("coordinator"), None);
            run_on(&*bus, &opts, stop).unwrap()
        });
        let agents: Vec<_> = ["robot1", "robot2"]
            .into_iter()
            .map(|robot| {
                let bus: Arc<dyn Bus> = bus.clone();
                let state = dir.path().join(robot);
                s.spawn(move || {
                    replay_agent(bus, robot, &state, Duration::from_secs(120), stop).unwrap()
                })
            })
            .collect();
        (
            coordinator.join().unwrap(),
            agents
                .into_iter()
                .map(|a| a.join().unwrap())
                .collect::<Vec<_>>(),
        )
    });
    let (result, counters) = coordinator;
    assert_eq!(counters.rejected, 0);
    let offline = common::offline_result_of(dir.path(), &dataset(), "board");
    common::assert_same(&result, &offline);
    // Every agent received the coordinator's result, as published.
    for got in agents {
        assert_eq!(got.as_ref(), Some(&result));
    }
    // The result travels in an envelope from the coordinator, like every message.
    let m = results
        .recv_timeout(Duration::from_secs(1))
        .unwrap()
        .unwrap();
    let envelope: serde_json::Value = serde_json::from_slice(&m.payload).unwrap();
    assert_eq!(envelope["robot"], COORDINATOR);
    assert!(envelope["seq"].as_u64().unwrap() >= 1);
    assert!(envelope["body"]["T_base1_base2"].is_object());
}

/// A bus that drops the session from one robot's statuses: an agent that never
/// echoes the coordinator's session (one of another run, or one that never
/// heard this coordinator).
struct WithoutEcho {
    inner: MemoryBus,
    robot: &'static str,
}

impl Bus for WithoutEcho {
    fn put(&self, key: &str, payload: Vec<u8>) -> Result<(), b2b_services::bus::BusError> {
        if key == format!("b2b/agent/{}/status", self.robot) {
            let mut v: serde_json::Value = serde_json::from_slice(&payload).unwrap();
            v.as_object_mut().unwrap().remove("session");
            return self.inner.put(key, serde_json::to_vec(&v).unwrap());
        }
        self.inner.put(key, payload)
    }
    fn subscribe(
        &self,
        key_expr: &str,
    ) -> Result<Box<dyn b2b_services::bus::Inbox>, b2b_services::bus::BusError> {
        self.inner.subscribe(key_expr)
    }
    fn query(
        &self,
        selector: &str,
        timeout: Duration,
    ) -> Result<Vec<b2b_services::bus::Received>, b2b_services::bus::BusError> {
        self.inner.query(selector, timeout)
    }
    fn serve(
        &self,
        key: &str,
        replies: b2b_services::bus::Replies,
    ) -> Result<b2b_services::bus::Declaration, b2b_services::bus::BusError> {
        self.inner.serve(key, replies)
    }
    fn announce(
        &self,
        key: &str,
    ) -> Result<b2b_services::bus::Declaration, b2b_services::bus::BusError> {
        self.inner.announce(key)
    }
}

/// The coordinator computes only once every robot's statuses echo its
/// session: with robot2's echo removed it is still waiting when stopped at
/// 6 s, although both agents finish within about two seconds (the test above).
#[test]
fn the_coordinator_waits_for_every_robot_to_echo_its_session() {
    let dir = tempfile::tempdir().unwrap();
    let bus = Arc::new(WithoutEcho {
        inner: MemoryBus::new(),
        robot: "robot2",
    });
    let stop = Arc::new(AtomicBool::new(false));
    let started = std::time::Instant::now();
    {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs(6));
            stop.store(true, Ordering::SeqCst);
        });
    }
    let stop = &*stop;
    let finished_at = std::thread::scope(|s| {
        let coordinator = s.spawn(|| {
            let order = Some(vec!["robot1".into(), "robot2".into()]);
            let _ = run_on(
                &*bus,
                &coordinator_options(&dir.path().join("coordinator"), order),
                stop,
            );
            started.elapsed()
        });
        for robot in ["robot1", "robot2"] {
            let bus: Arc<dyn Bus> = bus.clone();
            let state = dir.path().join(robot);
            s.spawn(move || {
                let _ = replay_agent(bus, robot, &state, Duration::from_secs(8), stop);
            });
        }
        coordinator.join().unwrap()
    });
    // Both agents finish in about a second (the test above); the coordinator
    // waited for robot2's echo until the stop.
    assert!(
        finished_at >= Duration::from_secs(6),
        "the coordinator solved after {finished_at:?} without robot2 echoing its session"
    );
}
