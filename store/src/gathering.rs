//! What `coordinator run` decides while it gathers, without the bus: which
//! messages of an agent belong to this run, what a history query's answer
//! tells of a robot, whose history is still worth asking, and when the run
//! has all it waits for. The coordinator's loop (`services/src/coordinator.rs`)
//! decodes the messages, feeds them here and to the [`Store`], and does what
//! these say; each rule is a unit test below rather than a run of processes.
//!
//! Which status of a robot to believe is the store's ([`Store::accept`]): a
//! status claiming more than the robot's history serves ([`CatchUp`] records
//! what it served) is replaced by the robot's own, and a robot finished with
//! every capture held stays finished. Here: history queries that bring a
//! robot nothing new stop after [`FRUITLESS_QUERIES`] ([`Gathering::to_ask`]),
//! and robots heard only through statuses do not hold a run without
//! `--robots` past [`STATUS_ONLY_GRACE`] ([`Gathering::without_status_only`]).
//! Time is passed in (`now`), never read.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use crate::{Arrival, Sample, Store};

/// How many history queries in a row may bring a robot nothing new before
/// the coordinator stops asking it (until something new of it arrives, or
/// it first echoes the session): what a status claims beyond that is not
/// waited for by re-asking.
pub const FRUITLESS_QUERIES: u32 = 3;

/// How long, once every robot that sent captures has finished, a run without
/// `--robots` waits for robots heard only through statuses before it leaves
/// them out, naming them: longer than an agent takes from its first status
/// to its first capture, well under the 10 s an operator waits past the last
/// agent.
pub const STATUS_ONLY_GRACE: Duration = Duration::from_secs(5);

/// What one valid message of an agent was.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Heard {
    pub robot: String,
    /// A status (a live message, unlike the captures a history query returns).
    pub status: bool,
    /// A capture's index.
    pub index: Option<u64>,
    /// It carries this run's session.
    pub in_session: bool,
    /// What the store made of it (`None`: not offered, not of this session).
    pub arrival: Option<Arrival>,
}

/// What becomes of a message by the session it carries.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Fate {
    /// This run's: offered to the store.
    Keep,
    /// A status of no session: the agent has not heard this run yet. Heard
    /// (it names a robot), neither kept nor stale.
    NotYetBound,
    /// A capture or hand-eye of no session, sent before the agent heard this
    /// run's: dropped as stale (its history serves it again in the session).
    BeforeSession,
    /// Another session's (an earlier run's, replayed, or an agent of another
    /// coordinator): dropped as stale, never taken for a conflict.
    OtherSession(String),
}

impl Heard {
    /// What `sample` is, and what becomes of it in the run of `session`.
    /// [`Heard::arrival`] is left for the store to fill in.
    pub fn of(sample: &Sample, session: &str) -> (Heard, Fate) {
        let (robot, theirs, status, index) = match sample {
            Sample::Capture(e) => (&e.robot, &e.session, false, Some(e.body.index)),
            Sample::Status(e) => (&e.robot, &e.session, true, None),
            Sample::HandEye(e) => (&e.robot, &e.session, false, None),
        };
        let fate = match theirs {
            Some(s) if s == session => Fate::Keep,
            None if status => Fate::NotYetBound,
            None => Fate::BeforeSession,
            Some(other) => Fate::OtherSession(other.clone()),
        };
        let heard = Heard {
            robot: robot.clone(),
            status,
            index,
            in_session: fate == Fate::Keep,
            arrival: None,
        };
        (heard, fate)
    }
}

/// The answer of one history query, reply by reply: each robot that answered
/// with how many valid captures of the session it served, and the robots that
/// gave something new. A robot that did not answer may be down, and says
/// nothing.
#[derive(Debug, Default)]
pub struct CatchUp {
    served: BTreeMap<String, BTreeSet<u64>>,
    news: BTreeSet<String>,
}

impl CatchUp {
    /// Notes one reply, as [`Heard`] after the store took it.
    pub fn replied(&mut self, h: Heard) {
        if !h.in_session {
            return;
        }
        if let Some(index) = h.index {
            self.served
                .entry(h.robot.clone())
                .or_default()
                .insert(index);
        }
        if h.arrival == Some(Arrival::New) {
            self.news.insert(h.robot);
        }
    }

    /// Records in `store` what each robot's history served
    /// ([`Store::history_served`]); returns the robots that gave something new.
    pub fn finish(self, store: &mut Store) -> BTreeSet<String> {
        for (robot, indices) in self.served {
            store.history_served(&robot, indices.len() as u64);
        }
        self.news
    }
}

/// What the gathering loop knows beside the store: the run's robots, who
/// echoes the session, and how often each robot's history was asked in vain.
#[derive(Debug, Default)]
pub struct Gathering {
    /// The robots of the run (`--robots`, robot 1 first), if named.
    expected: Option<Vec<String>>,
    /// How many robots make a calibration.
    robots: usize,
    /// The robots whose statuses have echoed this run's session (a later
    /// status without it, forged or stale, takes nothing back).
    echoed: BTreeSet<String>,
    /// Robots heard only without this run's session so far.
    unbound: BTreeSet<String>,
    /// History queries in a row that brought a robot nothing new.
    fruitless: BTreeMap<String, u32>,
    /// Since when every robot holding captures is done while others were
    /// heard only through statuses ([`Gathering::without_status_only`]).
    status_only_since: Option<Instant>,
}

impl Gathering {
    /// A run of the `expected` robots, or of at least `robots` of those heard
    /// from.
    pub fn new(expected: Option<Vec<String>>, robots: usize) -> Gathering {
        Gathering {
            expected,
            robots,
            ..Default::default()
        }
    }

    /// Every robot of the run finished with every capture held, and each
    /// echoing the session: time to solve.
    pub fn done(&self, store: &Store) -> bool {
        store.complete(self.expected.as_deref(), self.robots) && self.not_echoing(store).is_empty()
    }

    /// Notes a valid message: a first echo of the session, or a new capture
    /// of a robot, makes its history worth asking again.
    pub fn heard(&mut self, h: &Heard) {
        if h.status && !h.in_session && !self.echoed.contains(&h.robot) {
            self.unbound.insert(h.robot.clone());
        }
        if h.status && h.in_session && self.echoed.insert(h.robot.clone()) {
            self.unbound.remove(&h.robot);
            self.fruitless.remove(&h.robot);
        }
        if h.index.is_some() && h.arrival == Some(Arrival::New) {
            self.fruitless.remove(&h.robot);
        }
    }

    /// The robots missing captures whose history is still worth asking:
    /// at most [`FRUITLESS_QUERIES`] answers in a row without anything new.
    pub fn to_ask(&self, store: &Store) -> Vec<String> {
        store
            .missing()
            .into_iter()
            .filter(|r| self.fruitless.get(r).copied().unwrap_or(0) < FRUITLESS_QUERIES)
            .collect()
    }

    /// Notes that `robot`'s history answered, with something new or not.
    pub fn answered(&mut self, robot: &str, anything_new: bool) {
        let n = self.fruitless.entry(robot.to_owned()).or_default();
        *n = if anything_new { 0 } else { *n + 1 };
    }

    /// Without `--robots`: once every robot holding captures has finished
    /// (at least `robots` of them, each echoing the session) while the
    /// others were heard only through statuses (no capture of theirs arrived
    /// nor is in their history), and [`STATUS_ONLY_GRACE`] has passed since,
    /// the robots to solve with and those left out. A stray or forged status
    /// of a robot that sends nothing cannot hold the run.
    pub fn without_status_only(
        &mut self,
        store: &Store,
        now: Instant,
    ) -> Option<(Vec<String>, Vec<String>)> {
        if self.expected.is_some() {
            return None;
        }
        let (with, without): (Vec<String>, Vec<String>) = store
            .robots()
            .into_iter()
            .chain(self.unbound.iter().cloned())
            .collect::<BTreeSet<_>>()
            .into_iter()
            .partition(|r| store.capture_count(r) > 0);
        let ready = !without.is_empty()
            && store.complete(Some(&with), self.robots)
            && with.iter().all(|r| self.echoed.contains(r));
        if !ready {
            self.status_only_since = None;
            return None;
        }
        let since = *self.status_only_since.get_or_insert(now);
        (now.duration_since(since) >= STATUS_ONLY_GRACE).then_some((with, without))
    }

    /// The robots of the run whose statuses have not echoed its session.
    pub fn not_echoing(&self, store: &Store) -> Vec<String> {
        let mut ids = self.expected.clone().unwrap_or_else(|| store.robots());
        if self.expected.is_none() {
            ids.extend(self.unbound.iter().cloned());
            ids.sort();
            ids.dedup();
        }
        ids.into_iter()
            .filter(|r| !self.echoed.contains(r))
            .collect()
    }

    /// One phrase per robot not done: what the store says of it, and that
    /// its statuses do not echo the `session`.
    pub fn waiting_for(&self, store: &Store, session: &str) -> Vec<String> {
        let mut waiting = store.waiting_for(self.expected.as_deref(), self.robots);
        for r in self.not_echoing(store) {
            let echo = format!(
                "its statuses do not echo this run's session {session} yet (an agent of \
                 another run, or one that has not heard the coordinator)"
            );
            match waiting
                .iter_mut()
                .find(|w| w.starts_with(&format!("{r}: ")))
            {
                Some(w) => {
                    w.push_str(", and ");
                    w.push_str(&echo);
                }
                None => waiting.push(format!("{r}: {echo}")),
            }
        }
        for (r, n) in &self.fruitless {
            if *n >= FRUITLESS_QUERIES
                && let Some(w) = waiting
                    .iter_mut()
                    .find(|w| w.starts_with(&format!("{r}: ")))
            {
                w.push_str(&format!(
                    " (its history, asked {n} times, gave nothing new: asked again when \
                     something new of it arrives)"
                ));
            }
        }
        waiting
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::tests::{capture, status};
    use b2b_protocol::messages::{AgentState, Envelope};

    const SESSION: &str = "this-run";

    fn capture_of(robot: &str, seq: u64, index: u64, session: Option<&str>) -> Sample {
        Sample::Capture(Envelope::new(robot, seq, capture(index)).in_session(session))
    }

    fn status_of(
        robot: &str,
        seq: u64,
        state: AgentState,
        published: u64,
        session: Option<&str>,
    ) -> Sample {
        Sample::Status(Envelope::new(robot, seq, status(state, published)).in_session(session))
    }

    /// What the coordinator's loop does with a message: the store takes what
    /// is of this session, the gathering notes every one.
    fn feed(store: &mut Store, gathering: &mut Gathering, sample: Sample) -> Heard {
        let (mut heard, fate) = Heard::of(&sample, SESSION);
        if fate == Fate::Keep {
            heard.arrival = Some(store.accept(sample).unwrap());
        }
        gathering.heard(&heard);
        heard
    }

    #[test]
    fn only_this_sessions_messages_are_kept_and_a_status_of_none_is_only_heard() {
        let fate = |s: Sample| Heard::of(&s, SESSION).1;
        assert_eq!(fate(capture_of("r1", 1, 0, Some(SESSION))), Fate::Keep);
        assert_eq!(
            fate(status_of("r1", 1, AgentState::Capturing, 0, None)),
            Fate::NotYetBound
        );
        assert_eq!(fate(capture_of("r1", 1, 0, None)), Fate::BeforeSession);
        assert_eq!(
            fate(capture_of("r1", 1, 0, Some("earlier"))),
            Fate::OtherSession("earlier".into())
        );
        let (heard, _) = Heard::of(&capture_of("r1", 1, 7, Some(SESSION)), SESSION);
        assert_eq!(
            heard,
            Heard {
                robot: "r1".into(),
                status: false,
                index: Some(7),
                in_session: true,
                arrival: None,
            }
        );
    }

    /// A robot whose status claims captures its history does not bring is
    /// asked [`FRUITLESS_QUERIES`] times, then no more (and the wait says
    /// so), until something new of it arrives.
    #[test]
    fn fruitless_history_queries_stop_until_something_new_arrives() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(dir.path()).unwrap();
        let mut g = Gathering::new(None, 1);
        feed(
            &mut store,
            &mut g,
            status_of("r1", 1, AgentState::Capturing, 2, Some(SESSION)),
        );
        for _ in 0..FRUITLESS_QUERIES {
            assert_eq!(g.to_ask(&store), ["r1"]);
            g.answered("r1", false);
        }
        assert!(g.to_ask(&store).is_empty());
        let waiting = g.waiting_for(&store, SESSION).join("; ");
        assert!(
            waiting.contains("asked 3 times, gave nothing new"),
            "{waiting}"
        );
        // A duplicate brings nothing new; a new capture does.
        feed(&mut store, &mut g, capture_of("r1", 2, 0, Some(SESSION)));
        assert_eq!(g.to_ask(&store), ["r1"]);
        g.answered("r1", false);
        feed(&mut store, &mut g, capture_of("r1", 2, 0, Some(SESSION)));
        g.answered("r1", false);
        g.answered("r1", false);
        assert!(g.to_ask(&store).is_empty());
        // An answer with something new resets the count too.
        g.answered("r1", true);
        assert_eq!(g.to_ask(&store), ["r1"]);
    }

    /// A status claiming more captures than the robot's history served (a
    /// forged or stale count) is not believed once the history was asked: the
    /// robot's own status, even of a lower sequence number, replaces it.
    #[test]
    fn a_status_claiming_more_than_the_history_serves_gives_way_to_the_robots_own() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(dir.path()).unwrap();
        let mut g = Gathering::new(None, 1);
        feed(
            &mut store,
            &mut g,
            status_of("r1", 100, AgentState::Finished, 5, Some(SESSION)),
        );
        let own = status_of("r1", 10, AgentState::Finished, 3, Some(SESSION));
        // Before the history is asked, the higher sequence number wins.
        assert_eq!(
            feed(&mut store, &mut g, own.clone()).arrival,
            Some(Arrival::Duplicate)
        );
        let mut answer = CatchUp::default();
        for index in 0..3 {
            let reply = capture_of("r1", index, index, Some(SESSION));
            let (mut h, _) = Heard::of(&reply, SESSION);
            h.arrival = Some(store.accept(reply).unwrap());
            answer.replied(h);
        }
        // Another session's reply counts for nothing.
        let (stale, _) = Heard::of(&capture_of("r1", 9, 9, Some("earlier")), SESSION);
        answer.replied(stale);
        assert_eq!(answer.finish(&mut store), BTreeSet::from(["r1".to_owned()]));
        assert_eq!(store.served("r1"), Some(3));
        assert!(!g.done(&store));
        let waiting = g.waiting_for(&store, SESSION).join("; ");
        assert!(waiting.contains("its history holds 3"), "{waiting}");
        assert_eq!(feed(&mut store, &mut g, own).arrival, Some(Arrival::New));
        assert!(g.done(&store));
    }

    /// A robot finished with every capture held stays finished: a later
    /// status (forged, or a stale one replayed) that does not finish it too
    /// takes nothing back.
    #[test]
    fn a_finished_robot_stays_finished() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(dir.path()).unwrap();
        let mut g = Gathering::new(Some(vec!["r1".into()]), 1);
        for index in 0..2 {
            feed(
                &mut store,
                &mut g,
                capture_of("r1", index, index, Some(SESSION)),
            );
        }
        feed(
            &mut store,
            &mut g,
            status_of("r1", 5, AgentState::Finished, 2, Some(SESSION)),
        );
        assert!(g.done(&store));
        for later in [
            status_of("r1", 6, AgentState::Capturing, 2, Some(SESSION)),
            status_of("r1", 1 << 50, AgentState::Capturing, 9, Some(SESSION)),
            status_of("r1", 7, AgentState::Capturing, 0, None),
        ] {
            feed(&mut store, &mut g, later);
            assert!(g.done(&store));
            assert!(g.to_ask(&store).is_empty());
        }
    }

    /// Until every robot of the run echoes the session, the run is not done,
    /// even with every capture held and the robot finished (as a restarted
    /// coordinator's journal has it); a later status without it takes no echo
    /// back.
    #[test]
    fn a_run_waits_for_every_robot_to_echo_the_session() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(dir.path()).unwrap();
        store.accept(capture_of("r1", 1, 0, Some(SESSION))).unwrap();
        let finished = status_of("r1", 2, AgentState::Finished, 1, Some(SESSION));
        store.accept(finished.clone()).unwrap();
        let mut g = Gathering::new(None, 1);
        assert!(!g.done(&store));
        assert_eq!(g.not_echoing(&store), ["r1"]);
        feed(
            &mut store,
            &mut g,
            status_of("r1", 3, AgentState::Finished, 1, None),
        );
        assert!(!g.done(&store));
        let waiting = g.waiting_for(&store, SESSION).join("; ");
        assert!(
            waiting.contains("do not echo this run's session"),
            "{waiting}"
        );
        // The same status again: nothing new for the store, but an echo.
        assert_eq!(
            feed(&mut store, &mut g, finished).arrival,
            Some(Arrival::Duplicate)
        );
        assert!(g.done(&store));
        feed(
            &mut store,
            &mut g,
            status_of("r1", 4, AgentState::Finished, 1, None),
        );
        assert!(g.done(&store));
    }

    /// Without `--robots`, a robot heard only through statuses holds the run
    /// for [`STATUS_ONLY_GRACE`] after the others finished, then is left out
    /// by name; with `--robots` it is never left out.
    #[test]
    fn robots_heard_only_through_statuses_are_left_out_after_the_grace() {
        let dir = tempfile::tempdir().unwrap();
        let mut store = Store::open(dir.path()).unwrap();
        let mut g = Gathering::new(None, 1);
        let t0 = Instant::now();
        feed(
            &mut store,
            &mut g,
            status_of("r9", 1, AgentState::Capturing, 999, Some(SESSION)),
        );
        feed(&mut store, &mut g, capture_of("r1", 1, 0, Some(SESSION)));
        assert_eq!(g.without_status_only(&store, t0), None);
        feed(
            &mut store,
            &mut g,
            status_of("r1", 2, AgentState::Finished, 1, Some(SESSION)),
        );
        assert!(!g.done(&store));
        assert_eq!(g.without_status_only(&store, t0), None);
        let almost = t0 + STATUS_ONLY_GRACE - Duration::from_millis(1);
        assert_eq!(g.without_status_only(&store, almost), None);
        assert_eq!(
            g.without_status_only(&store, t0 + STATUS_ONLY_GRACE),
            Some((vec!["r1".to_owned()], vec!["r9".to_owned()]))
        );
        let mut named = Gathering::new(Some(vec!["r1".into(), "r9".into()]), 2);
        assert_eq!(
            named.without_status_only(&store, t0 + 10 * STATUS_ONLY_GRACE),
            None
        );
    }
}
