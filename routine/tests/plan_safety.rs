//! Safety of the automatic routine's plans: for random boards, mounts, workspace
//! boxes, joint margins and start postures, no planned viewpoint and no point of any
//! planned leg leaves the joint limits (with the margin) or the workspace box, and the
//! re-centring step only ever returns poses the same envelope accepts. (Every command
//! the FRI client then sends passes the same envelope again, in its session's guard:
//! kuka-fri's own property tests.)

use b2b_calib::camera::CameraModel;
use b2b_robot::{Arm, IiwaModel, JointLimits, Joints, SafetyEnvelope, WorkspaceBox};
use b2b_routine::plan::{PlanConfig, PlanScene, leg_is_safe, plan_viewpoints, reach, recentre};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};
use proptest::prelude::*;

fn envelope(model: IiwaModel, min: [f64; 3], max: [f64; 3], margin: f64) -> SafetyEnvelope {
    let limits = match model {
        IiwaModel::Iiwa7R800 => JointLimits::iiwa7(),
        IiwaModel::Iiwa14R820 => JointLimits::iiwa14(),
    };
    SafetyEnvelope::new(limits, WorkspaceBox::new(min, max).unwrap())
        .unwrap()
        .with_position_margin(margin)
        .unwrap()
}

/// Joint limits with the margin, checked independently of the envelope's code.
fn inside_limits(model: IiwaModel, q: &Joints, margin: f64) -> bool {
    let l = match model {
        IiwaModel::Iiwa7R800 => JointLimits::iiwa7(),
        IiwaModel::Iiwa14R820 => JointLimits::iiwa14(),
    };
    (0..7).all(|j| q[j] >= l.position_min[j] + margin && q[j] <= l.position_max[j] - margin)
}

fn inside_box(arm: &Arm, q: &Joints, min: &[f64; 3], max: &[f64; 3]) -> bool {
    let t = arm.fk(q).translation.vector;
    (0..3).all(|k| t[k] >= min[k] && t[k] <= max[k])
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, .. ProptestConfig::default() })]

    #[test]
    fn plans_never_leave_the_limits_or_the_box(
        iiwa14 in any::<bool>(),
        bx in 0.35f64..0.75, by in -0.3f64..0.3, yaw in -1.0f64..1.0,
        tilt_x in -0.2f64..0.2,
        box_lo in prop::array::uniform3(-0.4f64..0.2),
        box_hi in prop::array::uniform3(0.5f64..1.2),
        z_floor in 0.05f64..0.35,
        margin in 0.0f64..0.2,
        start_jitter in prop::array::uniform7(-0.3f64..0.3),
        mount_roll in -1.6f64..1.6,
    ) {
        let model = if iiwa14 { IiwaModel::Iiwa14R820 } else { IiwaModel::Iiwa7R800 };
        let arm = Arm::new(model);
        let min = [box_lo[0], box_lo[1], z_floor];
        let max = box_hi;
        let g = envelope(model, min, max, margin);
        let camera = CameraModel::new(640, 480, [615.0, 615.0, 320.0, 240.0], &[0.0; 5]).unwrap();
        let points = b2b_calib::synth::board_points(9, 6, 0.025);
        let board = Isometry3::from_parts(
            Translation3::new(bx, by, 0.0),
            UnitQuaternion::from_euler_angles(std::f64::consts::PI + tilt_x, 0.0, yaw),
        );
        let mount = Isometry3::from_parts(
            Translation3::new(0.0, 0.06, 0.035),
            UnitQuaternion::from_euler_angles(0.0, 0.0, mount_roll),
        );
        let scene = PlanScene {
            arm: &arm,
            envelope: &g,
            camera: &camera,
            base_from_target: board,
            flange_from_camera: mount,
            target_points: &points,
            view_axis: -nalgebra::Vector3::z(),
        };
        let start: Joints = std::array::from_fn(|j| Arm::comfortable()[j] + start_jitter[j]);
        let cfg = PlanConfig { count: 10, ..PlanConfig::default() };
        let plan = plan_viewpoints(&scene, &start, &cfg).unwrap();
        let mut prev = start;
        let start_ok = g.check_pose(&start, &arm).is_ok();
        for (i, v) in plan.viewpoints.iter().enumerate() {
            prop_assert!(inside_limits(model, &v.q, margin), "viewpoint {i} outside the limits: {:?}", v.q);
            prop_assert!(inside_box(&arm, &v.q, &min, &max), "viewpoint {i} outside the box");
            // Every leg, sampled independently at a finer step than the planner's.
            if i > 0 || start_ok {
                for k in 0..=200 {
                    let s = k as f64 / 200.0;
                    let q: Joints = std::array::from_fn(|j| prev[j] + (v.q[j] - prev[j]) * s);
                    prop_assert!(inside_limits(model, &q, margin) && inside_box(&arm, &q, &min, &max),
                        "leg {i} leaves the safe set at s = {s}");
                }
            }
            prev = v.q;
        }
        // Re-centring from any planned viewpoint towards an arbitrary point: whatever
        // it returns passes the same checks.
        if let Some(v) = plan.viewpoints.first() {
            let base_from_camera = v.base_from_flange * mount;
            let wanted = recentre(&base_from_camera, &Point3::new(0.2, -0.15, 0.4), Some(0.3));
            if let Ok((q, _)) = reach(&scene, &wanted, &v.q) {
                prop_assert!(inside_limits(model, &q, margin) && inside_box(&arm, &q, &min, &max));
                if leg_is_safe(&g, &arm, &v.q, &q, 0.01) {
                    for k in 0..=100 {
                        let s = k as f64 / 100.0;
                        let p: Joints = std::array::from_fn(|j| v.q[j] + (q[j] - v.q[j]) * s);
                        prop_assert!(inside_limits(model, &p, margin));
                    }
                }
            }
        }
    }
}
