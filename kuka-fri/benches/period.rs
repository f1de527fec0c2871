//! The simulated controller's period over real UDP: how long one message takes on the
//! loop `SimServer` runs (deadline timer, SCHED_FIFO where permitted), at 5 ms and 1 ms,
//! with our `FriClient` answering every message on loopback.
//!
//! Criterion times `n` consecutive sends, so its figure is the achieved interval between
//! two messages (messages per 10 s = 10 s / interval); after each period the late sends
//! (more than half a period after the deadline) and the skipped deadlines of the whole run
//! are printed.
//!
//! `cargo bench -p kuka-fri --bench period` (release) and
//! `cargo bench -p kuka-fri --bench period --profile dev` (the profile tests use);
//! `cargo test -p kuka-fri --benches` runs each benchmark once as a smoke test (well under
//! a second).

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use b2b_robot::{JointLimits, WorkspaceBox};
use criterion::{Criterion, criterion_group, criterion_main};
use kuka_fri::{FriClient, FriClientConfig, SafetyGuard, SimConfig, SimServer, SimServerConfig};

fn loopback() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 0))
}

/// Waits (sleeping most of the time, polling near the end) until the controller has sent
/// `count` messages; returns when it saw that happen.
fn wait_for_sent(server: &SimServer, count: u64, period: Duration) -> Instant {
    loop {
        let sent = server.snapshot().stats.sent;
        if sent >= count {
            return Instant::now();
        }
        let ahead = count - sent;
        std::thread::sleep(if ahead > 2 {
            period * u32::try_from(ahead - 2).unwrap_or(u32::MAX).min(100)
        } else {
            Duration::from_micros(20)
        });
    }
}

fn period(c: &mut Criterion) {
    let mut group = c.benchmark_group("controller_period");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(10));
    for period_ms in [5u32, 1] {
        let period = Duration::from_millis(u64::from(period_ms));
        let guard = SafetyGuard::new(
            JointLimits::iiwa7(),
            WorkspaceBox::unbounded(),
            |_: &b2b_robot::Joints| [0.0, 0.0, 1.0],
        )
        .expect("guard");
        let client = FriClient::start(FriClientConfig::new(loopback()), guard).expect("client");
        let server = SimServer::start(SimServerConfig {
            bind: loopback(),
            auto_command: false,
            ..SimServerConfig::new(
                client.local_addr(),
                SimConfig {
                    send_period_ms: period_ms,
                    ..SimConfig::default()
                },
            )
        })
        .expect("controller");
        group.bench_function(format!("message_interval/{period_ms}ms"), |b| {
            b.iter_custom(|iters| {
                // Start at a send, time `iters` further sends.
                let first = server.snapshot().stats.sent + 1;
                let t0 = wait_for_sent(&server, first, period);
                wait_for_sent(&server, first + iters, period) - t0
            })
        });
        let (controller, snap) = server.finish().expect("controller ran");
        client.shutdown();
        let s = controller.stats();
        println!(
            "controller_period/{period_ms}ms: {} messages, {} late sends ({:.2} %), {} \
             deadlines skipped, longest {:.2} ms late, {} replies missed; cycle thread {:?}",
            s.sent,
            s.late_sends,
            100.0 * s.late_sends as f64 / s.sent.max(1) as f64,
            s.skipped_cycles,
            s.max_send_lateness.as_secs_f64() * 1e3,
            s.missed_replies,
            snap.scheduling,
        );
    }
    group.finish();
}

criterion_group!(benches, period);
criterion_main!(benches);
