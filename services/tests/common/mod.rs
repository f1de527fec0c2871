//! Scaffolding shared by the multi-process tests: loopback zenoh configurations on
//! a free port, and child processes killed when a test ends.

#![allow(dead_code)]

use std::net::TcpListener;
use std::path::PathBuf;

pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A temporary folder with a coordinator configuration listening on a free
/// loopback port and an agent configuration connecting to it (multicast off).
pub struct Net {
    pub dir: tempfile::TempDir,
    pub coordinator_cfg: PathBuf,
    pub agent_cfg: PathBuf,
}

pub fn net() -> Net {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let coordinator_cfg = dir.path().join("coordinator.json5");
    let agent_cfg = dir.path().join("agent.json5");
    std::fs::write(
        &coordinator_cfg,
        format!(
            r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#
        ),
    )
    .unwrap();
    std::fs::write(
        &agent_cfg,
        format!(
            r#"{{ mode: "peer", listen: {{ endpoints: ["tcp/127.0.0.1:0"] }}, connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}"#
        ),
    )
    .unwrap();
    Net {
        dir,
        coordinator_cfg,
        agent_cfg,
    }
}

/// A child process killed (and reaped) when dropped.
pub struct Killed(pub std::process::Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
