//! The virtual clock of the in-process live-source tests (`live_port.rs`,
//! `live_render.rs`): time passes only when someone sleeps or waits on it.

#![allow(dead_code)]

use std::cell::Cell;
use std::rc::Rc;
use std::time::{Duration, Instant};

use b2b_live::Clock;

/// Host time of the virtual clock's start, ns since the Unix epoch.
pub const EPOCH_NS: u64 = 1_700_000_000_000_000_000;

/// Time that passes only when someone sleeps or waits on it.
#[derive(Debug, Clone)]
pub struct VirtualClock {
    origin: Instant,
    elapsed: Rc<Cell<Duration>>,
}

impl VirtualClock {
    pub fn new() -> Self {
        VirtualClock {
            origin: Instant::now(),
            elapsed: Rc::default(),
        }
    }

    /// Virtual time since the start.
    pub fn elapsed(&self) -> Duration {
        self.elapsed.get()
    }
}

impl Clock for VirtualClock {
    fn now(&self) -> Instant {
        self.origin + self.elapsed.get()
    }

    fn now_ns(&self) -> u64 {
        EPOCH_NS + self.elapsed.get().as_nanos() as u64
    }

    fn sleep(&self, d: Duration) {
        self.elapsed.set(self.elapsed.get() + d);
    }
}
