//! Untrusted client bytes through the codec and the simulated controller.
#![no_main]

use kuka_fri::{SimConfig, SimulatedController};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = kuka_fri::codec::decode_command(data);
    let now = std::time::Instant::now();
    if let Ok(mut sim) = SimulatedController::new(SimConfig::default(), now) {
        let _ = sim.handle_datagram(now, data);
        let mut buf = [0u8; 1500];
        let _ = sim.poll_transmit(now, &mut buf);
    }
});
