//! FRI replies on time with every core busy (issue #14).
//!
//! The simulated controller and the client driver talk over real loopback UDP at the
//! project's 5 ms period while every core is kept busy: spinning threads (twice as many as
//! cores) and threads that allocate and copy large buffers the way rendering and detection
//! do. Meanwhile an "agent" thread moves the arm back and forth through the client API and
//! polls it for stillness, as `agent` does during a calibration.
//!
//! The controller counts, per cycle, whether a reply came back before its next cycle
//! ([`kuka_fri::SimStats::missed_replies`], the zeros of its connection-quality window),
//! and whether it sent late itself; a missed reply is blamed on the controller when its own
//! send was late, else on the client. The test prints the figures (run with `--nocapture`)
//! and requires zero aborted commanding phases and at most one missed reply per 100
//! cycles (0 to 30 per 10,000 measured; the allowance is for stalls of the virtual
//! machine itself, and the code before the fix missed 4,761 per 10,000).
//!
//! CI runs 2,000 cycles (10 s); `FRI_STRESS_CYCLES=10000` gives the per-10,000 figure, and
//! `FRI_STRESS_NORMAL_SCHEDULING=1` runs both cycle threads without SCHED_FIFO.
//!
//! The rendering-like load draws into images it keeps. Fresh multi-megabyte images every
//! frame, which the allocator hands back to the kernel (`FRI_STRESS_PAGE_CHURN=1`), stall
//! the CPUs of the virtual machines this project runs on for up to 30 ms, SCHED_FIFO
//! threads and threads of other processes alike (the kernel and the hypervisor handle the
//! page churn): no design inside the process can keep a 5 ms cycle through that, so it is
//! left out of the assertion and kept as a switch to measure it.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use b2b_robot::{JointLimits, Joints, WorkspaceBox};
use kuka_fri::{
    FriClient, FriClientConfig, SafetyGuard, SessionState, SimConfig, SimServer, SimServerConfig,
};

const SEND_PERIOD_MS: u32 = 5;
const DEFAULT_CYCLES: u64 = 2_000;
/// One missed reply allowed per this many cycles (see the assertion).
const MISS_ALLOWANCE_CYCLES: u64 = 100;

fn fk(q: &Joints) -> [f64; 3] {
    [0.5 * q[0].cos(), 0.5 * q[0].sin(), 0.8 + 0.2 * q[1].sin()]
}

/// Busy threads on every core until dropped.
struct Load {
    stop: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
    work: Arc<AtomicU64>,
}

impl Load {
    fn start() -> Self {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        let stop = Arc::new(AtomicBool::new(false));
        let work = Arc::new(AtomicU64::new(0));
        let mut threads = Vec::new();
        // Pure CPU: twice as many spinning threads as cores.
        for i in 0..2 * cores {
            let (stop, work) = (Arc::clone(&stop), Arc::clone(&work));
            threads.push(
                std::thread::Builder::new()
                    .name(format!("load-spin-{i}"))
                    .spawn(move || {
                        let mut x = 0u64;
                        while !stop.load(Ordering::Relaxed) {
                            for _ in 0..10_000 {
                                x = std::hint::black_box(x.wrapping_mul(6364136223846793005) + 1);
                            }
                            work.fetch_add(1, Ordering::Relaxed);
                        }
                    })
                    .expect("spawn load"),
            );
        }
        // Rendering-like, one per core: an 8 MB image drawn and copied each frame, with
        // per-frame scratch allocations. With FRI_STRESS_PAGE_CHURN set, every frame is a
        // fresh 8 MB allocation that goes back to the kernel instead (see the module docs).
        let churn = std::env::var_os("FRI_STRESS_PAGE_CHURN").is_some();
        for i in 0..cores {
            let (stop, work) = (Arc::clone(&stop), Arc::clone(&work));
            threads.push(
                std::thread::Builder::new()
                    .name(format!("load-render-{i}"))
                    .spawn(move || {
                        let mut frame = 0u8;
                        let mut image = vec![0u8; 8 << 20];
                        let mut copy = vec![0u8; 8 << 20];
                        while !stop.load(Ordering::Relaxed) {
                            if churn {
                                image = vec![frame; 8 << 20];
                                copy = image.clone();
                            } else {
                                image.fill(frame);
                                copy.copy_from_slice(&image);
                                let scratch: Vec<Vec<u8>> =
                                    (0..64).map(|k| vec![frame ^ k; 1 << 10]).collect();
                                std::hint::black_box(&scratch);
                            }
                            std::hint::black_box(&copy);
                            frame = frame.wrapping_add(1);
                            work.fetch_add(1, Ordering::Relaxed);
                        }
                    })
                    .expect("spawn load"),
            );
        }
        Self {
            stop,
            threads,
            work,
        }
    }
}

impl Drop for Load {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

/// The agent's use of the client: motions back and forth, stillness polled in between.
fn agent(client: &FriClient, stop: &AtomicBool) -> (u64, u64) {
    let poses: [Joints; 2] = [
        [0.4, 0.3, -0.2, -1.0, 0.3, 0.6, 0.4],
        [0.0, 0.5, 0.0, -1.2, 0.0, 0.8, 0.0],
    ];
    let (mut moves, mut failures) = (0, 0);
    while !stop.load(Ordering::SeqCst) {
        for target in poses {
            if stop.load(Ordering::SeqCst) {
                break;
            }
            match client.move_to(target) {
                Ok(()) => moves += 1,
                Err(e) => {
                    failures += 1;
                    eprintln!("agent: move_to failed: {e}");
                    let _ = client
                        .wait_for_state(SessionState::CommandingActive, Duration::from_secs(2));
                }
            }
            let polled_until = Instant::now() + Duration::from_millis(200);
            while Instant::now() < polled_until {
                let _ = client.is_still(Duration::from_millis(100), 2e-4);
                let _ = client.latest();
                std::thread::sleep(Duration::from_millis(10));
            }
        }
    }
    (moves, failures)
}

/// CPU time the hypervisor gave to other guests while this one wanted to run
/// ("steal", summed over CPUs; `/proc/stat`, 10 ms per tick), when the kernel
/// reports it. A cycle thread cannot be on time while its CPU is stolen.
fn steal_ms() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let cpu = stat.lines().find(|l| l.starts_with("cpu "))?;
    let ticks: u64 = cpu.split_whitespace().nth(8)?.parse().ok()?;
    Some(ticks as f64 * 10.0)
}

fn per_10k(count: u64, cycles: u64) -> f64 {
    count as f64 * 10_000.0 / cycles.max(1) as f64
}

#[test]
fn replies_stay_on_time_with_every_core_busy() {
    let cycles: u64 = std::env::var("FRI_STRESS_CYCLES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(DEFAULT_CYCLES);
    let guard = SafetyGuard::new(
        JointLimits::iiwa7(),
        WorkspaceBox::new([-1.0, -1.0, 0.0], [1.0, 1.0, 1.5]).expect("box"),
        fk,
    )
    .expect("guard");
    // To see what the dedicated threads achieve without real-time scheduling.
    let priority = match std::env::var_os("FRI_STRESS_NORMAL_SCHEDULING") {
        Some(_) => None,
        None => Some(kuka_fri::DEFAULT_CYCLE_PRIORITY),
    };
    let client = FriClient::start(
        FriClientConfig {
            realtime_priority: priority,
            ..FriClientConfig::new("127.0.0.1:0".parse().expect("addr"))
        },
        guard,
    )
    .expect("client");
    let controller = SimServer::start(SimServerConfig {
        bind: "127.0.0.1:0".parse().expect("addr"),
        realtime_priority: priority,
        ..SimServerConfig::new(
            client.local_addr(),
            SimConfig {
                send_period_ms: SEND_PERIOD_MS,
                ..SimConfig::default()
            },
        )
    })
    .expect("controller");
    client
        .wait_for_state(SessionState::CommandingActive, Duration::from_secs(10))
        .expect("commanding before the load starts");

    let steal_before = steal_ms();
    let load = Load::start();
    let stop_agent = AtomicBool::new(false);
    let before = controller.snapshot().stats;
    let started = Instant::now();
    let (after, (moves, failures)) = std::thread::scope(|s| {
        let agent = s.spawn(|| agent(&client, &stop_agent));
        let limit = started + Duration::from_millis(u64::from(SEND_PERIOD_MS) * cycles * 3);
        let after = loop {
            std::thread::sleep(Duration::from_millis(50));
            let now = controller.snapshot().stats;
            if now.sent - before.sent >= cycles || Instant::now() > limit {
                break now;
            }
        };
        stop_agent.store(true, Ordering::SeqCst);
        (after, agent.join().expect("agent thread"))
    });
    let elapsed = started.elapsed();
    let stolen = steal_ms().zip(steal_before).map(|(a, b)| a - b);
    let work = load.work.load(Ordering::Relaxed);
    drop(load);
    let client_stats = client.stats();
    let client_scheduling = client.scheduling();
    let controller_scheduling = controller.snapshot().scheduling;
    controller.shutdown().expect("controller ran to the end");
    client.shutdown();

    let sent = after.sent - before.sent;
    let missed = after.missed_replies - before.missed_replies;
    let missed_controller = after.missed_after_late_send - before.missed_after_late_send;
    let missed_client = missed - missed_controller;
    let late_sends = after.late_sends - before.late_sends;
    let aborted = after.aborted - before.aborted;
    println!(
        "FRI under load: {sent} cycles at {SEND_PERIOD_MS} ms in {:.1} s, every core busy \
         ({work} load work units), {moves} motions ({failures} failed)",
        elapsed.as_secs_f64()
    );
    println!(
        "  missed replies: {missed} ({:.1} per 10,000 cycles): {missed_controller} after a late \
         controller send, {missed_client} with the client late; {} replies arrived late",
        per_10k(missed, sent),
        after.late_replies - before.late_replies,
    );
    println!(
        "  controller: {late_sends} late sends ({:.1} per 10,000), longest {:.2} ms late; \
         longest reply latency {:.2} ms; {aborted} commanding phases aborted",
        per_10k(late_sends, sent),
        after.max_send_lateness.as_secs_f64() * 1e3,
        after.max_reply_latency.as_secs_f64() * 1e3,
    );
    println!("  client: {client_stats:?}");
    match stolen {
        Some(ms) => {
            println!("  CPU time stolen by the hypervisor during the run: {ms:.0} ms over all CPUs")
        }
        None => println!("  CPU time stolen by the hypervisor: not reported by this kernel"),
    }
    println!(
        "  cycle threads scheduled: controller {controller_scheduling:?}, client \
         {client_scheduling:?}"
    );

    assert!(sent >= cycles, "only {sent} of {cycles} cycles ran");
    // No commanding phase may ever be lost. Missed replies: the code before the fix
    // missed 4,761 per 10,000; the cycle threads now miss 0 to 30 per 10,000 on
    // this virtual machine (0 in a quiet 10,000-cycle run, 5 and 30 in fresh-clone
    // CI runs: stalls of the machine itself, both sides, SCHED_FIFO or not). The
    // bound, 1%, keeps the test able to fail on the old behaviour without failing
    // on the machine.
    let allowed = sent / MISS_ALLOWANCE_CYCLES;
    assert_eq!(aborted, 0, "commanding phases aborted");
    assert!(
        missed <= allowed,
        "{missed} missed replies in {sent} cycles (controller late: {missed_controller}, client \
         late: {missed_client}); at most {allowed} allowed"
    );
    assert_eq!(failures, 0, "motions failed");
}
