//! `agent run`: one cart's captures onto the bus.
//!
//! Per capture the agent publishes one [`Capture`] message (flange pose, board
//! observation or rejection reason, and `base_from_target` corrected by its
//! current hand-eye), and whenever its captures allow a hand-eye, a
//! [`HandEyeUpdate`]. A status message goes out on every change and as a
//! heartbeat, so a coordinator that starts late still learns what it missed; the
//! `history` queryable then serves every capture published so far. Sequence
//! numbers are kept in the state folder, so a restarted agent continues its
//! sequence; capture indices are the dataset's, so a replay restarted from the
//! beginning re-sends the same captures and the coordinator drops the repeats.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::bus::{self, Bus};
use crate::{Result, ServiceError};
use b2b_calib::degeneracy::{MotionThresholds, check_motions};
use b2b_calib::refine::RefineOptions;
use b2b_live::{CaptureSource, Progress, ReplaySource, SourceCapture};
use b2b_pipeline::{HandEyeChoice, Observation, RobotObservations, error_chain, hand_eye};
use b2b_protocol::messages::{
    AgentState, AgentStatus, BoardObservation, Capture, Envelope, HandEyeUpdate, Intrinsics,
    RunFailure, SessionAnnouncement, agent_key, failure_key, result_key, session_key,
};
use b2b_protocol::{CalibrationResult, Pose};

/// The persisted sequence counter of one agent.
#[derive(Debug)]
pub struct Sequence {
    path: PathBuf,
    next: Mutex<u64>,
}

impl Sequence {
    /// Continues from the number stored in `dir` for agent `robot` (or starts at 1).
    pub fn open(dir: &Path, robot: &str) -> Result<Sequence> {
        Sequence::open_named(dir, &format!("agent-{robot}"))
    }

    /// Continues from the number stored in `dir/{name}.seq` (or starts at 1).
    pub fn open_named(dir: &Path, name: &str) -> Result<Sequence> {
        std::fs::create_dir_all(dir).map_err(ServiceError::io("create state folder", dir))?;
        let path = dir.join(format!("{name}.seq"));
        let next = match std::fs::read_to_string(&path) {
            Ok(text) => match text.trim().parse::<u64>() {
                Ok(n) => n + 1,
                Err(source) => return Err(ServiceError::NotASequenceNumber { path, source }),
            },
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => 1,
            Err(e) => return Err(ServiceError::io("read", &path)(e)),
        };
        Ok(Sequence {
            path,
            next: Mutex::new(next),
        })
    }

    /// The next number, stored before it is used.
    pub fn take(&self) -> Result<u64> {
        let mut next = self
            .next
            .lock()
            .map_err(|_| ServiceError::Poisoned { what: "sequence" })?;
        let n = *next;
        *next += 1;
        let tmp = self.path.with_extension("seq.tmp");
        std::fs::write(&tmp, n.to_string())
            .and_then(|_| std::fs::rename(&tmp, &self.path))
            .map_err(ServiceError::io("write", &self.path))?;
        Ok(n)
    }
}

/// Options of `agent run`, whatever the source.
#[derive(Debug, Clone)]
pub struct AgentOptions {
    pub robot: String,
    pub zenoh: Option<PathBuf>,
    pub state_dir: PathBuf,
    /// Pause between captures (a real arm takes seconds per pose).
    pub pace: Duration,
    /// How long to wait for the coordinator's result after the last capture.
    pub wait_result: Duration,
    pub progress: bool,
    /// Robot pose noise of the agent's own hand-eye estimates.
    pub refine: RefineOptions,
    /// Where captures are recorded (disabled: nowhere).
    pub rerun: Arc<b2b_viz::Recorder>,
}

/// How an agent reaches the coordinator (`agent run`, `agent auto`).
#[derive(clap::Args, Debug, Clone)]
pub struct BusArgs {
    /// zenoh configuration file (JSON5); default: loopback peer connecting to
    /// the coordinator on tcp/127.0.0.1:7447.
    #[arg(long)]
    pub zenoh: Option<PathBuf>,
    /// Where the agent keeps its sequence number.
    #[arg(long, default_value = "agent-state")]
    pub state_dir: PathBuf,
    /// Seconds to wait for the coordinator's result after the last capture.
    #[arg(long, default_value_t = 600)]
    pub wait_result_s: u64,
    /// No progress bar.
    #[arg(long)]
    pub quiet: bool,
}

fn board_observation(
    o: &Observation,
    target_centre: &nalgebra::Point3<f64>,
    target: Option<&str>,
) -> BoardObservation {
    BoardObservation {
        target_points: o
            .board
            .target_points
            .iter()
            .map(|p| [p.x, p.y, p.z])
            .collect(),
        pixels: o.board.pixels.iter().map(|p| [p.x, p.y]).collect(),
        camera_from_target: Pose::from_isometry(&o.camera_from_target),
        residuals_px: o.residuals_px.clone(),
        rms_px: o.pnp_rms_px,
        target_centre: Some(target_centre.coords.into()),
        target: target.map(str::to_owned),
    }
}

/// Replays a dataset's captures for one robot onto the bus (with local
/// features for the RGB-D method when `features` is given, for captures with a
/// depth image), then waits for the coordinator's result. Returns it when it came.
pub fn run_replay(
    opts: &AgentOptions,
    dataset: &Path,
    features: Option<b2b_vision::features::FeatureKind>,
    stop: &AtomicBool,
) -> Result<Option<CalibrationResult>> {
    b2b_protocol::messages::validate_cart_id(&opts.robot)?;
    let mut source = ReplaySource::open(dataset, &opts.robot)?;
    if let Some(kind) = features {
        source = source.with_features(kind);
    }
    run_agent(opts, &mut source, stop)
}

/// Publishes one source's captures onto a zenoh session (captures, hand-eye,
/// status, history), then waits for the coordinator's result. Returns it when
/// it came.
pub fn run_agent(
    opts: &AgentOptions,
    source: &mut dyn CaptureSource,
    stop: &AtomicBool,
) -> Result<Option<CalibrationResult>> {
    b2b_protocol::messages::validate_cart_id(&opts.robot)?;
    let bus = Arc::new(bus::ZenohBus::open(
        opts.zenoh.as_deref(),
        bus::Role::Agent,
    )?);
    run_agent_on(bus, opts, source, stop)
}

/// [`run_agent`] on any bus.
pub fn run_agent_on(
    bus: Arc<dyn Bus>,
    opts: &AgentOptions,
    source: &mut dyn CaptureSource,
    stop: &AtomicBool,
) -> Result<Option<CalibrationResult>> {
    b2b_protocol::messages::validate_cart_id(&opts.robot)?;
    let link = AgentLink::open(bus, &opts.robot, &opts.state_dir, source.describe())?;
    let results = link.status.bus.subscribe(&result_key())?;
    let failures = link.status.bus.subscribe(&failure_key())?;
    let bar = progress_bar(opts.progress, source.expected(), &opts.robot);
    let mut captures = CaptureLoop::default();
    let run = captures.run(&link, opts, source, stop, &bar);
    bar.finish();
    let robot = &opts.robot;
    if let Some(line) = source.summary() {
        eprintln!("{robot}: {line}");
    }
    if let Some(o) = &captures.observations {
        if let Some(e) = &o.estimated_intrinsics {
            let c = captures.camera.as_ref().unwrap_or(&o.camera);
            eprintln!(
                "{robot}: camera estimated (the camera gave no intrinsics): fx {:.2} fy {:.2} \
                 cx {:.2} cy {:.2}, fitted to {} of {} captures at {:.3} px and refined with \
                 the hand-eye; the coordinator fits it again from every capture",
                c.fx,
                c.fy,
                c.cx,
                c.cy,
                e.images_used,
                o.observations.len(),
                e.rms_px
            );
        }
        for r in &o.rejected {
            eprintln!(
                "{robot}: rejected {} (row {}): {}",
                r.image.as_deref().unwrap_or("-"),
                r.row.map_or("-".into(), |n| n.to_string()),
                r.reason
            );
        }
    }
    link.status.update(|s| match &run {
        Ok(()) => {
            s.state = AgentState::Finished;
            s.message = "all captures published".into();
        }
        Err(e) => {
            s.state = AgentState::Failed;
            s.message = error_chain(e);
        }
    })?;
    link.status.publish()?;
    run?;
    // Stay reachable (history, heartbeat) until the coordinator answers.
    let answer = wait_for_result(
        Answers {
            results: &*results,
            failures: &*failures,
        },
        &link.status,
        opts.wait_result,
        stop,
    );
    match answer {
        Answer::Result(r) => Ok(Some(*r)),
        Answer::Failed(reason) => Err(ServiceError::SolveFailed { reason }),
        Answer::None if stop.load(Ordering::SeqCst) => Ok(None),
        Answer::None => match link.status.session()? {
            Some(_) => Ok(None),
            None => Err(ServiceError::NoCoordinator {
                waited_s: opts.wait_result.as_secs(),
                why: link.status.bus.unreached().unwrap_or_else(|| {
                    "connected, but no session announced: is the coordinator running (or \
                     another program in its place: is another coordinator running?)"
                        .into()
                }),
            }),
        },
    }
}

/// The status message of one agent, published on every change and as a heartbeat.
#[derive(Clone)]
struct StatusLink {
    bus: Arc<dyn Bus>,
    robot: String,
    seq: Arc<Sequence>,
    status: Arc<Mutex<AgentStatus>>,
    /// The coordinator's session, as last announced: echoed in every message.
    session: Arc<Mutex<Option<String>>>,
    /// The coordinator's session announcements.
    sessions: Arc<Mutex<Box<dyn bus::Inbox>>>,
}

impl StatusLink {
    fn update(&self, change: impl FnOnce(&mut AgentStatus)) -> Result<()> {
        let mut s = self
            .status
            .lock()
            .map_err(|_| ServiceError::Poisoned { what: "status" })?;
        change(&mut s);
        Ok(())
    }

    fn publish(&self) -> Result<()> {
        let body = self
            .status
            .lock()
            .map_err(|_| ServiceError::Poisoned { what: "status" })?
            .clone();
        self.send("status", body)
    }

    /// Publishes a message of this agent under `b2b/agent/{robot}/{topic}`,
    /// with the next sequence number, in the coordinator's session.
    fn send<T: serde::Serialize + b2b_protocol::messages::Validate>(
        &self,
        topic: &str,
        body: T,
    ) -> Result<()> {
        let key = agent_key(&self.robot, topic);
        Ok(bus::publish(&*self.bus, &key, &self.envelope(body)?)?)
    }

    /// `body` with the next sequence number, in the session echoed now.
    fn envelope<T: b2b_protocol::messages::Validate>(&self, body: T) -> Result<Envelope<T>> {
        Ok(Envelope::new(&self.robot, self.seq.take()?, body)
            .in_session(self.session()?.as_deref()))
    }

    /// The session echoed now.
    fn session(&self) -> Result<Option<String>> {
        Ok(self
            .session
            .lock()
            .map_err(|_| ServiceError::Poisoned { what: "session" })?
            .clone())
    }

    /// Whether an answer of the coordinator in `theirs` is for this agent:
    /// of the session it echoes (taking an announcement that arrived since
    /// the last heartbeat first). Logs the ones it is not.
    fn ours(&self, theirs: Option<&str>, what: &str) -> bool {
        self.hear_session();
        let echoed = self.session().ok().flatten();
        if theirs.is_some() && theirs == echoed.as_deref() {
            return true;
        }
        tracing::warn!(
            "{}: ignored a {what} of session {} (this agent echoes {})",
            self.robot,
            theirs.unwrap_or("none"),
            echoed
                .as_deref()
                .unwrap_or("none: no coordinator session heard")
        );
        false
    }

    /// Takes the coordinator's newest session announcement, if one arrived.
    fn hear_session(&self) {
        let Ok(inbox) = self.sessions.lock() else {
            return;
        };
        loop {
            match inbox.recv_timeout(Duration::ZERO) {
                Ok(Some(m)) => match bus::decode::<SessionAnnouncement>(&m.key, &m.payload) {
                    Ok(e) => {
                        if let Ok(mut current) = self.session.lock()
                            && current.as_deref() != Some(e.body.session.as_str())
                        {
                            tracing::info!(
                                "{}: coordinator session {}",
                                self.robot,
                                e.body.session
                            );
                            *current = Some(e.body.session);
                        }
                    }
                    Err(reason) => crate::warn_limited(
                        &m.key,
                        &format!("ignored a session announcement: {reason}"),
                    ),
                },
                Ok(None) => return,
                Err(e) => {
                    tracing::warn!("{e}");
                    return;
                }
            }
        }
    }
}

/// One agent's presence on the bus: its status (with a heartbeat twice a
/// second) and the `history` queryable serving every capture published so far.
/// Dropping it stops the heartbeat.
struct AgentLink {
    status: StatusLink,
    /// Every capture published, served in the session echoed at the time
    /// of the query (one sent before the coordinator's session was heard
    /// then carries it too).
    history: Arc<Mutex<Vec<Envelope<Capture>>>>,
    _queryable: bus::Declaration,
    done: Arc<AtomicBool>,
    heartbeat: Option<std::thread::JoinHandle<()>>,
}

/// Time between two heartbeat status messages.
const HEARTBEAT: Duration = Duration::from_millis(500);

impl AgentLink {
    fn open(
        bus: Arc<dyn Bus>,
        robot: &str,
        state_dir: &Path,
        describe: String,
    ) -> Result<AgentLink> {
        let seq = Arc::new(Sequence::open(state_dir, robot)?);
        let history: Arc<Mutex<Vec<Envelope<Capture>>>> = Arc::new(Mutex::new(Vec::new()));
        let session: Arc<Mutex<Option<String>>> = Arc::new(Mutex::new(None));
        let served = Arc::clone(&history);
        let now = Arc::clone(&session);
        let key = agent_key(robot, "history");
        let reply_key = key.clone();
        let queryable = bus.serve(
            &key,
            Arc::new(move || {
                let session = now.lock().map(|s| s.clone()).unwrap_or_default();
                let Ok(history) = served.lock() else {
                    return Vec::new();
                };
                history
                    .iter()
                    .filter_map(|e| {
                        let e = e.clone().in_session(session.as_deref());
                        bus::encode(&reply_key, &e)
                            .map_err(|err| tracing::warn!("{err}"))
                            .ok()
                    })
                    .collect()
            }),
        )?;
        let sessions = bus.subscribe(&session_key())?;
        let status = StatusLink {
            bus,
            robot: robot.to_owned(),
            seq,
            session,
            sessions: Arc::new(Mutex::new(sessions)),
            status: Arc::new(Mutex::new(AgentStatus {
                state: AgentState::Starting,
                good: 0,
                rejected: 0,
                published: 0,
                rotation_diversity_deg: 0.0,
                enough_data: false,
                message: describe,
            })),
        };
        let done = Arc::new(AtomicBool::new(false));
        let heartbeat = {
            let done = Arc::clone(&done);
            let status = status.clone();
            std::thread::spawn(move || {
                while !done.load(Ordering::SeqCst) {
                    status.hear_session();
                    if let Err(e) = status.publish() {
                        tracing::warn!("status heartbeat: {}", error_chain(&e));
                    }
                    std::thread::sleep(HEARTBEAT);
                }
            })
        };
        Ok(AgentLink {
            status,
            history,
            _queryable: queryable,
            done,
            heartbeat: Some(heartbeat),
        })
    }

    /// Publishes a capture and keeps it for the history queryable.
    fn publish_capture(&self, msg: Capture) -> Result<()> {
        let key = agent_key(&self.status.robot, "capture");
        let envelope = self.status.envelope(msg)?;
        let bytes = bus::encode(&key, &envelope)?;
        self.history
            .lock()
            .map_err(|_| ServiceError::Poisoned { what: "history" })?
            .push(envelope);
        self.status.bus.put(&key, bytes)?;
        Ok(())
    }
}

impl Drop for AgentLink {
    fn drop(&mut self) {
        self.done.store(true, Ordering::SeqCst);
        if let Some(h) = self.heartbeat.take() {
            let _ = h.join();
        }
    }
}

fn progress_bar(show: bool, expected: Option<u64>, robot: &str) -> indicatif::ProgressBar {
    if !show {
        return indicatif::ProgressBar::hidden();
    }
    let bar = match expected {
        Some(n) => indicatif::ProgressBar::new(n),
        None => indicatif::ProgressBar::no_length(),
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    bar.set_prefix(robot.to_owned());
    bar
}

/// A capture as published: the flange pose, the camera, and the observation
/// or the reason there is none.
fn capture_message(cap: &SourceCapture) -> Capture {
    let (observation, rejected) = match &cap.observed {
        Ok(o) => (
            Some(board_observation(
                o,
                &cap.target_centre,
                cap.target.as_deref(),
            )),
            None,
        ),
        Err(r) => (None, Some(r.reason.clone())),
    };
    Capture {
        index: cap.index,
        controller_time_s: cap.controller_time_s,
        image: cap.image.clone(),
        base_from_flange: Pose::from_isometry(&cap.base_from_flange),
        camera: Intrinsics {
            estimated: cap.intrinsics_estimated,
            ..b2b_dataset::intrinsics_of(&cap.camera, 5)
        },
        observation,
        rejected,
        base_from_target: None,
        features: cap.features.clone(),
    }
}

/// The key of an agent's drift-watch observations (`b2b/agent/{robot}/watch`):
/// the same `Capture` message as during calibration, published at the watch's
/// rate after it.
pub const WATCH_TOPIC: &str = "watch";

/// `agent watch`: publishes a still frame's observation every `period` from
/// the watch pose ([`LiveSource::watch`]) until `stop`, each with the next
/// sequence number of this robot. Returns how many were published.
pub fn run_watch(
    bus: &dyn Bus,
    robot: &str,
    state_dir: &Path,
    source: &mut b2b_live::LiveSource,
    period: Duration,
    observe: b2b_live::WatchObserve,
    stop: &AtomicBool,
) -> Result<u64> {
    b2b_protocol::messages::validate_cart_id(robot)?;
    let seq = Sequence::open(state_dir, robot)?;
    let key = agent_key(robot, WATCH_TOPIC);
    let mut published = 0u64;
    source.watch(period, observe, stop, &mut |cap| -> Result<()> {
        match (&cap.observed, &cap.features) {
            (Err(r), None) => tracing::warn!(
                "{robot}: watch frame without the target or features: {}",
                r.reason
            ),
            (Err(r), Some(_)) if observe != b2b_live::WatchObserve::Features => {
                tracing::debug!("{robot}: watch frame without the target: {}", r.reason)
            }
            _ => {}
        }
        let envelope = Envelope::new(robot, seq.take()?, capture_message(&cap));
        bus::publish(bus, &key, &envelope)?;
        published += 1;
        Ok(())
    })?;
    Ok(published)
}

/// What the capture loop has gathered.
#[derive(Default)]
struct CaptureLoop {
    observations: Option<RobotObservations>,
    flange_from_camera: Option<nalgebra::Isometry3<f64>>,
    /// The newest estimate of a camera that gave no intrinsics.
    camera: Option<b2b_calib::camera::CameraModel>,
    progress: Progress,
    published: u64,
}

impl CaptureLoop {
    fn run(
        &mut self,
        link: &AgentLink,
        opts: &AgentOptions,
        source: &mut dyn CaptureSource,
        stop: &AtomicBool,
        bar: &indicatif::ProgressBar,
    ) -> Result<()> {
        loop {
            if stop.load(Ordering::SeqCst) {
                return Err(ServiceError::InterruptedAfter {
                    captures: self.published,
                });
            }
            let started = Instant::now();
            let Some(cap) = source.next(&self.progress, stop)? else {
                return Ok(());
            };
            if let Some(camera) = self.capture(link, opts, &cap, bar)? {
                source.use_camera(&camera);
                self.camera = Some(camera);
            }
            bar.inc(1);
            let spent = started.elapsed();
            if spent < opts.pace {
                std::thread::sleep(opts.pace - spent);
            }
        }
    }

    /// One capture: published, recorded, folded into the hand-eye and the status.
    /// When the camera gave no intrinsics, returns the agent's newest estimate of
    /// them (fitted to the corners of every capture so far, then refined with
    /// the hand-eye) for the source's next detections.
    fn capture(
        &mut self,
        link: &AgentLink,
        opts: &AgentOptions,
        cap: &SourceCapture,
        bar: &indicatif::ProgressBar,
    ) -> Result<Option<b2b_calib::camera::CameraModel>> {
        let robot = &opts.robot;
        let obs = self.observations.get_or_insert_with(|| RobotObservations {
            robot: robot.clone(),
            camera: cap.camera.clone(),
            observations: vec![],
            rejected: vec![],
            detect_ms: 0.0,
            estimated_intrinsics: None,
        });
        let mut msg = capture_message(cap);
        match &cap.observed {
            Ok(o) => {
                if let Some(x) = self.flange_from_camera {
                    let t = cap.base_from_flange * x * o.camera_from_target;
                    msg.base_from_target = Some(Pose::from_isometry(&t));
                    self.progress.base_from_target.push(t);
                }
                obs.observations.push(o.clone());
                self.progress.good_poses.push(cap.base_from_flange);
            }
            Err(r) => {
                obs.rejected.push(r.clone());
            }
        }
        record(opts, cap, &msg);
        link.publish_capture(msg)?;
        self.published += 1;

        // A camera without intrinsics: fitted again to every capture's corners
        // once there are enough, before any hand-eye (one from a guessed camera
        // would put the board centimetres off).
        let mut camera = None;
        if b2b_routine::refit_intrinsics(
            cap.intrinsics_estimated,
            cap.observed.is_ok(),
            obs.observations.len(),
            b2b_pipeline::MIN_VIEWS_FOR_INTRINSICS,
        ) {
            match b2b_pipeline::estimate_intrinsics_from_observations(obs.clone()) {
                Ok(fitted) => {
                    *obs = fitted;
                    camera = Some(obs.camera.clone());
                }
                Err(e) => tracing::warn!("{robot}: {}", error_chain(&e)),
            }
        }
        let intrinsics_known = !cap.intrinsics_estimated || obs.estimated_intrinsics.is_some();
        let poses: Vec<_> = obs
            .observations
            .iter()
            .map(|o| o.board.base_from_flange)
            .collect();
        let motion = check_motions(&poses, &MotionThresholds::default());
        if b2b_routine::fit_hand_eye(motion.is_ok(), intrinsics_known)
            && let Ok(he) = hand_eye(obs, HandEyeChoice::Refined, &opts.refine)
        {
            if cap.intrinsics_estimated {
                camera = Some(he.estimate.camera.clone());
            }
            self.flange_from_camera = Some(he.estimate.flange_from_camera);
            let update = HandEyeUpdate {
                flange_from_camera: he.result.flange_from_camera,
                covariance: he.result.covariance,
                captures_used: obs.observations.len(),
                reprojection_rms_px: he.result.reprojection_rms_px,
            };
            self.progress.hand_eye = Some(update.clone());
            if let Err(e) = opts.rerun.log_hand_eye(
                b2b_viz::Base::One,
                &he.estimate.flange_from_camera,
                &b2b_dataset::intrinsics_of(&cap.camera, 5),
            ) {
                tracing::warn!("rerun: {}", error_chain(&e));
            }
            link.status.send("hand_eye", update)?;
        }
        self.progress.good = obs.observations.len();
        self.progress.rejected = obs.rejected.len();
        let (good, rejected, published) =
            (self.progress.good, self.progress.rejected, self.published);
        link.status.update(|s| {
            s.state = AgentState::Capturing;
            s.good = good;
            s.rejected = rejected;
            s.published = published;
            s.rotation_diversity_deg = motion.as_ref().map_or(0.0, |m| m.max_axis_angle_deg);
            s.enough_data = b2b_routine::enough_data(motion.is_ok(), good);
            s.message = match &cap.observed {
                Ok(_) => format!("capture {}: board found", cap.index),
                Err(r) => format!("capture {} rejected: {}", cap.index, r.reason),
            };
            bar.set_message(format!(
                "good {} rejected {} diversity {:.0} deg {}",
                s.good,
                s.rejected,
                s.rotation_diversity_deg,
                if s.enough_data {
                    "enough data"
                } else {
                    "need more data"
                }
            ));
        })?;
        if let Err(r) = &cap.observed {
            bar.println(format!(
                "{robot}: capture {} rejected: {}",
                cap.index, r.reason
            ));
        }
        link.status.publish()?;
        Ok(camera)
    }
}

/// Logs a capture (and its image, when the source has it) to the recording.
fn record(opts: &AgentOptions, cap: &SourceCapture, msg: &Capture) {
    if !opts.rerun.is_enabled() {
        return;
    }
    let base = b2b_viz::Base::One;
    let logged = opts
        .rerun
        .log_capture(base, msg)
        .and_then(|()| match &cap.pixels {
            Some(p) => opts.rerun.log_image(
                base,
                b2b_viz::ImageView {
                    pixels: p,
                    width: cap.camera.width,
                    height: cap.camera.height,
                    format: b2b_viz::PixelFormat::Gray,
                },
            ),
            None => Ok(()),
        });
    if let Err(e) = logged {
        tracing::warn!("rerun: {}", error_chain(&e));
    }
}

/// The coordinator's answers to a run: its result, or the reason its solve
/// failed.
#[derive(Clone, Copy)]
struct Answers<'a> {
    results: &'a dyn bus::Inbox,
    failures: &'a dyn bus::Inbox,
}

/// What the coordinator answered.
#[derive(Debug, Clone, PartialEq)]
enum Answer {
    Result(Box<CalibrationResult>),
    /// The run's solve failed, for this reason.
    Failed(String),
    /// Nothing within the wait (or stopped).
    None,
}

/// How long an agent waits for a coordinator's session before it says it
/// hears none (and what its endpoints answer), once.
pub const NO_COORDINATOR_WARNING: Duration = Duration::from_secs(5);

/// The next message of `inbox` within 50 ms when it is valid and of the
/// session this agent echoes (`what` names it in the log); an invalid one, or
/// one of another session, is logged and gives `Ok(None)`. `Err` when the
/// inbox itself failed (logged).
fn take_ours<T: serde::de::DeserializeOwned + b2b_protocol::messages::Validate>(
    inbox: &dyn bus::Inbox,
    link: &StatusLink,
    what: &str,
) -> Result<Option<T>, ()> {
    match inbox.recv_timeout(Duration::from_millis(50)) {
        Ok(Some(m)) => match bus::decode::<T>(&m.key, &m.payload) {
            Ok(envelope) => Ok(link
                .ours(envelope.session.as_deref(), what)
                .then_some(envelope.body)),
            Err(reason) => {
                crate::warn_limited(&m.key, &format!("ignored a {what} message: {reason}"));
                Ok(None)
            }
        },
        Ok(None) => Ok(None),
        Err(e) => {
            tracing::warn!("{e}");
            Err(())
        }
    }
}

/// The coordinator's result or failure, validated and of the session this
/// agent echoes, or [`Answer::None`] when `wait` passed (or `stop` was set)
/// without one. Invalid messages, and answers of another session or of none,
/// are logged and ignored. With no session heard after
/// [`NO_COORDINATOR_WARNING`], says so once, with why.
fn wait_for_result(
    answers: Answers<'_>,
    link: &StatusLink,
    wait: Duration,
    stop: &AtomicBool,
) -> Answer {
    let started = Instant::now();
    let deadline = started + wait;
    let mut warned = false;
    while Instant::now() < deadline && !stop.load(Ordering::SeqCst) {
        if !warned && started.elapsed() >= NO_COORDINATOR_WARNING {
            warned = true;
            link.hear_session();
            if link.session().ok().flatten().is_none() {
                eprintln!(
                    "{}: no coordinator heard yet: {}",
                    link.robot,
                    link.bus
                        .unreached()
                        .unwrap_or_else(|| "connected, but no session announced".into())
                );
            }
        }
        // Each inbox waits half the loop's 100 ms, so neither delays the other.
        match take_ours::<CalibrationResult>(answers.results, link, "result") {
            Ok(Some(result)) => return Answer::Result(Box::new(result)),
            Ok(None) => {}
            Err(()) => return Answer::None,
        }
        match take_ours::<RunFailure>(answers.failures, link, "failure") {
            Ok(Some(failure)) => return Answer::Failed(failure.reason),
            Ok(None) => {}
            Err(()) => return Answer::None,
        }
    }
    Answer::None
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_protocol::messages::COORDINATOR;

    /// An agent takes a result only from the coordinator's key and only in the
    /// session it echoes: a result in no session, in another session, or
    /// before any session was heard is ignored; the session's own is taken.
    /// Its own messages carry the session from the announcement on.
    #[test]
    fn results_are_taken_only_in_the_echoed_session() {
        let dir = tempfile::tempdir().unwrap();
        let bus = Arc::new(bus::MemoryBus::new());
        let mine = bus.subscribe(&agent_key("robot1", "**")).unwrap();
        let results = bus.subscribe(&result_key()).unwrap();
        let failures = bus.subscribe(&failure_key()).unwrap();
        let answers = Answers {
            results: &*results,
            failures: &*failures,
        };
        let link = AgentLink::open(bus.clone(), "robot1", dir.path(), "test".into()).unwrap();
        let result: CalibrationResult =
            serde_json::from_str(include_str!("../../report/tests/fixtures/RESULT.json")).unwrap();
        let ours = "0123456789abcdef0123456789abcdef";
        let theirs = "fedcba9876543210fedcba9876543210";
        let put_result = |session: Option<&str>, tx: f64| {
            let mut r = result.clone();
            r.base1_from_base2.t[0] = tx;
            let e = Envelope::new(COORDINATOR, 1, r).in_session(session);
            bus::publish(&*bus, &result_key(), &e).unwrap();
        };
        let stop = AtomicBool::new(false);
        let wait = Duration::from_millis(300);
        // Nothing heard yet: even a well-formed result is not this agent's.
        put_result(Some(ours), 1.0);
        assert_eq!(
            wait_for_result(answers, &link.status, wait, &stop),
            Answer::None
        );
        let announce = Envelope::new(
            COORDINATOR,
            2,
            SessionAnnouncement {
                session: ours.into(),
            },
        );
        bus::publish(&*bus, &session_key(), &announce).unwrap();
        put_result(None, 2.0);
        put_result(Some(theirs), 3.0);
        put_result(Some(ours), 4.0);
        let Answer::Result(got) =
            wait_for_result(answers, &link.status, Duration::from_secs(2), &stop)
        else {
            panic!("no result taken");
        };
        assert_eq!(got.base1_from_base2.t[0], 4.0);
        // The agent's own messages echo the session now.
        link.status.publish().unwrap();
        let mut echoed = None;
        while let Some(m) = mine.recv_timeout(Duration::from_millis(100)).unwrap() {
            let e: Envelope<serde_json::Value> = serde_json::from_slice(&m.payload).unwrap();
            echoed = e.session;
        }
        assert_eq!(echoed.as_deref(), Some(ours));
    }

    /// A failed solve of the echoed session ends the wait with its reason;
    /// one of another session, or a forged one with control characters, is
    /// ignored.
    #[test]
    fn a_failure_of_the_echoed_session_ends_the_wait_with_its_reason() {
        let dir = tempfile::tempdir().unwrap();
        let bus = Arc::new(bus::MemoryBus::new());
        let results = bus.subscribe(&result_key()).unwrap();
        let failures = bus.subscribe(&failure_key()).unwrap();
        let answers = Answers {
            results: &*results,
            failures: &*failures,
        };
        let link = AgentLink::open(bus.clone(), "robot1", dir.path(), "test".into()).unwrap();
        let ours = "0123456789abcdef0123456789abcdef";
        let announce = Envelope::new(
            COORDINATOR,
            1,
            SessionAnnouncement {
                session: ours.into(),
            },
        );
        bus::publish(&*bus, &session_key(), &announce).unwrap();
        let fail = |session: &str, reason: &str| {
            let e = Envelope::new(
                COORDINATOR,
                2,
                RunFailure {
                    reason: reason.into(),
                },
            )
            .in_session(Some(session));
            bus::publish(&*bus, &failure_key(), &e).unwrap();
        };
        fail("fedcba9876543210fedcba9876543210", "not yours");
        fail(ours, "escape \u{1b}[2J");
        fail(ours, "need two robots, heard from 1");
        let stop = AtomicBool::new(false);
        assert_eq!(
            wait_for_result(answers, &link.status, Duration::from_secs(5), &stop),
            Answer::Failed("need two robots, heard from 1".into())
        );
    }

    #[test]
    fn sequence_continues_across_restarts() {
        let dir = tempfile::tempdir().unwrap();
        let s = Sequence::open(dir.path(), "robot1").unwrap();
        assert_eq!(s.take().unwrap(), 1);
        assert_eq!(s.take().unwrap(), 2);
        drop(s);
        let s = Sequence::open(dir.path(), "robot1").unwrap();
        assert_eq!(s.take().unwrap(), 3);
        std::fs::write(dir.path().join("agent-robot2.seq"), "x").unwrap();
        let err = Sequence::open(dir.path(), "robot2")
            .unwrap_err()
            .to_string();
        assert!(err.contains("agent-robot2.seq"), "{err}");
    }
}
