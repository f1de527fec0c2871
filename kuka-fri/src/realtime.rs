//! Real-time scheduling of the FRI cycle threads.
//!
//! # Why SCHED_FIFO
//! A cycle thread sleeps almost all of the time and has microseconds of work when its
//! datagram or its due time comes. Under the fair scheduler it then queues behind every
//! runnable thread on its core: with every core busy, the two cycle threads on their own
//! but normally scheduled still missed 1,593 replies in 10,000 cycles, and a cycle ran up
//! to 118 ms late (`tests/cycle_under_load.rs`). Under SCHED_FIFO it preempts every normally
//! scheduled thread at once, and since it blocks again within microseconds it cannot starve
//! them (the kernel also caps real-time threads at 95 % of each second by default).
//!
//! Raising a thread to SCHED_FIFO needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO; without
//! it the thread keeps normal scheduling and a warning is logged once per thread.

/// SCHED_FIFO priority of the cycle threads unless configured otherwise: the middle of
/// Linux's 1..=99, where the kernel's threaded interrupt handlers and ros2_control's
/// controller manager also run.
pub const DEFAULT_CYCLE_PRIORITY: u8 = 50;

/// How a cycle thread ended up being scheduled.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum CycleScheduling {
    /// Not started yet.
    #[default]
    Pending,
    /// SCHED_FIFO at this priority.
    Fifo(u8),
    /// The operating system's normal scheduling (not requested, or not permitted).
    Normal,
}

/// Puts the calling thread under SCHED_FIFO at `priority` (1..=99), or leaves it alone
/// with `None`. A refusal is logged, not returned: the cycle then runs without the
/// guarantee, which the missed-reply counters show.
pub fn promote_current_thread(what: &str, priority: Option<u8>) -> CycleScheduling {
    let Some(priority) = priority else {
        return CycleScheduling::Normal;
    };
    match set_fifo(priority) {
        Ok(()) => {
            tracing::debug!(what, priority, "cycle thread runs under SCHED_FIFO");
            CycleScheduling::Fifo(priority)
        }
        Err(reason) => {
            tracing::warn!(
                what,
                priority,
                %reason,
                "cycle thread keeps normal scheduling (SCHED_FIFO needs root, CAP_SYS_NICE or \
                 an RLIMIT_RTPRIO): replies may be late when every core is busy"
            );
            CycleScheduling::Normal
        }
    }
}

#[cfg(target_os = "linux")]
fn set_fifo(priority: u8) -> Result<(), String> {
    use thread_priority::{
        RealtimeThreadSchedulePolicy, ThreadPriority, ThreadPriorityValue, ThreadSchedulePolicy,
        set_thread_priority_and_policy, thread_native_id,
    };
    let value = ThreadPriorityValue::try_from(priority)?;
    set_thread_priority_and_policy(
        thread_native_id(),
        ThreadPriority::Crossplatform(value),
        ThreadSchedulePolicy::Realtime(RealtimeThreadSchedulePolicy::Fifo),
    )
    .map_err(|e| format!("{e:?}"))
}

#[cfg(not(target_os = "linux"))]
fn set_fifo(_priority: u8) -> Result<(), String> {
    Err("SCHED_FIFO is only requested on Linux".into())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_priority_requested_means_normal_scheduling() {
        let s = std::thread::spawn(|| promote_current_thread("test", None))
            .join()
            .unwrap();
        assert_eq!(s, CycleScheduling::Normal);
    }

    #[test]
    fn an_impossible_priority_is_refused_not_fatal() {
        let s = std::thread::spawn(|| promote_current_thread("test", Some(0)))
            .join()
            .unwrap();
        assert_eq!(s, CycleScheduling::Normal);
    }
}
