//! The coordinator's memory: every accepted sample, appended to a journal on disk
//! (and flushed to the device) before it is used, so a restarted coordinator
//! resumes with all of them.
//!
//! The journal is one JSON object per line. A crash can leave a partial last
//! line; loading reports it and ignores it (that sample had not been used, and the
//! agents still have it in their history).
//!
//! What the coordinator decides while it gathers (which messages are this
//! run's, whose history to ask again, when the run is done) is [`gathering`].

use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use b2b_calib::refine::BoardCapture;
use b2b_pipeline::{Observation, RobotObservations};
use b2b_protocol::RejectedCapture;
use b2b_protocol::messages::{AgentState, AgentStatus, Capture, Envelope, HandEyeUpdate};
use nalgebra::{Point2, Point3};
use serde::{Deserialize, Serialize};

pub mod gathering;

/// What the store could not do, with the cause kept as the source.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("cannot {action} {}", path.display())]
    Io {
        action: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{}: line {line}", path.display())]
    Line {
        path: PathBuf,
        line: usize,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot encode a sample for the journal")]
    Encode(#[source] serde_json::Error),
    #[error("no usable captures from robot '{robot}'")]
    NoCaptures { robot: String },
    #[error("no usable capture from {robots:?}")]
    NoneFrom { robots: Vec<String> },
    #[error(
        "robot '{robot}' capture {index} reports the target centre at {at:?}, robot \
         '{first_robot}' capture {first_index} at {first_at:?}: are the agents configured \
         with the same target?"
    )]
    CentresDisagree {
        robot: String,
        index: u64,
        at: [f64; 3],
        first_robot: String,
        first_index: u64,
        first_at: [f64; 3],
    },
    #[error("robot '{robot}': camera")]
    Camera {
        robot: String,
        #[source]
        source: b2b_calib::CalibError,
    },
    #[error("robot '{robot}' capture {index}: {field}")]
    Pose {
        robot: String,
        index: u64,
        field: &'static str,
        #[source]
        source: b2b_protocol::ProtocolError,
    },
    #[error("robot '{robot}' capture {index}: features")]
    Features {
        robot: String,
        index: u64,
        #[source]
        source: Box<b2b_pipeline::PipelineError>,
    },
    #[error("robot '{robot}': the intrinsics from the published corners")]
    Intrinsics {
        robot: String,
        #[source]
        source: Box<b2b_pipeline::PipelineError>,
    },
}

fn io(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> StoreError {
    let path = path.to_path_buf();
    move |source| StoreError::Io {
        action,
        path,
        source,
    }
}

/// The number of `target` (`None`: the main one, 0) among `further`, the
/// further targets seen ([`Store::further_targets`]).
fn target_number(further: &std::collections::BTreeSet<String>, target: Option<&str>) -> usize {
    target.map_or(0, |id| {
        1 + further.iter().take_while(|t| t.as_str() != id).count()
    })
}

/// Everything the coordinator keeps.
// Most samples are captures, each moved once into the store: boxing them
// would add an allocation to the common case to save stack on the rare one.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Sample {
    Capture(Envelope<Capture>),
    Status(Envelope<AgentStatus>),
    HandEye(Envelope<HandEyeUpdate>),
}

/// A capture's pose as an isometry, or which one of which capture was not one.
fn pose(
    robot: &str,
    index: u64,
    field: &'static str,
    pose: &b2b_protocol::Pose,
) -> Result<nalgebra::Isometry3<f64>, StoreError> {
    pose.to_isometry(field).map_err(|source| StoreError::Pose {
        robot: robot.to_owned(),
        index,
        field,
        source,
    })
}

/// The 1-based row a capture index is reported as (an index near `u64::MAX`,
/// which no agent sends but anyone can, saturates).
fn row_of(index: u64) -> usize {
    usize::try_from(index)
        .unwrap_or(usize::MAX)
        .saturating_add(1)
}

/// The journal file name inside the state folder.
pub const JOURNAL: &str = "samples.jsonl";

/// The journal line's field naming the certificate that signed the sample.
pub const SIGNER_FIELD: &str = "signer";

/// What became of a sample offered to the store.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Arrival {
    /// Kept and used.
    New,
    /// The same as one held (a re-send, a catch-up): dropped.
    Duplicate,
    /// A capture whose index is held with different content: journaled and
    /// counted, and that index is used by neither version.
    Conflict,
}

/// Samples by robot, de-duplicated.
#[derive(Debug)]
pub struct Store {
    path: PathBuf,
    journal: File,
    captures: BTreeMap<String, BTreeMap<u64, Capture>>,
    /// Captures that arrived with an index already held but other content, by
    /// robot and index: no version of such an index is used (which one is the
    /// robot's cannot be told from the bus), and the result lists it.
    conflicts: BTreeMap<String, BTreeMap<u64, Vec<Capture>>>,
    status: BTreeMap<String, (u64, AgentStatus)>,
    hand_eye: BTreeMap<String, (u64, HandEyeUpdate)>,
    /// By robot, the most captures its `history` has served in one answer
    /// ([`Store::history_served`]): a status claiming more is not believed.
    served: BTreeMap<String, u64>,
    /// Lines of the journal that could not be read back (a crash mid-write).
    pub skipped_lines: usize,
}

impl Store {
    /// Opens (or creates) the journal in `dir` and replays it.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        std::fs::create_dir_all(dir).map_err(io("create state folder", dir))?;
        let path = dir.join(JOURNAL);
        let mut store = Store {
            journal: OpenOptions::new()
                .create(true)
                .append(true)
                .open(&path)
                .map_err(io("open", &path))?,
            path: path.clone(),
            captures: BTreeMap::new(),
            conflicts: BTreeMap::new(),
            status: BTreeMap::new(),
            hand_eye: BTreeMap::new(),
            served: BTreeMap::new(),
            skipped_lines: 0,
        };
        // A partial last line (crash mid-write) must not swallow the next sample.
        let bytes = std::fs::read(&path).map_err(io("read", &path))?;
        if bytes.last().is_some_and(|b| *b != b'\n') {
            store
                .journal
                .write_all(b"\n")
                .map_err(io("append to", &path))?;
        }
        let reader = BufReader::new(bytes.as_slice());
        for (i, line) in reader.lines().enumerate() {
            let line = line.map_err(|source| StoreError::Line {
                path: path.clone(),
                line: i + 1,
                source,
            })?;
            if line.trim().is_empty() {
                continue;
            }
            match serde_json::from_str::<Sample>(&line) {
                Ok(sample) => {
                    store.apply(sample);
                }
                Err(e) => {
                    tracing::warn!("{}: line {} ignored: {e}", path.display(), i + 1);
                    store.skipped_lines += 1;
                }
            }
        }
        Ok(store)
    }

    /// What a sample adds: a capture not yet held, a newer status; or a capture
    /// held with other content (a conflict, unless that version is known).
    fn classify(&self, sample: &Sample) -> Arrival {
        let new = |is: bool| if is { Arrival::New } else { Arrival::Duplicate };
        match sample {
            Sample::Capture(e) => {
                let Some(held) = self
                    .captures
                    .get(&e.robot)
                    .and_then(|m| m.get(&e.body.index))
                else {
                    return Arrival::New;
                };
                let known = held == &e.body
                    || self
                        .conflicts
                        .get(&e.robot)
                        .and_then(|m| m.get(&e.body.index))
                        .is_some_and(|v| v.contains(&e.body));
                if known {
                    Arrival::Duplicate
                } else {
                    Arrival::Conflict
                }
            }
            // A newer status, or any status when the one held is contradicted
            // by the captures that arrived or claims more than the robot's
            // history holds (a forged or stale status must not outrank the
            // robot's own by its sequence number). A robot finished with
            // every capture held stays so: only a newer status that finishes
            // it as well replaces that one.
            Sample::Status(e) => new(match self.status.get(&e.robot) {
                None => true,
                Some((_, s)) if s == &e.body => false,
                Some((seq, s)) if self.finished(&e.robot, s) => {
                    e.seq > *seq && self.finished(&e.robot, &e.body)
                }
                Some((seq, s)) => {
                    e.seq > *seq || self.contradicted(&e.robot, s) || self.overclaims(&e.robot, s)
                }
            }),
            Sample::HandEye(e) => new(self
                .hand_eye
                .get(&e.robot)
                .is_none_or(|(seq, _)| e.seq > *seq)),
        }
    }

    /// Classifies a sample and keeps it accordingly.
    fn apply(&mut self, sample: Sample) -> Arrival {
        let arrival = self.classify(&sample);
        self.keep(sample, arrival);
        arrival
    }

    /// Keeps a sample already classified as `arrival`.
    fn keep(&mut self, sample: Sample, arrival: Arrival) {
        match (arrival, sample) {
            (Arrival::Duplicate, _) => {}
            (Arrival::Conflict, Sample::Capture(e)) => {
                tracing::warn!(
                    "robot '{}' capture {}: a second, different capture with this index \
                     (envelope seq {}); neither is used",
                    e.robot,
                    e.body.index,
                    e.seq
                );
                self.conflicts
                    .entry(e.robot)
                    .or_default()
                    .entry(e.body.index)
                    .or_default()
                    .push(e.body);
            }
            (_, Sample::Capture(e)) => {
                self.captures
                    .entry(e.robot)
                    .or_default()
                    .insert(e.body.index, e.body);
            }
            (_, Sample::Status(e)) => {
                self.status.insert(e.robot, (e.seq, e.body));
            }
            (_, Sample::HandEye(e)) => {
                self.hand_eye.insert(e.robot, (e.seq, e.body));
            }
        }
    }

    /// Keeps a sample: written and flushed to the journal first (a conflicting
    /// capture too: nothing that arrived is lost), then used.
    pub fn accept(&mut self, sample: Sample) -> Result<Arrival, StoreError> {
        self.accept_from(sample, None)
    }

    /// [`Store::accept`], the journal line also naming who sent the sample:
    /// on the secured bus, the certificate that signed it (`"signer"`).
    pub fn accept_from(
        &mut self,
        sample: Sample,
        signer: Option<&str>,
    ) -> Result<Arrival, StoreError> {
        let arrival = self.classify(&sample);
        if arrival == Arrival::Duplicate {
            return Ok(arrival);
        }
        let mut value = serde_json::to_value(&sample).map_err(StoreError::Encode)?;
        if let (Some(signer), Some(fields)) = (signer, value.as_object_mut()) {
            fields.insert(SIGNER_FIELD.into(), signer.into());
        }
        let mut line = serde_json::to_vec(&value).map_err(StoreError::Encode)?;
        line.push(b'\n');
        self.journal
            .write_all(&line)
            .and_then(|_| self.journal.sync_data())
            .map_err(io("append to", &self.path))?;
        self.keep(sample, arrival);
        Ok(arrival)
    }

    /// The robots heard from, in id order.
    pub fn robots(&self) -> Vec<String> {
        let mut ids: Vec<String> = self
            .status
            .keys()
            .chain(self.captures.keys())
            .cloned()
            .collect();
        ids.sort();
        ids.dedup();
        ids
    }

    /// Captures held for a robot.
    pub fn capture_count(&self, robot: &str) -> u64 {
        self.captures.get(robot).map_or(0, |m| m.len() as u64)
    }

    /// Of the first `published` capture indices of a robot, how many are held.
    /// An agent numbers its captures 0, 1, ...: what its status claims is
    /// checked against these, so a stray index (999) neither completes nor
    /// stalls a robot.
    fn held_of(&self, robot: &str, published: u64) -> u64 {
        self.captures
            .get(robot)
            .map_or(0, |m| m.range(..published).count() as u64)
    }

    /// How many captures a robot has demonstrably published: indices 0, 1, ...
    /// held without a gap.
    fn contiguous(&self, robot: &str) -> u64 {
        let Some(m) = self.captures.get(robot) else {
            return 0;
        };
        m.keys()
            .zip(0u64..)
            .take_while(|(index, expected)| *index == expected)
            .count() as u64
    }

    /// A status that says fewer captures were published than have arrived.
    fn contradicted(&self, robot: &str, s: &AgentStatus) -> bool {
        s.published < self.contiguous(robot)
    }

    /// Records that `robot`'s `history` queryable, asked, served `captures`
    /// valid captures of this run. The robot's own statuses never claim more
    /// than its history holds.
    pub fn history_served(&mut self, robot: &str, captures: u64) {
        let most = self.served.entry(robot.to_owned()).or_default();
        *most = (*most).max(captures);
    }

    /// A status that claims more captures than the robot's history has
    /// served and than have arrived (a forged or stale count: the robot's own
    /// history holds every capture it published). `None` before its history
    /// was asked.
    fn overclaims(&self, robot: &str, s: &AgentStatus) -> bool {
        self.served
            .get(robot)
            .is_some_and(|served| s.published > (*served).max(self.contiguous(robot)))
    }

    /// What a robot's history has served at most, once asked.
    pub fn served(&self, robot: &str) -> Option<u64> {
        self.served.get(robot).copied()
    }

    /// Captures with conflicting versions, over all robots.
    pub fn conflict_count(&self) -> usize {
        self.conflicts.values().map(BTreeMap::len).sum()
    }

    /// A robot's captures that may be used, and the reason each other one is
    /// not: an index with conflicting versions, or (once the robot finished) an
    /// index beyond the captures it says it published.
    fn usable(&self, robot: &str) -> (Vec<(u64, &Capture)>, Vec<RejectedCapture>) {
        let finished = self
            .status(robot)
            .filter(|s| s.state == AgentState::Finished)
            .map(|s| s.published);
        let conflicts = self.conflicts.get(robot);
        let mut usable = Vec::new();
        let mut left_out = Vec::new();
        for (index, cap) in self.captures.get(robot).into_iter().flatten() {
            let reason = if let Some(v) = conflicts.and_then(|m| m.get(index)) {
                Some(format!(
                    "conflict: {} different captures arrived with index {index}; neither is used",
                    v.len() + 1
                ))
            } else {
                finished.filter(|p| index >= p).map(|published| {
                    format!(
                        "index {index} is beyond the {published} captures robot '{robot}' says it published"
                    )
                })
            };
            match reason {
                Some(reason) => left_out.push(RejectedCapture {
                    robot: robot.to_owned(),
                    image: cap.image.clone(),
                    row: Some(row_of(*index)),
                    reason,
                }),
                None => usable.push((*index, cap)),
            }
        }
        (usable, left_out)
    }

    pub fn status(&self, robot: &str) -> Option<&AgentStatus> {
        self.status.get(robot).map(|(_, s)| s)
    }

    /// Robots whose status says they published captures that are not held.
    pub fn missing(&self) -> Vec<String> {
        self.status
            .iter()
            .filter(|(robot, (_, s))| s.published > self.held_of(robot, s.published))
            .map(|(r, _)| r.clone())
            .collect()
    }

    /// Who the coordinator is still waiting for, one phrase per robot not yet done
    /// ("robot2: not heard from", "robot1: capturing, 12 captures held"): the
    /// `expected` ids, or those heard from, padded with "N more robots" to `robots`.
    pub fn waiting_for(&self, expected: Option<&[String]>, robots: usize) -> Vec<String> {
        let heard = self.robots();
        let ids: Vec<String> = match expected {
            Some(ids) => ids.to_vec(),
            None => heard.clone(),
        };
        let mut out: Vec<String> = ids
            .iter()
            .filter_map(|r| {
                let held = self.capture_count(r);
                match self.status(r) {
                    None if held == 0 => Some(format!("{r}: not heard from")),
                    None => Some(format!("{r}: no status yet, {held} captures held")),
                    Some(s) if self.finished(r, s) => None,
                    Some(s) if self.contradicted(r, s) => Some(format!(
                        "{r}: its status says {} published, but {} arrived (a stale or forged \
                         status; waiting for one that agrees)",
                        s.published,
                        self.contiguous(r)
                    )),
                    Some(s) if self.overclaims(r, s) => Some(format!(
                        "{r}: its status says {} published, but its history holds {} (a stale \
                         or forged status; waiting for one that agrees)",
                        s.published,
                        self.served(r).unwrap_or_default()
                    )),
                    Some(s) if s.state == AgentState::Finished => Some(format!(
                        "{r}: finished, {} of its {} captures held (asking for the rest)",
                        self.held_of(r, s.published),
                        s.published
                    )),
                    Some(s) => Some(format!(
                        "{r}: {}, {held} captures held",
                        format!("{:?}", s.state).to_lowercase()
                    )),
                }
            })
            .collect();
        if expected.is_none() && heard.len() < robots {
            let more = robots - heard.len();
            out.push(format!(
                "{more} more robot{} not heard from",
                if more == 1 { "" } else { "s" }
            ));
        }
        out
    }

    /// Finished, every capture it says it published held, and no more than
    /// that arrived.
    fn finished(&self, robot: &str, s: &AgentStatus) -> bool {
        s.state == AgentState::Finished
            && self.held_of(robot, s.published) == s.published
            && !self.contradicted(robot, s)
    }

    /// The `expected` robots (or at least `robots` of those heard from) all
    /// finished, with every capture held. A robot not expected (a stray or
    /// forged id) is not waited for.
    pub fn complete(&self, expected: Option<&[String]>, robots: usize) -> bool {
        let ids = match expected {
            Some(ids) => ids.to_vec(),
            None => self.robots(),
        };
        ids.len() >= robots
            && ids
                .iter()
                .all(|r| self.status(r).is_some_and(|s| self.finished(r, s)))
    }

    /// The centre of the target (in its frame) the agents of `robots` report
    /// with their observations: the same point for every capture, or an error
    /// naming the first disagreement (the agents would be looking at different
    /// targets). Captures from agents that do not report it fall back to the
    /// mean of every distinct corner seen, with a warning.
    pub fn target_centre(&self, robots: &[&str]) -> Result<Point3<f64>, StoreError> {
        // With several targets, the first of them any of these robots saw
        // (the main target when seen: the pipeline numbers them so).
        let main_seen = robots.iter().any(|r| {
            self.usable(r)
                .0
                .iter()
                .any(|(_, c)| c.observation.as_ref().is_some_and(|o| o.target.is_none()))
        });
        let first = if main_seen {
            None
        } else {
            self.further_targets(robots).into_iter().next()
        };
        let mut reported: Option<(String, u64, [f64; 3])> = None;
        let mut missing = 0usize;
        for robot in robots {
            for (index, cap) in self.usable(robot).0 {
                let Some(o) = cap.observation.as_ref().filter(|o| o.target == first) else {
                    continue;
                };
                match (&reported, o.target_centre) {
                    (_, None) => missing += 1,
                    (None, Some(c)) => reported = Some((robot.to_string(), index, c)),
                    (Some((r0, i0, c0)), Some(c)) => {
                        let d = (0..3).map(|k| (c[k] - c0[k]).powi(2)).sum::<f64>().sqrt();
                        if d >= 1e-9 {
                            return Err(StoreError::CentresDisagree {
                                robot: robot.to_string(),
                                index,
                                at: c,
                                first_robot: r0.clone(),
                                first_index: *i0,
                                first_at: *c0,
                            });
                        }
                    }
                }
            }
        }
        if let Some((_, _, c)) = reported {
            if missing > 0 {
                tracing::warn!(
                    "{missing} observation(s) without a target centre; using the reported one"
                );
            }
            return Ok(Point3::from(c));
        }
        // Only agents that report no centre at all get here: the corners seen.
        let mut seen: Vec<[f64; 3]> = Vec::new();
        for robot in robots {
            let (caps, _) = self.usable(robot);
            for p in caps
                .iter()
                .flat_map(|(_, c)| c.observation.iter().flat_map(|o| &o.target_points))
            {
                if !seen.contains(p) {
                    seen.push(*p);
                }
            }
        }
        if seen.is_empty() {
            return Err(StoreError::NoneFrom {
                robots: robots.iter().map(|r| r.to_string()).collect(),
            });
        }
        tracing::warn!(
            "the agents do not report the target centre; using the mean of the {} distinct corners seen",
            seen.len()
        );
        let sum = seen.iter().fold(nalgebra::Vector3::zeros(), |a, p| {
            a + nalgebra::Vector3::from(*p)
        });
        Ok(Point3::from(sum / seen.len() as f64))
    }

    /// The further targets (by id) the captures of `robots` saw, in order:
    /// an observation of target `id` is numbered 1 + its place here, one of
    /// the main target 0 ([`target_number`]), as the pipeline numbers a
    /// dataset's.
    fn further_targets(&self, robots: &[&str]) -> std::collections::BTreeSet<String> {
        robots
            .iter()
            .flat_map(|r| self.usable(r).0)
            .filter_map(|(_, c)| c.observation.as_ref()?.target.clone())
            .collect()
    }

    /// A robot's captures as the pipeline takes them; with several targets
    /// each observation's target numbered over every robot's (see
    /// [`Store::further_targets`]).
    pub fn observations(&self, robot: &str) -> Result<RobotObservations, StoreError> {
        let robots = self.robots();
        let names: Vec<&str> = robots.iter().map(String::as_str).collect();
        let further = self.further_targets(&names);
        let (caps, mut rejected) = self.usable(robot);
        let (_, first) = caps.first().ok_or_else(|| StoreError::NoCaptures {
            robot: robot.to_owned(),
        })?;
        let c = &first.camera;
        let camera =
            b2b_dataset::camera_model(&first.camera).map_err(|source| StoreError::Camera {
                robot: robot.to_owned(),
                source,
            })?;
        let mut observations = Vec::new();
        for (index, cap) in &caps {
            // A camera without intrinsics: each capture carries the agent's
            // estimate of its time; all of them are fitted again below.
            let same = if c.estimated {
                cap.camera.estimated && (cap.camera.width, cap.camera.height) == (c.width, c.height)
            } else {
                cap.camera == *c
            };
            if !same {
                rejected.push(RejectedCapture {
                    robot: robot.to_owned(),
                    image: cap.image.clone(),
                    row: Some(row_of(*index)),
                    reason: if c.estimated != cap.camera.estimated {
                        format!(
                            "the camera gave {} intrinsics on this capture and {} on the robot's \
                             first: one camera cannot be both",
                            if cap.camera.estimated { "no" } else { "its" },
                            if c.estimated { "none" } else { "its own" },
                        )
                    } else if c.estimated {
                        format!(
                            "image size {}x{}, the robot's first capture's is {}x{}",
                            cap.camera.width, cap.camera.height, c.width, c.height
                        )
                    } else {
                        "camera intrinsics differ from the robot's first capture".into()
                    },
                });
                continue;
            }
            match (&cap.observation, &cap.rejected) {
                (Some(o), _) => observations.push(Observation {
                    row: row_of(*index),
                    image: cap.image.clone(),
                    camera_from_target: pose(
                        robot,
                        *index,
                        "T_camera_target",
                        &o.camera_from_target,
                    )?,
                    board: BoardCapture {
                        base_from_flange: pose(
                            robot,
                            *index,
                            "T_base_flange",
                            &cap.base_from_flange,
                        )?,
                        target_points: o.target_points.iter().map(|p| Point3::from(*p)).collect(),
                        pixels: o.pixels.iter().map(|p| Point2::from(*p)).collect(),
                        target: target_number(&further, o.target.as_deref()),
                    },
                    pnp_rms_px: o.rms_px,
                    residuals_px: o.residuals_px.clone(),
                }),
                (None, reason) => rejected.push(RejectedCapture {
                    robot: robot.to_owned(),
                    image: cap.image.clone(),
                    row: Some(row_of(*index)),
                    reason: reason.clone().unwrap_or_default(),
                }),
            }
        }
        let obs = RobotObservations {
            robot: robot.to_owned(),
            camera,
            observations,
            rejected,
            detect_ms: 0.0,
            estimated_intrinsics: None,
        };
        if !c.estimated {
            return Ok(obs);
        }
        let obs = b2b_pipeline::estimate_intrinsics_from_observations(obs).map_err(|source| {
            StoreError::Intrinsics {
                robot: robot.to_owned(),
                source: Box::new(source),
            }
        })?;
        if let Some(e) = &obs.estimated_intrinsics {
            tracing::info!(
                robot,
                fx = obs.camera.fx,
                fy = obs.camera.fy,
                cx = obs.camera.cx,
                cy = obs.camera.cy,
                images = e.images_used,
                rms_px = e.rms_px,
                "the camera gave no intrinsics: fitted to the published corners"
            );
        }
        Ok(obs)
    }

    /// A robot's published feature sets as the RGB-D method takes them; captures
    /// without features (no depth, or the agent was not asked) are returned as
    /// rejected with that reason.
    pub fn rgbd_views(
        &self,
        robot: &str,
    ) -> Result<(Vec<b2b_pipeline::rgbd::RgbdView>, Vec<RejectedCapture>), StoreError> {
        let (caps, mut rejected) = self.usable(robot);
        if caps.is_empty() {
            return Err(StoreError::NoCaptures {
                robot: robot.to_owned(),
            });
        }
        let mut views = Vec::new();
        for (index, cap) in caps {
            let row = row_of(index);
            let Some(set) = &cap.features else {
                rejected.push(RejectedCapture {
                    robot: robot.to_owned(),
                    image: cap.image.clone(),
                    row: Some(row),
                    reason: "no features published (no depth image, or the agent ran without --features)"
                        .into(),
                });
                continue;
            };
            let view = b2b_pipeline::rgbd::RgbdView::from_feature_set(
                row,
                cap.image.clone().unwrap_or_default(),
                pose(robot, index, "T_base_flange", &cap.base_from_flange)?,
                set,
            )
            .map_err(|source| StoreError::Features {
                robot: robot.to_owned(),
                index,
                source: Box::new(source),
            })?;
            views.push(view);
        }
        Ok((views, rejected))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_protocol::Pose;
    use b2b_protocol::messages::{BoardObservation, Intrinsics};

    pub(crate) fn capture(index: u64) -> Capture {
        Capture {
            index,
            controller_time_s: None,
            image: None,
            base_from_flange: Pose::IDENTITY,
            camera: Intrinsics {
                width: 640,
                height: 480,
                fx: 600.0,
                fy: 600.0,
                cx: 320.0,
                cy: 240.0,
                dist: vec![],
                estimated: false,
            },
            observation: Some(BoardObservation {
                target_points: vec![[0.0; 3]; 4],
                pixels: vec![[1.0, 1.0]; 4],
                camera_from_target: Pose::IDENTITY,
                residuals_px: vec![0.0; 4],
                rms_px: 0.0,
                target_centre: None,
                target: None,
            }),
            rejected: None,
            base_from_target: None,
            features: None,
        }
    }

    pub(crate) fn status(state: AgentState, published: u64) -> AgentStatus {
        AgentStatus {
            state,
            good: published as usize,
            rejected: 0,
            published,
            rotation_diversity_deg: 0.0,
            enough_data: false,
            message: String::new(),
        }
    }

    fn with_centre(index: u64, centre: Option<[f64; 3]>, corner: [f64; 3]) -> Capture {
        let mut c = capture(index);
        if let Some(o) = &mut c.observation {
            o.target_centre = centre;
            o.target_points = vec![corner; 4];
        }
        c
    }

    #[test]
    fn says_whom_it_waits_for() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        assert_eq!(s.waiting_for(None, 2), ["2 more robots not heard from"]);
        let ids = ["robot1".to_owned(), "robot2".to_owned()];
        assert_eq!(
            s.waiting_for(Some(&ids), 2),
            ["robot1: not heard from", "robot2: not heard from"]
        );
        s.accept(Sample::Capture(Envelope::new("robot1", 1, capture(0))))
            .unwrap();
        s.accept(Sample::Status(Envelope::new(
            "robot1",
            2,
            status(AgentState::Capturing, 1),
        )))
        .unwrap();
        s.accept(Sample::Status(Envelope::new(
            "robot2",
            1,
            status(AgentState::Finished, 3),
        )))
        .unwrap();
        assert_eq!(
            s.waiting_for(Some(&ids), 2),
            [
                "robot1: capturing, 1 captures held",
                "robot2: finished, 0 of its 3 captures held (asking for the rest)"
            ]
        );
        s.accept(Sample::Status(Envelope::new(
            "robot1",
            3,
            status(AgentState::Finished, 1),
        )))
        .unwrap();
        assert_eq!(
            s.waiting_for(None, 2),
            ["robot2: finished, 0 of its 3 captures held (asking for the rest)"]
        );
    }

    #[test]
    fn one_target_centre_for_all_robots_or_a_named_disagreement() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        let c = Some([0.1, 0.05, 0.0]);
        // Partial detections: the corners seen do not average to the centre,
        // the reported centre is used.
        for (robot, seq, cap) in [
            ("robot1", 1, with_centre(0, c, [0.0; 3])),
            ("robot2", 1, with_centre(0, c, [0.02, 0.0, 0.0])),
        ] {
            s.accept(Sample::Capture(Envelope::new(robot, seq, cap)))
                .unwrap();
        }
        let got = s.target_centre(&["robot1", "robot2"]).unwrap();
        assert_eq!(got, Point3::new(0.1, 0.05, 0.0));
        s.accept(Sample::Capture(Envelope::new(
            "robot2",
            2,
            with_centre(1, Some([0.2, 0.05, 0.0]), [0.0; 3]),
        )))
        .unwrap();
        let err = s
            .target_centre(&["robot1", "robot2"])
            .unwrap_err()
            .to_string();
        assert!(err.contains("robot2") && err.contains("capture 1"), "{err}");
        // Agents that do not report it: the mean of the distinct corners seen.
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        s.accept(Sample::Capture(Envelope::new(
            "robot1",
            1,
            with_centre(0, None, [0.0; 3]),
        )))
        .unwrap();
        s.accept(Sample::Capture(Envelope::new(
            "robot1",
            2,
            with_centre(1, None, [0.04, 0.0, 0.0]),
        )))
        .unwrap();
        assert_eq!(
            s.target_centre(&["robot1"]).unwrap(),
            Point3::new(0.02, 0.0, 0.0)
        );
    }

    #[test]
    fn duplicates_are_dropped_and_restart_resumes() {
        let dir = tempfile::tempdir().unwrap();
        let take = |s: &mut Store, seq, sample| {
            s.accept(Sample::Capture(Envelope::new("robot1", seq, sample)))
                .unwrap()
        };
        {
            let mut s = Store::open(dir.path()).unwrap();
            assert_eq!(take(&mut s, 1, capture(0)), Arrival::New);
            assert_eq!(take(&mut s, 2, capture(0)), Arrival::Duplicate);
            assert_eq!(take(&mut s, 3, capture(1)), Arrival::New);
            assert_eq!(
                s.accept(Sample::Status(Envelope::new(
                    "robot1",
                    4,
                    status(AgentState::Finished, 3)
                )))
                .unwrap(),
                Arrival::New
            );
            assert_eq!(s.missing(), vec!["robot1".to_string()]);
            assert!(!s.complete(None, 1));
        }
        // A crash mid-write leaves half a line.
        let mut f = OpenOptions::new()
            .append(true)
            .open(dir.path().join(JOURNAL))
            .unwrap();
        f.write_all(b"{\"kind\":\"capture\",\"sch").unwrap();
        drop(f);
        let mut s = Store::open(dir.path()).unwrap();
        assert_eq!(s.skipped_lines, 1);
        assert_eq!(s.capture_count("robot1"), 2);
        assert_eq!(take(&mut s, 5, capture(2)), Arrival::New);
        assert!(s.complete(None, 1));
        assert!(!s.complete(None, 2));
        assert_eq!(s.observations("robot1").unwrap().observations.len(), 3);
    }

    /// A forged capture with an index the robot also sends, either first or
    /// second: neither version is used, the conflict is journaled (a restart
    /// sees it too), counted, and listed among the rejected captures; a
    /// re-send of either version is a plain duplicate.
    #[test]
    fn a_conflicting_capture_is_kept_counted_and_neither_version_used() {
        let dir = tempfile::tempdir().unwrap();
        let mut forged = capture(0);
        forged.base_from_flange.t[0] += 0.05;
        {
            let mut s = Store::open(dir.path()).unwrap();
            let mut take = |seq, c| {
                s.accept(Sample::Capture(Envelope::new("robot1", seq, c)))
                    .unwrap()
            };
            assert_eq!(take(1, forged.clone()), Arrival::New);
            assert_eq!(take(2, capture(0)), Arrival::Conflict);
            assert_eq!(take(3, capture(0)), Arrival::Duplicate);
            assert_eq!(take(4, forged.clone()), Arrival::Duplicate);
            assert_eq!(take(5, capture(1)), Arrival::New);
        }
        let mut s = Store::open(dir.path()).unwrap();
        assert_eq!(s.conflict_count(), 1);
        s.accept(Sample::Status(Envelope::new(
            "robot1",
            6,
            status(AgentState::Finished, 2),
        )))
        .unwrap();
        // Both indices arrived: the robot is complete, but index 0 is not used.
        assert!(s.complete(None, 1));
        let o = s.observations("robot1").unwrap();
        assert_eq!(o.observations.len(), 1);
        assert_eq!(o.observations[0].row, 2);
        assert_eq!(o.rejected.len(), 1);
        assert!(
            o.rejected[0]
                .reason
                .starts_with("conflict: 2 different captures arrived with index 0"),
            "{:?}",
            o.rejected
        );
    }

    /// A forged "finished, 0 published" status with a huge sequence number
    /// neither completes the robot nor outranks the robot's own statuses.
    #[test]
    fn a_status_contradicted_by_the_captures_is_replaced_and_completes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        let forged = || {
            Sample::Status(Envelope::new(
                "robot1",
                1 << 50,
                status(AgentState::Finished, 0),
            ))
        };
        assert_eq!(s.accept(forged()).unwrap(), Arrival::New);
        for i in 0..2 {
            s.accept(Sample::Capture(Envelope::new("robot1", i + 1, capture(i))))
                .unwrap();
        }
        assert!(!s.complete(None, 1));
        assert!(s.waiting_for(None, 1)[0].contains("a stale or forged status"));
        let real = Sample::Status(Envelope::new("robot1", 3, status(AgentState::Finished, 2)));
        assert_eq!(s.accept(real).unwrap(), Arrival::New);
        assert!(s.complete(None, 1));
        // The forgery again, or one that says it is still capturing: a
        // finished robot stays finished, whatever the sequence number.
        assert_eq!(s.accept(forged()).unwrap(), Arrival::Duplicate);
        let capturing = Sample::Status(Envelope::new(
            "robot1",
            1 << 51,
            status(AgentState::Capturing, 999),
        ));
        assert_eq!(s.accept(capturing).unwrap(), Arrival::Duplicate);
        assert!(s.complete(None, 1));
        // A capture beyond what it said it published: the finished status is
        // contradicted, and the robot's next status takes over.
        s.accept(Sample::Capture(Envelope::new("robot1", 4, capture(2))))
            .unwrap();
        assert!(!s.complete(None, 1));
        let real = Sample::Status(Envelope::new("robot1", 5, status(AgentState::Finished, 3)));
        assert_eq!(s.accept(real).unwrap(), Arrival::New);
        assert!(s.complete(None, 1));
    }

    /// A forged "capturing, 999 published" with a huge sequence number: it
    /// outranks the robot's own statuses only until the robot's history,
    /// asked, serves fewer; then the robot's own status (lower sequence)
    /// replaces it and finishes the robot.
    #[test]
    fn a_status_claiming_more_than_the_history_holds_is_replaced() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        for i in 0..3 {
            s.accept(Sample::Capture(Envelope::new("robot1", i + 1, capture(i))))
                .unwrap();
        }
        let forged = Sample::Status(Envelope::new(
            "robot1",
            1 << 50,
            status(AgentState::Capturing, 999),
        ));
        assert_eq!(s.accept(forged).unwrap(), Arrival::New);
        assert_eq!(s.missing(), ["robot1"]);
        let real = || Sample::Status(Envelope::new("robot1", 9, status(AgentState::Finished, 3)));
        // Not yet disproved: the sequence number decides.
        assert_eq!(s.accept(real()).unwrap(), Arrival::Duplicate);
        assert!(!s.complete(None, 1));
        s.history_served("robot1", 3);
        assert!(
            s.waiting_for(None, 1)[0].contains("says 999 published, but its history holds 3"),
            "{:?}",
            s.waiting_for(None, 1)
        );
        // An answer with fewer (a reply lost) does not lower what was served.
        s.history_served("robot1", 0);
        assert_eq!(s.served("robot1"), Some(3));
        assert_eq!(s.accept(real()).unwrap(), Arrival::New);
        assert!(s.complete(None, 1));
        assert!(s.missing().is_empty());
    }

    /// A status from a robot nobody expects, and a capture with a stray
    /// index, neither stall nor complete a run; the stray index is not used.
    #[test]
    fn stray_statuses_and_indices_neither_stall_nor_complete_a_run() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        let ids = ["robot1".to_string(), "robot2".to_string()];
        for robot in ["robot1", "robot2"] {
            for i in 0..2 {
                s.accept(Sample::Capture(Envelope::new(robot, i + 1, capture(i))))
                    .unwrap();
            }
        }
        s.accept(Sample::Capture(Envelope::new("robot1", 9, capture(999))))
            .unwrap();
        s.accept(Sample::Status(Envelope::new(
            "robot9",
            1,
            status(AgentState::Capturing, 0),
        )))
        .unwrap();
        for robot in ["robot1", "robot2"] {
            assert!(!s.complete(Some(&ids), 2));
            s.accept(Sample::Status(Envelope::new(
                robot,
                10,
                status(AgentState::Finished, 2),
            )))
            .unwrap();
        }
        // robot9 is not waited for; robot1's index 999 does not count as one
        // of its two.
        assert!(s.complete(Some(&ids), 2));
        assert!(s.missing().is_empty());
        let o = s.observations("robot1").unwrap();
        assert_eq!(o.observations.len(), 2);
        assert!(
            o.rejected[0]
                .reason
                .contains("index 999 is beyond the 2 captures"),
            "{:?}",
            o.rejected
        );
        // A finished robot stays so: a later status that says it published 3
        // with index 2 missing takes nothing back.
        let more = || Sample::Status(Envelope::new("robot2", 11, status(AgentState::Finished, 3)));
        assert_eq!(s.accept(more()).unwrap(), Arrival::Duplicate);
        assert!(s.complete(Some(&ids), 2));
        // Before it finished, that status is taken: not complete, and
        // index 2 is asked for.
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        for i in 0..2 {
            s.accept(Sample::Capture(Envelope::new("robot2", i + 1, capture(i))))
                .unwrap();
        }
        assert_eq!(s.accept(more()).unwrap(), Arrival::New);
        assert!(!s.complete(None, 1));
        assert_eq!(s.missing(), ["robot2"]);
    }

    /// A camera that gave intrinsics on some captures and none on others is two
    /// cameras: the captures unlike the first are rejected with the reason, and
    /// too few estimated-camera captures to fit one is a named error.
    #[test]
    fn estimated_and_given_intrinsics_do_not_mix() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        let estimated = |index| {
            let mut c = capture(index);
            c.camera.estimated = true;
            c
        };
        for (seq, sample) in [(1, estimated(0)), (2, capture(1)), (3, estimated(2))] {
            s.accept(Sample::Capture(Envelope::new("robot1", seq, sample)))
                .unwrap();
        }
        let err = s.observations("robot1").unwrap_err();
        b2b_errors::assert_cause_once(&err);
        let err = b2b_errors::chain(&err);
        assert!(
            err.contains("robot1") && err.contains("at least 5"),
            "{err}"
        );
        let dir = tempfile::tempdir().unwrap();
        let mut s = Store::open(dir.path()).unwrap();
        for (seq, sample) in [(1, capture(0)), (2, estimated(1))] {
            s.accept(Sample::Capture(Envelope::new("robot1", seq, sample)))
                .unwrap();
        }
        let o = s.observations("robot1").unwrap();
        assert_eq!(o.observations.len(), 1);
        assert!(
            o.rejected[0]
                .reason
                .contains("gave no intrinsics on this capture"),
            "{:?}",
            o.rejected
        );
    }
}
