//! A small valid dataset on disk that each validation test breaks in one way.

#![allow(dead_code)]

use std::fs;
use std::path::{Path, PathBuf};

use b2b_dataset::{Dataset, DatasetError};

pub const MANIFEST: &str = r#"{
  "format": "b2b-dataset/1",
  "name": "fixture",
  "source": "tests/common",
  "license": "CC0",
  "extra_field_from_a_newer_writer": {"ignored": true},
  "target": { "kind": "checkerboard", "inner_corners": [9, 6], "square_m": 0.025 },
  "robots": [
    {
      "id": "robot1",
      "camera": { "width": 1280, "height": 720, "fx": 910.0, "fy": 910.0,
                  "cx": 640.0, "cy": 360.0, "dist": [0.0, 0.0, 0.0, 0.0, 0.0] },
      "depth_unit_m": 0.001
    },
    { "id": "robot2" }
  ]
}
"#;

pub const CAPTURES1: &str = "image,depth,tx,ty,tz,qx,qy,qz,qw
images/000.png,depth/000.png,0.512,-0.103,0.644,0.0,1.0,0.0,0.0
images/001.png,,0.5,-0.1,0.6,0.0,0.0,0.0,1.0
";

pub const CAPTURES2: &str = "image,depth,tx,ty,tz,qx,qy,qz,qw,ctx,cty,ctz,cqx,cqy,cqz,cqw
,,0.4,0.2,0.5,0,0,0,1,0.01,0.02,0.7,0,0,0,1
images/a.jpg,,0.4,0.2,0.5,0,0,0,1,,,,,,,
";

pub const TOUCH: &str = "x1,y1,z1,x2,y2,z2
0.612,0.034,0.081,0.402,-0.221,0.079
0.5,0.0,0.1,0.3,-0.2,0.1
";

/// A valid two-robot dataset in a fresh temporary folder.
pub struct Fixture {
    pub dir: tempfile::TempDir,
}

impl Fixture {
    pub fn new() -> Fixture {
        let dir = tempfile::tempdir().expect("tempdir");
        let f = Fixture { dir };
        f.write("dataset.json", MANIFEST);
        f.write("robot1/captures.csv", CAPTURES1);
        f.write("robot2/captures.csv", CAPTURES2);
        f.write("touch_points.csv", TOUCH);
        for image in [
            "robot1/images/000.png",
            "robot1/images/001.png",
            "robot1/depth/000.png",
            "robot2/images/a.jpg",
        ] {
            f.write(image, "not really an image");
        }
        f
    }

    pub fn root(&self) -> &Path {
        self.dir.path()
    }

    pub fn path(&self, rel: &str) -> PathBuf {
        self.dir.path().join(rel)
    }

    pub fn write(&self, rel: &str, text: &str) {
        let p = self.path(rel);
        fs::create_dir_all(p.parent().unwrap()).unwrap();
        fs::write(p, text).unwrap();
    }

    /// Replaces `from` by `to` in a file, asserting that `from` is there.
    pub fn edit(&self, rel: &str, from: &str, to: &str) {
        let text = fs::read_to_string(self.path(rel)).unwrap();
        assert!(
            text.contains(from),
            "fixture {rel} does not contain {from:?}"
        );
        self.write(rel, &text.replacen(from, to, 1));
    }

    pub fn load(&self) -> Result<Dataset, DatasetError> {
        Dataset::load(self.root())
    }

    /// Loads, expecting an error whose message contains the full path of `rel` and
    /// every one of `parts`.
    pub fn load_err(&self, rel: &str, parts: &[&str]) -> DatasetError {
        let e = match self.load() {
            Ok(_) => panic!("loading should fail (file {rel}, expecting {parts:?})"),
            Err(e) => e,
        };
        assert_message(&e, &self.path(rel), parts);
        e
    }
}

pub use b2b_errors::chain;

pub fn assert_message(e: &DatasetError, file: &Path, parts: &[&str]) {
    let msg = chain(e);
    let file = file.display().to_string();
    assert!(msg.contains(&file), "message does not name {file}: {msg}");
    for part in parts {
        assert!(
            msg.contains(part),
            "message does not contain {part:?}: {msg}"
        );
    }
}
