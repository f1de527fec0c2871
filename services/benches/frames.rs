//! Camera frames between processes: iceoryx2 shared memory against zenoh, in one run.
//!
//! A RealSense-sized stream pair, 848x480 Z16 depth (814,080 bytes) and 1280x720
//! RGB8 colour (2,764,800 bytes), at 90 fps. This process is the camera; a second
//! process (this executable again, `B2B_FRAMES_BENCH_CHILD` set) subscribes to both
//! streams, takes the receive time of every frame and checks every 16th frame's
//! bytes. Latency is the receiver's clock minus the sender's (the same host's
//! realtime clock, so no round trip is needed):
//!
//! * iceoryx2 "written -> received": the camera writes the frame into the loaned
//!   shared-memory sample ([`FramePublisher::publish_with`]) and the clock starts
//!   when it has finished; the subscriber busy-polls.
//! * iceoryx2 "loan -> received": the same, the clock started before the loan
//!   (includes zeroing and writing 2.7 MB).
//! * zenoh "put -> received": the frame is in the camera's memory and the clock
//!   starts before `put` (two peers on TCP loopback, the services' configuration).
//!
//! CPU is each process's user + system time over the phase (from /proc, 10 ms
//! ticks), per second of streaming. The iceoryx2 subscriber spins, so its CPU is
//! one core by construction; the camera side is the number to compare.
//!
//! `cargo bench -p b2b-services --bench frames` streams 10 s per transport; under
//! `cargo test --benches` a smoke pass streams 20 frame pairs.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpListener;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use b2b_frames::{FrameHeader, FramePublisher, FrameSubscriber, Stream, StreamKind, now_ns};
use zenoh::Wait;

const CHILD: &str = "B2B_FRAMES_BENCH_CHILD";
const FPS: f64 = 90.0;
const DEPTH: (u32, u32) = (848, 480);
const COLOUR: (u32, u32) = (1280, 720);
const CHECK_EVERY: u64 = 16;

fn cpu_seconds() -> f64 {
    // utime and stime, fields 14 and 15 of /proc/self/stat, in 1/100 s ticks.
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

/// A cheap checksum: 64-bit words, rotated and xored (the bench checks bytes,
/// not adversaries).
fn checksum(bytes: &[u8]) -> u64 {
    let mut h = bytes.len() as u64;
    let mut words = bytes.chunks_exact(8);
    for w in &mut words {
        let mut a = [0u8; 8];
        a.copy_from_slice(w);
        h = h.rotate_left(5) ^ u64::from_le_bytes(a);
    }
    for b in words.remainder() {
        h = h.rotate_left(5) ^ u64::from(*b);
    }
    h
}

fn percentile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// Four different frames per stream, cycled.
fn frames() -> [Vec<Vec<u8>>; 2] {
    let make = |len: usize, seed: u64| -> Vec<Vec<u8>> {
        (0..4u64)
            .map(|k| {
                let mut x = (seed + k).wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
                (0..len)
                    .map(|_| {
                        x ^= x << 13;
                        x ^= x >> 7;
                        x ^= x << 17;
                        (x >> 24) as u8
                    })
                    .collect()
            })
            .collect()
    };
    [
        make((DEPTH.0 * DEPTH.1 * 2) as usize, 1),
        make((COLOUR.0 * COLOUR.1 * 3) as usize, 100),
    ]
}

fn headers() -> [FrameHeader; 2] {
    [
        FrameHeader::new(StreamKind::Z16, DEPTH.0, DEPTH.1)
            .with_intrinsics(425.0, 425.0, 424.0, 240.0, [0.0; 5]),
        FrameHeader::new(StreamKind::Rgb8, COLOUR.0, COLOUR.1)
            .with_intrinsics(910.0, 910.0, 640.0, 360.0, [0.0; 5]),
    ]
}

/// What the subscriber process saw of one frame.
#[derive(Debug, Clone, Copy)]
struct Arrival {
    stream: usize,
    seq: u64,
    t_ns: u64,
    check: u64,
}

// ---------------------------------------------------------------- child side

struct Recorder {
    arrivals: Vec<Arrival>,
    warm: bool,
    last: [u64; 2],
}

impl Recorder {
    fn record(&mut self, stream: usize, seq: u64, t_ns: u64, data: &[u8], out: &mut dyn Write) {
        if seq == 0 {
            if !self.warm {
                self.warm = true;
                let _ = writeln!(out, "warm");
                let _ = out.flush();
            }
            return;
        }
        let check = if seq % CHECK_EVERY == 1 {
            checksum(data)
        } else {
            0
        };
        self.arrivals.push(Arrival {
            stream,
            seq,
            t_ns,
            check,
        });
        self.last[stream] = self.last[stream].max(seq);
    }
}

fn child_main(mode: &str) {
    let arg = std::env::var("B2B_FRAMES_BENCH_ARG").expect("arg");
    let n: u64 = std::env::var("B2B_FRAMES_BENCH_N")
        .ok()
        .and_then(|v| v.parse().ok())
        .expect("N");
    let mut out = std::io::stdout().lock();
    let mut rec = Recorder {
        arrivals: Vec::with_capacity(2 * n as usize),
        warm: false,
        last: [0; 2],
    };
    let deadline = Instant::now() + Duration::from_secs(60 + n / 10);
    let cpu0;
    match mode {
        "iceoryx2" => {
            b2b_frames::quiet_iceoryx2_logs();
            let mut subs = [Stream::Depth, Stream::Colour].map(|s| {
                FrameSubscriber::new(&b2b_frames::service_name_in(&arg, "bench", s))
                    .expect("subscriber")
            });
            writeln!(out, "ready").expect("stdout");
            out.flush().expect("stdout");
            cpu0 = cpu_seconds();
            while rec.last.iter().any(|l| *l < n) && Instant::now() < deadline {
                for (i, sub) in subs.iter_mut().enumerate() {
                    if let Some(frame) = sub.next().expect("receive") {
                        let t = now_ns();
                        let h = *frame.header();
                        // The warm-up frames carry frame number 0.
                        let seq = if h.frame_number == 0 {
                            0
                        } else {
                            h.frame_number
                        };
                        rec.record(i, seq, t, frame.data(), &mut out);
                    }
                }
            }
        }
        "zenoh" => {
            let session = b2b_services::bus::open(
                b2b_services::bus::config(Some(Path::new(&arg)), b2b_services::bus::Role::Agent)
                    .expect("config"),
            )
            .expect("session");
            let sub = session
                .declare_subscriber("b2b/bench/frames/*")
                .wait()
                .expect("subscribe");
            writeln!(out, "ready").expect("stdout");
            out.flush().expect("stdout");
            cpu0 = cpu_seconds();
            while rec.last.iter().any(|l| *l < n) && Instant::now() < deadline {
                if let Ok(Some(sample)) = sub.recv_timeout(Duration::from_millis(100)) {
                    let t = now_ns();
                    let stream = usize::from(sample.key_expr().as_str().ends_with("colour"));
                    let seq = sample
                        .attachment()
                        .map(|a| {
                            let b = a.to_bytes();
                            let mut s = [0u8; 8];
                            s.copy_from_slice(&b[..8]);
                            u64::from_le_bytes(s)
                        })
                        .unwrap_or(0);
                    let bytes = sample.payload().to_bytes();
                    rec.record(stream, seq, t, &bytes, &mut out);
                }
            }
        }
        other => panic!("unknown child mode {other}"),
    }
    let cpu = cpu_seconds() - cpu0;
    for a in &rec.arrivals {
        writeln!(out, "{} {} {} {}", a.stream, a.seq, a.t_ns, a.check).expect("stdout");
    }
    writeln!(out, "cpu {cpu}").expect("stdout");
    writeln!(out, "end").expect("stdout");
}

// ---------------------------------------------------------------- parent side

struct ChildLines {
    child: Child,
    lines: mpsc::Receiver<String>,
}

fn spawn_child(mode: &str, arg: &str, n: u64) -> ChildLines {
    let mut child = Command::new(std::env::current_exe().expect("exe"))
        .env(CHILD, mode)
        .env("B2B_FRAMES_BENCH_ARG", arg)
        .env("B2B_FRAMES_BENCH_N", n.to_string())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("spawn subscriber process");
    let stdout = child.stdout.take().expect("stdout");
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let first = rx.recv_timeout(Duration::from_secs(30));
    assert_eq!(
        first.as_deref(),
        Ok("ready"),
        "subscriber process did not start"
    );
    ChildLines { child, lines: rx }
}

/// Sends warm-up frames (frame number 0) until the child has one.
fn warm_up(child: &ChildLines, mut send: impl FnMut()) {
    let start = Instant::now();
    loop {
        send();
        if let Ok(line) = child.lines.recv_timeout(Duration::from_millis(50)) {
            assert_eq!(line, "warm");
            return;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "no warm-up frame arrived"
        );
    }
}

struct Sent {
    /// Per stream, per frame (index seq-1): clock at loan/put start, and when written.
    start_ns: [Vec<u64>; 2],
    written_ns: [Vec<u64>; 2],
    cpu: f64,
    seconds: f64,
}

fn collect(child: ChildLines, sent: &Sent, frames: &[Vec<Vec<u8>>; 2], name: &str, n: u64) {
    let mut arrivals = Vec::new();
    let mut child_cpu = f64::NAN;
    loop {
        let line = child
            .lines
            .recv_timeout(Duration::from_secs(120))
            .expect("subscriber results");
        if line == "end" {
            break;
        }
        if let Some(c) = line.strip_prefix("cpu ") {
            child_cpu = c.parse().unwrap_or(f64::NAN);
            continue;
        }
        let v: Vec<u64> = line.split(' ').filter_map(|x| x.parse().ok()).collect();
        if v.len() == 4 {
            arrivals.push(Arrival {
                stream: v[0] as usize,
                seq: v[1],
                t_ns: v[2],
                check: v[3],
            });
        }
    }
    let mut child = child.child;
    let _ = child.wait();
    let mut from_written = [Vec::new(), Vec::new()];
    let mut from_start = [Vec::new(), Vec::new()];
    let mut received = [0u64; 2];
    for a in &arrivals {
        let i = (a.seq - 1) as usize;
        received[a.stream] += 1;
        from_written[a.stream].push((a.t_ns as f64 - sent.written_ns[a.stream][i] as f64) / 1e3);
        from_start[a.stream].push((a.t_ns as f64 - sent.start_ns[a.stream][i] as f64) / 1e3);
        if a.check != 0 {
            let want = checksum(&frames[a.stream][i % 4]);
            assert_eq!(
                a.check, want,
                "{name}: frame {} of stream {} differs",
                a.seq, a.stream
            );
        }
    }
    for (s, label) in [(0, "depth 848x480 Z16"), (1, "colour 1280x720 RGB8")] {
        let (w, st) = (&mut from_written[s], &mut from_start[s]);
        let lost = n - received[s];
        let over = |v: &[f64]| v.iter().filter(|x| **x > 50.0).count();
        if name == "iceoryx2" {
            println!(
                "  {name:8} {label:21}: written->received p50 {:7.1} us, p90 {:7.1} us, p99 {:7.1} us, max {:7.1} us, over 50 us {}/{} | loan->received p50 {:7.1} us, p99 {:7.1} us | lost {lost}/{n}",
                percentile(w, 0.5),
                percentile(w, 0.9),
                percentile(w, 0.99),
                w.iter().copied().fold(0.0, f64::max),
                over(w),
                w.len(),
                percentile(st, 0.5),
                percentile(st, 0.99),
            );
        } else {
            println!(
                "  {name:8} {label:21}: put->received p50 {:7.1} us, p90 {:7.1} us, p99 {:7.1} us, max {:7.1} us, over 50 us {}/{} | lost {lost}/{n}",
                percentile(st, 0.5),
                percentile(st, 0.9),
                percentile(st, 0.99),
                st.iter().copied().fold(0.0, f64::max),
                over(st),
                st.len(),
            );
        }
    }
    println!(
        "  {name:8} CPU per second of streaming: camera process {:.1} %, subscriber process {:.1} %{}",
        100.0 * sent.cpu / sent.seconds,
        100.0 * child_cpu / sent.seconds,
        if name == "iceoryx2" {
            " (busy-polls)"
        } else {
            ""
        }
    );
}

/// Paces `n` frame pairs at FPS, calling `send(index)` for each.
fn stream(n: u64, mut send: impl FnMut(u64)) -> (f64, f64) {
    let cpu0 = cpu_seconds();
    let start = Instant::now();
    let period = Duration::from_secs_f64(1.0 / FPS);
    let mut next = start;
    for k in 1..=n {
        send(k);
        next += period;
        let now = Instant::now();
        if next > now {
            std::thread::sleep(next - now);
        }
    }
    (cpu_seconds() - cpu0, start.elapsed().as_secs_f64())
}

fn iceoryx2(n: u64, frames: &[Vec<Vec<u8>>; 2]) {
    b2b_frames::quiet_iceoryx2_logs();
    let prefix = format!("b2b-bench/{}/{}", std::process::id(), now_ns());
    let child = spawn_child("iceoryx2", &prefix, n);
    let hs = headers();
    let mut pubs = [Stream::Depth, Stream::Colour].map(|s| {
        let h = &hs[usize::from(s == Stream::Colour)];
        FramePublisher::new(
            &b2b_frames::service_name_in(&prefix, "bench", s),
            h.payload_len(),
        )
        .expect("publisher")
    });
    warm_up(&child, || {
        for (s, p) in pubs.iter_mut().enumerate() {
            p.publish_bytes(&hs[s].at(0, now_ns()), &frames[s][0])
                .expect("warm-up");
        }
    });
    let mut sent = Sent {
        start_ns: [Vec::new(), Vec::new()],
        written_ns: [Vec::new(), Vec::new()],
        cpu: 0.0,
        seconds: 0.0,
    };
    let (cpu, seconds) = stream(n, |k| {
        for (s, p) in pubs.iter_mut().enumerate() {
            let t0 = now_ns();
            let mut written = 0;
            let src = &frames[s][(k - 1) as usize % 4];
            // The camera writes its frame into the loan (here: from memory).
            p.publish_with(&hs[s].at(k, t0), |buf| {
                buf.copy_from_slice(src);
                written = now_ns();
            })
            .expect("publish");
            sent.start_ns[s].push(t0);
            sent.written_ns[s].push(written);
        }
    });
    (sent.cpu, sent.seconds) = (cpu, seconds);
    collect(child, &sent, frames, "iceoryx2", n);
}

fn zenoh_configs(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let port = TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .unwrap_or(17449);
    let listen = dir.join("listen.json5");
    let connect = dir.join("connect.json5");
    std::fs::write(
        &listen,
        format!(r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#),
    )
    .expect("write config");
    std::fs::write(
        &connect,
        format!(r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:0"] }}, connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#),
    )
    .expect("write config");
    (listen, connect)
}

fn zenoh_run(n: u64, frames: &[Vec<Vec<u8>>; 2]) {
    let dir = tempfile::tempdir().expect("tempdir");
    let (listen, connect) = zenoh_configs(dir.path());
    let session = b2b_services::bus::open(
        b2b_services::bus::config(Some(&listen), b2b_services::bus::Role::Coordinator)
            .expect("config"),
    )
    .expect("session");
    let child = spawn_child("zenoh", &connect.display().to_string(), n);
    let pubs = ["b2b/bench/frames/depth", "b2b/bench/frames/colour"]
        .map(|k| session.declare_publisher(k).wait().expect("publisher"));
    warm_up(&child, || {
        for (s, p) in pubs.iter().enumerate() {
            p.put(frames[s][0].clone())
                .attachment(0u64.to_le_bytes().to_vec())
                .wait()
                .expect("put");
        }
    });
    let mut sent = Sent {
        start_ns: [Vec::new(), Vec::new()],
        written_ns: [Vec::new(), Vec::new()],
        cpu: 0.0,
        seconds: 0.0,
    };
    let (cpu, seconds) = stream(n, |k| {
        for (s, p) in pubs.iter().enumerate() {
            let t0 = now_ns();
            p.put(frames[s][(k - 1) as usize % 4].clone())
                .attachment(k.to_le_bytes().to_vec())
                .wait()
                .expect("put");
            sent.start_ns[s].push(t0);
            sent.written_ns[s].push(t0);
        }
    });
    (sent.cpu, sent.seconds) = (cpu, seconds);
    collect(child, &sent, frames, "zenoh", n);
}

fn main() {
    if let Ok(mode) = std::env::var(CHILD) {
        child_main(&mode);
        return;
    }
    let full = std::env::args().any(|a| a == "--bench");
    let n = if full { (10.0 * FPS) as u64 } else { 20 };
    let frames = frames();
    println!(
        "848x480 Z16 depth + 1280x720 RGB8 colour at {FPS} fps between two processes, {n} frame pairs per transport:"
    );
    iceoryx2(n, &frames);
    zenoh_run(n, &frames);
}
