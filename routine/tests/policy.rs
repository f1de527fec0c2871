//! Every branch of the capture policy, without processes: observations in,
//! actions out.

use b2b_robot::Joints;
use b2b_routine::*;
use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector3};

type Iso3 = Isometry3<f64>;

const Q: Joints = [0.1, 0.2, 0.0, -1.2, 0.0, 1.0, 0.0];
const Q2: Joints = [0.2, 0.2, 0.0, -1.2, 0.0, 1.0, 0.0];

fn auto() -> Routine {
    Routine::new(Mode::Auto(RoutineConfig::default()), 30)
}

fn status() -> Status<'static> {
    Status::default()
}

fn pose(x: f64) -> Iso3 {
    Iso3::from_parts(Translation3::new(x, 0.0, 0.5), UnitQuaternion::identity())
}

/// A board detected `off` (fraction of the width) right of the principal point.
fn seen(off: f64, sharpness: f64) -> VisitEvent {
    VisitEvent::Seen(View {
        base_from_flange: pose(0.4),
        board: Ok(BoardInImage {
            centre_px: Point2::new(640.0 + off * 1280.0, 360.0),
            width: 1280,
            height: 720,
            principal_px: Point2::new(640.0, 360.0),
            centre_in_camera: Point3::new(0.05, 0.0, 0.5),
        }),
        predicted_centre_in_camera: None,
        sharpness: Some(sharpness),
    })
}

fn lost(predicted: Option<Point3<f64>>) -> VisitEvent {
    VisitEvent::Seen(View {
        base_from_flange: pose(0.4),
        board: Err("no chessboard".into()),
        predicted_centre_in_camera: predicted,
        sharpness: Some(1000.0),
    })
}

/// Runs a visit to its first frame.
fn to_frame(r: &mut Routine) -> Visit {
    let (mut v, a) = r.visit(Q);
    assert_eq!(a, VisitAction::MoveTo(Q));
    assert_eq!(
        r.step_visit(&mut v, VisitEvent::Moved, &status()),
        VisitAction::Capture
    );
    v
}

#[test]
fn a_centred_sharp_new_view_is_delivered() {
    let mut r = auto();
    let mut v = to_frame(&mut r);
    assert_eq!(
        r.step_visit(&mut v, seen(0.0, 1000.0), &status()),
        VisitAction::Deliver
    );
}

#[test]
fn an_off_centre_board_is_recentred_then_delivered() {
    let mut r = auto();
    let mut v = to_frame(&mut r);
    let off = OFF_CENTRE_FRACTION + 0.05;
    assert_eq!(
        r.step_visit(&mut v, seen(off, 1000.0), &status()),
        VisitAction::Recentre {
            centre_in_camera: Point3::new(0.05, 0.0, 0.5)
        }
    );
    assert_eq!(
        r.step_visit(&mut v, VisitEvent::Recentred(Ok(Q2)), &status()),
        VisitAction::MoveTo(Q2)
    );
    assert_eq!(r.retries(), 1);
    assert_eq!(
        r.step_visit(&mut v, VisitEvent::Moved, &status()),
        VisitAction::Capture
    );
    assert_eq!(
        r.step_visit(&mut v, seen(0.0, 1000.0), &status()),
        VisitAction::Deliver
    );
    // Just inside the bound is not re-centred.
    let mut v = to_frame(&mut r);
    assert_eq!(
        r.step_visit(&mut v, seen(OFF_CENTRE_FRACTION - 0.01, 1000.0), &status()),
        VisitAction::Deliver
    );
}

#[test]
fn the_recentre_bound_ends_in_the_last_frame() {
    let mut r = auto();
    let mut v = to_frame(&mut r);
    let off = OFF_CENTRE_FRACTION + 0.05;
    for _ in 1..MAX_TRIES {
        assert!(matches!(
            r.step_visit(&mut v, seen(off, 1000.0), &status()),
            VisitAction::Recentre { .. }
        ));
        assert_eq!(
            r.step_visit(&mut v, VisitEvent::Recentred(Ok(Q2)), &status()),
            VisitAction::MoveTo(Q2)
        );
        r.step_visit(&mut v, VisitEvent::Moved, &status());
    }
    assert_eq!(v.attempt(), MAX_TRIES);
    // Still off-centre at the last try: the board was found, so it is a capture.
    assert_eq!(
        r.step_visit(&mut v, seen(off, 1000.0), &status()),
        VisitAction::Deliver
    );
}

#[test]
fn a_lost_board_is_looked_for_where_it_should_be() {
    let mut r = auto();
    let mut v = to_frame(&mut r);
    let p = Point3::new(0.0, 0.1, 0.6);
    assert_eq!(
        r.step_visit(&mut v, lost(Some(p)), &status()),
        VisitAction::Recentre {
            centre_in_camera: p
        }
    );
    // Lost on every try: rejected with the reason and the count.
    for _ in 1..MAX_TRIES {
        r.step_visit(&mut v, VisitEvent::Recentred(Ok(Q2)), &status());
        r.step_visit(&mut v, VisitEvent::Moved, &status());
        let a = r.step_visit(&mut v, lost(Some(p)), &status());
        if v.attempt() < MAX_TRIES {
            assert!(matches!(a, VisitAction::Recentre { .. }));
        } else {
            assert_eq!(
                a,
                VisitAction::Reject(format!(
                    "board not found (no chessboard) after {MAX_TRIES} tries"
                ))
            );
        }
    }
}

#[test]
fn a_lost_board_with_no_estimate_is_rejected_at_once() {
    let mut r = auto();
    let mut v = to_frame(&mut r);
    assert_eq!(
        r.step_visit(&mut v, lost(None), &status()),
        VisitAction::Reject("board not found (no chessboard) after 1 tries".into())
    );
}

#[test]
fn an_unreachable_recentring_keeps_a_found_board_and_names_why() {
    let mut r = auto();
    let mut v = to_frame(&mut r);
    r.step_visit(&mut v, seen(0.3, 1000.0), &status());
    assert_eq!(
        r.step_visit(
            &mut v,
            VisitEvent::Recentred(Err("the re-centred pose has no safe path".into())),
            &status()
        ),
        VisitAction::Deliver
    );
    let mut v = to_frame(&mut r);
    r.step_visit(&mut v, lost(Some(Point3::new(0.0, 0.0, 0.5))), &status());
    assert_eq!(
        r.step_visit(
            &mut v,
            VisitEvent::Recentred(Err("the re-centred pose: out of reach".into())),
            &status()
        ),
        VisitAction::Reject(
            "board not found (no chessboard); the re-centred pose: out of reach after 1 tries"
                .into()
        )
    );
}

#[test]
fn a_view_too_similar_to_a_good_one_is_rejected() {
    let mut r = auto();
    let near = [pose(0.9), pose(0.4 + SIMILAR_T_M / 2.0)];
    let s = Status {
        good_poses: &near,
        ..Default::default()
    };
    let mut v = to_frame(&mut r);
    assert_eq!(
        r.step_visit(&mut v, seen(0.0, 1000.0), &s),
        VisitAction::Reject("too similar to good capture 2".into())
    );
    // Far enough in translation, or turned enough, is new.
    let turned = Iso3::from_parts(
        pose(0.4).translation,
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), (2.0 * SIMILAR_R_DEG).to_radians()),
    );
    let apart = [pose(0.4 + 2.0 * SIMILAR_T_M), turned];
    let s = Status {
        good_poses: &apart,
        ..Default::default()
    };
    let mut v = to_frame(&mut r);
    assert_eq!(
        r.step_visit(&mut v, seen(0.0, 1000.0), &s),
        VisitAction::Deliver
    );
}

#[test]
fn a_blurred_view_is_rejected_once_there_is_a_median() {
    let mut r = auto();
    // Too few sharp captures to judge: delivered, whatever its sharpness.
    let mut v = to_frame(&mut r);
    assert_eq!(
        r.step_visit(&mut v, seen(0.0, 10.0), &status()),
        VisitAction::Deliver
    );
    let mut r = auto();
    for _ in 0..BLUR_MIN_HISTORY {
        let mut v = to_frame(&mut r);
        assert_eq!(
            r.step_visit(&mut v, seen(0.0, 1000.0), &status()),
            VisitAction::Deliver
        );
    }
    let mut v = to_frame(&mut r);
    let blurred = BLUR_FRACTION * 1000.0 - 1.0;
    assert_eq!(
        r.step_visit(&mut v, seen(0.0, blurred), &status()),
        VisitAction::Reject(format!(
            "blurred: sharpness {blurred:.0} < 30% of the median 1000"
        ))
    );
    let mut v = to_frame(&mut r);
    assert_eq!(
        r.step_visit(&mut v, seen(0.0, BLUR_FRACTION * 1000.0 + 1.0), &status()),
        VisitAction::Deliver
    );
}

#[test]
fn a_refused_motion_ends_the_visit_and_a_missing_frame_is_retried() {
    let mut r = auto();
    let (mut v, _) = r.visit(Q);
    assert_eq!(
        r.step_visit(
            &mut v,
            VisitEvent::MoveFailed("joint 4 limit".into()),
            &status()
        ),
        VisitAction::GiveUp("motion refused or aborted: joint 4 limit".into())
    );
    let (mut v, _) = r.visit(Q);
    for k in 1..=MAX_TRIES {
        r.step_visit(&mut v, VisitEvent::Moved, &status());
        let a = r.step_visit(
            &mut v,
            VisitEvent::NoFrame("the arm did not come to rest".into()),
            &status(),
        );
        if k < MAX_TRIES {
            assert_eq!(a, VisitAction::MoveTo(Q));
        } else {
            assert_eq!(
                a,
                VisitAction::GiveUp("the arm did not come to rest".into())
            );
        }
    }
}

#[test]
fn a_program_delivers_every_frame_once_and_never_stops_early() {
    let mut r = Routine::new(Mode::Program, 2);
    assert_eq!(
        r.next_step(&status()),
        Step::Plan {
            count: MIN_PLAN_COUNT,
            first_view: false,
            phase: 0.0
        }
    );
    r.planned(2, pose(0.5));
    let tiny = [[0.0; 6]; 6];
    let s = Status {
        good: 100,
        hand_eye_covariance: Some(&tiny),
        ..Default::default()
    };
    assert_eq!(r.next_step(&s), Step::Visit(0));
    let (mut v, _) = r.visit(Q);
    r.step_visit(&mut v, VisitEvent::Moved, &s);
    assert_eq!(r.step_visit(&mut v, lost(None), &s), VisitAction::Deliver);
    let (mut v, _) = r.visit(Q);
    assert_eq!(
        r.step_visit(&mut v, VisitEvent::NoFrame("no frame".into()), &s),
        VisitAction::GiveUp("no frame".into())
    );
    assert_eq!(r.next_step(&s), Step::Visit(1));
    assert_eq!(r.next_step(&s), Step::Stop("plan exhausted".into()));
}

fn covariance(sigma_t: f64, sigma_r: f64) -> [[f64; 6]; 6] {
    let mut c = [[0.0; 6]; 6];
    for i in 0..3 {
        c[i][i] = sigma_r * sigma_r;
        c[i + 3][i + 3] = sigma_t * sigma_t;
    }
    c
}

#[test]
fn the_stop_rule_needs_enough_captures_and_both_sigmas() {
    let mut r = auto();
    assert!(matches!(
        r.next_step(&status()),
        Step::Plan {
            first_view: true,
            ..
        }
    ));
    r.planned(30, pose(0.5));
    let good = covariance(STOP_SIGMA_T_M * 0.9, STOP_SIGMA_R_DEG.to_radians() * 0.9);
    let s = Status {
        good: MIN_GOOD,
        hand_eye_covariance: Some(&good),
        ..Default::default()
    };
    assert!(
        matches!(r.next_step(&s), Step::Stop(why) if why.starts_with("data sufficient after 20 good captures"))
    );
    let mut r = auto();
    r.planned(30, pose(0.5));
    let few = Status {
        good: MIN_GOOD - 1,
        ..s
    };
    assert_eq!(r.next_step(&few), Step::Visit(0));
    let loose = covariance(STOP_SIGMA_T_M * 1.1, STOP_SIGMA_R_DEG.to_radians() * 0.9);
    let wide = Status {
        hand_eye_covariance: Some(&loose),
        ..s
    };
    assert_eq!(r.next_step(&wide), Step::Visit(1));
    let loose = covariance(STOP_SIGMA_T_M * 0.9, STOP_SIGMA_R_DEG.to_radians() * 1.1);
    let turned = Status {
        hand_eye_covariance: Some(&loose),
        ..s
    };
    assert_eq!(r.next_step(&turned), Step::Visit(2));
}

#[test]
fn a_board_seen_elsewhere_than_planned_for_is_replanned() {
    let mut r = auto();
    r.next_step(&status());
    r.planned(30, pose(0.5));
    r.board_seen(pose(0.5 + REPLAN_SHIFT_M / 2.0));
    assert_eq!(r.next_step(&status()), Step::Visit(0));
    r.visit(Q);
    r.board_seen(pose(0.5 + 2.0 * REPLAN_SHIFT_M));
    assert_eq!(
        r.next_step(&status()),
        Step::Plan {
            count: 29,
            first_view: false,
            phase: REPLAN_PHASE_STEP_RAD
        }
    );
    r.planned(29, pose(0.5 + 2.0 * REPLAN_SHIFT_M));
    assert_eq!(r.next_step(&status()), Step::Visit(0));
    // Once re-planned, later sightings no longer move the estimate.
    r.board_seen(pose(0.9));
    assert_eq!(r.board_estimate(), Some(pose(0.5 + 2.0 * REPLAN_SHIFT_M)));
}

#[test]
fn a_plan_run_out_short_of_good_captures_is_topped_up_within_the_budget() {
    let count = 10;
    let mut r = Routine::new(Mode::Auto(RoutineConfig::default()), count);
    r.next_step(&status());
    r.planned(count, pose(0.5));
    for k in 0..count {
        assert_eq!(r.next_step(&status()), Step::Visit(k));
        r.visit(Q);
    }
    let s = Status {
        good: 8,
        ..Default::default()
    };
    // 12 good captures missing: top_up(12) = 20, but only 10 visits are left.
    assert_eq!(top_up(MIN_GOOD - 8), 20);
    assert_eq!(
        r.next_step(&s),
        Step::Plan {
            count: VISIT_BUDGET_FACTOR * count - count,
            first_view: false,
            phase: REPLAN_PHASE_STEP_RAD
        }
    );
    r.planned(count, pose(0.5));
    for k in 0..count {
        assert_eq!(r.next_step(&s), Step::Visit(k));
        r.visit(Q);
    }
    // The budget is spent.
    assert_eq!(r.next_step(&s), Step::Stop("plan exhausted".into()));
    assert_eq!(r.stopped_because(), Some("plan exhausted"));
}

#[test]
fn settings_that_cannot_work_are_refused() {
    assert!(RoutineConfig::default().validate().is_ok());
    let zero = RoutineConfig {
        stop_sigma_t_m: 0.0,
        ..Default::default()
    };
    assert_eq!(
        zero.validate(),
        Err(RoutineError::NotPositive {
            what: "the stop rule's translation sigma",
            value: 0.0
        })
    );
    let nan = RoutineConfig {
        stop_sigma_r_rad: f64::NAN,
        ..Default::default()
    };
    assert!(nan.validate().is_err());
    let none = RoutineConfig {
        max_tries: 0,
        ..Default::default()
    };
    assert!(matches!(
        none.validate(),
        Err(RoutineError::TooSmall { .. })
    ));
}

/// The agent's fitting rules after each capture.
mod fitting {
    use b2b_routine::{ENOUGH_CAPTURES, enough_data, fit_hand_eye, refit_intrinsics};

    #[test]
    fn intrinsics_are_refitted_only_for_a_camera_without_them_from_enough_views() {
        assert!(!refit_intrinsics(true, true, 4, 5));
        assert!(refit_intrinsics(true, true, 5, 5));
        // Given by the camera: never.
        assert!(!refit_intrinsics(false, true, 30, 5));
        // A capture that saw nothing adds no view to fit to.
        assert!(!refit_intrinsics(true, false, 30, 5));
    }

    #[test]
    fn enough_data_needs_the_captures_and_motions_that_pass_the_checks() {
        assert!(!enough_data(true, ENOUGH_CAPTURES - 1));
        assert!(enough_data(true, ENOUGH_CAPTURES));
        assert!(!enough_data(false, 3 * ENOUGH_CAPTURES));
    }

    #[test]
    fn the_hand_eye_waits_for_motions_and_a_known_camera() {
        assert!(fit_hand_eye(true, true));
        assert!(!fit_hand_eye(false, true));
        assert!(!fit_hand_eye(true, false));
    }
}
