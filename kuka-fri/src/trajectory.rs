//! Synchronised joint trajectories with bounded velocity and acceleration.
//!
//! # Why a straight line in joint space with one shared time law
//! All joints follow `q(t) = start + (end − start) · s(t)` with a single path parameter
//! `s ∈ [0, 1]`. The time law `s(t)` is a trapezoid (or triangle) whose peak rate and
//! acceleration are the largest that keep *every* joint within its own velocity and
//! acceleration limit: `ṡ_max = min_i v_i / |Δq_i|`, `s̈_max = min_i a_i / |Δq_i|`. So the
//! joints start and arrive together, the path is predictable (it can be checked against the
//! workspace box before moving) and a stop can brake along the same path, never leaving the
//! segment that was checked.
//!
//! The profile is stored as constant-acceleration segments so a braking profile (from any
//! point, at the planned deceleration) is the same type.

use b2b_robot::{JointLimits, Joints};

use crate::error::{FriError, Result};
use crate::messages::NUM_JOINTS;

/// One segment of constant path acceleration.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Segment {
    duration: f64,
    accel: f64,
}

/// A time-scaled joint trajectory along a straight joint-space segment.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory {
    origin: Joints,
    delta: Joints,
    s0: f64,
    v0: f64,
    segments: Vec<Segment>,
    accel_max: f64,
    duration: f64,
    end: Joints,
}

/// Displacements below this (rad) count as no motion.
const MIN_DISPLACEMENT: f64 = 1e-12;

impl Trajectory {
    /// Plans a rest-to-rest motion from `start` to `end` within `limits`' velocities and
    /// accelerations. Position limits are not checked here (see [`crate::SafetyGuard`]).
    pub fn plan(start: &Joints, end: &Joints, limits: &JointLimits) -> Result<Self> {
        limits.validate()?;
        for j in 0..NUM_JOINTS {
            if !start[j].is_finite() {
                return Err(FriError::NonFinite {
                    what: "trajectory start",
                    joint: j,
                });
            }
            if !end[j].is_finite() {
                return Err(FriError::NonFinite {
                    what: "trajectory target",
                    joint: j,
                });
            }
        }
        let mut delta = [0.0; NUM_JOINTS];
        let mut v_max = f64::INFINITY;
        let mut a_max = f64::INFINITY;
        for j in 0..NUM_JOINTS {
            delta[j] = end[j] - start[j];
            let d = delta[j].abs();
            if d > MIN_DISPLACEMENT {
                v_max = v_max.min(limits.velocity[j] / d);
                a_max = a_max.min(limits.acceleration[j] / d);
            }
        }
        if !v_max.is_finite() {
            // No motion at all.
            return Ok(Self {
                origin: *start,
                delta: [0.0; NUM_JOINTS],
                s0: 1.0,
                v0: 0.0,
                segments: Vec::new(),
                accel_max: 1.0,
                duration: 0.0,
                end: *end,
            });
        }
        let segments = if v_max * v_max / a_max >= 1.0 {
            // Triangle: accelerate over s = 1/2, decelerate over the rest.
            let t = (1.0 / a_max).sqrt();
            vec![
                Segment {
                    duration: t,
                    accel: a_max,
                },
                Segment {
                    duration: t,
                    accel: -a_max,
                },
            ]
        } else {
            let ta = v_max / a_max;
            let tc = (1.0 - v_max * v_max / a_max) / v_max;
            vec![
                Segment {
                    duration: ta,
                    accel: a_max,
                },
                Segment {
                    duration: tc,
                    accel: 0.0,
                },
                Segment {
                    duration: ta,
                    accel: -a_max,
                },
            ]
        };
        let duration = segments.iter().map(|s| s.duration).sum();
        Ok(Self {
            origin: *start,
            delta,
            s0: 0.0,
            v0: 0.0,
            segments,
            accel_max: a_max,
            duration,
            end: *end,
        })
    }

    /// Total duration (s).
    pub fn duration(&self) -> f64 {
        self.duration
    }

    /// Where the trajectory ends.
    pub fn end(&self) -> Joints {
        self.end
    }

    /// Where the trajectory starts.
    pub fn start(&self) -> Joints {
        self.at_s(self.s0)
    }

    fn path_state(&self, t: f64) -> (f64, f64) {
        let mut s = self.s0;
        let mut v = self.v0;
        let mut remaining = if t.is_finite() { t.max(0.0) } else { 0.0 };
        for seg in &self.segments {
            let dt = remaining.min(seg.duration);
            s += v * dt + 0.5 * seg.accel * dt * dt;
            v += seg.accel * dt;
            remaining -= dt;
            if remaining <= 0.0 {
                break;
            }
        }
        (s.clamp(0.0, 1.0), v.max(0.0))
    }

    fn at_s(&self, s: f64) -> Joints {
        if s >= 1.0 {
            return self.end;
        }
        let mut q = self.origin;
        for (qj, dj) in q.iter_mut().zip(&self.delta) {
            *qj += dj * s;
        }
        q
    }

    /// Joint positions at time `t` (s) after the start; clamped to the ends.
    pub fn sample(&self, t: f64) -> Joints {
        if t >= self.duration && self.s0 == 0.0 && self.v0 == 0.0 {
            return self.end;
        }
        self.at_s(self.path_state(t).0)
    }

    /// Joint velocities at time `t` (rad/s).
    pub fn velocity(&self, t: f64) -> Joints {
        let v = self.path_state(t).1;
        self.delta.map(|d| d * v)
    }

    /// A profile that brakes from the state at time `t` at the planned deceleration, along
    /// the same path. Its time 0 corresponds to `t` of `self`.
    pub fn braking_at(&self, t: f64) -> Self {
        let (s, v) = self.path_state(t);
        let stop = if v > 0.0 { v / self.accel_max } else { 0.0 };
        let end = self.at_s((s + 0.5 * v * stop).min(1.0));
        Self {
            origin: self.origin,
            delta: self.delta,
            s0: s,
            v0: v,
            segments: vec![Segment {
                duration: stop,
                accel: -self.accel_max,
            }],
            accel_max: self.accel_max,
            duration: stop,
            end,
        }
    }

    /// Points along the path spaced at most `max_step` rad apart in every joint (start and
    /// end included), for checking the path before moving.
    pub fn path_points(&self, max_step: f64) -> impl Iterator<Item = Joints> + '_ {
        let span = self.delta.iter().fold(0.0f64, |m, d| m.max(d.abs())) * (1.0 - self.s0);
        let step = if max_step.is_finite() && max_step > 0.0 {
            max_step
        } else {
            1e-3
        };
        let n = ((span / step).ceil() as usize).clamp(1, 1_000_000);
        let s0 = self.s0;
        (0..=n).map(move |k| self.at_s(s0 + (1.0 - s0) * k as f64 / n as f64))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn respects_limits_and_arrives_together() {
        let limits = JointLimits::iiwa14();
        let a = [0.0, 0.5, 0.0, -1.0, 0.0, 0.5, 0.0];
        let b = [1.0, -0.3, 0.2, -0.5, 2.0, -0.1, 1.5];
        let traj = Trajectory::plan(&a, &b, &limits).unwrap();
        let dt = 0.001;
        let n = (traj.duration() / dt).ceil() as usize + 10;
        let mut prev = traj.sample(0.0);
        let mut prev_v = [0.0; 7];
        assert_eq!(prev, a);
        for k in 1..=n {
            let q = traj.sample(k as f64 * dt);
            for j in 0..7 {
                let v = (q[j] - prev[j]) / dt;
                assert!(
                    v.abs() <= limits.velocity[j] * (1.0 + 1e-9),
                    "joint {j} v {v}"
                );
                // Finite-difference acceleration of a piecewise-quadratic path is bounded by a_max.
                let acc = (v - prev_v[j]) / dt;
                assert!(
                    acc.abs() <= limits.acceleration[j] * (1.0 + 1e-6) + 1e-6,
                    "joint {j} a {acc}"
                );
                prev_v[j] = v;
            }
            prev = q;
        }
        assert_eq!(traj.sample(traj.duration()), b);
    }

    #[test]
    fn zero_motion_has_zero_duration() {
        let q = [0.3; 7];
        let t = Trajectory::plan(&q, &q, &JointLimits::iiwa7()).unwrap();
        assert_eq!(t.duration(), 0.0);
        assert_eq!(t.sample(0.0), q);
    }

    #[test]
    fn braking_stops_on_the_path() {
        let limits = JointLimits::iiwa7();
        let a = [0.0; 7];
        let b = [1.5; 7];
        let traj = Trajectory::plan(&a, &b, &limits).unwrap();
        let t = traj.duration() * 0.3;
        let brake = traj.braking_at(t);
        assert_eq!(brake.sample(0.0), traj.sample(t));
        let stop = brake.sample(brake.duration() + 1.0);
        assert!(stop[0] > traj.sample(t)[0] && stop[0] < 1.5);
        assert!(
            brake
                .velocity(brake.duration())
                .iter()
                .all(|v| v.abs() < 1e-9)
        );
    }

    #[test]
    fn rejects_non_finite() {
        let mut b = [0.0; 7];
        b[4] = f64::INFINITY;
        assert!(matches!(
            Trajectory::plan(&[0.0; 7], &b, &JointLimits::iiwa7()),
            Err(FriError::NonFinite { joint: 4, .. })
        ));
    }
}
