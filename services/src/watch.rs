//! `coordinator watch`: the drift watch during the operation.
//!
//! The agents keep observing the target at a low rate (`agent watch`,
//! publishing `Capture` messages under `b2b/agent/{robot}/watch`). Each
//! observation of a robot other than the reference is paired with the
//! reference robot's latest one (received within
//! [`WatchOptions::max_age`]), both are put into the reference base through
//! RESULT.json (each robot's hand-eye and base), and their difference goes to
//! that pair's sequential test ([`b2b_calib::drift::PairWatch`]: first against
//! the result and its covariance, then a CUSUM). An alarm goes out on
//! `b2b/coordinator/alarm`, on stderr and into the recording; each pair alarms
//! once.
//!
//! An agent's observation can also carry the scene's local features lifted
//! with its depth frame (`agent watch --observe auto|features`; `auto`
//! attaches them to every frame, with the target or without). Each robot is
//! then also watched against the scene itself, so that the watch goes on
//! where no target is left in view: its first frame with features is the
//! scene's reference; each later one is matched to it
//! (RANSAC + Umeyama over the lifted points, as the RGB-D method pairs views),
//! which says where the reference camera is now, and through the robot's
//! reported flange pose and hand-eye, where the scene is in the robot's base.
//! A still cart sees the scene where it was; a moved cart sees it moved by the
//! cart's motion. The scene's shift at its centre goes to the same sequential
//! test, with no result covariance to test against (the baseline is the scene
//! as the watch began). Every robot, the reference included, is watched so;
//! its alarm names `scene` as what it moved against. A frame with both is
//! tested both ways. So when the watch starts with the target still in view,
//! the scene's reference is taken while the target test checks the cart
//! against the result, and a cart bumped as the target is taken away is seen
//! against the scene; a scene reference taken without the target says that a
//! move before it is not seen.
//!
//! The first frame after the reference is matched by brute force (every
//! feature against every one) and its fit's inliers are remembered. Later
//! frames are matched near where the robot's pose predicts each feature
//! ([`match_views_near`], [`NEAR_GATE`]): a few descriptor distances per
//! feature instead of one per pair. A frame whose guided fit fails or keeps
//! fewer than half those inliers (the cart moved beyond the gate, or the
//! scene changed) is matched by brute force again, so a large move is seen
//! as it is ([`Watcher::scene_matching`] counts both). When brute force too
//! keeps fewer than half, the scene has lost features (the target taken
//! away) and its count is the one later frames are held to.
//!
//! The decisions are [`b2b_watch::Watcher`]'s; this module is its I/O: the
//! bus, the alarms' sequence numbers, the console and the recording.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use b2b_calib::drift::DriftOptions;
use b2b_protocol::CalibrationResult;
use b2b_protocol::messages::{COORDINATOR, Capture, DriftAlarm, Envelope, agent_key, alarm_key};
pub use b2b_watch::{SCENE, SceneMatching, WatchError, WatchEvent, Watcher};

use crate::agent::{Sequence, WATCH_TOPIC};
use crate::bus::{self, Bus};
use crate::{Result, ServiceError};

/// Settings of `coordinator watch`.
#[derive(Debug, Clone)]
pub struct WatchOptions {
    pub drift: DriftOptions,
    /// The oldest reference observation an observation is paired with.
    pub max_age: Duration,
    /// Stop at the first alarm.
    pub until_alarm: bool,
    /// Stop after this long (`None`: until Ctrl-C).
    pub duration: Option<Duration>,
    /// Where the alarms' sequence number is kept.
    pub state_dir: PathBuf,
}

/// What a test runs against, for an operator: the reference robot's target,
/// or the scene.
fn against_name(against: &str) -> String {
    if against == SCENE {
        "the scene".into()
    } else {
        format!("{against}'s target")
    }
}

/// What a watch saw.
#[derive(Debug, Clone, Default)]
pub struct WatchRun {
    /// Observations received and valid.
    pub observations: u64,
    /// Messages rejected as invalid.
    pub rejected: u64,
    pub alarms: Vec<DriftAlarm>,
    /// How each robot's scene frames were matched (robots watched through
    /// the scene's features only).
    pub scene_matching: BTreeMap<String, SceneMatching>,
}

/// Runs `watcher` on `bus` until `stop`, the duration, or (with
/// `until_alarm`) the first alarm; `on_event` sees every observation's
/// decisions.
pub fn run(
    bus: &dyn Bus,
    mut watcher: Watcher,
    opts: &WatchOptions,
    stop: &AtomicBool,
    on_event: &mut dyn FnMut(&[WatchEvent]),
) -> Result<WatchRun> {
    let inbox = bus.subscribe(&agent_key("*", WATCH_TOPIC))?;
    let seq = Sequence::open_named(&opts.state_dir, "watch")?;
    let started = Instant::now();
    let mut run = WatchRun::default();
    while !stop.load(Ordering::SeqCst) {
        if opts.duration.is_some_and(|d| started.elapsed() >= d) {
            break;
        }
        let Some(msg) = inbox.recv_timeout(Duration::from_millis(200))? else {
            continue;
        };
        let Some((robot, _)) = bus::parse_agent_key(&msg.key) else {
            continue;
        };
        let robot = robot.to_owned();
        let envelope = match bus::decode::<Capture>(&msg.key, &msg.payload) {
            Ok(e) => e,
            Err(reason) => {
                run.rejected += 1;
                crate::warn_limited(&msg.key, &reason);
                continue;
            }
        };
        run.observations += 1;
        let events = watcher.observe(&robot, Instant::now(), &envelope.body);
        on_event(&events);
        let mut stop_now = false;
        for event in &events {
            if let WatchEvent::Alarm(alarm) = event {
                bus::publish(
                    bus,
                    &alarm_key(),
                    &Envelope::new(COORDINATOR, seq.take()?, alarm.clone()),
                )?;
                run.alarms.push(alarm.clone());
                stop_now |= opts.until_alarm;
            }
        }
        if stop_now {
            break;
        }
    }
    run.scene_matching = watcher.scene_matchings();
    Ok(run)
}

/// `coordinator watch` as the binary runs it: reads RESULT.json, watches on
/// zenoh, prints the decisions (each robot's baseline, a summary every 5 s,
/// every alarm on stderr) and records them; with `until_alarm`, an alarm ends
/// the command with exit status 3.
pub fn watch_command(
    result_file: &std::path::Path,
    zenoh: Option<&std::path::Path>,
    opts: &WatchOptions,
    recorder: &b2b_viz::Recorder,
    stop: &AtomicBool,
) -> Result<()> {
    let result: CalibrationResult = crate::read_json(result_file)?;
    result
        .validate()
        .map_err(|e| ServiceError::from(e).in_file(result_file))?;
    let bus = bus::ZenohBus::open(zenoh, bus::Role::Coordinator)?;
    let watcher = Watcher::new(&result, opts.drift, opts.max_age)
        .map_err(|e| ServiceError::from(e).in_file(result_file))?;
    eprintln!(
        "watching {} against {} (baseline {} observations, CUSUM k {}, h {}; against the result: chi2 limit {})",
        watcher.robots().join(", "),
        result_file.display(),
        opts.drift.baseline,
        opts.drift.k,
        opts.drift.h,
        opts.drift.result_chi2
    );
    // Per robot and what it is tested against: observations tested since
    // the last summary, the largest z; per robot, those not tested at all,
    // with the last reason.
    let mut summary: BTreeMap<(String, String), (u64, f64)> = BTreeMap::new();
    let mut untested: BTreeMap<String, (u64, String)> = BTreeMap::new();
    let reference = result.reference.clone().unwrap_or_default();
    let mut last_summary = Instant::now();
    let now_s = || crate::history::now_unix_ms() as f64 / 1e3;
    let run = run(&bus, watcher, opts, stop, &mut |events| {
        // An observation none of whose tests ran (the reference's own
        // targets are used, not skipped).
        let untested_now = events
            .iter()
            .all(|e| matches!(e, WatchEvent::Skipped { robot, .. } if *robot != reference));
        if untested_now && let Some(WatchEvent::Skipped { robot, why }) = events.last() {
            let entry = untested.entry(robot.clone()).or_insert((0, String::new()));
            entry.0 += 1;
            entry.1.clone_from(why);
        }
        for event in events {
            match event {
                WatchEvent::Skipped { robot, why } => {
                    tracing::debug!("{robot}: skipped: {why}");
                }
                WatchEvent::SceneReference {
                    robot,
                    index,
                    features,
                    with_target,
                } => {
                    let taken = if *with_target {
                        "with the target in view"
                    } else {
                        "without the target: a move before it is not seen"
                    };
                    eprintln!(
                        "{robot}: frame {index} is the scene's reference ({features} features with depth), taken {taken}"
                    );
                }
                WatchEvent::Learning {
                    robot,
                    against,
                    seen,
                    needed,
                } => {
                    if *seen == 1 {
                        eprintln!(
                            "{robot}: learning the baseline against {} ({needed} observations)",
                            against_name(against)
                        );
                    }
                }
                WatchEvent::Armed {
                    robot,
                    against,
                    chi2,
                } => {
                    if against == SCENE {
                        eprintln!(
                            "{robot}: armed on the scene's features; the baseline's misfit against the scene's reference frame: chi2 {chi2:.1} (limit {:.1})",
                            opts.drift.result_chi2
                        )
                    } else {
                        eprintln!(
                            "{robot}: armed; its misfit against the result: chi2 {chi2:.1} (limit {:.1})",
                            opts.drift.result_chi2
                        )
                    }
                }
                WatchEvent::Watching {
                    robot,
                    against,
                    z,
                    cusum,
                } => {
                    let entry = summary
                        .entry((robot.clone(), against.clone()))
                        .or_insert((0, 0.0));
                    entry.0 += 1;
                    entry.1 = entry.1.max(*z);
                    if let Err(e) = recorder.log_watch(robot, against, now_s(), *z, *cusum) {
                        tracing::warn!("rerun: {e}");
                    }
                }
                WatchEvent::Alarm(alarm) => {
                    eprintln!("{}", alarm.message);
                    if let Err(e) = recorder.log_alarm(now_s(), &alarm.message) {
                        tracing::warn!("rerun: {e}");
                    }
                }
            }
        }
        if last_summary.elapsed() >= Duration::from_secs(5) {
            for ((robot, against), (n, z)) in std::mem::take(&mut summary) {
                eprintln!(
                    "{robot}: watching against {}, {n} observations in the last 5 s, largest z {z:.1}",
                    against_name(&against)
                );
            }
            // Observations that could not be tested, so an operator sees why a
            // cart is not watched (its reference silent, the target out of view).
            for (robot, (n, why)) in std::mem::take(&mut untested) {
                eprintln!(
                    "{robot}: {n} observations in the last 5 s not tested, the last because: {why}"
                );
            }
            last_summary = Instant::now();
        }
    })?;
    eprintln!(
        "watch ended: {} observations, {} rejected, {} alarm(s)",
        run.observations,
        run.rejected,
        run.alarms.len()
    );
    for (robot, m) in &run.scene_matching {
        eprintln!(
            "{robot}: scene frames matched near the robot's prediction {}, by brute force {} (the first, and any the prediction did not hold)",
            m.guided, m.brute_force
        );
    }
    if opts.until_alarm && !run.alarms.is_empty() {
        return Err(crate::ExitStatus {
            code: 3,
            message: "watch: alarm raised (exit status 3)".into(),
        }
        .into());
    }
    Ok(())
}
