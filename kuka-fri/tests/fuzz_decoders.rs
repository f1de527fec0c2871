//! The fuzz targets of `kuka-fri/fuzz` (cargo-fuzz, nightly) as a seeded
//! campaign on stable, which CI runs: the same target functions, fed random
//! bytes and mutations (flipped, inserted, deleted bytes, truncation) of valid
//! datagrams taken from a client session talking to the simulated controller.
//! A panic anywhere fails the test; errors are the point.

mod common;

use std::time::{Duration, Instant};

use common::Harness;
use kuka_fri::messages::MAX_DATAGRAM_SIZE;
use kuka_fri::{ClientSession, SessionConfig, SimConfig, SimulatedController};
use proptest::prelude::*;

/// `fuzz_targets/decode_monitoring.rs`: controller bytes through the codec
/// and the whole client session.
fn monitoring_target(data: &[u8]) {
    let _ = kuka_fri::codec::decode_monitoring(data);
    let mut session = ClientSession::new(SessionConfig::default(), Harness::default_guard());
    let now = Instant::now();
    let _ = session.handle_datagram(now, data);
    let mut buf = [0u8; MAX_DATAGRAM_SIZE];
    let _ = session.poll_transmit(now, &mut buf);
    let (a, b) = data.split_at(data.len() / 2);
    let _ = session.handle_datagram(now, a);
    let _ = session.handle_datagram(now, b);
    let _ = session.poll_transmit(now, &mut buf);
}

/// `fuzz_targets/decode_command.rs`: client bytes through the codec and the
/// simulated controller.
fn command_target(data: &[u8]) {
    let _ = kuka_fri::codec::decode_command(data);
    let now = Instant::now();
    if let Ok(mut sim) = SimulatedController::new(SimConfig::default(), now) {
        let _ = sim.handle_datagram(now, data);
        let mut buf = [0u8; MAX_DATAGRAM_SIZE];
        let _ = sim.poll_transmit(now, &mut buf);
    }
}

/// Datagrams both ways: (monitoring, commands).
type Datagrams = (Vec<Vec<u8>>, Vec<Vec<u8>>);

/// Valid datagrams both ways, as a session exchanges them while the
/// controller goes from monitoring to commanding.
fn seeds() -> Datagrams {
    let mut now = Instant::now();
    let mut sim = SimulatedController::new(SimConfig::default(), now).expect("sim");
    let mut client = ClientSession::new(SessionConfig::default(), Harness::default_guard());
    let (mut down, mut up) = (vec![], vec![]);
    let mut buf = [0u8; MAX_DATAGRAM_SIZE];
    for k in 0..400 {
        if k == 100 {
            sim.start_commanding();
        }
        now = now.max(sim.poll_timeout());
        while let Some(n) = sim.poll_transmit(now, &mut buf) {
            let datagram = buf[..n].to_vec();
            let _ = client.handle_datagram(now, &datagram);
            if let Some(m) = client.poll_transmit(now, &mut buf) {
                let _ = sim.handle_datagram(now, &buf[..m]);
                if k % 20 == 0 {
                    up.push(buf[..m].to_vec());
                }
            }
            if k % 20 == 0 {
                down.push(datagram);
            }
        }
        now += Duration::from_micros(100);
    }
    assert!(!down.is_empty() && !up.is_empty(), "no valid datagrams");
    (down, up)
}

/// One mutation of a datagram.
#[derive(Debug, Clone)]
enum Mutation {
    Flip { at: usize, mask: u8 },
    Insert { at: usize, byte: u8 },
    Delete { at: usize },
    Truncate { to: usize },
    Set { at: usize, byte: u8 },
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), 1u8..).prop_map(|(at, mask)| Mutation::Flip { at, mask }),
        (any::<usize>(), any::<u8>()).prop_map(|(at, byte)| Mutation::Insert { at, byte }),
        any::<usize>().prop_map(|at| Mutation::Delete { at }),
        any::<usize>().prop_map(|to| Mutation::Truncate { to }),
        (
            any::<usize>(),
            prop::sample::select(vec![0u8, 0x7f, 0x80, 0xff])
        )
            .prop_map(|(at, byte)| Mutation::Set { at, byte }),
    ]
}

fn mutate(mut bytes: Vec<u8>, mutations: &[Mutation]) -> Vec<u8> {
    for m in mutations {
        let len = bytes.len();
        match *m {
            Mutation::Flip { at, mask } if len > 0 => bytes[at % len] ^= mask,
            Mutation::Insert { at, byte } => bytes.insert(at % (len + 1), byte),
            Mutation::Delete { at } if len > 0 => {
                bytes.remove(at % len);
            }
            Mutation::Truncate { to } => bytes.truncate(to % (len + 1)),
            Mutation::Set { at, byte } if len > 0 => bytes[at % len] = byte,
            _ => {}
        }
    }
    bytes
}

proptest! {
    // CI's short campaign; PROPTEST_CASES=100000 runs a long one.
    #![proptest_config(ProptestConfig { cases: cases(3000), ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(data in prop::collection::vec(any::<u8>(), 0..MAX_DATAGRAM_SIZE)) {
        monitoring_target(&data);
        command_target(&data);
    }

    #[test]
    fn mutated_datagrams_never_panic(
        pick in any::<prop::sample::Index>(),
        mutations in prop::collection::vec(mutation(), 1..8),
    ) {
        let (down, up) = seeds_cached();
        monitoring_target(&mutate(pick.get(down).clone(), &mutations));
        command_target(&mutate(pick.get(up).clone(), &mutations));
    }
}

fn seeds_cached() -> &'static Datagrams {
    static SEEDS: std::sync::OnceLock<Datagrams> = std::sync::OnceLock::new();
    SEEDS.get_or_init(seeds)
}

/// The seeds are what they claim: valid datagrams that decode (so the
/// mutations start from inside the format, not from noise).
#[test]
fn the_seeds_are_valid_datagrams() {
    let (down, up) = seeds_cached();
    for d in down {
        kuka_fri::codec::decode_monitoring_with_header(d).expect("valid monitoring");
    }
    for u in up {
        kuka_fri::codec::decode_command_with_header(u).expect("valid command");
    }
}

/// `PROPTEST_CASES` when set, else `default` (CI's short campaign).
fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
