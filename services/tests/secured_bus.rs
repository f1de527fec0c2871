//! The secured bus end to end: `coordinator pki init`, then `coordinator run`
//! and two agents over mutual TLS with access control, each its own process,
//! while rogue peers, each its own process too, try what the issue saw work on
//! the open bus:
//!
//! - robot2's certificate, with its own access control removed (a rogue
//!   controls its own configuration), runs `agent run --robot robot1` on a copy
//!   of robot1's captures moved by 5 cm, and publishes forged statuses ("robot1
//!   finished, 0 published", with a huge sequence number) and a forged result
//!   ("coordinator" says T = [9, 9, 9]);
//! - robot1's own certificate sends garbage on its capture key (a broken agent);
//! - a peer without a certificate runs `agent run --robot robot1` on the same
//!   moved copy.
//!
//! The result must equal the offline calibration of the untouched dataset, and
//! the real agents must receive the real result. It must also when every
//! access-control rule is gone (a wrong configuration): then the messages'
//! signatures keep the rogues out, and the journal names the certificate that
//! signed each sample.

mod common;

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use b2b_protocol::messages::{AgentState, AgentStatus, COORDINATOR, Envelope};
use b2b_services::bus::{Role, ZenohBus};
use common::{Killed, assert_same, free_port, offline_result_of};
use zenoh::Wait;

fn dataset() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12")
}

fn bin(name: &str) -> PathBuf {
    Path::new(env!("CARGO_BIN_EXE_agent"))
        .with_file_name(format!("{name}{}", std::env::consts::EXE_SUFFIX))
}

/// `dataset()` copied into `to`, robot1's flange positions moved by 5 cm in x.
fn moved_copy(to: &Path) {
    common::copy_dir(&dataset(), to);
    let captures = to.join("robot1/captures.csv");
    let text = std::fs::read_to_string(&captures).unwrap();
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let tx = header.iter().position(|h| *h == "tx").unwrap();
    let mut out = header.join(",") + "\n";
    for line in lines {
        let mut cells: Vec<String> = line.split(',').map(str::to_owned).collect();
        let v: f64 = cells[tx].parse().unwrap();
        cells[tx] = format!("{:?}", v + 0.05);
        out += &(cells.join(",") + "\n");
    }
    std::fs::write(&captures, out).unwrap();
}

/// `coordinator pki ARGS --dir DIR`, which must succeed; its stdout.
fn pki_command(args: &[&str], dir: &Path) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .arg("pki")
        .args(args)
        .arg("--dir")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A configuration derived from `base` by `edit` (the files are JSON).
fn derived(base: &Path, to: &Path, edit: impl FnOnce(&mut serde_json::Value)) -> PathBuf {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(base).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(to, serde_json::to_string_pretty(&v).unwrap()).unwrap();
    to.to_owned()
}

/// `agent run --replay`, one capture every `pace_ms`, waiting up to 60 s for
/// the result (answering the coordinator's history queries meanwhile).
fn agent(robot: &str, dataset: &Path, config: &Path, state: &Path, pace_ms: u32) -> Child {
    Command::new(env!("CARGO_BIN_EXE_agent"))
        .args(["run", "--quiet", "--robot", robot, "--replay"])
        .arg(dataset)
        .arg("--zenoh")
        .arg(config)
        .arg("--state-dir")
        .arg(state)
        .args(["--wait-result-s", "60", "--pace-ms", &pace_ms.to_string()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn put(config: &Path, key: &str, payload: &Path) -> Child {
    Command::new(bin("b2b-bus-put"))
        .arg("--zenoh")
        .arg(config)
        .args(["--key", key, "--count", "150", "--every-ms", "200"])
        .arg("--payload")
        .arg(payload)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// A child's stdout and stderr, read while it runs: a test can wait for what
/// it prints (the event a line stands for), and a full pipe never stalls it.
struct Printout {
    /// Stdout, then stderr.
    streams: [Arc<Mutex<Vec<u8>>>; 2],
    readers: Vec<std::thread::JoinHandle<()>>,
}

impl Printout {
    /// Takes `child`'s piped stdout and stderr and reads them from now on.
    fn of(child: &mut Child) -> Printout {
        let streams: [Arc<Mutex<Vec<u8>>>; 2] = Default::default();
        let pipes = [
            child
                .stdout
                .take()
                .map(|p| Box::new(p) as Box<dyn Read + Send>),
            child
                .stderr
                .take()
                .map(|p| Box::new(p) as Box<dyn Read + Send>),
        ];
        let readers = pipes
            .into_iter()
            .zip(&streams)
            .filter_map(|(pipe, text)| {
                let (mut pipe, text) = (pipe?, Arc::clone(text));
                Some(std::thread::spawn(move || {
                    let mut buf = [0u8; 8192];
                    loop {
                        match pipe.read(&mut buf) {
                            Ok(0) => break,
                            Ok(n) => text.lock().unwrap().extend_from_slice(&buf[..n]),
                            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                            Err(_) => break,
                        }
                    }
                }))
            })
            .collect();
        Printout { streams, readers }
    }

    /// What the child printed so far: its stdout, then its stderr.
    fn text(&self) -> String {
        self.streams
            .iter()
            .map(|s| String::from_utf8_lossy(&s.lock().unwrap()).into_owned())
            .collect()
    }

    /// Waits until what the child printed satisfies `heard`, up to `limit`
    /// (a generous bound: it only turns an event that never comes into a
    /// failure, naming `what` was awaited).
    fn wait_for(&self, what: &str, limit: Duration, heard: impl Fn(&str) -> bool) {
        let start = Instant::now();
        loop {
            let text = self.text();
            if heard(&text) {
                return;
            }
            assert!(
                start.elapsed() < limit,
                "not within {limit:?}: {what}; it printed:\n{text}"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits for `child` to exit, up to `limit`; whether it succeeded, and
    /// everything it printed (its stdout, then its stderr).
    fn exited(mut self, mut child: Killed, limit: Duration) -> (bool, String) {
        let start = Instant::now();
        let status = loop {
            if let Some(status) = child.0.try_wait().unwrap() {
                break status;
            }
            assert!(
                start.elapsed() < limit,
                "no exit within {limit:?}; it printed:\n{}",
                self.text()
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        // Its pipes are closed: the readers end with the last bytes.
        for reader in std::mem::take(&mut self.readers) {
            let _ = reader.join();
        }
        (status.success(), self.text())
    }
}

/// Waits for a child to exit; whether it succeeded, and its stdout then stderr.
fn exited(child: Child, limit: Duration) -> (bool, String) {
    let mut child = Killed(child);
    let printout = Printout::of(&mut child.0);
    printout.exited(child, limit)
}

/// The number of the last message an agent sent (a capture or a status, its
/// heartbeat twice a second included): its sequence counter, which it stores
/// in its state folder before each message goes out. 0 before the first.
fn last_sequence(state: &Path, robot: &str) -> u64 {
    std::fs::read_to_string(state.join(format!("agent-{robot}.seq")))
        .ok()
        .and_then(|t| t.trim().parse().ok())
        .unwrap_or(0)
}

/// Waits for a child to exit successfully and returns its stdout, then its stderr.
fn finished(mut child: Child, what: &str, limit: Duration) -> String {
    let start = Instant::now();
    loop {
        if child.try_wait().unwrap().is_some() {
            let out = child.wait_with_output().unwrap();
            assert!(
                out.status.success(),
                "{what} failed: {}",
                String::from_utf8_lossy(&out.stderr)
            );
            return format!(
                "{}{}",
                String::from_utf8_lossy(&out.stdout),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            panic!("{what} did not finish within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// How many peers a session with `config` has once connected: waits for the
/// first (up to 30 s, then 0: it was refused).
fn peers_of(config: &Path) -> usize {
    let bus = ZenohBus::open(Some(config), Role::Agent).unwrap();
    connected(&bus, Duration::from_secs(30))
}

/// The peers of `bus` as soon as it has one, or 0 after `limit`.
fn connected(bus: &ZenohBus, limit: Duration) -> usize {
    let start = Instant::now();
    loop {
        let n = bus.session().info().peers_zid().wait().count();
        if n > 0 || start.elapsed() > limit {
            return n;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Whether a session with `refused` is refused where one with `admitted`,
/// opened just after it, is connected: no fixed wait, the admitted one's
/// connection is the event (the refused one had as long to connect).
fn refused_where_admitted(refused: &Path, admitted: &Path) -> bool {
    let first = ZenohBus::open(Some(refused), Role::Agent).unwrap();
    let second = ZenohBus::open(Some(admitted), Role::Agent).unwrap();
    assert_eq!(connected(&second, Duration::from_secs(30)), 1);
    first.session().info().peers_zid().wait().count() == 0
}

/// What a run with the rogues gave: the result and the offline one, the
/// coordinator's printout, and the real agents' printouts.
struct Outcome {
    /// `None` when the coordinator failed.
    live: Option<b2b_protocol::CalibrationResult>,
    offline: b2b_protocol::CalibrationResult,
    /// Its stdout, then its stderr.
    coordinator: String,
    agents: Vec<String>,
    /// The coordinator's journal.
    journal: String,
}

/// Every journal line names its signer, and the signer is the robot the
/// sample's envelope names.
fn assert_journal_signed(journal: &str) {
    let lines: Vec<serde_json::Value> = journal
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert!(lines.len() >= 20, "{journal}");
    for l in &lines {
        assert_eq!(l["signer"], l["robot"], "{l}");
    }
}

/// The run gave the clean result: the offline one, no capture in conflict,
/// every journal line signed by its robot, and each real agent took the real
/// result.
fn assert_clean(o: &Outcome) {
    let live = o
        .live
        .as_ref()
        .unwrap_or_else(|| panic!("{}", o.coordinator));
    assert_same(live, &o.offline);
    assert!(
        o.coordinator.contains(" 0 conflicting captures"),
        "{}",
        o.coordinator
    );
    assert_journal_signed(&o.journal);
    let t = o.offline.base1_from_base2.t;
    let real = format!("t = [{:.6}, {:.6}, {:.6}] m", t[0], t[1], t[2]);
    assert_eq!(o.agents.len(), 2);
    for said in &o.agents {
        assert!(said.contains(&real), "{said} (expected {real})");
    }
}

#[test]
fn rogue_peers_change_nothing_on_the_secured_bus() {
    let o = run_with_rogues(true);
    assert_clean(&o);
    // The garbage robot1's certificate sent was logged, counted and survived.
    assert!(
        o.coordinator
            .contains("b2b/agent/robot1/capture: not a valid message")
            && !o.coordinator.contains(" 0 rejected"),
        "{}",
        o.coordinator
    );
    // The access control's refusals are logged: robot2's certificate speaking
    // for robot1. (Its forged result is refused nowhere: zenoh sends a put
    // only towards subscribers, and the agents that subscribe to results are
    // reached through the coordinator, which does not forward between peers.)
    for line in o
        .coordinator
        .lines()
        .filter(|l| l.contains("access control refused"))
        .take(3)
    {
        eprintln!("{line}");
    }
    let key = "b2b/agent/robot1/";
    assert!(
        o.coordinator
            .lines()
            .any(|l| l.contains("access control refused") && l.contains(key)),
        "no refusal of {key} logged: {}",
        o.coordinator
    );
}

/// The same run with every access-control rule removed (TLS still on), as a
/// wrong configuration would leave it. robot2's certificate now reaches
/// robot1's keys. Without signatures, its moved captures were heard
/// (conflicts, or a moved result: this test's earlier form showed it). Now
/// each of its messages is dropped and logged for its signature: signed by
/// robot2 under robot1's key. The result is the clean one and each agent takes
/// the real result. (Its forged result reaches no agent either way: carts
/// listen on nothing, and the coordinator does not forward a put between
/// peers; an agent's own check of the result's signature is
/// `signing::tests`.)
#[test]
fn without_access_control_the_signatures_keep_the_rogues_out() {
    let o = run_with_rogues(false);
    assert_clean(&o);
    for key in ["b2b/agent/robot1/capture", "b2b/agent/robot1/status"] {
        let said = format!(
            "{key}: rejected: signed with the certificate of 'robot2', but the key is robot1's"
        );
        assert!(
            o.coordinator.lines().any(|l| l.contains(&said)),
            "no '{said}' in {}",
            o.coordinator
        );
    }
    // No access-control refusals: there was no rule to refuse by.
    assert!(!o.coordinator.contains("access control refused"));
}

/// The coordinator killed mid-run on the secured bus and started again with
/// the same state folder: the samples it had journalled and those the agents
/// published meanwhile (answered from their history when it asks, over mutual
/// TLS) complete the run. The result equals the offline calibration, and each
/// agent receives it.
#[test]
fn the_coordinator_killed_and_restarted_mid_run_under_tls_loses_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let pki = dir.join("pki");
    let listen = format!("tls/127.0.0.1:{}", free_port());
    pki_command(
        &["init", "--robots", "robot1,robot2", "--listen", &listen],
        &pki,
    );
    let coordinator = || {
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["run", "--robots", "robot1,robot2", "--zenoh"])
            .arg(pki.join("coordinator.json5"))
            .arg("--state-dir")
            .arg(dir.join("coordinator-state"))
            .arg("--out")
            .arg(dir.join("RESULT.json"))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let first = Killed(coordinator());
    // Paced, so that captures are still coming when the coordinator dies.
    let agents: Vec<(Child, &str)> = ["robot1", "robot2"]
        .into_iter()
        .map(|robot| {
            let config = pki.join(format!("{robot}.json5"));
            let state = dir.join(format!("agent-{robot}"));
            (agent(robot, &dataset(), &config, &state, 300), robot)
        })
        .collect();
    let journal = dir.join("coordinator-state/samples.jsonl");
    let lines = || std::fs::read_to_string(&journal).map_or(0, |t| t.lines().count());
    let start = Instant::now();
    while lines() < 6 {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "nothing reached the coordinator over TLS"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    drop(first);
    let kept = lines();
    assert!(kept >= 6, "{kept} samples journalled");
    // Each agent sends on with no coordinator to hear it (what the restarted
    // one must ask their history for) before the restart.
    let sent_at_kill: Vec<u64> = agents
        .iter()
        .map(|(_, robot)| last_sequence(&dir.join(format!("agent-{robot}")), robot))
        .collect();
    let start = Instant::now();
    for ((_, robot), at_kill) in agents.iter().zip(sent_at_kill) {
        let state = dir.join(format!("agent-{robot}"));
        while last_sequence(&state, robot) <= at_kill {
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "{robot} sent nothing within 60 s of the coordinator's kill (its last message was number {at_kill})"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }
    let (ok, printed) = exited(coordinator(), Duration::from_secs(180));
    assert!(ok, "the restarted coordinator failed: {printed}");
    // The restart had work left: samples arrived after it.
    let total = lines();
    eprintln!("journalled before the kill: {kept}; in all: {total}");
    assert!(total > kept, "{kept} of {total} samples before the kill");
    let live: b2b_protocol::CalibrationResult =
        serde_json::from_str(&std::fs::read_to_string(dir.join("RESULT.json")).unwrap()).unwrap();
    let offline = offline_result_of(dir, &dataset(), "board");
    assert_same(&live, &offline);
    let t = offline.base1_from_base2.t;
    let real = format!("t = [{:.6}, {:.6}, {:.6}] m", t[0], t[1], t[2]);
    for (a, robot) in agents {
        let said = finished(a, robot, Duration::from_secs(60));
        assert!(said.contains(&real), "{robot}: {said} (expected {real})");
    }
}

fn run_with_rogues(access_control: bool) -> Outcome {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let pki = dir.join("pki");
    let port = free_port();
    let listen = format!("tls/127.0.0.1:{port}");
    let stdout = pki_command(
        &["init", "--robots", "robot1,robot2", "--listen", &listen],
        &pki,
    );
    assert!(stdout.contains("robot1: --zenoh "), "{stdout}");
    // A third cart added later (`pki add`): its certificate is the authority's.
    pki_command(&["add", "--robot", "robot3"], &pki);

    // robot2's certificate without its access control; and no certificate.
    let rogue = derived(&pki.join("robot2.json5"), &dir.join("rogue.json5"), |v| {
        v.as_object_mut().unwrap().remove("access_control");
    });
    let anonymous = derived(
        &pki.join("robot1.json5"),
        &dir.join("anonymous.json5"),
        |v| {
            v.as_object_mut().unwrap().remove("access_control");
            let tls = v["transport"]["link"]["tls"].as_object_mut().unwrap();
            for k in [
                "listen_private_key",
                "listen_certificate",
                "connect_private_key",
                "connect_certificate",
            ] {
                tls.remove(k);
            }
            tls.insert("enable_mtls".into(), false.into());
        },
    );
    let moved = dir.join("moved");
    moved_copy(&moved);

    let offline = offline_result_of(dir, &dataset(), "board");
    let mut forged_result = offline.clone();
    forged_result.method = "forged".into();
    forged_result.base1_from_base2.t = [9.0, 9.0, 9.0];
    let forged_result_file = dir.join("forged-result.json");
    std::fs::write(
        &forged_result_file,
        serde_json::to_vec(&Envelope::new(COORDINATOR, 1 << 50, forged_result)).unwrap(),
    )
    .unwrap();
    let garbage_file = dir.join("garbage.bin");
    std::fs::write(
        &garbage_file,
        b"{\"schema\": 1, \"robot\": \"robot1\", \x00\xff garbage",
    )
    .unwrap();
    let forged_status_file = dir.join("forged-status.json");
    let status = AgentStatus {
        state: AgentState::Finished,
        good: 0,
        rejected: 0,
        published: 0,
        rotation_diversity_deg: 0.0,
        enough_data: false,
        message: "forged".into(),
    };
    std::fs::write(
        &forged_status_file,
        serde_json::to_vec(&Envelope::new("robot1", 1 << 50, status)).unwrap(),
    )
    .unwrap();

    // Every real process's configuration, with or without its access control.
    let config_of = |holder: &str| {
        let file = pki.join(format!("{holder}.json5"));
        if access_control {
            file
        } else {
            derived(&file, &dir.join(format!("open-{holder}.json5")), |v| {
                v.as_object_mut().unwrap().remove("access_control");
            })
        }
    };
    let coordinator_cfg = config_of(COORDINATOR);
    let mut coordinator = Killed(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["run", "--robots", "robot1,robot2", "--zenoh"])
            .arg(&coordinator_cfg)
            .arg("--state-dir")
            .arg(dir.join("coordinator-state"))
            .arg("--out")
            .arg(dir.join("RESULT.json"))
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let printout = Printout::of(&mut coordinator.0);
    // The rogues first, so that what they say is there before the real agents.
    let _rogues: Vec<Killed> = vec![
        // Paced, so that they are still publishing once connected.
        Killed(agent(
            "robot1",
            &moved,
            &rogue,
            &dir.join("rogue-state"),
            300,
        )),
        Killed(agent(
            "robot1",
            &moved,
            &anonymous,
            &dir.join("anon-state"),
            300,
        )),
        Killed(put(&rogue, "b2b/coordinator/result", &forged_result_file)),
        Killed(put(&rogue, "b2b/agent/robot1/status", &forged_status_file)),
        // Garbage from a certificate that may speak there: robot1's own (a
        // broken agent), on its capture key.
        Killed(put(
            &pki.join("robot1.json5"),
            "b2b/agent/robot1/capture",
            &garbage_file,
        )),
    ];
    // A peer without a certificate is never connected; one with is (the
    // check can fail).
    assert!(refused_where_admitted(
        &anonymous,
        &pki.join("robot1.json5")
    ));
    assert_eq!(peers_of(&pki.join("robot3.json5")), 1);
    // The rogues are speaking before the real agents start: the coordinator
    // has turned away the garbage robot1's certificate sent, and robot2's
    // certificate on robot1's keys (refused by the access control, or, with
    // no rule, rejected for its signature).
    let garbage = "b2b/agent/robot1/capture: not a valid message";
    let robot2_as_robot1 = |line: &str| {
        if access_control {
            line.contains("access control refused") && line.contains("b2b/agent/robot1/")
        } else {
            line.contains("signed with the certificate of 'robot2', but the key is robot1's")
        }
    };
    printout.wait_for(
        "the coordinator heard the rogues (robot1's garbage and robot2's certificate on robot1's keys)",
        Duration::from_secs(60),
        |text| text.contains(garbage) && text.lines().any(robot2_as_robot1),
    );
    let a1 = agent(
        "robot1",
        &dataset(),
        &config_of("robot1"),
        &dir.join("a1"),
        0,
    );
    let a2 = agent(
        "robot2",
        &dataset(),
        &config_of("robot2"),
        &dir.join("a2"),
        0,
    );
    let (ok, printed) = printout.exited(coordinator, Duration::from_secs(180));
    let live = ok.then(|| {
        serde_json::from_str(&std::fs::read_to_string(dir.join("RESULT.json")).unwrap()).unwrap()
    });
    let agents = [(a1, "agent robot1"), (a2, "agent robot2")]
        .into_iter()
        .filter_map(|(mut a, what)| {
            if ok {
                return Some(finished(a, what, Duration::from_secs(60)));
            }
            let _ = a.kill();
            let _ = a.wait();
            None
        })
        .collect();
    Outcome {
        live,
        offline,
        coordinator: printed,
        agents,
        journal: std::fs::read_to_string(dir.join("coordinator-state/samples.jsonl"))
            .unwrap_or_default(),
    }
}

/// The deployment the README describes, on one machine: the coordinator's host
/// is 127.0.0.3 (a loopback address of its own), it listens on every address,
/// and `pki init` names that host in its certificate. Each host gets only its
/// own files, copied into its own folder with the paths in its configuration
/// fixed (`ca.key` stays with the authority). Both carts reach the coordinator
/// by its host's address and the run gives the offline result; a cart that
/// reaches the same coordinator by an address its certificate does not name
/// (127.0.0.2; it names 127.0.0.3, `localhost` and 127.0.0.1) is refused.
#[test]
fn three_hosts_configured_as_the_readme_says_calibrate() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let authority = dir.join("authority");
    let port = free_port();
    let listen = format!("tls/0.0.0.0:{port}");
    let connect = format!("tls/127.0.0.3:{port}");
    pki_command(
        &[
            "init",
            "--robots",
            "robot1,robot2",
            "--listen",
            &listen,
            "--connect",
            &connect,
        ],
        &authority,
    );
    // "Copy ca.pem, <robot>.pem, <robot>.key and <robot>.json5 to each cart
    // and fix the file paths in the configuration."
    let install = |host: &str, holder: &str| -> PathBuf {
        let to = dir.join(host);
        std::fs::create_dir_all(&to).unwrap();
        for file in [
            "ca.pem".to_owned(),
            format!("{holder}.pem"),
            format!("{holder}.key"),
        ] {
            std::fs::copy(authority.join(&file), to.join(&file)).unwrap();
        }
        let from = authority.display().to_string();
        let there = to.display().to_string();
        derived(
            &authority.join(format!("{holder}.json5")),
            &to.join(format!("{holder}.json5")),
            |v| {
                let tls = v["transport"]["link"]["tls"].as_object_mut().unwrap();
                for value in tls.values_mut() {
                    if let Some(path) = value.as_str() {
                        *value = path.replace(&from, &there).into();
                    }
                }
            },
        )
    };
    let coordinator_cfg = install("coordinator-host", "coordinator");
    let carts: Vec<(&str, PathBuf)> = [("robot1", "cart1-host"), ("robot2", "cart2-host")]
        .into_iter()
        .map(|(robot, host)| (robot, install(host, robot)))
        .collect();
    for host in ["coordinator-host", "cart1-host", "cart2-host"] {
        let mut names: Vec<String> = std::fs::read_dir(dir.join(host))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        assert_eq!(names.len(), 4, "{host}: {names:?}");
        assert!(!names.contains(&"ca.key".to_owned()), "{host}: {names:?}");
        let config = names.iter().find(|n| n.ends_with(".json5")).unwrap();
        let config = std::fs::read_to_string(dir.join(host).join(config)).unwrap();
        assert!(!config.contains("authority"), "{host}: {config}");
    }
    let run = Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .current_dir(dir.join("coordinator-host"))
        .args(["run", "--robots", "robot1,robot2", "--zenoh"])
        .arg(&coordinator_cfg)
        .arg("--state-dir")
        .arg(dir.join("coordinator-host/state"))
        .arg("--out")
        .arg(dir.join("coordinator-host/RESULT.json"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut run = Killed(run);
    // The coordinator's host by an address the certificate does not name.
    let elsewhere = derived(&carts[0].1, &dir.join("cart1-host/elsewhere.json5"), |v| {
        v["connect"]["endpoints"] = serde_json::json!([format!("tls/127.0.0.2:{port}")]);
    });
    assert!(
        refused_where_admitted(&elsewhere, &carts[1].1),
        "a certificate naming 127.0.0.3 was taken for 127.0.0.2"
    );
    let agents: Vec<(Child, &str)> = carts
        .iter()
        .map(|(robot, config)| {
            let state = dir.join(format!("{robot}-state"));
            (agent(robot, &dataset(), config, &state, 0), *robot)
        })
        .collect();
    let offline = offline_result_of(dir, &dataset(), "board");
    let t = offline.base1_from_base2.t;
    let real = format!("t = [{:.6}, {:.6}, {:.6}] m", t[0], t[1], t[2]);
    for (a, robot) in agents {
        let said = finished(a, robot, Duration::from_secs(120));
        assert!(said.contains(&real), "{robot}: {said} (expected {real})");
        // A clean run: nothing refused, nothing rejected (the access
        // control's advance decisions for declared keys are no refusals).
        assert!(
            !said.contains("access control refused") && !said.contains(": rejected: "),
            "{robot}: {said}"
        );
    }
    let start = Instant::now();
    let status = loop {
        if let Some(status) = run.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "the coordinator did not exit"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "the coordinator failed");
    let mut printed = String::new();
    for pipe in [
        run.0.stdout.take().map(|p| Box::new(p) as Box<dyn Read>),
        run.0.stderr.take().map(|p| Box::new(p) as Box<dyn Read>),
    ]
    .into_iter()
    .flatten()
    {
        let mut pipe = pipe;
        pipe.read_to_string(&mut printed).unwrap();
    }
    assert!(
        !printed.contains("access control refused") && !printed.contains(": rejected: "),
        "coordinator: {printed}"
    );
    let live: b2b_protocol::CalibrationResult = serde_json::from_str(
        &std::fs::read_to_string(dir.join("coordinator-host/RESULT.json")).unwrap(),
    )
    .unwrap();
    assert_same(&live, &offline);
}

/// `pki init`, `pki add` and `pki revoke` under `umask 000` (set in the
/// process that runs them): the folder (and a parent it creates) is not
/// writable by group or others, keys are the owner's only, and certificates,
/// configurations and the revocation list are readable by all and writable
/// by the owner only, whatever the umask.
#[test]
fn pki_writes_with_explicit_modes_under_umask_000() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().unwrap();
    let pki = tmp.path().join("parent/pki");
    let coordinator = env!("CARGO_BIN_EXE_coordinator");
    for args in [
        "init --robots robot1,robot2",
        "add --robot robot3",
        "revoke --robot robot1",
    ] {
        let out = Command::new("sh")
            .arg("-c")
            .arg(format!("umask 000; exec \"$0\" pki {args} --dir \"$1\""))
            .arg(coordinator)
            .arg(&pki)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{args}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode(&pki), 0o755);
    assert_eq!(mode(pki.parent().unwrap()), 0o755);
    let mut seen = 0;
    for e in std::fs::read_dir(&pki).unwrap() {
        let path = e.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let want = if name.ends_with(".key") { 0o600 } else { 0o644 };
        assert_eq!(mode(&path), want, "{name}: {:o}", mode(&path));
        seen += 1;
    }
    // ca.pem, ca.key, three holders' pem/key/json5 each, robot3's, the
    // revocation list and the revoked certificate kept aside.
    assert!(seen >= 14, "{seen} files");
}
