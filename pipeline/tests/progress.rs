//! The pipeline reports its detection stage to an installed sink: one stage per
//! robot, one step per capture, and the stage closed.

use std::path::Path;
use std::sync::{Arc, Mutex};

use b2b_pipeline::progress::{ProgressSink, set_sink};

#[derive(Debug, Default)]
struct Record(Arc<Mutex<Vec<String>>>);

impl ProgressSink for Record {
    fn begin(&self, what: &str, total: u64) {
        self.0.lock().unwrap().push(format!("begin {what} {total}"));
    }
    fn step(&self) {
        self.0.lock().unwrap().push("step".into());
    }
    fn end(&self) {
        self.0.lock().unwrap().push("end".into());
    }
}

#[test]
fn detection_reports_one_step_per_capture() {
    let events = Arc::new(Mutex::new(vec![]));
    assert!(set_sink(Box::new(Record(Arc::clone(&events)))));
    // A second sink does not replace the first.
    assert!(!set_sink(Box::new(Record::default())));
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/sim-checkerboard-2x12");
    let ds = b2b_pipeline::load_dataset(&dir).unwrap();
    b2b_pipeline::observe_robot(&ds, "robot2").unwrap();
    let events = events.lock().unwrap();
    let n = ds.robot("robot2").unwrap().captures.len();
    assert_eq!(
        events.first().map(String::as_str),
        Some(&*format!("begin robot2: detecting the target {n}"))
    );
    assert_eq!(events.iter().filter(|e| *e == "step").count(), n);
    assert_eq!(events.last().map(String::as_str), Some("end"));
}
