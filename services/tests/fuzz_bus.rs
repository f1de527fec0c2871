//! The bus message decoder as a seeded fuzz campaign (stable, proptest; CI
//! runs it): random bytes, and mutations of valid messages (bytes flipped,
//! inserted, deleted, truncated; numbers replaced by extreme or wrong-typed
//! values), under agent and coordinator keys. Whatever decodes then goes into
//! the coordinator's journal and out as the pipeline's observations. Nothing
//! may panic; every refusal names the key. The secured bus's signature check
//! gets the same treatment on random and mutated attachments.

use b2b_protocol::CalibrationResult;
use b2b_protocol::Pose;
use b2b_protocol::messages::{
    AgentState, AgentStatus, BoardObservation, Capture, DriftAlarm, Envelope, FAILURE_REASON_MAX,
    HandEyeUpdate, Intrinsics, RunFailure,
};
use b2b_services::bus::decode;
use b2b_services::store::{Sample, Store};
use proptest::prelude::*;
use serde_json::Value;

const CAPTURE_KEY: &str = "b2b/agent/robot1/capture";
const STATUS_KEY: &str = "b2b/agent/robot1/status";

fn capture() -> Envelope<Capture> {
    let points: Vec<[f64; 3]> = (0..6)
        .map(|i| [0.025 * f64::from(i % 3), 0.025 * f64::from(i / 3), 0.0])
        .collect();
    let pixels: Vec<[f64; 2]> = (0..6)
        .map(|i| {
            [
                600.0 + 30.0 * f64::from(i % 3),
                340.0 + 30.0 * f64::from(i / 3),
            ]
        })
        .collect();
    Envelope::new(
        "robot1",
        3,
        Capture {
            index: 0,
            controller_time_s: Some(1.79e9),
            image: Some("images/000.png".into()),
            base_from_flange: Pose {
                t: [0.51, -0.1, 0.64],
                q: [0.0, 1.0, 0.0, 0.0],
            },
            camera: Intrinsics {
                width: 1280,
                height: 720,
                fx: 910.0,
                fy: 910.0,
                cx: 640.0,
                cy: 360.0,
                dist: vec![0.0; 5],
                estimated: false,
            },
            observation: Some(BoardObservation {
                target_points: points,
                pixels,
                camera_from_target: Pose {
                    t: [0.0, 0.0, 0.5],
                    q: [0.0, 0.0, 0.0, 1.0],
                },
                residuals_px: vec![0.1; 6],
                rms_px: 0.1,
                target_centre: Some([0.025, 0.0125, 0.0]),
                target: None,
            }),
            rejected: None,
            base_from_target: None,
            features: None,
        },
    )
}

fn status() -> Envelope<AgentStatus> {
    Envelope::new(
        "robot1",
        4,
        AgentStatus {
            state: AgentState::Finished,
            good: 1,
            rejected: 0,
            published: 1,
            rotation_diversity_deg: 12.0,
            enough_data: false,
            message: "all captures published".into(),
        },
    )
}

/// Every key and message type the services decode, on `bytes`.
fn decode_everything(bytes: &[u8]) -> Vec<Sample> {
    let mut decoded = vec![];
    for key in [
        CAPTURE_KEY,
        "b2b/agent/robot1/watch",
        "b2b/coordinator/result",
        "nope",
    ] {
        match decode::<Capture>(key, bytes) {
            Ok(e) if key == CAPTURE_KEY => decoded.push(Sample::Capture(e)),
            Ok(_) => {}
            Err(e) => assert!(e.starts_with(key), "{e}"),
        }
    }
    if let Ok(e) = decode::<AgentStatus>(STATUS_KEY, bytes) {
        decoded.push(Sample::Status(e));
    }
    if let Ok(e) = decode::<HandEyeUpdate>("b2b/agent/robot1/hand_eye", bytes) {
        decoded.push(Sample::HandEye(e));
    }
    let _ = decode::<CalibrationResult>("b2b/coordinator/result", bytes);
    let _ = decode::<DriftAlarm>("b2b/coordinator/alarm", bytes);
    if let Ok(e) = decode::<RunFailure>("b2b/coordinator/failure", bytes) {
        // What an agent prints: bounded and without control characters.
        assert!(e.body.reason.len() <= FAILURE_REASON_MAX);
        assert!(!e.body.reason.chars().any(|c| c.is_control() && c != '\n'));
    }
    decoded
}

/// What decoded goes into a journal and out as observations.
fn through_the_store(samples: Vec<Sample>) {
    if samples.is_empty() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path()).unwrap();
    for s in samples {
        store.accept(s).unwrap();
    }
    store.history_served("robot1", 1);
    let _ = store.observations("robot1");
    let _ = store.rgbd_views("robot1");
    let _ = store.target_centre(&["robot1"]);
    let _ = store.complete(None, 1);
    let _ = store.waiting_for(None, 2);
}

#[derive(Debug, Clone)]
enum Mutation {
    Flip {
        at: usize,
        mask: u8,
    },
    Insert {
        at: usize,
        byte: u8,
    },
    Delete {
        at: usize,
    },
    Truncate {
        to: usize,
    },
    /// The n-th number of the message replaced.
    Number {
        nth: usize,
        value: Value,
    },
}

fn odd_value() -> impl Strategy<Value = Value> {
    prop_oneof![
        Just(serde_json::json!(1e308)),
        Just(serde_json::json!(-1e308)),
        Just(serde_json::json!(0)),
        Just(serde_json::json!(-1)),
        Just(serde_json::json!(u64::MAX)),
        Just(serde_json::json!(4_294_967_296u64)),
        Just(serde_json::json!("NaN")),
        Just(Value::Null),
        Just(serde_json::json!([])),
        any::<f64>()
            .prop_filter("finite", |v| v.is_finite())
            .prop_map(|v| serde_json::json!(v)),
    ]
}

/// Half the time a few numbers replaced (the message stays JSON, and the
/// checks behind the parser are what is tried), half the time bytes broken.
fn mutations() -> impl Strategy<Value = Vec<Mutation>> {
    let number =
        (any::<usize>(), odd_value()).prop_map(|(nth, value)| Mutation::Number { nth, value });
    let byte = prop_oneof![
        (any::<usize>(), 1u8..).prop_map(|(at, mask)| Mutation::Flip { at, mask }),
        (any::<usize>(), any::<u8>()).prop_map(|(at, byte)| Mutation::Insert { at, byte }),
        any::<usize>().prop_map(|at| Mutation::Delete { at }),
        any::<usize>().prop_map(|to| Mutation::Truncate { to }),
    ];
    prop_oneof![
        prop::collection::vec(number, 1..4),
        prop::collection::vec(byte, 1..5),
    ]
}

/// Replaces the `nth` number (modulo their count) found walking `v`.
fn replace_number(v: &mut Value, nth: usize, with: &Value) {
    fn count(v: &Value) -> usize {
        match v {
            Value::Number(_) => 1,
            Value::Array(a) => a.iter().map(count).sum(),
            Value::Object(o) => o.values().map(count).sum(),
            _ => 0,
        }
    }
    fn walk(v: &mut Value, k: &mut usize, with: &Value) -> bool {
        match v {
            Value::Number(_) => {
                if *k == 0 {
                    *v = with.clone();
                    return true;
                }
                *k -= 1;
                false
            }
            Value::Array(a) => a.iter_mut().any(|x| walk(x, k, with)),
            Value::Object(o) => o.values_mut().any(|x| walk(x, k, with)),
            _ => false,
        }
    }
    let n = count(v);
    if n > 0 {
        let mut k = nth % n;
        walk(v, &mut k, with);
    }
}

fn mutate(message: &Value, mutations: &[Mutation]) -> Vec<u8> {
    let mut value = message.clone();
    for m in mutations {
        if let Mutation::Number { nth, value: with } = m {
            replace_number(&mut value, *nth, with);
        }
    }
    let mut bytes = serde_json::to_vec(&value).unwrap();
    for m in mutations {
        let len = bytes.len();
        match *m {
            Mutation::Flip { at, mask } if len > 0 => bytes[at % len] ^= mask,
            Mutation::Insert { at, byte } => bytes.insert(at % (len + 1), byte),
            Mutation::Delete { at } if len > 0 => {
                bytes.remove(at % len);
            }
            Mutation::Truncate { to } => bytes.truncate(to % (len + 1)),
            _ => {}
        }
    }
    bytes
}

proptest! {
    // CI's short campaign; PROPTEST_CASES=100000 runs a long one.
    #![proptest_config(ProptestConfig { cases: cases(1500), ..ProptestConfig::default() })]

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..2048)) {
        through_the_store(decode_everything(&bytes));
    }

    #[test]
    fn mutated_messages_never_panic(
        which in 0usize..2,
        mutations in mutations(),
    ) {
        let message = if which == 0 {
            serde_json::to_value(capture()).unwrap()
        } else {
            serde_json::to_value(status()).unwrap()
        };
        through_the_store(decode_everything(&mutate(&message, &mutations)));
    }

    /// The secured bus's signature check on a peer's attachment: random
    /// bytes, and a valid signature with bytes flipped, inserted or cut. Never
    /// a panic; only the untouched signature is believed.
    #[test]
    fn signature_attachments_never_panic(
        random in prop::collection::vec(any::<u8>(), 0..1024),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 0..4),
        insert in prop::option::of((any::<prop::sample::Index>(), any::<u8>())),
        cut in prop::option::of(any::<prop::sample::Index>()),
    ) {
        let (verifier, signed, payload) = &*SIGNED;
        prop_assert!(verifier.verify(CAPTURE_KEY, payload, Some(&random)).is_err());
        let mut a = signed.clone();
        for (at, bits) in &flips {
            let i = at.index(a.len());
            a[i] ^= bits;
        }
        if let Some((at, byte)) = insert {
            let i = at.index(a.len() + 1);
            a.insert(i, byte);
        }
        if let Some(at) = cut {
            a.truncate(at.index(a.len()));
        }
        let verdict = verifier.verify(CAPTURE_KEY, payload, Some(&a));
        if a == *signed {
            prop_assert_eq!(verdict.unwrap(), "robot1");
        } else {
            prop_assert!(verdict.is_err(), "a changed signature was believed");
        }
    }
}

/// An authority, a message robot1 signed, and its payload (made once).
static SIGNED: std::sync::LazyLock<(b2b_services::signing::Verifier, Vec<u8>, Vec<u8>)> =
    std::sync::LazyLock::new(|| {
        use b2b_services::signing::{Identity, Verifier};
        let dir = tempfile::tempdir().unwrap();
        b2b_services::pki::init(
            dir.path(),
            &["robot1".to_owned()],
            &b2b_services::pki::Endpoints::at(b2b_services::pki::DEFAULT_TLS_ENDPOINT).unwrap(),
        )
        .unwrap();
        let me = Identity::from_files(
            &dir.path().join("robot1.pem"),
            &dir.path().join("robot1.key"),
        )
        .unwrap();
        let verifier = Verifier::from_file(&dir.path().join("ca.pem")).unwrap();
        let payload = serde_json::to_vec(&capture()).unwrap();
        let signed = me.sign(CAPTURE_KEY, &payload).unwrap();
        (verifier, signed, payload)
    });

/// The seeds decode as they are, go through the journal into observations,
/// and a flange pose whose quaternion is not a unit one is refused with the
/// key named (so the campaign starts inside the format and can tell).
#[test]
fn the_seeds_decode_and_a_broken_pose_is_refused() {
    let capture = serde_json::to_vec(&capture()).unwrap();
    let samples = decode_everything(&capture);
    assert_eq!(samples.len(), 1);
    let dir = tempfile::tempdir().unwrap();
    let mut store = Store::open(dir.path()).unwrap();
    store.accept(samples.into_iter().next().unwrap()).unwrap();
    assert_eq!(store.observations("robot1").unwrap().observations.len(), 1);
    decode::<AgentStatus>(STATUS_KEY, &serde_json::to_vec(&status()).unwrap()).unwrap();
    let mut v: Value = serde_json::from_slice(&capture).unwrap();
    v["body"]["T_base_flange"]["q"][3] = serde_json::json!(2.0);
    let bytes = serde_json::to_vec(&v).unwrap();
    let e = decode::<Capture>(CAPTURE_KEY, &bytes).unwrap_err();
    assert!(e.starts_with(CAPTURE_KEY), "{e}");
}

/// The campaign reaches past the decoder: of 500 drawn mutations of the
/// capture, a good share still decode and go through the journal (numbers
/// replaced by other numbers mostly), and a good share are refused.
#[test]
fn the_mutations_reach_the_journal_and_the_refusals() {
    use proptest::strategy::ValueTree;
    use proptest::test_runner::TestRunner;
    let mut runner = TestRunner::deterministic();
    let message = serde_json::to_value(capture()).unwrap();
    let strategy = mutations();
    let mut decoded = 0;
    for _ in 0..500 {
        let mutations = strategy.new_tree(&mut runner).unwrap().current();
        decoded += usize::from(!decode_everything(&mutate(&message, &mutations)).is_empty());
    }
    assert!((50..450).contains(&decoded), "{decoded} of 500 decoded");
}

/// `PROPTEST_CASES` when set, else `default` (CI's short campaign).
fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
