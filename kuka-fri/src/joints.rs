//! Measured joint states, stamped with the controller clock, and "is the robot still?".
//!
//! # Why the controller timestamp
//! A calibration capture must pair an image with the joint angles of the same instant. The
//! controller stamps each measurement with its own clock (`monitorData.timestamp`, Unix
//! time), which is free of the network's delay and jitter; the host receive time is kept
//! next to it only for diagnostics. Stillness windows are measured on the controller clock for
//! the same reason.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use b2b_robot::Joints;

/// A controller time stamp (Unix time of the robot controller's clock).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub struct ControllerTime {
    /// Seconds.
    pub sec: u32,
    /// Nanoseconds, `< 1_000_000_000`.
    pub nanosec: u32,
}

impl ControllerTime {
    /// Time since the Unix epoch.
    pub fn as_duration(self) -> Duration {
        Duration::new(u64::from(self.sec), self.nanosec.min(999_999_999))
    }

    /// From a time since the Unix epoch (saturating at `u32::MAX` seconds).
    pub fn from_duration(d: Duration) -> Self {
        Self {
            sec: u32::try_from(d.as_secs()).unwrap_or(u32::MAX),
            nanosec: d.subsec_nanos(),
        }
    }
}

/// One measurement of the arm.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointState {
    /// Measured joint positions (rad).
    pub q: Joints,
    /// Controller time of the measurement.
    pub timestamp: ControllerTime,
    /// Host time the datagram was handled (diagnostics only).
    pub received_at: Instant,
}

/// A bounded history of joint states for stillness detection.
#[derive(Clone, Debug)]
pub struct JointHistory {
    samples: VecDeque<JointState>,
    capacity: usize,
}

impl JointHistory {
    /// A history that keeps at most `capacity` samples (at least 2).
    pub fn new(capacity: usize) -> Self {
        let capacity = capacity.max(2);
        Self {
            samples: VecDeque::with_capacity(capacity.min(1 << 16)),
            capacity,
        }
    }

    /// Adds a sample. A time stamp older than the newest sample (controller restart or clock
    /// step) clears the history first, so windows never mix two clocks.
    pub fn push(&mut self, state: JointState) {
        if let Some(last) = self.samples.back()
            && state.timestamp < last.timestamp
        {
            self.samples.clear();
        }
        if self.samples.len() == self.capacity {
            self.samples.pop_front();
        }
        self.samples.push_back(state);
    }

    /// Forgets everything.
    pub fn clear(&mut self) {
        self.samples.clear();
    }

    /// The newest sample.
    pub fn latest(&self) -> Option<&JointState> {
        self.samples.back()
    }

    /// Number of samples kept.
    pub fn len(&self) -> usize {
        self.samples.len()
    }

    /// Whether no sample is kept.
    pub fn is_empty(&self) -> bool {
        self.samples.is_empty()
    }

    /// True if the history covers at least `window` of controller time up to the newest
    /// sample, and within that window every joint stayed within a band of width `tol` rad
    /// (max − min ≤ tol). False when there is not enough history to tell.
    pub fn is_still(&self, window: Duration, tol: f64) -> bool {
        let (Some(first), Some(last)) = (self.samples.front(), self.samples.back()) else {
            return false;
        };
        if !(tol.is_finite() && tol >= 0.0) || self.samples.len() < 2 {
            return false;
        }
        let end = last.timestamp.as_duration();
        let Some(begin) = end.checked_sub(window) else {
            return false;
        };
        if first.timestamp.as_duration() > begin {
            return false;
        }
        let mut lo = [f64::INFINITY; 7];
        let mut hi = [f64::NEG_INFINITY; 7];
        for s in self.samples.iter().rev() {
            if s.timestamp.as_duration() < begin {
                break;
            }
            for j in 0..7 {
                lo[j] = lo[j].min(s.q[j]);
                hi[j] = hi[j].max(s.q[j]);
            }
        }
        (0..7).all(|j| hi[j] - lo[j] <= tol)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(ms: u64, q0: f64) -> JointState {
        JointState {
            q: [q0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            timestamp: ControllerTime::from_duration(Duration::from_millis(1_000_000 + ms)),
            received_at: Instant::now(),
        }
    }

    #[test]
    fn still_needs_full_window_and_small_band() {
        let mut h = JointHistory::new(1000);
        for k in 0..50 {
            h.push(state(k * 5, 0.1 + 1e-5 * (k % 3) as f64));
        }
        assert!(h.is_still(Duration::from_millis(200), 1e-4));
        assert!(
            !h.is_still(Duration::from_millis(300), 1e-4),
            "not enough history"
        );
        assert!(
            !h.is_still(Duration::from_millis(200), 1e-6),
            "band too narrow"
        );
        h.push(state(250, 0.2));
        assert!(!h.is_still(Duration::from_millis(100), 1e-4));
    }

    #[test]
    fn clock_step_back_clears() {
        let mut h = JointHistory::new(10);
        h.push(state(100, 0.0));
        h.push(state(50, 0.0));
        assert_eq!(h.len(), 1);
    }
}
