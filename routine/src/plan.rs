//! Viewpoint planning for the automatic routine (`agent auto`, and the pose program of
//! `agent run --sim`), without I/O.
//!
//! Candidates lie on a spherical cap above the board: viewing directions on a Fibonacci
//! spiral out to the largest tilt, distances spread over the camera's useful range,
//! rolls alternating in sign and growing, so that the relative rotations between
//! captures have axes in all directions. Each candidate is turned into a flange pose
//! with the approximate hand-eye (the mount's drawing), solved with the nominal IK, and
//! kept only if the joint configuration is inside the limits (with a margin), the
//! flange is inside the configured workspace box, and every board point projects into
//! the image with a margin. The kept ones are thinned by farthest-point sampling and
//! ordered nearest-neighbour in joint space from the start; every leg of the path is
//! checked at a fine joint step against the same envelope, and a viewpoint whose leg
//! leaves the workspace is dropped rather than approached.

use b2b_calib::camera::CameraModel;
use b2b_robot::{Arm, ForwardKinematics, IkOptions, Joints, SafetyEnvelope};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use crate::RoutineError;

type Iso3 = Isometry3<f64>;

/// What the planner aims for.
#[derive(Debug, Clone)]
pub struct PlanConfig {
    /// Viewpoints wanted.
    pub count: usize,
    /// Camera-to-board-centre distance range, m.
    pub distance_m: [f64; 2],
    /// Largest angle between the viewing direction and the board normal, rad.
    pub max_tilt_rad: f64,
    /// Largest roll about the viewing direction, rad.
    pub max_roll_rad: f64,
    /// Every board point at least this far inside the image, px.
    pub margin_px: f64,
    /// Joint step at which each leg of the path is checked, rad.
    pub path_step_rad: f64,
    /// Shifts the candidate spiral (azimuths and distances), so that a re-plan visits
    /// new viewpoints rather than the same ones again.
    pub phase: f64,
}

impl Default for PlanConfig {
    fn default() -> Self {
        PlanConfig {
            count: 30,
            distance_m: [0.35, 0.6],
            max_tilt_rad: 45f64.to_radians(),
            max_roll_rad: 40f64.to_radians(),
            margin_px: 20.0,
            path_step_rad: 0.01,
            phase: 0.0,
        }
    }
}

impl PlanConfig {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), RoutineError> {
        if self.count < 3 {
            return Err(RoutineError::TooSmall {
                what: "plan: viewpoints",
                min: 3,
                value: self.count,
            });
        }
        let [d0, d1] = self.distance_m;
        if !(d0.is_finite() && d1.is_finite() && 0.05 < d0 && d0 <= d1) {
            return Err(RoutineError::PlanDistances { near: d0, far: d1 });
        }
        let out = |what, value: f64, range| RoutineError::OutOfRange { what, value, range };
        if !(self.max_tilt_rad.is_finite() && (0.0..1.4).contains(&self.max_tilt_rad)) {
            return Err(out(
                "plan: largest tilt (rad)",
                self.max_tilt_rad,
                "[0, 1.4) (up to 80 degrees)",
            ));
        }
        if !(self.max_roll_rad.is_finite()
            && (0.0..=std::f64::consts::PI).contains(&self.max_roll_rad))
        {
            return Err(out(
                "plan: largest roll (rad)",
                self.max_roll_rad,
                "[0, pi] (up to 180 degrees)",
            ));
        }
        if !(self.path_step_rad.is_finite() && self.path_step_rad > 0.0) {
            return Err(RoutineError::NotPositive {
                what: "plan: path step (rad)",
                value: self.path_step_rad,
            });
        }
        Ok(())
    }
}

/// The scene as the planner knows it (no ground truth: approximate values).
#[derive(Debug, Clone)]
pub struct PlanScene<'a> {
    /// The nominal kinematics: the planner's IK, and the flange positions the
    /// envelope's workspace box is checked on.
    pub arm: &'a Arm,
    /// The envelope the FRI session applies to every command (joint limits
    /// with the margin, the workspace box): every viewpoint and every leg keeps
    /// inside it.
    pub envelope: &'a SafetyEnvelope,
    pub camera: &'a CameraModel,
    /// The board's pose in the base, approximately (a first view, or configuration).
    pub base_from_target: Iso3,
    /// The camera mount, approximately (the drawing).
    pub flange_from_camera: Iso3,
    /// The target's points in its own frame (corners).
    pub target_points: &'a [Point3<f64>],
    /// Unit direction (target frame) from the target towards where it is seen
    /// from (`b2b_vision::Target::view_axis`: -z for a board).
    pub view_axis: Vector3<f64>,
}

/// One planned viewpoint.
#[derive(Debug, Clone, PartialEq)]
pub struct Viewpoint {
    pub q: Joints,
    /// Nominal flange pose at `q`.
    pub base_from_flange: Iso3,
    pub distance_m: f64,
    pub tilt_rad: f64,
    pub roll_rad: f64,
}

/// A plan and what was left out.
#[derive(Debug, Clone)]
pub struct Plan {
    pub viewpoints: Vec<Viewpoint>,
    /// Candidates tried.
    pub candidates: usize,
    /// Why candidates were dropped: (reason, count).
    pub dropped: Vec<(String, usize)>,
    /// Joint travel along the path, rad (sum over legs of the largest joint move).
    pub travel_rad: f64,
}

/// The board centre in the target frame (mean of its points).
pub fn target_centre(points: &[Point3<f64>]) -> Point3<f64> {
    if points.is_empty() {
        return Point3::origin();
    }
    let sum = points
        .iter()
        .fold(Vector3::zeros(), |acc, p| acc + p.coords);
    Point3::from(sum / points.len() as f64)
}

/// A camera at `eye` looking at `centre`, rolled about its view axis: the
/// simulator's own aiming, so planned and generated viewpoints agree.
pub use b2b_calib::pose::look_at;

/// Whether every target point projects at least `margin` px inside the image.
pub fn all_in_view(
    camera: &CameraModel,
    camera_from_target: &Iso3,
    points: &[Point3<f64>],
    margin: f64,
) -> bool {
    points.iter().all(|p| {
        let pc = camera_from_target * p;
        pc.z > 0.0
            && camera.project(&pc).is_some_and(|uv| {
                uv.x >= margin
                    && uv.y >= margin
                    && uv.x <= camera.width as f64 - 1.0 - margin
                    && uv.y <= camera.height as f64 - 1.0 - margin
            })
    })
}

/// Checks the straight joint-space leg `a -> b` against the envelope (flange
/// positions from `fk`). The joint limits
/// are a box in joint space, so the ends decide them; the workspace box is checked at
/// samples `step` rad apart (largest joint) with the box shrunk by the largest flange
/// move between neighbouring samples, so the flange between samples stays inside too.
pub fn leg_is_safe<K>(envelope: &SafetyEnvelope, fk: &K, a: &Joints, b: &Joints, step: f64) -> bool
where
    K: ForwardKinematics + ?Sized,
{
    if envelope.check_pose(a, fk).is_err() || envelope.check_pose(b, fk).is_err() {
        return false;
    }
    let largest = joint_distance(a, b);
    if !(largest.is_finite() && step.is_finite() && step > 0.0) {
        return false;
    }
    let n = (largest / step).ceil().max(1.0) as usize;
    let points: Vec<[f64; 3]> = (0..=n)
        .map(|k| {
            let s = k as f64 / n as f64;
            let q: Joints = std::array::from_fn(|j| a[j] + (b[j] - a[j]) * s);
            fk.flange_position(&q)
        })
        .collect();
    let spacing = points
        .windows(2)
        .map(|w| {
            ((w[1][0] - w[0][0]).powi(2)
                + (w[1][1] - w[0][1]).powi(2)
                + (w[1][2] - w[0][2]).powi(2))
            .sqrt()
        })
        .fold(0.0, f64::max);
    let ws = envelope.workspace();
    points
        .iter()
        .all(|p| (0..3).all(|k| p[k] >= ws.min[k] + spacing && p[k] <= ws.max[k] - spacing))
        || n == 0
}

fn joint_distance(a: &Joints, b: &Joints) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (y - x).abs())
        .fold(0.0, f64::max)
}

/// The flange pose that puts the camera at `base_from_camera`, solved with the nominal
/// IK near `seed`, checked against the envelope. `Err` says why not.
pub fn reach(
    scene: &PlanScene<'_>,
    base_from_camera: &Iso3,
    seed: &Joints,
) -> Result<(Joints, Iso3), String> {
    let wanted = base_from_camera * scene.flange_from_camera.inverse();
    // Out of reach for certain: the wrist centre (the flange minus the last link
    // along its axis) further from the shoulder than the two arm links can stretch.
    let arm = scene.arm;
    let wrist = arm.wrist_centre_in_base(&wanted);
    if (wrist - arm.shoulder_in_base()).norm() > arm.max_shoulder_to_wrist_m() - 1e-3 {
        return Err("out of the arm's reach".to_owned());
    }
    let margin = scene.envelope.position_margin().max(2f64.to_radians());
    let opts = IkOptions {
        tolerance_m: 1e-7,
        tolerance_rad: 1e-7,
        restarts: 0,
        max_iterations: PLAN_IK_ITERATIONS,
        limit_margin: margin,
        preferred: Some(*seed),
        settle_rad: PLAN_IK_SETTLE_RAD,
        ..IkOptions::default()
    };
    let q = scene
        .arm
        .ik(&wanted, seed, &opts)
        .map_err(|_| "no IK solution inside the joint limits".to_owned())?;
    scene
        .envelope
        .check_pose(&q, scene.arm)
        .map_err(|e| format!("outside the safe set: {e}"))?;
    Ok((q, scene.arm.fk(&q)))
}

/// The planner's IK. Every candidate is solved once, from the start posture and
/// pulled towards it (no restarts from elsewhere in joint space: a solution found
/// from another start would resolve the redundancy another way, the elbow flip the
/// single seed exists to avoid). A reachable candidate converges in ~20 iterations;
/// one the joint limits block never does, and was the planner's whole cost: with
/// the IK's defaults (5 starts x 400 iterations) 34 ms per blocked candidate, 0.8 s
/// per 30-viewpoint plan, against 80 ms now (`cargo bench -p b2b-services --bench
/// plan`, on the agent's setup), with 57 of 58 feasible candidates kept.
pub const PLAN_IK_ITERATIONS: usize = 120;
/// How still the elbow posture must be before the planner's IK stops (rad per
/// iteration; the null-space pull moves no flange).
pub const PLAN_IK_SETTLE_RAD: f64 = 1e-5;

/// Plans viewpoints from `start`.
pub fn plan_viewpoints(
    scene: &PlanScene<'_>,
    start: &Joints,
    cfg: &PlanConfig,
) -> Result<Plan, RoutineError> {
    cfg.validate()?;
    if scene.target_points.is_empty() {
        return Err(RoutineError::NoTargetPoints);
    }
    let centre = target_centre(scene.target_points);
    // Viewing directions lie in a cone about the target's view axis (a board's
    // printed side faces -z of its frame); "up" in the image follows the base's z
    // as seen from the target.
    let up_in_target = scene.base_from_target.inverse().rotation * Vector3::z();
    let axis = scene
        .view_axis
        .try_normalize(1e-9)
        .ok_or(RoutineError::ZeroViewAxis)?;
    // Two directions across the cone; for a board (axis -z) exactly x and y.
    let across_1 = if axis.x.abs() < 0.9 {
        (Vector3::x() - axis * axis.x).normalize()
    } else {
        (Vector3::y() - axis * axis.y).normalize()
    };
    let across_2 = -axis.cross(&across_1);
    let candidates = cfg.count * 4;
    let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
    let mut dropped: std::collections::BTreeMap<String, usize> = Default::default();
    let mut feasible: Vec<(Viewpoint, Vector3<f64>)> = vec![];
    // Every candidate is solved from the start posture and pulled towards it, so
    // the redundancy is resolved the same way throughout (no elbow flips between
    // neighbouring viewpoints).
    let seed = *start;
    for i in 0..candidates {
        let s = (i as f64 + 0.5) / candidates as f64;
        let tilt = cfg.max_tilt_rad * s.sqrt();
        let azimuth = i as f64 * golden + cfg.phase;
        let frac = (i as f64 * 0.618_033_988_75 + cfg.phase * 0.381_966).fract();
        let dist = cfg.distance_m[0] + (cfg.distance_m[1] - cfg.distance_m[0]) * frac;
        let roll_sign = if i % 2 == 0 { 1.0 } else { -1.0 };
        let roll = roll_sign * cfg.max_roll_rad * ((i as f64 * 0.381_966).fract());
        let dir = across_1 * (tilt.sin() * azimuth.cos())
            + across_2 * (tilt.sin() * azimuth.sin())
            + axis * tilt.cos();
        let eye = centre + dir * dist;
        let target_from_camera = look_at(&eye, &centre, &up_in_target, roll);
        let camera_from_target = target_from_camera.inverse();
        if !all_in_view(
            scene.camera,
            &camera_from_target,
            scene.target_points,
            cfg.margin_px,
        ) {
            *dropped
                .entry("board not fully in the image".into())
                .or_default() += 1;
            continue;
        }
        let base_from_camera = scene.base_from_target * target_from_camera;
        match reach(scene, &base_from_camera, &seed) {
            Ok((q, base_from_flange)) => {
                // Diversity key: viewing direction and roll together.
                let key = Vector3::new(dir.x, dir.y, roll / std::f64::consts::PI);
                feasible.push((
                    Viewpoint {
                        q,
                        base_from_flange,
                        distance_m: dist,
                        tilt_rad: tilt,
                        roll_rad: roll,
                    },
                    key,
                ));
            }
            Err(reason) => *dropped.entry(reason).or_default() += 1,
        }
    }
    // Farthest-point sampling for coverage.
    let mut chosen: Vec<usize> = vec![];
    if !feasible.is_empty() {
        chosen.push(0);
        let mut best: Vec<f64> = feasible
            .iter()
            .map(|(_, k)| (k - feasible[0].1).norm())
            .collect();
        while chosen.len() < cfg.count.min(feasible.len()) {
            let (next, _) = best
                .iter()
                .enumerate()
                .filter(|(i, _)| !chosen.contains(i))
                .fold(
                    (usize::MAX, -1.0),
                    |acc, (i, &d)| if d > acc.1 { (i, d) } else { acc },
                );
            if next == usize::MAX {
                break;
            }
            chosen.push(next);
            for (i, (_, k)) in feasible.iter().enumerate() {
                best[i] = best[i].min((k - feasible[next].1).norm());
            }
        }
    }
    // Nearest-neighbour order in joint space, each leg checked.
    let mut remaining: Vec<Viewpoint> = chosen.iter().map(|&i| feasible[i].0.clone()).collect();
    let mut path = vec![];
    let mut at = *start;
    let mut travel = 0.0;
    while !remaining.is_empty() {
        remaining.sort_by(|a, b| joint_distance(&at, &a.q).total_cmp(&joint_distance(&at, &b.q)));
        let Some(k) = remaining
            .iter()
            .position(|v| leg_is_safe(scene.envelope, scene.arm, &at, &v.q, cfg.path_step_rad))
        else {
            *dropped
                .entry("no safe straight joint path from the previous viewpoint".into())
                .or_default() += remaining.len();
            break;
        };
        let v = remaining.remove(k);
        travel += joint_distance(&at, &v.q);
        at = v.q;
        path.push(v);
    }
    Ok(Plan {
        viewpoints: path,
        candidates,
        dropped: dropped.into_iter().collect(),
        travel_rad: travel,
    })
}

/// The camera pose that centres the board: the camera turns about its own centre so that
/// the ray to `centre_in_camera` becomes the optical axis, and moves along that ray to
/// `distance` (if given).
pub fn recentre(
    base_from_camera: &Iso3,
    centre_in_camera: &Point3<f64>,
    distance: Option<f64>,
) -> Iso3 {
    let d = centre_in_camera.coords;
    let n = d.norm();
    if n < 1e-9 {
        return *base_from_camera;
    }
    let d = d / n;
    let turn = UnitQuaternion::rotation_between(&Vector3::z(), &d)
        .unwrap_or_else(UnitQuaternion::identity);
    let mut camera_from_new = Iso3::from_parts(Translation3::identity(), turn);
    if let Some(want) = distance {
        camera_from_new.translation.vector = d * (n - want);
    }
    base_from_camera * camera_from_new
}

#[cfg(test)]
mod tests {
    use super::*;
    use b2b_robot::{IiwaModel, JointLimits, WorkspaceBox};

    fn setup() -> (Arm, SafetyEnvelope, CameraModel, Vec<Point3<f64>>) {
        let arm = Arm::new(IiwaModel::Iiwa7R800);
        let envelope = SafetyEnvelope::new(
            JointLimits::iiwa7(),
            WorkspaceBox::new([0.0, -0.6, 0.15], [0.9, 0.6, 1.2]).unwrap(),
        )
        .unwrap()
        .with_position_margin(0.05)
        .unwrap();
        let camera = CameraModel::new(640, 480, [615.0, 615.0, 320.0, 240.0], &[0.0; 5]).unwrap();
        let points = b2b_calib::synth::board_points(9, 6, 0.025);
        (arm, envelope, camera, points)
    }

    fn board() -> Iso3 {
        Iso3::from_parts(
            Translation3::new(0.5, -0.1, 0.0),
            UnitQuaternion::from_euler_angles(std::f64::consts::PI, 0.0, 0.1),
        )
    }

    fn mount() -> Iso3 {
        Iso3::from_parts(
            Translation3::new(0.0, 0.065, 0.035),
            UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
        )
    }

    #[test]
    fn plans_thirty_safe_diverse_viewpoints() {
        let (arm, envelope, camera, points) = setup();
        let scene = PlanScene {
            arm: &arm,
            envelope: &envelope,
            camera: &camera,
            base_from_target: board(),
            flange_from_camera: mount(),
            target_points: &points,
            view_axis: -Vector3::z(),
        };
        let start = Arm::comfortable();
        let plan = plan_viewpoints(&scene, &start, &PlanConfig::default()).unwrap();
        assert!(plan.viewpoints.len() >= 28, "{plan:?}");
        let mut prev = start;
        for v in &plan.viewpoints {
            envelope.check_pose(&v.q, &arm).unwrap();
            assert!(leg_is_safe(&envelope, &arm, &prev, &v.q, 0.01));
            prev = v.q;
            let camera_from_target = (v.base_from_flange * mount()).inverse() * board();
            assert!(all_in_view(&camera, &camera_from_target, &points, 19.0));
        }
        let poses: Vec<Iso3> = plan.viewpoints.iter().map(|v| v.base_from_flange).collect();
        let m = b2b_calib::degeneracy::check_motions(
            &poses,
            &b2b_calib::degeneracy::MotionThresholds::default(),
        )
        .unwrap();
        assert!(
            m.max_axis_angle_deg > 45.0,
            "rotation axes not spread: {m:?}"
        );
        let tilts: Vec<f64> = plan
            .viewpoints
            .iter()
            .map(|v| v.tilt_rad.to_degrees())
            .collect();
        assert!(
            tilts.iter().cloned().fold(0.0, f64::max) > 35.0,
            "{tilts:?}"
        );
    }

    #[test]
    fn settings_that_cannot_plan_are_named() {
        let bad = |cfg: PlanConfig| cfg.validate().unwrap_err().to_string();
        let d = PlanConfig::default();
        assert!(
            bad(PlanConfig {
                count: 2,
                ..d.clone()
            })
            .contains("at least 3")
        );
        assert!(
            bad(PlanConfig {
                distance_m: [0.6, 0.35],
                ..d.clone()
            })
            .contains("[0.6, 0.35]")
        );
        assert!(
            bad(PlanConfig {
                max_tilt_rad: f64::NAN,
                ..d.clone()
            })
            .contains("largest tilt")
        );
        assert!(
            bad(PlanConfig {
                max_roll_rad: 4.0,
                ..d.clone()
            })
            .contains("largest roll")
        );
        assert!(
            bad(PlanConfig {
                path_step_rad: 0.0,
                ..d
            })
            .contains("path step")
        );
    }

    #[test]
    fn an_unreachable_board_gives_an_empty_plan_with_reasons() {
        let (arm, envelope, camera, points) = setup();
        let scene = PlanScene {
            arm: &arm,
            envelope: &envelope,
            camera: &camera,
            base_from_target: Iso3::translation(3.0, 0.0, 0.0) * board(),
            flange_from_camera: mount(),
            target_points: &points,
            view_axis: -Vector3::z(),
        };
        let plan = plan_viewpoints(&scene, &Arm::comfortable(), &PlanConfig::default()).unwrap();
        assert!(plan.viewpoints.is_empty());
        assert!(!plan.dropped.is_empty());
    }

    #[test]
    fn recentring_puts_the_point_on_the_axis_at_the_distance() {
        let base_from_camera = Iso3::from_parts(
            Translation3::new(0.3, 0.1, 0.5),
            UnitQuaternion::from_euler_angles(3.0, 0.2, -0.4),
        );
        let p_cam = Point3::new(0.08, -0.05, 0.45);
        let p_base = base_from_camera * p_cam;
        let new = recentre(&base_from_camera, &p_cam, Some(0.4));
        let p_new = new.inverse() * p_base;
        assert!(p_new.x.abs() < 1e-12 && p_new.y.abs() < 1e-12, "{p_new}");
        assert!((p_new.z - 0.4).abs() < 1e-12);
    }
}
