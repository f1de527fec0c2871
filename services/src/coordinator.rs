//! `coordinator run`: listen to every agent, keep every sample, and compute
//! `base1_from_base2` once every agent heard from has finished.
//!
//! Nothing is lost: each valid sample is journalled (see [`crate::store`]) before
//! it is used; a restarted coordinator replays the journal, then asks the agents'
//! `history` queryables for whatever it missed while it was down (an agent's
//! status says how many captures it has published, so a gap is visible).
//! Invalid messages are rejected, counted and logged, never trusted.
//!
//! A run has a session ([`session_of`]), announced twice a second; agents
//! stamp it into every message, and only messages of this session are used.
//! An earlier run's captures replayed into this one (signed ones cannot be
//! re-stamped) are dropped and logged, never taken for conflicts; an agent's
//! captures sent before it heard the session come again, stamped, from its
//! history. A status is believed no further than can be checked: one that
//! claims more captures than the robot's history serves is replaced by the
//! robot's own, history queries that bring nothing new stop after
//! `FRUITLESS_QUERIES`, and a robot finished with every capture held stays
//! finished. Those decisions are `b2b-store`'s, unit-tested there
//! ([`crate::store::gathering`]: `Heard`, `CatchUp`, `Gathering`); this loop
//! decodes the messages, feeds them in and does what they say. A failed solve
//! is published ([`RunFailure`]) so that the agents stop waiting.

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use b2b_calib::refine::RefineOptions;
use b2b_protocol::CalibrationResult;
use b2b_protocol::messages::{
    AgentStatus, COORDINATOR, Capture, Envelope, FAILURE_REASON_MAX, HandEyeUpdate, KEY_ROOT,
    RunFailure, SessionAnnouncement, agent_key, coordinator_alive_key, failure_key, result_key,
    session_key,
};

use crate::agent::Sequence;
use crate::bus::{self, Bus};
use crate::store::gathering::{CatchUp, Fate, Gathering, Heard, STATUS_ONLY_GRACE};
use crate::store::{Arrival, Sample, Store};
use crate::{Result, ServiceError};

/// Options of `coordinator run`.
#[derive(Debug, Clone)]
pub struct RunOptions {
    pub zenoh: Option<PathBuf>,
    pub state_dir: PathBuf,
    /// How many robots make a calibration.
    pub robots: usize,
    /// Robot order (robot 1 first); default: robot ids sorted.
    pub order: Option<Vec<String>>,
    pub refine: RefineOptions,
    /// `board` or `multimarker` (the same joint problem over the target points the
    /// agents report; the name goes into the result).
    pub method: b2b_pipeline::B2bMethod,
    /// Matching, RANSAC and pair screening of the RGB-D method.
    pub rgbd: b2b_pipeline::rgbd::RgbdOptions,
}

/// Counters of what arrived.
#[derive(Debug, Default, Clone, Copy)]
pub struct Counters {
    pub accepted: usize,
    pub duplicates: usize,
    /// Captures that arrived with an index already held but other content.
    pub conflicts: usize,
    pub rejected: usize,
    /// Messages of another session than this run's (an earlier run's
    /// replayed, an agent of another coordinator), and captures and
    /// hand-eyes of none (sent before the agent heard this run's session;
    /// its history serves them again in the session): dropped, never a
    /// conflict.
    pub stale: usize,
}

/// Checks one message from the bus and, when it belongs to this run's
/// `session`, journals and keeps it, with the certificate that signed it on
/// the secured bus. What is not of the session is dropped (logged, counted
/// as stale), except a status of none, which only says the agent has not
/// heard this run yet. Returns what the message was, for a valid one.
fn handle(
    store: &mut Store,
    counters: &mut Counters,
    key: &str,
    bytes: &[u8],
    signer: Option<&str>,
    session: &str,
) -> Result<Option<Heard>> {
    let Some((_, topic)) = bus::parse_agent_key(key) else {
        return Ok(None);
    };
    let decoded = match topic {
        "capture" => bus::decode::<Capture>(key, bytes).map(Sample::Capture),
        "status" => bus::decode::<AgentStatus>(key, bytes).map(Sample::Status),
        "hand_eye" => bus::decode::<HandEyeUpdate>(key, bytes).map(Sample::HandEye),
        _ => return Ok(None),
    };
    let sample = match decoded {
        Ok(sample) => sample,
        Err(reason) => {
            counters.rejected += 1;
            crate::warn_limited(key, &reason);
            return Ok(None);
        }
    };
    let (mut heard, fate) = Heard::of(&sample, session);
    match fate {
        Fate::Keep => {}
        Fate::NotYetBound => return Ok(Some(heard)),
        Fate::BeforeSession => {
            counters.stale += 1;
            tracing::debug!(
                "{key}: sent before the agent heard this run's session: dropped (its history \
                 serves it again in the session)"
            );
            return Ok(Some(heard));
        }
        Fate::OtherSession(other) => {
            counters.stale += 1;
            crate::warn_limited(
                &format!("{key} stale"),
                &format!(
                    "{key}: dropped a message of session {other}, not this run's {session} (an \
                     earlier run's, replayed, or an agent of another coordinator)"
                ),
            );
            return Ok(Some(heard));
        }
    }
    let arrival = store.accept_from(sample, signer)?;
    match arrival {
        Arrival::New => counters.accepted += 1,
        Arrival::Duplicate => counters.duplicates += 1,
        Arrival::Conflict => counters.conflicts += 1,
    }
    heard.arrival = Some(arrival);
    Ok(Some(heard))
}

/// Asks the `history` queryables matching `selector` for every capture and
/// keeps those of this run's session, noting what each robot's history
/// served ([`CatchUp`]). Returns the robots that gave something new.
fn catch_up(
    bus: &dyn Bus,
    store: &mut Store,
    counters: &mut Counters,
    selector: &str,
    session: &str,
) -> Result<BTreeSet<String>> {
    let mut answer = CatchUp::default();
    for reply in bus.query(selector, HISTORY_QUERY_TIMEOUT)? {
        let key = reply.key.replace("/history", "/capture");
        let heard = handle(
            store,
            counters,
            &key,
            &reply.payload,
            reply.signer.as_deref(),
            session,
        )?;
        if let Some(h) = heard {
            answer.replied(h);
        }
    }
    Ok(answer.finish(store))
}

/// How long a history query waits for its replies.
pub const HISTORY_QUERY_TIMEOUT: Duration = Duration::from_secs(2);

/// Computes the result from what the store holds.
pub fn compute(store: &Store, opts: &RunOptions) -> Result<CalibrationResult> {
    let ids = match &opts.order {
        Some(order) => order.clone(),
        None => store.robots(),
    };
    if ids.len() < 2 {
        return Err(ServiceError::TooFewRobots { robots: ids });
    }
    if opts.method == b2b_pipeline::B2bMethod::Rgbd {
        if ids.len() != 2 {
            return Err(ServiceError::RgbdNeedsTwoRobots { robots: ids });
        }
        let o1 = store.observations(&ids[0])?;
        let o2 = store.observations(&ids[1])?;
        return compute_rgbd(store, [&ids[0], &ids[1]], [&o1, &o2], opts);
    }
    let observations = ids
        .iter()
        .map(|id| store.observations(id))
        .collect::<Result<Vec<_>, _>>()?;
    let robots: Vec<&b2b_pipeline::RobotObservations> = observations.iter().collect();
    // The one board centre: the target's, as the agents report it.
    let names: Vec<&str> = ids.iter().map(String::as_str).collect();
    let centre = store.target_centre(&names)?;
    let b2b_pipeline::JointFit {
        mut result,
        cameras,
        spread,
    } = b2b_pipeline::bases_and_cameras_from_observations(
        &robots,
        &centre,
        &opts.refine,
        opts.method,
    )?;
    tracing::info!("{}", spread.describe());
    // A camera that gave no intrinsics was calibrated from these same captures:
    // the operator sees that, and with what.
    for c in cameras.iter().filter(|c| c.estimated.is_some()) {
        result.warnings.push(format!(
            "{} (the camera published none; the result's covariance includes their uncertainty)",
            c.describe()
        ));
    }
    Ok(result)
}

/// The RGB-D method over the agents' feature sets, with each robot's hand-eye
/// refined from its board observations (the same estimator as offline).
fn compute_rgbd(
    store: &Store,
    ids: [&str; 2],
    observations: [&b2b_pipeline::RobotObservations; 2],
    opts: &RunOptions,
) -> Result<CalibrationResult> {
    let start = Instant::now();
    // The same hand-eyes, and covariances, as offline.
    let [he1, he2] =
        b2b_pipeline::rgbd::rgbd_hand_eyes(observations, &opts.refine).map_err(|source| {
            ServiceError::RgbdHandEyes {
                robots: ids.map(str::to_owned),
                source: Box::new(source),
            }
        })?;
    let hand_eye_ms = start.elapsed().as_secs_f64() * 1e3;
    let (v1, mut rejected) = store.rgbd_views(ids[0])?;
    let (v2, r2) = store.rgbd_views(ids[1])?;
    rejected.extend(r2);
    let mut run = b2b_pipeline::rgbd::rgbd_from_views(
        ids,
        [&v1, &v2],
        [&observations[0].camera, &observations[1].camera],
        rejected,
        [he1.0, he2.0],
        Some([he1.1, he2.1]),
        &opts.rgbd,
    )?;
    run.result.timings_ms.detect = hand_eye_ms;
    run.result.timings_ms.total = start.elapsed().as_secs_f64() * 1e3;
    Ok(run.result)
}

/// Runs on a zenoh session (see [`bus::config`]) until every agent has
/// finished (or `stop` is set), then computes, publishes and returns the result.
pub fn run(opts: &RunOptions, stop: &AtomicBool) -> Result<(CalibrationResult, Counters)> {
    let bus = bus::ZenohBus::open(opts.zenoh.as_deref(), bus::Role::Coordinator)?;
    let out = run_on(&bus, opts, stop);
    // Give the result, or the failure, a moment to leave before the session
    // closes.
    std::thread::sleep(Duration::from_millis(300));
    out
}

/// How often `run` says whom it is still waiting for (stderr).
pub const WAIT_REPORT_PERIOD: Duration = Duration::from_secs(10);

/// [`run`] on any bus.
pub fn run_on(
    bus: &dyn Bus,
    opts: &RunOptions,
    stop: &AtomicBool,
) -> Result<(CalibrationResult, Counters)> {
    let mut store = Store::open(&opts.state_dir)?;
    if store.skipped_lines > 0 {
        eprintln!(
            "warning: {} unreadable journal line(s) skipped (an earlier crash mid-write)",
            store.skipped_lines
        );
    }
    let seq = Sequence::open_named(&opts.state_dir, COORDINATOR)?;
    let session = session_of(&opts.state_dir)?;
    let announcement = bus::encode(
        &session_key(),
        &Envelope::new(
            COORDINATOR,
            seq.take()?,
            SessionAnnouncement {
                session: session.clone(),
            },
        ),
    )?;
    let _alive = bus.announce(&coordinator_alive_key())?;
    let inbox = bus.subscribe(&format!("{KEY_ROOT}/agent/**"))?;
    // The session goes out twice a second for as long as the run lasts (the
    // solve included), so an agent that connects late hears it before the
    // result.
    let done = AtomicBool::new(false);
    std::thread::scope(|scope| {
        scope.spawn(|| {
            while !done.load(Ordering::SeqCst) {
                if let Err(e) = bus.put(&session_key(), announcement.clone()) {
                    tracing::warn!("announcing the session: {e}");
                }
                let started = Instant::now();
                while started.elapsed() < SESSION_PERIOD && !done.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(20));
                }
            }
        });
        let out = collect_and_solve(bus, opts, stop, &mut store, &*inbox, &seq, &session);
        done.store(true, Ordering::SeqCst);
        out
    })
}

/// How often `run` announces its session.
pub const SESSION_PERIOD: Duration = Duration::from_millis(500);

/// The session of the run whose journal is in `state_dir`: read from
/// `state_dir/session`, or a new random one written there. A coordinator
/// restarted on the same folder resumes the same run, so its agents' echo
/// still holds.
pub fn session_of(state_dir: &std::path::Path) -> Result<String> {
    let path = state_dir.join("session");
    match std::fs::read_to_string(&path) {
        Ok(text) => {
            let id = text.trim().to_owned();
            b2b_protocol::messages::validate_session_id(&id)
                .map_err(|e| ServiceError::from(e).in_file(&path))?;
            Ok(id)
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let id = format!("{:032x}", rand::random::<u128>());
            let tmp = path.with_extension("tmp");
            std::fs::write(&tmp, &id)
                .and_then(|()| std::fs::rename(&tmp, &path))
                .map_err(ServiceError::io("write", &path))?;
            Ok(id)
        }
        Err(e) => Err(ServiceError::io("read", &path)(e)),
    }
}

/// The body of [`run_on`]: gathers until complete, solves, publishes the
/// result in `session`, or the reason the solve failed.
fn collect_and_solve(
    bus: &dyn Bus,
    opts: &RunOptions,
    stop: &AtomicBool,
    store: &mut Store,
    inbox: &dyn bus::Inbox,
    seq: &Sequence,
    session: &str,
) -> Result<(CalibrationResult, Counters)> {
    let mut counters = Counters::default();
    catch_up(
        bus,
        store,
        &mut counters,
        &agent_key("*", "history"),
        session,
    )?;
    let mut gather = Gathering::new(opts.order.clone(), opts.robots);
    let mut last_check = Instant::now();
    let mut last_report = Instant::now();
    let mut solve_with = None;
    loop {
        if stop.load(Ordering::SeqCst) || gather.done(store) {
            break;
        }
        if let Some((with, without)) = gather.without_status_only(store, Instant::now()) {
            let text = format!(
                "not waiting for {}: heard only through statuses, no capture of theirs arrived \
                 nor is in their history {} s after the others finished (a stray or forged \
                 status? give --robots to name the robots of the run)",
                without.join(", "),
                STATUS_ONLY_GRACE.as_secs()
            );
            eprintln!("coordinator: {text}");
            tracing::warn!("{text}");
            solve_with = Some(with);
            break;
        }
        if last_report.elapsed() >= WAIT_REPORT_PERIOD {
            last_report = Instant::now();
            eprintln!(
                "coordinator: waiting for {}",
                gather.waiting_for(store, session).join("; ")
            );
        }
        if let Some(m) = inbox.recv_timeout(Duration::from_millis(100))?
            && let Some(heard) = handle(
                store,
                &mut counters,
                &m.key,
                &m.payload,
                m.signer.as_deref(),
                session,
            )?
        {
            gather.heard(&heard);
        }
        if last_check.elapsed() > Duration::from_millis(500) {
            last_check = Instant::now();
            for robot in gather.to_ask(store) {
                tracing::info!("asking {robot} for captures missed");
                let news = catch_up(
                    bus,
                    store,
                    &mut counters,
                    &agent_key(&robot, "history"),
                    session,
                )?;
                gather.answered(&robot, news.contains(&robot));
            }
        }
    }
    let narrowed;
    let opts = match solve_with {
        Some(with) => {
            narrowed = RunOptions {
                order: Some(with),
                ..opts.clone()
            };
            &narrowed
        }
        None => opts,
    };
    let result = match compute(store, opts) {
        Ok(result) => result,
        Err(e) => {
            // The agents wait for this run's answer: they hear the failure
            // and stop waiting.
            let failure = RunFailure {
                reason: failure_reason(&b2b_pipeline::error_chain(&e)),
            };
            let sent = seq.take().and_then(|n| {
                bus::publish(
                    bus,
                    &failure_key(),
                    &Envelope::new(COORDINATOR, n, failure).in_session(Some(session)),
                )
                .map_err(ServiceError::from)
            });
            if let Err(p) = sent {
                tracing::warn!(
                    "could not tell the agents the solve failed: {}",
                    b2b_pipeline::error_chain(&p)
                );
            }
            return Err(e);
        }
    };
    bus::publish(
        bus,
        &result_key(),
        &Envelope::new(COORDINATOR, seq.take()?, result.clone()).in_session(Some(session)),
    )?;
    Ok((result, counters))
}

/// An error as a [`RunFailure::reason`]: one line of printable characters,
/// cut to [`FAILURE_REASON_MAX`] bytes.
fn failure_reason(text: &str) -> String {
    let line: String = text
        .chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .collect();
    let line = line.trim();
    if line.is_empty() {
        return "the solve failed without a reason".into();
    }
    if line.len() <= FAILURE_REASON_MAX {
        return line.to_owned();
    }
    let mut cut = FAILURE_REASON_MAX - '…'.len_utf8();
    while !line.is_char_boundary(cut) {
        cut -= 1;
    }
    format!("{}…", &line[..cut])
}

/// The RGB-D method with hand-eyes read from HANDEYE.json files, one per robot of
/// the dataset.
pub fn rgbd_with_hand_eye_files(
    ds: &b2b_dataset::Dataset,
    files: &[PathBuf],
) -> Result<CalibrationResult> {
    let ids: Vec<String> = ds.manifest.robots.iter().map(|r| r.id.clone()).collect();
    if ids.len() != 2 {
        return Err(ServiceError::DatasetNotTwoRobots { listed: ids.len() });
    }
    let mut found: Vec<Option<(nalgebra::Isometry3<f64>, nalgebra::Matrix6<f64>)>> =
        vec![None, None];
    for path in files {
        let he: b2b_protocol::HandEyeResult = crate::read_json(path)?;
        if he.format != b2b_protocol::HANDEYE_FORMAT {
            return Err(ServiceError::WrongFormat {
                path: path.clone(),
                found: he.format,
                expected: b2b_protocol::HANDEYE_FORMAT,
            });
        }
        let Some(k) = ids.iter().position(|id| *id == he.robot) else {
            return Err(ServiceError::HandEyeRobotNotInDataset {
                path: path.clone(),
                robot: he.robot,
                robots: ids,
            });
        };
        if found[k].is_some() {
            return Err(ServiceError::SecondHandEye {
                path: path.clone(),
                robot: he.robot,
            });
        }
        let x = he
            .flange_from_camera
            .to_isometry("T_flange_camera")
            .map_err(|e| ServiceError::from(e).in_file(path))?;
        let cov = nalgebra::Matrix6::from_fn(|i, j| he.covariance[i][j]);
        if !cov.iter().all(|v| v.is_finite()) {
            return Err(ServiceError::NonFiniteCovariance { path: path.clone() });
        }
        found[k] = Some((x, cov));
    }
    let (Some(a), Some(b)) = (found[0], found[1]) else {
        return Err(ServiceError::MissingHandEye {
            robots: [ids[0].clone(), ids[1].clone()],
        });
    };
    let run = b2b_pipeline::rgbd::rgbd_base_to_base_with_hand_eyes(
        ds,
        [a.0, b.0],
        Some([a.1, b.1]),
        &b2b_pipeline::rgbd::RgbdOptions::default(),
    )?;
    Ok(run.result)
}
