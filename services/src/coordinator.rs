//! `coordinator run`: listen to every agent, keep every sample, and compute
//! `base1_from_base2` once every agent heard from has finished.
//!
//! Nothing is lost: each valid sample is journalled (see [`crate::store`]) before
//! it is used; a restarted coordinator replays the journal, then asks the agents'
//! `history` queryables for whatever it missed while it was down (an agent's
//! status says how many captures it has published, so a gap is visible).
//! Invalid messages are rejected, counted and logged, never trusted.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::Context;
use b2b_calib::refine::RefineOptions;
use b2b_protocol::CalibrationResult;
use b2b_protocol::messages::{
    AgentStatus, COORDINATOR, Capture, Envelope, HandEyeUpdate, KEY_ROOT, SessionAnnouncement,
    agent_key, coordinator_alive_key, result_key, session_key,
};

use crate::agent::Sequence;
use crate::bus::{self, Bus};
use crate::store::{Arrival, Sample, Store};

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
}

/// Journals and keeps one message from the bus, with the certificate that
/// signed it on the secured bus; for a valid status, returns its robot and the
/// session it echoes (a live message, unlike the captures a history query
/// returns).
fn handle(
    store: &mut Store,
    counters: &mut Counters,
    key: &str,
    bytes: &[u8],
    signer: Option<&str>,
) -> anyhow::Result<Option<(String, Option<String>)>> {
    let Some((_, topic)) = bus::parse_agent_key(key) else {
        return Ok(None);
    };
    let mut echo = None;
    let sample = match topic {
        "capture" => bus::decode::<Capture>(key, bytes).map(Sample::Capture),
        "status" => bus::decode::<AgentStatus>(key, bytes).map(|e| {
            echo = Some((e.robot.clone(), e.session.clone()));
            Sample::Status(e)
        }),
        "hand_eye" => bus::decode::<HandEyeUpdate>(key, bytes).map(Sample::HandEye),
        _ => return Ok(None),
    };
    match sample {
        Ok(sample) => match store.accept_from(sample, signer)? {
            Arrival::New => counters.accepted += 1,
            Arrival::Duplicate => counters.duplicates += 1,
            Arrival::Conflict => counters.conflicts += 1,
        },
        Err(reason) => {
            counters.rejected += 1;
            crate::warn_limited(key, &reason);
        }
    }
    Ok(echo)
}

fn catch_up(
    bus: &dyn Bus,
    store: &mut Store,
    counters: &mut Counters,
    selector: &str,
) -> anyhow::Result<()> {
    for reply in bus.query(selector, Duration::from_secs(2))? {
        let key = reply.key.replace("/history", "/capture");
        handle(
            store,
            counters,
            &key,
            &reply.payload,
            reply.signer.as_deref(),
        )?;
    }
    Ok(())
}

/// Computes the result from what the store holds.
pub fn compute(store: &Store, opts: &RunOptions) -> anyhow::Result<CalibrationResult> {
    let ids = match &opts.order {
        Some(order) => order.clone(),
        None => store.robots(),
    };
    anyhow::ensure!(
        ids.len() >= 2,
        "need two robots, heard from {}: {:?}",
        ids.len(),
        ids
    );
    if opts.method == b2b_pipeline::B2bMethod::Rgbd {
        anyhow::ensure!(
            ids.len() == 2,
            "the rgbd method pairs two robots' images, heard from {}: {:?} (give --robots a,b)",
            ids.len(),
            ids
        );
        let o1 = store.observations(&ids[0])?;
        let o2 = store.observations(&ids[1])?;
        return compute_rgbd(store, [&ids[0], &ids[1]], [&o1, &o2], opts);
    }
    let observations = ids
        .iter()
        .map(|id| store.observations(id))
        .collect::<anyhow::Result<Vec<_>>>()?;
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
) -> anyhow::Result<CalibrationResult> {
    let start = Instant::now();
    let mut flange_from_camera = Vec::new();
    let mut covariance = Vec::new();
    for (id, obs) in ids.iter().zip(observations) {
        let he = b2b_pipeline::hand_eye(obs, b2b_pipeline::HandEyeChoice::Refined, &opts.refine)
            .with_context(|| format!("robot '{id}': hand-eye for the RGB-D method"))?;
        flange_from_camera.push(he.estimate.flange_from_camera);
        covariance.push(he.estimate.flange_from_camera_covariance);
    }
    let hand_eye_ms = start.elapsed().as_secs_f64() * 1e3;
    let (v1, mut rejected) = store.rgbd_views(ids[0])?;
    let (v2, r2) = store.rgbd_views(ids[1])?;
    rejected.extend(r2);
    let mut run = b2b_pipeline::rgbd::rgbd_from_views(
        ids,
        [&v1, &v2],
        [&observations[0].camera, &observations[1].camera],
        rejected,
        [flange_from_camera[0], flange_from_camera[1]],
        Some([covariance[0], covariance[1]]),
        &opts.rgbd,
    )?;
    run.result.timings_ms.detect = hand_eye_ms;
    run.result.timings_ms.total = start.elapsed().as_secs_f64() * 1e3;
    Ok(run.result)
}

/// Runs on a zenoh session (see [`bus::config`]) until every agent has
/// finished (or `stop` is set), then computes, publishes and returns the result.
pub fn run(opts: &RunOptions, stop: &AtomicBool) -> anyhow::Result<(CalibrationResult, Counters)> {
    let bus = bus::ZenohBus::open(opts.zenoh.as_deref(), bus::Role::Coordinator)?;
    let out = run_on(&bus, opts, stop)?;
    // Give the result a moment to leave before the session closes.
    std::thread::sleep(Duration::from_millis(300));
    Ok(out)
}

/// How often `run` says whom it is still waiting for (stderr).
pub const WAIT_REPORT_PERIOD: Duration = Duration::from_secs(10);

/// [`run`] on any bus.
pub fn run_on(
    bus: &dyn Bus,
    opts: &RunOptions,
    stop: &AtomicBool,
) -> anyhow::Result<(CalibrationResult, Counters)> {
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
pub fn session_of(state_dir: &std::path::Path) -> anyhow::Result<String> {
    let path = state_dir.join("session");
    match std::fs::read_to_string(&path) {
        Ok(text) => {
            let id = text.trim().to_owned();
            b2b_protocol::messages::validate_session_id(&id)
                .with_context(|| format!("{}", path.display()))?;
            Ok(id)
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let id = format!("{:032x}", rand::random::<u128>());
            let tmp = path.with_extension("tmp");
            std::fs::write(&tmp, &id)
                .and_then(|()| std::fs::rename(&tmp, &path))
                .with_context(|| format!("cannot write {}", path.display()))?;
            Ok(id)
        }
        Err(e) => Err(e).with_context(|| format!("cannot read {}", path.display())),
    }
}

/// The body of [`run_on`]: gathers until complete, solves, publishes the
/// result in `session`.
fn collect_and_solve(
    bus: &dyn Bus,
    opts: &RunOptions,
    stop: &AtomicBool,
    store: &mut Store,
    inbox: &dyn bus::Inbox,
    seq: &Sequence,
    session: &str,
) -> anyhow::Result<(CalibrationResult, Counters)> {
    let mut counters = Counters::default();
    catch_up(bus, store, &mut counters, &agent_key("*", "history"))?;
    let mut last_check = Instant::now();
    let mut last_report = Instant::now();
    // The robots whose statuses have echoed this run's session (a later
    // status without it, forged or stale, takes nothing back).
    let mut echoed: std::collections::BTreeSet<String> = Default::default();
    let not_echoing = |store: &Store, echoed: &std::collections::BTreeSet<String>| {
        let ids = opts.order.clone().unwrap_or_else(|| store.robots());
        ids.into_iter()
            .filter(|r| !echoed.contains(r))
            .collect::<Vec<_>>()
    };
    loop {
        if stop.load(Ordering::SeqCst)
            || (store.complete(opts.order.as_deref(), opts.robots)
                && not_echoing(store, &echoed).is_empty())
        {
            break;
        }
        if last_report.elapsed() >= WAIT_REPORT_PERIOD {
            last_report = Instant::now();
            let mut waiting = store.waiting_for(opts.order.as_deref(), opts.robots);
            // One phrase per robot: the echo joins what the store says of it.
            for r in not_echoing(store, &echoed) {
                let echo = format!(
                    "its statuses do not echo this run's session {session} yet (an agent of \
                     another run, or one that has not heard the coordinator)"
                );
                match waiting
                    .iter_mut()
                    .find(|w| w.starts_with(&format!("{r}: ")))
                {
                    Some(w) => {
                        w.push_str(", and ");
                        w.push_str(&echo);
                    }
                    None => waiting.push(format!("{r}: {echo}")),
                }
            }
            eprintln!("coordinator: waiting for {}", waiting.join("; "));
        }
        if let Some(m) = inbox.recv_timeout(Duration::from_millis(100))?
            && let Some((robot, Some(echo))) = handle(
                store,
                &mut counters,
                &m.key,
                &m.payload,
                m.signer.as_deref(),
            )?
            && echo == session
        {
            echoed.insert(robot);
        }
        if last_check.elapsed() > Duration::from_millis(500) {
            last_check = Instant::now();
            for robot in store.missing() {
                tracing::info!("asking {robot} for captures missed");
                catch_up(bus, store, &mut counters, &agent_key(&robot, "history"))?;
            }
        }
    }
    let result = compute(store, opts)?;
    bus::publish(
        bus,
        &result_key(),
        &Envelope::new(COORDINATOR, seq.take()?, result.clone()).in_session(Some(session)),
    )?;
    Ok((result, counters))
}

/// The RGB-D method with hand-eyes read from HANDEYE.json files, one per robot of
/// the dataset.
pub fn rgbd_with_hand_eye_files(
    ds: &b2b_dataset::Dataset,
    files: &[PathBuf],
) -> anyhow::Result<CalibrationResult> {
    let ids: Vec<String> = ds.manifest.robots.iter().map(|r| r.id.clone()).collect();
    anyhow::ensure!(
        ids.len() == 2,
        "base-to-base needs two robots, the dataset lists {}",
        ids.len()
    );
    let mut found: Vec<Option<(nalgebra::Isometry3<f64>, nalgebra::Matrix6<f64>)>> =
        vec![None, None];
    for path in files {
        let he: b2b_protocol::HandEyeResult = crate::read_json(path)?;
        anyhow::ensure!(
            he.format == b2b_protocol::HANDEYE_FORMAT,
            "{}: format '{}', expected '{}'",
            path.display(),
            he.format,
            b2b_protocol::HANDEYE_FORMAT
        );
        let k = ids.iter().position(|id| *id == he.robot).with_context(|| {
            format!(
                "{}: robot '{}' is not in the dataset ({})",
                path.display(),
                he.robot,
                ids.join(", ")
            )
        })?;
        anyhow::ensure!(
            found[k].is_none(),
            "{}: a second hand-eye for robot '{}'",
            path.display(),
            he.robot
        );
        let x = he
            .flange_from_camera
            .to_isometry("T_flange_camera")
            .with_context(|| path.display().to_string())?;
        let cov = nalgebra::Matrix6::from_fn(|i, j| he.covariance[i][j]);
        anyhow::ensure!(
            cov.iter().all(|v| v.is_finite()),
            "{}: covariance has a non-finite entry",
            path.display()
        );
        found[k] = Some((x, cov));
    }
    let (Some(a), Some(b)) = (found[0], found[1]) else {
        anyhow::bail!(
            "--hand-eye: need one HANDEYE.json for each of {} and {}",
            ids[0],
            ids[1]
        );
    };
    let run = b2b_pipeline::rgbd::rgbd_base_to_base_with_hand_eyes(
        ds,
        [a.0, b.0],
        Some([a.1, b.1]),
        &b2b_pipeline::rgbd::RgbdOptions::default(),
    )?;
    Ok(run.result)
}
