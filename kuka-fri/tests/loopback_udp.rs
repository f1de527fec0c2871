//! Two processes over loopback UDP: `FriClient` here, `fri-sim-controller` as a child.

use std::net::SocketAddr;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use b2b_robot::{JointLimits, Joints, WorkspaceBox};
use kuka_fri::{FriClient, FriClientConfig, SafetyGuard, SessionState};

fn fk(q: &Joints) -> [f64; 3] {
    // Any smooth function will do for this test; the box is generous.
    [0.5 * q[0].cos(), 0.5 * q[0].sin(), 0.8 + 0.2 * q[1].sin()]
}

#[test]
fn client_and_simulated_controller_in_two_processes() {
    let guard = SafetyGuard::new(
        JointLimits::iiwa7(),
        WorkspaceBox::new([-1.0, -1.0, 0.0], [1.0, 1.0, 1.5]).expect("box"),
        fk,
    )
    .expect("guard");
    let bind: SocketAddr = "127.0.0.1:0".parse().expect("addr");
    let client = FriClient::start(FriClientConfig::new(bind), guard).expect("client binds");
    let started = Instant::now();
    let mut child = Command::new(env!("CARGO_BIN_EXE_fri-sim-controller"))
        .args(["--client", &client.local_addr().to_string()])
        .args([
            "--send-period-ms",
            "4",
            "--duration-ms",
            "6000",
            "--command",
        ])
        .args(["--loss", "0.01", "--seed", "3"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn fri-sim-controller");

    let result = (|| -> Result<(), String> {
        let first = client
            .wait_for_joints(Duration::from_secs(3))
            .map_err(|e| e.to_string())?;
        client
            .wait_for_state(SessionState::CommandingActive, Duration::from_secs(4))
            .map_err(|e| format!("{e}; state {}", client.state()))?;
        let target = [0.4, 0.3, -0.2, -1.0, 0.3, 0.6, 0.4];
        client
            .move_to(target)
            .map_err(|e| format!("move_to: {e}"))?;
        std::thread::sleep(Duration::from_millis(300));
        let now = client.latest().ok_or("no joints")?;
        let err = now
            .q
            .iter()
            .zip(&target)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        if err > 1e-3 {
            return Err(format!("arm at {:?}, error {err}", now.q));
        }
        if now.timestamp <= first.timestamp {
            return Err("controller time stamp did not advance".into());
        }
        if !client.is_still(Duration::from_millis(200), 5e-4) {
            return Err("arm not reported still after the motion".into());
        }
        // The controller closes the session at the end of its run: IDLE, no more replies.
        client
            .wait_for_state(SessionState::Idle, Duration::from_secs(8))
            .map_err(|e| format!("{e}; state {}", client.state()))?;
        Ok(())
    })();

    // Bounded wait for the child, whatever happened above.
    let deadline = Instant::now() + Duration::from_secs(15);
    let status = loop {
        if let Some(s) = child.try_wait().expect("try_wait") {
            break Some(s);
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            break None;
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    let out = child.wait_with_output().expect("child output");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    result.unwrap_or_else(|e| panic!("{e}\nchild stdout: {stdout}\nchild stderr: {stderr}"));
    assert!(
        status.is_some_and(|s| s.success()),
        "child failed: {status:?}\n{stdout}\n{stderr}"
    );
    assert!(stdout.contains("violations=0"), "{stdout}");
    assert!(
        stdout.contains(
            "states=MONITORING_WAIT,MONITORING_READY,COMMANDING_WAIT,COMMANDING_ACTIVE,IDLE"
        ),
        "{stdout}"
    );
    let stats = client.stats();
    assert!(stats.received > 1000 && stats.sent > 1000, "{stats:?}");
    assert!(started.elapsed() < Duration::from_secs(20));
}
