//! Progress of the long stages (detecting the target in every image, the
//! intrinsics fit, the solve), for the commands that show it: an operator must
//! never face a silent command for minutes. The library only reports; a binary
//! that wants a progress bar installs a [`ProgressSink`] once at start
//! ([`set_sink`]). Without one, reporting costs nothing.

use std::sync::OnceLock;

/// Where the pipeline's progress goes.
pub trait ProgressSink: Send + Sync {
    /// A stage of `total` steps begins (`what`: e.g. "robot1: detecting the target").
    fn begin(&self, what: &str, total: u64);
    /// One step of the current stage is done.
    fn step(&self);
    /// The current stage is over.
    fn end(&self);
}

static SINK: OnceLock<Box<dyn ProgressSink>> = OnceLock::new();

/// Installs the process's progress sink; `false` when one is already installed
/// (the first stays).
pub fn set_sink(sink: Box<dyn ProgressSink>) -> bool {
    SINK.set(sink).is_ok()
}

/// One stage, reported from its creation to its drop.
#[derive(Debug)]
pub(crate) struct Stage {
    active: bool,
}

impl Stage {
    pub(crate) fn new(what: &str, total: usize) -> Stage {
        match SINK.get() {
            Some(sink) => {
                sink.begin(what, total as u64);
                Stage { active: true }
            }
            None => Stage { active: false },
        }
    }

    pub(crate) fn step(&self) {
        if self.active
            && let Some(sink) = SINK.get()
        {
            sink.step();
        }
    }
}

impl Drop for Stage {
    fn drop(&mut self) {
        if self.active
            && let Some(sink) = SINK.get()
        {
            sink.end();
        }
    }
}
