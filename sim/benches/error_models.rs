//! The error-model study: the default estimator against the seven closed forms
//! and against the maximum-likelihood limit, under robot pose errors of several
//! structures, magnitudes, capture counts and targets.
//!
//! Two iiwa arms (a 7 and a 14) a metre apart face a board on the table between
//! them. Viewpoints are planned around the board, each reached by the nominal
//! kinematics' IK; the robot then reports a flange pose with an error of one
//! structure:
//!
//! - `a` orientation turned in the base frame, position moved independently;
//! - `b` tool side, `base_from_flange * delta`;
//! - `c` a rotation about the base origin, `delta * base_from_flange`;
//! - `d` joint encoder noise through the kinematics;
//! - `e` systematic DH errors (drawn once per arm, the same at every capture);
//! - `f` structure `a` plus one (15 captures) or two (30) gross typo rows;
//!
//! and, as real arms err and the structures above miss (checkerboard, 30
//! captures only), each through the published iiwa kinematics, the arm
//! standing at joint angles other than those it reports:
//!
//! - `g` joint zero offsets (drawn once per arm, 0.004° per joint at 1x);
//! - `h` joint compliance under gravity: each joint yields by its gravity
//!   torque (link masses of the iiwa 14's published model, a 0.6 kg camera at
//!   the flange) times a compliance of 2e-6 rad/Nm at 1x, so the error
//!   depends on the pose;
//! - `i` gear backlash: each joint off by half its play (0.004° at 1x) in the
//!   direction it last moved, so the error depends on the approach;
//! - `j` a time skew between the exposure and the flange pose: 1 ms at 1x of
//!   a capture taken on the fly, moving towards the next view in 2 s.
//!
//! Link length errors are in `e`. `e` and `g`-`j` have no random model, so
//! their "limit" is the fit to the true flange poses (a bound).
//!
//! "1x" is the iiwa's repeatability as the project configures it (0.05 mm and
//! 0.01° per axis); for `d` a joint noise giving about that at the flange
//! (0.004° per joint), for `e` DH errors of 0.03 mm and 0.002° per parameter.
//! Corner noise is 0.15 px on a 1280x720 camera. Every run of the default
//! starts from its own closed-form seed, never from the truth.
//!
//! The limit: the maximum-likelihood estimate given the true error structure
//! and magnitudes (each capture's true pose covariance), seeded at the truth,
//! without gross rows. For `e` the errors are not random across captures, so
//! no such estimate exists; its "limit" is the fit to the true flange poses, a
//! bound that no method reaches (marked "bound").
//!
//! The measure is the error at touch locations: the mean distance between
//! where the estimate and the truth map points of a 0.3 m cube centred on the
//! board (27 points), averaged over seeds. For `e` the study also measures what
//! a touch-point verification would see: both arms touch each point with a
//! pointer held straight down (through their true kinematics) and report it
//! through their nominal kinematics; part of a systematic error could cancel
//! there, and the study shows how little does. It also runs the default told
//! the arms' accuracy (`--robot-accuracy-*`: the reported flange poses' RMS
//! error per axis over the views), and holds that covariance honest.
//!
//! Every seed is also verified as `coordinator verify` would: 27 touch pairs
//! with 0.1 mm tip noise, judged at once against the result's error model
//! (`b2b_calib::metrics::BoundCheck`). Under the random structures the check
//! must stay quiet; under `e` the study counts what it finds, and calibrates
//! again with the accuracy it suggests, then checks that result against a
//! second set of touches.
//!
//! `cargo bench -p b2b-sim --bench error_models` runs and asserts the study and prints the table
//! (`cargo test --benches` runs its smoke mode).

use b2b_calib::base_to_base::{BaseToBaseInitial, refine_base_to_base};
use b2b_calib::camera::CameraModel;
use b2b_calib::estimate::{RobotCaptures, estimate_base_to_base};
use b2b_calib::handeye::{self, HandEyeMethod, RobotWorldMethod};
use b2b_calib::metrics::{predicted_error, verify_touches};
use b2b_calib::pose::{adjoint, left_difference, perturb_left, skew};
use b2b_calib::refine::{BoardCapture, NoiseFrame, NoiseModel, RefineOptions, RobotNoise};
use b2b_calib::synth::{board_points, fit_pose};
use b2b_robot::{Arm, IiwaModel, IkOptions, Joints};
use b2b_sim::generate::look_at;
use nalgebra::{Matrix6, Point2, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

type Iso3 = nalgebra::Isometry3<f64>;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Structure {
    BaseAxes,
    Tool,
    BaseOrigin,
    Encoder,
    Dh,
    Typo,
    JointOffsets,
    Gravity,
    Backlash,
    TimeSkew,
}

impl Structure {
    fn label(&self) -> &'static str {
        match self {
            Structure::BaseAxes => "a base-axes",
            Structure::Tool => "b tool",
            Structure::BaseOrigin => "c base-origin",
            Structure::Encoder => "d encoder",
            Structure::Dh => "e DH",
            Structure::Typo => "f typo rows",
            Structure::JointOffsets => "g joint zeros",
            Structure::Gravity => "h gravity",
            Structure::Backlash => "i backlash",
            Structure::TimeSkew => "j time skew",
        }
    }

    /// No random model describes it: the limit is the fit to the true
    /// flange poses, and the covariance is not expected to hold it.
    fn systematic(&self) -> bool {
        !matches!(
            self,
            Structure::BaseAxes
                | Structure::Tool
                | Structure::BaseOrigin
                | Structure::Encoder
                | Structure::Typo
        )
    }

    /// The real-arm structures `g`-`j`, studied on the checkerboard with 30
    /// captures only.
    fn real_arm(&self) -> bool {
        self.systematic() && *self != Structure::Dh
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Board {
    Checkerboard,
    Charuco,
}

const SIGMA_T_1X: f64 = 0.05e-3;
const SIGMA_R_1X_DEG: f64 = 0.01;
const ENCODER_1X_DEG: f64 = 0.004;
const DH_LENGTH_1X: f64 = 0.03e-3;
const DH_ANGLE_1X_DEG: f64 = 0.002;
const PIXEL_SIGMA: f64 = 0.15;
const JOINT_OFFSET_1X_DEG: f64 = 0.004;
/// rad per N m: the part of the joints' yield the controller leaves.
const COMPLIANCE_1X: f64 = 2e-6;
const BACKLASH_1X_DEG: f64 = 0.004;
const TIME_SKEW_1X_S: f64 = 1e-3;
/// How long a move to the next view takes (s).
const MOVE_S: f64 = 2.0;
/// The iiwa 14's link masses (kg), links 1 to 7, and the camera's at the
/// flange.
const LINK_MASS_KG: [f64; 7] = [4.0, 4.0, 3.0, 2.7, 1.7, 1.8, 0.3];
const PAYLOAD_KG: f64 = 0.6;

/// Each joint's gravity torque (N m) at `q`: the gradient of the arm's
/// potential energy, each link's mass at the middle of its two joint frames.
fn gravity_torque(arm: &Arm, q: &Joints) -> [f64; 7] {
    let potential = |q: &Joints| {
        let f = arm.frames(q);
        let mut v = 0.0;
        for (i, m) in LINK_MASS_KG.iter().enumerate() {
            let a = f[i + 1].translation.vector;
            let b = f[(i + 2).min(7)].translation.vector;
            v += m * 9.81 * 0.5 * (a.z + b.z);
        }
        v + PAYLOAD_KG * 9.81 * f[7].translation.vector.z
    };
    std::array::from_fn(|i| {
        let h = 1e-6;
        let (mut a, mut b) = (*q, *q);
        a[i] += h;
        b[i] -= h;
        (potential(&a) - potential(&b)) / (2.0 * h)
    })
}

fn gauss(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

fn gauss6(rng: &mut ChaCha8Rng, sr: f64, st: f64) -> Vector6<f64> {
    Vector6::new(
        sr * gauss(rng),
        sr * gauss(rng),
        sr * gauss(rng),
        st * gauss(rng),
        st * gauss(rng),
        st * gauss(rng),
    )
}

fn camera() -> CameraModel {
    CameraModel {
        width: 1280,
        height: 720,
        fx: 910.0,
        fy: 910.0,
        cx: 640.0,
        cy: 360.0,
        dist: [0.0; 8],
    }
}

/// One robot's generated captures and the truth behind them.
struct RobotData {
    captures: Vec<BoardCapture>,
    camera_from_target: Vec<Iso3>,
    /// Per capture: the true covariance of the reported pose's error (left, base).
    true_cov: Vec<Matrix6<f64>>,
    /// Per capture: the true flange pose.
    true_base_from_flange: Vec<Iso3>,
    /// Rows made gross typos.
    typos: Vec<usize>,
    /// The arm as it really is (for `e`, its DH parameters perturbed).
    true_arm: Arm,
}

struct Problem {
    robots: [RobotData; 2],
    base1_from_base2: Iso3,
    base1_from_target: Iso3,
    flange_from_camera: [Iso3; 2],
    board_centre: Point3<f64>,
    models: [IiwaModel; 2],
}

/// `left_difference(fk(q + h e_i), fk(q)) / h` for each joint: the map from joint
/// errors to the left perturbation of the flange pose in the base.
fn joint_map(arm: &Arm, q: &Joints) -> nalgebra::SMatrix<f64, 6, 7> {
    let f0 = arm.fk(q);
    let h = 1e-7;
    let mut j = nalgebra::SMatrix::<f64, 6, 7>::zeros();
    for i in 0..7 {
        let mut qh = *q;
        qh[i] += h;
        j.set_column(i, &(left_difference(&arm.fk(&qh), &f0) / h));
    }
    j
}

fn diag6(sr: f64, st: f64) -> Matrix6<f64> {
    Matrix6::from_diagonal(&Vector6::new(
        sr * sr,
        sr * sr,
        sr * sr,
        st * st,
        st * st,
        st * st,
    ))
}

fn board_geometry(board: Board) -> (Vec<Point3<f64>>, Point3<f64>) {
    let (cols, rows, square) = match board {
        Board::Checkerboard => (9, 6, 0.025),
        Board::Charuco => (6, 4, 0.035),
    };
    (
        board_points(cols, rows, square),
        Point3::new(
            (cols - 1) as f64 * square / 2.0,
            (rows - 1) as f64 * square / 2.0,
            0.0,
        ),
    )
}

/// One planned viewpoint and its standard-normal draws, shared by every
/// structure and magnitude of a seed (a paired design: cells differ only in
/// what is studied).
#[derive(Clone)]
struct View {
    q: Joints,
    delta: Vector6<f64>,
    dq: [f64; 7],
    pixel_noise: Vec<(f64, f64)>,
    keep: Vec<bool>,
}

#[derive(Clone)]
struct Geometry {
    base1_from_base2: Iso3,
    base1_from_target: Iso3,
    flange_from_camera: [Iso3; 2],
    models: [IiwaModel; 2],
    views: [Vec<View>; 2],
    /// Standard-normal DH draws per arm: d, a, alpha, theta per joint.
    dh: [[f64; 28]; 2],
}

fn plan_views(
    rng: &mut ChaCha8Rng,
    model: IiwaModel,
    base_from_target: &Iso3,
    flange_from_camera: &Iso3,
    board: Board,
    n: usize,
) -> Vec<View> {
    let nominal = Arm::new(model);
    let (points, centre) = board_geometry(board);
    let cam = camera();
    let ik = IkOptions {
        restarts: 1,
        max_iterations: 100,
        tolerance_m: 1e-7,
        tolerance_rad: 1e-7,
        ..Default::default()
    };
    let shoulder = Point3::new(0.0, 0.0, nominal.dh[0].d);
    let reach = nominal.dh[2].d + nominal.dh[4].d - 0.02;
    let mut views = Vec::with_capacity(n);
    let mut attempts = 0;
    while views.len() < n {
        attempts += 1;
        assert!(attempts < 400 * n, "could not plan {n} viewpoints");
        let tilt = rng.random_range(0.0..40f64.to_radians());
        let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
        let dist = rng.random_range(0.35..0.6);
        let dir = Vector3::new(
            tilt.sin() * azimuth.cos(),
            tilt.sin() * azimuth.sin(),
            -tilt.cos(),
        );
        let jitter = Vector3::new(
            rng.random_range(-0.03..0.03),
            rng.random_range(-0.03..0.03),
            0.0,
        );
        let roll = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let target_from_camera = look_at(
            &(centre + dir * dist),
            &(centre + jitter),
            &Vector3::x(),
            roll,
        );
        let desired = base_from_target * target_from_camera * flange_from_camera.inverse();
        let wrist = desired * Point3::new(0.0, 0.0, -nominal.dh[6].d);
        if (wrist - shoulder).norm() > reach {
            continue;
        }
        let Ok(q) = nominal.ik(&desired, &Arm::comfortable(), &ik) else {
            continue;
        };
        let camera_from_target = (nominal.fk(&q) * flange_from_camera).inverse() * base_from_target;
        let all_in = points.iter().all(|p| {
            cam.project(&(camera_from_target * p))
                .is_some_and(|uv| cam.contains(&uv))
        });
        if !all_in {
            continue;
        }
        let keep_share = rng.random_range(0.6..1.0);
        let keep: Vec<bool> = points
            .iter()
            .map(|_| board == Board::Checkerboard || rng.random::<f64>() < keep_share)
            .collect();
        if keep.iter().filter(|k| **k).count() < 8 {
            continue;
        }
        views.push(View {
            q,
            delta: gauss6(rng, 1.0, 1.0),
            dq: std::array::from_fn(|_| gauss(rng)),
            pixel_noise: points.iter().map(|_| (gauss(rng), gauss(rng))).collect(),
            keep,
        });
    }
    views
}

/// Geometries by (seed, captures, ChArUco), shared by every structure's test.
type GeometryCache = std::collections::HashMap<(u64, usize, bool), Geometry>;

/// Per seed: the default's, the limit's and each closed form's mean error.
type SeedErrors = (f64, f64, [f64; 7]);

fn geometry(seed: u64, n: usize, board: Board) -> Geometry {
    static CACHE: std::sync::OnceLock<std::sync::Mutex<GeometryCache>> = std::sync::OnceLock::new();
    let key = (seed, n, board == Board::Charuco);
    let cache = CACHE.get_or_init(Default::default);
    if let Some(g) = cache.lock().unwrap().get(&key) {
        return g.clone();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ ((n as u64) << 32) ^ ((key.2 as u64) << 40));
    let base1_from_base2 = Iso3::from_parts(
        Translation3::new(
            1.1 + rng.random_range(-0.05..0.05),
            rng.random_range(-0.1..0.1),
            0.0,
        ),
        UnitQuaternion::from_axis_angle(
            &Vector3::z_axis(),
            std::f64::consts::PI + rng.random_range(-0.3..0.3),
        ),
    );
    let base1_from_target = Iso3::from_parts(
        Translation3::new(0.55, rng.random_range(-0.05..0.05), 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-3.0..3.0)),
    );
    let hand_eye = |rng: &mut ChaCha8Rng| {
        Iso3::from_parts(
            Translation3::new(
                rng.random_range(-0.06..0.06),
                rng.random_range(-0.06..0.06),
                0.06,
            ),
            UnitQuaternion::from_scaled_axis(Vector3::new(
                rng.random_range(-0.1..0.1),
                rng.random_range(-0.1..0.1),
                rng.random_range(-3.0..3.0),
            )),
        )
    };
    let x = [hand_eye(&mut rng), hand_eye(&mut rng)];
    let models = [IiwaModel::Iiwa7R800, IiwaModel::Iiwa14R820];
    let targets = [
        base1_from_target,
        base1_from_base2.inverse() * base1_from_target,
    ];
    let views = [0, 1].map(|r| plan_views(&mut rng, models[r], &targets[r], &x[r], board, n));
    let dh = [0, 1].map(|_| std::array::from_fn(|_| gauss(&mut rng)));
    let g = Geometry {
        base1_from_base2,
        base1_from_target,
        flange_from_camera: x,
        models,
        views,
        dh,
    };
    cache.lock().unwrap().insert(key, g.clone());
    g
}

fn make_robot(
    g: &Geometry,
    r: usize,
    board: Board,
    structure: Structure,
    magnitude: f64,
) -> RobotData {
    let nominal = Arm::new(g.models[r]);
    let mut true_arm = nominal.clone();
    if structure == Structure::Dh {
        for (i, dh) in true_arm.dh.iter_mut().enumerate() {
            dh.d += magnitude * DH_LENGTH_1X * g.dh[r][4 * i];
            dh.a += magnitude * DH_LENGTH_1X * g.dh[r][4 * i + 1];
            dh.alpha += magnitude * DH_ANGLE_1X_DEG.to_radians() * g.dh[r][4 * i + 2];
            dh.theta += magnitude * DH_ANGLE_1X_DEG.to_radians() * g.dh[r][4 * i + 3];
        }
    }
    let base_from_target = if r == 0 {
        g.base1_from_target
    } else {
        g.base1_from_base2.inverse() * g.base1_from_target
    };
    let flange_from_camera = g.flange_from_camera[r];
    let (points, _) = board_geometry(board);
    let cam = camera();
    let sr = magnitude * SIGMA_R_1X_DEG.to_radians();
    let st = magnitude * SIGMA_T_1X;
    let sq = magnitude * ENCODER_1X_DEG.to_radians();
    let mut out = RobotData {
        captures: vec![],
        camera_from_target: vec![],
        true_cov: vec![],
        true_base_from_flange: vec![],
        typos: vec![],
        true_arm: true_arm.clone(),
    };
    for (k, v) in g.views[r].iter().enumerate() {
        let q = v.q;
        let fk = nominal.fk(&q);
        // Where the arm really stands for `g`-`j` (the joints it reports: `q`).
        let before = if k == 0 {
            Arm::comfortable()
        } else {
            g.views[r][k - 1].q
        };
        let after = g.views[r].get(k + 1).map_or(q, |v| v.q);
        let dq: [f64; 7] = match structure {
            Structure::JointOffsets => std::array::from_fn(|i| {
                magnitude * JOINT_OFFSET_1X_DEG.to_radians() * g.dh[r][4 * i + 3]
            }),
            Structure::Gravity => {
                let tau = gravity_torque(&nominal, &q);
                std::array::from_fn(|i| -magnitude * COMPLIANCE_1X * tau[i])
            }
            Structure::Backlash => std::array::from_fn(|i| {
                0.5 * magnitude * BACKLASH_1X_DEG.to_radians() * (q[i] - before[i]).signum()
            }),
            // The image is of `q`; the pose read TIME_SKEW later, on the way on.
            Structure::TimeSkew => {
                std::array::from_fn(|i| -magnitude * TIME_SKEW_1X_S * (after[i] - q[i]) / MOVE_S)
            }
            _ => [0.0; 7],
        };
        let delta = Vector6::new(
            sr * v.delta[0],
            sr * v.delta[1],
            sr * v.delta[2],
            st * v.delta[3],
            st * v.delta[4],
            st * v.delta[5],
        );
        let (true_flange, reported, cov) = match structure {
            Structure::BaseAxes | Structure::Typo => {
                let rot =
                    UnitQuaternion::from_scaled_axis(Vector3::new(delta[0], delta[1], delta[2]));
                let reported = Iso3::from_parts(
                    Translation3::from(
                        fk.translation.vector + Vector3::new(delta[3], delta[4], delta[5]),
                    ),
                    rot * fk.rotation,
                );
                let mut s = Matrix6::identity();
                s.fixed_view_mut::<3, 3>(3, 0)
                    .copy_from(&skew(&fk.translation.vector));
                (fk, reported, s * diag6(sr, st) * s.transpose())
            }
            Structure::Tool => {
                let reported = fk * perturb_left(&delta, &Iso3::identity());
                let ad = adjoint(&fk);
                (fk, reported, ad * diag6(sr, st) * ad.transpose())
            }
            Structure::BaseOrigin => (fk, perturb_left(&delta, &fk), diag6(sr, st)),
            Structure::Encoder => {
                let qm: Joints = std::array::from_fn(|i| q[i] + sq * v.dq[i]);
                let j = joint_map(&nominal, &q);
                (fk, nominal.fk(&qm), j * j.transpose() * sq * sq)
            }
            Structure::Dh => (true_arm.fk(&q), fk, Matrix6::zeros()),
            Structure::JointOffsets
            | Structure::Gravity
            | Structure::Backlash
            | Structure::TimeSkew => {
                let q_true: Joints = std::array::from_fn(|i| q[i] + dq[i]);
                (nominal.fk(&q_true), fk, Matrix6::zeros())
            }
        };
        let camera_from_target = (true_flange * flange_from_camera).inverse() * base_from_target;
        let mut obs: Vec<(usize, Point2<f64>)> = Vec::new();
        for (k, p) in points.iter().enumerate() {
            if !v.keep[k] {
                continue;
            }
            if let Some(uv) = cam.project(&(camera_from_target * p)) {
                let noisy = Point2::new(
                    uv.x + PIXEL_SIGMA * v.pixel_noise[k].0,
                    uv.y + PIXEL_SIGMA * v.pixel_noise[k].1,
                );
                if cam.contains(&noisy) {
                    obs.push((k, noisy));
                }
            }
        }
        let fitted = fit_pose(&cam, &points, &obs, &camera_from_target).expect("pose fit");
        out.captures.push(BoardCapture {
            base_from_flange: reported,
            target_points: obs.iter().map(|(k, _)| points[*k]).collect(),
            pixels: obs.iter().map(|(_, uv)| *uv).collect(),
            target: 0,
        });
        out.camera_from_target.push(fitted);
        out.true_cov.push(cov);
        out.true_base_from_flange.push(true_flange);
    }
    if structure == Structure::Typo {
        // One typo in 15 captures, two in 30: tx off by 65 cm; a rotation off by 10°.
        let n = out.captures.len();
        let a = n / 3;
        let m = out.captures[a].base_from_flange;
        out.captures[a].base_from_flange = Iso3::from_parts(
            Translation3::from(m.translation.vector + Vector3::new(0.65, 0.0, 0.0)),
            m.rotation,
        );
        out.typos.push(a);
        if n >= 30 {
            let b = 2 * n / 3;
            let m = out.captures[b].base_from_flange;
            out.captures[b].base_from_flange = Iso3::from_parts(
                m.translation,
                UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 10f64.to_radians())
                    * m.rotation,
            );
            out.typos.push(b);
        }
    }
    out
}

fn problem(seed: u64, structure: Structure, magnitude: f64, n: usize, board: Board) -> Problem {
    let g = geometry(seed, n, board);
    let robots = [0, 1].map(|r| make_robot(&g, r, board, structure, magnitude));
    Problem {
        robots,
        base1_from_base2: g.base1_from_base2,
        base1_from_target: g.base1_from_target,
        flange_from_camera: g.flange_from_camera,
        board_centre: board_geometry(board).1,
        models: g.models,
    }
}

/// Pointer length from the flange to its tip along the flange's z axis.
const TIP_M: f64 = 0.15;

/// Where a robot with the true arm, touching `point_in_base` with a pointer
/// held straight down, reports the tip: through its nominal kinematics, as a
/// touch-point verification records it. `None` when the pose is out of reach.
fn reported_touch(
    nominal: &Arm,
    true_arm: &Arm,
    point_in_base: &Point3<f64>,
) -> Option<Point3<f64>> {
    let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let flange = Iso3::from_parts(
        Translation3::from(point_in_base.coords + Vector3::new(0.0, 0.0, TIP_M)),
        down,
    );
    let ik = IkOptions {
        restarts: 3,
        max_iterations: 200,
        tolerance_m: 1e-9,
        tolerance_rad: 1e-9,
        ..Default::default()
    };
    let q = true_arm.ik(&flange, &Arm::comfortable(), &ik).ok()?;
    Some(nominal.fk(&q) * Point3::new(0.0, 0.0, TIP_M))
}

/// Per touch location both robots reach: where robot 1 reports its tip (in
/// base1) and where robot 2 reports its own (in base2), the touch pairs of
/// `coordinator verify`. Through the true kinematics for `e`; the arms are
/// exact otherwise (every point reached).
fn touch_pairs(
    p: &Problem,
    structure: Structure,
    points: &[Point3<f64>],
) -> Vec<(Point3<f64>, Point3<f64>)> {
    let nominal = p.models.map(Arm::new);
    let exact = structure != Structure::Dh;
    points
        .iter()
        .filter_map(|pt| {
            let in_base2 = p.base1_from_base2.inverse() * pt;
            if exact {
                return Some((*pt, in_base2));
            }
            let p1 = reported_touch(&nominal[0], &p.robots[0].true_arm, pt)?;
            let p2 = reported_touch(&nominal[1], &p.robots[1].true_arm, &in_base2)?;
            Some((p1, p2))
        })
        .collect()
}

/// The distance between where robot 1 reports its tip and where the estimate
/// maps robot 2's report, per touch. This is what `coordinator verify`
/// measures on real arms: errors common to the calibration's and the touches'
/// configurations cancel in it.
fn operational_errors(pairs: &[(Point3<f64>, Point3<f64>)], estimate: &Iso3) -> Vec<f64> {
    pairs
        .iter()
        .map(|(p1, p2)| (estimate * p2 - p1).norm())
        .collect()
}

/// Each pointer tip's noise in the study's verifications (per axis).
const TIP_SIGMA_M: f64 = 0.1e-3;

/// The touch pairs as a verification records them: each tip with its noise.
fn noisy_pairs(
    pairs: &[(Point3<f64>, Point3<f64>)],
    rng: &mut ChaCha8Rng,
) -> Vec<(Point3<f64>, Point3<f64>)> {
    let mut noise = || Vector3::new(gauss(rng), gauss(rng), gauss(rng)) * TIP_SIGMA_M;
    pairs
        .iter()
        .map(|(a, b)| (a + noise(), b + noise()))
        .collect()
}

/// The 95th percentile of sorted values (the nearest rank).
fn p95(sorted: &[f64]) -> f64 {
    sorted[((sorted.len() - 1) as f64 * 0.95).round() as usize]
}

/// 27 touch locations: a 0.3 m cube centred on the board (in base1).
fn touch_points(centre_in_base1: &Point3<f64>) -> Vec<Point3<f64>> {
    let mut pts = Vec::with_capacity(27);
    for i in 0..3 {
        for j in 0..3 {
            for k in 0..3 {
                let o = Vector3::new(i as f64, j as f64, k as f64) * 0.15 - Vector3::repeat(0.15);
                pts.push(centre_in_base1 + o);
            }
        }
    }
    pts
}

/// Per touch point, |estimate - truth| where each maps base2 points into base1.
fn touch_errors(estimate: &Iso3, truth: &Iso3, points: &[Point3<f64>]) -> Vec<f64> {
    let d = estimate * truth.inverse();
    points.iter().map(|p| (d * p - p).norm()).collect()
}

const CLOSED: [&str; 7] = [
    "tsai",
    "park",
    "horaud",
    "andreff",
    "daniilidis",
    "shah",
    "li",
];

/// `base1_from_base2` of each closed form (both robots by the same method).
fn closed_forms(p: &Problem) -> Vec<Option<Iso3>> {
    let board_pose = |r: &RobotData, k: usize| -> Option<Iso3> {
        let b: Vec<Iso3> = r.captures.iter().map(|c| c.base_from_flange).collect();
        let c = &r.camera_from_target;
        let methods = [
            HandEyeMethod::Tsai,
            HandEyeMethod::Park,
            HandEyeMethod::Horaud,
            HandEyeMethod::Andreff,
            HandEyeMethod::Daniilidis,
        ];
        if k < 5 {
            let x = handeye::hand_eye(&b, c, methods[k]).ok()?;
            handeye::base_from_target_given(&x, &b, c).ok()
        } else {
            let m = if k == 5 {
                RobotWorldMethod::Shah
            } else {
                RobotWorldMethod::Li
            };
            handeye::robot_world(&b, c, m)
                .ok()
                .map(|rw| rw.base_from_target)
        }
    };
    (0..7)
        .map(|k| {
            let w1 = board_pose(&p.robots[0], k)?;
            let w2 = board_pose(&p.robots[1], k)?;
            Some(w1 * w2.inverse())
        })
        .collect()
}

/// The maximum-likelihood limit (or, for DH errors, the true-flange bound).
fn limit(p: &Problem, structure: Structure) -> Iso3 {
    let cam = camera();
    let mut caps: [Vec<BoardCapture>; 2] = [vec![], vec![]];
    let mut covs = Vec::new();
    for (r, robot) in p.robots.iter().enumerate() {
        for (i, c) in robot.captures.iter().enumerate() {
            if robot.typos.contains(&i) {
                continue;
            }
            let mut c = c.clone();
            if structure.systematic() {
                c.base_from_flange = robot.true_base_from_flange[i];
            }
            caps[r].push(c);
            covs.push(robot.true_cov[i]);
        }
    }
    let options = RefineOptions {
        noise: if structure.systematic() {
            NoiseModel::Fixed(NoiseFrame::Base)
        } else {
            NoiseModel::PerCapture(covs)
        },
        robot_noise: RobotNoise {
            sigma_t_m: 0.0,
            sigma_r_rad: 0.0,
        },
        capture_chi2_limit: f64::INFINITY,
        ..Default::default()
    };
    let initial = BaseToBaseInitial {
        flange_from_camera: p.flange_from_camera,
        base1_from_target: p.base1_from_target,
        base1_from_base2: p.base1_from_base2,
    };
    refine_base_to_base([&cam, &cam], [&caps[0], &caps[1]], &initial, &options)
        .expect("limit fit")
        .base1_from_base2
}

struct CellResult {
    per_seed: Vec<SeedErrors>,
    default_mean: f64,
    limit_mean: f64,
    closed_mean: [f64; 7],
    closed_failed: [usize; 7],
    true_p95: f64,
    predicted_p95: f64,
    coverage: f64,
    typos_caught: usize,
    typos_total: usize,
    clean_rejected: usize,
    /// For `e`: the errors a touch-point verification would see.
    operational: Option<Operational>,
    /// For `e`: the default with the arms' accuracy given.
    accuracy_given: Option<Recalibrated>,
    /// Seeds whose verification (`coordinator verify`'s check of the touches
    /// against the result's error model) calls the offset, or the scatter,
    /// beyond chance.
    offset_flags: usize,
    scatter_flags: usize,
    /// Over the seeds whose verification passes: (seed, point) errors inside
    /// the predicted p95, and all.
    accepted: (usize, usize),
    /// For `e`: the default given the accuracy its own verification suggests.
    from_touches: Option<Recalibrated>,
}

/// For `e`: the default estimator calibrated again with an accuracy for the
/// arms (`--robot-accuracy-mm` and `-deg`), as [`Recalibration`] sums it.
///
/// Two accuracies: the arms' own (the RMS per axis of the reported flange
/// poses' error over the views, at the flange, the larger arm's: what a spec
/// sheet or a laser-tracker check of the arm states), and the one the first
/// result's verification suggested (`BoundCheck::offset_sigma_m` and
/// `offset_sigma_rad` where it found the offset beyond chance, 0 elsewhere, as
/// an operator would leave it).
struct Recalibrated {
    sigma_t_m: f64,
    sigma_r_rad: f64,
    true_p95: f64,
    predicted_p95: f64,
    coverage: f64,
    /// Against touches: the verification's own for the arms' accuracy; a
    /// second verification at other points for the suggested one (the first
    /// one's touches chose it).
    touch_coverage: f64,
    /// The first result against those second touches.
    first_touch_coverage: Option<f64>,
}

impl Recalibrated {
    fn row(&self, cell: &str) -> String {
        let first = self
            .first_touch_coverage
            .map(|c| format!(" ({:.0}%)", c * 100.0))
            .unwrap_or_default();
        format!(
            "| {cell} | {:.3} mm, {:.4}° | {:.3} / {:.3} | {:.2} | {:.0}% | {:.0}%{first} |",
            self.sigma_t_m * 1e3,
            self.sigma_r_rad.to_degrees(),
            self.true_p95 * 1e3,
            self.predicted_p95 * 1e3,
            self.predicted_p95 / self.true_p95,
            self.coverage * 100.0,
            self.touch_coverage * 100.0
        )
    }
}

/// Sums over seeds of the default estimator calibrated again with an accuracy.
#[derive(Default)]
struct Recalibration {
    sigma_t_m: f64,
    sigma_r_rad: f64,
    errors: Vec<f64>,
    predicted_p95: f64,
    covered: usize,
    touch_covered: usize,
    touches: usize,
    first_touch_covered: Option<usize>,
}

impl Recalibration {
    /// Calibrates again with `accuracy` and tallies the result against the
    /// truth at `points` and against `touches` (the pairs at `touch_at`).
    fn add(
        &mut self,
        inputs: &[RobotCaptures<'_>],
        accuracy: RobotNoise,
        truth: &Iso3,
        points: &[Point3<f64>],
        touch_at: &[Point3<f64>],
        touches: &[(Point3<f64>, Point3<f64>)],
    ) {
        let options = RefineOptions {
            systematic: accuracy,
            ..RefineOptions::default()
        };
        let again = estimate_base_to_base([&inputs[0], &inputs[1]], &options)
            .expect("default estimator, calibrated again with an accuracy");
        let estimate = again.estimate.base1_from_base2;
        let errors = touch_errors(&estimate, truth, points);
        let (_, p95) = predicted_error(&again.estimate.covariance, points, 0.0);
        let (_, touch_p95) = predicted_error(&again.estimate.covariance, touch_at, 0.0);
        self.sigma_t_m += accuracy.sigma_t_m;
        self.sigma_r_rad += accuracy.sigma_r_rad;
        self.predicted_p95 += p95;
        self.covered += errors.iter().filter(|e| **e <= p95).count();
        self.errors.extend(errors);
        let touched = operational_errors(touches, &estimate);
        self.touch_covered += touched.iter().filter(|e| **e <= touch_p95).count();
        self.touches += touched.len();
    }

    fn finish(mut self, seeds: f64) -> Option<Recalibrated> {
        if self.errors.is_empty() {
            return None;
        }
        self.errors.sort_by(f64::total_cmp);
        let touches = self.touches.max(1) as f64;
        Some(Recalibrated {
            sigma_t_m: self.sigma_t_m / seeds,
            sigma_r_rad: self.sigma_r_rad / seeds,
            true_p95: p95(&self.errors),
            predicted_p95: self.predicted_p95 / seeds,
            coverage: self.covered as f64 / self.errors.len() as f64,
            touch_coverage: self.touch_covered as f64 / touches,
            first_touch_coverage: self.first_touch_covered.map(|c| c as f64 / touches),
        })
    }
}

/// The arms' own accuracy (see [`Recalibrated`]).
fn arm_accuracy(p: &Problem) -> RobotNoise {
    let (mut t, mut r) = (0.0f64, 0.0f64);
    for robot in &p.robots {
        let (mut st, mut sr) = (0.0, 0.0);
        for (c, truth) in robot.captures.iter().zip(&robot.true_base_from_flange) {
            let d = truth.inverse() * c.base_from_flange;
            st += d.translation.vector.norm_squared();
            sr += d.rotation.scaled_axis().norm_squared();
        }
        let n = 3.0 * robot.captures.len() as f64;
        t = t.max((st / n).sqrt());
        r = r.max((sr / n).sqrt());
    }
    RobotNoise {
        sigma_t_m: t,
        sigma_r_rad: r,
    }
}

/// The touch-point view of one cell (see [`operational_errors`]).
struct Operational {
    p95: f64,
    mean: f64,
    coverage: f64,
    reached: f64,
}

fn run_cell(
    structure: Structure,
    magnitude: f64,
    n: usize,
    board: Board,
    seeds: u64,
) -> CellResult {
    let cam = camera();
    let mut default_sum = 0.0;
    let mut limit_sum = 0.0;
    let mut closed_sum = [0.0; 7];
    let mut closed_failed = [0; 7];
    let mut all_errors = Vec::new();
    let mut predicted = 0.0;
    let mut covered = 0;
    let mut total_points = 0;
    let (mut op_errors, mut op_covered, mut op_total) = (Vec::new(), 0, 0);
    let mut given = Recalibration::default();
    let mut suggested = Recalibration {
        first_touch_covered: Some(0),
        ..Default::default()
    };
    let (mut caught, mut typos, mut clean_rejected) = (0, 0, 0);
    let (mut offset_flags, mut scatter_flags) = (0, 0);
    let (mut accepted_covered, mut accepted_points) = (0, 0);
    let mut per_seed = Vec::new();
    for s in 0..seeds {
        let seed = s;
        let p = problem(seed, structure, magnitude, n, board);
        let points = touch_points(&(p.base1_from_target * p.board_centre));
        let mean = |t: &Iso3| {
            let e = touch_errors(t, &p.base1_from_base2, &points);
            e.iter().sum::<f64>() / e.len() as f64
        };
        let inputs: Vec<RobotCaptures<'_>> = p
            .robots
            .iter()
            .map(|r| RobotCaptures {
                camera: &cam,
                captures: &r.captures,
                camera_from_target: &r.camera_from_target,
            })
            .collect();
        let run = estimate_base_to_base([&inputs[0], &inputs[1]], &RefineOptions::default())
            .expect("default estimator");
        let est = run.estimate.base1_from_base2;
        let pairs = touch_pairs(&p, structure, &points);
        let mut tips = ChaCha8Rng::seed_from_u64(0x7195 ^ seed);
        let check = verify_touches(
            &est,
            &run.estimate.covariance,
            &noisy_pairs(&pairs, &mut tips),
            TIP_SIGMA_M,
        )
        .expect("verification")
        .bound_check;
        offset_flags += usize::from(check.offset.beyond_chance());
        scatter_flags += usize::from(check.scatter.beyond_chance());
        let accepted = !check.beyond_chance();
        let default_error = mean(&est);
        default_sum += default_error;
        let errors = touch_errors(&est, &p.base1_from_base2, &points);
        let (_, p95) = predicted_error(&run.estimate.covariance, &points, 0.0);
        predicted += p95;
        covered += errors.iter().filter(|e| **e <= p95).count();
        total_points += errors.len();
        if accepted {
            accepted_covered += errors.iter().filter(|e| **e <= p95).count();
            accepted_points += errors.len();
        }
        all_errors.extend(errors);
        if structure == Structure::Dh {
            given.add(
                &inputs,
                arm_accuracy(&p),
                &p.base1_from_base2,
                &points,
                &points,
                &pairs,
            );
            // As an operator would: calibrate again with the accuracy the
            // verification suggests when it found the offset beyond chance,
            // and verify that at other points (the cube moved by 7, -5 and 5
            // cm).
            let accuracy = if check.offset.beyond_chance() {
                RobotNoise {
                    sigma_t_m: check.offset_sigma_m,
                    sigma_r_rad: check.offset_sigma_rad,
                }
            } else {
                RobotNoise {
                    sigma_t_m: 0.0,
                    sigma_r_rad: 0.0,
                }
            };
            let others = touch_points(
                &(p.base1_from_target * p.board_centre + Vector3::new(0.07, -0.05, 0.05)),
            );
            let second = touch_pairs(&p, structure, &others);
            suggested.add(
                &inputs,
                accuracy,
                &p.base1_from_base2,
                &points,
                &others,
                &second,
            );
            // The first result, against the same second touches.
            let (_, first_p95) = predicted_error(&run.estimate.covariance, &others, 0.0);
            if let Some(c) = &mut suggested.first_touch_covered {
                *c += operational_errors(&second, &est)
                    .iter()
                    .filter(|e| **e <= first_p95)
                    .count();
            }
            let e = operational_errors(&pairs, &est);
            op_covered += e.iter().filter(|v| **v <= p95).count();
            op_total += 27;
            op_errors.extend(e);
        }
        for (r, robot) in p.robots.iter().enumerate() {
            for (i, rej) in run.rejections[r].iter().enumerate() {
                match (robot.typos.contains(&i), rej.is_some()) {
                    (true, true) => caught += 1,
                    (false, true) => clean_rejected += 1,
                    _ => {}
                }
            }
            typos += robot.typos.len();
        }
        let limit_error = mean(&limit(&p, structure));
        limit_sum += limit_error;
        let mut closed_errors = [f64::INFINITY; 7];
        for (k, c) in closed_forms(&p).into_iter().enumerate() {
            match c {
                Some(t) => {
                    closed_errors[k] = mean(&t);
                    closed_sum[k] += closed_errors[k];
                }
                None => {
                    closed_failed[k] += 1;
                    closed_sum[k] += f64::INFINITY;
                }
            }
        }
        per_seed.push((default_error, limit_error, closed_errors));
    }
    all_errors.sort_by(f64::total_cmp);
    op_errors.sort_by(f64::total_cmp);
    let operational = (!op_errors.is_empty()).then(|| Operational {
        p95: p95(&op_errors),
        mean: op_errors.iter().sum::<f64>() / op_errors.len() as f64,
        coverage: op_covered as f64 / op_errors.len() as f64,
        reached: op_errors.len() as f64 / op_total as f64,
    });
    let sf = seeds as f64;
    let accuracy_given = given.finish(sf);
    let from_touches = suggested.finish(sf);
    CellResult {
        accepted: (accepted_covered, accepted_points),
        offset_flags,
        scatter_flags,
        from_touches,
        per_seed,
        default_mean: default_sum / sf,
        limit_mean: limit_sum / sf,
        closed_mean: closed_sum.map(|v| v / sf),
        closed_failed,
        true_p95: p95(&all_errors),
        predicted_p95: predicted / sf,
        coverage: covered as f64 / total_points as f64,
        typos_caught: caught,
        typos_total: typos,
        clean_rejected,
        operational,
        accuracy_given,
    }
}

const MAGNITUDES: [f64; 3] = [0.5, 2.0, 5.0];
/// Seeds per cell: every cell is a paired comparison (all methods see the
/// same captures), so a dozen seeds separate the methods; a true p95 needs
/// more (with twelve it is about the largest of twelve draws). `B2B_STUDY_SEEDS`
/// runs more.
fn seeds() -> u64 {
    std::env::var("B2B_STUDY_SEEDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(24)
}

/// Runs every cell of one structure, prints its rows, asserts, and returns the
/// rows' pooled coverage.
fn study(structure: Structure) {
    let mut lines = Vec::new();
    let mut op_lines = Vec::new();
    let mut op_pooled = Vec::new();
    let mut given_lines = Vec::new();
    let mut given_pooled = Vec::new();
    let mut given_touch_pooled = Vec::new();
    let mut failures = Vec::new();
    let (mut covered, mut cells) = (0.0, 0.0);
    let mut below_truth = Vec::new();
    let (mut offset_flags, mut scatter_flags, mut checks) = (0, 0, 0);
    let (mut accepted_covered, mut accepted_points) = (0, 0);
    let mut check_lines = Vec::new();
    let mut touch_lines = Vec::new();
    let mut touch_pooled: Vec<(f64, f64, f64)> = vec![];
    let (boards, counts): (&[Board], &[usize]) = if structure.real_arm() {
        (&[Board::Checkerboard], &[30])
    } else {
        (&[Board::Checkerboard, Board::Charuco], &[15, 30])
    };
    for &board in boards {
        for &n in counts {
            for m in MAGNITUDES {
                let r = run_cell(structure, m, n, board, seeds());
                let (best_k, best) = r
                    .closed_mean
                    .iter()
                    .enumerate()
                    .min_by(|a, b| a.1.total_cmp(b.1))
                    .map(|(k, v)| (k, *v))
                    .unwrap();
                let cell = format!(
                    "{:<14} {:>4.1}x {:>2} {:<6}",
                    structure.label(),
                    m,
                    n,
                    if board == Board::Checkerboard {
                        "chess"
                    } else {
                        "charuco"
                    }
                );
                lines.push(format!(
                    "| {cell} | {:.3} | {:.3}{} | {:.3} ({}) | {:.2} | {:.2} | {:.3} / {:.3} | {:.0}% | {} |",
                    r.default_mean * 1e3,
                    r.limit_mean * 1e3,
                    if structure.systematic() { " bound" } else { "" },
                    best * 1e3,
                    CLOSED[best_k],
                    r.default_mean / best,
                    r.default_mean / r.limit_mean,
                    r.true_p95 * 1e3,
                    r.predicted_p95 * 1e3,
                    r.coverage * 100.0,
                    if structure == Structure::Typo {
                        format!("{}/{} typos out, {} clean out", r.typos_caught, r.typos_total, r.clean_rejected)
                    } else {
                        format!("{} clean out", r.clean_rejected)
                    },
                ));
                let _ = r.closed_failed;
                offset_flags += r.offset_flags;
                accepted_covered += r.accepted.0;
                accepted_points += r.accepted.1;
                scatter_flags += r.scatter_flags;
                checks += r.per_seed.len();
                check_lines.push(format!(
                    "| {cell} | {} / {} | {} / {} |",
                    r.offset_flags,
                    r.per_seed.len(),
                    r.scatter_flags,
                    r.per_seed.len()
                ));
                if let Some(t) = &r.from_touches {
                    touch_lines.push(t.row(&cell));
                    touch_pooled.push((
                        t.coverage,
                        t.touch_coverage,
                        t.first_touch_coverage.unwrap_or(0.0),
                    ));
                }
                if let Some(g) = &r.accuracy_given {
                    given_lines.push(g.row(&cell));
                    given_touch_pooled.push(g.touch_coverage);
                    given_pooled.push(g.coverage);
                    // With the accuracy given, honest as the other structures are.
                    if g.predicted_p95 < 0.75 * g.true_p95 || g.predicted_p95 > 2.0 * g.true_p95 {
                        failures.push(format!(
                            "{cell}, accuracy given: predicted p95 {:.4} mm against a true p95 of {:.4} mm",
                            g.predicted_p95 * 1e3,
                            g.true_p95 * 1e3
                        ));
                    }
                }
                if let Some(o) = &r.operational {
                    op_lines.push(format!(
                        "| {cell} | {:.3} | {:.3} / {:.3} | {:.0}% | {:.0}% |",
                        o.mean * 1e3,
                        o.p95 * 1e3,
                        r.predicted_p95 * 1e3,
                        o.coverage * 100.0,
                        o.reached * 100.0
                    ));
                    op_pooled.push(o.coverage);
                }
                covered += r.coverage;
                cells += 1.0;
                // Ahead of every closed form and near the limit, judged on the
                // paired per-seed differences: worse only if the mean
                // difference exceeds two standard errors (and 2%).
                let worse = |ratio: f64, other: &dyn Fn(&SeedErrors) -> f64| {
                    let d: Vec<f64> = r.per_seed.iter().map(|s| s.0 - ratio * other(s)).collect();
                    let n = d.len() as f64;
                    let mean = d.iter().sum::<f64>() / n;
                    let sd = (d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
                    mean > 2.0 * sd / n.sqrt() && mean > 0.02 * r.default_mean
                };
                if worse(1.0, &|s| s.2[best_k]) {
                    failures.push(format!(
                        "{cell}: default {:.4} mm worse than the best closed form {:.4} mm",
                        r.default_mean * 1e3,
                        best * 1e3
                    ));
                }
                if !structure.systematic() {
                    if worse(1.25, &|s| s.1) {
                        failures.push(format!(
                            "{cell}: default {:.4} mm > 1.25 x limit {:.4} mm",
                            r.default_mean * 1e3,
                            r.limit_mean * 1e3
                        ));
                    }
                    // Honest p95: not far below the truth (the goal is at or above;
                    // see the README for the one cell below, 0.99x),
                    // not more than twice it.
                    if r.predicted_p95 < r.true_p95 {
                        below_truth.push((cell.clone(), r.predicted_p95 / r.true_p95));
                    }
                    if r.predicted_p95 < 0.75 * r.true_p95 || r.predicted_p95 > 2.0 * r.true_p95 {
                        failures.push(format!(
                            "{cell}: predicted p95 {:.4} mm against a true p95 of {:.4} mm",
                            r.predicted_p95 * 1e3,
                            r.true_p95 * 1e3
                        ));
                    }
                }
                if structure == Structure::Typo && r.typos_caught != r.typos_total {
                    failures.push(format!(
                        "{cell}: {} of {} typo rows left in",
                        r.typos_total - r.typos_caught,
                        r.typos_total
                    ));
                }
                if r.clean_rejected as f64 > 0.25 * seeds() as f64 {
                    failures.push(format!(
                        "{cell}: {} clean captures rejected in {} seeds",
                        r.clean_rejected,
                        seeds()
                    ));
                }
            }
        }
    }
    eprintln!(
        "| cell | default mm | limit mm | best closed form mm | default / best | default / limit | true / predicted p95 mm | inside p95 | rejections |"
    );
    for l in &lines {
        eprintln!("{l}");
    }
    let pooled = covered / cells;
    if !op_lines.is_empty() {
        eprintln!(
            "\nAs a touch-point verification sees it (both arms touch each point through their true kinematics and report it through the nominal):"
        );
        eprintln!("| cell | touch mean mm | true / predicted p95 mm | inside p95 | reached |");
        for l in &op_lines {
            eprintln!("{l}");
        }
        eprintln!(
            "pooled coverage against the touches: {:.1}%\n",
            100.0 * op_pooled.iter().sum::<f64>() / op_pooled.len() as f64
        );
    }
    eprintln!(
        "pooled coverage of the predicted p95: {:.1}%",
        pooled * 100.0
    );
    if !given_lines.is_empty() {
        eprintln!(
            "\nWith the arms' accuracy given (--robot-accuracy-mm/-deg: the reported flange poses' RMS error per axis over the views, the larger arm's):"
        );
        eprintln!(
            "| cell | accuracy given | true / predicted p95 mm | predicted / true | inside p95 | touches inside p95 |"
        );
        for l in &given_lines {
            eprintln!("{l}");
        }
        let given = given_pooled.iter().sum::<f64>() / given_pooled.len() as f64;
        eprintln!(
            "pooled coverage with the accuracy given: {:.1}%",
            100.0 * given
        );
        let touches = given_touch_pooled.iter().sum::<f64>() / given_touch_pooled.len() as f64;
        eprintln!(
            "pooled coverage against the touches with the accuracy given: {:.1}%",
            100.0 * touches
        );
        if !(0.90..=0.995).contains(&given) || touches < 0.90 {
            failures.push(format!(
                "pooled coverage with the accuracy given {given}, against the touches {touches}"
            ));
        }
    }
    eprintln!(
        "\nThe verification's check of the touches (0.1 mm tip noise per axis) against each result's error model, seeds called beyond chance:"
    );
    eprintln!("| cell | offset | scatter |");
    for l in &check_lines {
        eprintln!("{l}");
    }
    eprintln!(
        "pooled: offset {offset_flags} of {checks}, scatter {scatter_flags} of {checks}; coverage of the results it accepts {:.1}% ({accepted_points} seed-points)",
        100.0 * accepted_covered as f64 / accepted_points.max(1) as f64
    );
    let accepted = accepted_covered as f64 / accepted_points.max(1) as f64;
    if structure == Structure::Dh {
        // README: the offset found beyond chance in 122 of 288 seeds, the
        // scatter in 104; the results the verification accepts 80.8% inside
        // their bound. Held within 1.5x.
        let share = |k: usize| k as f64 / checks as f64;
        if share(offset_flags) < 122.0 / 288.0 / 1.5
            || share(scatter_flags) < 104.0 / 288.0 / 1.5
            || !(0.808 / 1.5..0.9).contains(&accepted)
        {
            failures.push(format!(
                "DH: offset beyond chance in {offset_flags} of {checks}, scatter in {scatter_flags}, accepted results' coverage {accepted}: update the README"
            ));
        }
    } else if !structure.systematic() && (offset_flags + scatter_flags) * 50 > checks {
        // A right (or conservative) error model is called wrong in 1% of
        // checks; README: none of 288 per structure.
        failures.push(format!(
            "the verification calls {offset_flags} offsets and {scatter_flags} scatters of {checks} beyond chance"
        ));
    }
    if !touch_lines.is_empty() {
        eprintln!(
            "\nCalibrated again with the accuracy the verification suggests when it finds the offset beyond chance (mean over seeds, 0 where it does not):"
        );
        eprintln!(
            "| cell | accuracy suggested | true / predicted p95 mm | predicted / true | inside p95 | second touches inside p95 (first result) |"
        );
        for l in &touch_lines {
            eprintln!("{l}");
        }
        let n = touch_pooled.len() as f64;
        let (truth, second, first) = (
            touch_pooled.iter().map(|t| t.0).sum::<f64>() / n,
            touch_pooled.iter().map(|t| t.1).sum::<f64>() / n,
            touch_pooled.iter().map(|t| t.2).sum::<f64>() / n,
        );
        eprintln!(
            "pooled coverage: {:.1}%, against a second set of touches {:.1}% (the first result: {:.1}%)",
            100.0 * truth,
            100.0 * second,
            100.0 * first
        );
        // README: 82.5% against the truth (below honest: the touches see less
        // of the error than there is), 92.8% against the second touches (the
        // first result 75.5%).
        if !(0.825 / 1.5..0.9).contains(&truth) || second < 0.9 || first > 0.9 {
            failures.push(format!(
                "calibrated again with the verification's accuracy: coverage {truth} against the truth, {second} against a second set of touches (the first result {first}): update the README"
            ));
        }
    }
    if !op_pooled.is_empty() {
        // The touch-point view does not rescue it: the touches stand in other
        // configurations than the views, so little of the error cancels.
        // README: 71.7%; held within 1.5x of it, and below honest.
        let op = op_pooled.iter().sum::<f64>() / op_pooled.len() as f64;
        assert!(
            (0.717 / 1.5..0.9).contains(&op),
            "DH coverage against touches {op}: update the README"
        );
    }
    if structure == Structure::Dh {
        // Systematic errors move the estimate without showing in the residuals;
        // the split-half check widens the covariance but cannot see the part
        // common to all captures. Pinned down: if this starts to hold, the
        // README's caveat is out of date.
        // README: 63%; held within 1.5x of it, and below honest.
        assert!(
            (0.63 / 1.5..0.9).contains(&pooled),
            "DH coverage {pooled}: update the README"
        );
    } else if !structure.systematic() && !(0.90..=0.995).contains(&pooled) {
        failures.push(format!("pooled coverage {pooled}"));
    }
    if structure.real_arm() {
        // docs/accuracy.md: pooled coverage g 64%, h 33% (flange poses alone
        // do not show a pose-dependent kinematic error, so the bound cannot
        // hold it), i 99%, j 99% (errors that vary from capture to capture:
        // the noise model sees them). Held within 1.5x; g and h below honest
        // so that the caveat cannot go stale, i and j honest.
        let stated: f64 = match structure {
            Structure::JointOffsets => 0.637,
            Structure::Gravity => 0.332,
            Structure::Backlash => 0.993,
            _ => 0.992,
        };
        let honest = matches!(structure, Structure::Backlash | Structure::TimeSkew);
        let within = (stated / 1.5..=(stated * 1.5).min(1.0)).contains(&pooled);
        if !within || honest != (pooled >= 0.90) {
            failures.push(format!(
                "{}: pooled coverage {pooled} (docs/accuracy.md: {stated})",
                structure.label()
            ));
        }
    }
    // README: the predicted p95 at or above the true one in 59 of the 60 cells
    // of a-d and f, the one below (in c) at 0.99x.
    if below_truth.len() > 1 || below_truth.iter().any(|(_, r)| *r < 0.95) {
        failures.push(format!(
            "predicted p95 below the true one in {} cells: {below_truth:?}",
            below_truth.len()
        ));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// Every structure, by the name its cells print under.
const STRUCTURES: [(&str, Structure); 10] = [
    ("structure_a_base_axes", Structure::BaseAxes),
    ("structure_b_tool", Structure::Tool),
    ("structure_c_base_origin", Structure::BaseOrigin),
    ("structure_d_encoder", Structure::Encoder),
    ("structure_e_dh", Structure::Dh),
    ("structure_f_typo_rows", Structure::Typo),
    ("structure_g_joint_zero_offsets", Structure::JointOffsets),
    ("structure_h_gravity_compliance", Structure::Gravity),
    ("structure_i_backlash", Structure::Backlash),
    ("structure_j_time_skew", Structure::TimeSkew),
];

/// The smoke mode (`cargo test --benches`, the gate): one cell of every
/// structure on two seeds, through every estimator, the default's error
/// finite and within a few millimetres; nothing of the study's statistics.
fn smoke(structure: Structure) {
    let n = if structure.real_arm() { 30 } else { 15 };
    let r = run_cell(structure, 2.0, n, Board::Checkerboard, 2);
    assert!(
        r.default_mean.is_finite() && r.default_mean < 5e-3,
        "{}: default {} m",
        structure.label(),
        r.default_mean
    );
    assert!(r.limit_mean.is_finite(), "{}: limit", structure.label());
    println!(
        "smoke {}: default {:.3} mm, limit {:.3} mm",
        structure.label(),
        r.default_mean * 1e3,
        r.limit_mean * 1e3
    );
}

/// `cargo bench -p b2b-sim --bench error_models [-- FILTER]` runs the study
/// (every cell, `B2B_STUDY_SEEDS` seeds, default 24) and asserts it; without
/// `--bench` (the gate's `cargo test --benches`) the smoke mode. FILTER keeps
/// the structures whose name contains it (`structure_g`). Two structures at a
/// time, one per core.
fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let full = args.iter().any(|a| a == "--bench");
    let filter: Vec<&String> = args.iter().filter(|a| !a.starts_with("--")).collect();
    let chosen: Vec<(&str, Structure)> = STRUCTURES
        .iter()
        .copied()
        .filter(|(name, _)| filter.is_empty() || filter.iter().any(|f| name.contains(f.as_str())))
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| {
                loop {
                    let k = next.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                    let Some((name, structure)) = chosen.get(k) else {
                        break;
                    };
                    if full {
                        study(*structure);
                    } else {
                        smoke(*structure);
                    }
                    println!("{name} ... ok");
                }
            });
        }
    });
}
