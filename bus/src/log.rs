//! What is logged of what peers send: zenoh's access-control refusals
//! ([`AccessRefusals`]) and warnings limited per topic ([`LogLimiter`]).

/// Where zenoh's access control logs its decisions.
pub const ACCESS_CONTROL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";

/// zenoh's access control says what it refuses only at trace level, beside a
/// trace line for every message it lets through. This layer takes the
/// refusals alone ("… is unauthorized to …", but not the permissions zenoh
/// works out in advance for a declared key expression) and writes each to
/// stderr as a warning: a cart speaking for another, named with its
/// certificate and the key.
#[derive(Debug, Clone, Copy)]
pub struct AccessRefusals;

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for AccessRefusals {
    fn on_event(
        &self,
        event: &tracing::Event<'_>,
        _ctx: tracing_subscriber::layer::Context<'_, S>,
    ) {
        struct Message(String);
        impl tracing::field::Visit for Message {
            fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
                if field.name() == "message" {
                    self.0 = format!("{value:?}");
                }
            }
        }
        let mut m = Message(String::new());
        event.record(&mut m);
        // When a key expression is declared, zenoh works out every permission
        // for it at once, to cache them ("caching permissions for `K`", then
        // decision lines for nine kinds of message in a fixed order, the
        // liveliness subscriber's last, on the same thread). Those decisions
        // refuse no message; a message's own check uses the cache ("Using
        // cached result: …") or decides anew.
        thread_local! {
            static CACHING: std::cell::RefCell<Option<String>> =
                const { std::cell::RefCell::new(None) };
        }
        if let Some((_, rest)) = m.0.split_once("caching permissions for `") {
            let key = rest.split('`').next().unwrap_or_default().to_owned();
            CACHING.with(|c| *c.borrow_mut() = Some(key));
            return;
        }
        let cached = m.0.starts_with("Using cached result: ");
        if !cached
            && let Some((_, key)) = m.0.rsplit_once(" on ")
            && CACHING.with(|c| c.borrow().as_deref() == Some(key))
        {
            // The batch ends with the liveliness subscriber's decision; a
            // message on the same key after it is checked for real.
            if m.0.contains("Declare Liveliness Subscriber (") {
                CACHING.with(|c| *c.borrow_mut() = None);
            }
            return;
        }
        if let Some((_, what)) = m.0.split_once(" is unauthorized to ") {
            // One topic per refused action and key, whoever the peer is.
            warn_limited(
                &format!("access control: {what}"),
                &format!(
                    "access control refused: {}",
                    m.0.trim_start_matches("Using cached result: ")
                ),
            );
        }
    }
}

/// Warnings about what peers send (refused, unsigned, forged) are limited per
/// topic, so that a peer flooding the bus cannot flood the log: in each
/// [`LogLimiter::EVERY`] the first [`LogLimiter::BURST`] lines of a topic are
/// written, the rest counted, and the next line written says how many were
/// left out.
#[derive(Debug, Default)]
pub struct LogLimiter {
    topics: std::collections::HashMap<String, LimitedTopic>,
}

#[derive(Debug, Clone, Copy)]
struct LimitedTopic {
    window_start: std::time::Instant,
    written: u32,
    left_out: u64,
}

impl LogLimiter {
    /// Lines of one topic written per window.
    pub const BURST: u32 = 5;
    /// The window.
    pub const EVERY: std::time::Duration = std::time::Duration::from_secs(10);
    /// Topics remembered; past this, the oldest window is forgotten.
    pub const TOPICS: usize = 1024;

    /// Whether a line of `topic` at `now` is written; if it is, how many lines
    /// of the topic were left out before it.
    pub fn admit(&mut self, topic: &str, now: std::time::Instant) -> Option<u64> {
        if !self.topics.contains_key(topic)
            && self.topics.len() >= Self::TOPICS
            && let Some(oldest) = self
                .topics
                .iter()
                .min_by_key(|(_, t)| t.window_start)
                .map(|(k, _)| k.clone())
        {
            self.topics.remove(&oldest);
        }
        let t = self.topics.entry(topic.to_owned()).or_insert(LimitedTopic {
            window_start: now,
            written: 0,
            left_out: 0,
        });
        if now.duration_since(t.window_start) >= Self::EVERY {
            t.window_start = now;
            t.written = 0;
        }
        if t.written >= Self::BURST {
            t.left_out += 1;
            return None;
        }
        t.written += 1;
        Some(std::mem::take(&mut t.left_out))
    }
}

/// Writes `line` to stderr as a warning, limited per `topic` ([`LogLimiter`]).
pub fn warn_limited(topic: &str, line: &str) {
    static LIMITER: std::sync::Mutex<Option<LogLimiter>> = std::sync::Mutex::new(None);
    let admitted = LIMITER.lock().map_or(Some(0), |mut l| {
        l.get_or_insert_with(LogLimiter::default)
            .admit(topic, std::time::Instant::now())
    });
    match admitted {
        Some(0) => eprintln!("WARN {line}"),
        Some(n) => eprintln!("WARN {line} ({n} more like it not logged)"),
        None => {}
    }
}

#[cfg(test)]
mod tests {
    use super::LogLimiter;
    use std::time::{Duration, Instant};

    #[test]
    fn a_flood_of_one_topic_is_limited_and_counted() {
        let mut l = LogLimiter::default();
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        // The first BURST of a topic are written; the rest of the window not.
        for i in 0..LogLimiter::BURST {
            assert_eq!(
                l.admit("b2b/agent/robot1/capture", at(u64::from(i))),
                Some(0)
            );
        }
        for i in 0..1000 {
            assert_eq!(l.admit("b2b/agent/robot1/capture", at(100 + i)), None);
        }
        // Another topic is not held back by the flood.
        assert_eq!(l.admit("b2b/coordinator/result", at(2000)), Some(0));
        // The next window's first line says how many were left out.
        assert_eq!(l.admit("b2b/agent/robot1/capture", at(10_100)), Some(1000));
        assert_eq!(l.admit("b2b/agent/robot1/capture", at(10_101)), Some(0));
    }

    #[test]
    fn a_flood_of_topics_is_bounded() {
        let mut l = LogLimiter::default();
        let t0 = Instant::now();
        for i in 0..(3 * LogLimiter::TOPICS as u64) {
            l.admit(&format!("key/{i}"), t0 + Duration::from_micros(i));
        }
        assert_eq!(l.topics.len(), LogLimiter::TOPICS);
        // The newest are the ones kept.
        assert!(
            l.topics
                .contains_key(&format!("key/{}", 3 * LogLimiter::TOPICS - 1))
        );
        assert!(!l.topics.contains_key("key/0"));
    }
}
