//! The drift watch's decisions during the operation, without the bus:
//! observations in, events out ([`Watcher`]). `coordinator watch`
//! (`b2b-services`) feeds it from the bus and prints, records and publishes
//! what it decides.
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

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use b2b_calib::Iso3;
use b2b_calib::drift::{DriftEvent, DriftOptions, PairWatch, innovation};
use b2b_pipeline::PipelineError;
use b2b_pipeline::rgbd::{
    NEAR_GATE, RgbdOptions, RgbdView, fit_camera_pair, match_views, match_views_near,
};
use b2b_protocol::messages::{Capture, DriftAlarm, FeatureSet};
use b2b_protocol::{CalibrationResult, ProtocolError};
use nalgebra::{Matrix6, Point3, Vector3};

/// Why a result cannot be watched.
#[derive(Debug, thiserror::Error)]
pub enum WatchError {
    #[error(
        "the result does not name its reference robot (written by an older version): calibrate again"
    )]
    NoReference,
    #[error("the result's robot '{id}'")]
    RobotId {
        id: String,
        #[source]
        source: ProtocolError,
    },
    #[error("the result's hand-eye of '{id}'")]
    HandEye {
        id: String,
        #[source]
        source: ProtocolError,
    },
    #[error("the result's base of '{id}'")]
    Base {
        id: String,
        #[source]
        source: Box<PipelineError>,
    },
    #[error("the result's reference robot '{reference}' has no hand-eye in it")]
    ReferenceMissing { reference: String },
}

/// One robot as the result has it.
#[derive(Debug, Clone)]
struct RobotModel {
    ref_from_base: Iso3,
    flange_from_camera: Iso3,
    /// The result's covariance of this robot's base in the reference's.
    covariance: Matrix6<f64>,
}

/// What one observation did.
#[derive(Debug, Clone, PartialEq)]
pub enum WatchEvent {
    /// Not tested, and why.
    Skipped { robot: String, why: String },
    /// Frame `index` became the robot's scene reference, with `features`
    /// lifted with depth; `with_target`: the target was in view too (tested
    /// against the result in the same frame), otherwise a move before it is
    /// not seen.
    SceneReference {
        robot: String,
        index: u64,
        features: usize,
        with_target: bool,
    },
    /// The test is still establishing its baseline. `against`: the
    /// reference robot, or [`SCENE`].
    Learning {
        robot: String,
        against: String,
        seen: usize,
        needed: usize,
    },
    /// The baseline is set and agrees with the result (`chi2` of its misfit).
    /// `against`: the reference robot, or [`SCENE`].
    Armed {
        robot: String,
        against: String,
        chi2: f64,
    },
    /// Tested: `z` of this observation and the CUSUM after it.
    Watching {
        robot: String,
        against: String,
        z: f64,
        cusum: f64,
    },
    /// A move.
    Alarm(DriftAlarm),
}

/// The decisions of the watch, without the bus: observations in, events out.
#[derive(Debug)]
pub struct Watcher {
    reference: String,
    options: DriftOptions,
    max_age: Duration,
    robots: BTreeMap<String, RobotModel>,
    pairs: BTreeMap<String, PairWatch>,
    alarmed: BTreeMap<String, DriftAlarm>,
    /// The reference robot's latest target pose in its base, when it arrived,
    /// and the target's centre (in the target frame).
    latest_reference: Option<(Instant, Iso3, Point3<f64>)>,
    /// Per robot watched through the scene's features.
    scenes: BTreeMap<String, SceneWatch>,
    /// How scene frames are matched (the RGB-D method's settings).
    rgbd: RgbdOptions,
}

/// What scene alarms name as the reference: the scene itself (a name no
/// robot can take).
pub use b2b_protocol::messages::SCENE;

/// One robot watched through the scene's features.
#[derive(Debug)]
struct SceneWatch {
    /// The scene's reference frame: its features and lifted points.
    reference: RgbdView,
    /// Where the reference camera was, in the robot's base.
    base_from_camera: Iso3,
    /// The lifted points' centroid, in the reference camera.
    centre: Point3<f64>,
    test: PairWatch,
    /// The inliers of the first brute-force fit, or of a later one that
    /// kept fewer than half as many (the scene lost features); a guided fit
    /// with fewer than half as many is not trusted.
    healthy_inliers: Option<usize>,
    matching: SceneMatching,
}

/// How a robot's scene frames were matched to the scene's reference.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SceneMatching {
    /// Near where the robot's pose predicts each feature.
    pub guided: u64,
    /// Every feature against every one: the first frame, and frames whose
    /// guided fit failed or kept too few inliers.
    pub brute_force: u64,
}

impl Watcher {
    /// Every robot of the result with its hand-eye and its base in the
    /// reference's; the result must name its reference (results of this version
    /// do).
    pub fn new(
        result: &CalibrationResult,
        options: DriftOptions,
        max_age: Duration,
    ) -> Result<Self, WatchError> {
        let reference = result.reference.clone().ok_or(WatchError::NoReference)?;
        let mut robots = BTreeMap::new();
        for (id, pose) in &result.hand_eye {
            // A robot called like the scene would be read as the scene.
            b2b_protocol::messages::validate_cart_id(id).map_err(|source| WatchError::RobotId {
                id: id.clone(),
                source,
            })?;
            let flange_from_camera =
                pose.to_isometry(&format!("hand_eye.{id}"))
                    .map_err(|source| WatchError::HandEye {
                        id: id.clone(),
                        source,
                    })?;
            let (ref_from_base, covariance) = if *id == reference {
                (Iso3::identity(), Matrix6::zeros())
            } else {
                b2b_pipeline::pair_transform(result, &reference, id).map_err(|source| {
                    WatchError::Base {
                        id: id.clone(),
                        source: Box::new(source),
                    }
                })?
            };
            robots.insert(
                id.clone(),
                RobotModel {
                    ref_from_base,
                    flange_from_camera,
                    covariance,
                },
            );
        }
        if !robots.contains_key(&reference) {
            return Err(WatchError::ReferenceMissing { reference });
        }
        Ok(Watcher {
            reference,
            options,
            max_age,
            robots,
            pairs: BTreeMap::new(),
            alarmed: BTreeMap::new(),
            latest_reference: None,
            scenes: BTreeMap::new(),
            rgbd: RgbdOptions::default(),
        })
    }

    /// The robots the result holds.
    pub fn robots(&self) -> Vec<String> {
        self.robots.keys().cloned().collect()
    }

    /// The alarms raised so far, by robot.
    pub fn alarms(&self) -> &BTreeMap<String, DriftAlarm> {
        &self.alarmed
    }

    /// How `robot`'s scene frames were matched so far; `None` before its
    /// scene's reference frame.
    pub fn scene_matching(&self, robot: &str) -> Option<SceneMatching> {
        self.scenes.get(robot).map(|s| s.matching)
    }

    /// How every robot watched through the scene had its frames matched.
    pub fn scene_matchings(&self) -> BTreeMap<String, SceneMatching> {
        self.scenes
            .iter()
            .map(|(robot, scene)| (robot.clone(), scene.matching))
            .collect()
    }

    /// Tests one observation of `robot`, received at `at`: its target
    /// against the reference robot's, and its scene features against the
    /// scene's reference frame (a frame that carries both is tested both
    /// ways, in that order). One event per test, or one saying why none ran.
    pub fn observe(&mut self, robot: &str, at: Instant, capture: &Capture) -> Vec<WatchEvent> {
        let Some(model) = self.robots.get(robot) else {
            return vec![WatchEvent::Skipped {
                robot: robot.to_owned(),
                why: "not a robot of the result".into(),
            }];
        };
        let flange_from_camera = model.flange_from_camera;
        let mut events = Vec::with_capacity(2);
        if let Some(o) = &capture.observation {
            events.push(self.observe_target(robot, at, capture, o));
        }
        if let Some(set) = &capture.features {
            events.push(self.observe_scene(robot, capture, set, &flange_from_camera));
        }
        if events.is_empty() {
            events.push(WatchEvent::Skipped {
                robot: robot.to_owned(),
                why: format!(
                    "no target in frame {}: {}",
                    capture.index,
                    capture.rejected.as_deref().unwrap_or("not seen")
                ),
            });
        }
        events
    }

    /// The target `o` that `robot` (a robot of the result) saw in `capture`.
    fn observe_target(
        &mut self,
        robot: &str,
        at: Instant,
        capture: &Capture,
        o: &b2b_protocol::messages::BoardObservation,
    ) -> WatchEvent {
        let skipped = |why: String| WatchEvent::Skipped {
            robot: robot.to_owned(),
            why,
        };
        let model = &self.robots[robot];
        let (Ok(base_from_flange), Ok(camera_from_target)) = (
            capture.base_from_flange.to_isometry("T_base_flange"),
            o.camera_from_target.to_isometry("T_camera_target"),
        ) else {
            return skipped("a pose that is not a rigid transform".into());
        };
        let ref_from_target =
            model.ref_from_base * base_from_flange * model.flange_from_camera * camera_from_target;
        let centre = match o.target_centre {
            Some(c) => Point3::from(c),
            None => {
                let n = o.target_points.len().max(1) as f64;
                Point3::from(
                    o.target_points
                        .iter()
                        .fold(nalgebra::Vector3::zeros(), |s, p| {
                            s + nalgebra::Vector3::from(*p)
                        })
                        / n,
                )
            }
        };
        if robot == self.reference {
            self.latest_reference = Some((at, ref_from_target, centre));
            return WatchEvent::Skipped {
                robot: robot.to_owned(),
                why: "the reference (its observations pair with the others')".into(),
            };
        }
        if self.alarmed.contains_key(robot) {
            return skipped("alarm already raised".into());
        }
        let Some((seen_at, reference_pose, _)) = self.latest_reference else {
            return skipped(format!("no observation of {} yet", self.reference));
        };
        let age = at.saturating_duration_since(seen_at);
        if age > self.max_age {
            return skipped(format!(
                "the latest observation of {} is {:.1} s old",
                self.reference,
                age.as_secs_f64()
            ));
        }
        let d = innovation(&ref_from_target, &reference_pose, &centre);
        let options = self.options;
        let covariance = model.covariance;
        let pair = self
            .pairs
            .entry(robot.to_owned())
            .or_insert_with(|| PairWatch::new(options, &covariance, &(reference_pose * centre)));
        let event = pair.update(&d);
        let reference = self.reference.clone();
        self.decide(robot, &reference, event)
    }

    /// A frame of `robot` (a robot of the result) without the target, with
    /// the scene's features.
    fn observe_scene(
        &mut self,
        robot: &str,
        capture: &Capture,
        set: &FeatureSet,
        flange_from_camera: &Iso3,
    ) -> WatchEvent {
        let skipped = |why: String| WatchEvent::Skipped {
            robot: robot.to_owned(),
            why,
        };
        if self.alarmed.contains_key(robot) {
            return skipped("alarm already raised".into());
        }
        let Ok(base_from_flange) = capture.base_from_flange.to_isometry("T_base_flange") else {
            return skipped("a pose that is not a rigid transform".into());
        };
        let row = capture.index as usize + 1;
        let image = capture.image.clone().unwrap_or_default();
        let view = match RgbdView::from_feature_set(row, image, base_from_flange, set) {
            Ok(v) => v,
            Err(e) => return skipped(format!("features of frame {}: {e}", capture.index)),
        };
        let base_from_camera = base_from_flange * flange_from_camera;
        let Some(scene) = self.scenes.get_mut(robot) else {
            let lifted: Vec<Vector3<f64>> =
                view.points.iter().flatten().map(|p| p.coords).collect();
            let need = self.rgbd.min_inliers;
            if lifted.len() < need {
                return skipped(format!(
                    "frame {}: {} features with depth, the scene's reference needs {need}",
                    capture.index,
                    lifted.len()
                ));
            }
            let centre = Point3::from(lifted.iter().sum::<Vector3<f64>>() / lifted.len() as f64);
            let test = PairWatch::new(
                self.options,
                &Matrix6::zeros(),
                &(base_from_camera * centre),
            );
            self.scenes.insert(
                robot.to_owned(),
                SceneWatch {
                    reference: view,
                    base_from_camera,
                    centre,
                    test,
                    healthy_inliers: None,
                    matching: SceneMatching::default(),
                },
            );
            return WatchEvent::SceneReference {
                robot: robot.to_owned(),
                index: capture.index,
                features: lifted.len(),
                with_target: capture.observation.is_some(),
            };
        };
        // Where the reference camera stands in this one, if the cart is still.
        let now_from_reference = base_from_camera.inverse() * scene.base_from_camera;
        let guided = scene.healthy_inliers.and_then(|healthy| {
            let m = match_views_near(
                &scene.reference,
                &view,
                &now_from_reference,
                NEAR_GATE,
                &self.rgbd,
            )
            .ok()?;
            let fit = fit_camera_pair(&m.points1, &m.points2, &self.rgbd).ok()?;
            (2 * fit.inliers >= healthy).then_some(fit)
        });
        let fit = match guided {
            Some(fit) => {
                scene.matching.guided += 1;
                fit
            }
            None => {
                scene.matching.brute_force += 1;
                let matched = match match_views(&scene.reference, &view, &self.rgbd) {
                    Ok(m) => m,
                    Err(e) => return skipped(format!("frame {}: matching: {e}", capture.index)),
                };
                let fit = match fit_camera_pair(&matched.points1, &matched.points2, &self.rgbd) {
                    Ok(f) => f,
                    Err(e) => {
                        return skipped(format!(
                            "frame {} against the scene's reference: {e}",
                            capture.index
                        ));
                    }
                };
                // The first count; or a smaller one that brute force finds
                // too: the scene lost features (the target taken away), so
                // later frames are held to what is left of it.
                if scene.healthy_inliers.is_none_or(|h| 2 * fit.inliers < h) {
                    scene.healthy_inliers = Some(fit.inliers);
                }
                fit
            }
        };
        // The reference camera's frame (the scene) as the robot places it now.
        let base_from_scene = base_from_camera * fit.camera1_from_camera2.inverse();
        let d = innovation(&base_from_scene, &scene.base_from_camera, &scene.centre);
        let event = scene.test.update(&d);
        self.decide(robot, SCENE, event)
    }

    /// The watch's event for a sequential test's outcome; an alarm is kept.
    fn decide(&mut self, robot: &str, reference: &str, event: DriftEvent) -> WatchEvent {
        let options = self.options;
        match event {
            DriftEvent::Learning { seen, needed } => WatchEvent::Learning {
                robot: robot.to_owned(),
                against: reference.to_owned(),
                seen,
                needed,
            },
            DriftEvent::Armed { chi2, .. } => WatchEvent::Armed {
                robot: robot.to_owned(),
                against: reference.to_owned(),
                chi2,
            },
            DriftEvent::Watching { z, g } => WatchEvent::Watching {
                robot: robot.to_owned(),
                against: reference.to_owned(),
                z,
                cusum: g,
            },
            DriftEvent::Alarm {
                z,
                g,
                shift,
                against_result,
            } => {
                let shift_m = shift.fixed_rows::<3>(3).norm();
                let turn_rad = shift.fixed_rows::<3>(0).norm();
                let (statistic, threshold) = if against_result {
                    (z, options.result_chi2)
                } else {
                    (g, options.h)
                };
                let why = if against_result && reference == SCENE {
                    format!(
                        "its first observations disagree with the scene's reference frame (chi2 {statistic:.1} > {threshold:.1}): moved while the watch began"
                    )
                } else if against_result {
                    format!(
                        "its first observations disagree with the result (chi2 {statistic:.1} > {threshold:.1}): moved before the watch began, or the result is off"
                    )
                } else {
                    format!("CUSUM {statistic:.1} > {threshold:.1}")
                };
                let alarm = DriftAlarm {
                    robot: robot.to_owned(),
                    reference: reference.to_owned(),
                    shift_m,
                    turn_rad,
                    against_result,
                    statistic,
                    threshold,
                    message: format!(
                        "ALARM: cart {robot} moved against {reference}: the {} shifted {:.2} mm and turned {:.3} deg ({why}); re-calibrate before going on",
                        if reference == SCENE {
                            "scene"
                        } else {
                            "target"
                        },
                        shift_m * 1e3,
                        turn_rad.to_degrees()
                    ),
                };
                self.alarmed.insert(robot.to_owned(), alarm.clone());
                WatchEvent::Alarm(alarm)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_protocol::Pose;
    use b2b_protocol::messages::{BoardObservation, Intrinsics};

    /// A result of two robots (the report's fixture), as an older version
    /// wrote it: without `reference`.
    fn older_result() -> CalibrationResult {
        serde_json::from_str(include_str!("../../report/tests/fixtures/RESULT.json")).unwrap()
    }

    fn capture(index: u64, seen: bool) -> Capture {
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
                dist: vec![0.0; 5],
                estimated: false,
            },
            observation: seen.then(|| BoardObservation {
                target_points: vec![[0.0; 3]; 4],
                pixels: vec![[1.0, 2.0]; 4],
                camera_from_target: Pose::from_isometry(&Iso3::translation(0.0, 0.0, 0.5)),
                residuals_px: vec![0.1; 4],
                rms_px: 0.1,
                target_centre: Some([0.1, 0.06, 0.0]),
                target: None,
            }),
            rejected: (!seen).then(|| "board not found".to_owned()),
            base_from_target: None,
            features: None,
        }
    }

    /// The one event of an observation that carries one kind of thing (the
    /// target, or the scene's features).
    fn observe1(w: &mut Watcher, robot: &str, at: Instant, capture: &Capture) -> WatchEvent {
        let mut events = w.observe(robot, at, capture);
        assert_eq!(events.len(), 1, "{events:?}");
        events.remove(0)
    }

    fn why(event: WatchEvent) -> String {
        match event {
            WatchEvent::Skipped { why, .. } => why,
            other => panic!("not skipped: {other:?}"),
        }
    }

    /// A result whose robot id is the scene's name, or whose hand-eye is not
    /// a rigid transform, is refused naming the robot, its cause printed once.
    #[test]
    fn a_bad_robot_of_the_result_is_named_with_its_cause_once() {
        let mut result = older_result();
        result.reference = Some("robot1".into());
        let mut bad_id = result.clone();
        let pose = bad_id.hand_eye.remove("robot2").unwrap();
        bad_id.hand_eye.insert(SCENE.to_owned(), pose);
        let err =
            Watcher::new(&bad_id, DriftOptions::default(), Duration::from_secs(2)).unwrap_err();
        assert!(matches!(err, WatchError::RobotId { .. }), "{err:?}");
        b2b_errors::assert_cause_once(&err);
        let mut bad_pose = result;
        bad_pose.hand_eye.get_mut("robot2").unwrap().t[0] = f64::NAN;
        let err =
            Watcher::new(&bad_pose, DriftOptions::default(), Duration::from_secs(2)).unwrap_err();
        assert!(
            matches!(err, WatchError::HandEye { ref id, .. } if id == "robot2"),
            "{err:?}"
        );
        b2b_errors::assert_cause_once(&err);
    }

    #[test]
    fn a_result_without_its_reference_is_refused() {
        let err = Watcher::new(
            &older_result(),
            DriftOptions::default(),
            Duration::from_secs(2),
        )
        .unwrap_err();
        let text = b2b_errors::chain(&err);
        assert!(text.contains("reference"), "{text}");
    }

    /// Observations that cannot be tested say why: an unknown robot, no
    /// target in view, no reference observation yet, a stale one; then the
    /// pair starts learning its baseline.
    #[test]
    fn untestable_observations_say_why() {
        let mut result = older_result();
        result.reference = Some("robot1".into());
        let max_age = Duration::from_secs(2);
        let mut w = Watcher::new(&result, DriftOptions::default(), max_age).unwrap();
        assert_eq!(w.robots(), ["robot1", "robot2"]);
        let t0 = Instant::now();
        assert!(why(observe1(&mut w, "robot9", t0, &capture(0, true))).contains("not a robot"));
        assert!(
            why(observe1(&mut w, "robot2", t0, &capture(1, false))).contains("board not found")
        );
        assert!(
            why(observe1(&mut w, "robot2", t0, &capture(2, true)))
                .contains("no observation of robot1")
        );
        observe1(&mut w, "robot1", t0, &capture(0, true));
        let late = t0 + max_age + Duration::from_millis(500);
        assert!(why(observe1(&mut w, "robot2", late, &capture(3, true))).contains("s old"));
        assert!(matches!(
            observe1(
                &mut w,
                "robot2",
                t0 + Duration::from_millis(100),
                &capture(4, true)
            ),
            WatchEvent::Learning { seen: 1, .. }
        ));
        assert!(w.alarms().is_empty());
    }

    /// A scene of `n` points in front of the camera with random ORB descriptors.
    fn scene(n: usize, rng: &mut rand::rngs::StdRng) -> (Vec<Point3<f64>>, Vec<u8>) {
        use rand::Rng;
        let points = (0..n)
            .map(|_| {
                Point3::new(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.2..0.2),
                    rng.random_range(0.5..1.0),
                )
            })
            .collect();
        let descriptors = (0..n * 32).map(|_| rng.random()).collect();
        (points, descriptors)
    }

    /// A frame without the target: the scene's points as the camera sees them
    /// (`camera_from_scene`), each with 0.05 mm of noise.
    fn scene_frame(
        index: u64,
        (points, descriptors): &(Vec<Point3<f64>>, Vec<u8>),
        camera_from_scene: &Iso3,
        rng: &mut rand::rngs::StdRng,
    ) -> Capture {
        use rand::Rng;
        let mut c = capture(index, false);
        let seen: Vec<Point3<f64>> = points
            .iter()
            .map(|p| {
                camera_from_scene * p
                    + Vector3::from_fn(|_, _| rng.random_range(-0.05e-3..0.05e-3) * 3f64.sqrt())
            })
            .collect();
        c.features = Some(FeatureSet {
            kind: "orb".into(),
            pixels: seen
                .iter()
                .map(|p| [320.0 + 600.0 * p.x / p.z, 240.0 + 600.0 * p.y / p.z])
                .collect(),
            responses: vec![1.0; points.len()],
            points_camera: seen.iter().map(|p| Some([p.x, p.y, p.z])).collect(),
            descriptor_len: 32,
            descriptors: descriptors.clone(),
        });
        c
    }

    /// Where no target is in view, each robot (the reference too) is watched
    /// against the scene's first frame: a still cart arms and stays quiet, a
    /// cart moved by 1 mm alarms within three frames, naming the scene.
    #[test]
    fn the_scene_watch_arms_on_a_still_scene_and_alarms_on_a_moved_cart() {
        use rand::SeedableRng;
        let mut result = older_result();
        result.reference = Some("robot1".into());
        let mut w = Watcher::new(&result, DriftOptions::default(), Duration::from_secs(2)).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(3);
        let scene = scene(200, &mut rng);
        let t0 = Instant::now();
        let still = Iso3::identity();
        for robot in ["robot1", "robot2"] {
            assert_eq!(
                observe1(&mut w, robot, t0, &scene_frame(0, &scene, &still, &mut rng)),
                WatchEvent::SceneReference {
                    robot: robot.into(),
                    index: 0,
                    features: 200,
                    with_target: false
                }
            );
            for k in 1..=20 {
                let event = observe1(&mut w, robot, t0, &scene_frame(k, &scene, &still, &mut rng));
                match (k, event) {
                    (20, WatchEvent::Armed { against, chi2, .. }) => {
                        assert_eq!(against, SCENE);
                        assert!(chi2 < 22.46, "{chi2}");
                    }
                    (1..20, WatchEvent::Learning { seen, .. }) => assert_eq!(seen, k as usize),
                    (_, other) => panic!("frame {k} of {robot}: {other:?}"),
                }
            }
        }
        for k in 21..100 {
            for robot in ["robot1", "robot2"] {
                let event = observe1(&mut w, robot, t0, &scene_frame(k, &scene, &still, &mut rng));
                assert!(matches!(event, WatchEvent::Watching { .. }), "{event:?}");
            }
        }
        // Robot 2's cart moves 1 mm along its base's x; its flange pose (here
        // the base's origin) and hand-eye are as before, so the camera sees
        // the scene moved by the inverse of the cart's move.
        let flange_from_camera = w.robots["robot2"].flange_from_camera;
        let moved = Iso3::translation(1e-3, 0.0, 0.0);
        let camera_from_scene = flange_from_camera.inverse() * moved.inverse() * flange_from_camera;
        let mut alarm = None;
        for k in 100..103 {
            if let WatchEvent::Alarm(a) = observe1(
                &mut w,
                "robot2",
                t0,
                &scene_frame(k, &scene, &camera_from_scene, &mut rng),
            ) {
                alarm = Some((k, a));
                break;
            }
        }
        let (k, a) = alarm.expect("no alarm within three frames of the move");
        assert_eq!(k, 102, "the CUSUM alarms on the third frame, not before");
        assert_eq!((a.robot.as_str(), a.reference.as_str()), ("robot2", SCENE));
        assert!((0.8e-3..1.2e-3).contains(&a.shift_m), "{a:?}");
        assert!(a.message.contains("moved against scene"), "{}", a.message);
        // The other cart stays quiet.
        let event = observe1(
            &mut w,
            "robot1",
            t0,
            &scene_frame(103, &scene, &still, &mut rng),
        );
        assert!(matches!(event, WatchEvent::Watching { .. }), "{event:?}");
        // The first frame after the reference was matched by brute force,
        // every later one near its prediction (the moved ones too: 1 mm is
        // well inside the gate).
        assert_eq!(
            w.scene_matching("robot1"),
            Some(SceneMatching {
                guided: 99,
                brute_force: 1
            })
        );
        assert_eq!(
            w.scene_matching("robot2")
                .map(|m| (m.guided, m.brute_force)),
            Some((k - 1, 1))
        );
    }

    /// A cart moved far beyond the matching gate (8 cm and 8°) leaves the
    /// guided match without its inliers; the frame is matched by brute force
    /// and the alarm says how far the scene moved.
    #[test]
    fn a_move_beyond_the_gate_is_matched_in_full_and_alarms() {
        use rand::SeedableRng;
        let mut result = older_result();
        result.reference = Some("robot1".into());
        let mut w = Watcher::new(&result, DriftOptions::default(), Duration::from_secs(2)).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let scene = scene(200, &mut rng);
        let t0 = Instant::now();
        let still = Iso3::identity();
        for k in 0..=30 {
            observe1(
                &mut w,
                "robot2",
                t0,
                &scene_frame(k, &scene, &still, &mut rng),
            );
        }
        let before = w.scene_matching("robot2").unwrap();
        assert_eq!((before.guided, before.brute_force), (29, 1));
        let flange_from_camera = w.robots["robot2"].flange_from_camera;
        let moved = Iso3::from_parts(
            nalgebra::Translation3::new(0.08, 0.0, 0.0),
            nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, 8f64.to_radians()),
        );
        let camera_from_scene = flange_from_camera.inverse() * moved.inverse() * flange_from_camera;
        let mut alarm = None;
        for k in 31..34 {
            if let WatchEvent::Alarm(a) = observe1(
                &mut w,
                "robot2",
                t0,
                &scene_frame(k, &scene, &camera_from_scene, &mut rng),
            ) {
                alarm = Some(a);
                break;
            }
        }
        let a = alarm.expect("no alarm within three frames of an 8 cm move");
        let after = w.scene_matching("robot2").unwrap();
        assert_eq!(after.guided, before.guided, "{after:?}");
        assert!(after.brute_force > before.brute_force, "{after:?}");
        assert!(
            (7f64..9.0).contains(&a.turn_rad.to_degrees()),
            "turned {} deg",
            a.turn_rad.to_degrees()
        );
        assert!(a.shift_m > 0.05, "{a:?}");
    }

    /// A frame with the target in view (robot 1's target pose, as `robot`
    /// sees it through the result, with 0.05 mm of noise) and the scene's
    /// features.
    fn target_and_scene_frame(
        w: &Watcher,
        robot: &str,
        index: u64,
        scene: &(Vec<Point3<f64>>, Vec<u8>),
        camera_from_scene: &Iso3,
        rng: &mut rand::rngs::StdRng,
    ) -> Capture {
        use rand::Rng;
        let mut c = scene_frame(index, scene, camera_from_scene, rng);
        let ref_from_target =
            w.robots["robot1"].flange_from_camera * Iso3::translation(0.0, 0.0, 0.5);
        let model = &w.robots[robot];
        let camera_from_target = Iso3::translation(
            rng.random_range(-0.05e-3..0.05e-3),
            rng.random_range(-0.05e-3..0.05e-3),
            rng.random_range(-0.05e-3..0.05e-3),
        ) * (model.ref_from_base * model.flange_from_camera).inverse()
            * ref_from_target;
        let seen = capture(index, true);
        c.observation = seen.observation.map(|mut o| {
            o.camera_from_target = Pose::from_isometry(&camera_from_target);
            o
        });
        c.rejected = None;
        c
    }

    /// The watch starts with the target in view, so each robot's scene
    /// reference is taken while its target agrees with the result. Robot 2's
    /// cart is bumped by 1 mm as the target is taken away (the board's
    /// features, over half the scene's, go with it): its scene watch, armed
    /// before, alarms; a watch whose scene reference is the first frame
    /// without the target (taken after the bump) sees nothing.
    #[test]
    fn a_cart_bumped_as_the_target_is_taken_away_alarms_on_the_scene() {
        use rand::SeedableRng;
        let mut result = older_result();
        result.reference = Some("robot1".into());
        let mut w = Watcher::new(&result, DriftOptions::default(), Duration::from_secs(2)).unwrap();
        let mut rng = rand::rngs::StdRng::seed_from_u64(11);
        let scene = scene(200, &mut rng);
        // The board's features: the first 120 of the scene's.
        let without_board = (scene.0[120..].to_vec(), scene.1[120 * 32..].to_vec());
        let t0 = Instant::now();
        let still = Iso3::identity();
        let mut armed = Vec::new();
        for k in 0..=25 {
            for robot in ["robot1", "robot2"] {
                let frame = target_and_scene_frame(&w, robot, k, &scene, &still, &mut rng);
                let events = w.observe(robot, t0, &frame);
                assert_eq!(events.len(), 2, "frame {k} of {robot}: {events:?}");
                for event in events {
                    match event {
                        WatchEvent::Armed { robot, against, .. } => armed.push((robot, against)),
                        WatchEvent::Alarm(a) => panic!("frame {k}: {}", a.message),
                        WatchEvent::SceneReference { with_target, .. } => {
                            assert!(k == 0 && with_target)
                        }
                        _ => {}
                    }
                }
            }
        }
        let against = |robot: &str, what: &str| (robot.to_owned(), what.to_owned());
        armed.sort();
        assert_eq!(
            armed,
            [
                against("robot1", SCENE),
                against("robot2", "robot1"),
                against("robot2", SCENE)
            ]
        );
        let flange_from_camera = w.robots["robot2"].flange_from_camera;
        let moved = Iso3::translation(1e-3, 0.0, 0.0);
        let bumped = flange_from_camera.inverse() * moved.inverse() * flange_from_camera;
        let frames_after: Vec<Capture> = (26..56)
            .map(|k| scene_frame(k, &without_board, &bumped, &mut rng))
            .collect();
        let mut alarm = None;
        for (k, frame) in frames_after.iter().enumerate().take(3) {
            let still_frame = scene_frame(26 + k as u64, &without_board, &still, &mut rng);
            let quiet = observe1(&mut w, "robot1", t0, &still_frame);
            assert!(matches!(quiet, WatchEvent::Watching { .. }), "{quiet:?}");
            if let WatchEvent::Alarm(a) = observe1(&mut w, "robot2", t0, frame) {
                alarm = Some(a);
                break;
            }
        }
        let a = alarm.expect("no alarm within three frames of the bump");
        assert_eq!(a.reference, SCENE);
        assert!((0.8e-3..1.2e-3).contains(&a.shift_m), "{a:?}");
        // Robot 1's scene lost over half its features with the board: its
        // first frame without them went to brute force and set the count its
        // later frames are held to, so they are guided again.
        let m = w.scene_matching("robot1").unwrap();
        assert_eq!((m.guided, m.brute_force), (25 + 1, 2), "{m:?}");

        // Without the target's frames the scene's reference is the bumped
        // cart's first frame: nothing to see.
        let mut late =
            Watcher::new(&result, DriftOptions::default(), Duration::from_secs(2)).unwrap();
        for frame in &frames_after {
            if let WatchEvent::Alarm(a) = observe1(&mut late, "robot2", t0, frame) {
                panic!("{}", a.message);
            }
        }
    }
}
