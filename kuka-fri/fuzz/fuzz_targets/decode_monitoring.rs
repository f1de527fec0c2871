//! Untrusted controller bytes through the codec and the whole client session.
#![no_main]

use b2b_robot::{JointLimits, WorkspaceBox};
use kuka_fri::{ClientSession, SafetyGuard, SessionConfig};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = kuka_fri::codec::decode_monitoring(data);
    let fk = |q: &[f64; 7]| [q[0], q[1], q[2]];
    if let Ok(guard) = SafetyGuard::new(JointLimits::iiwa7(), WorkspaceBox::unbounded(), fk) {
        let mut session = ClientSession::new(SessionConfig::default(), guard);
        let now = std::time::Instant::now();
        // Feed the input twice (as one datagram, then split in two) to reach reply paths.
        let _ = session.handle_datagram(now, data);
        let mut buf = [0u8; 1500];
        let _ = session.poll_transmit(now, &mut buf);
        let (a, b) = data.split_at(data.len() / 2);
        let _ = session.handle_datagram(now, a);
        let _ = session.handle_datagram(now, b);
        let _ = session.poll_transmit(now, &mut buf);
    }
});
