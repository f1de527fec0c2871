//! Per-datagram cost of the client: decode + session step + encode of the reply.
//!
//! Run `cargo bench -p kuka-fri`; `cargo test -p kuka-fri --benches` runs each benchmark
//! once as a smoke test. Peer: the codec alone (decode, encode), so the session's own
//! overhead can be read off as the difference.

use std::hint::black_box;
use std::time::{Duration, Instant};

use b2b_robot::{JointLimits, Joints, WorkspaceBox};
use criterion::{Criterion, criterion_group, criterion_main};
use kuka_fri::codec;
use kuka_fri::messages::MAX_DATAGRAM_SIZE;
use kuka_fri::{
    ClientSession, SafetyGuard, SessionConfig, SessionState, SimConfig, SimulatedController,
};

const N: usize = 4096;

fn fk(q: &Joints) -> [f64; 3] {
    [q[0].cos() * 0.5, q[0].sin() * 0.5, 0.8 + 0.1 * q[1].sin()]
}

/// `N` consecutive monitoring datagrams from the simulator in `state`.
fn datagrams(commanding: bool) -> Vec<Vec<u8>> {
    let t0 = Instant::now();
    let mut sim = SimulatedController::new(SimConfig::default(), t0).expect("sim");
    let mut buf = [0u8; MAX_DATAGRAM_SIZE];
    let mut out = Vec::with_capacity(N);
    let mut t = t0;
    let guard =
        SafetyGuard::new(JointLimits::iiwa7(), WorkspaceBox::unbounded(), fk).expect("guard");
    let mut client = ClientSession::new(SessionConfig::default(), guard);
    let mut reply = [0u8; MAX_DATAGRAM_SIZE];
    // Run a real exchange so the simulator reaches the wanted state, then record.
    while out.len() < N {
        if let Some(n) = sim.poll_transmit(t, &mut buf) {
            let bytes = buf[..n].to_vec();
            if client.handle_datagram(t, &bytes).is_ok()
                && let Some(m) = client.poll_transmit(t, &mut reply)
            {
                let _ = sim.handle_datagram(t, &reply[..m]);
            }
            if sim.state() == SessionState::MonitoringReady && commanding {
                sim.start_commanding();
            }
            let wanted = if commanding {
                SessionState::CommandingActive
            } else {
                SessionState::MonitoringReady
            };
            if sim.state() == wanted {
                out.push(bytes);
            }
        }
        t += Duration::from_millis(5);
    }
    out
}

fn cycle(c: &mut Criterion) {
    let mut group = c.benchmark_group("fri_cycle");
    group
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_millis(500));
    for (name, commanding) in [("monitoring", false), ("commanding_active", true)] {
        let dgrams = datagrams(commanding);
        let guard =
            SafetyGuard::new(JointLimits::iiwa7(), WorkspaceBox::unbounded(), fk).expect("guard");
        let new_session = || ClientSession::new(SessionConfig::default(), guard.clone());
        let mut session = new_session();
        let mut k = 0usize;
        let mut out = [0u8; MAX_DATAGRAM_SIZE];
        let now = Instant::now();
        group.bench_function(format!("decode_step_encode/{name}"), |b| {
            b.iter(|| {
                if k == N {
                    // Sequence counters would run backwards: start a fresh session.
                    k = 0;
                    session = new_session();
                }
                let ev = session.handle_datagram(now, black_box(&dgrams[k]));
                k += 1;
                let n = session.poll_transmit(now, &mut out);
                black_box((ev.is_ok(), n))
            })
        });
    }
    let dgrams = datagrams(false);
    group.bench_function("peer/decode_only", |b| {
        let mut k = 0;
        b.iter(|| {
            k = (k + 1) % N;
            black_box(codec::decode_monitoring(black_box(&dgrams[k])).is_ok())
        })
    });
    group.finish();
}

criterion_group!(benches, cycle);
criterion_main!(benches);
