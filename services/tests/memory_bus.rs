//! The agent and coordinator loops without processes or sockets: two agents
//! replaying the simulator's two-robot dataset and a coordinator, as threads of
//! one process on the in-process bus. Their result equals the offline
//! `calibrate`, as it does over zenoh between processes (`tests/live.rs`): the
//! loops depend on the [`Bus`] trait, not on the transport.

mod common;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use b2b_calib::refine::RefineOptions;
use b2b_live::ReplaySource;
use b2b_protocol::messages::{
    AgentState, AgentStatus, COORDINATOR, Envelope, SessionAnnouncement, result_key, session_key,
};
use b2b_services::agent::{AgentOptions, run_agent_on};
use b2b_services::bus::{Bus, BusError, Declaration, Inbox, MemoryBus, Received, Replies};
use b2b_services::coordinator::{Counters, RunOptions, run_on};
use b2b_services::store::gathering::FRUITLESS_QUERIES;

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
) -> b2b_services::Result<Option<b2b_protocol::CalibrationResult>> {
    replay_agent_of(bus, &dataset(), robot, state_dir, wait_result, stop)
}

/// [`replay_agent`] on `data`.
fn replay_agent_of(
    bus: Arc<dyn Bus>,
    data: &Path,
    robot: &str,
    state_dir: &Path,
    wait_result: Duration,
    stop: &AtomicBool,
) -> b2b_services::Result<Option<b2b_protocol::CalibrationResult>> {
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
    let mut source = ReplaySource::open(data, robot)?;
    run_agent_on(bus, &opts, &mut source, stop)
}

#[test]
fn agents_and_coordinator_on_the_in_process_bus_give_the_offline_result() {
    let dir = tempfile::tempdir().unwrap();
    let bus = Arc::new(MemoryBus::new());
    let results = bus.subscribe(&result_key()).unwrap();
    // Without `--robots`; the run fails if its watchdog has to stop it (a
    // stopped coordinator still solves what it has, so a run whose agents
    // never finished could otherwise look like a good one).
    let (coordinator, agents) = run_beside_as(
        bus.clone(),
        dir.path(),
        &dataset(),
        b2b_pipeline::B2bMethod::Board,
        None,
        |_| {},
    );
    let (result, counters) = coordinator.unwrap();
    assert_eq!(counters.rejected, 0);
    let offline = common::offline_result_of(dir.path(), &dataset(), "board");
    common::assert_same(&result, &offline);
    // Every agent received the coordinator's result, as published.
    for got in agents {
        assert_eq!(got.unwrap().as_ref(), Some(&result));
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

/// A bus that drops the session from one robot's statuses (an agent that
/// never echoes the coordinator's session: one of another run, or one that
/// never heard this coordinator), and counts the history queries.
#[derive(Default)]
struct Tampered {
    inner: MemoryBus,
    without_echo: Option<&'static str>,
    queries: AtomicUsize,
}

impl Bus for Tampered {
    fn put(&self, key: &str, payload: Vec<u8>) -> Result<(), BusError> {
        if let Some(robot) = self.without_echo
            && key == format!("b2b/agent/{robot}/status")
        {
            let mut v: serde_json::Value = serde_json::from_slice(&payload).unwrap();
            v.as_object_mut().unwrap().remove("session");
            return self.inner.put(key, serde_json::to_vec(&v).unwrap());
        }
        self.inner.put(key, payload)
    }
    fn subscribe(&self, key_expr: &str) -> Result<Box<dyn Inbox>, BusError> {
        self.inner.subscribe(key_expr)
    }
    fn query(&self, selector: &str, timeout: Duration) -> Result<Vec<Received>, BusError> {
        self.queries.fetch_add(1, Ordering::SeqCst);
        self.inner.query(selector, timeout)
    }
    fn serve(&self, key: &str, replies: Replies) -> Result<Declaration, BusError> {
        self.inner.serve(key, replies)
    }
    fn announce(&self, key: &str) -> Result<Declaration, BusError> {
        self.inner.announce(key)
    }
}

/// Sets `stop` after `limit` unless `done` is set first; says whether it did.
/// Only so that a stalled loop fails its test instead of hanging it.
fn watchdog(stop: Arc<AtomicBool>, done: Arc<AtomicBool>, limit: Duration) -> Arc<AtomicBool> {
    let fired = Arc::new(AtomicBool::new(false));
    let said = Arc::clone(&fired);
    std::thread::spawn(move || {
        let start = Instant::now();
        while !done.load(Ordering::SeqCst) {
            if start.elapsed() > limit {
                said.store(true, Ordering::SeqCst);
                stop.store(true, Ordering::SeqCst);
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    });
    fired
}

/// Sets its flag when dropped, also while a panic unwinds: a scope's threads
/// waiting for the flag then end, so that a failed assertion fails the test
/// instead of leaving the scope waiting for them for ever.
struct SetOnDrop<'a>(&'a AtomicBool);

impl Drop for SetOnDrop<'_> {
    fn drop(&mut self) {
        self.0.store(true, Ordering::SeqCst);
    }
}

/// The run's session, as the coordinator announces it on `bus`.
fn announced_session(sessions: &dyn Inbox) -> String {
    let m = sessions
        .recv_timeout(Duration::from_secs(30))
        .unwrap()
        .expect("no session announced");
    let e: Envelope<SessionAnnouncement> = serde_json::from_slice(&m.payload).unwrap();
    e.body.session
}

type Outcome = (
    b2b_services::Result<(b2b_protocol::CalibrationResult, Counters)>,
    Vec<b2b_services::Result<Option<b2b_protocol::CalibrationResult>>>,
);

/// A coordinator for robot1 and robot2 and their agents replaying `data`,
/// threads on `bus`, while `meddle` runs beside them until the coordinator
/// returns (its argument says when). Fails the test if the watchdog had to
/// stop anything: it watches until the agents have ended too, so agents that
/// never finish (or never take the coordinator's answer) fail the run.
fn run_beside(
    bus: Arc<dyn Bus>,
    dir: &Path,
    data: &Path,
    method: b2b_pipeline::B2bMethod,
    meddle: impl FnOnce(&AtomicBool) + Send,
) -> Outcome {
    run_beside_as(
        bus,
        dir,
        data,
        method,
        Some(vec!["robot1".into(), "robot2".into()]),
        meddle,
    )
}

/// [`run_beside`] with the coordinator's `--robots` (`None`: every robot
/// heard from).
fn run_beside_as(
    bus: Arc<dyn Bus>,
    dir: &Path,
    data: &Path,
    method: b2b_pipeline::B2bMethod,
    order: Option<Vec<String>>,
    meddle: impl FnOnce(&AtomicBool) + Send,
) -> Outcome {
    let stop = Arc::new(AtomicBool::new(false));
    // The whole run (the coordinator and both agents) has ended: what the
    // watchdog waits for. A run takes seconds; the limit only turns a stall
    // into a failure.
    let done = Arc::new(AtomicBool::new(false));
    let limit = Duration::from_secs(240);
    let fired = watchdog(Arc::clone(&stop), Arc::clone(&done), limit);
    // The coordinator has returned: what `meddle` waits for.
    let returned = AtomicBool::new(false);
    let outcome = std::thread::scope(|s| {
        let coordinator = s.spawn(|| {
            // Set however the coordinator ends, a panic included.
            let _returned = SetOnDrop(&returned);
            let mut opts = coordinator_options(&dir.join("coordinator"), order);
            opts.method = method;
            run_on(&*bus, &opts, &stop)
        });
        s.spawn(|| meddle(&returned));
        let agents: Vec<_> = ["robot1", "robot2"]
            .into_iter()
            .map(|robot| {
                let bus = Arc::clone(&bus);
                let state = dir.join(robot);
                let stop = &*stop;
                s.spawn(move || {
                    // The default wait: agents must not need it.
                    replay_agent_of(bus, data, robot, &state, Duration::from_secs(600), stop)
                })
            })
            .collect();
        let c = coordinator.join().unwrap();
        // The agents end at once on the coordinator's answer; the watchdog
        // is still running, and stops them if they do not.
        let agents = agents.into_iter().map(|a| a.join().unwrap()).collect();
        done.store(true, Ordering::SeqCst);
        (c, agents)
    });
    assert!(
        !fired.load(Ordering::SeqCst),
        "the watchdog had to stop the run after {limit:?}: the coordinator or an agent never finished"
    );
    outcome
}

/// Reads `statuses` until both agents have said they finished and robot2 has
/// sent `more` statuses since. An error when an agent failed, or when that
/// did not happen within `limit` (the agents' heartbeats alone would keep a
/// wait without a limit going for ever).
fn finished_then_more_of_robot2(
    statuses: &dyn Inbox,
    more: usize,
    limit: Duration,
) -> Result<(), String> {
    let deadline = Instant::now() + limit;
    let mut finished = std::collections::BTreeSet::new();
    let mut after = 0;
    while after < more {
        let left = deadline.saturating_duration_since(Instant::now());
        let not_yet = || {
            format!(
                "within {limit:?} the agents did not both finish and robot2 send {more} \
                 statuses after: finished {finished:?}, then {after} of robot2's statuses"
            )
        };
        if left.is_zero() {
            return Err(not_yet());
        }
        let m = statuses
            .recv_timeout(left)
            .map_err(|e| format!("statuses: {e}"))?
            .ok_or_else(not_yet)?;
        let e: Envelope<AgentStatus> = serde_json::from_slice(&m.payload).unwrap();
        if e.body.state == AgentState::Failed {
            return Err(format!("{} failed: {}", e.robot, e.body.message));
        }
        if finished.len() == 2 && e.robot == "robot2" {
            after += 1;
        }
        if e.body.state == AgentState::Finished {
            finished.insert(e.robot);
        }
    }
    Ok(())
}

/// The coordinator computes only once every robot's statuses echo its
/// session: with robot2's echo removed it is still waiting after both agents
/// have finished and robot2 has sent four more statuses since, and only the
/// stop ends it. If the agents never finished, the test fails.
#[test]
fn the_coordinator_waits_for_every_robot_to_echo_its_session() {
    let dir = tempfile::tempdir().unwrap();
    let bus = Arc::new(Tampered {
        without_echo: Some("robot2"),
        ..Default::default()
    });
    let statuses = bus.subscribe("b2b/agent/*/status").unwrap();
    let stop = AtomicBool::new(false);
    let agents_stop = AtomicBool::new(false);
    let (heard, solved, agents) = std::thread::scope(|s| {
        // However this ends, a panic included, the threads are stopped and
        // the scope can end.
        let _stop_all = [SetOnDrop(&agents_stop), SetOnDrop(&stop)];
        let coordinator = s.spawn(|| {
            let order = Some(vec!["robot1".into(), "robot2".into()]);
            run_on(
                &*bus,
                &coordinator_options(&dir.path().join("coordinator"), order),
                &stop,
            )
        });
        let agents: Vec<_> = ["robot1", "robot2"]
            .into_iter()
            .map(|robot| {
                let bus: Arc<dyn Bus> = bus.clone();
                let state = dir.path().join(robot);
                let agents_stop = &agents_stop;
                s.spawn(move || {
                    replay_agent(bus, robot, &state, Duration::from_secs(600), agents_stop)
                })
            })
            .collect();
        // A run takes seconds; the limit only turns agents that never finish
        // into a failure.
        let heard = finished_then_more_of_robot2(&*statuses, 4, Duration::from_secs(240));
        let solved = coordinator.is_finished();
        // The agents first: the coordinator, once stopped, solves what it has
        // and publishes it, which the agents are not to take.
        agents_stop.store(true, Ordering::SeqCst);
        let agents: Vec<_> = agents.into_iter().map(|a| a.join().unwrap()).collect();
        stop.store(true, Ordering::SeqCst);
        let _ = coordinator.join().unwrap();
        (heard, solved, agents)
    });
    if let Err(e) = heard {
        panic!("{e}");
    }
    assert!(
        !solved,
        "the coordinator solved without robot2 echoing its session"
    );
    // Each agent waited for a result until it was stopped, and none came.
    for (robot, got) in ["robot1", "robot2"].into_iter().zip(agents) {
        assert!(
            matches!(got, Ok(None)),
            "{robot} did not end by the stop without a result: {got:?}"
        );
    }
}

/// `dataset()` copied into `to`, robot1's flange positions moved by 5 cm in x.
fn moved_copy(to: &Path) {
    common::copy_dir(&dataset(), to);
    let captures = to.join("robot1/captures.csv");
    let text = std::fs::read_to_string(&captures).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let tx = header.iter().position(|h| *h == "tx").unwrap();
    let mut out = header.join(",") + "\n";
    for line in lines {
        let mut cells: Vec<String> = line.split(',').map(str::to_owned).collect();
        let v: f64 = cells[tx].parse().unwrap();
        cells[tx] = format!("{:?}", v + 0.05);
        out += &(cells.join(",") + "\n");
    }
    std::fs::write(&captures, out).unwrap();
}

/// An earlier run's captures (on data moved by 5 cm, in that run's session)
/// replayed into a new run over and over: each is dropped as of another
/// session, none counts as a conflict, and the run gives the offline result
/// of its own data, which both agents receive.
#[test]
fn an_earlier_runs_captures_replayed_into_a_new_run_are_dropped() {
    let dir = tempfile::tempdir().unwrap();
    let moved = dir.path().join("moved");
    moved_copy(&moved);
    // The earlier run, recorded.
    let earlier = Arc::new(MemoryBus::new());
    let recorded = earlier.subscribe("b2b/agent/*/capture").unwrap();
    let (first, agents) = run_beside(
        earlier.clone(),
        &dir.path().join("earlier"),
        &moved,
        b2b_pipeline::B2bMethod::Board,
        |_| {},
    );
    let (first, _) = first.unwrap();
    for got in agents {
        assert_eq!(
            got.unwrap().as_ref(),
            Some(&first),
            "the earlier run's agents"
        );
    }
    let mut replay = Vec::new();
    while let Some(m) = recorded.recv_timeout(Duration::from_millis(10)).unwrap() {
        replay.push((m.key, m.payload));
    }
    assert!(replay.len() >= 24, "{} captures recorded", replay.len());

    let bus = Arc::new(MemoryBus::new());
    let (now, agents) = run_beside(
        bus.clone(),
        &dir.path().join("now"),
        &dataset(),
        b2b_pipeline::B2bMethod::Board,
        |done| {
            while !done.load(Ordering::SeqCst) {
                for (key, payload) in &replay {
                    bus.put(key, payload.clone()).unwrap();
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        },
    );
    let (result, counters) = now.unwrap();
    assert_eq!(counters.conflicts, 0, "{counters:?}");
    assert!(counters.stale >= replay.len(), "{counters:?}");
    common::assert_same(
        &result,
        &common::offline_result_of(dir.path(), &dataset(), "board"),
    );
    for got in agents {
        assert_eq!(got.unwrap().as_ref(), Some(&result));
    }
}

/// A forged status "robot1 capturing, 999 published" with a huge sequence
/// number, sent in this run's session, in none and in another, over and over
/// from the start: the coordinator asks robot1's history a bounded number of
/// times, believes no more than it serves, and gives the offline result once
/// the agents finish.
#[test]
fn a_forged_status_count_neither_stalls_nor_floods_the_run() {
    let dir = tempfile::tempdir().unwrap();
    let bus = Arc::new(Tampered::default());
    let sessions = bus.subscribe(&session_key()).unwrap();
    let forger = Arc::clone(&bus);
    let (now, agents) = run_beside(
        bus.clone(),
        dir.path(),
        &dataset(),
        b2b_pipeline::B2bMethod::Board,
        move |done| {
            let bus = forger;
            let session = announced_session(&*sessions);
            let key = "b2b/agent/robot1/status";
            let forged = AgentStatus {
                state: AgentState::Capturing,
                good: 999,
                rejected: 0,
                published: 999,
                rotation_diversity_deg: 90.0,
                enough_data: true,
                message: "forged".into(),
            };
            let other = "fedcba9876543210fedcba9876543210";
            while !done.load(Ordering::SeqCst) {
                for s in [Some(session.as_str()), None, Some(other)] {
                    let e = Envelope::new("robot1", 1 << 50, forged.clone()).in_session(s);
                    b2b_services::bus::publish(&*bus, key, &e).unwrap();
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        },
    );
    let (result, counters) = now.unwrap();
    assert_eq!(counters.conflicts, 0);
    common::assert_same(
        &result,
        &common::offline_result_of(dir.path(), &dataset(), "board"),
    );
    for got in agents {
        assert_eq!(got.unwrap().as_ref(), Some(&result));
    }
    // The first catch-up, and per robot at most FRUITLESS_QUERIES in a row
    // after each of its 12 captures arrived (what resets the count).
    let queries = bus.queries.load(Ordering::SeqCst);
    let bound = 1 + 2 * (12 + 1) * FRUITLESS_QUERIES as usize;
    assert!(
        queries <= bound,
        "{queries} history queries (at most {bound})"
    );
}

/// Without `--robots`, a forged status of a robot that does not exist
/// ("robot9 capturing, 999 published", in this run's session) over and over:
/// once both real agents have finished, the coordinator leaves robot9 out
/// (it never sent a capture, its history serves none) and gives the offline
/// result of the two, which both agents receive. Before, it waited for
/// robot9 for ever.
#[test]
fn a_forged_status_of_an_unknown_robot_does_not_hold_a_run_without_robots() {
    let dir = tempfile::tempdir().unwrap();
    let bus = Arc::new(Tampered::default());
    let sessions = bus.subscribe(&session_key()).unwrap();
    let forger = Arc::clone(&bus);
    let (now, agents) = run_beside_as(
        bus.clone(),
        dir.path(),
        &dataset(),
        b2b_pipeline::B2bMethod::Board,
        None,
        move |done| {
            let bus = forger;
            let session = announced_session(&*sessions);
            let forged = AgentStatus {
                state: AgentState::Capturing,
                good: 999,
                rejected: 0,
                published: 999,
                rotation_diversity_deg: 90.0,
                enough_data: true,
                message: "forged".into(),
            };
            while !done.load(Ordering::SeqCst) {
                let e = Envelope::new("robot9", 1 << 50, forged.clone()).in_session(Some(&session));
                b2b_services::bus::publish(&*bus, "b2b/agent/robot9/status", &e).unwrap();
                std::thread::sleep(Duration::from_millis(20));
            }
        },
    );
    let (result, counters) = now.unwrap();
    assert_eq!(counters.conflicts, 0);
    common::assert_same(
        &result,
        &common::offline_result_of(dir.path(), &dataset(), "board"),
    );
    for got in agents {
        assert_eq!(got.unwrap().as_ref(), Some(&result));
    }
}

/// A solve that fails (the RGB-D method on captures without depth) is
/// published in the run's session: each agent ends at once with the
/// coordinator's reason instead of waiting out its 600 s.
#[test]
fn a_failed_solve_ends_the_agents_wait_with_its_reason() {
    let dir = tempfile::tempdir().unwrap();
    let bus = Arc::new(MemoryBus::new());
    let (now, agents) = run_beside(
        bus,
        dir.path(),
        &dataset(),
        b2b_pipeline::B2bMethod::Rgbd,
        |_| {},
    );
    let reason = b2b_pipeline::error_chain(&now.unwrap_err());
    for got in agents {
        let e = b2b_pipeline::error_chain(&got.unwrap_err());
        assert!(
            e.starts_with("the coordinator's solve failed: ") && e.ends_with(&reason),
            "{e} (the coordinator: {reason})"
        );
    }
}
