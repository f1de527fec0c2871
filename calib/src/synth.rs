//! Synthetic calibration problems with known ground truth.
//!
//! Every solver in this crate is tested (and benchmarked) on problems made here:
//! a board on a table, a camera on a flange by a known hand-eye, viewpoints spread
//! over a hemisphere above the board, corner pixels with Gaussian noise and flange
//! poses with the robot's own error. Generation is deterministic for a seed.

use nalgebra::{Point2, Point3, Translation3, UnitQuaternion, Vector3, Vector6};
use rand::{Rng, SeedableRng, rngs::StdRng};

use crate::camera::CameraModel;
use crate::pose::perturb_left;
use crate::{CalibError, Iso3};

/// The inner corners of a checkerboard, `(i * square, j * square, 0)`, row by row.
pub fn board_points(cols: usize, rows: usize, square: f64) -> Vec<Point3<f64>> {
    (0..rows)
        .flat_map(|j| {
            (0..cols).map(move |i| Point3::new(i as f64 * square, j as f64 * square, 0.0))
        })
        .collect()
}

/// How to make a problem.
#[derive(Debug, Clone)]
pub struct SynthConfig {
    pub captures: usize,
    pub board_cols: usize,
    pub board_rows: usize,
    pub square_m: f64,
    /// Standard deviation of corner pixels (px).
    pub pixel_sigma: f64,
    /// Robot flange error: translation (m) and rotation (rad) standard deviations.
    pub robot_sigma_t: f64,
    pub robot_sigma_r: f64,
    /// Camera-to-board distance range (m).
    pub distance: (f64, f64),
    /// Largest tilt of the viewing direction from the board normal (rad).
    pub max_tilt: f64,
    pub camera: CameraModel,
}

impl Default for SynthConfig {
    fn default() -> Self {
        SynthConfig {
            captures: 30,
            board_cols: 9,
            board_rows: 6,
            square_m: 0.025,
            pixel_sigma: 0.2,
            robot_sigma_t: 0.05e-3,
            robot_sigma_r: 0.01_f64.to_radians(),
            distance: (0.35, 0.6),
            max_tilt: 40f64.to_radians(),
            camera: CameraModel {
                width: 1280,
                height: 720,
                fx: 910.0,
                fy: 910.0,
                cx: 640.0,
                cy: 360.0,
                dist: [0.0; 8],
            },
        }
    }
}

/// One robot's synthetic captures and the truth behind them.
#[derive(Debug, Clone)]
pub struct SynthRobot {
    pub flange_from_camera: Iso3,
    pub base_from_target: Iso3,
    pub true_base_from_flange: Vec<Iso3>,
    /// What the controller reports: the true pose with the robot's error.
    pub base_from_flange: Vec<Iso3>,
    /// Per capture: (board corner index, noisy pixel) for corners inside the image.
    pub observations: Vec<Vec<(usize, Point2<f64>)>>,
    /// Per capture: the board pose fitted to the noisy pixels (what PnP would give).
    pub camera_from_target: Vec<Iso3>,
    pub board: Vec<Point3<f64>>,
}

/// A standard normal sample (Box-Muller: enough for simulated noise and Monte
/// Carlo, and keeps rand_distr out of the library).
pub(crate) fn gauss(rng: &mut StdRng) -> f64 {
    let u1: f64 = rng.random::<f64>().max(1e-300);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// A random rigid transform: rotation angle up to `max_angle`, translation in a box.
pub fn random_pose(rng: &mut StdRng, max_angle: f64, t_box: f64) -> Iso3 {
    let axis = Vector3::new(gauss(rng), gauss(rng), gauss(rng)).normalize();
    let angle = rng.random_range(0.0..max_angle);
    let t = Vector3::new(
        rng.random_range(-t_box..t_box),
        rng.random_range(-t_box..t_box),
        rng.random_range(-t_box..t_box),
    );
    Iso3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_scaled_axis(axis * angle),
    )
}

/// A camera pose looking at `centre` from `eye`, with a roll about the view axis.
fn look_at(eye: &Point3<f64>, centre: &Point3<f64>, roll: f64) -> Iso3 {
    let z = (centre - eye).normalize();
    let helper = if z.x.abs() < 0.9 {
        Vector3::x()
    } else {
        Vector3::y()
    };
    let x = helper.cross(&z).normalize();
    let y = z.cross(&x);
    let m = nalgebra::Matrix3::from_columns(&[x, y, z]);
    let r =
        UnitQuaternion::from_matrix(&m) * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll);
    Iso3::from_parts(Translation3::from(eye.coords), r)
}

/// Makes one robot's problem with the given truth.
pub fn make_robot(
    rng: &mut StdRng,
    cfg: &SynthConfig,
    flange_from_camera: Iso3,
    base_from_target: Iso3,
) -> Result<SynthRobot, CalibError> {
    let board = board_points(cfg.board_cols, cfg.board_rows, cfg.square_m);
    let centre_in_target = Point3::new(
        (cfg.board_cols - 1) as f64 * cfg.square_m / 2.0,
        (cfg.board_rows - 1) as f64 * cfg.square_m / 2.0,
        0.0,
    );
    let mut out = SynthRobot {
        flange_from_camera,
        base_from_target,
        true_base_from_flange: vec![],
        base_from_flange: vec![],
        observations: vec![],
        camera_from_target: vec![],
        board: board.clone(),
    };
    let mut attempts = 0;
    while out.observations.len() < cfg.captures {
        attempts += 1;
        if attempts > cfg.captures * 200 {
            return Err(CalibError::Synthesis {
                reason: "could not place viewpoints with the board in view",
            });
        }
        // The board's printed side faces -z of the target frame (z points into the board).
        let tilt = rng.random_range(0.0..cfg.max_tilt);
        let azimuth = rng.random_range(0.0..std::f64::consts::TAU);
        let dist = rng.random_range(cfg.distance.0..cfg.distance.1);
        let dir_in_target = Vector3::new(
            tilt.sin() * azimuth.cos(),
            tilt.sin() * azimuth.sin(),
            -tilt.cos(),
        );
        let look_jitter = Vector3::new(
            rng.random_range(-0.03..0.03),
            rng.random_range(-0.03..0.03),
            0.0,
        );
        let eye_in_target = centre_in_target + dir_in_target * dist;
        let roll = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        let target_from_camera = look_at(&eye_in_target, &(centre_in_target + look_jitter), roll);
        let camera_from_target = target_from_camera.inverse();
        let pixels: Vec<(usize, Point2<f64>)> = board
            .iter()
            .enumerate()
            .filter_map(|(k, p)| {
                let uv = cfg.camera.project(&(camera_from_target * p))?;
                let noisy = Point2::new(
                    uv.x + cfg.pixel_sigma * gauss(rng),
                    uv.y + cfg.pixel_sigma * gauss(rng),
                );
                cfg.camera.contains(&noisy).then_some((k, noisy))
            })
            .collect();
        if pixels.len() < board.len() {
            continue;
        }
        let true_base_from_flange =
            base_from_target * target_from_camera * flange_from_camera.inverse();
        let noise = Vector6::new(
            cfg.robot_sigma_r * gauss(rng),
            cfg.robot_sigma_r * gauss(rng),
            cfg.robot_sigma_r * gauss(rng),
            cfg.robot_sigma_t * gauss(rng),
            cfg.robot_sigma_t * gauss(rng),
            cfg.robot_sigma_t * gauss(rng),
        );
        let fitted = fit_pose(&cfg.camera, &board, &pixels, &camera_from_target)?;
        out.true_base_from_flange.push(true_base_from_flange);
        out.base_from_flange
            .push(perturb_left(&noise, &true_base_from_flange));
        out.camera_from_target.push(fitted);
        out.observations.push(pixels);
    }
    Ok(out)
}

/// A random single-robot problem with a plausible hand-eye and board placement.
pub fn random_robot(seed: u64, cfg: &SynthConfig) -> Result<SynthRobot, CalibError> {
    let mut rng = StdRng::seed_from_u64(seed);
    // Camera some centimetres off the flange, looking roughly along the flange z.
    let flange_from_camera = Iso3::from_parts(
        Translation3::new(
            rng.random_range(-0.08..0.08),
            rng.random_range(-0.08..0.08),
            rng.random_range(0.02..0.1),
        ),
        UnitQuaternion::from_scaled_axis(Vector3::new(
            rng.random_range(-0.3..0.3),
            rng.random_range(-0.3..0.3),
            rng.random_range(-3.1..3.1),
        )),
    );
    let base_from_target = Iso3::from_parts(
        Translation3::new(
            rng.random_range(0.4..0.7),
            rng.random_range(-0.2..0.2),
            rng.random_range(-0.1..0.1),
        ),
        // Board lying on the table, printed side up: target z points down.
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-3.1..3.1)),
    );
    make_robot(&mut rng, cfg, flange_from_camera, base_from_target)
}

/// Gauss-Newton pose fit of board points to pixels from a nearby start (the
/// synthetic stand-in for PnP).
pub fn fit_pose(
    camera: &CameraModel,
    points: &[Point3<f64>],
    pixels: &[(usize, Point2<f64>)],
    start: &Iso3,
) -> Result<Iso3, CalibError> {
    let mut pose = *start;
    for _ in 0..10 {
        let mut jtj = nalgebra::Matrix6::<f64>::zeros();
        let mut jtr = Vector6::<f64>::zeros();
        for (k, uv) in pixels {
            let p = pose * points[*k];
            let (proj, jp) = camera
                .project_with_jacobian(&p)
                .ok_or(CalibError::Synthesis {
                    reason: "point behind camera",
                })?;
            let r = proj - uv;
            // d p / d(left perturbation [w, v]) = [-[p]x, I]
            let mut dp = nalgebra::Matrix3x6::<f64>::zeros();
            dp.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(-crate::pose::skew(&p.coords)));
            dp.fixed_view_mut::<3, 3>(0, 3)
                .copy_from(&nalgebra::Matrix3::identity());
            let j = jp * dp;
            jtj += j.transpose() * j;
            jtr += j.transpose() * r;
        }
        let Some(step) = jtj.cholesky().map(|c| c.solve(&(-jtr))) else {
            return Err(CalibError::DegeneratePoints(
                "pose fit normal equations are singular".into(),
            ));
        };
        pose = perturb_left(&step, &pose);
        if step.norm() < 1e-12 {
            break;
        }
    }
    Ok(pose)
}

impl SynthRobot {
    /// The captures as the refinement takes them.
    pub fn board_captures(&self) -> Vec<crate::refine::BoardCapture> {
        self.observations
            .iter()
            .zip(&self.base_from_flange)
            .map(|(obs, b)| crate::refine::BoardCapture {
                base_from_flange: *b,
                target_points: obs.iter().map(|(k, _)| self.board[*k]).collect(),
                pixels: obs.iter().map(|(_, uv)| *uv).collect(),
                target: 0,
            })
            .collect()
    }
}

/// Two robots sharing a board, and the transform between their bases.
#[derive(Debug, Clone)]
pub struct TwoRobots {
    pub robots: [SynthRobot; 2],
    pub base1_from_base2: Iso3,
}

/// Two carts about a metre apart facing each other (the seed paper's set-up),
/// a board on the table between them; deterministic for a seed.
pub fn two_robots(seed: u64, cfg: &SynthConfig) -> Result<TwoRobots, CalibError> {
    let mut rng = StdRng::seed_from_u64(seed);
    let base1_from_base2 = Iso3::from_parts(
        Translation3::new(
            1.0 + rng.random_range(-0.1..0.1),
            rng.random_range(-0.1..0.1),
            rng.random_range(-0.05..0.05),
        ),
        UnitQuaternion::from_axis_angle(
            &Vector3::z_axis(),
            std::f64::consts::PI + rng.random_range(-0.2..0.2),
        ),
    );
    let base1_from_target = Iso3::from_parts(
        Translation3::new(0.5, rng.random_range(-0.1..0.1), 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    );
    let hand_eye = |rng: &mut StdRng| {
        Iso3::from_parts(
            Translation3::new(
                rng.random_range(-0.06..0.06),
                rng.random_range(-0.06..0.06),
                0.05,
            ),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, rng.random_range(-3.0..3.0))),
        )
    };
    let x1 = hand_eye(&mut rng);
    let x2 = hand_eye(&mut rng);
    let r1 = make_robot(&mut rng, cfg, x1, base1_from_target)?;
    let r2 = make_robot(
        &mut rng,
        cfg,
        x2,
        base1_from_base2.inverse() * base1_from_target,
    )?;
    Ok(TwoRobots {
        robots: [r1, r2],
        base1_from_base2,
    })
}

/// Three robots sharing a board: [`two_robots`] (the same two for the same
/// seed) and a third cart about a metre from both, beside the board, facing it.
#[derive(Debug, Clone)]
pub struct ThreeRobots {
    pub robots: [SynthRobot; 3],
    /// `base1_from_base2`, `base1_from_base3`.
    pub base1_from_base: [Iso3; 2],
}

/// [`two_robots`] and a third robot; deterministic for a seed.
pub fn three_robots(seed: u64, cfg: &SynthConfig) -> Result<ThreeRobots, CalibError> {
    let two = two_robots(seed, cfg)?;
    let mut rng = StdRng::seed_from_u64(seed ^ 0x7468_7265_6500_0003);
    let base1_from_base3 = Iso3::from_parts(
        Translation3::new(
            0.5 + rng.random_range(-0.1..0.1),
            1.0 + rng.random_range(-0.1..0.1),
            rng.random_range(-0.05..0.05),
        ),
        UnitQuaternion::from_axis_angle(
            &Vector3::z_axis(),
            -std::f64::consts::FRAC_PI_2 + rng.random_range(-0.2..0.2),
        ),
    );
    let x3 = Iso3::from_parts(
        Translation3::new(
            rng.random_range(-0.06..0.06),
            rng.random_range(-0.06..0.06),
            0.05,
        ),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, rng.random_range(-3.0..3.0))),
    );
    let base1_from_target = two.robots[0].base_from_target;
    let r3 = make_robot(
        &mut rng,
        cfg,
        x3,
        base1_from_base3.inverse() * base1_from_target,
    )?;
    let [r1, r2] = two.robots;
    Ok(ThreeRobots {
        robots: [r1, r2, r3],
        base1_from_base: [two.base1_from_base2, base1_from_base3],
    })
}

/// Three robots and two targets that no robot but the second sees both of:
/// robot 1 sees target 0 (the board of [`three_robots`]), robot 3 sees target
/// 1 (a board beside robot 3, out of robot 1's sight), robot 2 sees both. Robot
/// 3 is found in robot 1's base only through robot 2.
#[derive(Debug, Clone)]
pub struct TwoTargets {
    /// `base1_from_base2`, `base1_from_base3`.
    pub base1_from_base: [Iso3; 2],
    /// Per target.
    pub base1_from_target: [Iso3; 2],
    /// `(robot, target, its captures of that target)`.
    pub views: Vec<(usize, usize, SynthRobot)>,
}

impl TwoTargets {
    /// One robot's captures of every target it sees (target indices set), and
    /// the board poses PnP gave for them.
    pub fn captures(&self, robot: usize) -> (Vec<crate::refine::BoardCapture>, Vec<Iso3>) {
        let mut captures = Vec::new();
        let mut poses = Vec::new();
        for (r, t, seen) in &self.views {
            if *r != robot {
                continue;
            }
            captures.extend(seen.board_captures().into_iter().map(|mut c| {
                c.target = *t;
                c
            }));
            poses.extend(seen.camera_from_target.iter().copied());
        }
        (captures, poses)
    }
}

/// [`TwoTargets`]; deterministic for a seed. With `linked` false robot 2 sees
/// only target 0, so robot 3 is cut off.
pub fn two_targets(seed: u64, cfg: &SynthConfig, linked: bool) -> Result<TwoTargets, CalibError> {
    let three = three_robots(seed, cfg)?;
    let mut rng = StdRng::seed_from_u64(seed ^ 0x7477_6f74_6172_6765);
    let base1_from_base3 = three.base1_from_base[1];
    // The second board lies on the table half a metre in front of robot 3
    // (its base's x), printed side up like the first.
    let base1_from_target1 = base1_from_base3
        * Iso3::from_parts(
            Translation3::new(0.5, rng.random_range(-0.1..0.1), 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        );
    let [r1, r2, r3] = three.robots;
    let base1_from_target0 = r1.base_from_target;
    let x2 = r2.flange_from_camera;
    let x3 = r3.flange_from_camera;
    let mut views = vec![(0, 0, r1), (1, 0, r2)];
    if linked {
        let base2_from_target1 = three.base1_from_base[0].inverse() * base1_from_target1;
        views.push((1, 1, make_robot(&mut rng, cfg, x2, base2_from_target1)?));
    }
    let base3_from_target1 = base1_from_base3.inverse() * base1_from_target1;
    views.push((2, 1, make_robot(&mut rng, cfg, x3, base3_from_target1)?));
    Ok(TwoTargets {
        base1_from_base: three.base1_from_base,
        base1_from_target: [base1_from_target0, base1_from_target1],
        views,
    })
}

/// `n` robots sharing one board, their carts spread on a circle about it.
#[derive(Debug, Clone)]
pub struct ManyRobots {
    pub robots: Vec<SynthRobot>,
    /// `base1_from_base` of robots 2 to `n`, in order.
    pub base1_from_base: Vec<Iso3>,
}

/// `n` carts (at least one) evenly spread on a circle of 0.5 m about a board,
/// each facing it (robot 1's base where [`two_robots`] puts it); the scaling
/// problem of a platform with many arms. Deterministic for a seed.
pub fn robots_around(n: usize, seed: u64, cfg: &SynthConfig) -> Result<ManyRobots, CalibError> {
    let mut rng = StdRng::seed_from_u64(seed ^ 0x6d61_6e79_0000_0000);
    let base1_from_target = Iso3::from_parts(
        Translation3::new(0.5, 0.0, 0.0),
        UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
    );
    let mut robots = Vec::with_capacity(n);
    let mut base1_from_base = Vec::with_capacity(n.saturating_sub(1));
    for k in 0..n.max(1) {
        // About the board's centre, by the cart's angle on the circle.
        let angle = std::f64::consts::TAU * k as f64 / n.max(1) as f64;
        let base1_from_basek = Iso3::from_parts(
            Translation3::new(0.5, 0.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), angle),
        ) * Iso3::from_parts(
            Translation3::new(
                -0.5 + rng.random_range(-0.05..0.05),
                rng.random_range(-0.05..0.05),
                rng.random_range(-0.02..0.02),
            ),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), rng.random_range(-0.1..0.1)),
        );
        let base1_from_basek = if k == 0 {
            Iso3::identity()
        } else {
            base1_from_basek
        };
        let hand_eye = Iso3::from_parts(
            Translation3::new(
                rng.random_range(-0.06..0.06),
                rng.random_range(-0.06..0.06),
                0.05,
            ),
            UnitQuaternion::from_scaled_axis(Vector3::new(0.0, 0.0, rng.random_range(-3.0..3.0))),
        );
        robots.push(make_robot(
            &mut rng,
            cfg,
            hand_eye,
            base1_from_basek.inverse() * base1_from_target,
        )?);
        if k > 0 {
            base1_from_base.push(base1_from_basek);
        }
    }
    Ok(ManyRobots {
        robots,
        base1_from_base,
    })
}
